//! `part-expansion` — the structure the reflectors sit on expands as the
//! hall warms.
//!
//! The reflectors' nests are fixed to a steel part or structure; its
//! temperature follows the hall's, which warms during the campaign
//! (lights, people, machines, the sun on the roof). A body of expansion
//! coefficient `α` that is `ΔT` warmer grows about its fixed centre `c`:
//!
//! ```text
//! x(t) = c + (x0 − c)·(1 + α·ΔT(t)),   ΔT(t) = rate·(t − t_ref)/3600
//! ```
//!
//! (computed as `x0 + (x0 − c)·α·ΔT`, so that no warming gives `x0`
//! exactly), `rate` in K/h, `t` and `t_ref` in s. Each reading changes by
//! the exact noise-free difference of what the tracker, with its errors,
//! reads of `x(t)` and of `x0` from the station's true pose.
//!
//! This moves the reflectors, not the beam: it is neither the catalogue's
//! `air-refraction` (the range's index, all stations alike) nor its
//! `range-scale` (one station's range). A station sees its reflectors
//! grow during its session, and every station sees a different size.
//!
//! Magnitudes: `α` 11.5e-6/K (steel), `rate` 0.3–2 K/h (a hall warming in
//! the morning). A reflector 5 m from `c` moves 58 µm per K.
//!
//! Factor `time`: the structure is a function of the time of the reading.

use super::{Context, Kind, log_uniform, time_of};
use crate::error_model::ErrorParams;
use crate::simulate::SimulatedCampaign;
use nalgebra::Vector3;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// Steel's linear expansion coefficient (1/K).
const STEEL_ALPHA_PER_K: f64 = 11.5e-6;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PartExpansion {
    pub alpha_per_k: f64,
    pub warming_k_per_h: f64,
    /// When the structure had its nominal size (s).
    pub t_ref_s: f64,
    /// The fixed centre of the expansion (mm, campaign frame).
    pub centre_mm: [f64; 3],
}

impl PartExpansion {
    /// Steel, warming log-uniform in 0.3–2 K/h from the campaign's first
    /// reading, about the reflectors' centroid.
    pub fn draw(rng: &mut ChaCha8Rng, ctx: &Context) -> Result<PartExpansion, String> {
        let t_ref_s = ctx
            .start_s()
            .ok_or("part-expansion needs the readings' time_s")?;
        let centre =
            ctx.targets.iter().map(|t| t.1).sum::<Vector3<f64>>() / ctx.targets.len().max(1) as f64;
        Ok(PartExpansion {
            alpha_per_k: STEEL_ALPHA_PER_K,
            warming_k_per_h: log_uniform(rng, 0.3, 2.0),
            t_ref_s,
            centre_mm: [centre.x, centre.y, centre.z],
        })
    }

    /// `ΔT` (K) at time `t_s`.
    pub fn delta_t_k(&self, t_s: f64) -> f64 {
        self.warming_k_per_h * (t_s - self.t_ref_s) / 3600.0
    }

    /// The true centre at time `t_s` of a reflector whose nominal centre is
    /// `x0` (mm).
    pub fn position(&self, x0: &Vector3<f64>, t_s: f64) -> Vector3<f64> {
        x0 + (x0 - Vector3::from(self.centre_mm)) * (self.alpha_per_k * self.delta_t_k(t_s))
    }

    pub fn describe(&self) -> String {
        let c = self.centre_mm;
        format!(
            "α = {:.2e}/K, warming {:.2} K/h from t = {:.0} s, about ({:.0}, {:.0}, {:.0}) mm",
            self.alpha_per_k, self.warming_k_per_h, self.t_ref_s, c[0], c[1], c[2]
        )
    }

