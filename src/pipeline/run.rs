//! The runner: executes a resolved pipeline level by level, stages of a level
//! in parallel (rayon), reusing cached results, and publishes every stage's
//! tables and figures under `results/<pipeline>/<stage>/` — or, for an
//! [`super::experiment`] (a run with `--set`), under
//! `results/<pipeline>/runs/<name>/`, the cache being shared. It returns
//! what it did ([`RunReport`]) and the tables it holds; the run's record
//! (`run.json`) and page (`index.html`) are published by a later layer,
//! [`super::publish`], which the page's renderer ([`super::report`]) sits
//! below: executing knows nothing of how a run is shown.
//!
//! A published file that differs from the stage's cached result is
//! replaced. It is reported as edited or damaged only when it is not what
//! the last run of these results published either (its record,
//! [`Store::last_record`], kept for every stage published, cached or not):
//! going back to an earlier result is no damage.
//!
//! A stage that fails — by error or by panic ([`super::panics`]) — is
//! reported as a failure of that stage with its message; by default the run
//! stops after the level in which it failed, with `keep_going` every stage
//! whose inputs exist runs. A sweep's failed points are data, not a stop:
//! every point runs and each failure is reported with its point; the
//! stages after the sweep run on the gathered tables of the points that
//! succeeded only with `keep_going` (otherwise they are skipped, saying how
//! many points failed), and never on a table no point produced.
//!
//! A cached entry that fails verification is recomputed, and the stage's
//! report says so (`cache_problem`), so that a damaged cache is visible
//! rather than silently repaired.

use super::cache::{self, Entry, KeyFields, Lookup, Manifest, Miss, Store};
use super::control::Control;
use super::experiment::{self, Experiment};
use super::panics;
use super::plan::{Graph, key_fields, reason};
use super::resolve::{Pipeline, Stage, Sweep};
use super::select::Selection;
use super::status::Status;
use super::sweep;
use crate::stages::{Context, StageInputs};
use crate::table;
use anyhow::{Result, anyhow};
use polars::prelude::DataFrame;
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Instant, SystemTime};

/// How to run.
#[derive(Clone, Debug)]
pub struct RunOptions {
    /// The folder holding every pipeline's results (`results`).
    pub results_root: PathBuf,
    pub keep_going: bool,
    /// Print a line per stage on stderr.
    pub progress: bool,
    /// Sweep points another executor did not finish, and why: reported as
    /// failed with that reason, never computed here.
    /// Point → (the stage it failed at, why).
    pub not_computed: Option<Arc<BTreeMap<usize, (String, String)>>>,
    /// Publish to this experiment's folder, not the pipeline's results.
    pub experiment: Option<Experiment>,
    /// The caller's view of the run under way, and its stop.
    pub control: Arc<Control>,
}

pub use super::run_report::{RunReport, StageReport, SweepReport, Tables};

/// A stage's outputs as the next stages see them.
struct Produced {
    tables: BTreeMap<String, Output>,
}

/// One table a stage produced: in memory, or — a cached stage of a sweep
/// point — in the cache, read and verified only if a later stage or the
/// gather reads it. A cached point whose tables nothing reads costs its
/// manifests, not its tables.
struct Output {
    frame: OnceLock<Arc<DataFrame>>,
    /// The entry holding the table, when it is read on demand.
    key: Option<String>,
    /// The content hash of its Parquet bytes.
    hash: String,
}

impl Output {
    fn loaded(df: Arc<DataFrame>, hash: String) -> Output {
        Output {
            frame: OnceLock::from(df),
            key: None,
            hash,
        }
    }

    fn frame(&self, store: &Store, name: &str) -> Result<Arc<DataFrame>> {
        if let Some(df) = self.frame.get() {
            return Ok(df.clone());
        }
        let key = self
            .key
            .as_deref()
            .expect("a table not in memory is in the cache");
        let bytes = store.table(key, name, &self.hash)?;
        let df = Arc::new(table::from_parquet_bytes(&bytes)?);
        Ok(self.frame.get_or_init(|| df).clone())
    }
}

pub fn timestamp(t: SystemTime) -> String {
    humantime::format_rfc3339_millis(t).to_string()
}

/// The folder of one pipeline's results (and cache).
pub fn pipeline_dir(root: &Path, p: &Pipeline) -> PathBuf {
    root.join(&p.name)
}

/// The folder a run publishes to: the pipeline's results, or the
/// experiment's folder below them.
pub fn results_dir(root: &Path, p: &Pipeline, e: Option<&Experiment>) -> PathBuf {
    let dir = pipeline_dir(root, p);
    match e {
        Some(e) => experiment::folder(&dir, &e.name),
        None => dir,
    }
}

/// The cache of the pipeline, its "last run" records those of the results
/// `e` names.
pub fn store(root: &Path, p: &Pipeline, e: Option<&Experiment>) -> Store {
    let store = Store::new(&pipeline_dir(root, p));
    match e {
        Some(e) => store.for_experiment(&e.name),
        None => store,
    }
}

