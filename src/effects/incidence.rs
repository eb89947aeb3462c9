//! `incidence` — the SMR's vertex offset: a reflector whose optical centre
//! is not its sphere's centre reads a distance that depends on the angle at
//! which the beam enters it (effects.md; the paper's Section 10).

use super::{DrawContext, Drawn, Effect, Forward, IncidenceAngles, Place, finite};
use crate::diagnose::candidates::{Context, Found, first, put_d};
use crate::diagnose::linear::Signature;
use crate::kinematics::Reading;
use crate::random;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// `incidence` — SMR vertex offset.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Incidence {
    #[serde(default)]
    pub e_axial_um: f64,
    #[serde(default)]
    pub e_h_um: f64,
    #[serde(default)]
    pub e_v_um: f64,
    #[serde(default = "default_max_angle")]
    pub max_angle_deg: f64,
}

fn default_max_angle() -> f64 {
    super::DEFAULT_MAX_ANGLE_DEG
}

impl Incidence {
    /// `Δd = e_axial·(1 − cos α) + e_h·sin α_h + e_v·sin α_v`, in µm.
    pub fn delta_d_um(&self, a: &IncidenceAngles) -> f64 {
        self.e_axial_um * (1.0 - a.alpha.cos())
            + self.e_h_um * a.alpha_h.sin()
            + self.e_v_um * a.alpha_v.sin()
    }
}

impl Forward for Incidence {
    /// effects.md: "a reading with α over max_angle_deg is not taken".
    fn max_angle_deg(&self) -> Option<f64> {
        Some(self.max_angle_deg)
    }

    fn delta_d_mm(&self, _: &Place, _: &Reading, a: &IncidenceAngles, _: f64) -> Option<f64> {
        Some(self.delta_d_um(a) * 1e-3)
    }
}

/// The reason both incidence models give when the axes are unknown.
pub(super) const NO_AXES: &str =
    "the SMR axes are unknown: no aim point usable in this frame and no aim rule";

impl Effect for Incidence {
    const ID: &'static str = "incidence";
    const SUMMARY: &'static str =
        "SMR vertex offset: Δd = e_axial·(1 − cos α) + e_h·sin α_h + e_v·sin α_v";

    fn check(&self) -> Vec<(String, String)> {
        let mut out = Vec::new();
        finite(&mut out, "e_axial_um", self.e_axial_um);
        finite(&mut out, "e_h_um", self.e_h_um);
        finite(&mut out, "e_v_um", self.e_v_um);
        if !(self.max_angle_deg > 0.0 && self.max_angle_deg <= 90.0) {
            out.push((
                "max_angle_deg".into(),
                format!(
                    "`max_angle_deg` must lie in (0, 90], got {}",
                    self.max_angle_deg
                ),
            ));
        }
        out
    }

    /// One candidate of three columns (axial, h, v), on the readings whose
    /// SMR axis is known: a reflector without an aim point contributes
    /// nothing to them.
    fn candidates(cx: &Context, out: &mut Found) {
        if cx.incidence_known() == 0 {
            return out.skip(Self::ID, NO_AXES);
        }
        let mut c = Signature::new(3);
        for (i, r) in cx.readings.iter().enumerate() {
            let Some(a) = r.incidence else { continue };
            put_d(&mut c, i, r, 0, 1e-3 * (1.0 - a.alpha.cos()));
            put_d(&mut c, i, r, 1, 1e-3 * a.alpha_h.sin());
            put_d(&mut c, i, r, 2, 1e-3 * a.alpha_v.sin());
        }
        out.push(Self::ID, "all", c, Arc::new(first), "µm");
        if let Some(last) = out.candidates.last_mut() {
            last.detail = cx.incidence_detail();
        }
    }

    /// An axial offset of 30–300 µm, side offsets within ±20 % of it.
    fn draw(rng: &mut ChaCha8Rng, cx: &DrawContext) -> Drawn<Self> {
        let e = cx.size * random::log_uniform(rng, 30.0, 300.0, false);
        let effect = Incidence {
            e_axial_um: e,
            e_h_um: 0.2 * e * (2.0 * random::uniform(rng) - 1.0),
            e_v_um: 0.2 * e * (2.0 * random::uniform(rng) - 1.0),
            max_angle_deg: super::DEFAULT_MAX_ANGLE_DEG,
        };
        Drawn {
            effect,
            place: "all".into(),
            magnitude: e,
            has_place: false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn incidence_delta_d_by_hand() {
        let e = Incidence {
            e_axial_um: 200.0,
            e_h_um: -20.0,
            e_v_um: 10.0,
            max_angle_deg: 30.0,
        };
        let a = IncidenceAngles {
            alpha: 0.3,
            alpha_h: 0.2,
            alpha_v: -0.1,
        };
        let expect = 200.0 * (1.0 - 0.3f64.cos()) - 20.0 * 0.2f64.sin() + 10.0 * (-0.1f64).sin();
        assert_eq!(e.delta_d_um(&a), expect);
    }
}
