//! Bad pipeline files: each error names the file, line and column, the exit
//! code is non-zero, and nothing is written.

use std::path::Path;
use std::process::Command;

/// Runs `ltcal run` on `text`; returns (exit code, stderr) and asserts that
/// no results folder appeared.
fn run_bad(text: &str) -> (i32, String) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("bad.toml");
    std::fs::write(&file, text).unwrap();
    let results = dir.path().join("results");
    let out = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .args([
            "run",
            file.to_str().unwrap(),
            "--results",
            results.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(!Path::new(&results).exists(), "results were written");
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn assert_located(stderr: &str, line_col: &str, message: &str) {
    assert!(
        stderr.contains(&format!("bad.toml:{line_col}")),
        "no location {line_col} in:\n{stderr}"
    );
    assert!(stderr.contains(message), "no `{message}` in:\n{stderr}");
    assert!(stderr.contains('^'), "no caret in:\n{stderr}");
}

#[test]
fn unknown_stage_kind() {
    let (code, err) = run_bad("[stages.a]\nkind = \"meshh\"\n");
    assert_eq!(code, 2);
    assert_located(&err, "2:8", "unknown stage kind `meshh`");
}

#[test]
fn unknown_field() {
    let (code, err) = run_bad("[stages.a]\nkind = \"mesh\"\nshape = \"plane\"\nstp = 3\n");
    assert_eq!(code, 2);
    assert_located(&err, "4:1", "unknown field `stp`");
}

#[test]
fn mistyped_field() {
    let (code, err) = run_bad(
        "[stages.a]\nkind = \"mesh\"\nshape = \"sphere\"\nr_mm = { from = 1000, to = 15000, step = \"big\" }\n",
    );
    assert_eq!(code, 2);
    assert_located(&err, "4:42", "`r_mm.step`: invalid type");
}

#[test]
fn input_naming_no_stage() {
    let (code, err) = run_bad(
        "[stages.a]\nkind = \"mesh\"\nshape = \"plane\"\n\n[stages.m]\nkind = \"measure\"\ninputs = { points = \"plne\" }\n",
    );
    assert_eq!(code, 2);
    assert_located(&err, "7:21", "names no stage `plne`");
}

#[test]
fn cycle() {
    let (code, err) = run_bad(
        "[stages.c]\nkind = \"correct\"\ninputs = { readings = \"m\", params = \"i\" }\n\n\
         [stages.m]\nkind = \"measure\"\ninputs = { points = \"c\" }\n\n\
         [stages.i]\nkind = \"identify\"\ninputs = { readings = \"m\" }\n",
    );
    assert_eq!(code, 2);
    assert_located(&err, "3:37", "cycle: c → i → m → c");
}

#[test]
fn mesh_step_of_zero() {
    let (code, err) = run_bad(
        "[stages.a]\nkind = \"mesh\"\nshape = \"cube\"\nx = { from = -1000, to = 1000, step = 0 }\n",
    );
    assert_eq!(code, 2);
    assert_located(&err, "4:39", "`x.step` must not be zero");
}

#[test]
fn toml_syntax_error() {
    let (code, err) = run_bad("[stages.a\nkind = \"mesh\"\n");
    assert_eq!(code, 2);
    assert!(err.contains("bad.toml:1:"), "{err}");
}

#[test]
fn bad_override_names_the_set_argument() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    let out = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .args([
            "run",
            crate::util::pipeline_path("synthetic-validation.toml")
                .to_str()
                .unwrap(),
            "--results",
            results.to_str().unwrap(),
            "--set",
            "stages.cube.x.step=0",
        ])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        err.contains("--set stages.cube.x.step=0: `x.step` must not be zero"),
        "{err}"
    );
    assert!(!results.exists());
}