/// What [`execute_stages`] needs besides the stages.
struct Runner<'a> {
    pipeline: &'a str,
    store: &'a Store,
    dir: &'a Path,
    keep_going: bool,
    /// Copy tables and figures to `results/<pipeline>/<stage>/`.
    publish: bool,
    /// The sweep point whose stages this runs: its entries go into packs.
    point: Option<usize>,
    /// Take a cached stage of a sweep point on its manifest, reading its
    /// tables only when needed; off for the second try of a point whose
    /// cached tables could not be read.
    lazy: bool,
    /// Print a line per stage.
    progress: bool,
    /// Run a level's stages in parallel. Off inside sweep points, which
    /// are the parallel units: a point blocked on nested parallel work
    /// would steal other points onto its stack.
    parallel: bool,
    /// [`RunOptions::not_computed`].
    not_computed: Option<&'a BTreeMap<usize, (String, String)>>,
    /// The stages it may compute, and those it computes even if cached.
    selection: &'a Selection,
    /// Asked before a stage or point starts ([`RunOptions::control`]).
    control: &'a Control,
}

/// What executing a pipeline came to: the run's report and the tables the
/// run holds in memory, for a later layer to publish ([`super::publish`]).
pub struct Executed {
    pub report: RunReport,
    pub tables: Tables,
    /// The cache's record of what it found good (`.ltcal/verified.json`,
    /// [`Store::heal_recorded`]), for the publisher to write beside the
    /// run's record.
    pub verified: Option<(PathBuf, Vec<u8>)>,
}

/// Executes the pipeline (and, with a `[sweep]`, every point of it),
/// computing only what `selection` allows (a stage it does not is served if
/// cached, else skipped) and its forced stages even if cached. Every
/// stage's tables and figures are published as they are computed or served;
/// the run's own record and page are not ([`super::publish::run`]).
pub fn execute_pipeline(
    p: &Pipeline,
    opts: &RunOptions,
    selection: &Selection,
) -> Result<Executed> {
    let started = SystemTime::now();
    let mut exp = opts.experiment.clone();
    let store = store(&opts.results_root, p, exp.as_ref());
    let dir = results_dir(&opts.results_root, p, exp.as_ref());
    let mut cleaned = store.clean_incomplete();
    // What killed runs left in the published folders: the pipeline's, and
    // every experiment's (a killed experiment may never be run again).
    let pdir = pipeline_dir(&opts.results_root, p);
    cleaned += cache::clean_temp_files(&pdir);
    for name in experiment::names(&pdir) {
        cleaned += cache::clean_temp_files(&experiment::folder(&pdir, &name));
    }
    if let Some(e) = &mut exp {
        let (recorded, before) = experiment::record(&dir, e)?;
        if let Some(before) = before {
            eprintln!(
                "note: experiment `{}` had other overrides ({}); its results are replaced",
                e.name,
                experiment::set_args(&before)
            );
        }
        *e = recorded;
    }
    let runner = Runner {
        pipeline: &p.name,
        store: &store,
        dir: &dir,
        keep_going: opts.keep_going,
        publish: true,
        point: None,
        lazy: false,
        progress: opts.progress,
        parallel: true,
        not_computed: opts.not_computed.as_deref(),
        selection,
        control: &opts.control,
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
            let mut all = point_reports;
            if sweep.failed > 0 && !runner.keep_going {
                // The gathered tables would lack the failed points: the
                // stages after the sweep do not run on them, and the run
                // ends with the failed points named.
                let why = format!(
                    "{} of {} sweep points failed (--keep-going runs it on the others)",
                    sweep.failed, sweep.points
                );
                all.extend(after.iter().map(|s| skipped(s, why.clone())));
                (all, BTreeMap::new(), Some(sweep))
            } else {
                let external =
                    BTreeMap::from([(sweep::PSEUDO_STAGE.to_string(), Arc::new(gathered))]);
                let (mut reports, produced) = execute_stages(&runner, &after, external);
                all.append(&mut reports);
                (all, produced, Some(sweep))
            }
        }
    };
    opts.control.check()?;
    let finished = timestamp(SystemTime::now());
    // Read before healing takes the unreadable packs out.
    let unreadable_packs = store
        .unreadable_packs()
        .into_iter()
        .map(|(path, why)| format!("{}: {why}", path.display()))
        .collect();
    let (healed, verified) = store.heal_recorded(false);
    let report = RunReport {
        pipeline: p.name.clone(),
        results: dir.clone(),
        experiment: exp,
        started: timestamp(started),
        finished,
        cleaned,
        stages,
        sweep,
        unreadable_packs,
        healed,
    };
    let tables: Tables = produced
        .into_iter()
        .map(|(stage, prod)| {
            let t = prod
                .tables
                .iter()
                .filter_map(|(name, out)| Some((name.clone(), out.frame.get()?.clone())))
                .collect();
            (stage, t)
        })
        .collect();
    Ok(Executed {
        report,
        tables,
        verified,
    })
}

/// A report per stage and what the stages produced, by stage name.
type StagesDone = (Vec<StageReport>, BTreeMap<String, Arc<Produced>>);

