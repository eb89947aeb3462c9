//! The tables stages exchange, column by column. These are the stable,
//! documented columns a user reads; the README lists them. Not a leaf:
//! it turns the domain's points, parameters and readings into these
//! tables and back, which is the stages' work, so it lives with them (the
//! domain never names it; `crate::schema` is kept as a path to it).
//!
//! * **points** — `target` (id), `x_mm`, `y_mm`, `z_mm`: reflector centres in
//!   the station frame.
//! * **params** — one row per coefficient: `coef` (`dx1`, `ez1.sin2`,
//!   `dz3.d2`), `param` (`dx1` … `ez3`), `symbol` (`δx1`, `εz1·sin2θ`),
//!   `unit` (`µm`, `µrad`, `µm/m²`), `value`; identification adds `free`,
//!   `std` (standard uncertainty, same unit) and `determined`.
//! * **readings** (Section 5.1) — `target`, `face` (1 front, 2 back),
//!   `az_deg`, `el_deg`, `d_mm` (the reading), `x_mm`, `y_mm`, `z_mm` (the
//!   coordinates the tracker reports: the nominal model at the reading), and
//!   `x_ref_mm`, `y_ref_mm`, `z_ref_mm` (the true position), then the
//!   reading noise they were taken with, 1 σ: `sigma_angle_urad`,
//!   `sigma_range_um`, `sigma_range_ppm` (the same on every row; zero: none
//!   drawn), so that an identification downstream knows it.

use crate::error_model::{Coef, ErrorParams};
use crate::kinematics::{Face, Reading, nominal_point};
use crate::mesh::MeshPoint;
use crate::noise::Noise;
use crate::table::{TableBuilder, TableRef};
use anyhow::{Result, anyhow, bail};
use nalgebra::Vector3;
use polars::prelude::DataFrame;
use std::collections::BTreeSet;

pub fn points_table(points: &[MeshPoint]) -> Result<DataFrame> {
    let ids: Vec<&str> = points.iter().map(|p| p.id.as_str()).collect();
    TableBuilder::new()
        .str("target", &ids)
        .f64("x_mm", points.iter().map(|p| p.p.x).collect())
        .f64("y_mm", points.iter().map(|p| p.p.y).collect())
        .f64("z_mm", points.iter().map(|p| p.p.z).collect())
        .build()
}

pub fn points_from(t: &TableRef) -> Result<Vec<MeshPoint>> {
    let ids = t.str("target")?;
    let (x, y, z) = (t.f64("x_mm")?, t.f64("y_mm")?, t.f64("z_mm")?);
    Ok(ids
        .into_iter()
        .enumerate()
        .map(|(i, id)| MeshPoint {
            id,
            p: Vector3::new(x[i], y[i], z[i]),
        })
        .collect())
}

/// The extra columns an identification adds to a params table.
pub struct IdentifiedColumns {
    pub free: Vec<bool>,
    pub std: Vec<Option<f64>>,
    /// Whether the coefficient is fully determined by the data (not part of
    /// any undetermined direction).
    pub determined: Vec<bool>,
}

pub fn params_table(p: &ErrorParams, extra: Option<&IdentifiedColumns>) -> Result<DataFrame> {
    let coefs = p.coefs();
    let names: Vec<String> = coefs.iter().map(Coef::name).collect();
    let params: Vec<&str> = coefs.iter().map(|c| c.param.id()).collect();
    let symbols: Vec<String> = coefs.iter().map(Coef::symbol).collect();
    let units: Vec<String> = coefs.iter().map(Coef::unit).collect();
    let mut b = TableBuilder::new()
        .str("coef", &names)
        .str("param", &params)
        .str("symbol", &symbols)
        .str("unit", &units)
        .f64("value", p.values().to_vec());
    if let Some(x) = extra {
        b = b
            .bool("free", x.free.clone())
            .opt_f64("std", x.std.clone())
            .bool("determined", x.determined.clone());
    }
    b.build()
}

pub fn params_from(t: &TableRef) -> Result<ErrorParams> {
    let names = t.str("coef")?;
    let values = t.f64("value")?;
    let mut coefs = Vec::with_capacity(names.len());
    let mut seen = BTreeSet::new();
    for (i, n) in names.iter().enumerate() {
        let c = Coef::parse(n).ok_or_else(|| {
            anyhow!(
                "table `{}`, row {i}: `{n}` is not a coefficient name (dx1 … ez3, optionally .sinK, .cosK or .dK, or a mirror tracker's misalignment)",
                t.name
            )
        })?;
        if !seen.insert(c) {
            bail!(
                "table `{}`, row {i}: coefficient `{n}` appears twice",
                t.name
            );
        }
        if !values[i].is_finite() {
            bail!("table `{}`, row {i}: value of `{n}` is not finite", t.name);
        }
        coefs.push(c);
    }
    if let Err((a, b)) = ErrorParams::tracker_of(&coefs) {
        bail!(
            "table `{}`: `{}` is a parameter of the {} model and `{}` of the {} model; \
             a parameter set describes one tracker",
            t.name,
            a.name(),
            a.param.tracker(),
            b.name(),
            b.param.tracker()
        );
    }
    Ok(ErrorParams::from_parts(coefs, values))
}

