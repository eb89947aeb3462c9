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
//! [`panics`], followed and stopped from another thread through
//! [`control`]) and writes the page [`report`]; [`explain`] says why a
//! stage would run, [`graph`] draws the stages, [`snapshot`] records and
//! checks result tables, [`published`] reads a published table back and
//! says whether it is current, [`gc`] removes what nothing reaches any
//! more. A run with `--set` is an [`experiment`],
//! published apart from the pipeline's results.

pub mod cache;
pub mod cluster;
pub mod control;
pub mod diagnose;
pub mod error;
pub mod experiment;
pub mod explain;
pub mod gc;
pub mod graph;
pub mod names;
pub mod overrides;
pub mod pack;
pub mod panics;
pub mod plan;
pub mod publish;
pub mod published;
pub mod raw;
pub mod report;
pub mod resolve;
pub mod run;
pub mod run_report;
pub mod select;
pub mod snapshot;
pub mod snapshot_spec;
pub mod status;
pub mod summary;
pub mod sweep;

/// Where [`Source`] was first defined; kept for code written against it.
pub use crate::diagnostics as source;
pub use crate::diagnostics::Problem;
pub use error::{InputError, MAX_FILE_BYTES};
pub use resolve::load_source;

use crate::diagnostics::Source;
use resolve::{Override, Pipeline};
use std::path::Path;

/// Reads, parses and resolves a pipeline file.
pub fn load(path: &Path, overrides: &[Override]) -> anyhow::Result<Pipeline> {
    let src = read(path).map_err(|p| InputError(vec![p]))?;
    load_source(&src, overrides)
}

/// A pipeline file's text. Anything that is not one — missing, a folder, a
/// FIFO or device (which would block or never end), too large, not UTF-8 —
/// is the user's input being wrong, named with the file (and the line and
/// column of the first byte that is not UTF-8).
fn read(path: &Path) -> Result<Source, Problem> {
    use crate::fs::Reason;
    let bytes = crate::fs::read_regular_file(path, MAX_FILE_BYTES).map_err(|e| {
        let why = match &e.reason {
            _ if e.is_missing() => "no such pipeline file".to_string(),
            Reason::NotRegular("a folder") => "a folder, not a pipeline file".to_string(),
            Reason::NotRegular(kind) => {
                format!("not a regular file ({kind}: a FIFO or device is not read)")
            }
            Reason::TooLarge { max_bytes } => {
                format!("larger than {} MiB: not a pipeline file", max_bytes >> 20)
            }
            Reason::Io(err) => format!("cannot be read: {err}"),
        };
        Problem::arg(format!("{}: {why}", path.display()))
    })?;
    String::from_utf8(bytes)
        .map(|text| Source::new(path, text))
        .map_err(|e| {
            // The text up to the bad byte is intact, so its position is
            // exact; the byte itself shows as one replacement character.
            let at = e.utf8_error().valid_up_to();
            let src = Source::new(path, String::from_utf8_lossy(e.as_bytes()).into_owned());
            Problem::At(src.error(
                at..at + char::REPLACEMENT_CHARACTER.len_utf8(),
                "not UTF-8 text: a pipeline file is TOML, which is UTF-8",
            ))
        })
}

/// [`load`] for a command about one run's results (`--name`, `--set`):
/// the pipeline with its overrides, and the experiment it is, if any
/// ([`experiment::target`]) — `--name` alone takes the experiment's
/// recorded overrides, found under `results_root`.
pub fn load_target(
    path: &Path,
    overrides: &[Override],
    name: Option<&str>,
    results_root: &Path,
) -> anyhow::Result<(Pipeline, Option<experiment::Experiment>)> {
    let src = read(path).map_err(|p| InputError(vec![p]))?;
    let raw =
        raw::parse(&src).map_err(|errs| InputError(errs.into_iter().map(Problem::At).collect()))?;
    let pipeline_name = resolve::name_of(&raw);
    let (exp, all) = if raw::valid_name(&pipeline_name) {
        experiment::target(&results_root.join(pipeline_name), name, overrides)?
    } else {
        // Not a folder name: `resolve` says so.
        (None, overrides.to_vec())
    };
    let p = resolve::resolve(&raw, &all).map_err(InputError)?;
    Ok((p, exp))
}

/// The name of the pipeline in `path` (its results folder), from the file
/// as written: nothing is resolved.
pub fn name(path: &Path) -> anyhow::Result<String> {
    let src = read(path).map_err(|p| InputError(vec![p]))?;
    let raw =
        raw::parse(&src).map_err(|errs| InputError(errs.into_iter().map(Problem::At).collect()))?;
    let name = resolve::name_of(&raw);
    if !raw::valid_name(&name) {
        // `resolve` says why, at its place.
        resolve::resolve(&raw, &[]).map_err(InputError)?;
    }
    Ok(name)
}

/// The `[summary]` of the pipeline in `path`, as written (checked as at
/// every load).
pub fn summary(path: &Path) -> anyhow::Result<raw::RawSummary> {
    let src = read(path).map_err(|p| InputError(vec![p]))?;
    let raw =
        raw::parse(&src).map_err(|errs| InputError(errs.into_iter().map(Problem::At).collect()))?;
    Ok(raw.summary)
}

/// [`load`] for a cluster task: of the sweep, only the (increasing) points
/// `points` are resolved at load ([`resolve::resolve_checking`]).
pub fn load_for_points(
    path: &Path,
    overrides: &[Override],
    points: &[usize],
) -> anyhow::Result<Pipeline> {
    let src = read(path).map_err(|p| InputError(vec![p]))?;
    let raw =
        raw::parse(&src).map_err(|errs| InputError(errs.into_iter().map(Problem::At).collect()))?;
    Ok(resolve::resolve_checking(&raw, overrides, Some(points)).map_err(InputError)?)
}
