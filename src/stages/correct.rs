//! `correct`: readings corrected with error parameters — Eq. (8) evaluated at
//! each reading's joints.
//!
//! ```toml
//! [stages.correct_sphere]
//! kind = "correct"
//! inputs = { readings = "measure_sphere", params = "identify_sphere" }
//! ```
//!
//! Output `corrected`: `target`, `face`, `x_mm`, `y_mm`, `z_mm`.

use super::{Context, Slot, StageInputs, StageKind, StageOutput};
use crate::error_model::Links;
use crate::schema;
use anyhow::Result;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Default, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct CorrectStage {}

impl StageKind for CorrectStage {
    const KIND: &'static str = "correct";
    const SUMMARY: &'static str = "readings corrected with error parameters (Eq. 8)";
    const INPUTS: &'static [Slot] = &[
        Slot::table("readings", true, "the readings to correct"),
        Slot::table(
            "params",
            true,
            "error parameters (an `identify` or `inject` stage)",
        ),
    ];
    const OUTPUTS: &'static [&'static str] = &["corrected"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "corrected" => Some(&["target", "face", "x_mm", "y_mm", "z_mm"]),
            _ => None,
        }
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let readings = schema::readings_from(&inputs.get("readings")?)?;
        let params = schema::params_from(&inputs.get("params")?)?;
        let eval = params.evaluator();
        let pts: Vec<_> = readings
            .iter()
            .map(|r| {
                let q = r.reading.joints();
                eval.point(q, &Links::new(q))
            })
            .collect();
        let ids: Vec<&str> = readings.iter().map(|r| r.target.as_str()).collect();
        let faces: Vec<_> = readings.iter().map(|r| r.face).collect();
        Ok(StageOutput::default().table("corrected", schema::corrected_table(&ids, &faces, &pts)?))
    }
}