/// A Section 5.1 reading with the true position of its reflector.
#[derive(Clone, Debug)]
pub struct KnownReading {
    pub target: String,
    pub face: Face,
    pub reading: Reading,
    pub reference: Vector3<f64>,
}

pub fn readings_table(rows: &[KnownReading], noise: &Noise) -> Result<DataFrame> {
    let ids: Vec<&str> = rows.iter().map(|r| r.target.as_str()).collect();
    let reported: Vec<Vector3<f64>> = rows.iter().map(|r| nominal_point(r.reading)).collect();
    let col = |f: &dyn Fn(&KnownReading) -> f64| rows.iter().map(f).collect::<Vec<f64>>();
    TableBuilder::new()
        .str("target", &ids)
        .i64("face", rows.iter().map(|r| r.face.number()).collect())
        .f64("az_deg", col(&|r| r.reading.az.to_degrees()))
        .f64("el_deg", col(&|r| r.reading.el.to_degrees()))
        .f64("d_mm", col(&|r| r.reading.d))
        .f64("x_mm", reported.iter().map(|p| p.x).collect())
        .f64("y_mm", reported.iter().map(|p| p.y).collect())
        .f64("z_mm", reported.iter().map(|p| p.z).collect())
        .f64("x_ref_mm", col(&|r| r.reference.x))
        .f64("y_ref_mm", col(&|r| r.reference.y))
        .f64("z_ref_mm", col(&|r| r.reference.z))
        .f64("sigma_angle_urad", col(&|_| noise.sigma_angle_urad))
        .f64("sigma_range_um", col(&|_| noise.sigma_range_um))
        .f64("sigma_range_ppm", col(&|_| noise.sigma_range_ppm))
        .build()
}

/// The reading noise a readings table carries: `None` when it has no noise
/// columns (written before they existed) or no rows; an error when the rows
/// disagree or a σ is not a number ≥ 0.
pub fn readings_noise(t: &TableRef) -> Result<Option<Noise>> {
    const COLS: [&str; 3] = ["sigma_angle_urad", "sigma_range_um", "sigma_range_ppm"];
    if !COLS.iter().all(|c| t.has(c)) {
        return Ok(None);
    }
    let [a, r, p] = COLS.map(|c| t.f64(c));
    let (a, r, p) = (a?, r?, p?);
    if a.is_empty() {
        return Ok(None);
    }
    let noise = Noise {
        sigma_angle_urad: a[0],
        sigma_range_um: r[0],
        sigma_range_ppm: p[0],
    };
    if let Err((f, v)) = noise.check() {
        bail!(
            "table `{}`, column `{f}`, row 0: must be a number ≥ 0, got {v}",
            t.name
        );
    }
    if let Some(i) = (0..a.len()).find(|&i| (a[i], r[i], p[i]) != (a[0], r[0], p[0])) {
        bail!(
            "table `{}`, row {i}: its reading noise differs from row 0's; \
             the readings of one identification share one noise",
            t.name
        );
    }
    Ok(Some(noise))
}

pub fn readings_from(t: &TableRef) -> Result<Vec<KnownReading>> {
    let ids = t.str("target")?;
    let faces = t.i64("face")?;
    let (az, el, d) = (t.f64("az_deg")?, t.f64("el_deg")?, t.f64("d_mm")?);
    let (x, y, z) = (t.f64("x_ref_mm")?, t.f64("y_ref_mm")?, t.f64("z_ref_mm")?);
    ids.into_iter()
        .enumerate()
        .map(|(i, target)| {
            let face = Face::from_number(faces[i]).ok_or_else(|| {
                anyhow!(
                    "table `{}`, row {i}: face must be 1 or 2, got {}",
                    t.name,
                    faces[i]
                )
            })?;
            Ok(KnownReading {
                target,
                face,
                reading: Reading {
                    az: az[i].to_radians(),
                    el: el[i].to_radians(),
                    d: d[i],
                },
                reference: Vector3::new(x[i], y[i], z[i]),
            })
        })
        .collect()
}

/// Corrected coordinates: `target`, `face`, `x_mm`, `y_mm`, `z_mm`.
pub fn corrected_table(ids: &[&str], faces: &[Face], pts: &[Vector3<f64>]) -> Result<DataFrame> {
    TableBuilder::new()
        .str("target", ids)
        .i64("face", faces.iter().map(|f| f.number()).collect())
        .f64("x_mm", pts.iter().map(|p| p.x).collect())
        .f64("y_mm", pts.iter().map(|p| p.y).collect())
        .f64("z_mm", pts.iter().map(|p| p.z).collect())
        .build()
}
