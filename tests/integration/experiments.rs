//! Runs with `--set` are experiments (issue 32): published to
//! `results/<pipeline>/runs/<name>/`, never over the pipeline's results;
//! switching back is no damage; `ltcal runs` lists them; `explain`, `show`
//! and `status` look at the run they are asked about.

use crate::cli::*;
use crate::util::pipeline_path;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

const PIPELINE: &str = "synthetic-validation";
const SEED2: &str = "stages.measure_sphere_noisy.seed=2";
const SEED3: &str = "stages.measure_sphere_noisy.seed=3";
const ITERS: &str = "stages.identify_sphere_noisy.max_iters=50";

fn file() -> String {
    pipeline_path("synthetic-validation.toml")
        .to_string_lossy()
        .into_owned()
}

/// `ltcal <cmd> <synthetic-validation> --results <results> <extra>…`.
fn cmd(results: &Path, command: &str, extra: &[&str]) -> std::process::Output {
    let (f, r) = (file(), results.to_string_lossy().into_owned());
    let mut args = vec![command, f.as_str(), "--results", r.as_str()];
    args.extend(extra);
    ltcal(results.parent().unwrap(), &args)
}

fn run_ok(results: &Path, extra: &[&str]) -> std::process::Output {
    let out = cmd(results, "run", extra);
    assert_code(&out, 0);
    out
}

