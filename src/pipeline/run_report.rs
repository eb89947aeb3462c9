//! What a run did, stage by stage: the record `run.json` holds, which the
//! page ([`super::report`]) renders, the snapshot check reads and the
//! command line summarises. A type of its own so that rendering a report
//! does not reach into the runner that fills it.

use super::cache;
use super::experiment::Experiment;
use super::names;
use super::status::Status;
use polars::prelude::DataFrame;
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;

/// Stage → table → frame, as a run produced or reused them (a sweep's
/// gathered tables under `sweep`): what the page previews without reading
/// them back.
pub type Tables = BTreeMap<String, BTreeMap<String, Arc<DataFrame>>>;

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
    /// The folder the run published to.
    pub results: PathBuf,
    /// The experiment the run was (a run with `--set`); absent for the
    /// pipeline's own results.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub experiment: Option<Experiment>,
    pub started: String,
    pub finished: String,
    /// Leftovers of killed runs (incomplete entries, temporary files)
    /// removed before this run.
    pub cleaned: usize,
    pub stages: Vec<StageReport>,
    /// For a pipeline with a `[sweep]`.
    pub sweep: Option<SweepReport>,
    /// Packs whose index could not be read, and why: their entries were
    /// not served (and, if needed, recomputed into new packs).
    pub unreadable_packs: Vec<String>,
    /// What was damaged in the cache and taken out after the run
    /// ([`Store::heal`]), so that `ltcal verify` passes again.
    pub healed: Vec<cache::Healed>,
}

impl RunReport {
    /// The run's page, `index.html` in its results folder.
    pub fn page(&self) -> PathBuf {
        self.results.join(names::PAGE)
    }

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
