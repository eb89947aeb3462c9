//! What happened, or would happen, to a stage: one closed set of values, so
//! that a misspelt status is a compile error rather than a stage counted
//! nowhere. Written out (`run.json`, `ltcal plan`, the page, the graph) as
//! the lowercase words users have always seen.

use serde::Serialize;
use std::fmt;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// Planned: its cache entry is current and will be reused.
    Cached,
    /// Planned: it would run (no current entry, or a damaged one).
    Run,
    /// After a run: it was computed.
    Ran,
    /// After a run: it was computed and failed.
    Failed,
    /// After a run: not attempted, because a stage it depends on failed.
    Skipped,
}

impl Status {
    pub fn as_str(self) -> &'static str {
        match self {
            Status::Cached => "cached",
            Status::Run => "run",
            Status::Ran => "ran",
            Status::Failed => "failed",
            Status::Skipped => "skipped",
        }
    }
}

impl fmt::Display for Status {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // `pad`, so that widths in format strings (`{:>6}`) apply.
        f.pad(self.as_str())
    }
}

/// Compares with the written-out word, for code that reads a status from
/// `run.json` or holds it as text.
impl PartialEq<&str> for Status {
    fn eq(&self, other: &&str) -> bool {
        self.as_str() == *other
    }
}
