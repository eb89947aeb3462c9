//! `measure`: the readings a tracker with error parameters takes of a mesh
//! (Section 5.1), optionally with seeded reading noise.
//!
//! ```toml
//! [stages.measure_sphere]
//! kind = "measure"
//! inputs = { points = "sphere", errors = "truth" }   # errors: optional (a perfect tracker)
//! face = "front"               # "front", "back" or "both"
//! noise = { sigma_angle_urad = 1.0, sigma_range_um = 2.0 }   # optional, 1 σ
//! seed = 1
//! ```
//!
//! Output `readings` (see [`crate::schema`]): the reading of each point in
//! each face, the coordinates the tracker reports, the true position, and
//! the noise drawn (so that `identify` uses it without being told).

use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput};
use crate::kinematics::Face;
use crate::noise::Noise;
use crate::random;
use crate::schema::{self, KnownReading};
use crate::simulate;
use anyhow::{Result, anyhow};
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Faces {
    #[default]
    Front,
    Back,
    Both,
}

impl Faces {
    pub fn list(self) -> &'static [Face] {
        match self {
            Faces::Front => &[Face::Front],
            Faces::Back => &[Face::Back],
            Faces::Both => &[Face::Front, Face::Back],
        }
    }
}

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct MeasureStage {
    /// Which faces are read: `front`, `back` or `both`.
    #[serde(default)]
    pub face: Faces,
    /// Reading noise, 1 σ: `{ sigma_angle_urad, sigma_range_um, sigma_range_ppm
    /// }`; none by default.
    #[serde(default)]
    pub noise: Noise,
    /// Seed of the noise draws.
    #[serde(default)]
    pub seed: u64,
}

impl StageKind for MeasureStage {
    const KIND: &'static str = "measure";
    const SUMMARY: &'static str =
        "readings of a mesh by a tracker with error parameters, solved exactly, plus seeded noise";
    const INPUTS: &'static [Slot] = &[
        Slot::table("points", true, "reflector positions (a `mesh` stage)"),
        Slot::table(
            "errors",
            false,
            "the tracker's error parameters (an `inject` stage); none: a perfect tracker",
        ),
    ];
    const OUTPUTS: &'static [&'static str] = &["readings"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "readings" => Some(&[
                "target",
                "face",
                "az_deg",
                "el_deg",
                "d_mm",
                "x_mm",
                "y_mm",
                "z_mm",
                "x_ref_mm",
                "y_ref_mm",
                "z_ref_mm",
                "sigma_angle_urad",
                "sigma_range_um",
                "sigma_range_ppm",
            ]),
            _ => None,
        }
    }

    fn validate(&self) -> Vec<Invalid> {
        Invalid::noise(&self.noise).into_iter().collect()
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let points = schema::points_from(&inputs.get("points")?)?;
        let errors = inputs
            .optional("errors")
            .map(|t| schema::params_from(&t))
            .transpose()?;
        // The stream depends on the settings only (not the stage name), so that
        // the cache key determines the output.
        let mut rng = random::stream(self.seed, "measure");
        let mut rows = Vec::with_capacity(points.len() * 2);
        for pt in &points {
            for &face in self.face.list() {
                let exact = simulate::read(errors.as_ref(), &pt.p, face)
                    .map_err(|e| anyhow!("point {} ({:.1?}): {e}", pt.id, pt.p.as_slice()))?;
                rows.push(KnownReading {
                    target: pt.id.clone(),
                    face,
                    reading: self.noise.apply(exact, &mut rng).wrapped(),
                    reference: pt.p,
                });
            }
        }
        Ok(StageOutput::default().table("readings", schema::readings_table(&rows, &self.noise)?))
    }
}
