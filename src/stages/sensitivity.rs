//! `sensitivity`: Section 6 — the error each parameter of a tracker model produces
//! alone (1 µm or 1 µrad) over the spherical mesh, which of θ, φ and d it
//! varies with against the paper's statement, and Figures 11 and 12.
//!
//! ```toml
//! [stages.sensitivity]
//! kind = "sensitivity"
//! model = "api-tracker3"                       # or "mirror-tracker": its ten misalignments
//! h_deg = { from = 0, to = 363, step = 33 }    # optional: the paper's sphere by default
//! v_deg = { from = 77, to = -63, step = -20 }  #   (NOTES item 7), as the `mesh` stage's
//! r_mm = { from = 1000, to = 15000, step = 3500 }  # sphere settings
//! rel_tol = 1e-6                               # "varies": differs by more than this × the largest error
//! ```
//!
//! The mesh is given by settings rather than taken from a `mesh` stage: the
//! classification compares points equal in two of (az, el, d), which only a
//! spherical grid has; the defaults are exactly the `mesh` stage's sphere.
//!
//! Outputs:
//! * `field` — `parameter`, `target`, `az_deg`, `el_deg`, `d_mm`, `err_um`:
//!   the error (reported minus true point) of every mesh point, one
//!   parameter at a time (`az`, `el` of the reading convention; the paper's
//!   θ = az − 90°, φ = el).
//! * `classification` — `parameter`, `symbol`, `min_um`, `max_um`,
//!   `mean_um`, `varies_theta`, `varies_phi`, `varies_d`, `ours`, `paper`
//!   (Section 6's statement; empty for the mirror tracker, of which the
//!   paper says nothing), `agrees` (null there), `note` (why ours differs,
//!   in words).
//! * `extremes` — for the parameters whose error varies with θ or φ: where
//!   on a 1° grid of directions at the mesh's largest distance the error is
//!   largest and smallest (`parameter`, `symbol`, `d_mm`, `max_um`,
//!   `min_um`, `extremes`, `as_paper`): the check of the paper's reading of
//!   Figure 12.
//! * files `figure11.svg` (every mesh point's error, one panel per
//!   parameter) and `figure12.svg` (the variable errors against θ and φ).

use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput};
use crate::error_model::ParamId;
use crate::mesh::{self, Range};
use crate::plots::{self, DirectionCurves, ParamField};
use crate::sensitivity::{self, Classification, MeshSpan};
use crate::table::TableBuilder;
use crate::trackers::TrackerModel;
use anyhow::{Result, anyhow};
use nalgebra::Vector3;
use polars::prelude::DataFrame;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct SensitivityStage {
    /// The tracker model: `api-tracker3` or `mirror-tracker`.
    #[serde(default)]
    pub model: TrackerModel,
    /// The sphere's azimuths `{ from, to, step }`, degrees (the paper's by
    /// default).
    #[serde(default = "sphere_h_deg")]
    pub h_deg: Range,
    /// The sphere's elevations `{ from, to, step }`, degrees.
    #[serde(default = "sphere_v_deg")]
    pub v_deg: Range,
    /// The sphere's radii `{ from, to, step }`, mm.
    #[serde(default = "sphere_r_mm")]
    pub r_mm: Range,
    /// An error "varies" with θ, φ or d when it differs by more than this × the
    /// largest error.
    #[serde(default = "default_rel_tol")]
    pub rel_tol: f64,
}

/// Section 6's "1 µm for linear error parameters or 1 µrad for angular".
const VALUE: f64 = 1.0;
/// The direction grid of the Figure 12 check, degrees.
const GRID_STEP_DEG: f64 = 1.0;

// The paper's sphere (NOTES item 7) unless the file says otherwise.
fn sphere_h_deg() -> Range {
    mesh::SPHERE_H_DEG
}
fn sphere_v_deg() -> Range {
    mesh::SPHERE_V_DEG
}
fn sphere_r_mm() -> Range {
    mesh::SPHERE_R_MM
}

fn default_rel_tol() -> f64 {
    1e-6
}

