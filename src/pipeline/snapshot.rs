//! Result snapshots: a pipeline's `[snapshot]` table names result tables
//! that `ltcal snapshot` records as aligned text
//! (`<dir>/<pipeline>/<stage>.<table>.txt`, numbers rounded to `digits`
//! decimals) and that `ltcal snapshot --check` compares the current results
//! with, column by column within an absolute tolerance.
//!
//! The recorded text is what a reviewer reads in a diff, and it is also what
//! the check parses back: [`crate::table::to_text`] right-aligns each column,
//! so a column ends where its header name ends. Numbers are compared after
//! the same rounding, with half a unit of the last recorded digit added to
//! the tolerance so that a tolerance of zero means "equal as recorded" and a
//! tolerance of one unit is not lost to binary rounding.
//!
//! `[snapshot]` is resolved beside the stages ([`super::snapshot_spec`]):
//! its table references are checked against the stages; its `tolerance` columns can
//! only be checked once the tables exist, and are then reported at their
//! place in the file like every other pipeline error.

use super::cache::{Lookup, Store};
use super::error::InputError;
use super::resolve::{InputRef, Pipeline};
use super::run_report::RunReport;
use super::status::Status;
use crate::diagnostics::Problem;
use crate::fs::write_atomic;
use crate::table;
use anyhow::{Result, anyhow, bail};
use polars::prelude::DataFrame;
use std::fmt;
use std::path::{Path, PathBuf};

/// Differing rows shown per table; the rest are counted.
const SHOWN_ROWS: usize = 20;

pub use super::snapshot_spec::{DEFAULT_DIGITS, Snapshot};

/// The pipeline's `[snapshot]`, or an error saying how to add one.
pub fn of(p: &Pipeline) -> Result<&Snapshot> {
    p.snapshot.as_ref().ok_or_else(|| {
        anyhow!(
            "{} has no [snapshot] table; add one, e.g.\n\n[snapshot]\ntables = [\"<stage>.<table>\"]",
            p.source.path.display()
        )
    })
}

/// The snapshot's tables as the run produced them, read from its cache
/// entries (by key, so a concurrent run with other settings cannot swap a
/// published copy underneath).
pub fn collect(
    p: &Pipeline,
    snap: &Snapshot,
    report: &RunReport,
    store: &Store,
) -> Result<Vec<(InputRef, DataFrame)>> {
    let mut out = Vec::new();
    for r in &snap.tables {
        let Some(key) = report
            .stages
            .iter()
            .find(|s| s.stage == r.stage && matches!(s.status, Status::Ran | Status::Cached))
            .and_then(|s| s.key.as_ref())
        else {
            bail!(
                "stage `{}` did not complete, so `{r}` has no result",
                r.stage
            );
        };
        let Lookup::Hit(entry) = store.lookup(key) else {
            bail!(
                "the result of stage `{}` vanished from the cache during the run",
                r.stage
            );
        };
        let bytes = entry
            .tables
            .get(&r.table)
            .ok_or_else(|| anyhow!("stage `{}` produced no table `{}`", r.stage, r.table))?;
        out.push((r.clone(), table::from_parquet_bytes(bytes)?));
    }
    check_columns(p, snap, &out)?;
    Ok(out)
}

/// Every `tolerance` column must be a column of some snapshot table.
fn check_columns(p: &Pipeline, snap: &Snapshot, tables: &[(InputRef, DataFrame)]) -> Result<()> {
    let mut problems = Vec::new();
    for (col, span) in &snap.tolerance_spans {
        let found = tables.iter().any(|(_, df)| df.column(col).is_ok());
        if !found {
            let mut have: Vec<String> = tables
                .iter()
                .flat_map(|(_, df)| df.get_column_names().into_iter().map(|c| c.to_string()))
                .collect();
            have.sort();
            have.dedup();
            problems.push(Problem::At(p.source.error(
                span.clone(),
                format!(
                    "[snapshot]: no snapshot table has a column `{col}`; their columns are: {}",
                    have.join(", ")
                ),
            )));
        }
    }
    if problems.is_empty() {
        Ok(())
    } else {
        Err(InputError(problems).into())
    }
}

