//! The command line as users of other tools expect it (issue 32): tables
//! printed for scripts, a row limit, "did you mean", shell completions, one
//! set of exit codes, a stable order of the stage lines.

use crate::cli::{assert_code, ltcal, stderr, stdout};
use crate::util::root;
use polars::prelude::*;
use std::path::PathBuf;

/// Every table published under `results/` by a pipeline of `pipelines/` or
/// `pipelines/examples/`: (pipeline file, `<stage>.<table>`, its Parquet file).
fn published_tables() -> Vec<(PathBuf, String, PathBuf)> {
    let mut out = Vec::new();
    for dir in ["pipelines", "pipelines/examples"] {
        let mut files: Vec<PathBuf> = std::fs::read_dir(root().join(dir))
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|e| e == "toml"))
            .collect();
        files.sort();
        for file in files {
            let name = ltcal::pipeline::load(&file, &[])
                .unwrap_or_else(|e| panic!("{}: {e}", file.display()))
                .name;
            let results = root().join("results").join(&name);
            for stage in std::fs::read_dir(&results).unwrap().flatten() {
                if !stage.path().is_dir() || stage.file_name().to_string_lossy().starts_with('.') {
                    continue;
                }
                for t in std::fs::read_dir(stage.path()).unwrap().flatten() {
                    let path = t.path();
                    if path.extension().is_some_and(|e| e == "parquet") {
                        let stem = path.file_stem().unwrap().to_string_lossy().into_owned();
                        let table = format!("{}.{stem}", stage.file_name().to_string_lossy());
                        out.push((file.clone(), table, path));
                    }
                }
            }
        }
    }
    out
}

/// `ltcal show <file> <table> --format <format>`, run from the repository
/// root on the committed results (reading only); its stdout.
fn show(file: &std::path::Path, table: &str, format: &str) -> Vec<u8> {
    let o = ltcal(
        &root(),
        &["show", file.to_str().unwrap(), table, "--format", format],
    );
    assert_code(&o, 0);
    o.stdout
}

#[test]
fn every_published_table_prints_as_csv_and_json_that_read_back_whole() {
    let tables = published_tables();
    assert!(tables.len() > 100, "only {} tables found", tables.len());
    for (file, table, parquet) in &tables {
        let df = ltcal::table::read_parquet(parquet).unwrap();
        let what = format!("{} {table}", file.display());

        let csv = show(file, table, "csv");
        let read = CsvReadOptions::default()
            .with_has_header(true)
            .into_reader_with_file_handle(std::io::Cursor::new(csv))
            .finish()
            .unwrap_or_else(|e| panic!("{what}: CSV does not read back: {e}"));
        assert_eq!(read.shape(), df.shape(), "{what}: CSV");
        assert_eq!(
            read.get_column_names(),
            df.get_column_names(),
            "{what}: CSV header"
        );

        let json: serde_json::Value = serde_json::from_slice(&show(file, table, "json"))
            .unwrap_or_else(|e| panic!("{what}: JSON does not read back: {e}"));
        let records = json
            .as_array()
            .unwrap_or_else(|| panic!("{what}: not an array"));
        assert_eq!(records.len(), df.height(), "{what}: JSON rows");
        for r in records {
            let r = r.as_object().unwrap();
            assert_eq!(r.len(), df.width(), "{what}: JSON columns");
            for c in df.columns() {
                let v = &r[c.name().as_str()];
                if c.dtype().is_primitive_numeric() {
                    assert!(v.is_number() || v.is_null(), "{what}: {} = {v}", c.name());
                }
            }
        }
    }
}