impl SensitivityStage {
    fn ranges(&self) -> [(&'static str, &Range); 3] {
        [
            ("h_deg", &self.h_deg),
            ("v_deg", &self.v_deg),
            ("r_mm", &self.r_mm),
        ]
    }
}

impl StageKind for SensitivityStage {
    const KIND: &'static str = "sensitivity";
    const SUMMARY: &'static str = "Section 6: each parameter's error over the sphere, classified against the paper; Figures 11 and 12";
    const INPUTS: &'static [Slot] = &[];
    const OUTPUTS: &'static [&'static str] = &["classification", "field", "extremes"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "classification" => Some(&[
                "parameter",
                "symbol",
                "min_um",
                "max_um",
                "mean_um",
                "varies_theta",
                "varies_phi",
                "varies_d",
                "ours",
                "paper",
                "agrees",
                "note",
            ]),
            "extremes" => Some(&[
                "parameter",
                "symbol",
                "d_mm",
                "max_um",
                "min_um",
                "extremes",
                "as_paper",
            ]),
            "field" => Some(&["parameter", "target", "az_deg", "el_deg", "d_mm", "err_um"]),
            _ => None,
        }
    }

    fn validate(&self) -> Vec<Invalid> {
        let mut out = Vec::new();
        for (name, r) in self.ranges() {
            if let Err((part, msg)) = r.check() {
                out.push(Invalid::new(
                    format!("{name}.{part}"),
                    format!("`{name}.{part}` {msg}"),
                ));
            }
        }
        let n = mesh::grid_points(&[&self.h_deg, &self.v_deg, &self.r_mm]);
        if out.is_empty() && n > mesh::MAX_GRID_POINTS {
            out.push(Invalid::new(
                "r_mm",
                format!(
                    "the sphere has {n} points, more than the limit of {}: use fewer or coarser ranges",
                    mesh::MAX_GRID_POINTS
                ),
            ));
        }
        if let Some(r) = Some(&self.r_mm).filter(|r| r.from.min(r.to) <= 0.0) {
            out.push(Invalid::new(
                "r_mm.from",
                format!("`r_mm` must stay above zero, got {} … {}", r.from, r.to),
            ));
        }
        // At ±90° the azimuth of a point is undefined.
        if let Some(v) = Some(&self.v_deg).filter(|v| v.from.abs().max(v.to.abs()) >= 90.0) {
            out.push(Invalid::new(
                "v_deg.from",
                format!(
                    "`v_deg` must stay inside (−90, 90), got {} … {}",
                    v.from, v.to
                ),
            ));
        }
        if !(self.rel_tol > 0.0 && self.rel_tol < 1.0) {
            out.push(Invalid::new(
                "rel_tol",
                format!("`rel_tol` must lie in (0, 1), got {}", self.rel_tol),
            ));
        }
        out
    }

    fn run(&self, _: &Context, _: &StageInputs) -> Result<StageOutput> {
        let (h, v, r) = (&self.h_deg, &self.v_deg, &self.r_mm);
        let mesh = mesh::sphere(h, v, r);
        let pts: Vec<Vector3<f64>> = mesh.iter().map(|m| m.p).collect();
        let mut fields = Vec::new();
        for p in ParamId::of(self.model) {
            let f = sensitivity::error_field(p, VALUE, &pts)
                .map_err(|e| anyhow!("parameter {}: {e}", p.id()))?;
            fields.push((p, f));
        }
        let classes: Vec<Classification> = fields
            .iter()
            .map(|(_, f)| sensitivity::classify(f, self.rel_tol))
            .collect();

        let theta = grid(-180.0, 180.0 - GRID_STEP_DEG);
        let (vlo, vhi) = (v.from.min(v.to), v.from.max(v.to));
        let phi = grid(vlo, vhi);
        let d_max = r.from.max(r.to);
        let mut variable = Vec::new();
        for ((p, _), c) in fields.iter().zip(&classes) {
            if c.theta || c.phi {
                let g = sensitivity::direction_grid(*p, VALUE, &theta, &phi, d_max)
                    .map_err(|e| anyhow!("parameter {}: {e}", p.id()))?;
                variable.push((*p, g));
            }
        }

        let ids: Vec<&str> = mesh.iter().map(|m| m.id.as_str()).collect();
        let figure11: Vec<ParamField> = fields
            .iter()
            .map(|(p, f)| ParamField {
                label: format!("{} = 1 {}", p.symbol(), p.unit()),
                err_um: f.iter().map(|x| x.magnitude_um()).collect(),
                d_mm: f.iter().map(|x| x.at.d).collect(),
            })
            .collect();
        let mesh_phi: Vec<f64> = distinct(
            mesh.iter()
                .map(|m| m.p.z.atan2(m.p.xy().norm()).to_degrees()),
        );
        let mesh_theta: Vec<f64> = distinct(
            mesh.iter()
                .map(|m| wrap_deg(m.p.y.atan2(m.p.x).to_degrees() - 90.0)),
        );
        let figure12: Vec<DirectionCurves> = variable
            .iter()
            .map(|(p, g)| curves(*p, g, &theta, &phi, &mesh_theta, &mesh_phi))
            .collect();

        Ok(StageOutput::default()
            .table(
                "classification",
                classification_table(&fields, &classes, self.rel_tol)?,
            )
            .table("field", field_table(&fields, &ids)?)
            .table("extremes", extremes_table(&variable, &theta, &phi, d_max)?)
            .file(
                "figure11.svg".into(),
                plots::sensitivity_fields(
                    "Figure 11: error of every point of the spherical mesh, one parameter at a time",
                    &figure11,
                )?
                .into_bytes(),
            )
            .file(
                "figure12.svg".into(),
                plots::sensitivity_directions(
                    "Figure 12: the variable errors against θ and φ",
                    d_max,
                    &figure12,
                )?
                .into_bytes(),
            ))
    }
}

