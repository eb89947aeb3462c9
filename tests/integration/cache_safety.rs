//! The cache under damage, kills and concurrency: a damaged entry is
//! detected, reported and recomputed; a run killed at any moment leaves
//! nothing that is later served; concurrent runs agree with a single one;
//! published copies are never seen half-written.

use crate::cli::*;
use crate::util::pipeline_path;
use ltcal::pipeline::cache::{Lookup, Manifest, Store};
use rand::rngs::ChaCha8Rng;
use rand::{RngExt, SeedableRng};
use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const PIPELINE: &str = "synthetic-validation";

fn file() -> String {
    pipeline_path("synthetic-validation.toml")
        .to_string_lossy()
        .into_owned()
}

/// `ltcal run` of the synthetic validation into `results`, with `--set`s.
fn run(results: &Path, sets: &[&str]) -> std::process::Output {
    let f = file();
    let r = results.to_string_lossy().into_owned();
    let mut args = vec!["run", f.as_str(), "--results", r.as_str()];
    for s in sets {
        args.extend(["--set", s]);
    }
    ltcal(results.parent().unwrap(), &args)
}

fn run_ok(results: &Path) -> std::process::Output {
    let out = run(results, &[]);
    assert_code(&out, 0);
    out
}

fn cache_dir(results: &Path) -> std::path::PathBuf {
    results.join(PIPELINE).join(".ltcal").join("cache")
}

/// The key of a stage in the last run.
fn key_of(results: &Path, stage: &str) -> String {
    stages(&run_json(results, PIPELINE))[stage]["key"]
        .as_str()
        .unwrap()
        .to_string()
}

/// Every entry in the cache verifies (manifest present, every hash right).
fn assert_every_entry_verifies(results: &Path) {
    let store = Store::new(&results.join(PIPELINE));
    for e in std::fs::read_dir(cache_dir(results)).unwrap().flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        assert!(!name.starts_with('.'), "leftover {name}");
        assert!(
            matches!(store.lookup(&name), Lookup::Hit(_)),
            "entry {name} does not verify"
        );
    }
}

#[test]
fn a_flipped_byte_in_a_cached_table_is_detected_reported_and_recomputed() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_ok(&results);
    let before = published(&results, PIPELINE);
    let key = key_of(&results, "evaluate_sphere");
    let table = cache_dir(&results).join(&key).join("summary.parquet");
    let mut bytes = std::fs::read(&table).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x01;
    std::fs::write(&table, &bytes).unwrap();

    let out = run_ok(&results);
    let err = stderr(&out);
    assert!(
        err.contains("1 CORRUPT cache entry recomputed"),
        "no summary of the damage in:\n{err}"
    );
    assert!(
        err.contains("cache entry of `evaluate_sphere` was corrupt and is recomputed: table summary.parquet does not match its manifest"),
        "{err}"
    );
    let st = stages(&run_json(&results, PIPELINE));
    let s = &st["evaluate_sphere"];
    assert_eq!(s["status"], "ran");
    assert!(
        s["cache_problem"]
            .as_str()
            .unwrap()
            .contains("summary.parquet does not match its manifest"),
        "{s}"
    );
    assert!(
        s["reason"]
            .as_str()
            .unwrap()
            .starts_with("its cached result was corrupt")
    );
    // Only that stage ran: its output is identical, so nothing downstream did.
    let ran: Vec<&String> = st
        .iter()
        .filter(|(_, s)| s["status"] == "ran")
        .map(|(n, _)| n)
        .collect();
    assert_eq!(ran, ["evaluate_sphere"]);
    assert_eq!(published(&results, PIPELINE), before);
    assert_eq!(std::fs::read(&table).unwrap()[mid], bytes[mid] ^ 0x01);
    assert_every_entry_verifies(&results);
    // The page says so too.
    let html = std::fs::read_to_string(results.join(PIPELINE).join("index.html")).unwrap();
    assert!(
        html.contains("<b>cache problem:</b> table summary.parquet does not match its manifest")
    );
}