/// Runs stages level by level, a level's stages in parallel. `external`
/// holds tables of producers that are not among `stages` (a sweep's
/// gathered tables). Returns a report per stage and what they produced.
fn execute_stages(
    runner: &Runner,
    stages: &[Stage],
    external: BTreeMap<String, Arc<Produced>>,
) -> StagesDone {
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
                // A producer without the table (a gathered table no sweep
                // point contributed to) leaves its readers skipped.
                !stop
                    && stages[i].wired_tables().iter().all(|(_, r)| {
                        done.get(&r.stage)
                            .is_some_and(|p| p.tables.contains_key(&r.table))
                    })
            })
            .collect();
        // Progress lines come in the plan's order (`ltcal plan`'s), whichever
        // thread finishes first: a finished stage's line waits for those
        // before it in its level, so that two runs print alike.
        let lines = Mutex::new((0, vec![None; ready.len()]));
        let run_one = |(pos, &i): (usize, &usize)| {
            // A stop keeps the pipeline's next stages from starting; a sweep
            // point's stages all run once the point has started.
            // (Its line is still printed in order: those after it wait.)
            let top = runner.point.is_none();
            let (report, out) = if top && runner.control.refuses() {
                let why = "the run was interrupted".to_string();
                (skipped(&stages[i], why), None)
            } else {
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
                let done = execute(runner, &stages[i], inputs);
                if top {
                    runner.control.stage_done();
                }
                done
            };
            if runner.progress {
                let mut lines = lines.lock().expect("no panics hold this lock");
                let (next, waiting) = &mut *lines;
                waiting[pos] = Some(progress_line(&report));
                while let Some(line) = waiting.get_mut(*next).and_then(Option::take) {
                    anstream::eprintln!("{line}");
                    *next += 1;
                }
            }
            (i, report, out)
        };
        let results: Vec<(usize, StageReport, Option<Produced>)> = if runner.parallel {
            ready.par_iter().enumerate().map(run_one).collect()
        } else {
            ready.iter().enumerate().map(run_one).collect()
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
                let mut failed_inputs: Vec<String> = s
                    .wired_tables()
                    .into_iter()
                    .filter(|(_, r)| {
                        produced
                            .get(&r.stage)
                            .is_none_or(|p| !p.tables.contains_key(&r.table))
                    })
                    .map(|(_, r)| {
                        if r.stage == sweep::PSEUDO_STAGE {
                            format!("{r} (no sweep point produced it)")
                        } else {
                            r.stage
                        }
                    })
                    .collect();
                // A group slot's tables all come from one stage.
                failed_inputs.dedup();
                skipped(
                    s,
                    if failed_inputs.is_empty() {
                        "the run stopped at the first failure (use --keep-going)".into()
                    } else {
                        format!("its input {} did not complete", failed_inputs.join(", "))
                    },
                )
            })
        })
        .collect();
    (reports, produced)
}

/// The report of a stage that did not run, and why.
fn skipped(s: &Stage, reason: String) -> StageReport {
    StageReport {
        stage: s.name.clone(),
        kind: s.config.kind().to_string(),
        status: Status::Skipped,
        cache_problem: None,
        reason,
        key: None,
        seconds: 0.0,
        tables: BTreeMap::new(),
        files: Vec::new(),
    }
}

/// A local run writes the new entries of its points as a pack every
/// `PACK_POINTS` points or `PACK_SECONDS` of work, whichever comes first:
/// many points to a file for cheap points, and little lost to a kill for
/// slow ones (a resumed sweep redoes at most that).
const PACK_POINTS: usize = 256;
const PACK_SECONDS: std::time::Duration = std::time::Duration::from_secs(1);

/// Runs every point of a sweep (points in parallel, each point's stages
/// cached like any), gathers the chosen tables with the swept values as
/// columns, and publishes them under `results/<pipeline>/sweep/`. Returns
/// one report per per-point stage (`ran` if any point ran it), the
/// gathered tables as the producer `sweep`, and the sweep's counts.
fn run_points(runner: &Runner, sw: &Sweep) -> Result<(Vec<StageReport>, Produced, SweepReport)> {
    let bar = progress_bar(runner.progress, sw.len(), "sweep".into());
    let done = run_point_set(runner, sw, &bar)?;
    bar.finish_and_clear();
    let PointsDone {
        reports,
        mut counts,
        gathered,
    } = done;
    if counts.failed > 0 && !runner.keep_going {
        // The gathered tables would be incomplete: stop here.
        let empty = Produced {
            tables: BTreeMap::new(),
        };
        return Ok((reports, empty, counts));
    }
    let mut tables = BTreeMap::new();
    for (g, gatherer) in sw.gather.iter().zip(gathered) {
        if gatherer.is_empty() {
            // Every point failed (kept going): no table, and its readers
            // are skipped rather than run on nothing.
            continue;
        }
        let (df, bytes) = gatherer.finish()?;
        let name = g.to_string();
        counts.gathered.insert(name.clone(), df.height());
        if runner.publish {
            let path = runner
                .dir
                .join(sweep::PSEUDO_STAGE)
                .join(format!("{name}.parquet"));
            if !crate::fs::read_regular_file(&path, cache::MAX_TABLE_BYTES)
                .is_ok_and(|old| old == bytes)
            {
                crate::fs::write_atomic(&path, &bytes)?;
            }
        }
        tables.insert(
            name,
            Output::loaded(Arc::new(df), cache::hash_bytes(&bytes)),
        );
    }
    Ok((reports, Produced { tables }, counts))
}

