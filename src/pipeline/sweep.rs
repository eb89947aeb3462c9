//! Batch parameter sweeps: a `[sweep]` table in any pipeline runs its
//! stages once per point of a grid of settings and gathers chosen tables
//! into one table with the swept values as columns.
//!
//! ```toml
//! [[sweep.axis]]                       # a list of values
//! path = "stages.corner.noise.sigma_angle_urad"
//! values = [0.5, 1.0, 2.0]
//! [[sweep.axis]]                       # a range
//! path = "stages.corner.layout.stations"
//! range = { from = 3, to = 6, step = 1 }
//! [[sweep.axis]]                       # seeded random draws
//! path = "stages.corner.seed"
//! name = "seed"                        # the column's name (default: the path's last part)
//! random = { count = 10, seed = 1, low = 0, high = 1000000, integer = true }
//! [[sweep.axis]]                       # axes of one group advance together (zip)
//! path = "stages.corner.noise.sigma_range_um"
//! group = "noise"
//! values = [1.0, 2.0, 4.0]
//!
//! [sweep]
//! gather = ["evaluation.table7"]       # stage.table, gathered over the points
//! ```
//!
//! Axes of the same `group` are zipped (same length, advancing together);
//! groups — every axis without a group is its own — combine as a grid.
//! Each point is the pipeline with its values as `--set` overrides, so every
//! stage of every point is cached like any stage: a rerun resumes where a
//! killed one stopped. Stages whose inputs name `sweep` (`inputs = { table =
//! "sweep.evaluation.table7" }`) run once, after the points, on the gathered
//! tables.
//!
//! Every count is bounded before anything is allocated: `random.count`, a
//! `range`'s values and the grid of all axes at [`MAX_POINTS`], each
//! refused at its place in the file.

use super::overrides::{Override, split_path};
use crate::diagnostics::{Problem, Source};
use crate::{random, table};
use anyhow::{Result, anyhow};
use polars::prelude::{Column, DataFrame};
use serde::Deserialize;
use std::collections::BTreeMap;
use std::ops::Range;
use toml::Spanned;

/// The most points a sweep may expand to.
pub const MAX_POINTS: usize = 100_000;

pub use super::names::PSEUDO_STAGE;

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawRange {
    pub from: f64,
    pub to: f64,
    pub step: f64,
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawRandom {
    /// Any integer TOML holds: bounded by [`MAX_POINTS`] before a value is
    /// drawn.
    pub count: u64,
    pub seed: u64,
    pub low: f64,
    pub high: f64,
    #[serde(default)]
    pub integer: bool,
}

/// One `[[sweep.axis]]` as written.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawAxis {
    pub path: Spanned<String>,
    pub name: Option<Spanned<String>>,
    pub group: Option<String>,
    pub values: Option<Spanned<Vec<toml::Value>>>,
    pub range: Option<Spanned<RawRange>>,
    pub random: Option<Spanned<RawRandom>>,
}

/// `[sweep]` as written.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawSweep {
    #[serde(rename = "axis")]
    pub axes: Vec<RawAxis>,
    #[serde(default)]
    pub gather: Vec<Spanned<String>>,
}

/// An axis with its values.
#[derive(Clone, Debug)]
pub struct Axis {
    /// The column name of the swept value in gathered tables.
    pub name: String,
    pub path: Vec<String>,
    pub values: Vec<serde_json::Value>,
    /// Where the axis's `path` stands in the file, for messages.
    pub span: Range<usize>,
}

/// One point: a value per axis.
#[derive(Clone, Debug)]
pub struct PointValues {
    pub index: usize,
    pub values: Vec<serde_json::Value>,
}

impl PointValues {
    /// The point as `--set` overrides.
    pub fn overrides(&self, axes: &[Axis]) -> Vec<Override> {
        axes.iter()
            .zip(&self.values)
            .map(|(a, v)| Override {
                path: a.path.clone(),
                value: v.clone(),
                text: format!("{}={v} (sweep point {})", a.path.join("."), self.index),
                origin: Some(a.span.clone()),
            })
            .collect()
    }
}

