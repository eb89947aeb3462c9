//! `[executor.slurm]`: how a pipeline's sweep goes out to a Slurm cluster.
//!
//! ```toml
//! [executor.slurm]
//! partition = "compute"           # sbatch --partition (the cluster's default if absent)
//! account = "metrology"           # sbatch --account
//! time_limit = "2:00:00"          # sbatch --time, per task, as Slurm reads it
//! memory_mb = 4000                # sbatch --mem, per task
//! cpus_per_task = 1               # sbatch --cpus-per-task; a task runs this many points at once
//! points_per_task = 50            # sweep points one array task runs
//! max_running = 100               # array tasks running at once (sbatch --array=…%N)
//! sbatch_options = ["--qos=long"] # anything else, one option per string
//! poll_seconds = 5                # how often the coordinator asks Slurm (squeue)
//! ```
//!
//! Every field can be set from the command line as well:
//! `--set executor.slurm.points_per_task=200`.

use serde::{Deserialize, Serialize};

/// The settings as written and overridden: every field has a default.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SlurmSettings {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub partition: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub account: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_limit: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub memory_mb: Option<u64>,
    #[serde(default = "one")]
    pub cpus_per_task: u32,
    #[serde(default = "default_points_per_task")]
    pub points_per_task: usize,
    #[serde(default = "default_max_running")]
    pub max_running: usize,
    #[serde(default)]
    pub sbatch_options: Vec<String>,
    #[serde(default = "default_poll_seconds")]
    pub poll_seconds: f64,
}

fn one() -> u32 {
    1
}

/// A task's fixed cost (Slurm starting it, ltcal loading the pipeline) is
/// about a second; 50 points of a few milliseconds to seconds each keep
/// it small while leaving hundreds of tasks to spread over the nodes of a
/// 10 000-point sweep. Cheap points want more (README: "Running on a
/// cluster").
fn default_points_per_task() -> usize {
    50
}

/// What clusters commonly allow one user without complaint.
fn default_max_running() -> usize {
    100
}

/// One `squeue` per job a few seconds apart is a load no controller
/// notices.
fn default_poll_seconds() -> f64 {
    5.0
}

impl Default for SlurmSettings {
    fn default() -> Self {
        serde_json::from_value(serde_json::json!({})).expect("every field has a default")
    }
}

impl SlurmSettings {
    /// What is wrong with the settings, field by field.
    pub fn problems(&self) -> Vec<String> {
        let mut out = Vec::new();
        if !(1..=1024).contains(&self.cpus_per_task) {
            out.push("`cpus_per_task` must be 1 … 1024".to_string());
        }
        if self.points_per_task == 0 {
            out.push("`points_per_task` must be at least 1".to_string());
        }
        if self.max_running == 0 {
            out.push("`max_running` must be at least 1".to_string());
        }
        if !(self.poll_seconds.is_finite() && (1.0..=600.0).contains(&self.poll_seconds)) {
            out.push("`poll_seconds` must be between 1 and 600".to_string());
        }
        let plain = |s: &str| {
            !s.is_empty()
                && s.chars()
                    .all(|c| c.is_ascii_graphic() && c != '\'' && c != '"')
        };
        for (name, v) in [
            ("partition", &self.partition),
            ("account", &self.account),
            ("time_limit", &self.time_limit),
        ] {
            if let Some(v) = v {
                if !plain(v) {
                    out.push(format!(
                        "`{name}` = {v:?}: a Slurm name has no spaces or quotes"
                    ));
                }
            }
        }
        for o in &self.sbatch_options {
            if !o.starts_with("--") || o.contains('\n') || o.contains('\r') {
                out.push(format!(
                    "`sbatch_options` entry {o:?} is not one long option (`--name=value`) on one line"
                ));
            }
            if o.starts_with("--array") || o.starts_with("--output") || o.starts_with("--error") {
                out.push(format!(
                    "`sbatch_options` entry {o:?}: ltcal sets the array and the logs itself"
                ));
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_and_problems() {
        let s = SlurmSettings::default();
        assert_eq!(
            (s.points_per_task, s.max_running, s.cpus_per_task),
            (50, 100, 1)
        );
        assert!(s.problems().is_empty());
        let bad = SlurmSettings {
            points_per_task: 0,
            partition: Some("a b".into()),
            sbatch_options: vec!["--array=1-3".into(), "-p x".into()],
            ..s
        };
        let p = bad.problems();
        assert_eq!(p.len(), 4, "{p:?}");
    }
}