#[test]
fn truncated_tables_edited_manifests_and_missing_figures_are_detected() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_ok(&results);
    let before = published(&results, PIPELINE);
    let cache = cache_dir(&results);
    // Truncated table.
    let t = cache
        .join(key_of(&results, "identify_plane"))
        .join("params.parquet");
    let b = std::fs::read(&t).unwrap();
    std::fs::write(&t, &b[..b.len() - 7]).unwrap();
    // A manifest edited to claim other content.
    let m = cache
        .join(key_of(&results, "measure_cube"))
        .join("manifest.json");
    let mut manifest: Manifest = serde_json::from_slice(&std::fs::read(&m).unwrap()).unwrap();
    manifest.tables[0].hash = "0".repeat(64);
    std::fs::write(&m, serde_json::to_vec(&manifest).unwrap()).unwrap();
    // A figure removed from its entry.
    let fig_key = key_of(&results, "figure7");
    std::fs::remove_file(cache.join(&fig_key).join("files").join("figure7.svg")).unwrap();

    let out = run_ok(&results);
    let err = stderr(&out);
    assert!(err.contains("3 CORRUPT cache entries recomputed"), "{err}");
    let st = stages(&run_json(&results, PIPELINE));
    let problem = |s: &str| st[s]["cache_problem"].as_str().unwrap_or("").to_string();
    assert!(
        problem("identify_plane").contains("params.parquet does not match"),
        "{st:?}"
    );
    assert!(
        problem("measure_cube").contains("readings.parquet does not match"),
        "{st:?}"
    );
    assert!(
        problem("figure7").contains("file figure7.svg is missing"),
        "{st:?}"
    );
    assert_eq!(published(&results, PIPELINE), before);
    assert_every_entry_verifies(&results);
}

#[test]
fn an_entry_without_a_manifest_is_ignored_and_removed() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_ok(&results);
    let key = key_of(&results, "correct_cube");
    let entry = cache_dir(&results).join(&key);
    std::fs::remove_file(entry.join("manifest.json")).unwrap();
    let out = run_ok(&results);
    let run = run_json(&results, PIPELINE);
    assert_eq!(run["cleaned"], 1, "{}", stderr(&out));
    let st = stages(&run);
    assert_eq!(st["correct_cube"]["status"], "ran");
    assert_eq!(st["correct_cube"]["reason"], "its cached result is missing");
    assert!(st["correct_cube"]["cache_problem"].is_null());
    assert!(entry.join("manifest.json").exists());
    assert_every_entry_verifies(&results);
}

#[test]
fn the_manifest_records_the_provenance_of_every_table() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_ok(&results);
    let st = stages(&run_json(&results, PIPELINE));
    let read = |stage: &str| -> Manifest {
        let k = st[stage]["key"].as_str().unwrap();
        serde_json::from_slice(
            &std::fs::read(cache_dir(&results).join(k).join("manifest.json")).unwrap(),
        )
        .unwrap()
    };
    let m = read("measure_sphere_noisy");
    assert_eq!(m.stage, "measure_sphere_noisy");
    assert_eq!(m.key_fields.kind, "measure");
    assert_eq!(m.key_fields.ltcal_version, ltcal::VERSION);
    assert_eq!(m.key_fields.code, ltcal::CODE_FINGERPRINT);
    assert_eq!(m.key_fields.params["seed"], 1);
    assert_eq!(m.key_fields.params["noise"]["sigma_angle_urad"], 1.0);
    assert_eq!(m.key_fields.hash(), m.key);
    // Each input's hash is the content hash its producer recorded.
    let points = read("sphere");
    assert_eq!(m.key_fields.inputs["points"], points.tables[0].hash);
    assert_eq!(m.key_fields.inputs["errors"], read("truth").tables[0].hash);
    // Rows and content hash of each table, as published.
    let t = &m.tables[0];
    assert_eq!(t.name, "readings");
    assert_eq!(t.rows, 480);
    let bytes = std::fs::read(
        results
            .join(PIPELINE)
            .join("measure_sphere_noisy/readings.parquet"),
    )
    .unwrap();
    assert_eq!(blake3::hash(&bytes).to_hex().as_str(), t.hash);
    assert_eq!(
        ltcal::table::from_parquet_bytes(&bytes).unwrap().height(),
        480
    );
    // Start and end as RFC 3339 times, in order.
    let start = humantime::parse_rfc3339(&m.started).unwrap();
    let end = humantime::parse_rfc3339(&m.finished).unwrap();
    assert!(start <= end, "{} > {}", m.started, m.finished);
}