/// The sweep's progress bar over `points` (hidden unless `show`), its
/// counts in the message, named `prefix`.
pub(super) fn progress_bar(show: bool, points: usize, prefix: String) -> indicatif::ProgressBar {
    if !show {
        return indicatif::ProgressBar::hidden();
    }
    let b = indicatif::ProgressBar::new(points as u64);
    b.set_style(
        indicatif::ProgressStyle::with_template(
            "{prefix} [{bar:40}] {pos}/{len} points  {msg} {elapsed_precise} elapsed, ETA {eta_precise}",
        )
        .expect("a valid template")
        .progress_chars("=> "),
    );
    b.set_prefix(prefix);
    b
}

/// What a set of sweep points came to: a report per per-point stage
/// (and one per failure), the counts, and the gathered tables so far.
struct PointsDone<'a> {
    reports: Vec<StageReport>,
    counts: SweepReport,
    gathered: Vec<sweep::Gatherer<'a>>,
}

/// One point's stages' reports and the tables the gather reads.
struct PointOutcome {
    reports: Vec<StageReport>,
    gathered: Vec<Option<Arc<DataFrame>>>,
}

/// Runs every sweep point, a few per thread at a time, in parallel; their
/// new entries are written as packs ([`PACK_POINTS`], [`PACK_SECONDS`]),
/// their gathered tables folded in and the rest of their outcomes dropped
/// — what the coordinator holds does not grow with the points but by their
/// gathered rows.
fn run_point_set<'a>(
    runner: &Runner,
    sw: &'a Sweep,
    bar: &indicatif::ProgressBar,
) -> Result<PointsDone<'a>> {
    let indices: Vec<usize> = (0..sw.len()).collect();
    let point_runner = Runner {
        publish: false,
        progress: false,
        parallel: false,
        ..*runner
    };
    let mut gathered = sw.gatherers();
    let mut counts = SweepReport {
        points: indices.len(),
        ..SweepReport::default()
    };
    // Per per-point stage: its first report, how many points ran it, the
    // seconds, how many points found its cached entry damaged (and the
    // first such problem).
    let mut per_stage: Vec<(StageReport, usize, f64, usize)> = Vec::new();
    let mut failures: Vec<StageReport> = Vec::new();
    let batch = 4 * rayon::current_num_threads();
    let (mut unpacked, mut flushed) = (0, Instant::now());
    let parts: Vec<&[usize]> = indices.chunks(batch).collect();
    for (n, part) in parts.iter().enumerate() {
        let outcomes: Vec<Option<PointOutcome>> = part
            .par_iter()
            .map(|&i| {
                if runner.control.refuses() {
                    return None;
                }
                let out = run_point(&point_runner, sw, i);
                bar.inc(1);
                runner.control.point_done();
                Some(out)
            })
            .collect();
        unpacked += part.len();
        // Stopped: the points finished are written now, not lost.
        let stopped = runner.control.stopping();
        if stopped
            || n + 1 == parts.len()
            || unpacked >= PACK_POINTS
            || flushed.elapsed() >= PACK_SECONDS
        {
            runner.store.flush("local")?;
            (unpacked, flushed) = (0, Instant::now());
        }
        for (&i, out) in part.iter().zip(outcomes) {
            let Some(out) = out else { continue };
            let failed: Vec<&StageReport> = out
                .reports
                .iter()
                .filter(|r| r.status == Status::Failed)
                .collect();
            if !failed.is_empty() {
                counts.failed += 1;
                for f in failed {
                    let mut f = f.clone();
                    f.reason = format!(
                        "sweep point {i} ({}): {}",
                        point_label(sw, &sw.values[i]),
                        f.reason
                    );
                    failures.push(f);
                }
            } else if out.reports.iter().any(|r| r.status == Status::Ran) {
                counts.ran += 1;
            } else {
                counts.cached += 1;
            }
            for r in &out.reports {
                let damaged = usize::from(r.cache_problem.is_some());
                match per_stage.iter_mut().find(|(x, ..)| x.stage == r.stage) {
                    Some((first, ran, secs, n)) => {
                        *ran += usize::from(r.status == Status::Ran);
                        *secs += r.seconds;
                        *n += damaged;
                        if first.cache_problem.is_none() {
                            first.cache_problem.clone_from(&r.cache_problem);
                        }
                    }
                    None => per_stage.push((
                        r.clone(),
                        usize::from(r.status == Status::Ran),
                        r.seconds,
                        damaged,
                    )),
                }
            }
            if failed_none(&out.reports) {
                for (g, df) in gathered.iter_mut().zip(&out.gathered) {
                    if let Some(df) = df {
                        g.push(i, df)?;
                    }
                }
            }
        }
        bar.set_message(format!(
            "({} ran, {} cached, {} failed)",
            counts.ran, counts.cached, counts.failed
        ));
    }
    // Points kept from starting (after a stop, every later part's points
    // are): nothing is gathered from a part of the sweep.
    runner.control.check()?;
    let mut reports = failures;
    // One line per per-point stage: ran if any point ran it.
    for (mut r, ran, seconds, damaged) in per_stage {
        if reports.iter().any(|x| x.stage == r.stage) {
            continue;
        }
        r.status = if ran > 0 { Status::Ran } else { Status::Cached };
        r.reason = format!("{ran} of {} sweep points ran it", indices.len());
        r.key = None;
        // A damaged entry is reported, not silently repaired.
        r.cache_problem = r
            .cache_problem
            .map(|first| format!("at {damaged} sweep points, recomputed; the first: {first}"));
        r.seconds = seconds;
        reports.push(r);
    }
    Ok(PointsDone {
        reports,
        counts,
        gathered,
    })
}