/// Every file below `dir` — path → blake3 of its bytes — but the cache
/// and the experiments: what `git status` would compare of the committed
/// results.
fn main_files(dir: &Path) -> BTreeMap<PathBuf, String> {
    fn walk(root: &Path, dir: &Path, out: &mut BTreeMap<PathBuf, String>) {
        for e in std::fs::read_dir(dir).unwrap().flatten() {
            let path = e.path();
            let rel = path.strip_prefix(root).unwrap().to_path_buf();
            if rel == Path::new(".ltcal") || rel == Path::new("runs") {
                continue;
            }
            if e.file_type().unwrap().is_dir() {
                walk(root, &path, out);
            } else {
                let hash = blake3::hash(&std::fs::read(&path).unwrap()).to_hex();
                out.insert(rel, hash.to_string());
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(dir, dir, &mut out);
    out
}

/// The experiment folders of the pipeline, by name.
fn experiments(results: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(results.join(PIPELINE).join("runs"))
        .map(|rd| {
            rd.flatten()
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    names.sort();
    names
}

fn read_json(path: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

#[test]
fn an_override_run_leaves_the_main_results_byte_identical() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_ok(&results, &[]);
    let main = results.join(PIPELINE);
    let before = main_files(&main);
    assert!(before.len() > 40, "{} files", before.len());

    let out = run_ok(&results, &["--set", SEED2]);
    assert_eq!(main_files(&main), before, "the main results changed");
    // It went to its own folder, named by its overrides, and says so.
    let names = experiments(&results);
    assert_eq!(names.len(), 1, "{names:?}");
    let name = &names[0];
    assert!(name.starts_with("set-") && name.len() == 16, "{name}");
    let exp = main.join("runs").join(name);
    assert!(
        stderr(&out).contains(&format!("results in {}", exp.join("index.html").display())),
        "{}",
        stderr(&out)
    );
    assert_eq!(
        std::fs::read_to_string(exp.join("overrides.toml"))
            .unwrap()
            .lines()
            .last(),
        Some(format!("set = [\"{SEED2}\"]").as_str())
    );
    let run = read_json(&exp.join("run.json"));
    assert_eq!(run["experiment"]["name"], name.as_str());
    assert_eq!(run["experiment"]["overrides"][0], SEED2);
    assert_eq!(stages(&run).len(), 25);
    assert_eq!(stages(&run_json(&results, PIPELINE)).len(), 25);
    assert!(run_json(&results, PIPELINE).get("experiment").is_none());
    // Its noisy chain is the other seed's; the rest is the main results'.
    let table = |root: &Path, stage: &str| std::fs::read(root.join(stage).join("points.parquet"));
    assert_ne!(
        table(&exp, "evaluate_sphere_noisy").unwrap(),
        table(&main, "evaluate_sphere_noisy").unwrap()
    );
    assert_eq!(
        table(&exp, "evaluate_sphere").unwrap(),
        table(&main, "evaluate_sphere").unwrap()
    );
    // Its page names it.
    let page = std::fs::read_to_string(exp.join("index.html")).unwrap();
    assert!(
        page.contains(&format!("Experiment <code>{name}</code>")),
        "{page}"
    );

    // An `executor.*` override changes nothing computed: no experiment.
    run_ok(&results, &["--set", "executor.slurm.partition=x"]);
    assert_eq!(experiments(&results), names);
    assert_eq!(main_files(&main).len(), before.len());
}

#[test]
fn switching_back_from_an_experiment_prints_no_damage_note() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_ok(&results, &[]);
    run_ok(&results, &["--set", SEED2]);
    // Back to the pipeline's own settings: all cached, nothing to restore.
    let out = run_ok(&results, &[]);
    let err = stderr(&out);
    assert!(!err.contains("restored"), "{err}");
    assert!(err.contains(": 0 ran, 25 cached;"), "{err}");

    // A legitimate switch inside the main results (the file edited, then
    // edited back) replaces the published copies, saying nothing alarming.
    let edited = dir.path().join("seed2.toml");
    let text = std::fs::read_to_string(file()).unwrap();
    std::fs::write(&edited, text.replace("\nseed = 1\n", "\nseed = 2\n")).unwrap();
    let r = results.to_string_lossy().into_owned();
    let out = ltcal(
        dir.path(),
        &["run", edited.to_str().unwrap(), "--results", &r],
    );
    assert_code(&out, 0);
    assert!(!stderr(&out).contains("restored"), "{}", stderr(&out));
    let out = run_ok(&results, &[]);
    assert!(!stderr(&out).contains("restored"), "{}", stderr(&out));
}

#[test]
fn a_hand_edited_published_table_is_noted_and_restored() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_ok(&results, &[]);
    run_ok(&results, &["--set", SEED2]);
    let path = results
        .join(PIPELINE)
        .join("evaluate_sphere/points.parquet");
    let good = std::fs::read(&path).unwrap();
    let mut bad = good.clone();
    let mid = bad.len() / 2;
    bad[mid] ^= 0x40;
    std::fs::write(&path, &bad).unwrap();
    // Shown even with -q: it is no progress line.
    let out = run_ok(&results, &["-q"]);
    let err = stderr(&out);
    let notes: Vec<&str> = err.lines().filter(|l| l.contains("restored")).collect();
    assert_eq!(
        notes,
        [format!(
            "note: restored {}: it differed from the cached result of `evaluate_sphere` (edited or damaged)",
            path.display()
        )
        .as_str()],
        "{err}"
    );
    assert_eq!(std::fs::read(&path).unwrap(), good);
    // An experiment's copy likewise.
    let name = &experiments(&results)[0];
    let path = results
        .join(PIPELINE)
        .join("runs")
        .join(name)
        .join("evaluate_sphere_noisy/points.parquet");
    let good = std::fs::read(&path).unwrap();
    std::fs::write(&path, b"not a table").unwrap();
    let out = run_ok(&results, &["-q", "--name", name]);
    assert!(
        stderr(&out).contains(&format!("note: restored {}", path.display())),
        "{}",
        stderr(&out)
    );
    assert_eq!(std::fs::read(&path).unwrap(), good);
}

#[test]
fn ltcal_runs_lists_each_experiment_with_its_overrides() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    // None yet: nothing on stdout, success.
    let none = cmd(&results, "runs", &[]);
    assert_code(&none, 0);
    assert_eq!(stdout(&none), "");
    assert!(
        stderr(&none).contains("no experiments"),
        "{}",
        stderr(&none)
    );

    run_ok(&results, &[]);
    run_ok(&results, &["--set", SEED2, "--set", ITERS]);
    let first = experiments(&results);
    // The same overrides in another order: the same folder.
    run_ok(&results, &["--set", ITERS, "--set", SEED2]);
    assert_eq!(experiments(&results), first);
    // Other values: another folder; a name given: that folder.
    run_ok(&results, &["--set", SEED3]);
    run_ok(&results, &["--set", SEED3, "--name", "seed3"]);
    let names = experiments(&results);
    assert_eq!(names.len(), 3, "{names:?}");
    assert!(names.contains(&"seed3".to_string()), "{names:?}");

    let out = cmd(&results, "runs", &[]);
    assert_code(&out, 0);
    let s = stdout(&out);
    let lines: Vec<&str> = s.lines().collect();
    assert_eq!(lines.len(), 3, "{s}");
    // By name, each: name, status, when, the `--set`s that run it again.
    let cells = |l: &str| -> Vec<String> {
        l.split("  ")
            .filter(|c| !c.is_empty())
            .map(|c| c.trim().to_string())
            .collect()
    };
    let rows: Vec<Vec<String>> = lines.iter().map(|l| cells(l)).collect();
    let listed: Vec<&str> = rows.iter().map(|r| r[0].as_str()).collect();
    assert_eq!(listed, names);
    let by: BTreeMap<&str, &Vec<String>> = rows.iter().map(|r| (r[0].as_str(), r)).collect();
    let seed3 = by["seed3"];
    assert_eq!(seed3[1], "ok");
    assert_eq!(seed3[3], format!("--set {SEED3}"));
    let finished = read_json(&results.join(PIPELINE).join("runs/seed3/run.json"))["finished"]
        .as_str()
        .unwrap()
        .to_string();
    assert_eq!(seed3[2], finished);
    assert_eq!(
        by[first[0].as_str()][3],
        format!("--set {SEED2} --set {ITERS}")
    );
    // A second listing is the same.
    assert_eq!(stdout(&cmd(&results, "runs", &[])), s);

    // A damaged record is listed as such, and the listing exits 1.
    std::fs::write(
        results.join(PIPELINE).join("runs/seed3/overrides.toml"),
        "set = [",
    )
    .unwrap();
    let out = cmd(&results, "runs", &[]);
    assert_code(&out, 1);
    let damaged = stdout(&out)
        .lines()
        .find(|l| l.starts_with("seed3 "))
        .map(cells);
    assert_eq!(damaged.unwrap(), ["seed3", "damaged", "-"]);
    assert!(
        stderr(&out).contains("experiment `seed3`: ") && stderr(&out).contains("overrides.toml"),
        "{}",
        stderr(&out)
    );
    assert_eq!(stdout(&out).lines().count(), 3);
    // A pipeline file that is not one: the input is wrong.
    let r = results.to_string_lossy().into_owned();
    assert_code(
        &ltcal(dir.path(), &["runs", "no-such.toml", "--results", &r]),
        2,
    );
}

#[test]
fn an_experiment_name_that_is_no_folder_name_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    for bad in ["../x", "a/b", "-x", ".x", "a b", ""] {
        let arg = format!("--name={bad}");
        let out = cmd(&results, "run", &["--set", SEED2, &arg]);
        assert_code(&out, 2);
        assert!(
            stderr(&out).contains("an experiment's name starts with a letter or digit"),
            "{bad:?}: {}",
            stderr(&out)
        );
    }
    // `--name` alone names a recorded experiment: none yet.
    let out = cmd(&results, "run", &["--name", "nope"]);
    assert_code(&out, 2);
    assert!(
        stderr(&out).contains("no experiment of that name"),
        "{}",
        stderr(&out)
    );
    assert!(
        !results.exists(),
        "a refused run wrote {}",
        results.display()
    );
}

#[test]
fn a_named_experiment_runs_again_by_its_name_alone() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_ok(&results, &["--set", SEED2, "--name", "s2"]);
    let out = run_ok(&results, &["--name", "s2"]);
    let err = stderr(&out);
    assert!(
        err.contains(&format!("experiment `s2` (--set {SEED2})")),
        "{err}"
    );
    assert!(err.contains(": 0 ran, 25 cached;"), "{err}");
    // No main results were written by either.
    assert!(!results.join(PIPELINE).join("run.json").exists());
}

