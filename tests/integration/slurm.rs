//! `--executor slurm` against a real Slurm: a controller and three slurmd
//! nodes on this machine, started by `.ci/slurm-up` (which `.ci/run` calls),
//! found through `SLURM_CONF`. Without it these tests say so and pass —
//! except under `CI=true`, where they must run.
//!
//! The tests share the cluster's three nodes, so they run one at a time.

use super::util::root;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::Mutex;
use std::time::{Duration, Instant};

static CLUSTER: Mutex<()> = Mutex::new(());

/// The cluster's folder (where `slurm.conf` is), or `None` to skip.
fn cluster() -> Option<PathBuf> {
    match std::env::var_os("SLURM_CONF") {
        Some(conf) if Path::new(&conf).is_file() => {
            Some(Path::new(&conf).parent().unwrap().to_path_buf())
        }
        _ if std::env::var("CI").is_ok_and(|v| v == "true") => {
            panic!(
                "CI=true but no Slurm cluster: .ci/run starts one with .ci/slurm-up and sets SLURM_CONF"
            )
        }
        _ => {
            eprintln!(
                "skipped: no Slurm cluster (start one with `.ci/slurm-up` and set SLURM_CONF=<its folder>/slurm.conf)"
            );
            None
        }
    }
}

fn ltcal(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .args(args)
        .current_dir(root())
        .output()
        .unwrap()
}

