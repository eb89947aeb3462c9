//! `encoder-harmonic` — an angle encoder's error with a harmonic of order
//! 2 or more (a first harmonic is an eccentricity, which the kinematic
//! model already holds).

use super::{DrawContext, Drawn, Effect, Forward, finite};
use crate::diagnose::candidates::{Candidate, Context, Found, norm};
use crate::diagnose::linear::Signature;
use crate::kinematics::Reading;
use crate::random;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// The axis an encoder harmonic acts on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Axis {
    #[default]
    Az,
    El,
}

/// `encoder-harmonic` — angle error with a higher harmonic.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderHarmonic {
    #[serde(default)]
    pub axis: Axis,
    pub order: u32,
    pub amplitude_urad: f64,
    #[serde(default)]
    pub phase_deg: f64,
}

impl EncoderHarmonic {
    /// `amplitude_urad·1e-6·sin(order·angle + phase_deg)`, rad, where `angle`
    /// is the reading's az (or el) in radians.
    pub fn delta_rad(&self, angle: f64) -> f64 {
        self.amplitude_urad * 1e-6 * (self.order as f64 * angle + self.phase_deg.to_radians()).sin()
    }
}

impl Forward for EncoderHarmonic {
    fn move_angles(&self, r: &mut Reading) {
        match self.axis {
            Axis::Az => r.az += self.delta_rad(r.az),
            Axis::El => r.el += self.delta_rad(r.el),
        }
    }
}

/// The orders the diagnosis tries on each axis; the best is chosen later
/// (and counted in the multiple-testing correction).
const ORDERS: std::ops::RangeInclusive<u32> = 2..=4;

impl Effect for EncoderHarmonic {
    const ID: &'static str = "encoder-harmonic";
    const SUMMARY: &'static str =
        "an encoder harmonic: Δaz (or Δel) = amplitude·sin(order·angle + phase), order ≥ 2";

    fn check(&self) -> Vec<(String, String)> {
        let mut out = Vec::new();
        finite(&mut out, "amplitude_urad", self.amplitude_urad);
        finite(&mut out, "phase_deg", self.phase_deg);
        if self.order < 2 {
            out.push((
                "order".into(),
                format!(
                    "`order` must be ≥ 2 (a first harmonic is an eccentricity the kinematic model holds), got {}",
                    self.order
                ),
            ));
        }
        out
    }

    /// Orders 2–4 on each axis, a sine and a cosine column each.
    fn candidates(cx: &Context, out: &mut Found) {
        for (axis, a) in [("az", 0usize), ("el", 1usize)] {
            for order in ORDERS {
                let mut c = Signature::new(2);
                for (i, r) in cx.readings.iter().enumerate() {
                    let angle = if a == 0 { r.az } else { r.el };
                    let k = order as f64 * angle;
                    c.add(i, a, 0, 1e-6 * k.sin() / r.sigma[a]);
                    c.add(i, a, 1, 1e-6 * k.cos() / r.sigma[a]);
                }
                out.candidates.push(Candidate {
                    effect: Self::ID.into(),
                    place: axis.into(),
                    columns: c,
                    magnitude: Arc::new(norm),
                    unit: "µrad".into(),
                    alternatives: ORDERS.count(),
                    detail: format!("order {order}"),
                });
            }
        }
    }

    /// Either axis, order 2–4, 3–25 µrad, any phase.
    fn draw(rng: &mut ChaCha8Rng, cx: &DrawContext) -> Drawn<Self> {
        let axis = if random::uniform(rng) < 0.5 {
            Axis::Az
        } else {
            Axis::El
        };
        let amp = cx.size * random::log_uniform(rng, 3.0, 25.0, false);
        let effect = EncoderHarmonic {
            axis,
            order: 2 + (random::uniform(rng) * 3.0) as u32 % 3,
            amplitude_urad: amp,
            phase_deg: 360.0 * random::uniform(rng),
        };
        Drawn {
            effect,
            place: if axis == Axis::Az { "az" } else { "el" }.into(),
            magnitude: amp,
            has_place: true,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn encoder_harmonic_by_hand() {
        let e = EncoderHarmonic {
            axis: Axis::Az,
            order: 3,
            amplitude_urad: 12.0,
            phase_deg: 90.0,
        };
        assert!((e.delta_rad(0.0) - 12e-6).abs() < 1e-18);
        let mut r = Reading {
            az: 0.0,
            el: 0.2,
            d: 1000.0,
        };
        e.move_angles(&mut r);
        assert!((r.az - 12e-6).abs() < 1e-18 && r.el == 0.2, "{r:?}");
    }
}
