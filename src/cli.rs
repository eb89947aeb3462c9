//! The command line: `ltcal run`, `status`, `verify`, `task`, `plan`, `explain`, `graph`, `snapshot`,
//! `show`, `runs`, `diagnose`, `kinds`, `completions`. What a script reads (tables,
//! results) goes to stdout, progress and notes to stderr, and every command
//! exits with the README's codes: 0 success, 1 the work did not succeed, 2
//! the input is wrong.

use crate::pipeline::{
    self, InputError, cache::Store, cluster, experiment, experiment::Experiment, explain, graph,
    plan, publish, published, resolve::Override, run, snapshot, status::Status,
};
use crate::stages;
use crate::table;
use anyhow::{Context as _, Result, bail};
use clap::{Args, CommandFactory as _, Parser, Subcommand, ValueEnum};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

#[derive(Parser, Debug)]
#[command(
    name = "ltcal",
    version,
    about = "Laser-tracker kinematic calibration research pipelines"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Args, Debug, Clone)]
struct PipelineArgs {
    /// The pipeline file.
    pipeline: PathBuf,
    /// Override a setting: `stages.<stage>.<field>=<TOML value>` (repeatable).
    /// A stage override makes the run an experiment, published to
    /// `results/<pipeline>/runs/<name>/`, not to the pipeline's results.
    #[arg(long = "set", value_name = "PATH=VALUE")]
    set: Vec<String>,
    /// The experiment's name (default with `--set`: `set-<hash of the
    /// overrides>`); without `--set`, the experiment of that name with its
    /// recorded overrides.
    #[arg(long, value_name = "NAME")]
    name: Option<String>,
    /// The folder that holds every pipeline's results.
    #[arg(long, default_value = "results")]
    results: PathBuf,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run a pipeline: every stage whose result is not cached — or only
    /// what the stages named need.
    Run {
        #[command(flatten)]
        p: PipelineArgs,
        /// Run only these stages and what they need (the other stages are
        /// served if cached, else skipped).
        #[arg(value_name = "STAGE")]
        stages: Vec<String>,
        /// Recompute this stage even if cached, and what depends on it
        /// among the stages run (repeatable).
        #[arg(long, value_name = "STAGE")]
        force: Vec<String>,
        /// Run every stage whose inputs exist even after a failure.
        #[arg(long)]
        keep_going: bool,
        /// Worker threads, 1 to 1024 (default: all cores).
        #[arg(short = 'j', long, value_parser = thread_count())]
        threads: Option<usize>,
        /// No per-stage lines.
        #[arg(short, long)]
        quiet: bool,
        /// Where the sweep points run: here, or as array jobs on a Slurm
        /// cluster (settings: the pipeline's `[executor.slurm]`).
        #[arg(long, value_enum, default_value_t = Executor::Local)]
        executor: Executor,
        /// With `--executor slurm`: submit and return; a later `ltcal run`
        /// or `ltcal status` picks up where the jobs stand.
        #[arg(long)]
        detach: bool,
    },
    /// Where a sweep stands: points done and missing, and the state of the
    /// cluster jobs submitted for it.
    Status {
        #[command(flatten)]
        p: PipelineArgs,
    },
    /// Read and verify every cached entry of a pipeline, loose and packed:
    /// exit 1 if any is damaged (nothing is removed, unless `--repair`).
    Verify {
        #[command(flatten)]
        p: PipelineArgs,
        /// Take out what is damaged (a damaged pack's good entries are
        /// rewritten), say what was done, and exit 0 once the cache is good:
        /// what is taken out is computed again by the next run.
        #[arg(long)]
        repair: bool,
    },
    /// Run a batch of sweep points as one task of a cluster job (the job
    /// scripts `--executor slurm` writes call this).
    #[command(hide = true)]
    Task {
        #[command(flatten)]
        p: PipelineArgs,
        /// The points: `a-b,c,…`.
        #[arg(long)]
        points: String,
        /// The coordinator's code fingerprint: a different binary refuses.
        #[arg(long)]
        code: String,
        /// The blake3 of the pipeline file the coordinator read.
        #[arg(long)]
        pipeline_hash: String,
        /// Name prefix of the packs this task writes.
        #[arg(long)]
        prefix: String,
        /// The task's CPUs: points run at once, and worker threads.
        #[arg(long, default_value_t = 1, value_parser = thread_count())]
        cpus: usize,
    },
    /// Print what `run` would do and why, without running anything.
    Plan {
        #[command(flatten)]
        p: PipelineArgs,
        /// Print the plan as JSON.
        #[arg(long)]
        json: bool,
        /// Exit with 1 if any stage would run (for CI: results are current).
        #[arg(long)]
        check: bool,
    },
    /// Why a stage would run or is cached: its key against the last run's,
    /// field by field.
    Explain {
        #[command(flatten)]
        p: PipelineArgs,
        stage: String,
        /// For a stage that runs per sweep point: the point (default: the
        /// first point that would run it, else point 0).
        #[arg(long)]
        point: Option<usize>,
        /// Print the explanation as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Print the stage graph, each stage coloured by whether it is cached.
    Graph {
        #[command(flatten)]
        p: PipelineArgs,
        #[arg(long, value_enum, default_value_t = GraphFormat::Dot)]
        format: GraphFormat,
    },
    /// Record the tables named in the pipeline's `[snapshot]` as text, or
    /// with `--check` compare the current results with the recording.
    Snapshot {
        #[command(flatten)]
        p: PipelineArgs,
        /// Compare instead of recording; exit with 1 on a difference.
        #[arg(long)]
        check: bool,
        /// The folder of recordings: `<dir>/<pipeline>/<stage>.<table>.txt`.
        #[arg(long, default_value = "tests/snapshots")]
        dir: PathBuf,
    },
    /// List a pipeline's experiments (runs with `--set`): name, status,
    /// when its last run finished, its overrides; one a line, by name.
    Runs {
        /// The pipeline file.
        pipeline: PathBuf,
        /// The folder that holds every pipeline's results.
        #[arg(long, default_value = "results")]
        results: PathBuf,
    },
    /// Print a result table: `<stage>` (its first table) or `<stage>.<table>`.
    Show {
        #[command(flatten)]
        p: PipelineArgs,
        table: String,
        /// Aligned text for reading, or CSV or JSON (an array of records)
        /// for scripts: those print the table alone on stdout, numbers at
        /// full precision, missing values empty (CSV) or null (JSON).
        #[arg(long, value_enum, default_value_t = ShowFormat::Table)]
        format: ShowFormat,
        /// Print the first N rows only (with `--format table`, stderr says
        /// how many were left out).
        #[arg(long, value_name = "N")]
        limit: Option<usize>,
        /// Decimal places of numbers in `--format table`.
        #[arg(long, default_value_t = 6)]
        digits: usize,
    },
    /// Diagnose a campaign folder: where its residual lies, which
    /// unmodelled effect causes it, how far the gap shrinks.
    Diagnose {
        /// The campaign folder (campaign-format.md).
        campaign: PathBuf,
        /// Where to write diagnosis.csv, report.md and the figures.
        #[arg(long)]
        out: PathBuf,
        /// Effect ids to try (repeatable; default: all of effects.md).
        #[arg(long = "effect", value_name = "ID")]
        effects: Vec<String>,
        /// Cross-validation folds.
        #[arg(long, default_value_t = 5)]
        folds: usize,
        /// Monte Carlo draws of the noise floor at most (the first 32 when
        /// their mean is already known to 0.1 %).
        #[arg(long, default_value_t = 100)]
        mc_draws: usize,
        /// Seed of the folds and the Monte Carlo draws.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// The tracker model to fit (default: the campaign's `[tracker] model`).
        #[arg(long, value_name = "ID", value_parser = tracker_model)]
        model: Option<crate::trackers::TrackerModel>,
        /// A hypothesis file: your own effects, tried beside the catalogue's
        /// (README, "Your own effects").
        #[arg(long, value_name = "FILE")]
        hypotheses: Option<PathBuf>,
    },
    /// Remove the cache entries and packs that no current pipeline and no
    /// recorded run can reach (after a code change, the superseded ones).
    Gc {
        /// The pipelines whose caches to collect (default: every `*.toml`
        /// under `pipelines/` beside the results folder).
        pipelines: Vec<PathBuf>,
        /// The folder that holds every pipeline's results.
        #[arg(long, default_value = "results")]
        results: PathBuf,
        /// List what would be removed, with sizes, and remove nothing.
        #[arg(long)]
        dry_run: bool,
    },
    /// List the stage kinds, or one kind's settings: name, type, default,
    /// unit (from the name's suffix).
    Kinds {
        /// The kind whose settings to print.
        kind: Option<String>,
    },
    /// Print the completion script of a shell (README, "Shell completions"
    /// says where each shell reads it from).
    Completions {
        #[arg(value_enum)]
        shell: clap_complete::Shell,
    },
}

/// The most worker threads `-j` accepts: far beyond any machine's cores,
/// and few enough that creating them costs no noticeable time (a hundred
/// thousand took minutes).
const MAX_THREADS: u64 = 1024;

fn tracker_model(s: &str) -> Result<crate::trackers::TrackerModel, String> {
    crate::trackers::TrackerModel::parse(s).ok_or_else(|| {
        format!(
            "unknown tracker model; expected {}",
            crate::trackers::TrackerModel::expected()
        )
    })
}

fn thread_count() -> clap::builder::RangedU64ValueParser<usize> {
    clap::builder::RangedU64ValueParser::new().range(1..=MAX_THREADS)
}

#[derive(Clone, Copy, Debug, PartialEq, ValueEnum)]
enum Executor {
    Local,
    Slurm,
}

#[derive(Clone, Copy, Debug, PartialEq, ValueEnum)]
enum ShowFormat {
    Table,
    Csv,
    Json,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum GraphFormat {
    Dot,
    Mermaid,
    Svg,
}

/// Runs the command line and returns the process exit code: 0 success,
/// 1 a stage failed (or a check found a difference), 2 the input is wrong,
/// 130 a run stopped by Ctrl-C.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    match dispatch(cli) {
        Ok(code) => code,
        Err(e) => {
            let (text, code) = if let Some(input) = e.downcast_ref::<InputError>() {
                (input.to_string(), 2)
            } else if let Some(at) = e.downcast_ref::<crate::diagnostics::SourceError>() {
                // A mistake found in a user's file while working (a
                // hypothesis not finite at some reading).
                (at.to_string(), 2)
            } else if let Some(stop) = e.downcast_ref::<pipeline::control::Interrupted>() {
                // 128 + SIGINT, as a shell reports a process Ctrl-C ended.
                (stop.to_string(), 130)
            } else {
                (format!("{e:#}"), 1)
            };
            anstream::eprintln!("{}", paint_error(&text));
            ExitCode::from(code)
        }
    }
}

