//! `measurement_uncertainty`: what a measurement made with the calibrated
//! tracker is worth — the corrected coordinates of new readings, or of a
//! grid over the measurement volume, with their standard uncertainty: the
//! calibration's and the new reading's noise combined (see
//! [`crate::calibrate::measurement`]), and a figure of that uncertainty in
//! plan and elevation, like SpatialAnalyzer's "uncertainty field".
//!
//! ```toml
//! [stages.field]
//! kind = "measurement_uncertainty"
//! inputs = { campaign = "corner" }     # the calibration campaign; readings = "…" optional
//! calibration = { objective = "bundle" }   # as a `calibrate` stage (the default)
//! noise = { sigma_angle_urad = 1.0, sigma_range_um = 2.0 }  # the new readings'; default: the campaign's
//! x_mm = [-10000.0, 10000.0]           # the grid, in the tracker's frame (z up)
//! y_mm = [-10000.0, 10000.0]
//! z_mm = [-2000.0, 6000.0]
//! step_mm = 1000.0
//! plan_z_mm = 0.0                      # the height of the plan view
//! elevation_y_mm = 0.0                 # the plane of the elevation view
//! min_range_mm = 1000.0                # nearer grid points are not measured
//! ```
//!
//! Outputs: `field` (per grid point: `view` — `plan` or `elevation` —,
//! `x_mm`, `y_mm`, `z_mm`, `d_mm`, then the uncertainty columns), `measured`
//! (per row of the optional `readings` input — any table with `target`,
//! `face`, `az_deg`, `el_deg`, `d_mm`, such as a campaign's readings —:
//! `target`, `face`, the corrected `x_mm`, `y_mm`, `z_mm` in the measuring
//! station's frame, then the uncertainty columns; empty without it — the
//! two parts add as independent, which holds for readings the calibration
//! did not use). The uncertainty columns:
//! `u_x_mm`, `u_y_mm`, `u_z_mm` (each coordinate's), `u_mm` (their root
//! mean square, as every position in ltcal), `u_cal_mm` and `u_reading_mm`
//! (the two parts of `u_mm`: `u_mm² = u_cal_mm² + u_reading_mm²`). The
//! file `uncertainty-field.svg` maps `u_mm` and `u_cal_mm` in µm over both
//! views.

use super::calibrate::CalibrateStage;
use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput, fitting};
use crate::calibrate::measurement::{Measured, Measurer};
use crate::campaign::Campaign;
use crate::kinematics::{self, Face, Reading};
use crate::noise::Noise;
use crate::plots::{self, FieldView};
use crate::table::TableBuilder;
use anyhow::{Result, anyhow};
use nalgebra::Vector3;
use polars::prelude::DataFrame;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct MeasurementUncertaintyStage {
    /// The calibration, as a `calibrate` stage's settings (the bundle by
    /// default).
    #[serde(default = "default_calibration")]
    pub calibration: CalibrateStage,
    /// The noise of the readings to come; `None`: the campaign's.
    #[serde(default)]
    pub noise: Option<Noise>,
    /// The grid's x range `[low, high]`, mm, in the tracker's frame.
    #[serde(default = "default_xy")]
    pub x_mm: [f64; 2],
    /// The grid's y range, mm.
    #[serde(default = "default_xy")]
    pub y_mm: [f64; 2],
    /// The grid's z range, mm (z up).
    #[serde(default = "default_z")]
    pub z_mm: [f64; 2],
    /// The grid's step, mm.
    #[serde(default = "default_step")]
    pub step_mm: f64,
    /// Height of the plan view, mm.
    #[serde(default)]
    pub plan_z_mm: f64,
    /// Plane of the elevation view, mm.
    #[serde(default)]
    pub elevation_y_mm: f64,
    /// Grid points nearer the tracker are not measured, mm.
    #[serde(default = "default_min_range")]
    pub min_range_mm: f64,
}

fn default_calibration() -> CalibrateStage {
    toml::from_str("objective = \"bundle\"").expect("the default calibration parses")
}
fn default_xy() -> [f64; 2] {
    [-10_000.0, 10_000.0]
}
fn default_z() -> [f64; 2] {
    [-2_000.0, 6_000.0]
}
fn default_step() -> f64 {
    1_000.0
}
fn default_min_range() -> f64 {
    1_000.0
}

/// Grid points per axis at most: a figure stays readable and a table
/// bounded whatever a setting says.
const MAX_CELLS: usize = 201;

const COLUMNS_U: [&str; 6] = [
    "u_x_mm",
    "u_y_mm",
    "u_z_mm",
    "u_mm",
    "u_cal_mm",
    "u_reading_mm",
];

/// The grid values along one axis, `lo` to `hi` by `step`.
fn axis(range: [f64; 2], step: f64) -> Vec<f64> {
    let n = ((range[1] - range[0]) / step + 1e-9).floor() as usize + 1;
    (0..n).map(|k| range[0] + k as f64 * step).collect()
}

/// One grid view: its name and the points, row by row (`rows × cols`).
struct View {
    name: &'static str,
    cols: Vec<f64>,
    rows: Vec<f64>,
    point: fn(&MeasurementUncertaintyStage, f64, f64) -> Vector3<f64>,
}

