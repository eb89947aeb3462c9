//! Running a sweep's points on a cluster: the coordinator.
//!
//! `ltcal run PIPELINE --executor slurm` does what the local runner does,
//! except that the sweep points still missing from the cache go out to a
//! batch scheduler as **one array job per wave**, each array task running
//! a batch of `points_per_task` points by calling `ltcal task` on the
//! shared working folder. The cache is the meeting point:
//!
//! - a task writes its points' entries — and the failures of its points,
//!   with their reasons — as packs ([`super::pack`]) into the same
//!   content-addressed cache, by one rename each; a task killed at any
//!   moment leaves no entry half-written, and one whose binary or pipeline
//!   file differs from the coordinator's refuses to start;
//! - the coordinator decides what is done from the cache (every entry
//!   verified when read) and from the scheduler's own task states: a point
//!   is done when its entries are in the cache, failed when its task has
//!   ended without them, and the reason given is the scheduler's (node
//!   failure, cancelled, timed out, out of memory) or, for a task that ran
//!   to its end, the stage's own error from the pack;
//! - so a rerun submits only the points still missing; a detached run's
//!   jobs are recorded (`.ltcal/slurm/jobs.json`) and a later run or
//!   `ltcal status` picks up where they stand.
//!
//! Stage dependencies are coordinator waves: the per-point stages of a
//! point depend only on each other, so one wave (one array) carries every
//! missing point, each task running its points' whole stage chains; the
//! stages after the sweep (on the gathered tables: a plot, a summary) and
//! the gather itself run in the coordinator, locally, as in a local run,
//! once the wave has ended — `run` with the points the cluster did not
//! finish marked failed with their reasons, never computed locally.
//!
//! The coordinator polls the scheduler every `poll_seconds` (5 s by
//! default: one `squeue` per job of the wave, whatever its size; `sacct`
//! for a job the controller has forgotten), which also feeds the progress
//! bar; every task's last known state is kept, since a scheduler lists an
//! ended task only for a while. Ctrl-C or SIGTERM while it waits cancels
//! the run's jobs (`scancel`); before it submits, it stops; a second one
//! ends it at once. A job of an earlier run is waited for only if it runs
//! the same code, pipeline file and `--set` arguments; any other is left
//! alone and its points submitted again. Two coordinators on one pipeline
//! may both submit a missing point; both tasks write identical entries,
//! either copy serves.
//!
//! This module knows nothing of Slurm's commands: [`Scheduler`] is what a
//! batch scheduler offers, [`slurm`] is Slurm's; PBS or LSF would be
//! another implementation.

pub mod scheduler;
pub mod settings;
pub mod slurm;

pub use scheduler::{ArrayJob, Scheduler, TaskState};
pub use settings::SlurmSettings;

use super::cache::Store;
use super::control::Interrupted;
use super::plan;
use super::publish;
use super::resolve::{Pipeline, Sweep};
use super::run::{self, RunOptions, point_label};
use super::run_report::RunReport;
use super::status::Status;
use anyhow::{Context as _, Result, anyhow, bail};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// One array task's points.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Unit {
    pub first: usize,
    pub last: usize,
    /// `a-b,c,…`: the points, in ranges.
    pub points: String,
}

impl Unit {
    fn of(points: &[usize]) -> Unit {
        Unit {
            first: points[0],
            last: points[points.len() - 1],
            points: ranges(points),
        }
    }

    fn log(&self, wave: &Path) -> PathBuf {
        wave.join(format!("points-{}-{}.log", self.first, self.last))
    }
}

/// A submitted wave, as recorded for later runs.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct JobRecord {
    pub job: String,
    pub wave: PathBuf,
    pub units: Vec<Unit>,
    /// What its tasks compute with: a later run waits for the job only if
    /// it would compute the same (the code fingerprint, the blake3 of the
    /// pipeline file, the `--set` arguments).
    pub code: String,
    pub pipeline_hash: String,
    pub set_args: Vec<String>,
    pub submitted: String,
}

