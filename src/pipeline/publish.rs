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
    let run::Executed {
        report,
        tables,
        verified,
    } = run::execute_pipeline(p, opts, selection)?;
    let dir = &report.results;
    let record = (dir.join("run.json"), serde_json::to_vec_pretty(&report)?);
    let files = report::files(dir, p, &report, &tables);
    // All synced at once (one after another, their syncs were a tenth of a
    // small calibration's process; issue 34): the cache's record of what it
    // found good on a thread of its own (its failure only makes the next run
    // read more), the run's landing in the order they always did: the
    // record, the graph, the page that shows both.
    std::thread::scope(|s| {
        if let Some((path, bytes)) = &verified {
            s.spawn(move || {
                let _ = crate::fs::write_atomic(path, bytes);
            });
        }
        match files {
            Ok([graph, page]) => {
                crate::fs::write_groups_atomic(&[&[record][..], &[graph][..], &[page][..]])
            }
            Err(e) => crate::fs::write_atomic(&record.0, &record.1).and(Err(e)),
        }
    })?;
    Ok(report)
}
