//! Batch sweeps: cached points, resumption after a kill, independence from
//! the number of threads, and errors that point into the file.

use crate::cli::*;
use crate::util::*;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// A sweep of `noise` zipped noise levels × `seeds` seeds over the corner
/// campaign: simulate, calibrate (bundle), evaluate.
fn sweep_file(dir: &Path, name: &str, noise: usize, seeds: usize) -> PathBuf {
    let text = format!(
        r#"
[pipeline]
name = "{name}"

[stages.truth]
kind = "inject"

[stages.corner]
kind = "simulate_campaign"
inputs = {{ errors = "truth" }}
layout = {{ kind = "corner", stations = 4 }}
noise = {{ sigma_angle_urad = 1.0, sigma_range_um = 2.0 }}

[stages.calibration]
kind = "calibrate"
inputs = {{ campaign = "corner" }}
objective = "bundle"

[stages.evaluation]
kind = "evaluate_campaign"
inputs = {{ campaign = "corner", params = "calibration" }}

[[sweep.axis]]
path = "stages.corner.noise.sigma_angle_urad"
group = "noise"
range = {{ from = 0.25, to = {a}, step = 0.25 }}

[[sweep.axis]]
path = "stages.corner.noise.sigma_range_um"
group = "noise"
range = {{ from = 0.5, to = {r}, step = 0.5 }}

[[sweep.axis]]
path = "stages.corner.seed"
random = {{ count = {seeds}, seed = 5, low = 0, high = 1000000, integer = true }}

[sweep]
gather = ["evaluation.criteria"]

[stages.figure]
kind = "plot"
plot = "metric"
inputs = {{ table = "sweep.evaluation.criteria" }}
x = "sigma_angle_urad"
y = "improvement_pct"
filter = {{ criterion = "coordinates", station = "all", statistic = "average" }}
"#,
        a = 0.25 * noise as f64,
        r = 0.5 * noise as f64,
    );
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(&path, text).unwrap();
    path
}

fn gathered(results: &Path, name: &str) -> Vec<u8> {
    std::fs::read(
        results
            .join(name)
            .join("sweep")
            .join("evaluation.criteria.parquet"),
    )
    .unwrap()
}

#[test]
fn a_sweep_of_200_points_gathers_and_an_immediate_rerun_recomputes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let file = sweep_file(dir.path(), "s200", 20, 10);
    let first = run_pipeline(&file, dir.path(), &[]);
    let sw = first.sweep.clone().unwrap();
    assert_eq!((sw.points, sw.ran, sw.cached, sw.failed), (200, 200, 0, 0));
    let g = table(dir.path(), "s200", "sweep", "evaluation.criteria");
    // Per point: coordinates and distances × (4 stations + all) × (average,
    // maximum) = 20 rows.
    assert_eq!(g.height(), 200 * 20);
    // The columns `evaluate_campaign` declares for `criteria` are the ones
    // it writes: plot settings are checked against them at load.
    let declared = <ltcal::stages::evaluate_campaign::EvaluateCampaignStage as ltcal::stages::StageKind>::columns("criteria").unwrap();
    let names: Vec<String> = g.get_column_names().iter().map(|c| c.to_string()).collect();
    assert_eq!(
        names[4..],
        declared.iter().map(|c| c.to_string()).collect::<Vec<_>>()[..]
    );
    for c in [
        "point",
        "sigma_angle_urad",
        "sigma_range_um",
        "seed",
        "criterion",
        "improvement_pct",
    ] {
        assert!(g.column(c).is_ok(), "gathered table lacks `{c}`");
    }
    assert!(
        first
            .stages
            .iter()
            .any(|s| s.stage == "figure" && s.status == "ran")
    );
    let second = run_pipeline(&file, dir.path(), &[]);
    let sw = second.sweep.clone().unwrap();
    assert_eq!((sw.ran, sw.cached), (0, 200));
    assert!(
        second.with_status("ran").is_empty(),
        "{:?}",
        second.with_status("ran")
    );

    // `plan --check` sees the whole sweep cached, and `show` reads the
    // gathered table.
    let r = dir.path().to_str().unwrap();
    let f = file.to_str().unwrap();
    let out = ltcal(dir.path(), &["plan", f, "--results", r, "--check"]);
    assert_code(&out, 0);
    let out = ltcal(
        dir.path(),
        &["show", f, "--results", r, "sweep.evaluation.criteria"],
    );
    assert_code(&out, 0);
    assert_eq!(stdout(&out).lines().count(), 1 + 200 * 20);
}

