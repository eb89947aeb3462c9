//! `tripod-knock` — a station's tripod is knocked in the middle of its
//! session.
//!
//! A boot or a cable catches a tripod leg: the tracker does not fall, but
//! from time `t0` on its origin sits elsewhere and its head is turned a
//! little about the vertical. The station's true pose `x = R·x_local + p`
//! becomes, for the readings at `t ≥ t0`,
//!
//! ```text
//! p' = p + s,        R' = R_z(ψ)·R
//! ```
//!
//! with `s` (µm, campaign frame) and the yaw `ψ` (µrad) about the campaign's
//! vertical through the station's origin. Each reading at `t ≥ t0` changes
//! by the exact noise-free difference `read(R', p') − read(R, p)` of the
//! tracker with its errors; readings before `t0` are untouched.
//!
//! Magnitudes: `|s|` 20–150 µm, `|ψ|` 5–30 µrad — a knock that the
//! tripod's feet survive (larger ones are noticed and the station is
//! restarted). At 10 m, 30 µrad of yaw moves the line of sight 300 µm.
//!
//! Factor `station × time`: one station, only after `t0`.

use super::{Context, Kind, between, geometric_change, log_uniform, mid_session, sign, time_of};
use crate::error_model::ErrorParams;
use crate::simulate::{SimulatedCampaign, StationPose};
use nalgebra::{Rotation3, Vector3};
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TripodKnock {
    pub station: String,
    /// The time of the knock (s, on the campaign's `time_s` clock).
    pub t0_s: f64,
    /// The origin's displacement, campaign frame (µm).
    pub shift_um: [f64; 3],
    /// The turn about the vertical (µrad, counter-clockwise seen from above).
    pub yaw_urad: f64,
}

impl TripodKnock {
    /// A random station, `t0` in the middle half of its session, `s` in a
    /// random direction with `|s|` log-uniform in 20–150 µm, `ψ`
    /// log-uniform in 5–30 µrad with a random sign.
    pub fn draw(rng: &mut ChaCha8Rng, ctx: &Context) -> Result<TripodKnock, String> {
        let (station, t0_s) = mid_session(rng, ctx, Kind::TripodKnock)?;
        let dir = Vector3::from_fn(|_, _| between(rng, -1.0, 1.0));
        let s = dir.normalize() * log_uniform(rng, 20.0, 150.0);
        Ok(TripodKnock {
            station,
            t0_s,
            shift_um: [s.x, s.y, s.z],
            yaw_urad: sign(rng) * log_uniform(rng, 5.0, 30.0),
        })
    }

    /// The station's pose after the knock.
    pub fn knocked(&self, pose: &StationPose) -> StationPose {
        let yaw = Rotation3::from_axis_angle(&Vector3::z_axis(), self.yaw_urad * 1e-6);
        StationPose {
            id: pose.id.clone(),
            position: pose.position + Vector3::from(self.shift_um) * 1e-3,
            rotation: yaw * pose.rotation,
        }
    }

    pub fn describe(&self) -> String {
        let s = Vector3::from(self.shift_um);
        format!(
            "station {} knocked at t = {:.0} s: shift ({:.1}, {:.1}, {:.1}) µm (|s| = {:.1} µm), yaw {:.1} µrad",
            self.station,
            self.t0_s,
            s.x,
            s.y,
            s.z,
            s.norm(),
            self.yaw_urad
        )
    }

