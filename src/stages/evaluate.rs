//! `evaluate`: Eq. (12) per point, before and after calibration, and the
//! summary the paper's headline comes from (Section 5.1: "reduces the LT
//! error more than 98 %").
//!
//! ```toml
//! [stages.evaluate_sphere]
//! kind = "evaluate"
//! inputs = { readings = "measure_sphere", corrected = "correct_sphere" }
//! ```
//!
//! Eq. (12) as extracted is the squared distance; the error of a point is its
//! distance, `errᵢ = ‖Pᵢ − Pᵢ,nom‖`, in µm.
//!
//! Outputs: `points` (`target`, `face`, `x_ref_mm`, `y_ref_mm`, `z_ref_mm`,
//! `err_before_um`, `err_after_um`) and `summary` (`statistic` = mean, rms,
//! max; `before_um`, `after_um`, `reduction_pct`).

use super::{Context, Slot, StageInputs, StageKind, StageOutput};
use crate::criteria::improvement_pct;
use crate::schema;
use crate::table::TableBuilder;
use anyhow::{Result, bail};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Default, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct EvaluateStage {}

/// Mean, RMS and maximum of a list of errors.
pub fn stats(e: &[f64]) -> [f64; 3] {
    let n = e.len().max(1) as f64;
    [
        e.iter().sum::<f64>() / n,
        (e.iter().map(|x| x * x).sum::<f64>() / n).sqrt(),
        e.iter().copied().fold(0.0, f64::max),
    ]
}

impl StageKind for EvaluateStage {
    const KIND: &'static str = "evaluate";
    const SUMMARY: &'static str =
        "Eq. (12) per point before and after calibration; mean, RMS, max and reduction %";
    const INPUTS: &'static [Slot] = &[
        Slot::table(
            "readings",
            true,
            "readings with reported and reference coordinates",
        ),
        Slot::table(
            "corrected",
            true,
            "the same readings corrected (a `correct` stage)",
        ),
    ];
    const OUTPUTS: &'static [&'static str] = &["summary", "points"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "points" => Some(&[
                "target",
                "face",
                "x_ref_mm",
                "y_ref_mm",
                "z_ref_mm",
                "err_before_um",
                "err_after_um",
            ]),
            "summary" => Some(&["statistic", "before_um", "after_um", "reduction_pct"]),
            _ => None,
        }
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let rt = inputs.get("readings")?;
        let ct = inputs.get("corrected")?;
        let readings = schema::readings_from(&rt)?;
        let reported = [rt.f64("x_mm")?, rt.f64("y_mm")?, rt.f64("z_mm")?];
        let corrected = [ct.f64("x_mm")?, ct.f64("y_mm")?, ct.f64("z_mm")?];
        let ids = ct.str("target")?;
        if ids.len() != readings.len() || ids.iter().zip(&readings).any(|(a, r)| *a != r.target) {
            bail!(
                "`{}` and `{}` do not list the same readings in the same order",
                rt.name,
                ct.name
            );
        }
        let at = |c: &[Vec<f64>; 3], i: usize| Vector3::new(c[0][i], c[1][i], c[2][i]);
        let before: Vec<f64> = (0..readings.len())
            .map(|i| (at(&reported, i) - readings[i].reference).norm() * 1e3)
            .collect();
        let after: Vec<f64> = (0..readings.len())
            .map(|i| (at(&corrected, i) - readings[i].reference).norm() * 1e3)
            .collect();
        let points = TableBuilder::new()
            .str("target", &ids)
            .i64("face", readings.iter().map(|r| r.face.number()).collect())
            .f64("x_ref_mm", readings.iter().map(|r| r.reference.x).collect())
            .f64("y_ref_mm", readings.iter().map(|r| r.reference.y).collect())
            .f64("z_ref_mm", readings.iter().map(|r| r.reference.z).collect())
            .f64("err_before_um", before.clone())
            .f64("err_after_um", after.clone())
            .build()?;
        let (b, a) = (stats(&before), stats(&after));
        let summary = TableBuilder::new()
            .str("statistic", &["mean", "rms", "max"])
            .f64("before_um", b.to_vec())
            .f64("after_um", a.to_vec())
            .f64(
                "reduction_pct",
                (0..3).map(|k| improvement_pct(b[k], a[k])).collect(),
            )
            .build()?;
        Ok(StageOutput::default()
            .table("summary", summary)
            .table("points", points))
    }
}