/// An error as printed: `error:` and the carets under the place in red
/// and bold (`anstream` strips them where there is no terminal).
fn paint_error(text: &str) -> String {
    let red = anstyle::Style::new()
        .bold()
        .fg_color(Some(anstyle::AnsiColor::Red.into()));
    let lines: Vec<String> = text
        .lines()
        .map(|l| {
            // `   |     ^^^^`: the caret line under a quoted source line.
            let rest = l.trim_start().strip_prefix('|').map(str::trim_start);
            match rest {
                Some(carets) if !carets.is_empty() && carets.chars().all(|c| c == '^') => {
                    let at = l.len() - carets.len();
                    format!("{}{red}{carets}{red:#}", &l[..at])
                }
                _ => l.to_string(),
            }
        })
        .collect();
    format!("{red}error:{red:#} {}", lines.join("\n"))
}

fn overrides(p: &PipelineArgs) -> Result<Vec<Override>> {
    p.set
        .iter()
        .map(|s| Override::parse(s))
        .collect::<Result<Vec<_>>>()
        .map_err(|e| InputError::arg(e.to_string()))
}

/// The pipeline with its overrides, and the experiment the arguments name
/// (`None`: the pipeline's own results), for a command that runs it: `--name`
/// with `--set` defines (or redefines) the experiment.
fn load_to_run(p: &PipelineArgs) -> Result<(pipeline::resolve::Pipeline, Option<Experiment>)> {
    pipeline::load_target(&p.pipeline, &overrides(p)?, p.name.as_deref(), &p.results)
}