impl MeasurementUncertaintyStage {
    fn views(&self) -> [View; 2] {
        [
            View {
                name: "plan",
                cols: axis(self.x_mm, self.step_mm),
                rows: axis(self.y_mm, self.step_mm),
                point: |s, x, y| Vector3::new(x, y, s.plan_z_mm),
            },
            View {
                name: "elevation",
                cols: axis(self.x_mm, self.step_mm),
                rows: axis(self.z_mm, self.step_mm),
                point: |s, x, z| Vector3::new(x, s.elevation_y_mm, z),
            },
        ]
    }
}

impl StageKind for MeasurementUncertaintyStage {
    const KIND: &'static str = "measurement_uncertainty";
    const SUMMARY: &'static str = "corrected coordinates of new readings or a grid over the volume, with the calibration's and the reading's uncertainty (uncertainty field)";
    const INPUTS: &'static [Slot] = &[
        fitting::CAMPAIGN,
        fitting::START,
        Slot::table(
            "readings",
            false,
            "readings to correct: `target`, `face`, `az_deg`, `el_deg`, `d_mm`",
        ),
    ];
    const OUTPUTS: &'static [&'static str] = &["field", "measured"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "field" => Some(&[
                "view",
                "x_mm",
                "y_mm",
                "z_mm",
                "d_mm",
                "u_x_mm",
                "u_y_mm",
                "u_z_mm",
                "u_mm",
                "u_cal_mm",
                "u_reading_mm",
            ]),
            "measured" => Some(&[
                "target",
                "face",
                "x_mm",
                "y_mm",
                "z_mm",
                "u_x_mm",
                "u_y_mm",
                "u_z_mm",
                "u_mm",
                "u_cal_mm",
                "u_reading_mm",
            ]),
            _ => None,
        }
    }

    fn validate(&self) -> Vec<Invalid> {
        let mut out: Vec<Invalid> = self
            .calibration
            .validate()
            .into_iter()
            .map(|i| Invalid::new(format!("calibration.{}", i.field), i.message))
            .collect();
        if self.calibration.reject_blunders {
            out.push(Invalid::new(
                "calibration.reject_blunders",
                "run data snooping in a `calibrate` stage and measure with its campaign: the rejected readings are not carried over here",
            ));
        }
        out.extend(self.noise.as_ref().and_then(Invalid::noise));
        if !(self.step_mm.is_finite() && self.step_mm > 0.0) {
            out.push(Invalid::new(
                "step_mm",
                format!("`step_mm` must be positive, got {}", self.step_mm),
            ));
        }
        for (name, r) in [
            ("x_mm", self.x_mm),
            ("y_mm", self.y_mm),
            ("z_mm", self.z_mm),
        ] {
            if !(r[0].is_finite() && r[1].is_finite() && r[0] < r[1]) {
                out.push(Invalid::new(
                    name,
                    format!("`{name}` must be [low, high] with low < high, got {r:?}"),
                ));
            } else if self.step_mm > 0.0 && (r[1] - r[0]) < self.step_mm {
                out.push(Invalid::new(
                    name,
                    format!(
                        "`{name}` must span at least one step (step_mm = {}) so that the figure has two grid points, got {r:?}",
                        self.step_mm
                    ),
                ));
            } else if self.step_mm > 0.0 && (r[1] - r[0]) / self.step_mm >= MAX_CELLS as f64 {
                out.push(Invalid::new(
                    name,
                    format!(
                        "`{name}` spans more than {MAX_CELLS} grid points at step_mm = {}: take a larger step",
                        self.step_mm
                    ),
                ));
            }
        }
        for (name, v) in [
            ("plan_z_mm", self.plan_z_mm),
            ("elevation_y_mm", self.elevation_y_mm),
        ] {
            if !v.is_finite() {
                out.push(Invalid::new(name, format!("`{name}` must be finite")));
            }
        }
        if !(self.min_range_mm.is_finite() && self.min_range_mm > 0.0) {
            out.push(Invalid::new(
                "min_range_mm",
                format!("`min_range_mm` must be positive, got {}", self.min_range_mm),
            ));
        }
        out
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let c = Campaign::from_inputs(inputs, "campaign")?;
        let (net, cal, _) = self.calibration.calibrate(&c, Some(inputs))?;
        if cal.estimate.cov.is_none() {
            return Err(anyhow!(
                "the calibration gives no covariance of the error parameters ({} of them determined): nothing to propagate",
                cal.estimate.analysis.rank
            ));
        }
        let noise = self.noise.unwrap_or(net.noise);
        let measurer = Measurer::new(&cal.estimate, noise);

        let mut field = Rows::default();
        let mut views = Vec::new();
        for v in self.views() {
            let mut total = Vec::with_capacity(v.rows.len());
            let mut part = Vec::with_capacity(v.rows.len());
            for &b in &v.rows {
                let (mut t, mut p) = (Vec::new(), Vec::new());
                for &a in &v.cols {
                    let x = (v.point)(self, a, b);
                    if x.norm() < self.min_range_mm {
                        t.push(f64::NAN);
                        p.push(f64::NAN);
                        continue;
                    }
                    let m = measurer.measure(kinematics::nominal_reading(&x, Face::Front));
                    field.view.push(v.name);
                    field.push(x, &m);
                    t.push(Measured::rms(&m.cov()) * 1e3);
                    p.push(Measured::rms(&m.cov_cal) * 1e3);
                }
                total.push(t);
                part.push(p);
            }
            views.push((v, total, part));
        }

        let mut measured = Rows::default();
        let mut targets = Vec::new();
        let mut faces = Vec::new();
        if let Some(t) = inputs.optional("readings") {
            let (ids, face) = (t.str("target")?, t.i64("face")?);
            let (az, el, d) = (t.f64("az_deg")?, t.f64("el_deg")?, t.f64("d_mm")?);
            for (i, id) in ids.into_iter().enumerate() {
                let f = Face::from_number(face[i]).ok_or_else(|| {
                    anyhow!(
                        "table `{}`, row {i}: face must be 1 or 2, got {}",
                        t.name,
                        face[i]
                    )
                })?;
                let r = Reading {
                    az: az[i].to_radians(),
                    el: el[i].to_radians(),
                    d: d[i],
                };
                if !(r.az.is_finite() && r.el.is_finite() && r.d.is_finite() && r.d > 0.0) {
                    return Err(anyhow!(
                        "table `{}`, row {i}: a reading needs finite angles and a positive distance",
                        t.name
                    ));
                }
                let m = measurer.measure(r);
                measured.push(m.point, &m);
                targets.push(id);
                faces.push(f.number());
            }
        }

        let m = |v: &[f64]| -> Vec<f64> { v.iter().map(|x| x / 1000.0).collect() };
        let axes: Vec<(Vec<f64>, Vec<f64>)> = views
            .iter()
            .map(|(v, _, _)| (m(&v.cols), m(&v.rows)))
            .collect();
        let mut panels = Vec::new();
        for ((v, total, part), (cols, rows)) in views.iter().zip(&axes) {
            let (x_desc, y_desc, at) = match v.name {
                "plan" => (
                    "x (m)",
                    "y (m)",
                    format!("z = {} m", self.plan_z_mm / 1000.0),
                ),
                _ => (
                    "x (m)",
                    "z (m)",
                    format!("y = {} m", self.elevation_y_mm / 1000.0),
                ),
            };
            for (grid, what) in [(total, "u"), (part, "u from the calibration")] {
                panels.push(FieldView {
                    caption: format!("{}, {at}: {what} (µm)", v.name),
                    x_desc,
                    y_desc,
                    x_m: cols,
                    y_m: rows,
                    u_um: grid,
                });
            }
        }
        let title = format!(
            "Uncertainty of a measurement after calibration ({}; new readings: {} µrad, {} µm + {} ppm)",
            c.meta.name, noise.sigma_angle_urad, noise.sigma_range_um, noise.sigma_range_ppm
        );
        let svg = plots::uncertainty_field(&title, &panels)?;
        Ok(StageOutput::default()
            .table(
                "field",
                field.table(TableBuilder::new().str("view", &field.view), true)?,
            )
            .table(
                "measured",
                measured.table(
                    TableBuilder::new()
                        .str("target", &targets)
                        .i64("face", faces),
                    false,
                )?,
            )
            .file("uncertainty-field.svg".into(), svg.into_bytes()))
    }
}