    pub(super) fn apply(
        &self,
        sim: &mut SimulatedCampaign,
        errors: Option<&ErrorParams>,
    ) -> Result<(), String> {
        let pose = super::pose(&sim.poses, &self.station)?;
        let knocked = self.knocked(pose);
        for r in sim
            .campaign
            .readings
            .iter_mut()
            .filter(|r| r.station == self.station)
        {
            if time_of(r, Kind::TripodKnock)? < self.t0_s {
                continue;
            }
            let x = super::target(&sim.targets, &r.target)?;
            let (daz, del, dd) = geometric_change(errors, r, (pose, &x), (&knocked, &x))?;
            super::move_reading(r, daz, del, dd);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::super::{OpenEffect, fixture};
    use super::*;
    use crate::kinematics::wrap_angle;
    use crate::random::stream;
    use crate::simulate::read;

    fn knock(station: &str, t0_s: f64) -> TripodKnock {
        TripodKnock {
            station: station.into(),
            t0_s,
            shift_um: [60.0, -80.0, 20.0],
            yaw_urad: 15.0,
        }
    }

    #[test]
    fn readings_before_t0_are_bit_identical_and_after_it_read_the_moved_pose() {
        let sim = fixture::campaign(true);
        let errors = fixture::errors();
        let station = sim.poses[1].id.clone();
        let times = fixture::times_of(&sim, &station);
        let t0 = times[times.len() / 2];
        let k = knock(&station, t0);
        let out = OpenEffect::TripodKnock(k.clone())
            .apply(&sim, Some(&errors))
            .unwrap();
        let (mut before, mut after) = (0, 0);
        for (a, b) in out.campaign.readings.iter().zip(&sim.campaign.readings) {
            if b.station != station || b.time_s.unwrap() < t0 {
                assert_eq!(a, b);
                before += (b.station == station) as usize;
                continue;
            }
            after += 1;
            // By hand: the reading of the knocked pose, minus the unmoved
            // one, added to the noisy reading.
            let pose = &sim.poses[1];
            let moved = StationPose {
                id: station.clone(),
                position: pose.position + Vector3::new(0.060, -0.080, 0.020),
                rotation: Rotation3::from_euler_angles(0.0, 0.0, 15e-6) * pose.rotation,
            };
            let x = sim.targets.iter().find(|t| t.0 == b.target).unwrap().1;
            let r0 = read(Some(&errors), &pose.to_local(&x), b.face).unwrap();
            let r1 = read(Some(&errors), &moved.to_local(&x), b.face).unwrap();
            assert!((a.d_mm - b.d_mm - (r1.d - r0.d)).abs() < 1e-9);
            assert!(((a.el_deg - b.el_deg).to_radians() - (r1.el - r0.el)).abs() < 1e-12);
            let daz = wrap_angle((a.az_deg - b.az_deg).to_radians());
            assert!((daz - wrap_angle(r1.az - r0.az)).abs() < 1e-12);
        }
        assert!(before > 0 && after > 0);
    }

    #[test]
    fn a_pure_yaw_turns_every_later_azimuth_by_the_yaw() {
        let sim = fixture::campaign(true);
        let station = sim.poses[0].id.clone();
        let k = TripodKnock {
            shift_um: [0.0; 3],
            ..knock(&station, 0.0)
        };
        // A perfect tracker: the station turned by +ψ sees every point
        // turned by −ψ, so it reads az − ψ and the same d, up to the
        // station's levelling (≈ 1 mrad, so to ~1e-3 of ψ).
        let out = OpenEffect::TripodKnock(k).apply(&sim, None).unwrap();
        for (a, b) in out.campaign.readings.iter().zip(&sim.campaign.readings) {
            if b.station == station {
                // In both faces: the back face's az is the front's + 180°.
                let daz = wrap_angle((a.az_deg - b.az_deg).to_radians());
                assert!((daz + 15e-6).abs() < 0.1e-6, "{daz}");
                assert!((a.d_mm - b.d_mm).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn draws_lie_in_the_documented_ranges() {
        let ctx = Context::of(&fixture::campaign(true));
        let mut rng = stream(3, "tripod-knock");
        for _ in 0..1000 {
            let k = TripodKnock::draw(&mut rng, &ctx).unwrap();
            let s = Vector3::from(k.shift_um).norm();
            assert!((20.0..=150.0).contains(&s), "{s}");
            assert!((5.0..=30.0).contains(&k.yaw_urad.abs()));
            let session = ctx
                .sessions
                .iter()
                .find(|x| x.station == k.station)
                .unwrap();
            let (a, b) = session.times_s.unwrap();
            assert!(k.t0_s >= a + 0.25 * (b - a) && k.t0_s <= a + 0.75 * (b - a));
        }
    }

    #[test]
    fn an_unknown_station_is_an_error() {
        let sim = fixture::campaign(true);
        let e = OpenEffect::TripodKnock(knock("S9", 0.0)).apply(&sim, None);
        assert_eq!(e.unwrap_err(), "station `S9` is not in the campaign");
    }
}
