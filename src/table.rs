//! Result tables: building them column by column, reading typed columns back
//! with errors that name the table and the column, and Parquet I/O.
//!
//! Every stage speaks in polars `DataFrame`s at its edges so that what a stage
//! writes is exactly what the next one reads and what a user opens. Column
//! names carry their unit (`d_mm`, `err_um`); each stage module documents the
//! columns it writes.

use anyhow::{Context, Result, anyhow, bail};
use polars::prelude::*;
use std::path::Path;

/// Builds a `DataFrame` one named column at a time.
#[derive(Default)]
pub struct TableBuilder {
    columns: Vec<Column>,
}

impl TableBuilder {
    pub fn new() -> Self {
        Self::default()
    }
    pub fn f64(mut self, name: &str, values: Vec<f64>) -> Self {
        self.columns.push(Column::new(name.into(), values));
        self
    }
    pub fn opt_f64(mut self, name: &str, values: Vec<Option<f64>>) -> Self {
        self.columns.push(Column::new(name.into(), values));
        self
    }
    pub fn i64(mut self, name: &str, values: Vec<i64>) -> Self {
        self.columns.push(Column::new(name.into(), values));
        self
    }
    pub fn str<S: AsRef<str>>(mut self, name: &str, values: &[S]) -> Self {
        let v: Vec<&str> = values.iter().map(|s| s.as_ref()).collect();
        self.columns.push(Column::new(name.into(), v));
        self
    }
    pub fn opt_bool(mut self, name: &str, values: Vec<Option<bool>>) -> Self {
        self.columns.push(Column::new(name.into(), values));
        self
    }
    pub fn bool(mut self, name: &str, values: Vec<bool>) -> Self {
        self.columns.push(Column::new(name.into(), values));
        self
    }
    pub fn build(self) -> Result<DataFrame> {
        DataFrame::new_infer_height(self.columns).map_err(|e| anyhow!("building a table: {e}"))
    }
}

/// Typed access to a table that says which table and column was wrong.
pub struct TableRef<'a> {
    pub name: &'a str,
    pub df: &'a DataFrame,
}

impl<'a> TableRef<'a> {
    pub fn new(name: &'a str, df: &'a DataFrame) -> Self {
        TableRef { name, df }
    }

    fn column(&self, col: &str) -> Result<&'a Column> {
        self.df.column(col).map_err(|_| {
            let have: Vec<String> = self
                .df
                .get_column_names()
                .iter()
                .map(|s| s.to_string())
                .collect();
            anyhow!(
                "table `{}` has no column `{col}` (it has: {})",
                self.name,
                have.join(", ")
            )
        })
    }

    pub fn has(&self, col: &str) -> bool {
        self.df.column(col).is_ok()
    }

    pub fn height(&self) -> usize {
        self.df.height()
    }

    /// A numeric column with no missing values.
    pub fn f64(&self, col: &str) -> Result<Vec<f64>> {
        self.opt_f64(col)?
            .iter()
            .enumerate()
            .map(|(i, v)| {
                v.ok_or_else(|| {
                    anyhow!(
                        "table `{}`, column `{col}`, row {i}: missing value",
                        self.name
                    )
                })
            })
            .collect()
    }

    pub fn opt_f64(&self, col: &str) -> Result<Vec<Option<f64>>> {
        let c = self.column(col)?;
        let c = c
            .cast(&DataType::Float64)
            .map_err(|_| anyhow!("table `{}`, column `{col}` is not numeric", self.name))?;
        Ok(c.f64()?.iter().collect())
    }

    pub fn i64(&self, col: &str) -> Result<Vec<i64>> {
        let c = self.column(col)?;
        let c = c
            .cast(&DataType::Int64)
            .map_err(|_| anyhow!("table `{}`, column `{col}` is not an integer", self.name))?;
        c.i64()?
            .iter()
            .enumerate()
            .map(|(i, v)| {
                v.ok_or_else(|| {
                    anyhow!(
                        "table `{}`, column `{col}`, row {i}: missing value",
                        self.name
                    )
                })
            })
            .collect()
    }

    pub fn str(&self, col: &str) -> Result<Vec<String>> {
        let c = self.column(col)?;
        let s = c
            .str()
            .map_err(|_| anyhow!("table `{}`, column `{col}` is not text", self.name))?;
        s.iter()
            .enumerate()
            .map(|(i, v)| {
                v.map(str::to_string).ok_or_else(|| {
                    anyhow!(
                        "table `{}`, column `{col}`, row {i}: missing value",
                        self.name
                    )
                })
            })
            .collect()
    }

    pub fn bool(&self, col: &str) -> Result<Vec<bool>> {
        let c = self.column(col)?;
        let s = c
            .bool()
            .map_err(|_| anyhow!("table `{}`, column `{col}` is not boolean", self.name))?;
        s.iter()
            .enumerate()
            .map(|(i, v)| {
                v.ok_or_else(|| {
                    anyhow!(
                        "table `{}`, column `{col}`, row {i}: missing value",
                        self.name
                    )
                })
            })
            .collect()
    }
}