/// The rows of `field` or `measured`: points and their uncertainties.
#[derive(Default)]
struct Rows {
    view: Vec<&'static str>,
    points: Vec<Vector3<f64>>,
    measured: Vec<Measured>,
}

impl Rows {
    fn push(&mut self, point: Vector3<f64>, m: &Measured) {
        self.points.push(point);
        self.measured.push(*m);
    }

    /// `b`'s leading columns, then the coordinates (with `d_mm` when
    /// `with_d`) and the uncertainty columns.
    fn table(&self, mut b: TableBuilder, with_d: bool) -> Result<DataFrame> {
        for (k, col) in ["x_mm", "y_mm", "z_mm"].iter().enumerate() {
            b = b.f64(col, self.points.iter().map(|p| p[k]).collect());
        }
        if with_d {
            b = b.f64("d_mm", self.points.iter().map(|p| p.norm()).collect());
        }
        let u = |f: &dyn Fn(&Measured) -> f64| self.measured.iter().map(f).collect::<Vec<f64>>();
        let values: [Vec<f64>; 6] = [
            u(&|m| m.cov()[(0, 0)].max(0.0).sqrt()),
            u(&|m| m.cov()[(1, 1)].max(0.0).sqrt()),
            u(&|m| m.cov()[(2, 2)].max(0.0).sqrt()),
            u(&|m| Measured::rms(&m.cov())),
            u(&|m| Measured::rms(&m.cov_cal)),
            u(&|m| Measured::rms(&m.cov_reading)),
        ];
        for (col, v) in COLUMNS_U.iter().zip(values) {
            b = b.f64(col, v);
        }
        b.build()
    }
}
