//! `plot`: an SVG figure of another stage's table.
//!
//! ```toml
//! [stages.figure8]
//! kind = "plot"
//! plot = "mesh-errors"                       # Figures 6–8
//! inputs = { table = "evaluate_sphere.points" }
//! title = "Figure 8: errors in a spherical mesh"
//! file = "figure8.svg"                       # optional, default "<plot>.svg"
//! ```
//!
//! `mesh-errors` reads an `evaluate` stage's `points` table; `criterion`
//! (with `criterion = "distances"` or another of `evaluate_campaign`'s
//! criteria; Figures 10, 15–18) its `terms` table. Output: the SVG
//! file, and a table `figure` (`file`, `plot`, `title`, `rows`) that records it.

use super::evaluate_campaign::CRITERIA;
use super::{ColumnUse, Context, Invalid, Slot, StageInputs, StageKind, StageOutput};
use crate::plots::{self, PointError};
use crate::table::TableBuilder;
use anyhow::Result;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PlotKind {
    /// Figures 6–8: error of each mesh point before and after calibration.
    MeshErrors,
    /// Figures 10, 15–18: one criterion of an `evaluate_campaign` stage's
    /// `terms` table, before and after.
    Criterion,
    /// A metric against a swept parameter, one line per value of a series
    /// column, mean ± 1 standard deviation over everything else (seeds).
    Metric,
}

impl PlotKind {
    fn name(self) -> &'static str {
        match self {
            PlotKind::MeshErrors => "mesh-errors",
            PlotKind::Criterion => "criterion",
            PlotKind::Metric => "metric",
        }
    }
}

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct PlotStage {
    /// The figure: `mesh-errors` (Figures 6–8), `criterion` (Figures 10, 15–18)
    /// or `metric` (a column against another).
    pub plot: PlotKind,
    /// The figure's title; the plot's own by default.
    #[serde(default)]
    pub title: String,
    /// The SVG file's name; `<plot>.svg` by default.
    #[serde(default)]
    pub file: String,
    /// For `plot = "criterion"`: `distances`, `coordinates`,
    /// `reference_distances` or `reference_coordinates`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub criterion: Option<String>,
    /// For `plot = "metric"`: the column of the x axis.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x: Option<String>,
    /// For `plot = "metric"`: the column of the y axis.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y: Option<String>,
    /// For `plot = "metric"`: the column whose values make separate series
    /// (optional).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub series: Option<String>,
    /// For `plot = "metric"`: rows to keep, `{ column = value }`.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub filter: BTreeMap<String, toml::Value>,
}

