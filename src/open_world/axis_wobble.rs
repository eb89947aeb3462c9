//! `axis-wobble` — the standing (azimuth) axis tilts as it turns.
//!
//! A bearing's races are not perfectly round: as the head turns, the
//! standing axis leans by a few µrad in a direction that repeats `k` times
//! per turn. The top of the axis leans towards, in the station frame,
//!
//! ```text
//! δ(az) = w·(cos(k·az + φ), sin(k·az + φ))        (rad)
//! ```
//!
//! A once-per-turn lean (`k = 1`) turns with the head: it is a fixed
//! misalignment of the head, which the kinematic model absorbs (it reduces
//! to a vertical index offset and a transit tilt), so `k` is 2 or 3.
//!
//! The lean is a rotation of the head by `ω = (−δy, δx, 0)` (it takes `ẑ`
//! to `ẑ + (δx, δy, 0)`). The tracker locks on the reflector, so its beam
//! `R(ω)·u(az, el)` is the true direction `u_true`, and it reads the
//! direction `u(az, el) = R(ω)ᵀ·u_true ≈ u_true − ω × u_true`. With
//! `u = (cos el·cos az, cos el·sin az, sin el)`, to first order in `w`:
//!
//! ```text
//! Δel = δx·cos az + δy·sin az            = w·cos((k−1)·az + φ)
//! Δaz = tan el·(δx·sin az − δy·cos az)   = −w·tan el·sin((k−1)·az + φ)
//! ```
//!
//! with `az`, `el` the reading's own (the back face's too: its `az` is the
//! head's, and the formula holds for any `(az, el)` of the direction). The
//! neglected terms are of order `w²` (< 1e-9 rad). Where the axis pivots
//! on its bearing also shifts the beam's origin by (pivot height)·`w`,
//! about 1 µm for 100 mm at 10 µrad: neglected.
//!
//! Magnitudes: `w` 3–20 µrad (precision spindle bearings run out by
//! 1–5 µm over a 100–300 mm base). The same instrument at every station.
//!
//! Factor `az`: a function of the head's azimuth (times `tan el` in az).

use super::{between, log_uniform};
use crate::simulate::SimulatedCampaign;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AxisWobble {
    /// Leans per turn, 2 or 3.
    pub order: u32,
    pub amplitude_urad: f64,
    pub phase_deg: f64,
}

impl AxisWobble {
    /// `k` 2 or 3, `w` log-uniform in 3–20 µrad, `φ` uniform.
    pub fn draw(rng: &mut ChaCha8Rng) -> AxisWobble {
        AxisWobble {
            order: if crate::random::uniform(rng) < 0.5 {
                2
            } else {
                3
            },
            amplitude_urad: log_uniform(rng, 3.0, 20.0),
            phase_deg: between(rng, 0.0, 360.0),
        }
    }

    /// The lean `δ(az)` of the axis's top (rad, station frame x and y).
    pub fn lean_rad(&self, az_rad: f64) -> (f64, f64) {
        let w = self.amplitude_urad * 1e-6;
        let a = f64::from(self.order) * az_rad + self.phase_deg.to_radians();
        (w * a.cos(), w * a.sin())
    }

    /// `(Δaz, Δel)` (rad) of a reading at `az`, `el` (rad).
    pub fn delta_rad(&self, az_rad: f64, el_rad: f64) -> (f64, f64) {
        let (dx, dy) = self.lean_rad(az_rad);
        let (s, c) = az_rad.sin_cos();
        (el_rad.tan() * (dx * s - dy * c), dx * c + dy * s)
    }

    pub fn describe(&self) -> String {
        format!(
            "k = {}, w = {:.1} µrad, φ = {:.0}°",
            self.order, self.amplitude_urad, self.phase_deg
        )
    }

    pub(super) fn apply(&self, sim: &mut SimulatedCampaign) {
        for r in &mut sim.campaign.readings {
            let (daz, del) = self.delta_rad(r.az_deg.to_radians(), r.el_deg.to_radians());
            super::move_reading(r, daz, del, 0.0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::{OpenEffect, fixture};
    use super::*;
    use crate::kinematics::{Face, Reading, nominal_point, nominal_reading, wrap_angle};
    use crate::random::stream;
    use nalgebra::{Rotation3, Vector3};

    fn wobble(order: u32) -> AxisWobble {
        AxisWobble {
            order,
            amplitude_urad: 20.0,
            phase_deg: 40.0,
        }
    }

    #[test]
    fn the_closed_forms_hold() {
        for k in [2, 3] {
            let e = wobble(k);
            for (az, el) in [(0.3, 0.2), (-2.0, -0.4), (2.9, 0.6), (1.0, 0.0)] {
                let a = f64::from(k - 1) * az + 40f64.to_radians();
                let (daz, del) = e.delta_rad(az, el);
                assert!((del - 20e-6 * a.cos()).abs() < 1e-18);
                assert!((daz + 20e-6 * f64::tan(el) * a.sin()).abs() < 1e-18);
            }
        }
        // On the horizon the azimuth does not move; at az = 0 with φ = 0
        // the lean is all towards x: Δel = w.
        let e = AxisWobble {
            phase_deg: 0.0,
            ..wobble(2)
        };
        let (daz, del) = e.delta_rad(0.0, 0.0);
        assert_eq!(daz, 0.0);
        assert!((del - 20e-6).abs() < 1e-20);
    }

    #[test]
    fn the_small_angle_formulas_match_the_exact_rotation() {
        let e = wobble(3);
        for face in [Face::Front, Face::Back] {
            for (az, el) in [(0.3, 0.2), (-2.0, -0.4), (2.9, 0.6)] {
                let r = nominal_reading(&nominal_point(Reading { az, el, d: 8000.0 }), face);
                let u_true = nominal_point(r);
                let (dx, dy) = e.lean_rad(r.az);
                let lean = Rotation3::new(Vector3::new(-dy, dx, 0.0));
                // The reading whose beam, turned by the lean, hits the point.
                let exact = nominal_reading(&(lean.inverse() * u_true), face);
                let (daz, del) = e.delta_rad(r.az, r.el);
                assert!((wrap_angle(exact.az - r.az) - daz).abs() < 1e-9, "{face:?}");
                assert!((exact.el - r.el - del).abs() < 1e-9, "{face:?}");
                assert!((exact.d - r.d).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn readings_move_in_angle_only() {
        let sim = fixture::campaign(true);
        let e = wobble(2);
        let out = OpenEffect::AxisWobble(e.clone()).apply(&sim, None).unwrap();
        for (a, b) in out.campaign.readings.iter().zip(&sim.campaign.readings) {
            assert_eq!(a.d_mm, b.d_mm);
            let (daz, del) = e.delta_rad(b.az_deg.to_radians(), b.el_deg.to_radians());
            assert!((wrap_angle((a.az_deg - b.az_deg).to_radians()) - daz).abs() < 1e-12);
            assert!(((a.el_deg - b.el_deg).to_radians() - del).abs() < 1e-12);
        }
    }

    #[test]
    fn draws_lie_in_the_documented_ranges() {
        let mut rng = stream(3, "axis-wobble");
        let mut orders = [0; 2];
        for _ in 0..1000 {
            let e = AxisWobble::draw(&mut rng);
            orders[e.order as usize - 2] += 1;
            assert!((3.0..=20.0).contains(&e.amplitude_urad));
            assert!((0.0..360.0).contains(&e.phase_deg));
        }
        assert!(orders[0] > 400 && orders[1] > 400, "{orders:?}");
    }
}