impl JobRecord {
    /// Whether the job's tasks compute what a run with `set_args` would:
    /// same code, same pipeline file, same settings of the stages (the
    /// `executor.slurm` settings and the order of the arguments change
    /// nothing the tasks compute).
    fn computes_as(&self, pipeline_hash: &str, set_args: &[String]) -> bool {
        let stages = |args: &[String]| {
            let mut v: Vec<String> = args
                .iter()
                .filter(|a| !a.trim_start().starts_with("executor."))
                .map(|a| a.trim().to_string())
                .collect();
            v.sort();
            v
        };
        self.code == crate::CODE_FINGERPRINT
            && self.pipeline_hash == pipeline_hash
            && stages(&self.set_args) == stages(set_args)
    }
}

/// `0-3,7,9-10` of increasing points.
pub fn ranges(points: &[usize]) -> String {
    let mut out: Vec<String> = Vec::new();
    let mut i = 0;
    while i < points.len() {
        let mut j = i;
        while j + 1 < points.len() && points[j + 1] == points[j] + 1 {
            j += 1;
        }
        out.push(if i == j {
            points[i].to_string()
        } else {
            format!("{}-{}", points[i], points[j])
        });
        i = j + 1;
    }
    out.join(",")
}

/// The points a `ranges` string names, increasing, each below `limit`;
/// more than `limit` in all (counting repeats) is refused, so no string
/// makes it allocate more than `limit` points.
pub fn parse_ranges(s: &str, limit: usize) -> Result<Vec<usize>> {
    let mut out = Vec::new();
    for part in s.split(',').filter(|p| !p.is_empty()) {
        let (a, b) = match part.split_once('-') {
            Some((a, b)) => (a.trim().parse::<usize>()?, b.trim().parse::<usize>()?),
            None => {
                let a = part.trim().parse::<usize>()?;
                (a, a)
            }
        };
        if a > b || b >= limit {
            bail!("`{part}` is not a range of points below {limit}");
        }
        if out.len() + (b - a) >= limit {
            bail!("more than {limit} points");
        }
        out.extend(a..=b);
    }
    out.sort_unstable();
    out.dedup();
    Ok(out)
}

/// Where the records of submitted jobs are kept.
fn jobs_path(store_dir: &Path) -> PathBuf {
    store_dir.join(".ltcal").join("slurm").join("jobs.json")
}

/// The jobs recorded for the pipeline: none when nothing was recorded; an
/// error, not an empty list, when the record cannot be read (forgetting
/// running jobs would submit their points again).
fn read_jobs(dir: &Path) -> Result<Vec<JobRecord>> {
    let path = jobs_path(dir);
    match crate::fs::read_regular_file(&path, super::cache::MAX_MANIFEST_BYTES) {
        Err(e) if e.is_missing() => Ok(Vec::new()),
        Err(e) => Err(e.into()),
        Ok(b) => serde_json::from_slice(&b).map_err(|e| {
            anyhow!(
                "{} is damaged ({e}): remove it to forget the jobs it recorded",
                path.display()
            )
        }),
    }
}

fn write_jobs(dir: &Path, jobs: &[JobRecord]) -> Result<()> {
    crate::fs::write_atomic(&jobs_path(dir), &serde_json::to_vec_pretty(jobs)?)
}

/// How the coordinator is asked to run.
pub struct ClusterOptions {
    /// The pipeline file, as the tasks will read it.
    pub pipeline_file: PathBuf,
    /// The `--set` arguments as typed, passed on to every task.
    pub set_args: Vec<String>,
    /// Submit and return.
    pub detach: bool,
    /// Set by Ctrl-C or SIGTERM.
    pub interrupted: Arc<AtomicBool>,
}

/// What a cluster run came to.
pub enum Outcome {
    /// The run ended: every point done, or failed with its reason.
    Finished(Box<RunReport>),
    /// Submitted and left running (`--detach`).
    Detached { jobs: Vec<String>, points: usize },
}

/// The sweep points not (wholly) in the cache, increasing.
pub fn missing_points(sw: &Sweep, store: &Store) -> Vec<usize> {
    let mut out = Vec::new();
    plan::assess_points(sw, store, |i, assessed| {
        if assessed.iter().any(|a| a.item.status != Status::Cached) {
            out.push(i);
        }
    });
    out
}