    pub(super) fn apply(
        &self,
        sim: &mut SimulatedCampaign,
        errors: Option<&ErrorParams>,
    ) -> Result<(), String> {
        for r in &mut sim.campaign.readings {
            let t = time_of(r, Kind::PartExpansion)?;
            let pose = super::pose(&sim.poses, &r.station)?;
            let x0 = super::target(&sim.targets, &r.target)?;
            let x = self.position(&x0, t);
            let (daz, del, dd) = super::geometric_change(errors, r, (pose, &x0), (pose, &x))?;
            super::move_reading(r, daz, del, dd);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::super::{OpenEffect, fixture};
    use super::*;
    use crate::random::stream;
    use crate::simulate::read;

    fn warming(rate: f64) -> PartExpansion {
        PartExpansion {
            alpha_per_k: STEEL_ALPHA_PER_K,
            warming_k_per_h: rate,
            t_ref_s: 0.0,
            centre_mm: [1000.0, 2000.0, 500.0],
        }
    }

    #[test]
    fn positions_grow_about_the_centre_by_alpha_delta_t() {
        let e = warming(1.5);
        // Two hours at 1.5 K/h: ΔT = 3 K.
        assert!((e.delta_t_k(7200.0) - 3.0).abs() < 1e-15);
        let x0 = Vector3::new(6000.0, 2000.0, 500.0);
        let x = e.position(&x0, 7200.0);
        // 5 m from the centre along x: 5000 mm · 11.5e-6 · 3 = 0.1725 mm.
        assert!((x - Vector3::new(6000.1725, 2000.0, 500.0)).norm() < 1e-9);
        assert_eq!(
            e.position(&Vector3::from(e.centre_mm), 7200.0),
            Vector3::from(e.centre_mm)
        );
        assert_eq!(e.position(&x0, 0.0), x0);
    }

    #[test]
    fn no_warming_is_the_identity() {
        let sim = fixture::campaign(true);
        let out = OpenEffect::PartExpansion(warming(0.0))
            .apply(&sim, Some(&fixture::errors()))
            .unwrap();
        assert_eq!(out.campaign.readings, sim.campaign.readings);
    }

    #[test]
    fn a_reading_moves_by_the_read_of_the_grown_structure() {
        let sim = fixture::campaign(true);
        let errors = fixture::errors();
        let t_ref_s = sim.campaign.readings[0].time_s.unwrap();
        let e = PartExpansion {
            t_ref_s,
            ..warming(2.0)
        };
        let out = OpenEffect::PartExpansion(e.clone())
            .apply(&sim, Some(&errors))
            .unwrap();
        let last = sim.campaign.readings.len() - 1;
        for i in [0, last / 2, last] {
            let (a, b) = (&out.campaign.readings[i], &sim.campaign.readings[i]);
            let t = b.time_s.unwrap();
            let pose = sim.poses.iter().find(|p| p.id == b.station).unwrap();
            let x0 = sim.targets.iter().find(|x| x.0 == b.target).unwrap().1;
            let c = Vector3::from(e.centre_mm);
            let x = c + (x0 - c) * (1.0 + 11.5e-6 * 2.0 * (t - t_ref_s) / 3600.0);
            let r0 = read(Some(&errors), &pose.to_local(&x0), b.face).unwrap();
            let r1 = read(Some(&errors), &pose.to_local(&x), b.face).unwrap();
            assert!((a.d_mm - b.d_mm - (r1.d - r0.d)).abs() < 1e-9);
            assert!(((a.el_deg - b.el_deg).to_radians() - (r1.el - r0.el)).abs() < 1e-11);
        }
        // The first reading, at t_ref, does not move; half an hour on, with
        // reflectors metres from the centre, ranges change by many µm.
        assert_eq!(out.campaign.readings[0], sim.campaign.readings[0]);
        let largest = out
            .campaign
            .readings
            .iter()
            .zip(&sim.campaign.readings)
            .map(|(a, b)| (a.d_mm - b.d_mm).abs())
            .fold(0.0, f64::max);
        assert!(largest > 5e-3, "{largest}");
    }

    #[test]
    fn draws_lie_in_the_documented_ranges() {
        let ctx = Context::of(&fixture::campaign(true));
        let mut rng = stream(3, "part-expansion");
        for _ in 0..1000 {
            let e = PartExpansion::draw(&mut rng, &ctx).unwrap();
            assert_eq!(e.alpha_per_k, 11.5e-6);
            assert!((0.3..=2.0).contains(&e.warming_k_per_h));
            assert_eq!(Some(e.t_ref_s), ctx.start_s());
        }
    }
}