#[test]
fn limit_prints_the_first_rows_and_says_how_many_were_left_out() {
    let file = root().join("pipelines/synthetic-validation.toml");
    let f = file.to_str().unwrap();
    let rows = ltcal::table::read_parquet(
        &root().join("results/synthetic-validation/sphere/points.parquet"),
    )
    .unwrap()
    .height();
    assert!(rows > 3);

    let o = ltcal(&root(), &["show", f, "sphere.points", "--limit", "3"]);
    assert_code(&o, 0);
    assert_eq!(stdout(&o).lines().count(), 1 + 3, "{}", stdout(&o));
    assert!(
        stderr(&o).contains(&format!("{} of {rows} rows not shown", rows - 3)),
        "{}",
        stderr(&o)
    );

    let o = ltcal(
        &root(),
        &[
            "show",
            f,
            "sphere.points",
            "--limit",
            "3",
            "--format",
            "csv",
        ],
    );
    assert_code(&o, 0);
    assert_eq!(stdout(&o).lines().count(), 1 + 3, "{}", stdout(&o));
    let o = ltcal(
        &root(),
        &[
            "show",
            f,
            "sphere.points",
            "--limit",
            "3",
            "--format",
            "json",
        ],
    );
    let json: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(json.as_array().unwrap().len(), 3);

    // A limit beyond the table prints it whole, with no note.
    let o = ltcal(&root(), &["show", f, "sphere.points", "--limit", "1000000"]);
    assert_eq!(stdout(&o).lines().count(), 1 + rows);
    assert!(!stderr(&o).contains("not shown"), "{}", stderr(&o));
}

/// `ltcal <args>` on a pipeline file holding `text`, in a fresh folder:
/// (exit code, stderr).
fn on_file(text: &str, args: &[&str]) -> (i32, String) {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("bad.toml"), text).unwrap();
    let mut all = vec![args[0], "bad.toml"];
    all.extend(&args[1..]);
    let o = ltcal(dir.path(), &all);
    (o.status.code().unwrap_or(-1), stderr(&o))
}

fn assert_located_hint(stderr: &str, line_col: &str, message: &str, meant: &str) {
    assert!(
        stderr.contains(&format!("bad.toml:{line_col}")),
        "no {line_col} in:\n{stderr}"
    );
    assert!(stderr.contains(message), "no `{message}` in:\n{stderr}");
    assert!(
        stderr.contains(&format!("did you mean `{meant}`?")),
        "no hint `{meant}` in:\n{stderr}"
    );
    assert!(stderr.contains('^'), "no caret in:\n{stderr}");
}

#[test]
fn a_misspelt_stage_kind_setting_stage_or_table_in_a_file_gets_the_nearest_name() {
    let (code, err) = on_file("[stages.a]\nkind = \"meshh\"\n", &["run"]);
    assert_eq!(code, 2);
    assert_located_hint(&err, "2:8", "unknown stage kind `meshh`", "mesh");

    let (code, err) = on_file("[stages.a]\nkind = \"mesh\"\nshap = \"plane\"\n", &["run"]);
    assert_eq!(code, 2);
    assert_located_hint(&err, "3:1", "unknown field `shap`", "shape");

    let plane =
        "[stages.plane]\nkind = \"mesh\"\nshape = \"plane\"\n\n[stages.m]\nkind = \"measure\"\n";
    let (code, err) = on_file(
        &format!("{plane}inputs = {{ points = \"plnae\" }}\n"),
        &["run"],
    );
    assert_eq!(code, 2);
    assert_located_hint(&err, "7:21", "names no stage `plnae`", "plane");

    let (code, err) = on_file(
        &format!("{plane}inputs = {{ points = \"plane.pionts\" }}\n"),
        &["run"],
    );
    assert_eq!(code, 2);
    assert_located_hint(&err, "7:21", "has no table `pionts`", "points");

    // Nothing near: no suggestion, the list of names as before.
    let (code, err) = on_file("[stages.a]\nkind = \"zzzzzz\"\n", &["run"]);
    assert_eq!(code, 2);
    assert!(
        err.contains("unknown stage kind `zzzzzz`; one of: "),
        "{err}"
    );
    assert!(!err.contains("did you mean"), "{err}");
}

