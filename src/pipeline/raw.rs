//! Layer 1: the pipeline file as written. Parses the TOML keeping every
//! span, checks its shape (top-level tables, stage names, `kind`,
//! `inputs`), and deserializes each stage table into its kind's typed
//! settings with `deny_unknown_fields` — so that every mistake is reported at
//! its line and column. Nothing after this layer reads TOML.
//!
//! Each top-level table has one arm in [`parse`] and one field in
//! [`RawPipeline`]; a new one (say `[sweep]`) is added the same way and
//! resolved in [`super::resolve`].

use crate::diagnostics::{Source, SourceError, toml_error};
use crate::stages::{KINDS, StageConfig};
use serde::Deserialize;
use std::collections::BTreeMap;
use std::ops::Range;
use toml::Spanned;
use toml::de::{DeTable, DeValue, ValueDeserializer};

/// `[pipeline]`: what the file is.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Meta {
    pub name: Option<Spanned<String>>,
    #[serde(default)]
    pub description: String,
}

/// `[snapshot]`: the result tables `ltcal snapshot` records as text and
/// checks against, with per-column tolerances. Spans are kept so that a
/// table or column that does not exist is reported at its place.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawSnapshot {
    /// `"stage.table"`, or `"stage"` for its first table.
    pub tables: Vec<Spanned<String>>,
    /// Decimal places of the recorded numbers.
    pub digits: Option<Spanned<usize>>,
    /// Column name → absolute tolerance.
    #[serde(default)]
    pub tolerance: BTreeMap<Spanned<String>, Spanned<f64>>,
    /// For columns not in `tolerance`.
    pub default_tolerance: Option<Spanned<f64>>,
}

/// One `[summary]` entry: a headline number, one cell of a result table —
/// `name = { table = "stage.table", column = "c", row = 0 }`, or the row
/// chosen by its values, `where = { statistic = "rms" }`. Printed on stdout
/// after `ltcal run`; part of no stage's cache key (nothing computed
/// depends on it).
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawSummaryItem {
    /// `"stage.table"`, or `"sweep.<stage>.<table>"` for a gathered one.
    pub table: Spanned<String>,
    pub column: Spanned<String>,
    /// The row's index (default 0, or the one row `where` picks).
    pub row: Option<Spanned<usize>>,
    /// Column → value: the one row holding them all.
    #[serde(rename = "where")]
    pub filter: Option<Spanned<BTreeMap<String, toml::Value>>>,
}

/// `[summary]` as written: name → the cell, in file order.
pub type RawSummary = Vec<(Spanned<String>, RawSummaryItem)>;

/// One `inputs` entry: `slot = "stage"` or `slot = "stage.table"`.
#[derive(Clone, Debug)]
pub struct RawInput {
    pub slot: String,
    pub slot_span: Range<usize>,
    pub target: String,
    pub span: Range<usize>,
}

/// One `[stages.<name>]` table.
#[derive(Clone, Debug)]
pub struct RawStage {
    pub name: String,
    /// The span of the stage's name in its header.
    pub span: Range<usize>,
    pub kind: String,
    /// As written: defaults that depend on other settings are not filled in.
    pub config: StageConfig,
    pub inputs: Vec<RawInput>,
    /// Dotted path of every value in the table → its span, so that later
    /// layers can point at a field.
    pub fields: BTreeMap<String, Range<usize>>,
}

/// The whole file.
#[derive(Clone, Debug)]
pub struct RawPipeline {
    pub source: Source,
    pub meta: Meta,
    pub stages: Vec<RawStage>,
    /// With the span of its header, for errors about the table as a whole.
    pub snapshot: Option<(RawSnapshot, Range<usize>)>,
    pub sweep: Option<(super::sweep::RawSweep, Range<usize>)>,
    /// With the span of its header.
    pub executor: Option<(RawExecutor, Range<usize>)>,
    /// The headline numbers, checked against the stages' tables and columns.
    pub summary: RawSummary,
}

