//! `--set path=value` and a sweep axis's values: a change to the settings
//! as written, at a dotted path. A leaf of `pipeline/`, read by the sweep's
//! expansion, by resolution and by experiments alike.

use crate::diagnostics::{Problem, Source};
use anyhow::{Result, anyhow, bail};
use serde::Deserialize;
use std::ops::Range;

/// One `--set path=value`: `path` is dotted (`stages.measure.seed`), with
/// double quotes around a segment that contains dots; `value` is a TOML
/// value, or a bare word taken as a string.
#[derive(Clone, Debug, PartialEq)]
pub struct Override {
    pub path: Vec<String>,
    pub value: serde_json::Value,
    /// As the user typed it, for messages.
    pub text: String,
    /// A sweep axis's `path` in the pipeline file; `None` for `--set`.
    pub origin: Option<Range<usize>>,
}

impl Override {
    pub fn parse(arg: &str) -> Result<Override> {
        let (path, value) = arg.split_once('=').ok_or_else(|| {
            anyhow!("--set {arg}: expected path=value, e.g. stages.measure.seed=3")
        })?;
        let path = split_path(path.trim())
            .ok_or_else(|| anyhow!("--set {arg}: `{}` is not a dotted path", path.trim()))?;
        let value = value.trim();
        let value = toml::de::ValueDeserializer::parse(value)
            .ok()
            .and_then(|d| serde_json::Value::deserialize(d).ok())
            .unwrap_or_else(|| serde_json::Value::String(value.to_string()));
        Ok(Override {
            path,
            value,
            text: arg.to_string(),
            origin: None,
        })
    }

    /// `--set <text>` or `sweep axis <text>`, for messages.
    pub(super) fn name(&self) -> String {
        match self.origin {
            Some(_) => format!("sweep axis `{}`", self.text),
            None => format!("--set {}", self.text),
        }
    }

    /// A problem with this override: at the sweep axis in the file, or
    /// naming the `--set` argument.
    pub(super) fn problem(&self, src: &Source, message: impl std::fmt::Display) -> Problem {
        let message = format!("{}: {message}", self.name());
        match &self.origin {
            Some(span) => Problem::At(src.error(span.clone(), message)),
            None => Problem::arg(message),
        }
    }

    /// The path after `stages.<name>.`, when it targets that stage.
    pub(super) fn within(&self, stage: &str) -> Option<&[String]> {
        match self.path.as_slice() {
            [s, name, rest @ ..] if s == "stages" && name == stage => Some(rest),
            _ => None,
        }
    }
}

/// Splits `a.b."c.d"` into `["a", "b", "c.d"]`.
pub fn split_path(p: &str) -> Option<Vec<String>> {
    let mut out = Vec::new();
    let mut cur = String::new();
    let mut quoted = false;
    for c in p.chars() {
        match c {
            '"' => quoted = !quoted,
            '.' if !quoted => out.push(std::mem::take(&mut cur)),
            _ => cur.push(c),
        }
    }
    out.push(cur);
    (!quoted && out.iter().all(|s| !s.is_empty())).then_some(out)
}

pub(super) fn get_path<'a>(
    root: &'a serde_json::Value,
    path: &[String],
) -> Option<&'a serde_json::Value> {
    path.iter().try_fold(root, |v, k| v.get(k))
}

/// Sets `value` at `path` inside a JSON object, creating objects on the way.
pub fn set_path(
    root: &mut serde_json::Value,
    path: &[String],
    value: serde_json::Value,
) -> Result<()> {
    let Some((last, parents)) = path.split_last() else {
        bail!("empty path");
    };
    let mut cur = root;
    for p in parents {
        if cur.get(p).is_none_or(|v| v.is_null()) {
            cur[p] = serde_json::json!({});
        }
        cur = cur
            .get_mut(p)
            .filter(|v| v.is_object())
            .ok_or_else(|| anyhow!("`{p}` is not a table"))?;
    }
    match cur {
        serde_json::Value::Object(m) => {
            m.insert(last.clone(), value);
            Ok(())
        }
        _ => bail!("cannot set `{last}` inside a value that is not a table"),
    }
}