/// Runs the pipeline with its sweep points on the scheduler.
pub fn run(
    p: &Pipeline,
    opts: &RunOptions,
    cluster: &ClusterOptions,
    scheduler: &dyn Scheduler,
) -> Result<Outcome> {
    let Some(sw) = &p.sweep else {
        return Err(super::error::InputError::arg(format!(
            "{}: the {} executor runs a sweep's points; this pipeline has no [sweep] (run it locally)",
            cluster.pipeline_file.display(),
            scheduler.name()
        )));
    };
    let settings = &p.slurm;
    let dir = run::pipeline_dir(&opts.results_root, p);
    let store = Store::new(&dir);
    store.clean_incomplete();
    let pipeline_file = std::path::absolute(&cluster.pipeline_file)?;
    let text = crate::fs::read_regular_file(&pipeline_file, super::error::MAX_FILE_BYTES)?;
    let pipeline_hash = super::cache::hash_bytes(&text);
    let mut jobs = read_jobs(&dir)?;
    // Jobs of earlier runs still running the same computation: waited for,
    // not submitted again. Others are left alone.
    let mut active: Vec<JobRecord> = Vec::new();
    for j in jobs
        .iter()
        .filter(|j| j.computes_as(&pipeline_hash, &cluster.set_args))
    {
        if let Some(tasks) = scheduler.tasks(&j.job)? {
            if tasks.iter().any(TaskState::active) {
                active.push(j.clone());
            }
        }
    }
    let in_flight: std::collections::BTreeSet<usize> = active
        .iter()
        .flat_map(|j| j.units.iter())
        .flat_map(|u| parse_ranges(&u.points, sw.len()).unwrap_or_default())
        .collect();
    let missing: Vec<usize> = missing_points(sw, &store)
        .into_iter()
        .filter(|i| !in_flight.contains(i))
        .collect();
    if cluster.interrupted.load(Ordering::SeqCst) {
        return Err(Interrupted::Cluster("before anything was submitted".into()).into());
    }
    let mut ours = active;
    if !missing.is_empty() {
        let record = submit(p, opts, cluster, scheduler, &dir, &missing, &pipeline_hash)?;
        if opts.progress {
            eprintln!(
                "submitted {} points as {} job {} ({} array tasks of up to {} points, at most {} at once); logs in {}",
                missing.len(),
                scheduler.name(),
                record.job,
                record.units.len(),
                settings.points_per_task,
                settings.max_running,
                record.wave.display()
            );
        }
        // Kept: the jobs waited for, and those of other computations that
        // may still run (for `ltcal status`); the new one.
        jobs.retain(|j| {
            ours.iter().any(|o| o.job == j.job) || !j.computes_as(&pipeline_hash, &cluster.set_args)
        });
        jobs.push(record.clone());
        write_jobs(&dir, &jobs)?;
        ours.push(record);
    }
    if cluster.detach {
        let points = ours
            .iter()
            .flat_map(|j| j.units.iter())
            .map(|u| count(&u.points))
            .sum();
        return Ok(Outcome::Detached {
            jobs: ours.into_iter().map(|j| j.job).collect(),
            points,
        });
    }
    let states = wait(p, opts, cluster, scheduler, &ours)?;
    if cluster.interrupted.load(Ordering::SeqCst) {
        return Err(Interrupted::Cluster(
            "after the jobs ended: a rerun gathers what they computed".into(),
        )
        .into());
    }
    // What the wave did not finish, and why.
    store.refresh_packs();
    let still = missing_points(sw, &store);
    // Each submitted point's (job, task), the latest submission winning.
    let mut owner: std::collections::HashMap<usize, (usize, usize)> = Default::default();
    for (a, j) in ours.iter().enumerate() {
        for (k, u) in j.units.iter().enumerate() {
            for i in parse_ranges(&u.points, sw.len()).unwrap_or_default() {
                owner.insert(i, (a, k));
            }
        }
    }
    // The failures the tasks recorded, by pack prefix and point.
    let mut recorded: std::collections::HashMap<(String, usize), (String, String)> =
        Default::default();
    for f in store.failures() {
        // The first failure a task recorded at a point: the one that
        // stopped the stages after it.
        recorded
            .entry((f.prefix, f.point))
            .or_insert((f.stage, f.reason));
    }
    let first = p
        .stages
        .iter()
        .find(|s| sw.point_stages().any(|n| n == s.name))
        .map(|s| s.name.clone())
        .unwrap_or_default();
    let failed: BTreeMap<usize, (String, String)> = still
        .into_iter()
        .map(|i| {
            let why = why_missing(
                scheduler,
                sw,
                &ours,
                &states,
                &recorded,
                i,
                owner.get(&i).copied(),
            );
            (i, (why.0.unwrap_or_else(|| first.clone()), why.1))
        })
        .collect();
    let run_opts = RunOptions {
        not_computed: Some(Arc::new(failed)),
        ..opts.clone()
    };
    let report = publish::run(p, &run_opts)?;
    Ok(Outcome::Finished(Box::new(report)))
}