const TOP_LEVEL: &[&str] = &[
    "pipeline", "stages", "snapshot", "sweep", "executor", "summary",
];

/// `[executor]`: where the stages run besides this machine.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawExecutor {
    pub slurm: Option<super::cluster::settings::SlurmSettings>,
}

fn key_str<'a>(k: &'a Spanned<std::borrow::Cow<'_, str>>) -> &'a str {
    k.get_ref().as_ref()
}

/// Deserializes a spanned value into `T`, errors located in `src`.
pub(crate) fn typed<'i, T: Deserialize<'i>>(
    src: &Source,
    v: Spanned<DeValue<'i>>,
) -> Result<T, SourceError> {
    let span = v.span();
    T::deserialize(ValueDeserializer::from(v)).map_err(|e| toml_error(src, e, span))
}

/// Records the span of every value under `prefix`.
fn collect_spans(prefix: &str, v: &Spanned<DeValue<'_>>, out: &mut BTreeMap<String, Range<usize>>) {
    out.insert(prefix.to_string(), v.span());
    match v.get_ref() {
        DeValue::Table(t) => {
            for (k, v) in t.iter() {
                collect_spans(&format!("{prefix}.{}", key_str(k)), v, out);
            }
        }
        DeValue::Array(a) => {
            for (i, v) in a.iter().enumerate() {
                collect_spans(&format!("{prefix}.{i}"), v, out);
            }
        }
        _ => {}
    }
}

use super::names::RESERVED_STAGE_NAMES;
pub use super::names::valid_name;

