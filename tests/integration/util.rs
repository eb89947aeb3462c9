//! Helpers shared by the integration tests.

use ltcal::pipeline::{self, resolve::Override, run};
use polars::prelude::DataFrame;
use std::path::{Path, PathBuf};

/// The repository root (where `pipelines/` lives).
pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

pub fn pipeline_path(name: &str) -> PathBuf {
    root().join("pipelines").join(name)
}

/// Runs a pipeline file into `results`, with `--set` overrides.
pub fn run_pipeline(file: &Path, results: &Path, sets: &[&str]) -> run::RunReport {
    let overrides: Vec<Override> = sets.iter().map(|s| Override::parse(s).unwrap()).collect();
    let p = pipeline::load(file, &overrides).unwrap_or_else(|e| panic!("{e}"));
    let report = ltcal::pipeline::publish::run(
        &p,
        &run::RunOptions {
            results_root: results.to_path_buf(),
            keep_going: false,
            progress: false,
            not_computed: None,
            experiment: None,
            control: Default::default(),
        },
    )
    .unwrap();
    assert!(report.failed().is_empty(), "failed: {:?}", report.failed());
    report
}

/// A published result table.
pub fn table(results: &Path, pipeline: &str, stage: &str, table: &str) -> DataFrame {
    ltcal::table::read_parquet(
        &results
            .join(pipeline)
            .join(stage)
            .join(format!("{table}.parquet")),
    )
    .unwrap()
}

pub fn col(df: &DataFrame, name: &str) -> Vec<f64> {
    ltcal::table::TableRef::new("t", df).f64(name).unwrap()
}

pub fn strs(df: &DataFrame, name: &str) -> Vec<String> {
    ltcal::table::TableRef::new("t", df).str(name).unwrap()
}

/// The value of `column` in the row whose `key` column equals `key`.
pub fn cell(df: &DataFrame, key: &str, value: &str, column: &str) -> f64 {
    let keys = strs(df, key);
    let i = keys
        .iter()
        .position(|k| k == value)
        .unwrap_or_else(|| panic!("no row {key} = {value} in {keys:?}"));
    col(df, column)[i]
}
