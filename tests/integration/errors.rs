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

/// Regression: an axis narrower than one step gave the uncertainty field a
/// single grid point, and the heat map indexed its second one (a panic).
#[test]
fn uncertainty_field_axis_narrower_than_a_step() {
    let (code, err) = run_bad(
        "[stages.c]\nkind = \"simulate_campaign\"\nname = \"c\"\nlayout = { kind = \"corner\" }\n\n\
         [stages.f]\nkind = \"measurement_uncertainty\"\ninputs = { campaign = \"c\" }\nz_mm = [0.0, 500.0]\n",
    );
    assert_eq!(code, 2);
    assert_located(&err, "9:8", "`z_mm` must span at least one step");
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

/// `ltcal <args>` in `dir`: (exit code, stderr).
fn ltcal_in(dir: &Path, args: &[&str]) -> (i32, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .current_dir(dir)
        .args(args)
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// `plan`, not `run`: on a build without the bound, `run` would attempt
/// the allocation this test is about.
#[test]
fn every_count_setting_has_an_upper_bound_checked_at_load() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(
        d.join("bad.toml"),
        "[stages.b]\nkind = \"blind_check\"\nmc_draws = 1_000_000_000\n",
    )
    .unwrap();
    let (code, err) = ltcal_in(d, &["plan", "bad.toml"]);
    assert_eq!(code, 2, "{err}");
    assert_located(
        &err,
        "3:12",
        "stage `b`: `mc_draws` must be at most 100000 (ltcal's bound on any count), got 1000000000",
    );
    // Through `--set`, the override is named; a fitting stage's iterations.
    std::fs::write(d.join("ok.toml"), "[stages.b]\nkind = \"blind_check\"\n").unwrap();
    let (code, err) = ltcal_in(d, &["plan", "ok.toml", "--set", "stages.b.mc_draws=100001"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("stages.b.mc_draws=100001"), "{err}");
    assert!(err.contains("`mc_draws` must be at most 100000"), "{err}");
    std::fs::write(
        d.join("fit.toml"),
        "[stages.m]\nkind = \"mesh\"\nshape = \"plane\"\n\n[stages.i]\nkind = \"identify\"\n\
         max_iters = 10_000_000_000\ninputs = { readings = \"m\" }\n",
    )
    .unwrap();
    let (code, err) = ltcal_in(d, &["plan", "fit.toml"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("fit.toml:7:13"), "{err}");
    assert!(err.contains("`max_iters` must be at most 100000"), "{err}");
}

#[test]
fn threads_beyond_1024_are_refused_by_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("p.toml"),
        "[stages.a]\nkind = \"mesh\"\nshape = \"plane\"\n",
    )
    .unwrap();
    for j in ["100000", "1025", "0"] {
        let started = std::time::Instant::now();
        let (code, err) = ltcal_in(dir.path(), &["run", "p.toml", "-j", j]);
        assert_eq!(code, 2, "-j {j}: {err}");
        assert!(err.contains(&format!("invalid value '{j}'")), "{err}");
        assert!(err.contains("1..=1024"), "{err}");
        assert!(started.elapsed().as_secs() < 10);
        assert!(!dir.path().join("results").exists());
    }
}

#[test]
fn a_pipeline_file_that_is_not_utf8_missing_or_a_folder_exits_2_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(
        d.join("latin1.toml"),
        b"[stages.a]\nkind = \"mesh\" # caf\xe9\n",
    )
    .unwrap();
    std::fs::create_dir(d.join("folder.toml")).unwrap();
    let cases = [
        ("latin1.toml", "latin1.toml:2:20"),
        ("latin1.toml", "not UTF-8 text"),
        ("missing.toml", "missing.toml: no such pipeline file"),
        ("folder.toml", "folder.toml: a folder, not a pipeline file"),
        // A device never ends: it is not read at all.
        ("/dev/zero", "/dev/zero: not a regular file"),
    ];
    for cmd in ["run", "plan"] {
        for (file, says) in cases {
            let (code, err) = ltcal_in(d, &[cmd, file]);
            assert_eq!(code, 2, "{cmd} {file}: {err}");
            assert!(err.contains(says), "{cmd} {file}: no `{says}` in:\n{err}");
        }
    }
    assert!(!d.join("results").exists());
}

#[test]
fn an_unknown_tracker_model_is_refused_at_its_place() {
    let (code, err) = run_bad("[stages.a]\nkind = \"inject\"\nmodel = \"leica-at960\"\n");
    assert_eq!(code, 2);
    assert_located(
        &err,
        "3:9",
        "unknown tracker model `leica-at960`; expected \"api-tracker3\" or \"mirror-tracker\"",
    );
}

#[test]
fn a_parameter_of_another_tracker_model_is_refused_at_its_place() {
    let (code, err) = run_bad(
        "[stages.a]\nkind = \"identify\"\ninputs = { readings = \"b.readings\" }\nmodel = \"mirror-tracker\"\nfixed = [\"dz1\"]\n[stages.b]\nkind = \"mesh\"\nshape = \"sphere\"\n",
    );
    assert_eq!(code, 2);
    assert_located(
        &err,
        "5:9",
        "`dz1` is a parameter of the api-tracker3 model, but this fit uses the mirror-tracker model",
    );
}

/// Regression: `model_blind_check` did not check its layout, and a layout
/// without reflectors reached the simulation (an index out of bounds).
#[test]
fn model_blind_check_checks_its_layout_at_load() {
    let (code, err) = run_bad(
        "[stages.a]\nkind = \"model_blind_check\"\nlayout = { kind = \"corner\", per_level = 0 }\n",
    );
    assert_eq!(code, 2);
    assert_located(&err, "3:41", "`per_level` must be 1 … 200, got 0");
}