fn failed_none(reports: &[StageReport]) -> bool {
    reports.iter().all(|r| r.status != Status::Failed)
}

/// Runs one sweep point. Its cached stages are taken on their manifests
/// first; if a cached table it then needs cannot be read (damaged since),
/// the point runs again reading every cached entry whole, which recomputes
/// the damaged ones.
fn run_point(runner: &Runner, sw: &Sweep, index: usize) -> PointOutcome {
    let pt = sw.point(index);
    if let Some((stage, why)) = runner.not_computed.and_then(|m| m.get(&index)) {
        let at = pt
            .stages
            .iter()
            .find(|s| &s.name == stage)
            .unwrap_or(&pt.stages[0]);
        let report = StageReport {
            stage: at.name.clone(),
            kind: at.config.kind().to_string(),
            status: Status::Failed,
            reason: why.clone(),
            cache_problem: None,
            key: None,
            seconds: 0.0,
            tables: BTreeMap::new(),
            files: Vec::new(),
        };
        return PointOutcome {
            reports: vec![report],
            gathered: Vec::new(),
        };
    }
    for lazy in [true, false] {
        let r = Runner {
            point: Some(index),
            lazy,
            ..*runner
        };
        let (reports, produced) = execute_stages(&r, &pt.stages, BTreeMap::new());
        // Damaged since it was taken on its manifest: the second try reads
        // every cached entry whole, which reports the damaged one
        // (`cache_problem`) and recomputes it.
        let mut damaged = reports
            .iter()
            .any(|r| r.status == Status::Failed && r.cache_problem.is_some());
        let mut gathered = Vec::new();
        for g in &sw.gather {
            let out = produced.get(&g.stage).and_then(|p| p.tables.get(&g.table));
            match out.map(|o| o.frame(runner.store, &g.table)) {
                None => gathered.push(None),
                Some(Ok(df)) => gathered.push(Some(df)),
                Some(Err(_)) => damaged = true,
            }
        }
        if !(lazy && damaged) {
            return PointOutcome { reports, gathered };
        }
    }
    unreachable!("the second try returns")
}

/// How much of a task's work a pack holds at most: a task killed (node
/// failure, time limit) loses no more than this, and a task of cheap points
/// writes one pack.
const TASK_FLUSH: std::time::Duration = std::time::Duration::from_secs(30);

/// What a task of a cluster did: its points, and those that failed.
#[derive(Clone, Debug, Default)]
pub struct TaskReport {
    pub ran: usize,
    pub cached: usize,
    /// (point, stage, reason) of every failure.
    pub failed: Vec<(usize, String, String)>,
    pub packs: Vec<PathBuf>,
}

/// Runs the sweep points `indices` of `p` as one task of a cluster: the
/// points `chunk` at a time (one per CPU of the task), their entries — and
/// their failures, with the reasons — written as packs named `<prefix>-…`
/// (one, or one per [`TASK_FLUSH`] of work), nothing published, nothing
/// gathered. The coordinator reads the packs.
pub fn run_task(
    p: &Pipeline,
    opts: &RunOptions,
    indices: &[usize],
    chunk: usize,
    prefix: &str,
) -> Result<TaskReport> {
    let sw = p
        .sweep
        .as_ref()
        .ok_or_else(|| anyhow!("`{}` has no [sweep]: a task runs sweep points", p.name))?;
    if let Some(&bad) = indices.iter().find(|&&i| i >= sw.len()) {
        return Err(anyhow!(
            "point {bad} is not a point of the sweep (it has {})",
            sw.len()
        ));
    }
    // Nothing is published: the experiment, if any, is the coordinator's.
    let dir = pipeline_dir(&opts.results_root, p);
    let store = Store::new(&dir);
    // What killed tasks on this machine left (another machine's are left
    // to the tasks that run there).
    store.clean_incomplete();
    let runner = Runner {
        pipeline: &p.name,
        store: &store,
        dir: &dir,
        keep_going: true,
        publish: false,
        point: None,
        lazy: true,
        progress: false,
        parallel: false,
        not_computed: None,
        selection: &Selection::default(),
        control: &opts.control,
    };
    let mut report = TaskReport::default();
    let mut flushed = Instant::now();
    let parts: Vec<&[usize]> = indices.chunks(chunk.max(1)).collect();
    for (n, part) in parts.iter().enumerate() {
        let outcomes: Vec<(usize, PointOutcome)> = part
            .par_iter()
            .map(|&i| (i, run_point(&runner, sw, i)))
            .collect();
        for (i, out) in &outcomes {
            let mut ran = false;
            for r in &out.reports {
                match r.status {
                    Status::Failed => {
                        store.fail_packed(*i, &r.stage, &r.reason);
                        report.failed.push((*i, r.stage.clone(), r.reason.clone()));
                    }
                    Status::Ran => ran = true,
                    _ => {}
                }
            }
            if failed_none(&out.reports) {
                if ran {
                    report.ran += 1;
                } else {
                    report.cached += 1;
                }
            }
        }
        // One pack for the task, unless its points are slow: then one every
        // `TASK_FLUSH` of work, so that a task killed late loses little.
        if n + 1 == parts.len() || flushed.elapsed() >= TASK_FLUSH {
            report.packs.extend(store.flush(prefix)?);
            flushed = Instant::now();
        }
    }
    Ok(report)
}