/// `from`, `from + 1°`, … `to`, and `to` itself when the step misses it.
fn grid(from: f64, to: f64) -> Vec<f64> {
    let mut v = Range::new(from, to, GRID_STEP_DEG).values();
    if v.last().is_some_and(|&x| (x - to).abs() > 1e-9) {
        v.push(to);
    }
    v
}

/// An angle in [−180°, 180°), like the direction grid's θ.
fn wrap_deg(a: f64) -> f64 {
    (a + 180.0).rem_euclid(360.0) - 180.0
}

fn distinct(v: impl Iterator<Item = f64>) -> Vec<f64> {
    let mut v: Vec<f64> = v.map(|x| (x * 1e9).round() / 1e9).collect();
    v.sort_by(f64::total_cmp);
    v.dedup();
    v
}

fn nearest(grid: &[f64], x: f64) -> usize {
    (0..grid.len())
        .min_by(|&a, &b| (grid[a] - x).abs().total_cmp(&(grid[b] - x).abs()))
        .expect("a non-empty grid")
}

/// Figure 12's curves of one parameter: against θ at the grid φ nearest
/// each mesh φ, against φ at the grid θ nearest each mesh θ.
fn curves(
    p: ParamId,
    g: &[Vec<f64>],
    theta: &[f64],
    phi: &[f64],
    mesh_theta: &[f64],
    mesh_phi: &[f64],
) -> DirectionCurves {
    let by_theta = mesh_phi
        .iter()
        .map(|&f| {
            let i = nearest(phi, f);
            (phi[i], g[i].clone())
        })
        .collect();
    let by_phi = mesh_theta
        .iter()
        .map(|&t| {
            let j = nearest(theta, t);
            (theta[j], g.iter().map(|row| row[j]).collect())
        })
        .collect();
    DirectionCurves {
        label: format!("{} = 1 {}", p.symbol(), p.unit()),
        theta_deg: theta.to_vec(),
        by_theta,
        phi_deg: phi.to_vec(),
        by_phi,
    }
}

