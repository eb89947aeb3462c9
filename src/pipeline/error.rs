//! What is wrong with a user's pipeline file or command line, reported
//! together. A leaf of `pipeline/`: every layer reports through it and it
//! imports none of them.

use crate::diagnostics::Problem;
use std::fmt;

/// The largest pipeline file read: real ones are a few kilobytes.
pub const MAX_FILE_BYTES: u64 = 1 << 20;

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