/// Writes the wave's folder (points file, job script) and submits it.
fn submit(
    p: &Pipeline,
    opts: &RunOptions,
    cluster: &ClusterOptions,
    scheduler: &dyn Scheduler,
    dir: &Path,
    missing: &[usize],
    pipeline_hash: &str,
) -> Result<JobRecord> {
    let settings = &p.slurm;
    let units: Vec<Unit> = missing
        .chunks(settings.points_per_task)
        .map(Unit::of)
        .collect();
    let started = std::time::SystemTime::now();
    let stamp = humantime::format_rfc3339_seconds(started)
        .to_string()
        .replace([':', '-'], "");
    let wave = std::path::absolute(
        dir.join("slurm")
            .join(format!("wave-{stamp}-{}", std::process::id())),
    )?;
    std::fs::create_dir_all(&wave).with_context(|| format!("creating {}", wave.display()))?;
    let units_file = wave.join("points.txt");
    let text: String = units
        .iter()
        .map(|u| format!("{}-{} {}\n", u.first, u.last, u.points))
        .collect();
    crate::fs::write_atomic(&units_file, text.as_bytes())?;
    let exe = std::env::current_exe().context("finding the ltcal binary to run tasks with")?;
    let pipeline_file = std::path::absolute(&cluster.pipeline_file)?;
    let mut command = vec![
        exe.display().to_string(),
        "task".into(),
        pipeline_file.display().to_string(),
        "--results".into(),
        std::path::absolute(&opts.results_root)?
            .display()
            .to_string(),
        "--code".into(),
        crate::CODE_FINGERPRINT.to_string(),
        "--pipeline-hash".into(),
        pipeline_hash.to_string(),
        "--cpus".into(),
        settings.cpus_per_task.to_string(),
    ];
    for s in &cluster.set_args {
        command.push("--set".into());
        command.push(s.clone());
    }
    let workdir = std::env::current_dir()?;
    let job = ArrayJob {
        name: &p.name,
        tasks: units.len(),
        settings,
        workdir: &workdir,
        wave: &wave,
        units: &units_file,
        command,
    };
    let script = wave.join("job.sh");
    crate::fs::write_atomic(&script, scheduler.script(&job).as_bytes())?;
    let id = scheduler.submit(&script)?;
    Ok(JobRecord {
        job: id,
        wave,
        units,
        code: crate::CODE_FINGERPRINT.to_string(),
        pipeline_hash: pipeline_hash.to_string(),
        set_args: cluster.set_args.clone(),
        submitted: run::timestamp(started),
    })
}

/// Job → its tasks' last known states.
type States = BTreeMap<String, Vec<TaskState>>;

/// The state given a task that was active when last seen and is listed no
/// more.
const FORGOTTEN: &str = "ended (no longer listed)";

