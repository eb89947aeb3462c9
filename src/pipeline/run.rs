//! The runner: executes a resolved pipeline level by level, stages of a level
//! in parallel (rayon), reusing cached results, and publishes every stage's
//! tables and figures under `results/<pipeline>/<stage>/`, the run report
//! (`run.json`) and the page [`crate::report`] (`index.html`).
//!
//! A stage that fails — by error or by panic ([`super::panics`]) — is
//! reported as a failure of that stage with its message; by default the run
//! stops after the level in which it failed, with `keep_going` every stage
//! whose inputs exist runs.
//!
//! A cached entry that fails verification is recomputed, and the stage's
//! report says so (`cache_problem`), so that a damaged cache is visible
//! rather than silently repaired.

use super::cache::{self, Entry, FileRecord, Lookup, Manifest, Store, TableRecord};
use super::panics;
use super::plan::{Graph, key_fields, reason};
use super::resolve::Pipeline;
use crate::report;
use crate::stages::{Context, StageInputs};
use crate::table;
use anyhow::{Result, anyhow};
use polars::prelude::DataFrame;
use rayon::prelude::*;
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Instant, SystemTime};

/// How to run.
#[derive(Clone, Debug)]
pub struct RunOptions {
    /// The folder holding every pipeline's results (`results`).
    pub results_root: PathBuf,
    pub keep_going: bool,
    /// Print a line per stage on stderr.
    pub progress: bool,
}

/// What happened to one stage.
#[derive(Clone, Debug, Serialize)]
pub struct StageReport {
    pub stage: String,
    pub kind: String,
    /// `ran`, `cached`, `failed` or `skipped`.
    pub status: String,
    /// Why it ran, failed or was skipped; empty when cached.
    pub reason: String,
    /// What was wrong with the stage's cached entry when it failed
    /// verification (truncated, corrupted or edited) and was recomputed.
    pub cache_problem: Option<String>,
    pub key: Option<String>,
    pub seconds: f64,
    /// Table name → rows.
    pub tables: BTreeMap<String, usize>,
    pub files: Vec<String>,
}

/// What happened to the pipeline; written to `results/<pipeline>/run.json`.
#[derive(Clone, Debug, Serialize)]
pub struct RunReport {
    pub pipeline: String,
    pub results: PathBuf,
    pub started: String,
    pub finished: String,
    /// Leftovers of killed runs (incomplete entries, temporary files)
    /// removed before this run.
    pub cleaned: usize,
    pub stages: Vec<StageReport>,
}

impl RunReport {
    pub fn with_status(&self, status: &str) -> Vec<&str> {
        self.stages
            .iter()
            .filter(|s| s.status == status)
            .map(|s| s.stage.as_str())
            .collect()
    }
    pub fn failed(&self) -> Vec<&StageReport> {
        self.stages
            .iter()
            .filter(|s| s.status == "failed")
            .collect()
    }
}

/// A stage's outputs as the next stages see them.
struct Produced {
    /// Table → (frame, content hash).
    tables: BTreeMap<String, (Arc<DataFrame>, String)>,
}

pub fn timestamp(t: SystemTime) -> String {
    humantime::format_rfc3339_millis(t).to_string()
}

/// The folder of one pipeline's results.
pub fn pipeline_dir(root: &Path, p: &Pipeline) -> PathBuf {
    root.join(&p.name)
}