/// Turns a results folder into what a build from other code (fingerprint
/// `code`) would have left: every cache entry's and every last-run
/// record's key fields carry `code`, each entry under its key from them.
/// The stale build computed `identify_sphere_table3` differently: its
/// first table, cached and published, holds other (valid) bytes. Returns
/// that table's published path and the bytes this build computes for it.
fn as_if_built_from(results: &Path, code: &str) -> (std::path::PathBuf, Vec<u8>) {
    let stale_stage = "identify_sphere_table3";
    let stale_key = key_of(results, stale_stage);
    // What the stale build computed: another stage's table of the same name.
    let donor = cache_dir(results).join(key_of(results, "identify_sphere"));
    let donor_m: Manifest =
        serde_json::from_slice(&std::fs::read(donor.join("manifest.json")).unwrap()).unwrap();
    let other = std::fs::read(donor.join(format!("{}.parquet", donor_m.tables[0].name))).unwrap();
    let mut fresh = None;
    let entries: Vec<_> = std::fs::read_dir(cache_dir(results))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    for dir in entries {
        let mpath = dir.join("manifest.json");
        let mut m: Manifest = serde_json::from_slice(&std::fs::read(&mpath).unwrap()).unwrap();
        if m.key == stale_key {
            let t = &mut m.tables[0];
            assert_eq!(t.name, donor_m.tables[0].name);
            let name = format!("{}.parquet", t.name);
            let published = results.join(PIPELINE).join(stale_stage).join(&name);
            fresh = Some((published.clone(), std::fs::read(dir.join(&name)).unwrap()));
            assert_ne!(fresh.as_ref().unwrap().1, other);
            std::fs::write(dir.join(&name), &other).unwrap();
            std::fs::write(&published, &other).unwrap();
            t.hash = ltcal::pipeline::cache::hash_bytes(&other);
            t.rows = donor_m.tables[0].rows;
        }
        m.key_fields.code = code.to_string();
        m.key = m.key_fields.hash();
        std::fs::write(&mpath, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
        std::fs::rename(&dir, cache_dir(results).join(&m.key)).unwrap();
    }
    let last = results.join(PIPELINE).join(".ltcal").join("last");
    for e in std::fs::read_dir(last).unwrap().flatten() {
        let mut k: serde_json::Value =
            serde_json::from_slice(&std::fs::read(e.path()).unwrap()).unwrap();
        k["code"] = code.into();
        std::fs::write(e.path(), serde_json::to_vec(&k).unwrap()).unwrap();
    }
    fresh.expect("the stale stage has an entry")
}

#[test]
fn a_code_change_invalidates_every_cached_stage() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_ok(&results);
    let old = "0123456789abcdef".repeat(4);
    let (published_table, fresh) = as_if_built_from(&results, &old);
    assert_every_entry_verifies(&results);
    let r = results.to_string_lossy().into_owned();
    let f = file();
    let because = format!(
        "the code changed (0123456789ab → {})",
        &ltcal::CODE_FINGERPRINT[..12]
    );

    // `plan`: every stage would run, each because of the code.
    let out = ltcal(dir.path(), &["plan", &f, "--results", &r, "--json"]);
    assert_code(&out, 0);
    let items: Vec<serde_json::Value> = serde_json::from_str(&stdout(&out)).unwrap();
    assert_eq!(items.len(), 25);
    for i in &items {
        assert_eq!(i["status"], "run", "{i}");
        assert_eq!(i["reason"], because.as_str(), "{i}");
    }
    assert_code(
        &ltcal(dir.path(), &["plan", &f, "--results", &r, "--check"]),
        1,
    );

    // `explain` says so, and marks the one field that differs.
    let out = ltcal(
        dir.path(),
        &["explain", &f, "--results", &r, "identify_sphere_table3"],
    );
    assert_code(&out, 0);
    let text = stdout(&out);
    assert!(text.contains(&format!("would run: {because}")), "{text}");
    let changed: Vec<&str> = text
        .lines()
        .filter(|l| l.trim_start().starts_with('*'))
        .collect();
    assert_eq!(changed.len(), 1, "{text}");
    assert!(
        changed[0].contains("code") && changed[0].contains("0123456789ab"),
        "{text}"
    );

    // `run` reruns everything and publishes what this code computes, not
    // the stale table.
    run_ok(&results);
    let st = stages(&run_json(&results, PIPELINE));
    assert!(
        st.values()
            .all(|s| s["status"] == "ran" && s["reason"] == because.as_str()),
        "{st:?}"
    );
    assert_eq!(std::fs::read(&published_table).unwrap(), fresh);
    assert_code(
        &ltcal(dir.path(), &["plan", &f, "--results", &r, "--check"]),
        0,
    );
}