#[test]
fn sweep_results_do_not_depend_on_the_number_of_threads() {
    let dir = tempfile::tempdir().unwrap();
    let file = sweep_file(dir.path(), "threads", 6, 4);
    let mut outputs = Vec::new();
    for threads in [1, 2] {
        let results = dir.path().join(format!("j{threads}"));
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| run_pipeline(&file, &results, &[]));
        outputs.push(gathered(&results, "threads"));
    }
    assert_eq!(
        outputs[0], outputs[1],
        "the gathered tables differ between 1 and 2 threads"
    );
}

#[test]
fn a_sweep_killed_midway_finishes_only_the_remaining_points() {
    let dir = tempfile::tempdir().unwrap();
    let file = sweep_file(dir.path(), "killed", 40, 10);
    let killed = dir.path().join("killed-results");
    let packs = killed.join("killed").join(".ltcal").join("packs");
    let mut child = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .args([
            "run",
            file.to_str().unwrap(),
            "--results",
            killed.to_str().unwrap(),
            "-q",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // Kill once the first pack of points' entries exists.
    let t0 = Instant::now();
    loop {
        let n = std::fs::read_dir(&packs)
            .map(|d| {
                d.flatten()
                    .filter(|e| e.path().extension().is_some_and(|x| x == "pack"))
                    .count()
            })
            .unwrap_or(0);
        if n >= 1 || t0.elapsed() > Duration::from_secs(60) {
            break;
        }
        if child.try_wait().unwrap().is_some() {
            panic!("the sweep finished before it could be killed: make it longer");
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let resumed = run_pipeline(&file, &killed, &[]);
    let sw = resumed.sweep.unwrap();
    assert_eq!(sw.ran + sw.cached, 400);
    assert!(
        sw.cached >= 30 && sw.ran >= 30,
        "cached {} ran {}: the kill should fall mid-sweep",
        sw.cached,
        sw.ran
    );
    // And the result is the one of an uninterrupted run.
    let clean = dir.path().join("clean-results");
    run_pipeline(&file, &clean, &[]);
    assert_eq!(gathered(&killed, "killed"), gathered(&clean, "killed"));
}

/// Before, Ctrl-C ended `ltcal run` at once: the points finished since the
/// last pack (up to a second of work) were lost. Now the first Ctrl-C
/// starts nothing more, lets what is under way finish, writes every
/// finished point to the cache and publishes nothing of the unfinished run.
#[test]
fn ctrl_c_stops_a_sweep_keeping_every_finished_point_and_publishing_nothing_of_it() {
    let dir = tempfile::tempdir().unwrap();
    let file = sweep_file(dir.path(), "stopped", 40, 10);
    let results = dir.path().join("results");
    let packs = results.join("stopped").join(".ltcal").join("packs");
    let child = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .args(["run", file.to_str().unwrap(), "--results"])
        .arg(&results)
        .arg("-q")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Stop once the first pack of points' entries exists: mid-sweep.
    let t0 = Instant::now();
    while std::fs::read_dir(&packs).map_or(0, |d| d.count()) == 0 {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "no pack in a minute"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    let kill = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(kill.success());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(130), "{err}");
    let finished: usize = err
        .split("after the stop; the ")
        .nth(1)
        .and_then(|rest| rest.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no count of finished points in: {err}"));
    assert!((1..400).contains(&finished), "{err}");
    // Nothing of the unfinished run is published.
    let folder = results.join("stopped");
    assert!(!folder.join("run.json").exists());
    assert!(!folder.join("sweep").exists());
    // Every point it said was finished is in the cache.
    let status = ltcal(
        dir.path(),
        &[
            "status",
            file.to_str().unwrap(),
            "--results",
            results.to_str().unwrap(),
        ],
    );
    let said = String::from_utf8_lossy(&status.stdout);
    assert!(
        said.contains(&format!("{finished} of 400 sweep points done")),
        "{said}"
    );
    let resumed = run_pipeline(&file, &results, &[]);
    let sw = resumed.sweep.unwrap();
    assert_eq!((sw.cached, sw.ran), (finished, 400 - finished));
}

#[test]
fn sweep_mistakes_point_into_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let file = sweep_file(dir.path(), "bad", 4, 2);
    let text = std::fs::read_to_string(&file)
        .unwrap()
        .replace("stages.corner.seed", "stages.cornr.seed");
    std::fs::write(&file, &text).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .args([
            "run",
            file.to_str().unwrap(),
            "--results",
            dir.path().join("r").to_str().unwrap(),
        ])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    let line = text.lines().position(|l| l.contains("cornr")).unwrap() + 1;
    assert_eq!(out.status.code(), Some(2));
    assert!(err.contains(&format!("bad.toml:{line}:8")), "{err}");
    assert!(
        err.contains("an axis sweeps `stages.<stage>.<field>`"),
        "{err}"
    );
}

#[test]
fn a_sweep_axis_naming_an_unknown_field_points_at_the_axis() {
    let dir = tempfile::tempdir().unwrap();
    let file = sweep_file(dir.path(), "badfield", 4, 2);
    let text = std::fs::read_to_string(&file)
        .unwrap()
        .replace("stages.corner.seed", "stages.corner.sed");
    std::fs::write(&file, &text).unwrap();
    let f = file.to_str().unwrap();
    let r = dir.path().join("r");
    let out = ltcal(dir.path(), &["plan", f, "--results", r.to_str().unwrap()]);
    assert_code(&out, 2);
    let err = stderr(&out);
    let line = text.lines().position(|l| l.contains("corner.sed")).unwrap() + 1;
    assert!(err.contains(&format!("badfield.toml:{line}:8")), "{err}");
    assert!(err.contains("sed"), "{err}");
}

#[test]
fn explain_compares_a_sweep_point_with_its_last_run() {
    let dir = tempfile::tempdir().unwrap();
    let file = sweep_file(dir.path(), "explained", 4, 2);
    run_pipeline(&file, dir.path(), &[]);
    let (f, r) = (file.to_str().unwrap(), dir.path().to_str().unwrap());
    let explain = |extra: &[&str]| {
        let mut args = vec!["explain", f, "--results", r, "corner", "--json"];
        args.extend(extra);
        let out = ltcal(dir.path(), &args);
        assert_code(&out, 0);
        serde_json::from_str::<serde_json::Value>(&stdout(&out)).unwrap()
    };
    let e = explain(&["--point", "5"]);
    assert_eq!(e["status"], "cached");
    assert_eq!(e["point"]["index"], 5);
    assert_eq!(e["point"]["points"], 8);
    assert_eq!(e["point"]["would_run"], 0);
    assert_eq!(e["point"]["values"]["sigma_angle_urad"], 0.75);
    assert_eq!(e["key"], e["last_key"]);
    assert!(
        e["rows"]
            .as_array()
            .unwrap()
            .iter()
            .all(|r| r["changed"] == false)
    );

    // One setting changed: every point would run, and the field is named.
    let e = explain(&["--set", "stages.corner.interval_s=30"]);
    assert_eq!(e["status"], "run");
    assert_eq!(e["point"]["index"], 0);
    assert_eq!(e["point"]["would_run"], 8);
    let changed: Vec<&str> = e["rows"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|r| r["changed"] == true)
        .map(|r| r["field"].as_str().unwrap())
        .collect();
    assert_eq!(changed, ["interval_s"]);

    let out = ltcal(
        dir.path(),
        &["explain", f, "--results", r, "corner", "--point", "8"],
    );
    assert_code(&out, 2);
    assert!(stderr(&out).contains("the sweep has 8 points, 0 to 7"));
}

/// Regression: `plan` matched a sweep's stages across points by position,
/// `show` served a gathered table without checking it, and `explain` was
/// only seen to pick point 0.
#[test]
fn plan_explain_and_show_follow_a_sweep_that_grew() {
    let dir = tempfile::tempdir().unwrap();
    let r = dir.path().to_str().unwrap();
    let small = sweep_file(dir.path(), "grows", 4, 2);
    run_pipeline(&small, dir.path(), &[]);
    // One more noise level: points 8 and 9 are new, 0–7 cached.
    let big = sweep_file(dir.path(), "grows", 5, 2);
    let f = big.to_str().unwrap();
    let out = ltcal(dir.path(), &["plan", f, "--results", r, "--json"]);
    assert_code(&out, 0);
    let plan: serde_json::Value = serde_json::from_str(&stdout(&out)).unwrap();
    let corner = plan
        .as_array()
        .unwrap()
        .iter()
        .find(|i| i["stage"] == "corner")
        .unwrap();
    assert_eq!(corner["status"], "run");
    let reason = corner["reason"].as_str().unwrap();
    assert!(
        reason.starts_with("2 of 10 sweep points would run it"),
        "{reason}"
    );

    let out = ltcal(
        dir.path(),
        &["explain", f, "--results", r, "corner", "--json"],
    );
    assert_code(&out, 0);
    let e: serde_json::Value = serde_json::from_str(&stdout(&out)).unwrap();
    assert_eq!(e["point"]["index"], 8);
    assert_eq!(e["point"]["would_run"], 2);

    // The gathered table on disk is the 8-point one: shown with a note.
    let out = ltcal(
        dir.path(),
        &["show", f, "--results", r, "sweep.evaluation.criteria"],
    );
    assert_code(&out, 0);
    assert!(
        stderr(&out)
            .contains("this table is from an earlier run; some sweep points would run again")
    );
    assert_eq!(stdout(&out).lines().count(), 1 + 8 * 20);

    // A stage that runs per point has no published table of its own.
    let out = ltcal(dir.path(), &["show", f, "--results", r, "corner"]);
    assert_code(&out, 2);
    assert!(
        stderr(&out).contains("`corner` runs at every sweep point"),
        "{}",
        stderr(&out)
    );

    // Current again: a gathered table changed by hand is refused.
    run_pipeline(&big, dir.path(), &[]);
    let gathered = dir.path().join("grows/sweep/evaluation.criteria.parquet");
    let mut bytes = std::fs::read(&gathered).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x01;
    std::fs::write(&gathered, bytes).unwrap();
    let out = ltcal(
        dir.path(),
        &["show", f, "--results", r, "sweep.evaluation.criteria"],
    );
    assert_code(&out, 1);
    assert!(stderr(&out).contains("differs from the result it was published from"));

    // Shrunk back: points 8 and 9 are no longer points of the sweep, and
    // every remaining point is cached (its record of the last run is in
    // the packs, 32 bytes a stage).
    let small = sweep_file(dir.path(), "grows", 4, 2);
    let shrunk = run_pipeline(&small, dir.path(), &[]);
    assert_eq!(shrunk.sweep.unwrap().cached, 8);
    let fs = small.to_str().unwrap();
    let out = ltcal(
        dir.path(),
        &["explain", fs, "--results", r, "corner", "--point", "9"],
    );
    assert_code(&out, 2);
    assert!(
        stderr(&out).contains("the sweep has 8 points"),
        "{}",
        stderr(&out)
    );
}

/// Regression: with an axis over a stage's input, the stages of one point
/// can run in another order than those of the next; `plan` matched them by
/// position and reported one stage's status under another's name.
#[test]
fn plan_matches_a_sweeps_stages_by_name_when_an_axis_reorders_them() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("reorder.toml");
    let text = |seed: u32| {
        format!(
            r#"
[pipeline]
name = "reorder"

[stages.truth]
kind = "inject"

[stages.a]
kind = "simulate_campaign"
inputs = {{ errors = "truth" }}
layout = {{ kind = "corner", stations = 3 }}

[stages.cal_a]
kind = "calibrate"
inputs = {{ campaign = "a" }}
objective = "bundle"

[stages.z]
kind = "simulate_campaign"
inputs = {{ errors = "truth" }}
layout = {{ kind = "corner", stations = 3 }}
seed = {seed}

[[sweep.axis]]
path = "stages.z.inputs.errors"
values = ["truth", "cal_a"]

[sweep]
gather = ["z.readings"]
"#
        )
    };
    std::fs::write(&file, text(5)).unwrap();
    run_pipeline(&file, dir.path(), &[]);
    std::fs::write(&file, text(6)).unwrap();
    let (f, r) = (file.to_str().unwrap(), dir.path().to_str().unwrap());
    let out = ltcal(dir.path(), &["plan", f, "--results", r, "--json"]);
    assert_code(&out, 0);
    let plan: serde_json::Value = serde_json::from_str(&stdout(&out)).unwrap();
    let item = |stage: &str| {
        plan.as_array()
            .unwrap()
            .iter()
            .find(|i| i["stage"] == stage)
            .unwrap()
            .clone()
    };
    assert_eq!(item("cal_a")["status"], "cached");
    let z = item("z");
    assert!(
        z["reason"]
            .as_str()
            .unwrap()
            .starts_with("2 of 2 sweep points would run it"),
        "{z}"
    );
}

/// Regression (issue 12): a plot `filter` naming a column that does not
/// exist was found only after the whole sweep had run. It is refused at
/// load, at its place in the file, with the table's columns; so are `x`,
/// `y` and `series`, and a table read directly rather than gathered.
#[test]
fn a_plot_filter_naming_a_missing_column_is_refused_at_load() {
    let dir = tempfile::tempdir().unwrap();
    let file = sweep_file(dir.path(), "typo", 4, 2);
    let text = std::fs::read_to_string(&file)
        .unwrap()
        .replace("station = \"all\"", "statoin = \"all\"")
        .replace("y = \"improvement_pct\"", "y = \"improvment_pct\"");
    std::fs::write(&file, &text).unwrap();
    let err = ltcal::pipeline::load(&file, &[]).unwrap_err().to_string();
    let at = |needle: &str| {
        let line = text.lines().position(|l| l.contains(needle)).unwrap();
        let col = text.lines().nth(line).unwrap().find(needle).unwrap();
        format!("typo.toml:{}:{}", line + 1, col + 1)
    };
    // The filter's value, where the column is named.
    let filter_line = text.lines().position(|l| l.contains("statoin")).unwrap() + 1;
    assert!(err.contains(&format!("typo.toml:{filter_line}:")), "{err}");
    assert!(err.contains(&at("\"improvment_pct\"")), "{err}");
    assert!(err.contains("column `statoin`"), "{err}");
    assert!(
        err.contains("sigma_angle_urad, sigma_range_um, seed, criterion"),
        "{err}"
    );

    // Read directly from the stage, not gathered.
    let direct = text
        .replace(
            "table = \"sweep.evaluation.criteria\"",
            "table = \"evaluation.criteria\"",
        )
        .replace("x = \"sigma_angle_urad\"", "x = \"before_um\"");
    let direct = direct[..direct.find("[[sweep.axis]]").unwrap()].to_string()
        + &direct[direct.find("[stages.figure]").unwrap()..];
    std::fs::write(&file, &direct).unwrap();
    let err = ltcal::pipeline::load(&file, &[]).unwrap_err().to_string();
    assert!(err.contains("column `improvment_pct`"), "{err}");
    assert!(!err.contains("column `before_um`"), "{err}");
}

fn packs_of(results: &Path, name: &str) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(results.join(name).join(".ltcal/packs"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "pack"))
        .collect();
    v.sort();
    v
}

/// The position in `pack` of the last byte of part `part` (tables, then
/// files, in manifest order) of the first entry of stage `stage`.
fn last_byte_of(pack: &Path, stage: &str, part: usize) -> usize {
    use ltcal::pipeline::pack;
    let ix = pack::read_index(pack).unwrap();
    let (_, span) = ix
        .entries
        .iter()
        .find(|(_, span)| {
            let m = pack::read_manifest(pack, *span).unwrap();
            let m: serde_json::Value = serde_json::from_slice(&m).unwrap();
            m["stage"] == stage
        })
        .unwrap();
    let bytes = pack::read_span(pack, *span).unwrap();
    let blob = pack::split(&bytes, |m| {
        let m: serde_json::Value = serde_json::from_slice(m).unwrap();
        Ok(m["tables"].as_array().unwrap().len() + m["files"].as_array().unwrap().len())
    })
    .unwrap();
    let b = blob.parts[part];
    span.offset as usize + (b.as_ptr() as usize - bytes.as_ptr() as usize) + b.len() - 1
}

/// A cached sweep point's gathered table is read and verified alone, not
/// its whole entry: a damaged table of the entry that nothing reads
/// (`evaluation.terms`, the last of its five) is never served, the gathered
/// table is unchanged, and the run's closing heal finds the pack changed,
/// reads it whole and takes the damaged entry out, saying so.
#[test]
fn a_damaged_table_nothing_reads_is_not_served_and_the_run_heals_it() {
    let dir = tempfile::tempdir().unwrap();
    let file = sweep_file(dir.path(), "unread", 2, 2);
    let results = dir.path().join("r");
    run_pipeline(&file, &results, &[]);
    let clean = gathered(&results, "unread");
    let pack = packs_of(&results, "unread").remove(0);
    let at = last_byte_of(&pack, "evaluation", 4);
    let mut bytes = std::fs::read(&pack).unwrap();
    bytes[at] ^= 0x01;
    std::fs::write(&pack, &bytes).unwrap();
    let r = run_pipeline(&file, &results, &[]);
    assert!(
        r.stages.iter().all(|s| s.cache_problem.is_none()),
        "{:?}",
        r.stages
    );
    assert_eq!(gathered(&results, "unread"), clean);
    assert_eq!(r.healed.len(), 1, "{:?}", r.healed);
    assert!(
        r.healed[0]
            .damage
            .contains("terms.parquet does not match its manifest"),
        "{}",
        r.healed[0]
    );
    // The entry taken out is computed again, and the same.
    let r = run_pipeline(&file, &results, &[]);
    assert_eq!(r.sweep.as_ref().unwrap().ran, 1);
    assert_eq!(gathered(&results, "unread"), clean);
}

/// A sweep point's damaged packed entry was recomputed without a word: the
/// per-stage line of a sweep dropped every `cache_problem`, and a pack
/// whose index could not be read was skipped silently.
#[test]
fn a_damaged_pack_is_reported_and_its_points_recomputed() {
    let dir = tempfile::tempdir().unwrap();
    let file = sweep_file(dir.path(), "damaged", 4, 2);
    let results = dir.path().join("r");
    run_pipeline(&file, &results, &[]);
    let clean = gathered(&results, "damaged");
    let pack = packs_of(&results, "damaged").remove(0);
    // The last byte of the gathered table in its stage's entry: read by the
    // gather, it fails its hash, is reported and recomputed. (A damaged
    // table nothing reads is never read, so never served:
    // `a_damaged_table_nothing_reads_is_not_served_and_the_run_heals_it`.)
    let at = last_byte_of(&pack, "evaluation", 0);
    let mut bytes = std::fs::read(&pack).unwrap();
    bytes[at] ^= 0x01;
    std::fs::write(&pack, &bytes).unwrap();
    let r = run_pipeline(&file, &results, &[]);
    let damaged: Vec<_> = r
        .stages
        .iter()
        .filter(|s| s.cache_problem.is_some())
        .collect();
    assert!(!damaged.is_empty(), "{:?}", r.stages);
    assert!(
        damaged[0]
            .cache_problem
            .as_ref()
            .unwrap()
            .contains("recomputed"),
        "{:?}",
        damaged[0].cache_problem
    );
    assert_eq!(gathered(&results, "damaged"), clean);
    // A byte of the index: the pack is not read at all, and said so.
    bytes[at] ^= 0x01;
    let end = bytes.len() - 60;
    bytes[end] ^= 0x01;
    std::fs::write(&pack, &bytes).unwrap();
    let r = run_pipeline(&file, &results, &[]);
    assert_eq!(r.unreadable_packs.len(), 1, "{:?}", r.unreadable_packs);
    assert!(r.unreadable_packs[0].contains("does not match its hash"));
    assert_eq!(gathered(&results, "damaged"), clean);
}

/// A sweep of a plane mesh measured by a tracker with errors, over the
/// plane's distance `x_mm`: a distance of 0 puts a reflector at the
/// tracker's origin, where the error model has no inverse, and fails that
/// point's `measure`. With
/// `after`, a plot of the gathered readings runs after the sweep.
pub fn origin_sweep(name: &str, xs: &str, after: bool) -> String {
    let mut text = format!(
        r#"
[pipeline]
name = "{name}"

[stages.truth]
kind = "inject"

[stages.mesh]
kind = "mesh"
shape = "plane"
x_mm = 1000
y = {{ from = 0, to = 500, step = 500 }}
z = {{ from = 0, to = 500, step = 500 }}

[stages.reading]
kind = "measure"
inputs = {{ points = "mesh", errors = "truth" }}

[[sweep.axis]]
path = "stages.mesh.x_mm"
name = "plane_x"
values = [{xs}]

[sweep]
gather = ["reading.readings"]
"#
    );
    if after {
        text.push_str(
            r#"
[stages.figure]
kind = "plot"
plot = "metric"
inputs = { table = "sweep.reading.readings" }
x = "plane_x"
y = "d_mm"
series = "target"
"#,
        );
    }
    text
}

/// The gathered readings' rows of `points`, the `point` column dropped.
fn rows_of(results: &Path, name: &str, points: &[i64]) -> polars::prelude::DataFrame {
    let df = ltcal::table::read_parquet(
        &results
            .join(name)
            .join("sweep")
            .join("reading.readings.parquet"),
    )
    .unwrap();
    let point = ltcal::table::TableRef::new("t", &df).i64("point").unwrap();
    let keep: polars::prelude::BooleanChunked = point.iter().map(|p| points.contains(p)).collect();
    df.filter(&keep).unwrap().drop("point").unwrap()
}

#[test]
fn a_failed_sweep_point_with_an_after_sweep_stage_names_the_point_instead_of_panicking() {
    let dir = tempfile::tempdir().unwrap();
    let r = dir.path().join("r");
    let results = r.to_str().unwrap();
    for after in [true, false] {
        let name = if after { "origin-after" } else { "origin" };
        let file = dir.path().join(format!("{name}.toml"));
        std::fs::write(&file, origin_sweep(name, "1000, 0, 2000, 0", after)).unwrap();
        let f = file.to_str().unwrap();
        for keep_going in [false, true] {
            let mut args = vec!["run", f, "-q", "--results", results];
            if keep_going {
                args.push("--keep-going");
            }
            let out = ltcal(dir.path(), &args);
            let err = stderr(&out);
            assert_code(&out, 1);
            assert!(!err.contains("panicked"), "{err}");
            // Every failed point named, with its stage and reason.
            for point in ["sweep point 1 (plane_x=0)", "sweep point 3 (plane_x=0)"] {
                assert!(err.contains(point), "{point}: {err}");
            }
            assert_eq!(
                err.matches("stage `reading` (measure) failed").count(),
                2,
                "{err}"
            );
            let st = stages(&run_json(&r, name));
            if after && keep_going {
                assert_eq!(st["figure"]["status"], "ran", "{err}");
            } else if after {
                assert_eq!(st["figure"]["status"], "skipped");
                assert_eq!(
                    st["figure"]["reason"],
                    "2 of 4 sweep points failed (--keep-going runs it on the others)"
                );
            }
        }
        // Kept going, the gathered rows of the points that succeeded are a
        // clean run's.
        let clean = format!("{name}-clean");
        let clean_file = dir.path().join(format!("{clean}.toml"));
        std::fs::write(
            &clean_file,
            origin_sweep(&clean, "1000, 500, 2000, 700", after),
        )
        .unwrap();
        let out = ltcal(
            dir.path(),
            &[
                "run",
                clean_file.to_str().unwrap(),
                "-q",
                "--results",
                results,
            ],
        );
        assert_code(&out, 0);
        let kept = rows_of(&r, name, &[0, 2]);
        assert_eq!(kept.height(), 2 * 4, "two points of four reflectors");
        assert!(kept.equals(&rows_of(&r, &clean, &[0, 2])));
        assert_eq!(rows_of(&r, name, &[1, 3]).height(), 0);
    }
}

#[test]
fn a_sweep_whose_every_point_failed_skips_its_after_sweep_stage_even_kept_going() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("all-failed.toml");
    std::fs::write(&file, origin_sweep("all-failed", "0, 0", true)).unwrap();
    let r = dir.path().join("r");
    let out = ltcal(
        dir.path(),
        &[
            "run",
            file.to_str().unwrap(),
            "-q",
            "--keep-going",
            "--results",
            r.to_str().unwrap(),
        ],
    );
    assert_code(&out, 1);
    let err = stderr(&out);
    assert!(err.contains("sweep point 0 (plane_x=0)"), "{err}");
    assert!(err.contains("sweep point 1 (plane_x=0)"), "{err}");
    let st = stages(&run_json(&r, "all-failed"));
    assert_eq!(st["figure"]["status"], "skipped");
    assert_eq!(
        st["figure"]["reason"],
        "its input sweep.reading.readings (no sweep point produced it) did not complete"
    );
}

/// Writes a pipeline whose one axis is `axis` and returns `plan`'s output
/// and how long it took.
fn plan_with_axis(dir: &Path, axis: &str) -> (std::process::Output, Duration, String) {
    let text = origin_sweep("big", "1", false).replace("values = [1]", axis);
    let file = dir.join("big.toml");
    std::fs::write(&file, &text).unwrap();
    let t = Instant::now();
    let out = ltcal(
        dir,
        &[
            "plan",
            file.to_str().unwrap(),
            "--results",
            dir.join("r").to_str().unwrap(),
        ],
    );
    (out, t.elapsed(), text)
}

#[test]
fn a_random_axis_of_a_billion_points_is_refused_at_load() {
    let dir = tempfile::tempdir().unwrap();
    for (axis, says) in [
        (
            "random = { count = 1000000000, seed = 1, low = 0, high = 1 }",
            "`random.count` = 1000000000 is more than the limit of 100000 points",
        ),
        (
            "random = { count = 100000000, seed = 1, low = 0, high = 1 }",
            "`random.count` = 100000000 is more than the limit of 100000 points",
        ),
        (
            "random = { count = 9223372036854775807, seed = 1, low = 0, high = 1 }",
            "more than the limit of 100000 points",
        ),
        (
            "range = { from = 0, to = 1, step = 0.00001 }",
            "`range` gives 100001 values, more than the limit of 100000 points",
        ),
        (
            "range = { from = 0, to = 1, step = 1e-12 }",
            "more than the limit of 1000000",
        ),
    ] {
        let (out, took, text) = plan_with_axis(dir.path(), axis);
        let err = stderr(&out);
        assert_code(&out, 2);
        let line = text.lines().position(|l| l.contains(axis)).unwrap() + 1;
        assert!(err.contains(&format!("big.toml:{line}:")), "{axis}: {err}");
        assert!(err.contains(says), "{axis}: {err}");
        assert!(took < Duration::from_secs(1), "{axis}: {took:?}");
    }
    // Numbers TOML cannot hold as integers are refused where they stand.
    for axis in [
        "random = { count = 18446744073709551615, seed = 1, low = 0, high = 1 }",
        "random = { count = 1e8, seed = 1, low = 0, high = 1 }",
    ] {
        let (out, took, text) = plan_with_axis(dir.path(), axis);
        let err = stderr(&out);
        assert_code(&out, 2);
        let line = text.lines().position(|l| l.contains(axis)).unwrap() + 1;
        assert!(err.contains(&format!("big.toml:{line}:")), "{axis}: {err}");
        assert!(took < Duration::from_secs(1), "{axis}: {took:?}");
    }
}

#[test]
fn a_grid_of_axes_over_the_limit_is_refused_at_the_widest_axis() {
    let dir = tempfile::tempdir().unwrap();
    let axis = "range = { from = 1, to = 1000, step = 1 }\n[[sweep.axis]]\npath = \"stages.reading.seed\"\nrange = { from = 1, to = 1000, step = 1 }";
    let (out, took, text) = plan_with_axis(dir.path(), axis);
    let err = stderr(&out);
    assert_code(&out, 2);
    let line = text
        .lines()
        .position(|l| l.contains("stages.mesh.x_mm"))
        .unwrap()
        + 1;
    assert!(err.contains(&format!("big.toml:{line}:8")), "{err}");
    assert!(
        err.contains("the sweep expands to 1000000 points, more than the limit of 100000"),
        "{err}"
    );
    assert!(took < Duration::from_secs(1), "{took:?}");
}

#[test]
fn a_mesh_of_a_trillion_points_is_refused_at_load() {
    let dir = tempfile::tempdir().unwrap();
    let text = origin_sweep("mesh", "1000", false).replace(
        "y = { from = 0, to = 500, step = 500 }",
        "y = { from = 0, to = 999999, step = 1 }",
    );
    let text = text.replace(
        "z = { from = 0, to = 500, step = 500 }",
        "z = { from = 0, to = 999999, step = 1 }",
    );
    let file = dir.path().join("mesh.toml");
    std::fs::write(&file, &text).unwrap();
    let t = Instant::now();
    let out = ltcal(
        dir.path(),
        &[
            "plan",
            file.to_str().unwrap(),
            "--results",
            dir.path().join("r").to_str().unwrap(),
        ],
    );
    let err = stderr(&out);
    assert_code(&out, 2);
    assert!(
        err.contains("the mesh has 1000000000000 points, more than the limit of 1000000"),
        "{err}"
    );
    let line = text.lines().position(|l| l.starts_with("z = ")).unwrap() + 1;
    assert!(err.contains(&format!("mesh.toml:{line}:")), "{err}");
    assert!(t.elapsed() < Duration::from_secs(1));
}