/// Runs the pipeline.
pub fn run(p: &Pipeline, opts: &RunOptions) -> Result<RunReport> {
    let started = SystemTime::now();
    let dir = pipeline_dir(&opts.results_root, p);
    let store = Store::new(&dir);
    let cleaned = store.clean_incomplete() + cache::clean_temp_files(&dir);
    let graph = Graph::new(p);
    let produced: Mutex<BTreeMap<String, Arc<Produced>>> = Mutex::new(BTreeMap::new());
    let mut reports: Vec<Option<StageReport>> = vec![None; p.stages.len()];
    let mut stop = false;
    for level in &graph.levels {
        let ready: Vec<usize> = level
            .iter()
            .copied()
            .filter(|&i| {
                let done = produced.lock().expect("no panics hold this lock");
                !stop
                    && p.stages[i]
                        .inputs
                        .values()
                        .all(|r| done.contains_key(&r.stage))
            })
            .collect();
        let results: Vec<(usize, StageReport, Option<Produced>)> = ready
            .par_iter()
            .map(|&i| {
                let inputs = {
                    let done = produced.lock().expect("no panics hold this lock");
                    p.stages[i]
                        .wired_tables()
                        .into_iter()
                        .map(|(slot, r)| {
                            let prod = done[&r.stage].clone();
                            (slot, r, prod)
                        })
                        .collect::<Vec<_>>()
                };
                let (report, out) = execute(p, i, inputs, &store, &dir);
                if opts.progress {
                    progress_line(&report);
                }
                (i, report, out)
            })
            .collect();
        for (i, report, out) in results {
            if report.status == "failed" && !opts.keep_going {
                stop = true;
            }
            if let Some(out) = out {
                produced
                    .lock()
                    .expect("no panics hold this lock")
                    .insert(p.stages[i].name.clone(), Arc::new(out));
            }
            reports[i] = Some(report);
        }
    }
    let stages = reports
        .into_iter()
        .enumerate()
        .map(|(i, r)| {
            r.unwrap_or_else(|| {
                let s = &p.stages[i];
                let failed_inputs: Vec<&str> = s
                    .inputs
                    .values()
                    .map(|r| r.stage.as_str())
                    .filter(|n| {
                        !produced
                            .lock()
                            .expect("no panics hold this lock")
                            .contains_key(*n)
                    })
                    .collect();
                StageReport {
                    stage: s.name.clone(),
                    kind: s.config.kind().to_string(),
                    status: "skipped".into(),
                    cache_problem: None,
                    reason: if failed_inputs.is_empty() {
                        "the run stopped at the first failure (use --keep-going)".into()
                    } else {
                        format!("its input {} did not complete", failed_inputs.join(", "))
                    },
                    key: None,
                    seconds: 0.0,
                    tables: BTreeMap::new(),
                    files: Vec::new(),
                }
            })
        })
        .collect();
    let report = RunReport {
        pipeline: p.name.clone(),
        results: dir.clone(),
        started: timestamp(started),
        finished: timestamp(SystemTime::now()),
        cleaned,
        stages,
    };
    cache::write_atomic(&dir.join("run.json"), &serde_json::to_vec_pretty(&report)?)?;
    let tables: report::Tables = produced
        .into_inner()
        .expect("no panics hold this lock")
        .into_iter()
        .map(|(stage, prod)| {
            let t = prod
                .tables
                .iter()
                .map(|(name, (df, _))| (name.clone(), df.clone()))
                .collect();
            (stage, t)
        })
        .collect();
    report::write(&dir, p, &report, &tables)?;
    Ok(report)
}

fn progress_line(r: &StageReport) {
    let detail = match r.status.as_str() {
        "cached" => String::new(),
        "ran" => format!("  {:.2} s  ({})", r.seconds, r.reason),
        _ => format!("  ({})", r.reason),
    };
    eprintln!("{:>8}  {}{detail}", r.status, r.stage);
}

type Wired = Vec<(String, super::resolve::InputRef, Arc<Produced>)>;