/// `name=value, …` of a point, for messages.
pub fn point_label(sw: &Sweep, values: &[serde_json::Value]) -> String {
    sw.axes
        .iter()
        .zip(values)
        .map(|(a, v)| format!("{}={v}", a.name))
        .collect::<Vec<_>>()
        .join(", ")
}

/// A stage's line, its status coloured (stripped by `anstream` unless
/// stderr is a terminal or `CLICOLOR_FORCE` is set, and with `NO_COLOR`).
fn progress_line(r: &StageReport) -> String {
    use anstyle::AnsiColor;
    let detail = match r.status {
        Status::Cached => String::new(),
        Status::Ran => format!("  {:.2} s  ({})", r.seconds, r.reason),
        _ => format!("  ({})", r.reason),
    };
    let colour = match r.status {
        Status::Ran => AnsiColor::Green,
        Status::Failed => AnsiColor::Red,
        Status::Skipped | Status::Run => AnsiColor::Yellow,
        Status::Cached => AnsiColor::Cyan,
    };
    let style = anstyle::Style::new().fg_color(Some(colour.into()));
    format!(
        "{style}{:>8}{style:#}  {}{detail}",
        r.status.to_string(),
        r.stage
    )
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
    let hashes = inputs
        .iter()
        .map(|(slot, r, prod)| (slot.clone(), prod.tables[&r.table].hash.clone()))
        .collect();
    let kf = key_fields(s, hashes);
    let key = kf.hash();
    report.key = Some(key.clone());
    let t0 = Instant::now();
    let forced = runner.selection.force.contains(&s.name);
    // A cached stage of a sweep point is taken on its manifest: its tables
    // are read only if something reads them.
    if runner.lazy && !forced {
        if let Some(Ok(m)) = store.manifest(&key) {
            report.status = Status::Cached;
            fill(&mut report, &m);
            return (report, Some(on_manifest(&key, &m)));
        }
    }
    // A forced stage is not looked up: its entry is neither read nor verified.
    let answer = if forced {
        Lookup::Miss(Miss::Forced)
    } else {
        store.lookup(&key)
    };
    let miss = match answer {
        Lookup::Hit(entry) => match decode(&entry) {
            Ok(prod) => return serve_cached(runner, s, &kf, &entry, prod, report),
            Err(e) => Miss::Unreadable(format!("{e:#}")),
        },
        Lookup::Miss(miss) => miss,
    };
    report.cache_problem = miss.damage().map(str::to_string);
    report.reason = match miss {
        // What changed since it last ran, or that its result went missing.
        Miss::Absent => reason(store, &s.name, runner.point, &kf),
        miss => miss.to_string(),
    };
    if !runner.selection.computes(&s.name) {
        report.status = Status::Skipped;
        report.reason = format!(
            "not a target and not needed by one (a full run runs it: {})",
            report.reason
        );
        return (report, None);
    }
    let stage_inputs = match read_inputs(store, &inputs) {
        Ok(i) => i,
        Err(why) => {
            // A cached input damaged since it was taken on its manifest:
            // the point runs again, reading entries whole.
            report.reason = why.clone();
            report.cache_problem = Some(why);
            return (report, None);
        }
    };
    let started = SystemTime::now();
    let output = match run_stage(runner, s, &stage_inputs) {
        Ok(o) => o,
        Err(why) => {
            report.reason = why;
            return (report, None);
        }
    };
    report.seconds = t0.elapsed().as_secs_f64();
    match store_output(runner, s, &kf, started, report.seconds, &output) {
        Ok(entry) => {
            report.status = Status::Ran;
            fill(&mut report, &entry.manifest);
            (report, Some(produced(output, &entry.manifest)))
        }
        Err(e) => {
            report.reason = format!("{e:#}");
            (report, None)
        }
    }
}

/// A cached stage taken on its manifest: each table's hash, read when
/// something reads it.
fn on_manifest(key: &str, m: &Manifest) -> Produced {
    let tables = m
        .tables
        .iter()
        .map(|t| {
            let out = Output {
                frame: OnceLock::new(),
                key: Some(key.to_string()),
                hash: t.hash.clone(),
            };
            (t.name.clone(), out)
        })
        .collect();
    Produced { tables }
}

