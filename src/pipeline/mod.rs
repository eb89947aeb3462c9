//! Declarative pipelines: TOML files whose stages form a graph, run with a
//! content-addressed Parquet cache.
//!
//! Configuration moves through three layers, and nothing downstream of the
//! first re-reads TOML:
//!
//! 1. [`raw`] — the file as written, with spans, every stage table
//!    deserialized into its kind's typed settings, `[snapshot]` typed;
//! 2. [`resolve`] — `--set` overrides applied, defaults filled in, settings
//!    validated, the graph checked, `[snapshot]` resolved ([`snapshot`]);
//! 3. [`plan`] — execution order, parallel levels and cache keys.
//!
//! [`run`] executes a plan against the [`cache`] (stage panics caught by
//! [`panics`]) and writes the page [`report`]; [`explain`] says why a
//! stage would run, [`graph`] draws the stages, [`snapshot`] records and
//! checks result tables, [`published`] reads a published table back and
//! says whether it is current.

pub mod cache;
pub mod explain;
pub mod graph;
pub mod panics;
pub mod plan;
pub mod published;
pub mod raw;
pub mod report;
pub mod resolve;
pub mod run;
pub mod snapshot;
pub mod status;
pub mod sweep;

/// Where [`Source`] was first defined; kept for code written against it.
pub use crate::diagnostics as source;
pub use crate::diagnostics::Problem;

use crate::diagnostics::Source;
use resolve::{Override, Pipeline};
use std::fmt;
use std::path::Path;

/// The largest pipeline file ltcal reads: hand-written TOML is a few
/// kilobytes; anything near this is not a pipeline file.
const MAX_PIPELINE_BYTES: u64 = 16 << 20;

/// Everything wrong with a pipeline file, reported together.
#[derive(Clone, Debug)]
pub struct InputError(pub Vec<Problem>);

impl fmt::Display for InputError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, p) in self.0.iter().enumerate() {
            if i > 0 {
                writeln!(f, "\n")?;
            }
            write!(f, "{p}")?;
        }
        Ok(())
    }
}

impl std::error::Error for InputError {}

impl InputError {
    /// One mistake in the command line's arguments.
    pub fn arg(message: impl Into<String>) -> anyhow::Error {
        InputError(vec![Problem::arg(message)]).into()
    }
}

/// Reads, parses and resolves a pipeline file.
pub fn load(path: &Path, overrides: &[Override]) -> anyhow::Result<Pipeline> {
    let src = Source::read(path, MAX_PIPELINE_BYTES)?;
    load_source(&src, overrides)
}

pub fn load_source(src: &Source, overrides: &[Override]) -> anyhow::Result<Pipeline> {
    let raw =
        raw::parse(src).map_err(|errs| InputError(errs.into_iter().map(Problem::At).collect()))?;
    Ok(resolve::resolve(&raw, overrides).map_err(InputError)?)
}