impl PlotStage {
    /// `plot = "metric"`: mean ± sd of `y` per (`series`, `x`).
    fn metric(&self, t: &crate::table::TableRef) -> Result<String> {
        let (xc, yc) = (
            self.x.as_deref().unwrap_or_default(),
            self.y.as_deref().unwrap_or_default(),
        );
        let mut keep: Vec<bool> = vec![true; t.height()];
        for (col, want) in &self.filter {
            let want = want.to_string().trim_matches('"').to_string();
            let have: Vec<String> = match t.str(col) {
                Ok(v) => v,
                Err(_) => t.f64(col)?.iter().map(|v| v.to_string()).collect(),
            };
            for (k, h) in keep.iter_mut().zip(&have) {
                *k &= *h == want
                    || h.parse::<f64>()
                        .ok()
                        .zip(want.parse::<f64>().ok())
                        .is_some_and(|(a, b)| a == b);
            }
        }
        let x = t.f64(xc)?;
        let y = t.f64(yc)?;
        let series: Vec<String> = match self.series.as_deref() {
            Some(c) => match t.str(c) {
                Ok(v) => v,
                Err(_) => {
                    let name = plots::axis_title(c);
                    t.f64(c)?.iter().map(|v| format!("{name} = {v}")).collect()
                }
            },
            None => vec![yc.to_string(); t.height()],
        };
        let mut groups: BTreeMap<String, BTreeMap<i64, Vec<f64>>> = BTreeMap::new();
        for i in (0..t.height()).filter(|&i| keep[i] && x[i].is_finite() && y[i].is_finite()) {
            // Group x values equal to 1e-9 (swept values are exact).
            groups
                .entry(series[i].clone())
                .or_default()
                .entry((x[i] * 1e9).round() as i64)
                .or_default()
                .push(y[i]);
        }
        // Series named by numbers go in numeric order.
        let mut groups: Vec<(String, BTreeMap<i64, Vec<f64>>)> = groups.into_iter().collect();
        groups.sort_by(|a, b| {
            let num = |s: &str| s.rsplit(' ').next().and_then(|x| x.parse::<f64>().ok());
            match (num(&a.0), num(&b.0)) {
                (Some(x), Some(y)) => x.total_cmp(&y),
                _ => a.0.cmp(&b.0),
            }
        });
        let lines: Vec<plots::MetricLine> = groups
            .into_iter()
            .map(|(name, pts)| plots::MetricLine {
                name,
                points: pts
                    .into_iter()
                    .map(|(xk, ys)| {
                        let n = ys.len() as f64;
                        let mean = ys.iter().sum::<f64>() / n;
                        let sd = if ys.len() > 1 {
                            (ys.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt()
                        } else {
                            0.0
                        };
                        (xk as f64 / 1e9, mean, sd, ys.len())
                    })
                    .collect(),
            })
            .collect();
        plots::metric_lines(
            &self.title,
            &plots::axis_title(xc),
            &plots::axis_title(yc),
            &lines,
        )
    }
}

impl StageKind for PlotStage {
    const KIND: &'static str = "plot";
    const SUMMARY: &'static str =
        "an SVG figure of another stage's table (Figures 6–8: mesh-errors)";
    const INPUTS: &'static [Slot] = &[Slot::table("table", true, "the table to draw")];
    const OUTPUTS: &'static [&'static str] = &["figure"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "figure" => Some(&["file", "plot", "title", "rows"]),
            _ => None,
        }
    }

    fn resolved(mut self) -> Self {
        if self.file.is_empty() {
            self.file = format!("{}.svg", self.plot.name());
        }
        self
    }

    fn validate(&self) -> Vec<Invalid> {
        let mut out = Vec::new();
        let ok = !self.file.contains(['/', '\\'])
            && self.file.ends_with(".svg")
            && self.file.len() > 4
            && !self.file.starts_with('.');
        if !ok {
            out.push(Invalid::new(
                "file",
                format!(
                    "`file` must be a plain file name ending in .svg, got \"{}\"",
                    self.file
                ),
            ));
        }
        match (self.plot, &self.criterion) {
            (PlotKind::Criterion, None) => out.push(Invalid::new(
                "plot",
                format!(
                    "plot = \"criterion\" needs `criterion`: one of {}",
                    CRITERIA.join(", ")
                ),
            )),
            (PlotKind::Criterion, Some(c)) if !CRITERIA.contains(&c.as_str()) => {
                out.push(Invalid::new(
                    "criterion",
                    format!("unknown criterion `{c}`; one of {}", CRITERIA.join(", ")),
                ))
            }
            (PlotKind::MeshErrors | PlotKind::Metric, Some(_)) => out.push(Invalid::new(
                "criterion",
                "`criterion` applies to plot = \"criterion\" only",
            )),
            _ => {}
        }
        let metric_fields = [
            ("x", self.x.is_some()),
            ("y", self.y.is_some()),
            ("series", self.series.is_some()),
            ("filter", !self.filter.is_empty()),
        ];
        if self.plot == PlotKind::Metric {
            for f in ["x", "y"] {
                if !metric_fields.iter().any(|(n, set)| *n == f && *set) {
                    out.push(Invalid::new(
                        "plot",
                        format!("plot = \"metric\" needs `{f}`: a column of the input table"),
                    ));
                }
            }
        } else {
            for (f, set) in metric_fields {
                if set {
                    out.push(Invalid::new(
                        f,
                        format!("`{f}` applies to plot = \"metric\" only"),
                    ));
                }
            }
        }
        out
    }

    /// `plot = "metric"` names its columns in `x`, `y`, `series` and
    /// `filter`; the other plots read fixed columns, checked when they run.
    fn columns_named(&self) -> Vec<ColumnUse> {
        if self.plot != PlotKind::Metric {
            return Vec::new();
        }
        let named = [("x", &self.x), ("y", &self.y), ("series", &self.series)];
        let mut out: Vec<ColumnUse> = named
            .into_iter()
            .filter_map(|(field, c)| {
                c.as_ref().map(|c| ColumnUse {
                    slot: "table",
                    field: field.into(),
                    column: c.clone(),
                })
            })
            .collect();
        out.extend(self.filter.keys().map(|c| ColumnUse {
            slot: "table",
            field: format!("filter.{c}"),
            column: c.clone(),
        }));
        out
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let t = inputs.get("table")?;
        let svg = match self.plot {
            PlotKind::MeshErrors => {
                let (x, y, z) = (t.f64("x_ref_mm")?, t.f64("y_ref_mm")?, t.f64("z_ref_mm")?);
                let (b, a) = (t.f64("err_before_um")?, t.f64("err_after_um")?);
                let pts: Vec<PointError> = (0..t.height())
                    .map(|i| PointError {
                        x_mm: x[i],
                        y_mm: y[i],
                        z_mm: z[i],
                        before_um: b[i],
                        after_um: a[i],
                    })
                    .collect();
                plots::mesh_errors(&self.title, &pts)?
            }
            PlotKind::Criterion => {
                let want = self.criterion.as_deref().unwrap_or_default();
                let names = t.str("criterion")?;
                let (b, a) = (t.f64("before_um")?, t.f64("after_um")?);
                let keep: Vec<usize> = (0..names.len()).filter(|&i| names[i] == want).collect();
                let before: Vec<f64> = keep.iter().map(|&i| b[i]).collect();
                let after: Vec<f64> = keep.iter().map(|&i| a[i]).collect();
                let label = match want {
                    "distances" => "distance difference between stations (µm)",
                    "coordinates" => "coordinate difference between stations (µm)",
                    "reference_distances" => "distance error against references (µm)",
                    _ => "coordinate error against references (µm)",
                };
                plots::criterion_errors(&self.title, label, &before, &after)?
            }
            PlotKind::Metric => self.metric(&t)?,
        };
        let figure = TableBuilder::new()
            .str("file", &[&self.file])
            .str("plot", &[self.plot.name()])
            .str("title", &[&self.title])
            .i64("rows", vec![t.height() as i64])
            .build()?;
        Ok(StageOutput::default()
            .table("figure", figure)
            .file(self.file.clone(), svg.into_bytes()))
    }
}