fn axis_values(src: &Source, a: &RawAxis) -> Result<Vec<serde_json::Value>, Problem> {
    let given = [a.values.is_some(), a.range.is_some(), a.random.is_some()];
    if given.iter().filter(|g| **g).count() != 1 {
        return Err(Problem::At(src.error(
            a.path.span(),
            "an axis gives exactly one of `values`, `range` or `random`",
        )));
    }
    if let Some(v) = &a.values {
        if v.get_ref().is_empty() {
            return Err(Problem::At(
                src.error(v.span(), "`values` must not be empty"),
            ));
        }
        return v
            .get_ref()
            .iter()
            .map(|x| {
                serde_json::to_value(x).map_err(|e| Problem::At(src.error(v.span(), e.to_string())))
            })
            .collect();
    }
    if let Some(r) = &a.range {
        let rr = r.get_ref();
        let range = crate::mesh::Range::new(rr.from, rr.to, rr.step);
        if let Err((part, msg)) = range.check() {
            return Err(Problem::At(
                src.error(r.span(), format!("`range.{part}` {msg}")),
            ));
        }
        // Counted before a value is made: a step of 1e-9 is refused here,
        // not after a billion values are allocated.
        if range.count() > MAX_POINTS {
            return Err(Problem::At(src.error(
                r.span(),
                format!(
                    "`range` gives {} values, more than the limit of {MAX_POINTS} points a sweep may have",
                    range.count()
                ),
            )));
        }
        let integral = [rr.from, rr.to, rr.step].iter().all(|x| x.fract() == 0.0);
        return Ok(range
            .values()
            .into_iter()
            .map(|v| {
                if integral {
                    serde_json::json!(v as i64)
                } else {
                    serde_json::json!(v)
                }
            })
            .collect());
    }
    let r = a.random.as_ref().expect("one of three");
    let rr = r.get_ref();
    if rr.count == 0 || rr.low >= rr.high || !rr.low.is_finite() || !rr.high.is_finite() {
        return Err(Problem::At(
            src.error(r.span(), "`random` needs count ≥ 1 and finite low < high"),
        ));
    }
    if rr.count > MAX_POINTS as u64 {
        return Err(Problem::At(src.error(
            r.span(),
            format!(
                "`random.count` = {} is more than the limit of {MAX_POINTS} points a sweep may have",
                rr.count
            ),
        )));
    }
    let mut rng = random::stream(rr.seed, &a.path.get_ref().to_string());
    Ok((0..rr.count)
        .map(|_| {
            let x = rr.low + (rr.high - rr.low) * random::uniform(&mut rng);
            if rr.integer {
                serde_json::json!(x.floor() as i64)
            } else {
                serde_json::json!(x)
            }
        })
        .collect())
}