/// Parses a pipeline file. Returns every error found, not only the first.
pub fn parse(src: &Source) -> Result<RawPipeline, Vec<SourceError>> {
    let text = src.text.clone();
    let root = DeTable::parse(&text).map_err(|e| vec![toml_error(src, e, 0..0)])?;
    let root_span = root.span();
    let mut errors = Vec::new();
    let mut meta = Meta::default();
    let mut stages = Vec::new();
    let mut snapshot = None;
    let mut sweep = None;
    let mut executor = None;
    let mut summary = RawSummary::new();
    for (key, value) in root.into_inner() {
        let k = key_str(&key).to_string();
        match k.as_str() {
            "pipeline" => match typed::<Meta>(src, value) {
                Ok(m) => meta = m,
                Err(e) => errors.push(e),
            },
            "snapshot" => {
                let span = key.span();
                match typed::<RawSnapshot>(src, value) {
                    Ok(s) => snapshot = Some((s, span)),
                    Err(mut e) => {
                        e.message = format!("[snapshot]: {}", e.message);
                        errors.push(e)
                    }
                }
            }
            "sweep" => {
                let span = key.span();
                match typed::<super::sweep::RawSweep>(src, value) {
                    Ok(s) => sweep = Some((s, span)),
                    Err(mut e) => {
                        e.message = format!("[sweep]: {}", e.message);
                        errors.push(e)
                    }
                }
            }
            "executor" => {
                let span = key.span();
                match typed::<RawExecutor>(src, value) {
                    Ok(x) => executor = Some((x, span)),
                    Err(mut e) => {
                        e.message = format!("[executor]: {}", e.message);
                        errors.push(e)
                    }
                }
            }
            "summary" => match typed::<BTreeMap<Spanned<String>, RawSummaryItem>>(src, value) {
                Ok(items) => summary = items.into_iter().collect(),
                Err(mut e) => {
                    e.message = format!("[summary]: {}", e.message);
                    errors.push(e)
                }
            },
            "stages" => {
                let span = value.span();
                match value.into_inner() {
                    DeValue::Table(t) => {
                        for (name, body) in t {
                            match parse_stage(src, &name, body) {
                                Ok(s) => stages.push(s),
                                Err(mut e) => errors.append(&mut e),
                            }
                        }
                    }
                    _ => errors.push(src.error(span, "`stages` must be a table of stage tables")),
                }
            }
            _ => errors.push(src.error(
                key.span(),
                format!(
                    "unknown table `{k}`; a pipeline has {}",
                    TOP_LEVEL
                        .iter()
                        .map(|t| format!("`{t}`"))
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            )),
        }
    }
    if stages.is_empty() && errors.is_empty() {
        errors.push(src.error(
            root_span.start..root_span.start,
            "the pipeline has no stages: add at least one `[stages.<name>]` table",
        ));
    }
    if errors.is_empty() {
        summary.sort_by_key(|(name, _)| name.span().start);
        let gathered = sweep.as_ref().map_or_else(Vec::new, |(sw, _)| {
            sw.gather.iter().map(|g| g.get_ref().clone()).collect()
        });
        errors.extend(
            summary
                .iter()
                .filter_map(|(name, item)| check_summary(src, &stages, &gathered, name, item)),
        );
    }
    if !errors.is_empty() {
        errors.sort_by_key(|e| e.span.start);
        return Err(errors);
    }
    // File order, so that reports list stages as the user wrote them.
    stages.sort_by_key(|s| s.span.start);
    Ok(RawPipeline {
        source: src.clone(),
        meta,
        stages,
        snapshot,
        sweep,
        executor,
        summary,
    })
}

/// What is wrong with a `[summary]` entry, at its place: a stage, table or
/// column that does not exist (with the nearest name), `row` with `where`.
fn check_summary(
    src: &Source,
    stages: &[RawStage],
    gathered: &[String],
    name: &Spanned<String>,
    item: &RawSummaryItem,
) -> Option<SourceError> {
    use crate::suggest::hint;
    let at = |s: &Spanned<String>, m: String| {
        Some(src.error(s.span(), format!("[summary] `{}`: {m}", name.get_ref())))
    };
    if !valid_name(name.get_ref()) {
        return at(
            name,
            "a headline number's name may only use letters, digits, `_` and `-`".into(),
        );
    }
    if let (Some(row), Some(_)) = (&item.row, &item.filter) {
        return Some(src.error(
            row.span(),
            format!("[summary] `{}`: `row` or `where`, not both", name.get_ref()),
        ));
    }
    let t = item.table.get_ref();
    if let Some(g) = t.strip_prefix("sweep.") {
        // A gathered table: its columns are the stage's and the axes'.
        if !gathered.iter().any(|x| x == g) {
            return at(
                &item.table,
                format!(
                    "`{t}` is not a gathered table (`[sweep] gather` lists {}){}",
                    gathered
                        .iter()
                        .map(|g| format!("`sweep.{g}`"))
                        .collect::<Vec<_>>()
                        .join(", "),
                    hint(g, gathered.iter().map(String::as_str))
                ),
            );
        }
        return None;
    }
    let Some((stage, table)) = t.split_once('.') else {
        return at(
            &item.table,
            format!("`{t}`: write the table as `stage.table`"),
        );
    };
    let Some(s) = stages.iter().find(|s| s.name == stage) else {
        return at(
            &item.table,
            format!(
                "no stage `{stage}`{}",
                hint(stage, stages.iter().map(|s| s.name.as_str()))
            ),
        );
    };
    let outputs = s.config.outputs();
    if !outputs.contains(&table) {
        return at(
            &item.table,
            format!(
                "stage `{stage}` ({}) writes no table `{table}`; it writes {}{}",
                s.kind,
                outputs
                    .iter()
                    .map(|o| format!("`{o}`"))
                    .collect::<Vec<_>>()
                    .join(", "),
                hint(table, outputs.iter().copied())
            ),
        );
    }
    let column = item.column.get_ref();
    if let Some(cols) = s.config.columns(table) {
        if !cols.contains(&column.as_str()) {
            return at(
                &item.column,
                format!(
                    "`{stage}.{table}` has no column `{column}`{}",
                    hint(column, cols.iter().copied())
                ),
            );
        }
    }
    None
}

fn parse_stage(
    src: &Source,
    name: &Spanned<std::borrow::Cow<'_, str>>,
    body: Spanned<DeValue<'_>>,
) -> Result<RawStage, Vec<SourceError>> {
    let name_str = key_str(name).to_string();
    if !valid_name(&name_str) {
        return Err(vec![src.error(
            name.span(),
            format!(
                "stage name `{name_str}` may only use letters, digits, `_` and `-` (it names files)"
            ),
        )]);
    }
    if let Some(why) = RESERVED_STAGE_NAMES
        .iter()
        .find_map(|(n, why)| (*n == name_str).then_some(why))
    {
        return Err(vec![src.error(
            name.span(),
            format!(
                "a stage cannot be named `{name_str}`: its folder would be \
                 results/<pipeline>/{name_str}/, which holds {why}; rename the stage"
            ),
        )]);
    }
    let body_span = body.span();
    let mut fields = BTreeMap::new();
    let table = match body.into_inner() {
        DeValue::Table(t) => t,
        _ => {
            return Err(vec![src.error(
                body_span,
                format!("stage `{name_str}` must be a table: `[stages.{name_str}]`"),
            )]);
        }
    };
    let mut kind: Option<(String, Range<usize>)> = None;
    let mut inputs = Vec::new();
    let mut errors = Vec::new();
    let mut rest = DeTable::new();
    for (k, v) in table {
        collect_spans(key_str(&k), &v, &mut fields);
        match key_str(&k) {
            "kind" => match v.get_ref().as_str() {
                Some(s) => kind = Some((s.to_string(), v.span())),
                None => errors.push(src.error(v.span(), "`kind` must be a string")),
            },
            "inputs" => match v.get_ref() {
                DeValue::Table(t) => {
                    for (slot, target) in t.iter() {
                        match target.get_ref().as_str() {
                            Some(s) => inputs.push(RawInput {
                                slot: key_str(slot).to_string(),
                                slot_span: slot.span(),
                                target: s.to_string(),
                                span: target.span(),
                            }),
                            None => errors.push(src.error(
                                target.span(),
                                "an input names a stage: `\"stage\"` or `\"stage.table\"`",
                            )),
                        }
                    }
                }
                _ => errors.push(src.error(
                    v.span(),
                    "`inputs` must be a table: `inputs = { slot = \"stage\" }`",
                )),
            },
            _ => {
                rest.insert(k, v);
            }
        }
    }
    let Some((kind, kind_span)) = kind else {
        errors.push(src.error(
            name.span(),
            format!(
                "stage `{name_str}` has no `kind`; one of: {}",
                KINDS.join(", ")
            ),
        ));
        return Err(errors);
    };
    let de = ValueDeserializer::from(Spanned::new(body_span.clone(), DeValue::Table(rest)));
    let config = match StageConfig::deserialize(&kind, de) {
        None => {
            errors.push(src.error(
                kind_span,
                format!(
                    "unknown stage kind `{kind}`; one of: {}{}",
                    KINDS.join(", "),
                    crate::suggest::hint(&kind, KINDS.iter().copied())
                ),
            ));
            None
        }
        Some(Err(e)) => {
            let mut err = toml_error(src, e, body_span);
            // Name the field whose value the error points at, if any.
            let field = fields
                .iter()
                .filter(|(_, sp)| sp.start <= err.span.start && err.span.end <= sp.end)
                .min_by_key(|(_, sp)| sp.end - sp.start)
                .map(|(f, _)| f.clone());
            err.message = match field {
                Some(f) => format!("stage `{name_str}`, `{f}`: {}", err.message),
                None => format!("stage `{name_str}`: {}", err.message),
            };
            errors.push(err);
            None
        }
        Some(Ok(c)) => Some(c),
    };
    match config {
        Some(config) if errors.is_empty() => {
            inputs.sort_by_key(|i| i.slot_span.start);
            Ok(RawStage {
                name: name_str,
                span: name.span(),
                kind,
                config,
                inputs,
                fields,
            })
        }
        _ => Err(errors),
    }
}
