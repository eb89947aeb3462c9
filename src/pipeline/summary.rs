//! A pipeline's headline numbers (`[summary]`), read from what a run
//! published: after `ltcal run` they are the results on stdout, one
//! `name = value` a line, while stage lines, progress and notes go to
//! stderr.
//!
//! Only a stage this run served or computed is read (a partial run that
//! skipped it has no current table to show): its published table, which
//! the run has just written from the cache entry.

use super::cache;
use super::raw::{RawSummary, RawSummaryItem};
use super::run_report::RunReport;
use super::status::Status;
use polars::prelude::{AnyValue, DataFrame};

/// One headline number, or why it cannot be given.
#[derive(Clone, Debug, PartialEq)]
pub struct Headline {
    pub name: String,
    /// The cell as TOML would write it (a string quoted).
    pub value: Result<String, String>,
}

/// Every `[summary]` entry, in file order, from `report`'s results.
pub fn read(summary: &RawSummary, report: &RunReport) -> Vec<Headline> {
    summary
        .iter()
        .map(|(name, item)| Headline {
            name: name.get_ref().clone(),
            value: cell(item, report),
        })
        .collect()
}

fn cell(item: &RawSummaryItem, report: &RunReport) -> Result<String, String> {
    let t = item.table.get_ref();
    let path = match t.strip_prefix("sweep.") {
        Some(g) => {
            if !report
                .sweep
                .as_ref()
                .is_some_and(|s| s.gathered.contains_key(g))
            {
                return Err(format!("`{t}` was not gathered by this run"));
            }
            report.results.join("sweep").join(format!("{g}.parquet"))
        }
        None => {
            let (stage, table) = t.split_once('.').unwrap_or((t, ""));
            let done = report
                .stages
                .iter()
                .any(|s| s.stage == stage && matches!(s.status, Status::Ran | Status::Cached));
            if !done {
                return Err(format!("stage `{stage}` did not complete in this run"));
            }
            report.results.join(stage).join(format!("{table}.parquet"))
        }
    };
    let bytes = crate::fs::read_regular_file(&path, cache::MAX_TABLE_BYTES)
        .map_err(|e| format!("{}: {}", path.display(), e.reason))?;
    let df = crate::table::from_parquet_bytes(&bytes).map_err(|e| format!("{t}: {e:#}"))?;
    let row = pick_row(&df, item).map_err(|why| format!("{t}: {why}"))?;
    let column = item.column.get_ref();
    let v = df
        .column(column)
        .and_then(|c| c.get(row))
        .map_err(|_| format!("{t} has no column `{column}`"))?;
    Ok(format_value(&v))
}

/// The row `row` names, or the one row `where` picks.
fn pick_row(df: &DataFrame, item: &RawSummaryItem) -> Result<usize, String> {
    let Some(filter) = &item.filter else {
        let row = item.row.as_ref().map_or(0, |r| *r.get_ref());
        return if row < df.height() {
            Ok(row)
        } else {
            Err(format!("no row {row} (it has {} rows)", df.height()))
        };
    };
    let mut rows: Vec<usize> = (0..df.height()).collect();
    for (col, want) in filter.get_ref() {
        let c = df
            .column(col)
            .map_err(|_| format!("no column `{col}` (in `where`)"))?;
        rows.retain(|&i| c.get(i).is_ok_and(|v| matches(&v, want)));
    }
    match rows[..] {
        [one] => Ok(one),
        [] => Err(format!("no row has {}", describe(filter.get_ref()))),
        _ => Err(format!(
            "{} rows have {}: `where` must pick one",
            rows.len(),
            describe(filter.get_ref())
        )),
    }
}

fn describe(filter: &std::collections::BTreeMap<String, toml::Value>) -> String {
    filter
        .iter()
        .map(|(k, v)| format!("{k} = {v}"))
        .collect::<Vec<_>>()
        .join(", ")
}

fn matches(v: &AnyValue, want: &toml::Value) -> bool {
    match want {
        toml::Value::String(s) => v.get_str() == Some(s.as_str()),
        toml::Value::Integer(i) => v.extract::<f64>() == Some(*i as f64),
        toml::Value::Float(f) => v.extract::<f64>() == Some(*f),
        toml::Value::Boolean(b) => matches!(v, AnyValue::Boolean(x) if x == b),
        _ => false,
    }
}

/// A number at full precision (the shortest text that reads back the same
/// `f64`), a string quoted, a missing value `nan`.
fn format_value(v: &AnyValue) -> String {
    if let Some(s) = v.get_str() {
        return serde_json::Value::String(s.to_string()).to_string();
    }
    match v {
        AnyValue::Null => "nan".into(),
        AnyValue::Boolean(b) => b.to_string(),
        _ if v.dtype().is_integer() => v
            .extract::<i64>()
            .map_or_else(|| v.to_string(), |i| i.to_string()),
        _ => v
            .extract::<f64>()
            .map_or_else(|| v.to_string(), |f| f.to_string()),
    }
}
