//! Result tables: building them column by column, reading typed columns back
//! with errors that name the table and the column, and Parquet I/O.
//!
//! Every stage speaks in polars `DataFrame`s at its edges so that what a stage
//! writes is exactly what the next one reads and what a user opens. Column
//! names carry their unit (`d_mm`, `err_um`); each stage module documents the
//! columns it writes.

use anyhow::{Context, Result, anyhow};
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
    pub fn opt_i64(mut self, name: &str, values: Vec<Option<i64>>) -> Self {
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

/// A column of `n` copies of a JSON value (number, string or boolean).
pub fn constant_column(name: &str, v: &serde_json::Value, n: usize) -> Result<Column> {
    Ok(match v {
        serde_json::Value::Number(x) if x.is_i64() => {
            Column::new(name.into(), vec![x.as_i64().unwrap_or(0); n])
        }
        serde_json::Value::Number(x) => {
            Column::new(name.into(), vec![x.as_f64().unwrap_or(f64::NAN); n])
        }
        serde_json::Value::String(s) => Column::new(name.into(), vec![s.as_str(); n]),
        serde_json::Value::Bool(b) => Column::new(name.into(), vec![*b; n]),
        other => Column::new(name.into(), vec![other.to_string(); n]),
    })
}

/// Stacks tables whose columns may differ (a campaign table with one
/// column per station, over sweep points with different station counts):
/// the union of the columns in order of first appearance, nulls where a
/// table lacks one. A column's type is that of its first appearance
/// (numbers are widened to f64 when the tables disagree).
pub fn concat_diagonal(frames: &[DataFrame]) -> Result<DataFrame> {
    let mut names: Vec<String> = Vec::new();
    let mut types: Vec<DataType> = Vec::new();
    for df in frames {
        for c in df.columns() {
            let name = c.name().to_string();
            match names.iter().position(|n| *n == name) {
                None => {
                    names.push(name);
                    types.push(c.dtype().clone());
                }
                Some(i)
                    if types[i] != *c.dtype()
                        && c.dtype().is_primitive_numeric()
                        && types[i].is_primitive_numeric() =>
                {
                    types[i] = DataType::Float64;
                }
                Some(_) => {}
            }
        }
    }
    let mut out: Vec<Column> = Vec::with_capacity(names.len());
    for (name, dtype) in names.iter().zip(&types) {
        let mut acc: Option<Series> = None;
        for df in frames {
            let part = match df.column(name) {
                Ok(c) => c
                    .as_materialized_series()
                    .cast(dtype)
                    .map_err(|e| anyhow!("column `{name}`: {e}"))?,
                Err(_) => Series::full_null(name.as_str().into(), df.height(), dtype),
            };
            match acc.as_mut() {
                Some(a) => {
                    a.append(&part)
                        .map_err(|e| anyhow!("column `{name}`: {e}"))?;
                }
                None => acc = Some(part),
            }
        }
        out.push(
            acc.unwrap_or_else(|| Series::new_empty(name.as_str().into(), dtype))
                .into(),
        );
    }
    DataFrame::new_infer_height(out).map_err(|e| anyhow!("stacking tables: {e}"))
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

    /// `values` of column `col`, or an error naming the first missing one.
    fn required<T>(&self, col: &str, values: impl Iterator<Item = Option<T>>) -> Result<Vec<T>> {
        values
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

    /// A numeric column with no missing values.
    pub fn f64(&self, col: &str) -> Result<Vec<f64>> {
        self.required(col, self.opt_f64(col)?.into_iter())
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
        self.required(col, c.i64()?.iter())
    }

    /// An integer column with missing values.
    pub fn opt_i64(&self, col: &str) -> Result<Vec<Option<i64>>> {
        let c = self
            .column(col)?
            .cast(&DataType::Int64)
            .map_err(|_| anyhow!("table `{}`, column `{col}` is not an integer", self.name))?;
        Ok(c.i64()?.iter().collect())
    }

    pub fn str(&self, col: &str) -> Result<Vec<String>> {
        let c = self.column(col)?;
        let s = c
            .str()
            .map_err(|_| anyhow!("table `{}`, column `{col}` is not text", self.name))?;
        self.required(col, s.iter().map(|v| v.map(str::to_string)))
    }

    /// Any column as text (numbers as polars writes them), for keys.
    pub fn text(&self, col: &str) -> Result<Vec<String>> {
        let c = self.column(col)?.cast(&DataType::String).map_err(|_| {
            anyhow!(
                "table `{}`, column `{col}` cannot be read as text",
                self.name
            )
        })?;
        self.required(col, c.str()?.iter().map(|v| v.map(str::to_string)))
    }

    /// A boolean column with missing values.
    pub fn opt_bool(&self, col: &str) -> Result<Vec<Option<bool>>> {
        let c = self.column(col)?;
        let s = c
            .bool()
            .map_err(|_| anyhow!("table `{}`, column `{col}` is not boolean", self.name))?;
        Ok(s.iter().collect())
    }

    pub fn bool(&self, col: &str) -> Result<Vec<bool>> {
        let c = self.column(col)?;
        let s = c
            .bool()
            .map_err(|_| anyhow!("table `{}`, column `{col}` is not boolean", self.name))?;
        self.required(col, s.iter())
    }
}

/// Serialises a table to Parquet bytes. Statistics are switched off so that
/// the bytes depend on the table alone. LZ4 rather than polars' default
/// zstd: a sweep writes thousands of small tables, and zstd's set-up per
/// column costs more than it saves. Columns are written one after the
/// other, because polars' own thread pool, entered from a worker of ours
/// (a sweep point), lets the waiting worker steal more points onto its
/// stack — and our tables are small.
pub fn to_parquet_bytes(df: &DataFrame) -> Result<Vec<u8>> {
    let mut buf = Vec::new();
    let mut df = df.clone();
    ParquetWriter::new(&mut buf)
        .with_statistics(StatisticsOptions::empty())
        .with_compression(ParquetCompression::Lz4Raw)
        .set_parallel(false)
        .finish(&mut df)
        .map_err(|e| anyhow!("writing Parquet: {e}"))?;
    Ok(buf)
}

pub fn from_parquet_bytes(bytes: &[u8]) -> Result<DataFrame> {
    ParquetReader::new(std::io::Cursor::new(bytes))
        .read_parallel(ParallelStrategy::None)
        .finish()
        .map_err(|e| anyhow!("reading Parquet: {e}"))
}

/// The largest Parquet file [`read_parquet`] reads: a table of a billion
/// cells, far beyond any result of this tool.
pub const MAX_PARQUET_BYTES: u64 = 16 << 30;

/// A Parquet file as a table, read through [`crate::fs::read_regular_file`]
/// (a regular file, bounded) like every file ltcal did not just write.
pub fn read_parquet(path: &Path) -> Result<DataFrame> {
    let bytes = crate::fs::read_regular_file(path, MAX_PARQUET_BYTES)?;
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

/// Renders a table as CSV for scripts (`ltcal show --format csv`): a header
/// of the column names, numbers at full precision (the shortest text that
/// reads back to the same number), missing values as empty fields, and
/// quoting where a value holds a comma, quote or line break — what pandas,
/// polars and spreadsheets read without options.
pub fn to_csv(df: &DataFrame) -> Result<Vec<u8>> {
    let mut buf = Vec::new();
    CsvWriter::new(&mut buf)
        .include_header(true)
        .finish(&mut df.clone())
        .map_err(|e| anyhow!("writing CSV: {e}"))?;
    Ok(buf)
}

/// Renders a table as JSON for scripts (`ltcal show --format json`): an
/// array of records, one per row and one line each, keyed by column name
/// in the table's order. Numbers are JSON numbers at full precision;
/// missing values are `null`, and so are NaN and the infinities, which JSON
/// cannot hold. A value of any other type is given as its text.
pub fn to_json(df: &DataFrame) -> String {
    use serde_json::Value;
    let keys: Vec<String> = df
        .get_column_names()
        .iter()
        .map(|n| Value::from(n.as_str()).to_string())
        .collect();
    let mut out = String::from("[");
    for i in 0..df.height() {
        out.push_str(if i == 0 { "\n{" } else { ",\n{" });
        for (j, (c, key)) in df.columns().iter().zip(&keys).enumerate() {
            let v = match c.get(i).unwrap_or(AnyValue::Null) {
                AnyValue::Null => Value::Null,
                AnyValue::Boolean(b) => Value::from(b),
                AnyValue::String(s) => Value::from(s),
                AnyValue::StringOwned(s) => Value::from(s.as_str()),
                AnyValue::Float64(x) => Value::from(x),
                AnyValue::Float32(x) => Value::from(x),
                v if v.is_integer() => v
                    .extract::<i64>()
                    .map(Value::from)
                    .or_else(|| v.extract::<u64>().map(Value::from))
                    .unwrap_or(Value::Null),
                other => Value::from(other.to_string()),
            };
            if j > 0 {
                out.push(',');
            }
            out.push_str(key);
            out.push(':');
            out.push_str(&v.to_string());
        }
        out.push('}');
    }
    out.push_str(if df.height() == 0 { "]\n" } else { "\n]\n" });
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
