//! Helpers for tests that drive the `ltcal` binary.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

pub const BIN: &str = env!("CARGO_BIN_EXE_ltcal");

/// `ltcal <args>` run in `cwd`.
pub fn ltcal(cwd: &Path, args: &[&str]) -> Output {
    Command::new(BIN)
        .current_dir(cwd)
        .args(args)
        .output()
        .unwrap()
}

pub fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Asserts the exit code, showing the output when it is not the expected one.
pub fn assert_code(o: &Output, code: i32) {
    assert_eq!(
        o.status.code(),
        Some(code),
        "stdout:\n{}\nstderr:\n{}",
        stdout(o),
        stderr(o)
    );
}

/// The run report `results/<pipeline>/run.json`.
pub fn run_json(results: &Path, pipeline: &str) -> serde_json::Value {
    let b = std::fs::read(results.join(pipeline).join("run.json")).unwrap();
    serde_json::from_slice(&b).unwrap()
}

/// Stage → its entry in `run.json`.
pub fn stages(run: &serde_json::Value) -> BTreeMap<String, serde_json::Value> {
    run["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| (s["stage"].as_str().unwrap().to_string(), s.clone()))
        .collect()
}

/// Every published result of a pipeline — `<stage>/<file>` → bytes — the
/// tables and figures, not the run report, page and graph (which say when
/// and how the run went).
pub fn published(results: &Path, pipeline: &str) -> BTreeMap<String, Vec<u8>> {
    let dir = results.join(pipeline);
    let mut out = BTreeMap::new();
    for stage in std::fs::read_dir(&dir).unwrap().flatten() {
        let name = stage.file_name().to_string_lossy().into_owned();
        // `runs/` holds the experiments, not a stage's files.
        if name.starts_with('.') || name == "runs" || !stage.path().is_dir() {
            continue;
        }
        for f in std::fs::read_dir(stage.path()).unwrap().flatten() {
            let fname = f.file_name().to_string_lossy().into_owned();
            out.insert(format!("{name}/{fname}"), std::fs::read(f.path()).unwrap());
        }
    }
    out
}

/// Paths under `dir` whose names say they are temporary: what a killed
/// run leaves behind.
pub fn leftovers(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let Ok(rd) = std::fs::read_dir(dir) else {
        return out;
    };
    for e in rd.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        if name.starts_with(".tmp-") || name.starts_with(".trash-") || name.ends_with(".tmp") {
            out.push(e.path());
        } else if e.path().is_dir() {
            out.extend(leftovers(&e.path()));
        }
    }
    out
}