/// A cached stage served: its entry published (restoring a published copy
/// edited or damaged since, with a note) and recorded as what the folder
/// holds.
fn serve_cached(
    runner: &Runner,
    s: &Stage,
    kf: &KeyFields,
    entry: &Entry,
    prod: Produced,
    mut report: StageReport,
) -> (StageReport, Option<Produced>) {
    let store = runner.store;
    report.status = Status::Cached;
    fill(&mut report, &entry.manifest);
    // What these results published last: a copy that differs from the
    // cached result but is that is an earlier result, switched back from;
    // one that is neither was edited or damaged since.
    let before = runner
        .publish
        .then(|| store.last_here(&s.name))
        .flatten()
        .and_then(|k| store.manifest(&k.hash()))
        .and_then(Result::ok);
    match publish(runner, &s.name, entry, runner.publish.then_some(kf)) {
        Ok(replaced) => {
            for (path, name, hash) in replaced {
                let switched_back = before
                    .as_ref()
                    .is_some_and(|m| published_hash(m, &name) == Some(&hash));
                if !switched_back {
                    eprintln!(
                        "note: restored {}: it differed from the cached result of `{}` \
                         (edited or damaged)",
                        path.display(),
                        s.name
                    );
                }
            }
            (report, Some(prod))
        }
        Err(e) => {
            report.status = Status::Failed;
            report.reason = format!("{e:#}");
            (report, None)
        }
    }
}

/// The stage's input tables, read from what produced them; or why one
/// could not be read.
fn read_inputs(store: &Store, inputs: &Wired) -> Result<StageInputs, String> {
    let mut stage_inputs = StageInputs::default();
    for (slot, r, prod) in inputs {
        match prod.tables[&r.table].frame(store, &r.table) {
            Ok(df) => stage_inputs.insert(slot, r.to_string(), df),
            Err(e) => {
                return Err(format!(
                    "its input `{r}` could not be read from the cache: {e:#}"
                ));
            }
        }
    }
    Ok(stage_inputs)
}

/// The stage's own computation, a panic caught as its failure.
fn run_stage(
    runner: &Runner,
    s: &Stage,
    inputs: &StageInputs,
) -> Result<crate::stages::StageOutput, String> {
    let ctx = Context {
        pipeline: runner.pipeline,
        stage: &s.name,
        file_hash: s.file_hash.as_deref(),
    };
    match panics::catch(|| s.config.run(&ctx, inputs)) {
        Ok(Ok(o)) => Ok(o),
        Ok(Err(e)) => Err(format!("{e:#}")),
        Err(panic) => Err(format!("the stage panicked: {panic}")),
    }
}

/// A stage's fresh output made an entry and stored: a sweep point's into
/// the next pack (which also records that it ran there), another stage's
/// as an entry of its own, published, and recorded as what the folder
/// holds (what `explain` compares with).
fn store_output(
    runner: &Runner,
    s: &Stage,
    kf: &KeyFields,
    started: SystemTime,
    seconds: f64,
    output: &crate::stages::StageOutput,
) -> Result<Entry> {
    for name in s.config.outputs() {
        if !output.tables.iter().any(|(n, _)| n == name) {
            return Err(anyhow!(
                "the stage did not produce its table `{name}` (a bug in ltcal)"
            ));
        }
    }
    let entry = Entry::new(
        &s.name,
        kf,
        (timestamp(started), timestamp(SystemTime::now())),
        seconds,
        &output.tables,
        output.files.iter().cloned().collect(),
    )?;
    match runner.point {
        None => {
            runner.store.put(&entry)?;
            publish(runner, &s.name, &entry, Some(kf))?;
        }
        Some(i) => runner.store.put_packed(entry.clone(), i),
    }
    Ok(entry)
}

/// A fresh output's tables, held in memory with their stored hashes.
fn produced(output: crate::stages::StageOutput, m: &Manifest) -> Produced {
    Produced {
        tables: output
            .tables
            .into_iter()
            .map(|(n, df)| {
                let h = m
                    .tables
                    .iter()
                    .find(|t| t.name == n)
                    .map(|t| t.hash.clone());
                (n, Output::loaded(Arc::new(df), h.unwrap_or_default()))
            })
            .collect(),
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
        tables.insert(t.name.clone(), Output::loaded(Arc::new(df), t.hash.clone()));
    }
    Ok(Produced { tables })
}

/// The content hash the manifest `m` records for its published file `name`
/// (`<table>.parquet` or a figure).
fn published_hash<'a>(m: &'a Manifest, name: &str) -> Option<&'a String> {
    let table = name.strip_suffix(".parquet");
    m.tables
        .iter()
        .find(|t| Some(t.name.as_str()) == table)
        .map(|t| &t.hash)
        .or_else(|| m.files.iter().find(|f| f.name == name).map(|f| &f.hash))
}