/// [`load_to_run`] for a command that looks at results: `--name` with
/// `--set` must be the experiment's recorded overrides.
fn load(p: &PipelineArgs) -> Result<(pipeline::resolve::Pipeline, Option<Experiment>)> {
    let (pipeline, e) = load_to_run(p)?;
    if let Some(e) = e.as_ref().filter(|_| p.name.is_some()) {
        experiment::check_recorded(&run::pipeline_dir(&p.results, &pipeline), e)?;
    }
    Ok((pipeline, e))
}

fn store(
    p: &PipelineArgs,
    pipeline: &pipeline::resolve::Pipeline,
    e: Option<&Experiment>,
) -> Store {
    run::store(&p.results, pipeline, e)
}

/// The command that brings these results up to date, for messages.
fn rerun(p: &PipelineArgs, e: Option<&Experiment>) -> String {
    match e {
        Some(e) => format!("`ltcal run {} --name {}`", p.pipeline.display(), e.name),
        None => format!("`ltcal run {}`", p.pipeline.display()),
    }
}

/// Says which experiment a command is about, when it is one.
fn say_experiment(e: Option<&Experiment>) {
    if let Some(e) = e {
        eprintln!(
            "experiment `{}` ({})",
            e.name,
            experiment::set_args(&e.overrides)
        );
    }
}

/// Prints the run's outcome — counts, recomputed cache entries, skipped
/// stages, and each failure with its message — and returns the exit code.
fn summarize(report: &run::RunReport) -> ExitCode {
    let (ran, cached) = (
        report.with_status(Status::Ran),
        report.with_status(Status::Cached),
    );
    let damaged: Vec<&run::StageReport> = report
        .stages
        .iter()
        .filter(|s| s.cache_problem.is_some())
        .collect();
    let failed = report.failed();
    eprintln!(
        "{}: {} ran, {} cached{}{}; results in {}",
        report.pipeline,
        ran.len(),
        cached.len(),
        match damaged.len() {
            0 => String::new(),
            n => format!(
                ", {n} CORRUPT cache entr{} recomputed",
                if n == 1 { "y" } else { "ies" }
            ),
        },
        match failed.len() {
            0 => String::new(),
            n => format!(", {n} FAILED"),
        },
        report.page().display()
    );
    for s in &damaged {
        eprintln!(
            "  cache entry of `{}` was corrupt and is recomputed: {}",
            s.stage,
            s.cache_problem.as_deref().unwrap_or_default()
        );
    }
    for p in &report.unreadable_packs {
        eprintln!("  DAMAGED pack, not read (its points are recomputed): {p}");
    }
    for h in &report.healed {
        eprintln!("  healed the cache: {h}");
    }
    for s in report.stages.iter().filter(|s| s.status == Status::Skipped) {
        eprintln!("  skipped `{}`: {}", s.stage, s.reason);
    }
    for f in &failed {
        eprintln!(
            "\nstage `{}` ({}) failed:\n  {}",
            f.stage,
            f.kind,
            f.reason.replace('\n', "\n  ")
        );
    }
    if failed.is_empty() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    }
}

/// Prints the pipeline's `[summary]` from the run's results: on stdout
/// (the results), each that cannot be given on stderr, saying why.
fn headlines(p: &PipelineArgs, report: &run::RunReport) -> Result<()> {
    let mut text = String::new();
    for h in pipeline::summary::read(&pipeline::summary(&p.pipeline)?, report) {
        match h.value {
            Ok(v) => text += &format!("{} = {v}\n", h.name),
            Err(why) => eprintln!("summary `{}` not available: {why}", h.name),
        }
    }
    print_out(text)
}

