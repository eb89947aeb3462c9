//! `beam-bending` — a vertical temperature gradient bends the beam and
//! changes its mean refractive index.
//!
//! Warm air rises: a heated hall is stratified, `G = dT/dz` of 0.2–1 K/m.
//! Air's refractive index falls with temperature, `dn/dT ≈ −0.93e-6 /K`
//! (Edlén, 633 nm, 20 °C, 1013 hPa), so `dn/dz = (dn/dT)·G`.
//!
//! **Bending.** A ray curves towards higher index with curvature equal to
//! the index gradient across it, `κ = |dn/dz|·cos e` for a ray at
//! elevation `e` (the part of the vertical gradient perpendicular to it).
//! Over a path of length `L` of constant curvature the tangent at the start
//! and the chord to the end differ by `κ·L/2`. The tracker reads the
//! tangent (its beam leaves along its pointing), the reflector lies on the
//! chord. With `G > 0` the index falls upward, the beam sags, and the
//! tracker aims above the reflector:
//!
//! ```text
//! Δel = −(dn/dz)·cos(el)·d/2 = 0.93e-6·G·cos(el)·d/2      (rad; G in K/m, d in m)
//! ```
//!
//! The sag at the reflector is `Δel·d = 0.93e-6·G·d²/2`: 23 µm at 10 m for
//! 0.5 K/m (FIELD.md).
//!
//! **Mean index.** The range is compensated with the index at the
//! tracker's height; the beam to a reflector `Δz = d·sin(el)` higher runs
//! through air on average `G·Δz/2` warmer, so (as in the catalogue's
//! air-refraction, but growing with height):
//!
//! ```text
//! Δd = (dn/dz)·(d·sin(el)/2)·d = −0.93e-6·G·(d_m·sin(el)/2)·d      (d_m in m, Δd in d's unit)
//! ```
//!
//! The path's extra length from the bending, `κ²·L³/24`, is below 1e-11 m:
//! neglected. In the back face the reading's `el` is `180° − e`: `cos el`
//! changes sign with the elevation axis, `sin el` does not, so both
//! formulas hold for the reading's own `el` in either face.
//!
//! Magnitudes: `G` 0.2–1 K/m, positive (stable stratification). At 10 m and
//! 0.5 K/m: Δel 2.3 µrad; at el = 20°, Δd = −8 µm. At 20 m and 1 K/m:
//! Δel 9.3 µrad, Δd up to −64 µm.
//!
//! Factor `range`: the bending grows with `d` and the range term with `d²`,
//! while within a hall's elevations (|el| ≤ 30°) `cos el` varies by under
//! 14 %; `d` varies by a factor of several between reflectors. The range
//! term's sign does follow `sin el` (reflectors above or below the head):
//! a localisation along `el` sees part of it.

use super::log_uniform;
use crate::simulate::SimulatedCampaign;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// Air's refractive index per kelvin at 633 nm, 20 °C, 1013 hPa.
const DN_DT_PER_K: f64 = -0.93e-6;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BeamBending {
    /// `dT/dz`, positive: warmer upward (K/m).
    pub gradient_k_per_m: f64,
}

impl BeamBending {
    /// `G` log-uniform in 0.2–1 K/m.
    pub fn draw(rng: &mut ChaCha8Rng) -> BeamBending {
        BeamBending {
            gradient_k_per_m: log_uniform(rng, 0.2, 1.0),
        }
    }

    /// `(Δel rad, Δd mm)` of a reading at elevation `el` (rad) and distance
    /// `d_mm`.
    pub fn delta(&self, el_rad: f64, d_mm: f64) -> (f64, f64) {
        let dn_dz_per_m = DN_DT_PER_K * self.gradient_k_per_m;
        let d_m = d_mm * 1e-3;
        let (s, c) = el_rad.sin_cos();
        (
            -dn_dz_per_m * c * d_m / 2.0,
            dn_dz_per_m * (d_m * s / 2.0) * d_mm,
        )
    }

    pub fn describe(&self) -> String {
        format!("dT/dz = {:.2} K/m", self.gradient_k_per_m)
    }

    pub(super) fn apply(&self, sim: &mut SimulatedCampaign) {
        for r in &mut sim.campaign.readings {
            let (del, dd) = self.delta(r.el_deg.to_radians(), r.d_mm);
            super::move_reading(r, 0.0, del, dd);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::{OpenEffect, fixture};
    use super::*;
    use crate::random::stream;

    const HALF: BeamBending = BeamBending {
        gradient_k_per_m: 0.5,
    };

    #[test]
    fn a_level_beam_of_10_m_in_half_a_kelvin_per_metre() {
        let (del, dd) = HALF.delta(0.0, 10_000.0);
        // 0.93e-6 · 0.5 · 10 / 2 = 2.325 µrad, 23.25 µm of sag; level: no
        // height, no range change.
        assert!((del - 2.325e-6).abs() < 1e-18);
        assert!((del * 10_000.0 - 0.02325).abs() < 1e-12);
        assert_eq!(dd, 0.0);
    }

    #[test]
    fn an_inclined_beam_bends_less_and_reads_short_above() {
        let el = 30f64.to_radians();
        let (del, dd) = HALF.delta(el, 10_000.0);
        assert!((del - 2.325e-6 * el.cos()).abs() < 1e-18);
        // Δz = 5 m: air on average 1.25 K warmer, −1.1625 ppm of 10 m.
        assert!((dd + 0.011625).abs() < 1e-12);
        // Below the head the range reads long.
        let (_, below) = HALF.delta(-el, 10_000.0);
        assert!((below - 0.011625).abs() < 1e-12);
    }

    #[test]
    fn the_back_face_reads_the_same_bend_with_its_flipped_elevation() {
        let e = 20f64.to_radians();
        let (front_del, front_dd) = HALF.delta(e, 8000.0);
        let (back_del, back_dd) = HALF.delta(std::f64::consts::PI - e, 8000.0);
        assert!((back_del + front_del).abs() < 1e-18);
        assert!((back_dd - front_dd).abs() < 1e-15);
    }

    #[test]
    fn readings_move_in_elevation_and_range_only() {
        let sim = fixture::campaign(true);
        let out = OpenEffect::BeamBending(HALF).apply(&sim, None).unwrap();
        for (a, b) in out.campaign.readings.iter().zip(&sim.campaign.readings) {
            assert_eq!(a.az_deg, b.az_deg);
            let (del, dd) = HALF.delta(b.el_deg.to_radians(), b.d_mm);
            assert!(((a.el_deg - b.el_deg).to_radians() - del).abs() < 1e-12);
            assert!((a.d_mm - b.d_mm - dd).abs() < 1e-12);
        }
    }

    #[test]
    fn draws_lie_in_the_documented_ranges() {
        let mut rng = stream(3, "beam-bending");
        for _ in 0..1000 {
            let g = BeamBending::draw(&mut rng).gradient_k_per_m;
            assert!((0.2..=1.0).contains(&g));
        }
    }
}