/// `ltcal run <file> -q --executor slurm --results <results> <extra>…`.
fn on_slurm(file: &str, results: &Path, extra: &[&str]) -> Output {
    let mut args = vec!["run", file, "-q", "--executor", "slurm", "--results"];
    args.push(results.to_str().unwrap());
    args.extend_from_slice(extra);
    ltcal(&args)
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

fn data(name: &str) -> String {
    root()
        .join("tests/data/slurm")
        .join(name)
        .display()
        .to_string()
}

fn squeue(job: &str) -> Vec<(String, String, String, String)> {
    let o = Command::new("squeue")
        .args(["-h", "-r", "-t", "all", "-j", job, "-o", "%i|%A|%T|%N"])
        .output()
        .unwrap();
    String::from_utf8_lossy(&o.stdout)
        .lines()
        .filter_map(|l| {
            let f: Vec<&str> = l.split('|').collect();
            (f.len() == 4).then(|| (f[0].into(), f[1].into(), f[2].into(), f[3].into()))
        })
        .collect()
}

fn jobs_record(results: &Path, pipeline: &str) -> serde_json::Value {
    let b = std::fs::read(results.join(pipeline).join(".ltcal/slurm/jobs.json")).unwrap();
    serde_json::from_slice(&b).unwrap()
}

fn files_under(dir: &Path) -> usize {
    std::fs::read_dir(dir)
        .map(|rd| {
            rd.flatten()
                .map(|e| {
                    if e.file_type().unwrap().is_dir() {
                        files_under(&e.path())
                    } else {
                        1
                    }
                })
                .sum()
        })
        .unwrap_or(0)
}

fn wait_until(what: &str, secs: u64, mut f: impl FnMut() -> bool) {
    let t = Instant::now();
    while !f() {
        assert!(
            t.elapsed() < Duration::from_secs(secs),
            "timed out waiting for {what}"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// Kills node `n` as a power cut would: its slurmd (by its PID file) and
/// every process of the jobs running there.
fn kill_node(dir: &Path, node: &str, job_ids: &[String]) {
    let pid = std::fs::read_to_string(dir.join(format!("slurmd-{node}.pid"))).unwrap();
    Command::new("kill")
        .args(["-9", pid.trim()])
        .status()
        .unwrap();
    for e in std::fs::read_dir("/proc").unwrap().flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else {
            continue;
        };
        let env = std::fs::read(e.path().join("environ")).unwrap_or_default();
        let cmd = std::fs::read(e.path().join("cmdline")).unwrap_or_default();
        let env = String::from_utf8_lossy(&env);
        let cmd = String::from_utf8_lossy(&cmd);
        let ours = job_ids.iter().any(|j| {
            env.split('\0').any(|v| v == format!("SLURM_JOB_ID={j}"))
                || cmd.contains(&format!("[{j}.batch]"))
        });
        if ours {
            let _ = Command::new("kill").args(["-9", &pid.to_string()]).status();
        }
    }
}

fn gathered(results: &Path, pipeline: &str, table: &str) -> Vec<u8> {
    std::fs::read(
        results
            .join(pipeline)
            .join("sweep")
            .join(format!("{table}.parquet")),
    )
    .unwrap()
}

#[test]
fn a_sweep_on_slurm_equals_the_local_run_in_one_array_over_several_nodes() {
    let Some(dir) = cluster() else { return };
    let _one = CLUSTER.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let (local, slurm) = (tmp.path().join("local"), tmp.path().join("slurm"));
    let file = data("sweep.toml");
    let o = ltcal(&["run", &file, "-q", "--results", local.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let o = on_slurm(&file, &slurm, &[]);
    assert!(o.status.success(), "{}", text(&o));
    // Value-identical: the same bytes.
    assert_eq!(
        gathered(&local, "slurm-sweep", "evaluation.criteria"),
        gathered(&slurm, "slurm-sweep", "evaluation.criteria")
    );
    // One sbatch for the wave: one job, 24 points in 5 tasks of ≤ 5.
    let jobs = jobs_record(&slurm, "slurm-sweep");
    assert_eq!(jobs.as_array().unwrap().len(), 1, "{jobs}");
    let job = jobs[0]["job"].as_str().unwrap().to_string();
    assert_eq!(jobs[0]["units"].as_array().unwrap().len(), 5);
    // The job record shows the array's tasks on more than one node.
    let comp = std::fs::read_to_string(dir.join("jobcomp.txt")).unwrap();
    let nodes: BTreeSet<&str> = comp
        .lines()
        .filter(|l| l.contains(&format!("ArrayJobId={job} ")))
        .filter_map(|l| {
            l.split_whitespace()
                .find_map(|f| f.strip_prefix("NodeList="))
        })
        .collect();
    assert!(nodes.len() >= 2, "tasks ran on {nodes:?}:\n{comp}");
    // Few files: packs and logs, not entries (22 files a point before).
    let files = files_under(&slurm.join("slurm-sweep"));
    assert!(files <= 24, "{files} files for 24 points");
    // A rerun finds every point in the cache and submits nothing.
    let o = on_slurm(&file, &slurm, &[]);
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(
        jobs_record(&slurm, "slurm-sweep").as_array().unwrap().len(),
        1
    );
    let o = ltcal(&["verify", &file, "--results", slurm.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("0 damaged"), "{}", text(&o));
}

#[test]
fn a_node_killed_and_a_task_cancelled_mid_run_fail_exactly_their_points_and_a_rerun_submits_only_those()
 {
    let Some(dir) = cluster() else { return };
    let _one = CLUSTER.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let results = tmp.path().join("r");
    let r = results.to_str().unwrap();
    let file = data("slow.toml");
    let o = on_slurm(&file, &results, &["--detach"]);
    assert!(o.status.success(), "{}", text(&o));
    let job = jobs_record(&results, "slurm-slow")[0]["job"]
        .as_str()
        .unwrap()
        .to_string();
    // Three tasks of four points, one per node.
    wait_until("three running tasks", 60, || {
        squeue(&job).iter().filter(|t| t.2 == "RUNNING").count() == 3
    });
    let o = ltcal(&["status", &file, "--results", r]);
    assert!(text(&o).contains("12 RUNNING"), "{}", text(&o));
    let tasks = squeue(&job);
    let on = |node: &str| tasks.iter().find(|t| t.3 == node).unwrap().clone();
    let (killed, cancelled) = (on("n2"), on("n3"));
    kill_node(&dir, "n2", std::slice::from_ref(&killed.1));
    let c = Command::new("scancel").arg(&cancelled.0).status().unwrap();
    assert!(c.success());
    // The attached run adopts the job, waits for it and names what failed.
    let o = on_slurm(&file, &results, &[]);
    let out = text(&o);
    assert_eq!(o.status.code(), Some(1), "{out}");
    let index = |t: &(String, String, String, String)| -> usize {
        t.0.rsplit('_').next().unwrap().parse().unwrap()
    };
    let units = jobs_record(&results, "slurm-slow")[0]["units"].clone();
    let points_of = |k: usize| -> Vec<usize> {
        let first = units[k]["first"].as_u64().unwrap() as usize;
        (first..first + 4).collect()
    };
    let failed_by = |word: &str| -> BTreeSet<usize> {
        out.lines()
            .filter(|l| l.contains(word))
            .filter_map(|l| {
                l.split("sweep point ")
                    .nth(1)?
                    .split(' ')
                    .next()?
                    .parse()
                    .ok()
            })
            .collect()
    };
    assert_eq!(
        failed_by("NODE_FAIL on n2"),
        points_of(index(&killed)).into_iter().collect(),
        "{out}"
    );
    assert_eq!(
        failed_by("ended CANCELLED"),
        points_of(index(&cancelled)).into_iter().collect(),
        "{out}"
    );
    assert!(
        out.contains(&format!("Slurm job {job}, array task")),
        "{out}"
    );
    assert!(out.contains("log "), "{out}");
    // Nothing bad is served.
    let v = ltcal(&["verify", &file, "--results", r]);
    assert!(v.status.success(), "{}", text(&v));
    // The node comes back; a rerun submits the eight missing points only.
    let conf = dir.join("slurm.conf");
    let s = Command::new("slurmd")
        .args(["-f", conf.to_str().unwrap(), "-N", "n2"])
        .status()
        .unwrap();
    assert!(s.success());
    wait_until("n2 back", 60, || {
        let o = Command::new("sinfo")
            .args(["-h", "-n", "n2", "-o", "%T"])
            .output()
            .unwrap();
        String::from_utf8_lossy(&o.stdout).trim() == "idle"
    });
    let o = on_slurm(&file, &results, &[]);
    assert!(o.status.success(), "{}", text(&o));
    let jobs = jobs_record(&results, "slurm-slow");
    let last = jobs.as_array().unwrap().last().unwrap();
    let resubmitted: BTreeSet<usize> = last["units"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|u| {
            let (a, b) = (u["first"].as_u64().unwrap(), u["last"].as_u64().unwrap());
            a as usize..=b as usize
        })
        .collect();
    let expected: BTreeSet<usize> = points_of(index(&killed))
        .into_iter()
        .chain(points_of(index(&cancelled)))
        .collect();
    assert_eq!(resubmitted, expected);
    // And the tables are the local run's.
    let local = tmp.path().join("local");
    let o = ltcal(&["run", &file, "-q", "--results", local.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(
        gathered(&local, "slurm-slow", "uncertainty.params"),
        gathered(&results, "slurm-slow", "uncertainty.params")
    );
    let v = ltcal(&["verify", &file, "--results", r]);
    assert!(v.status.success(), "{}", text(&v));
}

#[test]
fn sigterm_to_the_coordinator_cancels_its_jobs() {
    let Some(_dir) = cluster() else { return };
    let _one = CLUSTER.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let results = tmp.path().join("r");
    let child = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .args([
            "run",
            &data("slow.toml"),
            "-q",
            "--executor",
            "slurm",
            "--results",
        ])
        .arg(&results)
        .current_dir(root())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let jobs = results.join("slurm-slow/.ltcal/slurm/jobs.json");
    wait_until("the submission", 60, || jobs.exists());
    let job = jobs_record(&results, "slurm-slow")[0]["job"]
        .as_str()
        .unwrap()
        .to_string();
    wait_until("a running task", 60, || {
        squeue(&job).iter().any(|t| t.2 == "RUNNING")
    });
    Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(130), "{err}");
    assert!(
        err.contains(&format!("interrupted: cancelled Slurm job {job}")),
        "{err}"
    );
    // Cancelled: none ran on (a task may have completed before).
    wait_until("every task cancelled or completed", 60, || {
        let t = squeue(&job);
        t.iter().any(|t| t.2 == "CANCELLED")
            && t.iter().all(|t| t.2 == "CANCELLED" || t.2 == "COMPLETED")
    });
}

/// The blind check of one pipeline file, its blocks of cases scored whole.
fn one_check_of(blocks_file: &str, cases: usize) -> String {
    let text = std::fs::read_to_string(blocks_file).unwrap();
    let head = &text[..text.find("[[sweep.axis]]").unwrap()];
    head.replace("name = \"blind-blocks\"", "name = \"blind-whole\"")
        .replace("cases = 4\n", &format!("cases = {cases}\n"))
}

/// Every table of `blind_summary` over the gathered blocks equals the one
/// check of the same cases, wherever the blocks ran.
fn assert_scores_equal_one_check(results: &Path, blocks: &str) {
    let tmp = tempfile::tempdir().unwrap();
    let whole = tmp.path().join("whole.toml");
    std::fs::write(&whole, one_check_of(blocks, 12)).unwrap();
    let o = ltcal(&[
        "run",
        whole.to_str().unwrap(),
        "-q",
        "--results",
        results.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    for t in ["summary", "kinds", "confusion", "cases"] {
        let a = std::fs::read(
            results
                .join("blind-blocks/scores")
                .join(format!("{t}.parquet")),
        )
        .unwrap();
        let b = std::fs::read(
            results
                .join("blind-whole/blind")
                .join(format!("{t}.parquet")),
        )
        .unwrap();
        assert_eq!(a, b, "table {t}");
    }
}

#[test]
fn a_blind_check_split_into_sweep_points_scores_as_one_check_locally_and_on_slurm() {
    let tmp = tempfile::tempdir().unwrap();
    let file = data("blind-blocks.toml");
    let local = tmp.path().join("local");
    let o = ltcal(&["run", &file, "-q", "--results", local.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert_scores_equal_one_check(&local, &file);
    let Some(_dir) = cluster() else { return };
    let _one = CLUSTER.lock().unwrap_or_else(|e| e.into_inner());
    let slurm = tmp.path().join("slurm");
    let o = on_slurm(&file, &slurm, &[]);
    assert!(o.status.success(), "{}", text(&o));
    // Each block an array task of one job.
    let jobs = jobs_record(&slurm, "blind-blocks");
    assert_eq!(jobs[0]["units"].as_array().unwrap().len(), 3);
    assert_scores_equal_one_check(&slurm, &file);
}

#[test]
fn a_task_of_another_binary_or_pipeline_file_refuses_and_writes_nothing() {
    // No cluster needed: the task is what the job script runs.
    let tmp = tempfile::tempdir().unwrap();
    let r = tmp.path().to_str().unwrap();
    let file = data("sweep.toml");
    let text_hash = blake3::hash(&std::fs::read(&file).unwrap())
        .to_hex()
        .to_string();
    let task = |code: &str, hash: &str| {
        ltcal(&[
            "task",
            &file,
            "--results",
            r,
            "--points",
            "0-1",
            "--code",
            code,
            "--pipeline-hash",
            hash,
            "--prefix",
            "slurm-1_0",
        ])
    };
    let o = task("0123456789abcdef", &text_hash);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        text(&o).contains("is not the coordinator's (code 0123456789ab)"),
        "{}",
        text(&o)
    );
    let o = task(ltcal::CODE_FINGERPRINT, "feed");
    assert!(
        text(&o).contains("changed since the job was submitted"),
        "{}",
        text(&o)
    );
    assert_eq!(files_under(tmp.path()), 0);
    // The right binary and file: two points, one pack.
    let o = task(ltcal::CODE_FINGERPRINT, &text_hash);
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains("2 ran, 0 cached, 0 failed"),
        "{}",
        text(&o)
    );
    assert_eq!(files_under(tmp.path()), 1);
}

/// A later run waited for any job still running for the pipeline, even one
/// started with other `--set` arguments (or another binary, or another
/// pipeline file), whose tasks compute other entries: its points were
/// neither submitted again nor computed.
#[test]
fn a_job_of_another_computation_is_not_waited_for() {
    let Some(_dir) = cluster() else { return };
    let _one = CLUSTER.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let results = tmp.path().join("r");
    let file = data("slow.toml");
    let detach = |set: &str| {
        let o = on_slurm(&file, &results, &["--detach", "--set", set]);
        assert!(o.status.success(), "{}", text(&o));
    };
    detach("stages.corner.seed=1");
    detach("stages.corner.seed=2");
    let jobs = jobs_record(&results, "slurm-slow");
    let jobs = jobs.as_array().unwrap();
    assert_eq!(jobs.len(), 2, "{jobs:?}");
    for j in jobs {
        assert_eq!(j["units"].as_array().unwrap().len(), 3);
    }
    assert_eq!(jobs[1]["set_args"][0], "stages.corner.seed=2");
    let ids: Vec<&str> = jobs.iter().map(|j| j["job"].as_str().unwrap()).collect();
    Command::new("scancel").args(&ids).status().unwrap();
}

/// `ltcal run` on Slurm of the origin sweep (two of four points fail at
/// their `measure`), with or without the plot after the sweep.
fn origin_on_slurm(tmp: &Path, name: &str, xs: &str, after: bool) -> String {
    let file = tmp.join(format!("{name}.toml"));
    let text = super::sweep::origin_sweep(name, xs, after)
        + "\n[executor.slurm]\npoints_per_task = 1\npoll_seconds = 1\n";
    std::fs::write(&file, text).unwrap();
    file.display().to_string()
}

#[test]
fn a_failed_sweep_point_on_slurm_is_named_with_and_without_an_after_sweep_stage() {
    let Some(_dir) = cluster() else { return };
    let _one = CLUSTER.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let results = tmp.path().join("r");
    for after in [true, false] {
        let name = if after { "origin-after" } else { "origin" };
        let file = origin_on_slurm(tmp.path(), name, "1000, 0, 2000, 0", after);
        for keep_going in [false, true] {
            let extra: &[&str] = if keep_going { &["--keep-going"] } else { &[] };
            let o = on_slurm(&file, &results, extra);
            let out = text(&o);
            assert_eq!(o.status.code(), Some(1), "{out}");
            assert!(!out.contains("panicked"), "{out}");
            for point in ["sweep point 1 (plane_x=0)", "sweep point 3 (plane_x=0)"] {
                let line = out
                    .lines()
                    .find(|l| l.contains(point))
                    .unwrap_or_else(|| panic!("{point} not named: {out}"));
                // The stage's own error, and where it ran.
                assert!(line.contains("stage `reading` failed"), "{line}");
                assert!(line.contains("array task"), "{line}");
                assert!(line.contains("log "), "{line}");
            }
            let run = std::fs::read(results.join(name).join("run.json")).unwrap();
            let run: serde_json::Value = serde_json::from_slice(&run).unwrap();
            let figure = run["stages"]
                .as_array()
                .unwrap()
                .iter()
                .find(|s| s["stage"] == "figure")
                .cloned();
            match (after, keep_going) {
                (true, true) => assert_eq!(figure.unwrap()["status"], "ran"),
                (true, false) => assert_eq!(figure.unwrap()["status"], "skipped"),
                _ => assert!(figure.is_none()),
            }
        }
        // The gathered rows of the points that ran are the local run's.
        let local = tmp.path().join("local");
        let o = ltcal(&[
            "run",
            &file,
            "-q",
            "--keep-going",
            "--results",
            local.to_str().unwrap(),
        ]);
        assert_eq!(o.status.code(), Some(1), "{}", text(&o));
        assert_eq!(
            gathered(&local, name, "reading.readings"),
            gathered(&results, name, "reading.readings")
        );
    }
}

/// Every array task of the shipped blind check in blocks ended without its
/// points (here cancelled while held; in the report, `NODE_FAIL`): the run
/// names every point with its Slurm job, task and log, and the summary
/// after the sweep is skipped — no panic.
#[test]
fn every_task_of_the_blind_check_blocks_failing_names_every_point_instead_of_panicking() {
    let Some(_dir) = cluster() else { return };
    let _one = CLUSTER.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let results = tmp.path().join("r");
    let file = tmp.path().join("blocks.toml");
    let text0 = std::fs::read_to_string(root().join("pipelines/examples/blind-check-blocks.toml"))
        .unwrap()
        .replace(
            "[executor.slurm]\n",
            "[executor.slurm]\nsbatch_options = [\"--hold\"]\npoll_seconds = 1\n",
        );
    assert!(text0.contains("--hold"));
    std::fs::write(&file, text0).unwrap();
    let child = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .args([
            "run",
            file.to_str().unwrap(),
            "-q",
            "--executor",
            "slurm",
            "--results",
        ])
        .arg(&results)
        .current_dir(root())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let jobs = results.join("blind-check-blocks/.ltcal/slurm/jobs.json");
    wait_until("the submission", 60, || jobs.exists());
    let job = jobs_record(&results, "blind-check-blocks")[0]["job"]
        .as_str()
        .unwrap()
        .to_string();
    wait_until("eight held tasks", 60, || squeue(&job).len() == 8);
    let c = Command::new("scancel").arg(&job).status().unwrap();
    assert!(c.success());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    for point in 0..8 {
        let line = err
            .lines()
            .find(|l| l.contains(&format!("sweep point {point} (")))
            .unwrap_or_else(|| panic!("point {point} not named: {err}"));
        assert!(
            line.contains(&format!("Slurm job {job}, array task {point}")),
            "{line}"
        );
    }
    assert!(
        err.contains("skipped `scores`: 8 of 8 sweep points failed"),
        "{err}"
    );
}

#[test]
fn sbatch_option_prefixes_cannot_override_the_array_or_the_logs() {
    // Refused at load, before anything reaches sbatch (no cluster needed).
    let tmp = tempfile::tempdir().unwrap();
    for bad in [
        "--arr=0-99",
        "--outpu=/tmp/x",
        "--erro=/tmp/x",
        "-Ho/tmp/x",
        "--export=ALL,PATH=/tmp/evil",
        "--qos=normal --arr=0",
    ] {
        let file = tmp.path().join("p.toml");
        let pipeline = std::fs::read_to_string(data("sweep.toml"))
            .unwrap()
            .replace(
                "[executor.slurm]\n",
                &format!("[executor.slurm]\nsbatch_options = [{bad:?}]\n"),
            );
        std::fs::write(&file, &pipeline).unwrap();
        let o = ltcal(&[
            "plan",
            file.to_str().unwrap(),
            "--results",
            tmp.path().to_str().unwrap(),
        ]);
        let out = text(&o);
        assert_eq!(o.status.code(), Some(2), "{bad}: {out}");
        let line = pipeline
            .lines()
            .position(|l| l == "[executor.slurm]")
            .unwrap()
            + 1;
        assert!(out.contains(&format!("p.toml:{line}:")), "{bad}: {out}");
        assert!(
            out.contains("ltcal sets the array, the logs"),
            "{bad}: {out}"
        );
    }
}