/// Expands the axes into points: zipped within a group, a grid across.
pub fn expand(src: &Source, raw: &RawSweep) -> Result<(Vec<Axis>, Vec<PointValues>), Vec<Problem>> {
    let mut problems = Vec::new();
    let mut axes = Vec::new();
    let mut groups: Vec<(String, Vec<usize>)> = Vec::new();
    if raw.axes.is_empty() {
        return Err(vec![Problem::arg(format!(
            "{}: [sweep] needs at least one [[sweep.axis]]",
            src.path.display()
        ))]);
    }
    for (i, a) in raw.axes.iter().enumerate() {
        let Some(path) = split_path(a.path.get_ref()) else {
            problems.push(Problem::At(src.error(a.path.span(), "not a dotted path")));
            continue;
        };
        let name = a
            .name
            .as_ref()
            .map(|n| n.get_ref().clone())
            .unwrap_or_else(|| path.last().cloned().unwrap_or_default());
        match axis_values(src, a) {
            Ok(values) => {
                let group = a.group.clone().unwrap_or_else(|| format!("\u{0}axis{i}"));
                match groups.iter_mut().find(|g| g.0 == group) {
                    Some(g) => g.1.push(axes.len()),
                    None => groups.push((group, vec![axes.len()])),
                }
                axes.push(Axis {
                    name,
                    path,
                    values,
                    span: a.path.span(),
                });
            }
            Err(p) => problems.push(p),
        }
    }
    let mut names: BTreeMap<&str, usize> = BTreeMap::new();
    for (i, a) in axes.iter().enumerate() {
        if names.insert(a.name.as_str(), i).is_some() {
            problems.push(Problem::At(src.error(
                a.span.clone(),
                format!("two axes are named `{}`: give one a `name`", a.name),
            )));
        }
    }
    for (g, members) in &groups {
        let n = axes[members[0]].values.len();
        for &m in &members[1..] {
            if axes[m].values.len() != n {
                problems.push(Problem::At(src.error(
                    axes[m].span.clone(),
                    format!(
                        "axes of group `{g}` advance together and need the same number of values ({n} and {})",
                        axes[m].values.len()
                    ),
                )));
            }
        }
    }
    if !problems.is_empty() {
        return Err(problems);
    }
    let total: usize = groups
        .iter()
        .map(|(_, m)| axes[m[0]].values.len())
        .try_fold(1usize, |acc, n| acc.checked_mul(n))
        .unwrap_or(usize::MAX);
    if total > MAX_POINTS {
        // Placed at the (first) axis with the most values: the one to shorten.
        let widest = axes
            .iter()
            .rev()
            .max_by_key(|a| a.values.len())
            .expect("a sweep has an axis");
        let total = if total == usize::MAX {
            "more than 2^64".to_string()
        } else {
            total.to_string()
        };
        return Err(vec![Problem::At(src.error(
            widest.span.clone(),
            format!("the sweep expands to {total} points, more than the limit of {MAX_POINTS}"),
        ))]);
    }
    let mut points = Vec::with_capacity(total);
    for index in 0..total {
        let mut values = vec![serde_json::Value::Null; axes.len()];
        let mut rest = index;
        // The last group varies fastest.
        for (_, members) in groups.iter().rev() {
            let n = axes[members[0]].values.len();
            let k = rest % n;
            rest /= n;
            for &m in members {
                values[m] = axes[m].values[k].clone();
            }
        }
        points.push(PointValues { index, values });
    }
    Ok((axes, points))
}

/// One gathered table, built as the points come: each point's table with
/// `point` and one column per axis in front, stacked in point order,
/// concatenated a chunk of points at a time so that what is held is one
/// table, not a frame per point. The same builder serves the run and the
/// plan, and the bytes do not depend on the chunking (the table is made
/// one chunk before it is written), so both hash the same bytes.
pub struct Gatherer<'a> {
    axes: &'a [Axis],
    /// Each point's value of each axis.
    values: &'a [Vec<serde_json::Value>],
    /// Each chunk's points stacked and made one contiguous chunk: a point's
    /// table appended as it is stays a chunk of its own in every column,
    /// and 100 000 points' chunks cost more to carry than their rows.
    parts: Vec<DataFrame>,
    chunk: Vec<DataFrame>,
    /// Points pushed so far.
    points: usize,
}

/// Points whose tables are stacked at once.
const GATHER_CHUNK: usize = 256;

impl<'a> Gatherer<'a> {
    fn new(axes: &'a [Axis], values: &'a [Vec<serde_json::Value>]) -> Gatherer<'a> {
        Gatherer {
            axes,
            values,
            parts: Vec::new(),
            chunk: Vec::new(),
            points: 0,
        }
    }

    /// No point's table was pushed (every point failed).
    pub fn is_empty(&self) -> bool {
        self.points == 0
    }

    /// `tables` gatherers over the points `values` of `axes`: one per
    /// table the sweep gathers.
    pub fn each(
        axes: &'a [Axis],
        values: &'a [Vec<serde_json::Value>],
        tables: usize,
    ) -> Vec<Gatherer<'a>> {
        (0..tables).map(|_| Gatherer::new(axes, values)).collect()
    }

    /// Adds point `index`'s table (points in increasing order).
    pub fn push(&mut self, index: usize, df: &DataFrame) -> Result<()> {
        self.chunk.push(with_point_columns(
            self.axes,
            index,
            &self.values[index],
            df,
        )?);
        self.points += 1;
        if self.chunk.len() >= GATHER_CHUNK {
            self.fold()?;
        }
        Ok(())
    }

    fn fold(&mut self) -> Result<()> {
        if !self.chunk.is_empty() {
            let mut part = table::concat_diagonal(&std::mem::take(&mut self.chunk))?;
            part.rechunk_mut();
            self.parts.push(part);
        }
        Ok(())
    }

    /// The gathered table and its Parquet bytes.
    pub fn finish(mut self) -> Result<(DataFrame, Vec<u8>)> {
        self.fold()?;
        let mut df = table::concat_diagonal(&self.parts)?;
        df.rechunk_mut();
        let bytes = table::to_parquet_bytes(&df)?;
        Ok((df, bytes))
    }
}