/// The compiled-in fingerprint is that of the sources in this checkout: what
/// `build.rs` hashes is what `cargo test` built from.
#[test]
fn the_built_in_code_fingerprint_is_the_hash_of_the_sources_built() {
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    assert_eq!(
        ltcal::code::fingerprint(&root).unwrap(),
        ltcal::CODE_FINGERPRINT
    );
}

/// The published results of a clean run, and how long it took.
fn reference() -> (tempfile::TempDir, BTreeMap<String, Vec<u8>>, Duration) {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    let t0 = Instant::now();
    run_ok(&results);
    let took = t0.elapsed();
    let published = published(&results, PIPELINE);
    (dir, published, took)
}

/// Starts `ltcal run` and SIGKILLs it after `delay`.
fn kill_after(results: &Path, sets: &[String], delay: Duration) {
    let mut cmd = Command::new(BIN);
    cmd.args(["run", &file(), "--results", results.to_str().unwrap(), "-q"]);
    for s in sets {
        cmd.args(["--set", s]);
    }
    let mut child = cmd
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(delay);
    // `kill` is SIGKILL on Unix; it fails only if the run already ended.
    let _ = child.kill();
    child.wait().unwrap();
}

#[test]
fn runs_killed_at_random_moments_never_leave_a_served_bad_entry() {
    let (_ref_dir, expected, took) = reference();
    // Delays up to a little beyond a whole run, so kills land everywhere:
    // before the first stage, amid writes, while publishing, at the end.
    let span = took.as_micros() as u64 * 6 / 5;
    let mut rng = ChaCha8Rng::seed_from_u64(20260);
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    let trials = 32;
    // Trials in which the kill cut work short: the next run had to compute.
    let mut interrupted = 0;
    // Trials in which the kill left temporary files or directories.
    let mut mid_write = 0;
    for trial in 0..trials {
        // Even trials start from nothing; odd ones continue from whatever
        // the previous trial left.
        if trial % 2 == 0 && results.exists() {
            std::fs::remove_dir_all(&results).unwrap();
        }
        // Some killed runs compute other settings (a new noisy chain):
        // experiments, published apart, which leave the reference alone.
        let sets: Vec<String> = if trial % 4 == 1 {
            vec![format!("stages.measure_sphere_noisy.seed={}", 100 + trial)]
        } else {
            Vec::new()
        };
        let delay = Duration::from_micros(rng.random_range(0..span));
        kill_after(&results, &sets, delay);
        if trial % 4 == 3 {
            // And sometimes the next run is killed as well.
            kill_after(
                &results,
                &[],
                Duration::from_micros(rng.random_range(0..span)),
            );
        }
        let out = run(&results, &[]);
        assert_code(&out, 0);
        let run = run_json(&results, PIPELINE);
        assert!(
            stages(&run).values().all(|s| s["cache_problem"].is_null()),
            "trial {trial} ({delay:?}): a published entry failed verification:\n{}",
            stderr(&out)
        );
        if stages(&run).values().any(|s| s["status"] == "ran") {
            interrupted += 1;
        }
        if run["cleaned"].as_u64().unwrap() > 0 {
            mid_write += 1;
        }
        let got = published(&results, PIPELINE);
        assert_eq!(
            got.keys().collect::<Vec<_>>(),
            expected.keys().collect::<Vec<_>>(),
            "trial {trial} ({delay:?})"
        );
        for (name, bytes) in &expected {
            assert!(
                got[name] == *bytes,
                "trial {trial} ({delay:?}): {name} differs from the reference"
            );
        }
        assert_every_entry_verifies(&results);
        let left = leftovers(&results);
        assert!(left.is_empty(), "trial {trial}: leftovers {left:?}");
    }
    // The kills landed amid work, not all after it.
    eprintln!("{trials} trials: {interrupted} interrupted a run, {mid_write} amid a write");
    assert!(
        interrupted >= trials / 8,
        "only {interrupted} of {trials} kills interrupted a run"
    );
}