/// `<dir>/<pipeline>/<stage>.<table>.txt`.
pub fn file(dir: &Path, p: &Pipeline, r: &InputRef) -> PathBuf {
    dir.join(&p.name)
        .join(format!("{}.{}.txt", r.stage, r.table))
}

/// Writes every table's text, atomically; returns the files.
pub fn record(
    p: &Pipeline,
    snap: &Snapshot,
    tables: &[(InputRef, DataFrame)],
    dir: &Path,
) -> Result<Vec<PathBuf>> {
    let mut written = Vec::new();
    for (r, df) in tables {
        let path = file(dir, p, r);
        write_atomic(&path, table::to_text(df, snap.digits).as_bytes())?;
        written.push(path);
    }
    Ok(written)
}

/// One value that moved beyond its tolerance.
#[derive(Clone, Debug, PartialEq)]
pub struct CellDiff {
    pub column: String,
    pub recorded: String,
    pub now: String,
    /// `now − recorded` when both are numbers.
    pub delta: Option<f64>,
    pub tolerance: Option<f64>,
}

/// The differences in one row.
#[derive(Clone, Debug, PartialEq)]
pub struct RowDiff {
    /// 1-based data row.
    pub row: usize,
    /// `statistic = rms`: the row's first text column, to recognise it by.
    pub label: Option<String>,
    pub cells: Vec<CellDiff>,
}

/// How one table compares with its recording.
#[derive(Clone, Debug, PartialEq)]
pub enum Outcome {
    /// Every value within tolerance; `values` were compared.
    Same { values: usize },
    /// No recording yet.
    NotRecorded,
    Differs {
        /// Columns or rows added or removed.
        shape: Vec<String>,
        rows: Vec<RowDiff>,
    },
}

/// One snapshot table checked.
#[derive(Clone, Debug)]
pub struct TableCheck {
    pub table: InputRef,
    pub file: PathBuf,
    pub outcome: Outcome,
}

/// The largest recording read back: a recorded table is text a person
/// reviews in a diff, far below this.
const MAX_RECORDED_BYTES: u64 = 256 << 20;

/// Compares every table with its recording in `dir`.
pub fn check(
    p: &Pipeline,
    snap: &Snapshot,
    tables: &[(InputRef, DataFrame)],
    dir: &Path,
) -> Result<Vec<TableCheck>> {
    let mut out = Vec::new();
    for (r, df) in tables {
        let path = file(dir, p, r);
        let read = crate::fs::read_regular_file(&path, MAX_RECORDED_BYTES);
        let outcome = match read.map(String::from_utf8) {
            Err(e) if e.is_missing() => Outcome::NotRecorded,
            Err(e) => bail!("reading {}: {}", path.display(), e.reason),
            Ok(Err(_)) => bail!(
                "reading {}: stream did not contain valid UTF-8",
                path.display()
            ),
            Ok(Ok(recorded)) => {
                let now = table::to_text(df, snap.digits);
                compare(snap, &recorded, &now).map_err(|e| anyhow!("{}: {e}", path.display()))?
            }
        };
        out.push(TableCheck {
            table: r.clone(),
            file: path,
            outcome,
        });
    }
    Ok(out)
}

/// A table as written by [`table::to_text`]: column names and cells.
#[derive(Debug, PartialEq)]
struct Text {
    columns: Vec<String>,
    rows: Vec<Vec<String>>,
}

/// Parses [`table::to_text`]'s output. Columns are right-aligned and
/// separated by at least two spaces, so each ends where its header name
/// ends; cells are cut at those ends (in characters), which keeps text
/// cells with spaces whole.
fn parse(text: &str) -> Result<Text> {
    let mut lines = text.lines();
    let header: Vec<char> = lines
        .next()
        .ok_or_else(|| anyhow!("the recording is empty"))?
        .chars()
        .collect();
    let mut columns = Vec::new();
    let mut ends = Vec::new();
    let mut i = 0;
    while i < header.len() {
        while i < header.len() && header[i] == ' ' {
            i += 1;
        }
        let start = i;
        // A name ends at two spaces in a row or at the end of the line.
        while i < header.len() && !(header[i] == ' ' && header.get(i + 1).is_none_or(|&c| c == ' '))
        {
            i += 1;
        }
        if i > start {
            columns.push(header[start..i].iter().collect::<String>());
            ends.push(i);
        }
    }
    let rows = lines
        .map(|line| {
            let chars: Vec<char> = line.chars().collect();
            let mut from = 0;
            ends.iter()
                .map(|&end| {
                    let cell: String = chars[from.min(chars.len())..end.min(chars.len())]
                        .iter()
                        .collect();
                    from = end;
                    cell.trim().to_string()
                })
                .collect()
        })
        .collect();
    Ok(Text { columns, rows })
}