/// Serialises a table to Parquet bytes. Statistics are switched off so that
/// the bytes depend on the table alone.
pub fn to_parquet_bytes(df: &DataFrame) -> Result<Vec<u8>> {
    let mut buf = Vec::new();
    let mut df = df.clone();
    ParquetWriter::new(&mut buf)
        .with_statistics(StatisticsOptions::empty())
        .finish(&mut df)
        .map_err(|e| anyhow!("writing Parquet: {e}"))?;
    Ok(buf)
}

pub fn from_parquet_bytes(bytes: &[u8]) -> Result<DataFrame> {
    ParquetReader::new(std::io::Cursor::new(bytes))
        .finish()
        .map_err(|e| anyhow!("reading Parquet: {e}"))
}

pub fn read_parquet(path: &Path) -> Result<DataFrame> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    from_parquet_bytes(&bytes).with_context(|| format!("reading {}", path.display()))
}

/// Renders a table as aligned text with numbers rounded to `digits`
/// significant decimals — for terminals, snapshots and reports.
pub fn to_text(df: &DataFrame, digits: usize) -> String {
    let names: Vec<String> = df
        .get_column_names()
        .iter()
        .map(|s| s.to_string())
        .collect();
    let mut rows: Vec<Vec<String>> = vec![names.clone()];
    for i in 0..df.height() {
        let mut row = Vec::with_capacity(names.len());
        for c in df.columns() {
            row.push(cell_text(&c.get(i).unwrap_or(AnyValue::Null), digits));
        }
        rows.push(row);
    }
    let widths: Vec<usize> = (0..names.len())
        .map(|j| rows.iter().map(|r| r[j].chars().count()).max().unwrap_or(0))
        .collect();
    let mut out = String::new();
    for r in rows {
        let line: Vec<String> = r
            .iter()
            .zip(&widths)
            .map(|(s, w)| format!("{s:>w$}"))
            .collect();
        out.push_str(line.join("  ").trim_end());
        out.push('\n');
    }
    out
}

/// One cell as text; floats with a fixed number of decimals, `-0` printed as `0`.
pub fn cell_text(v: &AnyValue, digits: usize) -> String {
    match v {
        AnyValue::Null => String::new(),
        AnyValue::Float64(x) => format_float(*x, digits),
        AnyValue::Float32(x) => format_float(*x as f64, digits),
        AnyValue::String(s) => s.to_string(),
        AnyValue::StringOwned(s) => s.to_string(),
        AnyValue::Boolean(b) => b.to_string(),
        other => other.to_string(),
    }
}

pub fn format_float(x: f64, digits: usize) -> String {
    if !x.is_finite() {
        return x.to_string();
    }
    let s = format!("{x:.digits$}");
    if s.trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        s.trim_start_matches('-').to_string()
    } else {
        s
    }
}

/// Fails unless the table has every listed column.
pub fn require_columns(t: &TableRef, cols: &[&str]) -> Result<()> {
    for c in cols {
        if !t.has(c) {
            bail!("table `{}` lacks the column `{c}`", t.name);
        }
    }
    Ok(())
}
