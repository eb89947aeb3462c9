//! A run from start to finish: the pipeline executed ([`super::run`]), then
//! its record (`run.json`) and its page ([`super::report`]: `index.html`,
//! `graph.svg`) published beside the stages' folders. Apart from `run` so
//! that executing a plan and showing what it did are layers one way: the
//! runner returns a [`RunReport`] and its tables, and knows nothing of the
//! page.

use super::report;
use super::resolve::Pipeline;
use super::run::{self, RunOptions};
use super::run_report::RunReport;
use super::select::Selection;
use anyhow::Result;

/// Runs the pipeline (and, with a `[sweep]`, every point of it) and
/// publishes its record and page.
pub fn run(p: &Pipeline, opts: &RunOptions) -> Result<RunReport> {
    run_selected(p, opts, &Selection::default())
}

/// [`run`], computing only what `selection` allows (a stage it does not is
/// served if cached, else skipped) and its forced stages even if cached.
pub fn run_selected(p: &Pipeline, opts: &RunOptions, selection: &Selection) -> Result<RunReport> {
    let run::Executed { report, tables } = run::execute_pipeline(p, opts, selection)?;
    let dir = &report.results;
    crate::fs::write_atomic(&dir.join("run.json"), &serde_json::to_vec_pretty(&report)?)?;
    report::write(dir, p, &report, &tables)?;
    Ok(report)
}
