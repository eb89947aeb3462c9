//! The names a pipeline file and its results folder share: what a stage may
//! be called, the folders beside the stages in `results/<pipeline>/` that
//! no stage may be, and a reference to a stage's table. A leaf of
//! `pipeline/`, so that reading a file (`raw`) and the layers that write
//! those folders (`experiment`, `sweep`, `cluster`) agree without
//! importing each other.

/// The folder below `results/<pipeline>/` that holds the experiments; no
/// stage may have this name ([`RESERVED_STAGE_NAMES`]).
pub const EXPERIMENTS_DIR: &str = "runs";

/// The page of a run's results folder ([`super::report`]).
pub const PAGE: &str = "index.html";

/// The name the gathered tables are read under: `sweep.<stage>.<table>`.
pub const PSEUDO_STAGE: &str = "sweep";

/// The folders ltcal writes beside the stage folders in
/// `results/<pipeline>/`, which no stage's folder may be, and what they hold.
pub const RESERVED_STAGE_NAMES: &[(&str, &str)] = &[
    (EXPERIMENTS_DIR, "the experiments (runs with --set)"),
    (PSEUDO_STAGE, "a sweep's gathered tables"),
    ("slurm", "the cluster's job scripts and logs"),
];

/// A valid stage name: used in file names and references.
pub fn valid_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 64
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

/// Where a stage reads a slot from.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct InputRef {
    pub stage: String,
    pub table: String,
}

impl std::fmt::Display for InputRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}.{}", self.stage, self.table)
    }
}