/// Compares a recording with the current text of the same table.
fn compare(snap: &Snapshot, recorded: &str, now: &str) -> Result<Outcome> {
    let (old, new) = (parse(recorded)?, parse(now)?);
    let mut shape = Vec::new();
    for c in &old.columns {
        if !new.columns.contains(c) {
            shape.push(format!("column `{c}` is gone"));
        }
    }
    for c in &new.columns {
        if !old.columns.contains(c) {
            shape.push(format!("column `{c}` is new"));
        }
    }
    if old.rows.len() != new.rows.len() {
        shape.push(format!(
            "{} recorded, {} now",
            n_rows(old.rows.len()),
            new.rows.len()
        ));
    }
    let common: Vec<(usize, usize, &String)> = old
        .columns
        .iter()
        .enumerate()
        .filter_map(|(i, c)| new.columns.iter().position(|n| n == c).map(|j| (i, j, c)))
        .collect();
    // Half a unit of the last recorded digit: see the module docs.
    let slack = 0.5 * 10f64.powi(-(snap.digits as i32));
    let label_col = common.iter().find(|(i, _, _)| {
        old.rows.iter().any(|r| {
            r.get(*i)
                .is_some_and(|v| !v.is_empty() && v.parse::<f64>().is_err())
        })
    });
    let mut rows = Vec::new();
    let mut values = 0;
    for (k, (o, n)) in old.rows.iter().zip(&new.rows).enumerate() {
        let mut cells = Vec::new();
        for &(i, j, col) in &common {
            let (a, b) = (&o[i], &n[j]);
            values += 1;
            if a == b {
                continue;
            }
            let diff = match (a.parse::<f64>(), b.parse::<f64>()) {
                (Ok(x), Ok(y)) => {
                    let tol = snap.tolerance_of(col);
                    if (y - x).abs() <= tol + slack {
                        continue;
                    }
                    CellDiff {
                        column: col.clone(),
                        recorded: a.clone(),
                        now: b.clone(),
                        delta: Some(y - x),
                        tolerance: Some(tol),
                    }
                }
                _ => CellDiff {
                    column: col.clone(),
                    recorded: a.clone(),
                    now: b.clone(),
                    delta: None,
                    tolerance: None,
                },
            };
            cells.push(diff);
        }
        if !cells.is_empty() {
            rows.push(RowDiff {
                row: k + 1,
                label: label_col.map(|&(i, _, c)| format!("{c} = {}", o[i])),
                cells,
            });
        }
    }
    Ok(if shape.is_empty() && rows.is_empty() {
        Outcome::Same { values }
    } else {
        Outcome::Differs { shape, rows }
    })
}

fn n_rows(n: usize) -> String {
    format!("{n} row{}", if n == 1 { "" } else { "s" })
}

/// Decimal places of a number as written.
fn decimals(s: &str) -> usize {
    s.split_once('.').map_or(0, |(_, d)| d.len())
}

/// The checks as a readable report: a line per table, and for a table that
/// differs, which rows and columns, recorded against now and by how much.
pub struct Report<'a>(pub &'a [TableCheck]);