fn classification_table(
    fields: &[(ParamId, Vec<sensitivity::FieldPoint>)],
    classes: &[Classification],
    rel_tol: f64,
) -> Result<DataFrame> {
    let stats: Vec<(f64, f64, f64)> = fields
        .iter()
        .map(|(_, f)| {
            let e: Vec<f64> = f.iter().map(|x| x.magnitude_um()).collect();
            let min = e.iter().copied().fold(f64::INFINITY, f64::min);
            let max = e.iter().copied().fold(0.0, f64::max);
            (min, max, e.iter().sum::<f64>() / e.len().max(1) as f64)
        })
        .collect();
    let params: Vec<ParamId> = fields.iter().map(|f| f.0).collect();
    let notes: Vec<String> = fields
        .iter()
        .zip(classes)
        .map(|((p, f), c)| sensitivity::explain_difference(*p, c, MeshSpan::of(f), rel_tol))
        .collect();
    TableBuilder::new()
        .str(
            "parameter",
            &params.iter().map(|p| p.id()).collect::<Vec<_>>(),
        )
        .str(
            "symbol",
            &params.iter().map(|p| p.symbol()).collect::<Vec<_>>(),
        )
        .f64("min_um", stats.iter().map(|s| s.0).collect())
        .f64("max_um", stats.iter().map(|s| s.1).collect())
        .f64("mean_um", stats.iter().map(|s| s.2).collect())
        .bool("varies_theta", classes.iter().map(|c| c.theta).collect())
        .bool("varies_phi", classes.iter().map(|c| c.phi).collect())
        .bool("varies_d", classes.iter().map(|c| c.d).collect())
        .str(
            "ours",
            &classes
                .iter()
                .map(Classification::describe)
                .collect::<Vec<_>>(),
        )
        .str(
            "paper",
            &params
                .iter()
                .map(|&p| sensitivity::paper_statement(p).unwrap_or(""))
                .collect::<Vec<_>>(),
        )
        .opt_bool(
            "agrees",
            params
                .iter()
                .zip(classes)
                .map(|(&p, c)| sensitivity::paper_classification(p).map(|paper| *c == paper))
                .collect(),
        )
        .str("note", &notes)
        .build()
}

fn field_table(
    fields: &[(ParamId, Vec<sensitivity::FieldPoint>)],
    ids: &[&str],
) -> Result<DataFrame> {
    let rows = || {
        fields
            .iter()
            .flat_map(|(p, f)| f.iter().map(move |x| (*p, x)))
    };
    TableBuilder::new()
        .str(
            "parameter",
            &rows().map(|(p, _)| p.id()).collect::<Vec<_>>(),
        )
        .str(
            "target",
            &fields
                .iter()
                .flat_map(|(_, f)| ids.iter().take(f.len()))
                .collect::<Vec<_>>(),
        )
        .f64(
            "az_deg",
            rows().map(|(_, x)| x.at.az.to_degrees()).collect(),
        )
        .f64(
            "el_deg",
            rows().map(|(_, x)| x.at.el.to_degrees()).collect(),
        )
        .f64("d_mm", rows().map(|(_, x)| x.at.d).collect())
        .f64("err_um", rows().map(|(_, x)| x.magnitude_um()).collect())
        .build()
}

fn extremes_table(
    variable: &[(ParamId, Vec<Vec<f64>>)],
    theta: &[f64],
    phi: &[f64],
    d_mm: f64,
) -> Result<DataFrame> {
    let ex: Vec<sensitivity::Extremes> = variable
        .iter()
        .map(|(_, g)| sensitivity::extremes(g, theta, phi))
        .collect();
    TableBuilder::new()
        .str(
            "parameter",
            &variable.iter().map(|v| v.0.id()).collect::<Vec<_>>(),
        )
        .str(
            "symbol",
            &variable.iter().map(|v| v.0.symbol()).collect::<Vec<_>>(),
        )
        .f64("d_mm", vec![d_mm; variable.len()])
        .f64("max_um", ex.iter().map(|e| e.max_um).collect())
        .f64("min_um", ex.iter().map(|e| e.min_um).collect())
        .str(
            "extremes",
            &ex.iter()
                .map(|e| e.describe(theta, phi))
                .collect::<Vec<_>>(),
        )
        .bool(
            "as_paper",
            ex.iter().map(|e| e.as_paper(theta, phi)).collect(),
        )
        .build()
}
