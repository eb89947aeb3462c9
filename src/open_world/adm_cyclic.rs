//! `adm-cyclic` — the absolute distance meter's cyclic error.
//!
//! A phase-measuring ADM (and a heterodyne interferometer) mixes a little of
//! its reference signal into the measuring one — polarisation leakage,
//! electronic crosstalk — so its phase, and so the distance, is off by a
//! periodic function of the distance itself:
//!
//! ```text
//! Δd = A·sin(2π·d/P + φ)        (A in µm; d, P in the same unit)
//! ```
//!
//! with `P` a fraction of the modulation wavelength. The same instrument
//! measured every station, so the error is the same function at every
//! station and reflector.
//!
//! Magnitudes: `A` 3–20 µm (a few µm for a good ADM, the ±10 µm of ISO
//! 10360-10's ADM figure for a worn one), `P` 0.5–1.5 m, `φ` anything.
//!
//! Factor `range`: a function of `d` alone.

use super::{between, log_uniform};
use crate::simulate::SimulatedCampaign;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::f64::consts::TAU;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdmCyclic {
    pub amplitude_um: f64,
    pub period_m: f64,
    pub phase_deg: f64,
}

impl AdmCyclic {
    /// `A` log-uniform in 3–20 µm, `P` uniform in 0.5–1.5 m, `φ` uniform.
    pub fn draw(rng: &mut ChaCha8Rng) -> AdmCyclic {
        AdmCyclic {
            amplitude_um: log_uniform(rng, 3.0, 20.0),
            period_m: between(rng, 0.5, 1.5),
            phase_deg: between(rng, 0.0, 360.0),
        }
    }

    /// `Δd` (mm) at distance `d_mm`.
    pub fn delta_d_mm(&self, d_mm: f64) -> f64 {
        let period_mm = self.period_m * 1e3;
        self.amplitude_um * 1e-3 * (TAU * d_mm / period_mm + self.phase_deg.to_radians()).sin()
    }

    pub fn describe(&self) -> String {
        format!(
            "A = {:.1} µm, P = {:.3} m, φ = {:.0}°",
            self.amplitude_um, self.period_m, self.phase_deg
        )
    }

    pub(super) fn apply(&self, sim: &mut SimulatedCampaign) {
        for r in &mut sim.campaign.readings {
            let dd = self.delta_d_mm(r.d_mm);
            super::move_reading(r, 0.0, 0.0, dd);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::{OpenEffect, fixture};
    use super::*;
    use crate::random::stream;

    #[test]
    fn a_quarter_period_gives_the_amplitude_and_a_half_period_nothing() {
        let e = AdmCyclic {
            amplitude_um: 12.0,
            period_m: 0.8,
            phase_deg: 0.0,
        };
        // d = P/4 = 200 mm: sin(π/2) = 1.
        assert!((e.delta_d_mm(200.0) - 0.012).abs() < 1e-15);
        assert!(e.delta_d_mm(400.0).abs() < 1e-15);
        assert!((e.delta_d_mm(600.0) + 0.012).abs() < 1e-15);
        // A whole number of periods further on: the same error.
        assert!((e.delta_d_mm(200.0 + 8.0 * 800.0) - 0.012).abs() < 1e-15);
        // φ = 90° turns the sine into a cosine: A at d = 0.
        let c = AdmCyclic {
            phase_deg: 90.0,
            ..e
        };
        assert!((c.delta_d_mm(0.0) - 0.012).abs() < 1e-15);
    }

    #[test]
    fn every_reading_moves_in_range_only_by_the_formula() {
        let sim = fixture::campaign(true);
        let e = AdmCyclic {
            amplitude_um: 7.0,
            period_m: 1.1,
            phase_deg: 30.0,
        };
        let out = OpenEffect::AdmCyclic(e.clone()).apply(&sim, None).unwrap();
        for (a, b) in out.campaign.readings.iter().zip(&sim.campaign.readings) {
            assert_eq!((a.az_deg, a.el_deg), (b.az_deg, b.el_deg));
            let by_hand =
                7e-3 * (2.0 * std::f64::consts::PI * b.d_mm / 1100.0 + 30f64.to_radians()).sin();
            assert!((a.d_mm - b.d_mm - by_hand).abs() < 1e-12);
        }
    }

    #[test]
    fn draws_lie_in_the_documented_ranges() {
        let mut rng = stream(3, "adm-cyclic");
        for _ in 0..1000 {
            let e = AdmCyclic::draw(&mut rng);
            assert!((3.0..=20.0).contains(&e.amplitude_um));
            assert!((0.5..=1.5).contains(&e.period_m));
            assert!((0.0..360.0).contains(&e.phase_deg));
        }
    }
}