/// A point's table with `point` and one column per axis in front.
fn with_point_columns(
    axes: &[Axis],
    index: usize,
    values: &[serde_json::Value],
    df: &DataFrame,
) -> Result<DataFrame> {
    let n = df.height();
    let mut cols = vec![Column::new("point".into(), vec![index as i64; n])];
    for (a, v) in axes.iter().zip(values) {
        cols.push(table::constant_column(&a.name, v, n)?);
    }
    for c in df.columns() {
        if axes.iter().any(|a| a.name == c.name().as_str()) || c.name().as_str() == "point" {
            return Err(anyhow!(
                "the gathered table already has a column `{}`: name the axis differently",
                c.name()
            ));
        }
        cols.push(c.clone());
    }
    DataFrame::new_infer_height(cols).map_err(|e| anyhow!("gathering a sweep table: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sweep(text: &str) -> Result<(Vec<Axis>, Vec<PointValues>), Vec<Problem>> {
        let src = Source::new("p.toml", text);
        #[derive(Deserialize)]
        struct Doc {
            sweep: RawSweep,
        }
        let doc: Doc = toml::from_str(text).unwrap();
        expand(&src, &doc.sweep)
    }

    #[test]
    fn grid_zip_list_range_and_random() {
        let (axes, points) = sweep(
            r#"
[[sweep.axis]]
path = "stages.a.x"
values = [1, 2]
[[sweep.axis]]
path = "stages.a.y"
range = { from = 0.5, to = 1.5, step = 0.5 }
group = "g"
[[sweep.axis]]
path = "stages.b.z"
values = ["p", "q", "r"]
group = "g"
[[sweep.axis]]
path = "stages.a.seed"
random = { count = 2, seed = 3, low = 0, high = 100, integer = true }
"#,
        )
        .unwrap();
        assert_eq!(axes.len(), 4);
        assert_eq!(points.len(), 2 * 3 * 2);
        // The zipped pair advances together.
        for p in &points {
            let y = p.values[1].as_f64().unwrap();
            let z = p.values[2].as_str().unwrap();
            assert_eq!(
                (y, z).1,
                ["p", "q", "r"][((y - 0.5) / 0.5).round() as usize]
            );
            assert!(p.values[3].as_i64().unwrap() < 100);
        }
        assert_eq!(points[0].values[0], serde_json::json!(1));
        assert_eq!(points[11].values[0], serde_json::json!(2));
        let again = sweep(
            "[[sweep.axis]]\npath = \"stages.a.seed\"\nrandom = { count = 2, seed = 3, low = 0, high = 100, integer = true }\n",
        )
        .unwrap();
        assert_eq!(again.0[0].values, axes[3].values, "random axes are seeded");
    }

    #[test]
    fn mistakes_point_at_the_axis() {
        let e = sweep("[[sweep.axis]]\npath = \"stages.a.x\"\nvalues = [1]\nrange = { from = 0, to = 1, step = 1 }\n")
            .unwrap_err();
        assert!(e[0].to_string().contains("exactly one of"), "{}", e[0]);
        let e = sweep(
            "[[sweep.axis]]\npath = \"stages.a.x\"\ngroup = \"g\"\nvalues = [1, 2]\n[[sweep.axis]]\npath = \"stages.a.y\"\ngroup = \"g\"\nvalues = [1]\n",
        )
        .unwrap_err();
        assert!(e[0].to_string().contains("p.toml:6:8"), "{}", e[0]);
    }
}