#[test]
fn concurrent_runs_on_one_folder_agree_with_a_single_run() {
    let (_ref_dir, expected, _) = reference();
    for round in 0..3 {
        let dir = tempfile::tempdir().unwrap();
        let results = dir.path().join("results");
        let children: Vec<_> = (0..3)
            .map(|_| {
                Command::new(BIN)
                    .args(["run", &file(), "--results", results.to_str().unwrap(), "-q"])
                    .stdout(Stdio::piped())
                    .stderr(Stdio::piped())
                    .spawn()
                    .unwrap()
            })
            .collect();
        for c in children {
            let out = c.wait_with_output().unwrap();
            assert_code(&out, 0);
            assert!(
                !stderr(&out).contains("CORRUPT"),
                "round {round}: {}",
                stderr(&out)
            );
        }
        assert!(published(&results, PIPELINE) == expected, "round {round}");
        assert_every_entry_verifies(&results);
        let again = run_ok(&results);
        let st = stages(&run_json(&results, PIPELINE));
        assert!(
            st.values().all(|s| s["status"] == "cached"),
            "round {round}: {}",
            stderr(&again)
        );
    }
}

#[test]
fn a_second_run_reuses_what_a_running_first_one_has_finished() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    let first = Command::new(BIN)
        .args(["run", &file(), "--results", results.to_str().unwrap(), "-q"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // Wait until it has published its first entries, then start the second.
    let cache = cache_dir(&results);
    let t0 = Instant::now();
    loop {
        let done = std::fs::read_dir(&cache)
            .map(|rd| {
                rd.flatten()
                    .filter(|e| !e.file_name().to_string_lossy().starts_with('.'))
                    .count()
            })
            .unwrap_or(0);
        if done >= 1 {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "the first run published nothing"
        );
        std::thread::sleep(Duration::from_micros(200));
    }
    let second = run(&results, &[]);
    assert_code(&second, 0);
    let out = first.wait_with_output().unwrap();
    assert!(out.status.success());
    let err = stderr(&second);
    let cached = err
        .lines()
        .filter(|l| l.trim_start().starts_with("cached "))
        .count();
    assert!(cached >= 1, "the second run reused nothing:\n{err}");
    assert_every_entry_verifies(&results);
}

#[test]
fn published_copies_are_never_seen_half_written() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    // Two versions of the noisy chain, both cached: the pipeline file, and
    // a copy of it with another seed (a run with `--set` would publish to
    // an experiment's folder instead).
    run_ok(&results);
    let edited = dir.path().join("seed2.toml");
    let text = std::fs::read_to_string(file()).unwrap();
    assert_eq!(text.matches("\nseed = 1\n").count(), 1);
    std::fs::write(&edited, text.replace("\nseed = 1\n", "\nseed = 2\n")).unwrap();
    let run_seed2 = || {
        let r = results.to_string_lossy().into_owned();
        ltcal(
            dir.path(),
            &["run", edited.to_str().unwrap(), "--results", &r],
        )
    };
    assert_code(&run_seed2(), 0);
    let path = results
        .join(PIPELINE)
        .join("evaluate_sphere_noisy/points.parquet");
    let v2 = std::fs::read(&path).unwrap();
    run_ok(&results);
    let v1 = std::fs::read(&path).unwrap();
    assert_ne!(v1, v2);
    // A reader reads the published copy over and over while runs switch it
    // between the two versions.
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let reader = {
        let (stop, path, v1, v2) = (stop.clone(), path.clone(), v1.clone(), v2.clone());
        std::thread::spawn(move || {
            let mut reads = 0;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                let b = std::fs::read(&path).unwrap();
                assert!(
                    b == v1 || b == v2,
                    "read a copy that is neither version ({} bytes)",
                    b.len()
                );
                reads += 1;
            }
            reads
        })
    };
    for i in 0..12 {
        let out = if i % 2 == 0 {
            run_seed2()
        } else {
            run(&results, &[])
        };
        assert_code(&out, 0);
        // Switching between two results is no damage.
        assert!(
            !stderr(&out).contains("edited or damaged"),
            "{}",
            stderr(&out)
        );
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let reads = reader.join().unwrap();
    assert!(reads > 12, "only {reads} reads");
}
