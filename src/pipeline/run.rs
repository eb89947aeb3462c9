//! The runner: executes a resolved pipeline level by level, stages of a level
//! in parallel (rayon), reusing cached results, and publishes every stage's
//! tables and figures under `results/<pipeline>/<stage>/`, the run report
//! (`run.json`) and the page [`super::report`] (`index.html`).
//!
//! A stage that fails — by error or by panic ([`super::panics`]) — is
//! reported as a failure of that stage with its message; by default the run
//! stops after the level in which it failed, with `keep_going` every stage
//! whose inputs exist runs.
//!
//! A cached entry that fails verification is recomputed, and the stage's
//! report says so (`cache_problem`), so that a damaged cache is visible
//! rather than silently repaired.

use super::cache::{self, Entry, FileRecord, Lookup, Manifest, PointRecords, Store, TableRecord};
use super::panics;
use super::plan::{Graph, key_fields, reason};
use super::report;
use super::resolve::{Pipeline, Stage, Sweep, SweepPoint};
use super::status::Status;
use super::sweep;
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
    /// [`Status::Ran`], [`Status::Cached`], [`Status::Failed`] or
    /// [`Status::Skipped`].
    pub status: Status,
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
    /// For a pipeline with a `[sweep]`.
    pub sweep: Option<SweepReport>,
}