#[test]
fn explain_compares_with_the_run_it_is_asked_about() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_ok(&results, &[]);
    run_ok(&results, &["--set", SEED2, "--name", "s2"]);
    let explain = |extra: &[&str]| -> Value {
        let mut args = vec!["measure_sphere_noisy", "--json"];
        args.extend(extra);
        let out = cmd(&results, "explain", &args);
        assert_code(&out, 0);
        serde_json::from_str(&stdout(&out)).unwrap()
    };
    let changed = |e: &Value| -> Vec<String> {
        e["rows"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|r| r["changed"] == true)
            .map(|r| r["field"].as_str().unwrap().to_string())
            .collect()
    };
    // The main results: their last run was seed 1, not the experiment's 2.
    let main = explain(&[]);
    assert_eq!(main["status"], "cached");
    assert_eq!(main["key"], main["last_key"]);
    assert!(changed(&main).is_empty(), "{main}");
    assert!(main["experiment"].is_null());
    assert_eq!(main["compared_with"], "main");
    // The experiment, by name or by its overrides: its own last run.
    for e in [
        explain(&["--name", "s2"]),
        explain(&["--name", "s2", "--set", SEED2]),
    ] {
        assert_eq!(e["status"], "cached");
        assert_eq!(e["key"], e["last_key"]);
        assert_ne!(e["key"], main["key"]);
        assert!(changed(&e).is_empty(), "{e}");
        assert_eq!(e["experiment"], "s2");
        assert_eq!(e["compared_with"], "experiment");
    }
    // The name with other overrides than it was run with: refused.
    let out = cmd(
        &results,
        "explain",
        &["measure_sphere_noisy", "--name", "s2", "--set", SEED3],
    );
    assert_code(&out, 2);
    assert!(
        stderr(&out).contains(&format!(
            "--name s2: the experiment was run with --set {SEED2}, not these overrides"
        )),
        "{}",
        stderr(&out)
    );
    // A new experiment has no run of its own: compared with the main
    // results, its change named.
    let new = explain(&["--set", SEED3]);
    assert_eq!(new["status"], "run");
    assert_eq!(new["compared_with"], "main");
    assert_eq!(new["last_key"], main["key"]);
    assert_eq!(changed(&new), ["seed"]);
    let text = stdout(&cmd(
        &results,
        "explain",
        &["measure_sphere_noisy", "--set", SEED3],
    ));
    assert!(
        text.contains("has not published it: compared with the pipeline's own results"),
        "{text}"
    );
    // `plan` likewise: the experiment `s2` is current.
    let plan = cmd(&results, "plan", &["--name", "s2", "--check"]);
    assert_code(&plan, 0);
}

