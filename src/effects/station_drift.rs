//! `station-drift` — the tracker moves while it measures (a tripod settling,
//! a floor warming): its origin runs at a constant velocity from the
//! station's first reading.

use super::{DrawContext, Drawn, Effect, Forward, Needs, Place, Setup, finite};
use crate::diagnose::candidates::{Context, Found, ReadingInfo, norm, put_point};
use crate::diagnose::linear::Signature;
use crate::random;
use nalgebra::Vector3;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// `station-drift` — the tracker moves while it measures.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StationDrift {
    /// The station that drifts; every station when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub station: Option<String>,
    /// A vector in the campaign frame.
    pub velocity_um_per_min: [f64; 3],
}

impl StationDrift {
    /// Whether the drift applies to `station`.
    pub fn applies_to(&self, station: &str) -> bool {
        self.station.as_deref().is_none_or(|s| s == station)
    }

    /// The station origin's displacement (mm) `dt_s` seconds after the
    /// station's first reading.
    pub fn displacement_mm(&self, dt_s: f64) -> Vector3<f64> {
        Vector3::from(self.velocity_um_per_min) * (dt_s / 60.0) * 1e-3
    }
}

impl Forward for StationDrift {
    fn prepare(&mut self, setup: &Setup) -> Result<(), String> {
        match &self.station {
            Some(s) if !setup.stations.contains(s) => Err(format!(
                "station-drift names station `{s}`, which the layout does not have"
            )),
            _ => Ok(()),
        }
    }

    fn station_shift_mm(&self, at: &Place, since_station_s: f64) -> Option<Vector3<f64>> {
        self.applies_to(at.station)
            .then(|| self.displacement_mm(since_station_s))
    }
}

impl Effect for StationDrift {
    const ID: &'static str = "station-drift";
    const SUMMARY: &'static str =
        "the station's origin moves at a constant velocity from its first reading";
    const NEEDS: Needs = Needs {
        time: true,
        temperature: false,
    };

    fn check(&self) -> Vec<(String, String)> {
        let mut out = Vec::new();
        if let Some(&v) = self.velocity_um_per_min.iter().find(|v| !v.is_finite()) {
            finite(&mut out, "velocity_um_per_min", v);
        }
        out
    }

    /// Each station, and one velocity for all: three columns (µm/min along
    /// x, y, z of the campaign frame).
    fn candidates(cx: &Context, out: &mut Found) {
        if !cx.readings.iter().all(|r| r.since_station_s.is_some()) {
            return out.skip(Self::ID, "readings.csv has no time_s for every reading");
        }
        let drift = |c: &mut Signature, i: usize, r: &ReadingInfo| {
            let minutes = r.since_station_s.expect("checked") / 60.0;
            for a in 0..3 {
                let mut s = Vector3::zeros();
                // The origin moves by v·τ: the reflector seems to move by −v·τ.
                s[a] = -1e-3 * minutes;
                put_point(c, i, r, a, s);
            }
        };
        for (s, id) in cx.stations.iter().enumerate() {
            let mut c = Signature::new(3);
            for (i, r) in cx.readings.iter().enumerate().filter(|(_, r)| r.station == s) {
                drift(&mut c, i, r);
            }
            out.push(Self::ID, id, c, Arc::new(norm), "µm/min");
        }
        let mut c = Signature::new(3);
        for (i, r) in cx.readings.iter().enumerate() {
            drift(&mut c, i, r);
        }
        out.push(Self::ID, "all", c, Arc::new(norm), "µm/min");
    }

    /// One station, 2–15 µm/min in a random direction.
    fn draw(rng: &mut ChaCha8Rng, cx: &DrawContext) -> Drawn<Self> {
        let s = random::pick(rng, cx.stations).clone();
        let v = random::direction(rng) * (cx.size * random::log_uniform(rng, 2.0, 15.0, false));
        Drawn {
            effect: StationDrift {
                station: Some(s.clone()),
                velocity_um_per_min: [v.x, v.y, v.z],
            },
            place: s,
            magnitude: v.norm(),
            has_place: true,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn station_drift_by_hand() {
        let d = StationDrift {
            station: Some("S4".into()),
            velocity_um_per_min: [6.0, 0.0, -3.0],
        };
        assert!(d.applies_to("S4") && !d.applies_to("S1"));
        assert!((d.displacement_mm(30.0) - Vector3::new(0.003, 0.0, -0.0015)).norm() < 1e-15);
    }
}