impl RunReport {
    /// The stages with `status` (a [`Status`], or the word it is written as).
    pub fn with_status<S>(&self, status: S) -> Vec<&str>
    where
        Status: PartialEq<S>,
    {
        self.stages
            .iter()
            .filter(|s| s.status == status)
            .map(|s| s.stage.as_str())
            .collect()
    }
    pub fn failed(&self) -> Vec<&StageReport> {
        self.stages
            .iter()
            .filter(|s| s.status == Status::Failed)
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

/// What a sweep did: how many points ran at least one stage, how many
/// were wholly cached, and which failed.
#[derive(Clone, Debug, Default, Serialize)]
pub struct SweepReport {
    pub points: usize,
    pub ran: usize,
    pub cached: usize,
    pub failed: usize,
    /// The gathered tables, `stage.table` → rows.
    pub gathered: BTreeMap<String, usize>,
}

/// What [`execute_stages`] needs besides the stages.
struct Runner<'a> {
    pipeline: &'a str,
    store: &'a Store,
    dir: &'a Path,
    keep_going: bool,
    /// Copy tables and figures to `results/<pipeline>/<stage>/`.
    publish: bool,
    /// The sweep point whose stages this runs, and where the runs at sweep
    /// points are recorded for `explain`.
    point: Option<(usize, &'a Mutex<PointRecords>)>,
    /// Print a line per stage.
    progress: bool,
    /// Run a level's stages in parallel. Off inside sweep points, which
    /// are the parallel units: a point blocked on nested parallel work
    /// would steal other points onto its stack.
    parallel: bool,
}

/// Runs the pipeline (and, with a `[sweep]`, every point of it).
pub fn run(p: &Pipeline, opts: &RunOptions) -> Result<RunReport> {
    let started = SystemTime::now();
    let dir = pipeline_dir(&opts.results_root, p);
    let store = Store::new(&dir);
    let cleaned = store.clean_incomplete() + cache::clean_temp_files(&dir);
    let runner = Runner {
        pipeline: &p.name,
        store: &store,
        dir: &dir,
        keep_going: opts.keep_going,
        publish: true,
        point: None,
        progress: opts.progress,
        parallel: true,
    };
    let (stages, produced, sweep) = match &p.sweep {
        None => {
            let (reports, produced) = execute_stages(&runner, &p.stages, BTreeMap::new());
            (reports, produced, None)
        }
        Some(sw) => {
            let (point_reports, gathered, sweep) = run_points(&runner, sw)?;
            let after: Vec<Stage> = p
                .stages
                .iter()
                .filter(|s| sw.after.contains(&s.name))
                .cloned()
                .collect();
            let external = BTreeMap::from([(sweep::PSEUDO_STAGE.to_string(), Arc::new(gathered))]);
            let (mut reports, produced) = execute_stages(&runner, &after, external);
            let mut all = point_reports;
            all.append(&mut reports);
            (all, produced, Some(sweep))
        }
    };
    let report = RunReport {
        pipeline: p.name.clone(),
        results: dir.clone(),
        started: timestamp(started),
        finished: timestamp(SystemTime::now()),
        cleaned,
        stages,
        sweep,
    };
    crate::fs::write_atomic(&dir.join("run.json"), &serde_json::to_vec_pretty(&report)?)?;
    let tables: report::Tables = produced
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

/// A report per stage and what the stages produced, by stage name.
type Executed = (Vec<StageReport>, BTreeMap<String, Arc<Produced>>);

/// Runs stages level by level, a level's stages in parallel. `external`
/// holds tables of producers that are not among `stages` (a sweep's
/// gathered tables). Returns a report per stage and what they produced.
fn execute_stages(
    runner: &Runner,
    stages: &[Stage],
    external: BTreeMap<String, Arc<Produced>>,
) -> Executed {
    let graph = Graph::of(stages);
    let produced: Mutex<BTreeMap<String, Arc<Produced>>> = Mutex::new(external);
    let mut reports: Vec<Option<StageReport>> = vec![None; stages.len()];
    let mut stop = false;
    for level in &graph.levels {
        let ready: Vec<usize> = level
            .iter()
            .copied()
            .filter(|&i| {
                let done = produced.lock().expect("no panics hold this lock");
                !stop
                    && stages[i]
                        .inputs
                        .values()
                        .all(|r| done.contains_key(&r.stage))
            })
            .collect();
        let run_one = |&i: &usize| {
            let inputs = {
                let done = produced.lock().expect("no panics hold this lock");
                stages[i]
                    .wired_tables()
                    .into_iter()
                    .map(|(slot, r)| {
                        let prod = done[&r.stage].clone();
                        (slot, r, prod)
                    })
                    .collect::<Vec<_>>()
            };
            let (report, out) = execute(runner, &stages[i], inputs);
            if runner.progress {
                progress_line(&report);
            }
            (i, report, out)
        };
        let results: Vec<(usize, StageReport, Option<Produced>)> = if runner.parallel {
            ready.par_iter().map(run_one).collect()
        } else {
            ready.iter().map(run_one).collect()
        };
        for (i, report, out) in results {
            if report.status == Status::Failed && !runner.keep_going {
                stop = true;
            }
            if let Some(out) = out {
                produced
                    .lock()
                    .expect("no panics hold this lock")
                    .insert(stages[i].name.clone(), Arc::new(out));
            }
            reports[i] = Some(report);
        }
    }
    let produced = produced.into_inner().expect("no panics hold this lock");
    let reports = reports
        .into_iter()
        .enumerate()
        .map(|(i, r)| {
            r.unwrap_or_else(|| {
                let s = &stages[i];
                let failed_inputs: Vec<&str> = s
                    .inputs
                    .values()
                    .map(|r| r.stage.as_str())
                    .filter(|n| !produced.contains_key(*n))
                    .collect();
                StageReport {
                    stage: s.name.clone(),
                    kind: s.config.kind().to_string(),
                    status: Status::Skipped,
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
    (reports, produced)
}

/// Runs every point of a sweep (points in parallel, each point's stages
/// cached like any), gathers the chosen tables with the swept values as
/// columns, and publishes them under `results/<pipeline>/sweep/`. Returns
/// one report per per-point stage (`ran` if any point ran it), the
/// gathered tables as the producer `sweep`, and the sweep's counts.
fn run_points(runner: &Runner, sw: &Sweep) -> Result<(Vec<StageReport>, Produced, SweepReport)> {
    let ran_at = Mutex::new(PointRecords::new());
    let point_runner = Runner {
        publish: false,
        progress: false,
        parallel: false,
        ..*runner
    };
    let bar = if runner.progress {
        let b = indicatif::ProgressBar::new(sw.points.len() as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template(
                "{prefix} [{bar:40}] {pos}/{len} points  {elapsed_precise} elapsed, ETA {eta_precise}",
            )
            .expect("a valid template")
            .progress_chars("=> "),
        );
        b.set_prefix("sweep");
        b
    } else {
        indicatif::ProgressBar::hidden()
    };
    let outcomes: Vec<Executed> = sw
        .points
        .par_iter()
        .map(|pt| {
            let runner = Runner {
                point: Some((pt.index, &ran_at)),
                ..point_runner
            };
            let (reports, produced) = execute_stages(&runner, &pt.stages, BTreeMap::new());
            bar.inc(1);
            (reports, gathered_only(sw, produced))
        })
        .collect();
    bar.finish_and_clear();
    let ran_at = ran_at.into_inner().unwrap_or_else(|e| e.into_inner());
    runner.store.record_points(sw.points.len(), ran_at)?;
    let mut counts = SweepReport {
        points: sw.points.len(),
        ..SweepReport::default()
    };
    let mut reports: Vec<StageReport> = Vec::new();
    for (pt, (rs, _)) in sw.points.iter().zip(&outcomes) {
        let failed: Vec<&StageReport> = rs.iter().filter(|r| r.status == Status::Failed).collect();
        if !failed.is_empty() {
            counts.failed += 1;
            for f in failed {
                let mut f = f.clone();
                f.reason = format!(
                    "sweep point {} ({}): {}",
                    pt.index,
                    point_label(sw, pt),
                    f.reason
                );
                reports.push(f);
            }
        } else if rs.iter().any(|r| r.status == Status::Ran) {
            counts.ran += 1;
        } else {
            counts.cached += 1;
        }
    }
    // One line per per-point stage: ran if any point ran it.
    if let Some((first, _)) = outcomes.first() {
        for (k, r0) in first.iter().enumerate() {
            let ran = outcomes
                .iter()
                .filter(|(rs, _)| rs.get(k).is_some_and(|r| r.status == Status::Ran))
                .count();
            let mut r = r0.clone();
            r.status = if ran > 0 { Status::Ran } else { Status::Cached };
            r.reason = format!("{ran} of {} sweep points ran it", sw.points.len());
            r.key = None;
            r.seconds = outcomes
                .iter()
                .filter_map(|(rs, _)| rs.get(k).map(|r| r.seconds))
                .sum();
            if reports.iter().all(|x| x.stage != r.stage) {
                reports.push(r);
            }
        }
    }
    if counts.failed > 0 && !runner.keep_going {
        // The gathered tables would be incomplete: stop here.
        return Ok((
            reports,
            Produced {
                tables: BTreeMap::new(),
            },
            counts,
        ));
    }
    let mut tables = BTreeMap::new();
    for g in &sw.gather {
        let frames = sw
            .points
            .iter()
            .zip(&outcomes)
            .filter_map(|(pt, (_, produced))| {
                let (df, _) = produced.get(&g.stage)?.tables.get(&g.table)?;
                Some((pt, df.as_ref()))
            });
        let (df, bytes) = sweep::gather(sw, frames)?;
        let name = g.to_string();
        counts.gathered.insert(name.clone(), df.height());
        if runner.publish {
            let path = runner
                .dir
                .join(sweep::PSEUDO_STAGE)
                .join(format!("{name}.parquet"));
            if !std::fs::read(&path).is_ok_and(|old| old == bytes) {
                crate::fs::write_atomic(&path, &bytes)?;
            }
        }
        tables.insert(name, (Arc::new(df), cache::hash_bytes(&bytes)));
    }
    Ok((reports, Produced { tables }, counts))
}

/// What of a point's tables the gather reads, and nothing else: every
/// point's outputs are held until the gather, and the rest of them (the
/// campaign, the residuals, …) cost 0.7 MB a point.
fn gathered_only(
    sw: &Sweep,
    produced: BTreeMap<String, Arc<Produced>>,
) -> BTreeMap<String, Arc<Produced>> {
    produced
        .into_iter()
        .filter_map(|(stage, p)| {
            let tables: BTreeMap<_, _> = p
                .tables
                .iter()
                .filter(|(t, _)| sw.gather.iter().any(|g| g.stage == stage && &g.table == *t))
                .map(|(t, v)| (t.clone(), v.clone()))
                .collect();
            (!tables.is_empty()).then(|| (stage, Arc::new(Produced { tables })))
        })
        .collect()
}

/// `name=value, …` of a point, for messages.
fn point_label(sw: &Sweep, pt: &SweepPoint) -> String {
    sw.axes
        .iter()
        .zip(&pt.values)
        .map(|(a, v)| format!("{}={v}", a.name))
        .collect::<Vec<_>>()
        .join(", ")
}

fn progress_line(r: &StageReport) {
    let detail = match r.status {
        Status::Cached => String::new(),
        Status::Ran => format!("  {:.2} s  ({})", r.seconds, r.reason),
        _ => format!("  ({})", r.reason),
    };
    eprintln!("{:>8}  {}{detail}", r.status, r.stage);
}

type Wired = Vec<(String, super::resolve::InputRef, Arc<Produced>)>;

/// Runs or reuses one stage.
fn execute(runner: &Runner, s: &Stage, inputs: Wired) -> (StageReport, Option<Produced>) {
    let store = runner.store;
    let mut report = StageReport {
        stage: s.name.clone(),
        kind: s.config.kind().to_string(),
        status: Status::Failed,
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
                report.status = Status::Cached;
                fill(&mut report, &entry.manifest);
                match publish(runner, &s.name, &entry) {
                    // The cached result is the stage's result: a published
                    // copy that differs was edited or damaged since.
                    Ok(replaced) => {
                        for path in replaced {
                            eprintln!(
                                "note: restored {}: it differed from the cached result of `{}` \
                                 (edited or damaged)",
                                path.display(),
                                s.name
                            );
                        }
                    }
                    Err(e) => {
                        report.status = Status::Failed;
                        report.reason = format!("{e:#}");
                        return (report, None);
                    }
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
        Lookup::Miss => reason(store, &s.name, runner.point.map(|(i, _)| i), &kf),
    };
    report.reason = why;
    let started = SystemTime::now();
    let ctx = Context {
        pipeline: runner.pipeline,
        stage: &s.name,
        file_hash: s.file_hash.as_deref(),
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
        // What `explain` compares with: the last run of a stage of this
        // name (at this sweep point).
        match runner.point {
            None => store.set_last(&s.name, &kf)?,
            Some((i, ran_at)) => {
                let mut ran_at = ran_at.lock().unwrap_or_else(|e| e.into_inner());
                ran_at
                    .entry(i)
                    .or_default()
                    .insert(s.name.clone(), kf.clone());
            }
        }
        publish(runner, &s.name, &entry)?;
        Ok(entry)
    })();
    match stored {
        Ok(entry) => {
            report.status = Status::Ran;
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
/// Copies an entry's tables and files to `results/<pipeline>/<stage>/`,
/// writing only what differs; returns the existing files it replaced.
fn publish(runner: &Runner, stage: &str, entry: &Entry) -> Result<Vec<PathBuf>> {
    let mut replaced = Vec::new();
    if !runner.publish {
        return Ok(replaced);
    }
    let out = runner.dir.join(stage);
    let items = entry
        .tables
        .iter()
        .map(|(n, b)| (format!("{n}.parquet"), b))
        .chain(entry.files.iter().map(|(n, b)| (n.clone(), b)));
    for (name, bytes) in items {
        let path = out.join(name);
        match std::fs::read(&path) {
            Ok(old) if old == *bytes => continue,
            Ok(_) => {
                crate::fs::write_atomic(&path, bytes)?;
                replaced.push(path);
            }
            Err(_) => crate::fs::write_atomic(&path, bytes)?,
        }
    }
    Ok(replaced)
}
