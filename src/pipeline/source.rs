//! Errors that point into the user's file: `pipeline.toml:14:9`, the line,
//! and a caret under the offending text.

use std::fmt;
use std::ops::Range;
use std::path::PathBuf;
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
