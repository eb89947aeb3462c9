//! What a batch scheduler offers the coordinator ([`Scheduler`]), and the
//! job and task states it speaks in. A leaf: the coordinator
//! ([`super`]) drives any implementation of it, and an implementation
//! ([`super::slurm`]) needs nothing of the coordinator.

use super::settings::SlurmSettings;
use anyhow::Result;
use std::path::Path;

/// One array job to submit.
pub struct ArrayJob<'a> {
    /// The pipeline's name (the job's name is `ltcal-<name>`).
    pub name: &'a str,
    pub tasks: usize,
    pub settings: &'a SlurmSettings,
    /// The working folder tasks start in.
    pub workdir: &'a Path,
    /// The wave's folder: its logs.
    pub wave: &'a Path,
    /// The points file: line `i + 1` is task `i`'s `<first>-<last> <points>`.
    pub units: &'a Path,
    /// `ltcal task …` up to the task's own arguments.
    pub command: Vec<String>,
}

/// A task as the scheduler sees it.
#[derive(Clone, Debug, PartialEq)]
pub struct TaskState {
    pub index: usize,
    /// The scheduler's word (Slurm: `PENDING`, `RUNNING`, `COMPLETED`,
    /// `FAILED`, `CANCELLED`, `TIMEOUT`, `NODE_FAIL`, `PREEMPTED`,
    /// `OUT_OF_MEMORY`, …).
    pub state: String,
    pub node: String,
}

impl TaskState {
    /// Still to run or running.
    pub fn active(&self) -> bool {
        matches!(
            self.state.as_str(),
            "PENDING"
                | "RUNNING"
                | "CONFIGURING"
                | "COMPLETING"
                | "REQUEUED"
                | "REQUEUE_FED"
                | "REQUEUE_HOLD"
                | "RESIZING"
                | "SUSPENDED"
                | "STOPPED"
                | "RESV_DEL_HOLD"
                | "STAGE_OUT"
                | "SIGNALING"
        )
    }

    pub fn pending(&self) -> bool {
        self.state == "PENDING"
    }
}

/// What a batch scheduler offers the coordinator.
pub trait Scheduler {
    fn name(&self) -> &'static str;
    /// The job script of an array job.
    fn script(&self, job: &ArrayJob) -> String;
    /// Submits a job script; returns the job's id.
    fn submit(&self, script: &Path) -> Result<String>;
    /// Every task of `job` the scheduler still knows of; `None` when it
    /// knows nothing of the job any more.
    fn tasks(&self, job: &str) -> Result<Option<Vec<TaskState>>>;
    fn cancel(&self, jobs: &[String]) -> Result<()>;
    /// The name prefix of the packs task `task` of `job` writes (its job
    /// script passes the same to `ltcal task --prefix`).
    fn task_prefix(&self, job: &str, task: usize) -> String;
}
