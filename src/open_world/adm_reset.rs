//! `adm-reset` — a station's ADM re-initialises with another zero.
//!
//! After a beam break the tracker re-establishes its absolute distance at
//! its home position (the bird-bath) with the SMR in hand; the dead path
//! (R0) it finds differs from the one before by the repeatability of the
//! nest's seat and of the SMR used. From that moment `t0` on, every range
//! of the station is off by the step:
//!
//! ```text
//! Δd = c        on the station's readings at t ≥ t0
//! ```
//!
//! Magnitudes: `|c|` 5–25 µm (ISO 10360-10's R0 figure is ±5 µm; a
//! mis-seated or other SMR at the reset gives tens of µm).
//!
//! Factor `station × time`: one station, only after `t0`.

use super::{Context, Kind, log_uniform, mid_session, sign, time_of};
use crate::simulate::SimulatedCampaign;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdmReset {
    pub station: String,
    /// The time of the re-initialisation (s).
    pub t0_s: f64,
    pub offset_um: f64,
}

impl AdmReset {
    /// A random station, `t0` in the middle half of its session, `|c|`
    /// log-uniform in 5–25 µm with a random sign.
    pub fn draw(rng: &mut ChaCha8Rng, ctx: &Context) -> Result<AdmReset, String> {
        let (station, t0_s) = mid_session(rng, ctx, Kind::AdmReset)?;
        Ok(AdmReset {
            station,
            t0_s,
            offset_um: sign(rng) * log_uniform(rng, 5.0, 25.0),
        })
    }

    pub fn describe(&self) -> String {
        format!(
            "station {} re-initialised at t = {:.0} s, c = {:.1} µm",
            self.station, self.t0_s, self.offset_um
        )
    }

    pub(super) fn apply(&self, sim: &mut SimulatedCampaign) -> Result<(), String> {
        super::pose(&sim.poses, &self.station)?;
        for r in sim
            .campaign
            .readings
            .iter_mut()
            .filter(|r| r.station == self.station)
        {
            if time_of(r, Kind::AdmReset)? >= self.t0_s {
                super::move_reading(r, 0.0, 0.0, self.offset_um * 1e-3);
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::super::{OpenEffect, fixture};
    use super::*;
    use crate::random::stream;

    #[test]
    fn ranges_step_by_c_from_t0_on_one_station() {
        let sim = fixture::campaign(true);
        let station = sim.poses[2].id.clone();
        let times = fixture::times_of(&sim, &station);
        let t0 = times[times.len() / 3];
        let e = AdmReset {
            station: station.clone(),
            t0_s: t0,
            offset_um: -12.0,
        };
        let out = OpenEffect::AdmReset(e).apply(&sim, None).unwrap();
        let mut stepped = 0;
        for (a, b) in out.campaign.readings.iter().zip(&sim.campaign.readings) {
            if b.station == station && b.time_s.unwrap() >= t0 {
                stepped += 1;
                assert_eq!((a.az_deg, a.el_deg), (b.az_deg, b.el_deg));
                assert_eq!(a.d_mm, b.d_mm + -12.0 * 1e-3);
            } else {
                assert_eq!(a, b);
            }
        }
        assert_eq!(stepped, times.len() - times.len() / 3);
    }

    #[test]
    fn draws_lie_in_the_documented_ranges() {
        let ctx = Context::of(&fixture::campaign(true));
        let mut rng = stream(3, "adm-reset");
        for _ in 0..1000 {
            let e = AdmReset::draw(&mut rng, &ctx).unwrap();
            assert!((5.0..=25.0).contains(&e.offset_um.abs()));
            let s = ctx
                .sessions
                .iter()
                .find(|s| s.station == e.station)
                .unwrap();
            let (a, b) = s.times_s.unwrap();
            assert!(e.t0_s >= a + 0.25 * (b - a) && e.t0_s <= a + 0.75 * (b - a));
        }
    }
}