/// Copies an entry's tables and files to `<results>/<stage>/`, atomically,
/// writing only what differs (when the runner publishes), then records
/// `record` as what the folder holds ([`Store::last_record`]); returns the
/// existing files it replaced: path, file name and the content hash of the
/// replaced copy. The record is synced with the files but renamed only after
/// they all landed: it never names what the folder does not hold.
fn publish(
    runner: &Runner,
    stage: &str,
    entry: &Entry,
    record: Option<&KeyFields>,
) -> Result<Vec<(PathBuf, String, String)>> {
    let mut replaced = Vec::new();
    let mut writes = Vec::new();
    if runner.publish {
        let out = runner.dir.join(stage);
        let items = entry
            .tables
            .iter()
            .map(|(n, b)| (format!("{n}.parquet"), b))
            .chain(entry.files.iter().map(|(n, b)| (n.clone(), b)));
        for (name, bytes) in items {
            let path = out.join(&name);
            match crate::fs::read_regular_file(&path, cache::MAX_TABLE_BYTES) {
                Ok(old) if old == *bytes => continue,
                Ok(old) => {
                    writes.push((path.clone(), bytes));
                    replaced.push((path, name, cache::hash_bytes(&old)));
                }
                Err(_) => writes.push((path, bytes)),
            }
        }
    }
    let record = match record {
        Some(kf) => runner.store.last_record(stage, kf)?,
        None => None,
    };
    let record: Vec<_> = record
        .iter()
        .map(|(path, bytes)| (path.clone(), bytes))
        .collect();
    crate::fs::write_groups_atomic(&[&writes[..], &record[..]])?;
    Ok(replaced)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diagnostics::Source;
    use crate::pipeline::resolve::{Override, load_source};

    const TEXT: &str = "[stages.a]\nkind = \"mesh\"\nshape = \"plane\"\n\
        [stages.t]\nkind = \"inject\"\n\
        [stages.m]\nkind = \"measure\"\ninputs = { points = \"a\", errors = \"t\" }\n";

    fn run_in(root: &Path, set: &[&str]) -> RunReport {
        let overrides: Vec<Override> = set.iter().map(|s| Override::parse(s).unwrap()).collect();
        let p = load_source(&Source::new("p.toml", TEXT), &overrides).unwrap();
        let opts = RunOptions {
            results_root: root.to_path_buf(),
            keep_going: false,
            progress: false,
            not_computed: None,
            experiment: None,
            control: Default::default(),
        };
        execute_pipeline(&p, &opts, &Selection::default())
            .unwrap()
            .report
    }

    fn statuses(r: &RunReport) -> Vec<(&str, Status)> {
        r.stages
            .iter()
            .map(|s| (s.stage.as_str(), s.status))
            .collect()
    }

    /// `execute` runs what is not cached, serves what is, and reruns only
    /// the stage whose settings changed, saying why.
    #[test]
    fn execute_runs_then_serves_from_the_cache_and_reruns_only_what_changed() {
        let dir = tempfile::tempdir().unwrap();
        let first = run_in(dir.path(), &[]);
        assert_eq!(
            statuses(&first),
            [("a", Status::Ran), ("t", Status::Ran), ("m", Status::Ran)]
        );
        assert_eq!(first.stages[0].reason, "never run");
        assert!(dir.path().join("p/m/readings.parquet").is_file());
        let second = run_in(dir.path(), &[]);
        assert_eq!(
            statuses(&second),
            [
                ("a", Status::Cached),
                ("t", Status::Cached),
                ("m", Status::Cached)
            ]
        );
        let keys = |r: &RunReport| r.stages.iter().map(|s| s.key.clone()).collect::<Vec<_>>();
        assert_eq!(keys(&first), keys(&second));
        assert_eq!(first.stages[2].tables, second.stages[2].tables);
        let third = run_in(dir.path(), &["stages.m.seed=3"]);
        assert_eq!(
            statuses(&third),
            [
                ("a", Status::Cached),
                ("t", Status::Cached),
                ("m", Status::Ran)
            ]
        );
        assert!(
            third.stages[2].reason.contains("seed"),
            "{}",
            third.stages[2].reason
        );
        assert_ne!(third.stages[2].key, first.stages[2].key);
    }

    /// A damaged cache entry is never served: it is recomputed, and the
    /// report says what was wrong.
    #[test]
    fn execute_recomputes_a_corrupt_entry_and_says_so() {
        let dir = tempfile::tempdir().unwrap();
        let first = run_in(dir.path(), &[]);
        let key = first.stages[0].key.clone().unwrap();
        let entry = dir.path().join("p/.ltcal/cache").join(&key);
        let table = std::fs::read_dir(&entry)
            .unwrap()
            .flatten()
            .map(|e| e.path())
            .find(|p| p.extension().is_some_and(|x| x == "parquet"))
            .unwrap();
        std::fs::write(&table, b"not parquet").unwrap();
        let second = run_in(dir.path(), &[]);
        assert_eq!(second.stages[0].status, Status::Ran);
        assert!(second.stages[0].cache_problem.is_some());
        assert!(
            second.stages[0].reason.contains("corrupt"),
            "{}",
            second.stages[0].reason
        );
        assert_eq!(second.stages[0].key, first.stages[0].key);
    }
}