#[test]
fn show_and_status_look_at_the_experiment_asked_about() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_ok(&results, &[]);
    run_ok(&results, &["--set", SEED2]);
    let name = experiments(&results).remove(0);
    let show = |extra: &[&str]| {
        let mut args = vec!["evaluate_sphere_noisy.points", "--format", "csv"];
        args.extend(extra);
        let out = cmd(&results, "show", &args);
        assert_code(&out, 0);
        stdout(&out)
    };
    let (main, by_set, by_name) = (show(&[]), show(&["--set", SEED2]), show(&["--name", &name]));
    assert_ne!(main, by_set);
    assert_eq!(by_set, by_name);
    let exp = results.join(PIPELINE).join("runs").join(&name);
    let expected = ltcal::table::to_csv(
        &ltcal::table::read_parquet(&exp.join("evaluate_sphere_noisy/points.parquet")).unwrap(),
    )
    .unwrap();
    assert_eq!(by_name.as_bytes(), expected.as_slice());
    // An experiment not run yet has no result to show.
    let out = cmd(&results, "show", &["evaluate_sphere_noisy", "--set", SEED3]);
    assert_code(&out, 1);
    assert!(stderr(&out).contains("no result yet"), "{}", stderr(&out));
    // Status of an experiment: its stages are cached.
    let out = cmd(&results, "status", &["--name", &name]);
    assert_code(&out, 0);
    assert!(
        stdout(&out).contains("25 of 25 stages cached"),
        "{}",
        stdout(&out)
    );
    let out = cmd(&results, "status", &["--set", SEED3]);
    assert!(
        stdout(&out).contains("20 of 25 stages cached"),
        "{}",
        stdout(&out)
    );
}

#[test]
fn a_stage_cannot_be_named_like_a_folder_ltcal_writes_beside_the_stages() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["runs", "sweep", "slurm"] {
        std::fs::write(
            dir.path().join("p.toml"),
            format!("[stages.{name}]\nkind = \"inject\"\npreset = \"table2\"\n"),
        )
        .unwrap();
        let out = ltcal(dir.path(), &["plan", "p.toml"]);
        assert_code(&out, 2);
        let err = stderr(&out);
        assert!(err.contains("p.toml:1:9"), "{err}");
        assert!(
            err.contains(&format!(
                "a stage cannot be named `{name}`: its folder would be results/<pipeline>/{name}/"
            )),
            "{err}"
        );
    }
}

#[test]
fn a_cluster_coordinator_publishes_an_experiment_to_its_folder() {
    // Every point cached by a local run first: the coordinator submits
    // nothing (no Slurm needed) and publishes as the local run would.
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    let file = crate::util::root().join("tests/data/slurm/sweep.toml");
    let run = |extra: &[&str]| {
        let r = results.to_string_lossy().into_owned();
        let mut args = vec!["run", file.to_str().unwrap(), "--results", &r, "-q"];
        args.extend(extra);
        let out = ltcal(dir.path(), &args);
        assert_code(&out, 0);
        stderr(&out)
    };
    let set = "stages.calibration.max_iters=60";
    run(&[]);
    let main = results.join("slurm-sweep");
    let before = main_files(&main);
    run(&["--set", set, "--name", "iters"]);
    let exp = main.join("runs/iters");
    let gathered = std::fs::read(exp.join("sweep/evaluation.criteria.parquet")).unwrap();
    std::fs::remove_dir_all(&exp).unwrap();
    let err = run(&["--set", set, "--name", "iters", "--executor", "slurm"]);
    assert!(err.contains("0 ran, 5 cached"), "{err}");
    assert!(
        err.contains(&exp.join("index.html").display().to_string()),
        "{err}"
    );
    assert_eq!(main_files(&main), before);
    assert_eq!(
        std::fs::read(exp.join("sweep/evaluation.criteria.parquet")).unwrap(),
        gathered
    );
    assert!(exp.join("overrides.toml").is_file());
}