#[test]
fn a_misspelt_stage_table_or_setting_on_the_command_line_gets_the_nearest_name() {
    let f = "pipelines/synthetic-validation.toml";
    let cases: [(&[&str], &str, &str); 4] = [
        (
            &["explain", f, "identify_sphre"],
            "no stage `identify_sphre`",
            "identify_sphere",
        ),
        (
            &["show", f, "sphere.pionts"],
            "has no table `pionts`",
            "points",
        ),
        (
            &["plan", f, "--set", "stages.identify_sphre.seed=1"],
            "no stage `identify_sphre`",
            "identify_sphere",
        ),
        (
            &["plan", f, "--set", "stages.measure_plane.sed=1"],
            "unknown field `sed`",
            "seed",
        ),
    ];
    for (args, message, meant) in cases {
        let o = ltcal(&root(), args);
        assert_code(&o, 2);
        let err = stderr(&o);
        assert!(err.contains(message), "{args:?}: no `{message}` in:\n{err}");
        assert!(
            err.contains(&format!("did you mean `{meant}`?")),
            "{args:?}:\n{err}"
        );
    }
}

#[test]
fn completions_generate_for_bash_zsh_and_fish() {
    for shell in ["bash", "zsh", "fish"] {
        let o = ltcal(&root(), &["completions", shell]);
        assert_code(&o, 0);
        let script = stdout(&o);
        for command in ["run", "show", "status", "completions", "kinds"] {
            assert!(
                script.contains(command),
                "{shell}: no `{command}` in:\n{script}"
            );
        }
        // Flags of a subcommand are completed too.
        assert!(script.contains("--format"), "{shell}: no `--format`");
    }
    let o = ltcal(&root(), &["completions", "tcsh"]);
    assert_code(&o, 2);
}

#[test]
fn exit_codes_follow_the_readme_table() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    let r = results.to_str().unwrap();
    let f = "pipelines/synthetic-validation.toml";
    // 0: success, and `status` on a pipeline without a sweep says so.
    let o = ltcal(&root(), &["status", f, "--results", r]);
    assert_code(&o, 0);
    assert!(stdout(&o).contains("no [sweep]"), "{}", stdout(&o));
    assert_code(&ltcal(&root(), &["kinds"]), 0);
    assert_code(&ltcal(&root(), &["--version"]), 0);
    // 1: a check that finds work left (nothing is cached in `results`).
    assert_code(&ltcal(&root(), &["plan", f, "--check", "--results", r]), 1);
    // 2: bad input — the command line, a missing file, a bad setting.
    assert_code(&ltcal(&root(), &["show"]), 2);
    assert_code(&ltcal(&root(), &["frobnicate"]), 2);
    assert_code(&ltcal(&root(), &["plan", "no-such.toml"]), 2);
    assert_code(&ltcal(&root(), &["show", f, "no_such_stage"]), 2);
    assert_code(
        &ltcal(&root(), &["run", f, "--results", r, "--set", "stages.x"]),
        2,
    );
}

#[test]
fn a_run_prints_its_stage_lines_in_the_plans_order() {
    // One level of stages that finish in any order on four threads.
    let dir = tempfile::tempdir().unwrap();
    let names = ["d", "b", "c", "a", "f", "e"];
    let text: String = names
        .iter()
        .map(|n| format!("[stages.{n}]\nkind = \"mesh\"\nshape = \"plane\"\n\n"))
        .collect();
    std::fs::write(dir.path().join("p.toml"), text).unwrap();
    let plan = ltcal(dir.path(), &["plan", "p.toml", "--json"]);
    let plan: serde_json::Value = serde_json::from_slice(&plan.stdout).unwrap();
    let order: Vec<&str> = plan
        .as_array()
        .unwrap()
        .iter()
        .map(|i| i["stage"].as_str().unwrap())
        .collect();
    assert_eq!(order, names, "the plan keeps the file's order among equals");
    for k in 0..5 {
        let o = ltcal(
            dir.path(),
            &["run", "p.toml", "-j", "4", "--results", &format!("r{k}")],
        );
        assert_code(&o, 0);
        let printed: Vec<String> = stderr(&o)
            .lines()
            // Alike stages share a cache entry: some lines say `cached`.
            .filter(|l| matches!(l.split_whitespace().next(), Some("ran" | "cached")))
            .map(|l| l.split_whitespace().nth(1).unwrap().to_string())
            .collect();
        assert_eq!(printed, names, "{}", stderr(&o));
    }
}