/// `ltcal task`: one array task of a cluster run. Refuses, writing nothing,
/// when its binary or the pipeline file is not the coordinator's — its
/// entries would be keyed by another code, or computed from another file.
fn task_command(
    p: &PipelineArgs,
    points: &str,
    code: &str,
    pipeline_hash: &str,
    prefix: &str,
    cpus: usize,
) -> Result<ExitCode> {
    if prefix.is_empty()
        || !prefix
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
    {
        return Err(InputError::arg(format!(
            "--prefix {prefix:?}: letters, digits, `_` and `-` only (it names the task's packs)"
        )));
    }
    if code != crate::CODE_FINGERPRINT {
        bail!(
            "this ltcal binary ({}) is not the coordinator's (code {}): it was rebuilt since the \
             job was submitted; nothing is written — rerun `ltcal run --executor slurm`, which submits \
             the missing points with the binary now in place",
            pipeline::cache::short(crate::CODE_FINGERPRINT),
            pipeline::cache::short(code)
        );
    }
    let text = crate::fs::read_regular_file(&p.pipeline, pipeline::MAX_FILE_BYTES)?;
    if pipeline::cache::hash_bytes(&text) != pipeline_hash {
        bail!(
            "{} changed since the job was submitted; nothing is written — rerun `ltcal run --executor slurm`",
            p.pipeline.display()
        );
    }
    let indices = cluster::parse_ranges(points, pipeline::sweep::MAX_POINTS)
        .map_err(|e| InputError::arg(format!("--points: {e}")))?;
    let pipeline = pipeline::load_for_points(&p.pipeline, &overrides(p)?, &indices)?;
    // The task's allocation, not the node's cores: a stage's own parallel
    // work would otherwise spread over CPUs Slurm gave to other jobs.
    rayon::ThreadPoolBuilder::new()
        .num_threads(cpus.clamp(1, MAX_THREADS as usize))
        .build_global()
        .context("setting the task's threads")?;
    let started = std::time::Instant::now();
    eprintln!(
        "ltcal task {prefix}: {} points ({points}) of {} on {}",
        indices.len(),
        pipeline.name,
        crate::fs::host_name()
    );
    // A task publishes nothing: the coordinator passes its overrides as
    // `--set`, and publishes to its experiment, if any.
    let opts = run::RunOptions {
        results_root: p.results.clone(),
        keep_going: true,
        progress: false,
        not_computed: None,
        experiment: None,
        control: Default::default(),
    };
    let report = run::run_task(&pipeline, &opts, &indices, cpus, prefix)?;
    for (i, stage, why) in &report.failed {
        eprintln!("point {i}: stage `{stage}` failed: {why}");
    }
    eprintln!(
        "ltcal task {prefix}: {} ran, {} cached, {} failed in {:.1} s; packs: {}",
        report.ran,
        report.cached,
        report.failed.len(),
        started.elapsed().as_secs_f64(),
        report
            .packs
            .iter()
            .map(|p| p.display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
    );
    Ok(if report.failed.is_empty() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// `ltcal snapshot`: runs the pipeline (cached stages cost nothing), then
/// records or checks the `[snapshot]` tables.
fn snapshot_command(p: &PipelineArgs, check: bool, dir: &Path) -> Result<ExitCode> {
    let (pipeline, e) = load_to_run(p)?;
    let snap = snapshot::of(&pipeline).map_err(|e| InputError::arg(e.to_string()))?;
    let report = publish::run(
        &pipeline,
        &run::RunOptions {
            results_root: p.results.clone(),
            keep_going: false,
            progress: false,
            not_computed: None,
            experiment: e.clone(),
            control: Default::default(),
        },
    )?;
    if !report.failed().is_empty() {
        summarize(&report);
        bail!("the pipeline did not complete, so there is nothing to snapshot");
    }
    let tables = snapshot::collect(&pipeline, snap, &report, &store(p, &pipeline, e.as_ref()))?;
    if !check {
        let files = snapshot::record(&pipeline, snap, &tables, dir)?;
        for f in &files {
            println!("recorded {}", f.display());
        }
        return Ok(ExitCode::SUCCESS);
    }
    let checks = snapshot::check(&pipeline, snap, &tables, dir)?;
    print_out(snapshot::Report(&checks).to_string())?;
    let bad = checks
        .iter()
        .filter(|c| !matches!(c.outcome, snapshot::Outcome::Same { .. }))
        .count();
    if bad == 0 {
        println!(
            "snapshot check: {} within tolerance of {}",
            n_tables(checks.len()),
            dir.join(&pipeline.name).display()
        );
        Ok(ExitCode::SUCCESS)
    } else {
        println!(
            "snapshot check: {bad} of {} differ from {}; if the change is intended, record it with `ltcal snapshot {}`",
            n_tables(checks.len()),
            dir.join(&pipeline.name).display(),
            p.pipeline.display()
        );
        Ok(ExitCode::from(1))
    }
}

/// `ltcal runs`: the pipeline's experiments, one a line on stdout, by
/// name: name, status, when its last run finished, its overrides as the
/// `--set` arguments that run it again. Exit 1 when an experiment's record
/// is damaged (listed, with why).
fn runs_command(file: &Path, results: &Path) -> Result<ExitCode> {
    let name = pipeline::name(file)?;
    let listed = experiment::list(&results.join(&name));
    if listed.is_empty() {
        eprintln!(
            "{name}: no experiments in {} (a run with --set makes one)",
            results.join(&name).join(experiment::DIR).display()
        );
        return Ok(ExitCode::SUCCESS);
    }
    let width = |f: fn(&experiment::Listed) -> usize| listed.iter().map(f).max().unwrap_or(0);
    let (wn, ws) = (width(|l| l.name.len()), width(|l| l.status.len()));
    let wf = width(|l| l.finished.as_ref().map_or(1, String::len));
    let mut text = String::new();
    for l in &listed {
        let line = format!(
            "{:wn$}  {:ws$}  {:wf$}  {}",
            l.name,
            l.status,
            l.finished.as_deref().unwrap_or("-"),
            experiment::set_args(&l.overrides)
        );
        text += line.trim_end();
        text += "\n";
    }
    print_out(text)?;
    let damaged: Vec<&experiment::Listed> = listed.iter().filter(|l| l.problem.is_some()).collect();
    for l in &damaged {
        eprintln!(
            "experiment `{}`: {}",
            l.name,
            l.problem.as_deref().unwrap_or_default()
        );
    }
    let damaged = damaged.len();
    Ok(if damaged == 0 {
        ExitCode::SUCCESS
    } else {
        eprintln!(
            "{damaged} experiment record(s) damaged: `ltcal run {} --name <name> --set …` writes one again",
            file.display()
        );
        ExitCode::from(1)
    })
}

/// `ltcal diagnose`: [`pipeline::diagnose::run`] with a spinner, and its
/// verdict printed.
fn diagnose_command(
    campaign: &Path,
    out: &Path,
    stage: stages::diagnose::DiagnoseStage,
) -> Result<ExitCode> {
    let step = step_spinner();
    let d = pipeline::diagnose::run(campaign, out, &stage, &|m| step.set_message(m))?;
    step.finish_and_clear();
    println!("{}", crate::diagnose::output::verdict(&d));
    eprintln!(
        "diagnosis of {} written to {}",
        campaign.display(),
        out.display()
    );
    Ok(ExitCode::SUCCESS)
}

/// A spinner naming the step under way, so a long campaign read or
/// adjustment (200 000 readings take minutes) is not silent. Only on a
/// terminal: hidden when stderr is a pipe or a file, as in tests. (It
/// reports steps, not the adjustment's iterations: those run inside the
/// bundle adjustment, which reports nothing while it works.)
fn step_spinner() -> indicatif::ProgressBar {
    use std::io::IsTerminal as _;
    if !std::io::stderr().is_terminal() {
        return indicatif::ProgressBar::hidden();
    }
    let b = indicatif::ProgressBar::new_spinner();
    b.set_style(
        indicatif::ProgressStyle::with_template("{spinner} {msg} ({elapsed})")
            .expect("a valid template"),
    );
    b.enable_steady_tick(std::time::Duration::from_millis(120));
    b
}

fn n_tables(n: usize) -> String {
    format!("{n} table{}", if n == 1 { "" } else { "s" })
}

/// `ltcal run`'s stages to run and to force.
struct Targets {
    stages: Vec<String>,
    force: Vec<String>,
}

/// `ltcal run`: here, or on Slurm as a coordinator.
fn run_command(
    p: &PipelineArgs,
    targets: &Targets,
    keep_going: bool,
    threads: Option<usize>,
    quiet: bool,
    executor: Executor,
    detach: bool,
) -> Result<ExitCode> {
    let (pipeline, e) = load_to_run(p)?;
    let selection = pipeline::select::Selection::new(&pipeline, &targets.stages, &targets.force)?;
    if let Some(n) = threads {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global()
            .context("setting the number of threads")?;
    }
    // The first Ctrl-C or SIGTERM stops the run (here: nothing starts
    // after it, what is under way finishes and is cached, exit 130; on
    // Slurm: the coordinator cancels its jobs); a second one ends the
    // process as the signal would.
    let interrupted = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register_conditional_default(sig, interrupted.clone())
            .and_then(|_| signal_hook::flag::register(sig, interrupted.clone()))
            .context("watching for Ctrl-C")?;
    }
    let opts = run::RunOptions {
        results_root: p.results.clone(),
        keep_going,
        progress: !quiet,
        not_computed: None,
        experiment: e.clone(),
        control: Arc::new(pipeline::control::Control::with_flag(interrupted.clone())),
    };
    if !quiet {
        say_experiment(e.as_ref());
    }
    if executor == Executor::Local {
        if detach {
            return Err(InputError::arg(
                "--detach submits to a cluster: use it with --executor slurm",
            ));
        }
        say_when_stopping(interrupted);
        let report = publish::run_selected(&pipeline, &opts, &selection)?;
        let code = summarize(&report);
        headlines(p, &report)?;
        return Ok(code);
    }
    if !(targets.stages.is_empty() && targets.force.is_empty()) {
        return Err(InputError::arg(
            "--executor slurm runs the whole pipeline: name no stages and no --force",
        ));
    }
    // The tasks compute with every stage override, recorded ones
    // too (`--name` alone), and the command line's `executor.*`.
    let mut set_args: Vec<String> = e.iter().flat_map(|e| e.overrides.iter().cloned()).collect();
    set_args.extend(
        overrides(p)?.into_iter().filter_map(|o| {
            (o.path.first().map(String::as_str) != Some("stages")).then_some(o.text)
        }),
    );
    let cluster = cluster::ClusterOptions {
        pipeline_file: p.pipeline.clone(),
        set_args,
        detach,
        interrupted,
    };
    match cluster::run(&pipeline, &opts, &cluster, &cluster::slurm::Slurm)? {
        cluster::Outcome::Finished(report) => {
            let code = summarize(&report);
            headlines(p, &report)?;
            Ok(code)
        }
        cluster::Outcome::Detached { jobs, points } => {
            let named = e
                .as_ref()
                .map(|e| format!(" --name {}", e.name))
                .unwrap_or_default();
            eprintln!(
                "{}: {points} points submitted or running as Slurm job {}; \
                 `ltcal status {}{named}` shows where they stand, `ltcal run {}{named} --executor slurm` picks up",
                pipeline.name,
                jobs.join(", "),
                p.pipeline.display(),
                p.pipeline.display()
            );
            Ok(ExitCode::SUCCESS)
        }
    }
}

/// Says on stderr, the moment `flag` is raised, that the run is stopping:
/// the stages under way may take a while to finish.
fn say_when_stopping(flag: Arc<AtomicBool>) {
    std::thread::spawn(move || {
        while !flag.load(std::sync::atomic::Ordering::SeqCst) {
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
        eprintln!(
            "stopping: nothing more starts; the stages and sweep points under way finish \
             and are cached (Ctrl-C again ends at once)"
        );
    });
}

/// `ltcal status`: where a sweep's points and cluster jobs stand.
fn status_command(p: &PipelineArgs) -> Result<ExitCode> {
    let (pipeline, e) = load(p)?;
    say_experiment(e.as_ref());
    if pipeline.sweep.is_none() {
        // No points, no cluster jobs: what a status can still say is
        // where the stages stand — and asking is no failure (exit 1
        // says a stage failed).
        let items = plan::plan(&pipeline, &store(p, &pipeline, e.as_ref()));
        let cached = items.iter().filter(|i| i.status == Status::Cached).count();
        print_out(format!(
            "{}: no [sweep], so no points or cluster jobs; {cached} of {} stages cached \
             (`ltcal plan {}` says which would run and why)\n",
            pipeline.name,
            items.len(),
            p.pipeline.display()
        ))?;
        return Ok(ExitCode::SUCCESS);
    }
    let opts = run::RunOptions {
        results_root: p.results.clone(),
        keep_going: false,
        progress: false,
        not_computed: None,
        experiment: e,
        control: Default::default(),
    };
    print_out(cluster::status(&pipeline, &opts, &cluster::slurm::Slurm)?)?;
    Ok(ExitCode::SUCCESS)
}

/// `ltcal verify`: every cache entry checked, the damaged ones taken out
/// with `--repair`.
fn verify_command(p: &PipelineArgs, repair: bool) -> Result<ExitCode> {
    // The cache is every run's: an experiment's is the pipeline's.
    let (pipeline, _) = load(p)?;
    let store = store(p, &pipeline, None);
    let v = store.verify();
    for why in &v.problems {
        eprintln!("  {why}");
    }
    for why in &v.superseded {
        eprintln!("  (not served: another copy is good) {why}");
    }
    println!(
        "{}: {} loose entries, {} packed entries in {} packs, {} damaged, {} damaged copies superseded",
        pipeline.name,
        v.loose,
        v.packed,
        v.packs,
        v.problems.len(),
        v.superseded.len()
    );
    if v.problems.is_empty() && v.superseded.is_empty() {
        return Ok(ExitCode::SUCCESS);
    }
    if !repair {
        if !v.problems.is_empty() {
            eprintln!(
                "the damaged entries are never served; `ltcal verify --repair {}` (or the \
                 next `ltcal run`) takes them out",
                p.pipeline.display()
            );
            return Ok(ExitCode::from(1));
        }
        return Ok(ExitCode::SUCCESS);
    }
    for h in store.heal(true) {
        println!("repaired {h}");
    }
    let after = store.verify();
    for why in &after.problems {
        eprintln!("  still damaged: {why}");
    }
    Ok(if after.problems.is_empty() {
        println!(
            "{}: the cache is good again; what was taken out is computed again by the next run",
            pipeline.name
        );
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// `ltcal plan`: which stage would run and why.
fn plan_command(p: &PipelineArgs, json: bool, check: bool) -> Result<ExitCode> {
    let (pipeline, e) = load(p)?;
    let items = plan::plan(&pipeline, &store(p, &pipeline, e.as_ref()));
    if json {
        print_out(format!("{}\n", serde_json::to_string_pretty(&items)?))?;
    } else {
        let width = items.iter().map(|i| i.stage.len()).max().unwrap_or(0);
        let mut text = String::new();
        for i in &items {
            let reason = if i.reason.is_empty() {
                String::new()
            } else {
                format!("  {}", i.reason)
            };
            let line = format!("{:>6}  {:width$}  {:9}{reason}", i.status, i.stage, i.kind);
            text += line.trim_end();
            text += "\n";
        }
        print_out(text)?;
    }
    let stale = items.iter().filter(|i| i.status != Status::Cached).count();
    if check && stale > 0 {
        eprintln!("plan --check: {stale} of {} stages would run", items.len());
        return Ok(ExitCode::from(1));
    }
    Ok(ExitCode::SUCCESS)
}

fn dispatch(cli: Cli) -> Result<ExitCode> {
    match cli.command {
        Command::Run {
            p,
            stages,
            force,
            keep_going,
            threads,
            quiet,
            executor,
            detach,
        } => run_command(
            &p,
            &Targets { stages, force },
            keep_going,
            threads,
            quiet,
            executor,
            detach,
        ),
        Command::Status { p } => status_command(&p),
        Command::Verify { p, repair } => verify_command(&p, repair),
        Command::Task {
            p,
            points,
            code,
            pipeline_hash,
            prefix,
            cpus,
        } => task_command(&p, &points, &code, &pipeline_hash, &prefix, cpus),
        Command::Plan { p, json, check } => plan_command(&p, json, check),
        Command::Explain {
            p,
            stage,
            point,
            json,
        } => {
            let (pipeline, e) = load(&p)?;
            let e = explain::explain(&pipeline, &store(&p, &pipeline, e.as_ref()), &stage, point)?;
            if json {
                print_out(format!("{}\n", serde_json::to_string_pretty(&e)?))?;
            } else {
                print_out(e.to_string())?;
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::Graph { p, format } => {
            let (pipeline, e) = load(&p)?;
            let statuses: graph::Statuses =
                plan::plan(&pipeline, &store(&p, &pipeline, e.as_ref()))
                    .into_iter()
                    .map(|i| (i.stage, i.status))
                    .collect();
            print_out(match format {
                GraphFormat::Dot => graph::dot(&pipeline, &statuses),
                GraphFormat::Mermaid => graph::mermaid(&pipeline, &statuses),
                GraphFormat::Svg => graph::svg(&pipeline, &statuses)?,
            })?;
            Ok(ExitCode::SUCCESS)
        }
        Command::Snapshot { p, check, dir } => snapshot_command(&p, check, &dir),
        Command::Runs { pipeline, results } => runs_command(&pipeline, &results),
        Command::Show {
            p,
            table,
            format,
            limit,
            digits,
        } => show(&p, &table, format, limit, digits),
        Command::Diagnose {
            campaign,
            out,
            effects,
            folds,
            mc_draws,
            seed,
            model,
            hypotheses,
        } => diagnose_command(
            &campaign,
            &out,
            stages::diagnose::DiagnoseStage {
                model,
                effects,
                folds,
                mc_draws,
                seed,
                hypotheses,
                ..Default::default()
            },
        ),
        Command::Gc {
            pipelines,
            results,
            dry_run,
        } => gc_command(&pipelines, &results, dry_run),
        Command::Kinds { kind: Some(kind) } => kind_command(&kind),
        Command::Kinds { kind: None } => {
            let kinds: String = stages::summaries()
                .into_iter()
                .map(|(k, s)| format!("{k:10}  {s}\n"))
                .collect();
            print_out(kinds)?;
            Ok(ExitCode::SUCCESS)
        }
        Command::Completions { shell } => {
            // Generated from the same definition clap parses with, so the
            // completions cannot fall behind the commands.
            let mut script = Vec::new();
            clap_complete::generate(shell, &mut Cli::command(), "ltcal", &mut script);
            print_out(script)?;
            Ok(ExitCode::SUCCESS)
        }
    }
}

/// Every `*.toml` below `dir`, sorted, folders recursively (links not
/// followed).
fn toml_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let Ok(t) = e.file_type() else { continue };
            let path = e.path();
            if t.is_dir() {
                todo.push(path);
            } else if t.is_file() && path.extension().is_some_and(|x| x == "toml") {
                out.push(path);
            }
        }
    }
    out.sort();
    out
}

/// The results folder a pipeline file that does not load may name: its
/// `[pipeline] name`, else its stem — `None` for TOML with neither
/// `[pipeline]` nor `[stages]` (a hypothesis file), which is no pipeline.
fn claimed_folder(file: &Path) -> Option<String> {
    let stem = || Some(file.file_stem()?.to_string_lossy().into_owned());
    let Ok(text) = crate::fs::read_regular_file(file, pipeline::MAX_FILE_BYTES) else {
        return stem();
    };
    match toml::from_str::<toml::Table>(&String::from_utf8_lossy(&text)) {
        Err(_) => stem(),
        Ok(t) if !t.contains_key("pipeline") && !t.contains_key("stages") => None,
        Ok(t) => match t.get("pipeline").and_then(|p| p.get("name")) {
            Some(toml::Value::String(n)) => Some(n.clone()),
            _ => stem(),
        },
    }
}

/// `ltcal gc`: per results folder a pipeline names, what nothing reaches
/// removed (listed on stdout with sizes; with `--dry-run`, only listed).
/// A folder is collected only when every pipeline file naming it loads:
/// otherwise what a broken file would reach is unknown, and nothing goes.
fn gc_command(files: &[PathBuf], results: &Path, dry_run: bool) -> Result<ExitCode> {
    use std::collections::BTreeMap;
    let discovered = files.is_empty();
    let files = if discovered {
        let dir = results.parent().unwrap_or(Path::new("")).join("pipelines");
        toml_files(&dir)
    } else {
        files.to_vec()
    };
    // Folder name → the pipelines reaching it (`None`: one did not load).
    let mut folders: BTreeMap<String, Option<Vec<pipeline::resolve::Pipeline>>> = BTreeMap::new();
    for file in &files {
        match pipeline::load(file, &[]) {
            Ok(p) => {
                let pdir = results.join(&p.name);
                let mut all = vec![];
                for name in experiment::names(&pdir) {
                    // An experiment whose overrides no longer apply keeps
                    // what its records name.
                    match pipeline::load_target(file, &[], Some(&name), results) {
                        Ok((e, _)) => all.push(e),
                        Err(why) => eprintln!(
                            "note: experiment `{name}` of {} no longer loads ({}); its recorded \
                             runs are kept",
                            file.display(),
                            why.to_string().lines().next().unwrap_or_default()
                        ),
                    }
                }
                let name = p.name.clone();
                all.push(p);
                if let Some(Some(v)) = folders.get_mut(&name) {
                    v.extend(all);
                } else {
                    folders.entry(name).or_insert(Some(all));
                }
            }
            Err(e) if !discovered => return Err(e),
            // Not a pipeline (a hypothesis file), or a broken one: its
            // folder, if it names one, is not collected.
            Err(_) => {
                if let Some(name) = claimed_folder(file) {
                    if results.join(&name).join(".ltcal").is_dir() {
                        eprintln!(
                            "note: {} does not load: results/{name} is not collected",
                            file.display()
                        );
                    }
                    folders.insert(name, None);
                }
            }
        }
    }
    let (mut removed, mut freed) = (0, 0);
    let mut text = String::new();
    for (name, pipelines) in &folders {
        let Some(pipelines) = pipelines else { continue };
        let pdir = results.join(name);
        if !pdir.join(".ltcal").is_dir() {
            continue;
        }
        let store = Store::new(&pdir);
        let reach = pipeline::gc::reachable(pipelines, &store, &pdir);
        let c = pipeline::gc::collect(&store, &reach, dry_run)?;
        for item in &c.removed {
            text += &format!(
                "{:>10}  {}  {}\n",
                pipeline::gc::human_bytes(item.bytes),
                item.path.display(),
                item.what
            );
        }
        for (path, why) in &c.unreadable {
            eprintln!(
                "note: pack {} cannot be read ({why}): left to `ltcal verify --repair`",
                path.display()
            );
        }
        let partly: usize = c.partly.iter().map(|(_, n, _)| n).sum();
        eprintln!(
            "{name}: {} {} ({}); kept {} entries and {} packs ({}){}",
            if dry_run { "would remove" } else { "removed" },
            c.removed.len(),
            pipeline::gc::human_bytes(c.freed()),
            c.kept_entries,
            c.kept_packs,
            pipeline::gc::human_bytes(c.kept_bytes),
            if partly == 0 {
                String::new()
            } else {
                format!(
                    ", {partly} unreachable entries among them in {} packs that also hold reachable ones",
                    c.partly.len()
                )
            }
        );
        removed += c.removed.len();
        freed += c.freed();
    }
    print_out(text)?;
    eprintln!(
        "gc: {removed} entries and packs, {} ({freed} bytes) {}",
        pipeline::gc::human_bytes(freed),
        if dry_run {
            "would be freed (--dry-run: nothing removed)"
        } else {
            "freed"
        }
    );
    Ok(ExitCode::SUCCESS)
}

/// `ltcal kinds <kind>`: the kind's settings, one a line, from the
/// deserializer that validates them ([`stages::settings`]).
fn kind_command(kind: &str) -> Result<ExitCode> {
    let Some(settings) = stages::settings::settings(kind) else {
        return Err(InputError::arg(format!(
            "unknown stage kind `{kind}`; one of: {}{}",
            stages::KINDS.join(", "),
            crate::suggest::hint(kind, stages::KINDS.iter().copied())
        )));
    };
    let summary = stages::summaries()
        .into_iter()
        .find(|(k, _)| *k == kind)
        .map_or("", |(_, s)| s);
    let w = |f: fn(&stages::settings::Setting) -> usize, head: usize| {
        settings.iter().map(f).max().unwrap_or(0).max(head)
    };
    let (wn, wk, wd) = (
        w(|s| s.name.len(), 7),
        w(|s| s.kind.len(), 4),
        w(|s| s.default.chars().count(), 7),
    );
    let wu = w(|s| s.unit.chars().count(), 4);
    let mut text = format!(
        "{kind}: {summary}\n\n{:wn$}  {:wk$}  {:wd$}  {:wu$}  meaning\n",
        "setting", "type", "default", "unit"
    );
    if settings.is_empty() {
        text += "(no settings)\n";
    }
    // The meaning wraps within 100 columns, continued under itself.
    let indent = wn + wk + wd + wu + 8;
    let width = 100usize.saturating_sub(indent).max(40);
    let pad = |t: &str, w: usize| format!("{t}{}", " ".repeat(w - t.chars().count()));
    for s in &settings {
        let mut lines = wrap(&s.doc, width).into_iter();
        let line = format!(
            "{}  {}  {}  {}  {}",
            pad(&s.name, wn),
            pad(&s.kind, wk),
            pad(&s.default, wd),
            pad(s.unit, wu),
            lines.next().unwrap_or_default()
        );
        text += line.trim_end();
        text += "\n";
        for more in lines {
            text += &format!("{}{more}\n", " ".repeat(indent));
        }
    }
    print_out(text)?;
    Ok(ExitCode::SUCCESS)
}

/// `text`'s words in lines of at most `width` characters (a longer word
/// alone on its line).
fn wrap(text: &str, width: usize) -> Vec<String> {
    let mut lines: Vec<String> = Vec::new();
    for word in text.split_whitespace() {
        match lines.last_mut() {
            Some(l) if l.chars().count() + 1 + word.chars().count() <= width => {
                l.push(' ');
                l.push_str(word);
            }
            _ => lines.push(word.to_string()),
        }
    }
    lines
}

/// `ltcal show`: a published table, checked against the cache entry it
/// came from, so that an edited or damaged file or a stale result is never
/// shown as current.
fn show(
    p: &PipelineArgs,
    table: &str,
    format: ShowFormat,
    limit: Option<usize>,
    digits: usize,
) -> Result<ExitCode> {
    let (pipeline, e) = load(p)?;
    say_experiment(e.as_ref());
    let dir = run::results_dir(&p.results, &pipeline, e.as_ref());
    let (stage, name) = match table.split_once('.') {
        Some((s, t)) => (s, Some(t)),
        None => (table, None),
    };
    let rerun = rerun(p, e.as_ref());
    let store = store(p, &pipeline, e.as_ref());
    let published = published::read(&pipeline, &store, &dir, stage, name, &rerun)?;
    if let Some(why) = &published.stale {
        eprintln!("note: this table is from an earlier run; {why}: run {rerun}");
    }
    let (path, bytes) = (published.path, published.bytes);
    let df = table::from_parquet_bytes(&bytes).with_context(|| {
        format!(
            "{} is not a readable table: {rerun} restores it",
            path.display()
        )
    })?;
    let rows = df.height();
    let df = match limit {
        Some(n) if n < rows => df.head(Some(n)),
        _ => df,
    };
    match format {
        ShowFormat::Table => {
            print_out(table::to_text(&df, digits))?;
            if df.height() < rows {
                eprintln!(
                    "({} of {rows} rows not shown: --limit {})",
                    rows - df.height(),
                    df.height()
                );
            }
        }
        ShowFormat::Csv => print_out(table::to_csv(&df)?)?,
        ShowFormat::Json => print_out(table::to_json(&df))?,
    }
    Ok(ExitCode::SUCCESS)
}

/// Writes to standard output; a closed pipe (`ltcal show … | head`) ends
/// the output quietly instead of panicking as `print!` does.
fn print_out(text: impl AsRef<[u8]>) -> Result<()> {
    use std::io::Write;
    match std::io::stdout().lock().write_all(text.as_ref()) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e.into()),
        _ => Ok(()),
    }
}
