//! The command line: `ltcal run`, `plan`, `show`, `kinds`.

use crate::pipeline::{self, InputError, plan, resolve::Override, run};
use crate::stages;
use crate::table;
use anyhow::{Context as _, Result, bail};
use clap::{Args, Parser, Subcommand};
use std::path::PathBuf;
use std::process::ExitCode;

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
    #[arg(long = "set", value_name = "PATH=VALUE")]
    set: Vec<String>,
    /// The folder that holds every pipeline's results.
    #[arg(long, default_value = "results")]
    results: PathBuf,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run a pipeline: every stage whose result is not cached.
    Run {
        #[command(flatten)]
        p: PipelineArgs,
        /// Run every stage whose inputs exist even after a failure.
        #[arg(long)]
        keep_going: bool,
        /// Worker threads (default: all cores).
        #[arg(short = 'j', long)]
        threads: Option<usize>,
        /// No per-stage lines.
        #[arg(short, long)]
        quiet: bool,
    },
    /// Print what `run` would do and why, without running anything.
    Plan {
        #[command(flatten)]
        p: PipelineArgs,
    },
    /// Print a result table: `<stage>` (its first table) or `<stage>.<table>`.
    Show {
        #[command(flatten)]
        p: PipelineArgs,
        table: String,
        /// Decimal places of numbers.
        #[arg(long, default_value_t = 6)]
        digits: usize,
    },
    /// List the stage kinds.
    Kinds,
}

/// Runs the command line and returns the process exit code: 0 success,
/// 1 a stage failed, 2 the input is wrong.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    match dispatch(cli) {
        Ok(code) => code,
        Err(e) => {
            if let Some(input) = e.downcast_ref::<InputError>() {
                eprintln!("error: {input}");
                ExitCode::from(2)
            } else {
                eprintln!("error: {e:#}");
                ExitCode::from(1)
            }
        }
    }
}

fn load(p: &PipelineArgs) -> Result<pipeline::resolve::Pipeline> {
    let overrides = p
        .set
        .iter()
        .map(|s| Override::parse(s))
        .collect::<Result<Vec<_>>>()
        .map_err(|e| InputError(vec![pipeline::Problem::Arg(e.to_string())]))?;
    pipeline::load(&p.pipeline, &overrides)
}

fn dispatch(cli: Cli) -> Result<ExitCode> {
    match cli.command {
        Command::Run {
            p,
            keep_going,
            threads,
            quiet,
        } => {
            let pipeline = load(&p)?;
            if let Some(n) = threads {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(n.max(1))
                    .build_global()
                    .context("setting the number of threads")?;
            }
            let report = run::run(
                &pipeline,
                &run::RunOptions {
                    results_root: p.results.clone(),
                    keep_going,
                    progress: !quiet,
                },
            )?;
            let (ran, cached) = (report.with_status("ran"), report.with_status("cached"));
            eprintln!(
                "{}: {} ran, {} cached{}; results in {}",
                report.pipeline,
                ran.len(),
                cached.len(),
                match report.failed().len() {
                    0 => String::new(),
                    n => format!(", {n} FAILED"),
                },
                report.results.display()
            );
            let failed = report.failed();
            for f in &failed {
                eprintln!(
                    "\nstage `{}` ({}) failed:\n  {}",
                    f.stage,
                    f.kind,
                    f.reason.replace('\n', "\n  ")
                );
            }
            Ok(if failed.is_empty() {
                ExitCode::SUCCESS
            } else {
                ExitCode::from(1)
            })
        }
        Command::Plan { p } => {
            let pipeline = load(&p)?;
            let store = pipeline::cache::Store::new(&run::pipeline_dir(&p.results, &pipeline));
            let items = plan::plan(&pipeline, &store);
            let width = items.iter().map(|i| i.stage.len()).max().unwrap_or(0);
            for i in &items {
                let reason = if i.reason.is_empty() {
                    String::new()
                } else {
                    format!("  {}", i.reason)
                };
                println!("{:>6}  {:width$}  {:9}{reason}", i.status, i.stage, i.kind);
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::Show { p, table, digits } => {
            let pipeline = load(&p)?;
            let (stage, name) = match table.split_once('.') {
                Some((s, t)) => (s.to_string(), Some(t.to_string())),
                None => (table.clone(), None),
            };
            let Some(s) = pipeline.stages.iter().find(|s| s.name == stage) else {
                bail!("the pipeline has no stage `{stage}`");
            };
            let name = name.unwrap_or_else(|| s.config.outputs()[0].to_string());
            let path = run::pipeline_dir(&p.results, &pipeline)
                .join(&stage)
                .join(format!("{name}.parquet"));
            let df = table::read_parquet(&path).with_context(|| {
                format!(
                    "no result yet: run `ltcal run {}` first",
                    p.pipeline.display()
                )
            })?;
            print!("{}", table::to_text(&df, digits));
            Ok(ExitCode::SUCCESS)
        }
        Command::Kinds => {
            for (k, s) in stages::summaries() {
                println!("{k:10}  {s}");
            }
            Ok(ExitCode::SUCCESS)
        }
    }
}
