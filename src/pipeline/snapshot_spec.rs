//! The `[snapshot]` table resolved: which result tables are recorded, to how
//! many decimals, within which tolerances. Resolved beside the stages
//! (by [`super::resolve`]); recording and checking the tables is
//! [`super::snapshot`]'s, after a run.

use super::names::InputRef;
use super::raw::RawSnapshot;
use crate::diagnostics::{Problem, Source};
use crate::stages::ResolvedConfig;
use std::collections::BTreeMap;
use std::ops::Range;

/// Decimal places of recorded numbers unless `digits` says otherwise.
pub const DEFAULT_DIGITS: usize = 6;
/// Beyond this, decimal text of an `f64` is noise.
const MAX_DIGITS: usize = 15;

/// The resolved `[snapshot]` table.
#[derive(Clone, Debug)]
pub struct Snapshot {
    pub tables: Vec<InputRef>,
    pub digits: usize,
    /// Column → absolute tolerance.
    pub tolerance: BTreeMap<String, f64>,
    pub default_tolerance: f64,
    /// Where each `tolerance` column is named in the file.
    pub tolerance_spans: BTreeMap<String, Range<usize>>,
}

impl Snapshot {
    pub fn tolerance_of(&self, column: &str) -> f64 {
        self.tolerance
            .get(column)
            .copied()
            .unwrap_or(self.default_tolerance)
    }
}

/// Resolves `[snapshot]` against the resolved stages (name, settings).
pub fn resolve(
    src: &Source,
    raw: &RawSnapshot,
    header: Range<usize>,
    stages: &[(&str, &ResolvedConfig)],
) -> Result<Snapshot, Vec<Problem>> {
    let mut problems = Vec::new();
    let mut err = |span: Range<usize>, msg: String| {
        problems.push(Problem::At(src.error(span, format!("[snapshot]: {msg}"))));
    };
    if raw.tables.is_empty() {
        err(
            header.clone(),
            "`tables` lists no table; name some, e.g. tables = [\"evaluate.summary\"]".into(),
        );
    }
    let mut tables: Vec<InputRef> = Vec::new();
    for t in &raw.tables {
        let span = t.span();
        let (stage, table) = match t.get_ref().split_once('.') {
            Some((s, t)) => (s, Some(t)),
            None => (t.get_ref().as_str(), None),
        };
        let Some((_, config)) = stages.iter().find(|(name, _)| *name == stage) else {
            let names: Vec<&str> = stages.iter().map(|(name, _)| *name).collect();
            err(
                span,
                format!(
                    "`{}` names no stage `{stage}`; the stages are: {}{}",
                    t.get_ref(),
                    names.join(", "),
                    crate::suggest::hint(stage, names.iter().copied())
                ),
            );
            continue;
        };
        let outputs = config.outputs();
        let table = table.unwrap_or(outputs[0]);
        if !outputs.contains(&table) {
            err(
                span,
                format!(
                    "stage `{stage}` ({}) has no table `{table}`; its tables are: {}{}",
                    config.kind(),
                    outputs.join(", "),
                    crate::suggest::hint(table, outputs.iter().copied())
                ),
            );
            continue;
        }
        let r = InputRef {
            stage: stage.to_string(),
            table: table.to_string(),
        };
        if tables.contains(&r) {
            err(span, format!("`{r}` is listed twice"));
            continue;
        }
        tables.push(r);
    }
    let digits = match &raw.digits {
        Some(d) if *d.get_ref() > MAX_DIGITS => {
            err(
                d.span(),
                format!("`digits` is at most {MAX_DIGITS}: an f64 holds no more"),
            );
            DEFAULT_DIGITS
        }
        Some(d) => *d.get_ref(),
        None => DEFAULT_DIGITS,
    };
    let mut tolerance = BTreeMap::new();
    let mut tolerance_spans = BTreeMap::new();
    let valid = |v: f64| v.is_finite() && v >= 0.0;
    for (col, tol) in &raw.tolerance {
        if !valid(*tol.get_ref()) {
            err(
                tol.span(),
                format!(
                    "the tolerance of `{}` must be a finite number ≥ 0",
                    col.get_ref()
                ),
            );
        }
        tolerance.insert(col.get_ref().clone(), *tol.get_ref());
        tolerance_spans.insert(col.get_ref().clone(), col.span());
    }
    let default_tolerance = match &raw.default_tolerance {
        Some(t) if !valid(*t.get_ref()) => {
            err(
                t.span(),
                "`default_tolerance` must be a finite number ≥ 0".into(),
            );
            0.0
        }
        Some(t) => *t.get_ref(),
        None => 0.0,
    };
    if !problems.is_empty() {
        return Err(problems);
    }
    Ok(Snapshot {
        tables,
        digits,
        tolerance,
        default_tolerance,
        tolerance_spans,
    })
}
