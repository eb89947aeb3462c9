//! Errors that point into the user's file: `pipeline.toml:14:9`, the line,
//! and a caret under the offending text.
//!
//! Every file ltcal reads from a user — a pipeline file, a campaign's files —
//! reports its mistakes the same way, through [`SourceError`], and collects
//! them as [`Problem`]s so that all of them are shown at once. Knowing
//! nothing of what the files mean, this module sits below both the domain
//! (campaign reading) and the runner (pipeline files).

use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// A file the user wrote, kept whole so that any later error can quote it.
#[derive(Clone, Debug)]
pub struct Source {
    pub path: PathBuf,
    pub text: Arc<str>,
}

impl Source {
    pub fn new(path: impl Into<PathBuf>, text: impl Into<Arc<str>>) -> Source {
        Source {
            path: path.into(),
            text: text.into(),
        }
    }

    /// 1-based line and column (in characters) of a byte offset.
    pub fn line_col(&self, offset: usize) -> (usize, usize) {
        let offset = offset.min(self.text.len());
        let before = &self.text[..offset];
        let line = before.matches('\n').count() + 1;
        let line_start = before.rfind('\n').map(|i| i + 1).unwrap_or(0);
        let col = self.text[line_start..offset].chars().count() + 1;
        (line, col)
    }

    /// An error located at `span` in this file.
    pub fn error(&self, span: Range<usize>, message: impl Into<String>) -> SourceError {
        SourceError {
            source: self.clone(),
            span,
            message: message.into(),
        }
    }
}

/// An error at a place in a user's file.
#[derive(Clone, Debug)]
pub struct SourceError {
    pub source: Source,
    pub span: Range<usize>,
    pub message: String,
}

impl SourceError {
    pub fn line_col(&self) -> (usize, usize) {
        self.source.line_col(self.span.start)
    }

    /// `path:line:col`, the form editors and terminals jump to.
    pub fn location(&self) -> String {
        let (l, c) = self.line_col();
        format!("{}:{l}:{c}", self.source.path.display())
    }
}

impl fmt::Display for SourceError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (line, col) = self.line_col();
        let text = &self.source.text;
        let start = self.span.start.min(text.len());
        let line_start = text[..start].rfind('\n').map(|i| i + 1).unwrap_or(0);
        let line_end = text[start..]
            .find('\n')
            .map(|i| start + i)
            .unwrap_or(text.len());
        let line_text = text[line_start..line_end].trim_end_matches('\r');
        let end = self.span.end.clamp(start, line_end);
        let width = text[start..end].chars().count().max(1);
        let gutter = line.to_string().len();
        writeln!(f, "{}", self.message)?;
        writeln!(
            f,
            "{:gutter$}--> {}:{line}:{col}",
            "",
            self.source.path.display()
        )?;
        writeln!(f, "{:gutter$} |", "")?;
        writeln!(f, "{line} | {line_text}")?;
        write!(
            f,
            "{:gutter$} | {}{}",
            "",
            " ".repeat(col - 1),
            "^".repeat(width)
        )
    }
}

impl std::error::Error for SourceError {}

/// A toml error turned into one that points into the file; `fallback` is
/// where it points when toml knows no place.
pub fn toml_error(src: &Source, e: toml::de::Error, fallback: Range<usize>) -> SourceError {
    let span = e.span().unwrap_or(fallback);
    src.error(span, crate::suggest::serde_message(e.message().trim()))
}

/// One problem with what the user gave ltcal.
#[derive(Clone, Debug)]
pub enum Problem {
    /// At a place in one of the user's files.
    At(SourceError),
    /// About a whole file or folder (`path`), or, without a path, about a
    /// command-line argument (`--set`): nothing to put a caret under.
    File {
        path: Option<PathBuf>,
        message: String,
    },
}

impl Problem {
    /// About the whole file or folder `path`.
    pub fn file(path: &Path, message: impl Into<String>) -> Problem {
        Problem::File {
            path: Some(path.to_path_buf()),
            message: message.into(),
        }
    }

    /// About a command-line argument, or otherwise without a place.
    pub fn arg(message: impl Into<String>) -> Problem {
        Problem::File {
            path: None,
            message: message.into(),
        }
    }

    /// `path:line:col`, or the path alone for a whole-file problem (empty
    /// for an argument).
    pub fn location(&self) -> String {
        match self {
            Problem::At(e) => e.location(),
            Problem::File { path, .. } => path
                .as_ref()
                .map(|p| p.display().to_string())
                .unwrap_or_default(),
        }
    }

    pub fn message(&self) -> &str {
        match self {
            Problem::At(e) => &e.message,
            Problem::File { message, .. } => message,
        }
    }
}

impl fmt::Display for Problem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Problem::At(e) => write!(f, "{e}"),
            Problem::File {
                path: Some(path),
                message,
            } => write!(f, "{}: {message}", path.display()),
            Problem::File {
                path: None,
                message,
            } => f.write_str(message),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_at_line_and_column_with_a_caret() {
        let src = Source::new("p.toml", "[a]\nx = 1\nstep = 0\n");
        let off = src.text.find("0\n").unwrap();
        let e = src.error(off..off + 1, "step must not be zero");
        assert_eq!(e.location(), "p.toml:3:8");
        let shown = e.to_string();
        assert!(shown.contains("3 | step = 0\n  |        ^"), "{shown}");
    }
}