impl fmt::Display for Report<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for c in self.0 {
            match &c.outcome {
                Outcome::Same { values } => {
                    writeln!(f, "  same     {}  ({values} values)", c.table)?
                }
                Outcome::NotRecorded => writeln!(
                    f,
                    "  MISSING  {}  (not recorded: {} does not exist)",
                    c.table,
                    c.file.display()
                )?,
                Outcome::Differs { shape, rows } => {
                    let n: usize = rows.iter().map(|r| r.cells.len()).sum();
                    writeln!(
                        f,
                        "  DIFFERS  {}  ({n} value{} in {} beyond tolerance; recorded in {})",
                        c.table,
                        if n == 1 { "" } else { "s" },
                        n_rows(rows.len()),
                        c.file.display()
                    )?;
                    for s in shape {
                        writeln!(f, "           {s}")?;
                    }
                    for r in rows.iter().take(SHOWN_ROWS) {
                        match &r.label {
                            Some(l) => writeln!(f, "           row {} ({l}):", r.row)?,
                            None => writeln!(f, "           row {}:", r.row)?,
                        }
                        let w = r.cells.iter().map(|d| d.column.len()).max().unwrap_or(0);
                        let wr = r.cells.iter().map(|d| d.recorded.len()).max().unwrap_or(0);
                        let wn = r.cells.iter().map(|d| d.now.len()).max().unwrap_or(0);
                        for d in &r.cells {
                            let by = match (d.delta, d.tolerance) {
                                (Some(delta), Some(tol)) => format!(
                                    "  off by {}{} (tolerance {tol})",
                                    if delta >= 0.0 { "+" } else { "" },
                                    table::format_float(
                                        delta,
                                        decimals(&d.recorded).max(decimals(&d.now))
                                    ),
                                ),
                                _ => String::new(),
                            };
                            writeln!(
                                f,
                                "             {:w$}  recorded {:>wr$}  now {:>wn$}{by}",
                                d.column, d.recorded, d.now
                            )?;
                        }
                    }
                    if rows.len() > SHOWN_ROWS {
                        writeln!(f, "           … and {} more rows", rows.len() - SHOWN_ROWS)?;
                    }
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::table::TableBuilder;
    use std::collections::BTreeMap;

    fn snap(tol: &[(&str, f64)], default: f64) -> Snapshot {
        Snapshot {
            tables: Vec::new(),
            digits: 6,
            tolerance: tol.iter().map(|(c, t)| (c.to_string(), *t)).collect(),
            default_tolerance: default,
            tolerance_spans: BTreeMap::new(),
        }
    }

    fn text(names: &[&str], a: Vec<f64>) -> String {
        let df = TableBuilder::new()
            .str("statistic", names)
            .f64("after_um", a)
            .build()
            .unwrap();
        table::to_text(&df, 6)
    }

    #[test]
    fn parse_reads_back_what_to_text_wrote_including_spaces_in_cells() {
        let df = TableBuilder::new()
            .str("sentence", &["a b  c", "x"])
            .f64("v", vec![1.5, -2.25])
            .str("empty", &["", ""])
            .build()
            .unwrap();
        let t = parse(&table::to_text(&df, 3)).unwrap();
        assert_eq!(t.columns, ["sentence", "v", "empty"]);
        assert_eq!(t.rows, [["a b  c", "1.500", ""], ["x", "-2.250", ""]]);
    }

    #[test]
    fn values_within_tolerance_pass_and_others_are_located() {
        let rec = text(&["mean", "rms"], vec![1.0, 2.0]);
        let now = text(&["mean", "rms"], vec![1.000001, 2.5]);
        let out = compare(&snap(&[("after_um", 1e-6)], 0.0), &rec, &now).unwrap();
        let Outcome::Differs { shape, rows } = out else {
            panic!("{out:?}")
        };
        assert!(shape.is_empty());
        assert_eq!(rows.len(), 1);
        assert_eq!(rows[0].row, 2);
        assert_eq!(rows[0].label.as_deref(), Some("statistic = rms"));
        let d = &rows[0].cells[0];
        assert_eq!(
            (d.recorded.as_str(), d.now.as_str()),
            ("2.000000", "2.500000")
        );
        assert!((d.delta.unwrap() - 0.5).abs() < 1e-12);
        // A tolerance of zero means equal as recorded.
        let exact = compare(&snap(&[], 0.0), &rec, &rec).unwrap();
        assert_eq!(exact, Outcome::Same { values: 4 });
        let loose = compare(&snap(&[], 0.5), &rec, &now).unwrap();
        assert_eq!(loose, Outcome::Same { values: 4 });
    }

    #[test]
    fn added_rows_and_columns_are_differences() {
        let rec = text(&["mean"], vec![1.0]);
        let now = text(&["mean", "rms"], vec![1.0, 2.0]);
        let Outcome::Differs { shape, .. } = compare(&snap(&[], 1.0), &rec, &now).unwrap() else {
            panic!()
        };
        assert_eq!(shape, ["1 row recorded, 2 now"]);
    }
}