/// Runs or reuses one stage.
fn execute(
    p: &Pipeline,
    i: usize,
    inputs: Wired,
    store: &Store,
    dir: &Path,
) -> (StageReport, Option<Produced>) {
    let s = &p.stages[i];
    let mut report = StageReport {
        stage: s.name.clone(),
        kind: s.config.kind().to_string(),
        status: "failed".into(),
        reason: String::new(),
        cache_problem: None,
        key: None,
        seconds: 0.0,
        tables: BTreeMap::new(),
        files: Vec::new(),
    };
    let mut hashes = BTreeMap::new();
    let mut stage_inputs = StageInputs::default();
    for (slot, r, prod) in &inputs {
        let (df, h) = &prod.tables[&r.table];
        hashes.insert(slot.clone(), h.clone());
        stage_inputs.insert(slot, r.to_string(), df.clone());
    }
    let kf = key_fields(s, hashes);
    let key = kf.hash();
    report.key = Some(key.clone());
    let t0 = Instant::now();
    let why = match store.lookup(&key) {
        Lookup::Hit(entry) => match decode(&entry) {
            Ok(prod) => {
                report.status = "cached".into();
                fill(&mut report, &entry.manifest);
                if let Err(e) = publish(dir, &s.name, &entry) {
                    report.status = "failed".into();
                    report.reason = format!("{e:#}");
                    return (report, None);
                }
                return (report, Some(prod));
            }
            Err(e) => format!("its cached result could not be read: {e:#}"),
        },
        Lookup::Corrupt(why) => {
            let reason = format!("its cached result was corrupt and is recomputed: {why}");
            report.cache_problem = Some(why);
            reason
        }
        Lookup::Miss => reason(store, &s.name, &kf),
    };
    report.reason = why;
    let started = SystemTime::now();
    let ctx = Context {
        pipeline: &p.name,
        stage: &s.name,
    };
    let output = match panics::catch(|| s.config.run(&ctx, &stage_inputs)) {
        Ok(Ok(o)) => o,
        Ok(Err(e)) => {
            report.reason = format!("{e:#}");
            return (report, None);
        }
        Err(panic) => {
            report.reason = format!("the stage panicked: {panic}");
            return (report, None);
        }
    };
    report.seconds = t0.elapsed().as_secs_f64();
    let stored = (|| -> Result<Entry> {
        for name in s.config.outputs() {
            if !output.tables.iter().any(|(n, _)| n == name) {
                return Err(anyhow!(
                    "the stage did not produce its table `{name}` (a bug in ltcal)"
                ));
            }
        }
        let mut tables = BTreeMap::new();
        let mut records = Vec::new();
        for (name, df) in &output.tables {
            let bytes = table::to_parquet_bytes(df)?;
            records.push(TableRecord {
                name: name.clone(),
                rows: df.height(),
                hash: cache::hash_bytes(&bytes),
            });
            tables.insert(name.clone(), bytes);
        }
        let files: BTreeMap<String, Vec<u8>> = output.files.iter().cloned().collect();
        let manifest = Manifest {
            stage: s.name.clone(),
            key: key.clone(),
            key_fields: kf.clone(),
            started: timestamp(started),
            finished: timestamp(SystemTime::now()),
            seconds: report.seconds,
            tables: records,
            files: files
                .iter()
                .map(|(n, b)| FileRecord {
                    name: n.clone(),
                    bytes: b.len(),
                    hash: cache::hash_bytes(b),
                })
                .collect(),
        };
        let entry = Entry {
            manifest,
            tables,
            files,
        };
        store.put(&entry)?;
        store.set_last(&s.name, &kf)?;
        publish(dir, &s.name, &entry)?;
        Ok(entry)
    })();
    match stored {
        Ok(entry) => {
            report.status = "ran".into();
            fill(&mut report, &entry.manifest);
            let prod = Produced {
                tables: output
                    .tables
                    .into_iter()
                    .map(|(n, df)| {
                        let h = entry
                            .manifest
                            .tables
                            .iter()
                            .find(|t| t.name == n)
                            .map(|t| t.hash.clone());
                        (n, (Arc::new(df), h.unwrap_or_default()))
                    })
                    .collect(),
            };
            (report, Some(prod))
        }
        Err(e) => {
            report.reason = format!("{e:#}");
            (report, None)
        }
    }
}

fn fill(report: &mut StageReport, m: &Manifest) {
    report.tables = m.tables.iter().map(|t| (t.name.clone(), t.rows)).collect();
    report.files = m.files.iter().map(|f| f.name.clone()).collect();
}

fn decode(entry: &Entry) -> Result<Produced> {
    let mut tables = BTreeMap::new();
    for t in &entry.manifest.tables {
        let df = table::from_parquet_bytes(&entry.tables[&t.name])?;
        tables.insert(t.name.clone(), (Arc::new(df), t.hash.clone()));
    }
    Ok(Produced { tables })
}

/// Copies an entry's tables and files to `results/<pipeline>/<stage>/`,
/// atomically, skipping files that are already identical.
fn publish(dir: &Path, stage: &str, entry: &Entry) -> Result<()> {
    let out = dir.join(stage);
    let items = entry
        .tables
        .iter()
        .map(|(n, b)| (format!("{n}.parquet"), b))
        .chain(entry.files.iter().map(|(n, b)| (n.clone(), b)));
    for (name, bytes) in items {
        let path = out.join(name);
        if std::fs::read(&path).is_ok_and(|old| old == *bytes) {
            continue;
        }
        cache::write_atomic(&path, bytes)?;
    }
    Ok(())
}
