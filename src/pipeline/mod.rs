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
//! [`panics`]) and writes the page [`crate::report`]; [`explain`] says why a
//! stage would run, [`graph`] draws the stages, [`snapshot`] records and
//! checks result tables.

pub mod cache;
pub mod explain;
pub mod graph;
pub mod panics;
pub mod plan;
pub mod raw;
pub mod resolve;
pub mod run;
pub mod snapshot;
pub mod source;
pub mod sweep;

use resolve::{Override, Pipeline};
use source::{Source, SourceError};
use std::fmt;
use std::path::Path;

/// One problem with the user's input.
#[derive(Clone, Debug)]
pub enum Problem {
    /// At a place in the pipeline file.
    At(SourceError),
    /// In a command-line argument (`--set`) or otherwise without a place.
    Arg(String),
}

impl fmt::Display for Problem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Problem::At(e) => write!(f, "{e}"),
            Problem::Arg(s) => f.write_str(s),
        }
    }
}

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
        InputError(vec![Problem::Arg(message.into())]).into()
    }
}

/// Reads, parses and resolves a pipeline file.
pub fn load(path: &Path, overrides: &[Override]) -> anyhow::Result<Pipeline> {
    let src = read(path).map_err(|p| InputError(vec![p]))?;
    load_source(&src, overrides)
}

/// The largest pipeline file read: real ones are a few kilobytes.
pub const MAX_FILE_BYTES: u64 = 1 << 20;

/// A pipeline file's text. Anything that is not one — missing, a folder, a
/// FIFO or device (which would block or never end), too large, not UTF-8 —
/// is the user's input being wrong, named with the file (and the line and
/// column of the first byte that is not UTF-8).
fn read(path: &Path) -> Result<Source, Problem> {
    use std::io::Read as _;
    let wrong = |m: &dyn fmt::Display| Problem::Arg(format!("{}: {m}", path.display()));
    let meta = std::fs::metadata(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => wrong(&"no such pipeline file"),
        _ => wrong(&format_args!("cannot be read: {e}")),
    })?;
    if meta.is_dir() {
        return Err(wrong(&"a folder, not a pipeline file"));
    }
    if !meta.is_file() {
        return Err(wrong(&"not a regular file (a FIFO or device is not read)"));
    }
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(MAX_FILE_BYTES + 1).read_to_end(&mut bytes))
        .map_err(|e| wrong(&format_args!("cannot be read: {e}")))?;
    if bytes.len() as u64 > MAX_FILE_BYTES {
        return Err(wrong(&format_args!(
            "larger than {} MiB: not a pipeline file",
            MAX_FILE_BYTES >> 20
        )));
    }
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

pub fn load_source(src: &Source, overrides: &[Override]) -> anyhow::Result<Pipeline> {
    let raw =
        raw::parse(src).map_err(|errs| InputError(errs.into_iter().map(Problem::At).collect()))?;
    Ok(resolve::resolve(&raw, overrides).map_err(InputError)?)
}