/// Waits until no task of `jobs` is active, showing progress; cancels
/// them on Ctrl-C or SIGTERM. Returns the tasks' last states.
fn wait(
    p: &Pipeline,
    opts: &RunOptions,
    cluster: &ClusterOptions,
    scheduler: &dyn Scheduler,
    jobs: &[JobRecord],
) -> Result<States> {
    // Points per task, counted once.
    let sizes: Vec<Vec<usize>> = jobs
        .iter()
        .map(|j| j.units.iter().map(|u| count(&u.points)).collect())
        .collect();
    let total: usize = sizes.iter().flatten().sum();
    let bar = run::progress_bar(
        opts.progress,
        total,
        format!("{} {}", p.name, scheduler.name()),
    );
    let poll = Duration::from_secs_f64(p.slurm.poll_seconds);
    // Every task's last known state: a scheduler lists an ended task only
    // for a while (Slurm: `MinJobAge`, 300 s), and a long wave's early
    // failures must still be named at its end.
    let mut states = States::new();
    let mut last_poll: Option<Instant> = None;
    let mut failed_polls = 0;
    loop {
        if cluster.interrupted.load(Ordering::SeqCst) {
            bar.finish_and_clear();
            let ids: Vec<String> = jobs
                .iter()
                .filter(|j| {
                    states
                        .get(&j.job)
                        .is_none_or(|t| t.is_empty() || t.iter().any(TaskState::active))
                })
                .map(|j| j.job.clone())
                .collect();
            scheduler.cancel(&ids)?;
            return Err(Interrupted::Cluster(format!(
                "cancelled {} job {} (a rerun submits the points still missing)",
                scheduler.name(),
                ids.join(", ")
            ))
            .into());
        }
        if last_poll.is_none_or(|t| t.elapsed() >= poll) {
            last_poll = Some(Instant::now());
            for j in jobs {
                let known = states.entry(j.job.clone()).or_default();
                match scheduler.tasks(&j.job) {
                    Ok(listed) => {
                        let listed = listed.unwrap_or_default();
                        // Active when last seen and no longer listed: it
                        // ended and was forgotten between two polls.
                        for t in known.iter_mut() {
                            if t.active() && !listed.iter().any(|l| l.index == t.index) {
                                t.state = FORGOTTEN.into();
                            }
                        }
                        for t in listed {
                            match known.iter_mut().find(|x| x.index == t.index) {
                                Some(x) => *x = t,
                                None => known.push(t),
                            }
                        }
                        failed_polls = 0;
                    }
                    // A controller that does not answer for a moment is no
                    // reason to give up the wave (nor to stop listening for
                    // Ctrl-C); three polls in a row are.
                    Err(e) => {
                        failed_polls += 1;
                        if failed_polls >= 3 * jobs.len() {
                            return Err(e);
                        }
                    }
                }
            }
            let mut queued = 0;
            let mut running = 0;
            let mut ended = 0;
            let mut unsuccessful = 0;
            let mut any_active = false;
            for (j, sizes) in jobs.iter().zip(&sizes) {
                let tasks = states.get(&j.job);
                for (k, &n) in sizes.iter().enumerate() {
                    match tasks.and_then(|t| t.iter().find(|t| t.index == k)) {
                        Some(t) if t.pending() => {
                            queued += n;
                            any_active = true
                        }
                        Some(t) if t.active() => {
                            running += n;
                            any_active = true
                        }
                        Some(t) => {
                            ended += n;
                            if t.state != "COMPLETED" {
                                unsuccessful += n;
                            }
                        }
                        // Not listed yet: a pending array not yet split
                        // into tasks is listed as one line.
                        None if tasks.is_some_and(|t| t.iter().any(TaskState::active)) => {
                            queued += n;
                            any_active = true
                        }
                        None => ended += n,
                    }
                }
            }
            bar.set_position(ended as u64);
            bar.set_message(format!(
                "queued {queued}, running {running}, ended {ended} ({unsuccessful} in tasks that did not complete)"
            ));
            if !any_active {
                break;
            }
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    bar.finish_and_clear();
    Ok(states)
}

fn count(points: &str) -> usize {
    parse_ranges(points, super::sweep::MAX_POINTS).map_or(0, |v| v.len())
}

/// Why point `i` is not in the cache after its task ended: the
/// scheduler's word for a task that did not complete (with its node), the
/// stage's error a task recorded, and where the task's log is.
fn why_missing(
    scheduler: &dyn Scheduler,
    sw: &Sweep,
    jobs: &[JobRecord],
    states: &States,
    recorded: &std::collections::HashMap<(String, usize), (String, String)>,
    i: usize,
    owner: Option<(usize, usize)>,
) -> (Option<String>, String) {
    let Some((a, k)) = owner else {
        return (
            None,
            format!(
                "it was not submitted (point {i}: {})",
                point_label(sw, &sw.values[i])
            ),
        );
    };
    let name = scheduler.name();
    let j = &jobs[a];
    let log = j.units[k].log(&j.wave);
    let at = format!("Slurm job {}, array task {k}, log {}", j.job, log.display());
    let task = states
        .get(&j.job)
        .and_then(|t| t.iter().find(|t| t.index == k));
    match (task, recorded.get(&(scheduler.task_prefix(&j.job, k), i))) {
        (_, Some((stage, reason))) => (
            Some(stage.clone()),
            format!("stage `{stage}` failed: {reason} ({at})"),
        ),
        (Some(t), None) if t.state == FORGOTTEN => (
            None,
            format!("its task ended and {name} no longer lists it; see the log ({at})"),
        ),
        (Some(t), None) if t.state != "COMPLETED" => {
            let node = if t.node.is_empty() {
                String::new()
            } else {
                format!(" on {}", t.node)
            };
            (None, format!("its task ended {}{node} ({at})", t.state))
        }
        (Some(_), None) => (
            None,
            format!("its task completed without its entries (see the log; {at})"),
        ),
        (None, None) => (
            None,
            format!("{name} no longer knows its task and the cache does not hold it ({at})"),
        ),
    }
}

/// What `ltcal status` shows: points done, and where the recorded jobs stand.
pub fn status(p: &Pipeline, opts: &RunOptions, scheduler: &dyn Scheduler) -> Result<String> {
    let Some(sw) = &p.sweep else {
        return Err(anyhow!("`{}` has no [sweep]", p.name));
    };
    let dir = run::pipeline_dir(&opts.results_root, p);
    let store = Store::new(&dir);
    let missing = missing_points(sw, &store);
    let mut out = format!(
        "{}: {} of {} sweep points done, {} missing\n",
        p.name,
        sw.len() - missing.len(),
        sw.len(),
        missing.len()
    );
    for j in read_jobs(&dir)? {
        let tasks = scheduler.tasks(&j.job)?;
        let mut by_state: BTreeMap<String, usize> = BTreeMap::new();
        for (k, u) in j.units.iter().enumerate() {
            let state = tasks
                .as_ref()
                .and_then(|t| t.iter().find(|t| t.index == k))
                .map(|t| t.state.clone())
                .unwrap_or_else(|| {
                    if tasks
                        .as_ref()
                        .is_some_and(|t| t.iter().any(TaskState::active))
                    {
                        "PENDING".into()
                    } else {
                        "unknown to Slurm now".into()
                    }
                });
            *by_state.entry(state).or_default() += count(&u.points);
        }
        let states: Vec<String> = by_state.iter().map(|(s, n)| format!("{n} {s}")).collect();
        out.push_str(&format!(
            "  job {} (submitted {}, {} tasks): points {}; logs in {}\n",
            j.job,
            j.submitted,
            j.units.len(),
            states.join(", "),
            j.wave.display()
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_round_trip() {
        let pts = vec![0, 1, 2, 3, 7, 9, 10];
        assert_eq!(ranges(&pts), "0-3,7,9-10");
        assert_eq!(parse_ranges("0-3,7,9-10", 11).unwrap(), pts);
        assert!(parse_ranges("9-12", 11).is_err());
        assert!(parse_ranges("3-1", 11).is_err());
        assert!(parse_ranges("x", 11).is_err());
    }

    #[test]
    fn repeated_ranges_cannot_allocate_beyond_the_limit() {
        let hostile = vec!["0-99999"; 1000].join(",");
        let e = parse_ranges(&hostile, 100_000).unwrap_err();
        assert!(e.to_string().contains("more than 100000 points"), "{e}");
        assert_eq!(parse_ranges("0-99999", 100_000).unwrap().len(), 100_000);
    }
}
