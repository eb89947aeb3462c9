//! `air-refraction` — the air's temperature drifts during the campaign
//! while the tracker compensates for a fixed one: the distance meter's
//! wavelength, and so its scale, follows the air (−0.93 ppm/K).

use super::{DrawContext, Drawn, Effect, Forward, IncidenceAngles, Needs, Place, finite};
use crate::diagnose::candidates::{Context, Found, first, put_d};
use crate::diagnose::linear::Signature;
use crate::kinematics::Reading;
use crate::random;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// `air-refraction` — temperature that drifts during the campaign. The
/// tracker compensates for `t0_c`; the air follows
/// `temperature_c(t) = t0_c + offset_c + amplitude_c·sin(2π·t/period_s + phase) + drift_c_per_h·t/3600`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AirRefraction {
    #[serde(default = "default_t0")]
    pub t0_c: f64,
    #[serde(default)]
    pub offset_c: f64,
    #[serde(default)]
    pub amplitude_c: f64,
    #[serde(default = "default_period")]
    pub period_s: f64,
    #[serde(default)]
    pub phase_deg: f64,
    #[serde(default)]
    pub drift_c_per_h: f64,
}

fn default_t0() -> f64 {
    20.0
}
fn default_period() -> f64 {
    900.0
}

impl AirRefraction {
    /// The air temperature at `t_s` seconds since the campaign began.
    pub fn temperature_c(&self, t_s: f64) -> f64 {
        self.t0_c
            + self.offset_c
            + self.amplitude_c
                * (2.0 * std::f64::consts::PI * t_s / self.period_s + self.phase_deg.to_radians())
                    .sin()
            + self.drift_c_per_h * t_s / 3600.0
    }

    /// `Δd = −0.93e-6·(temperature_c − t0_c)·d`, in mm.
    pub fn delta_d_mm(&self, temperature_c: f64, d_mm: f64) -> f64 {
        -0.93e-6 * (temperature_c - self.t0_c) * d_mm
    }
}

impl Forward for AirRefraction {
    fn temperature_c(&self, time_s: f64) -> Option<f64> {
        Some(AirRefraction::temperature_c(self, time_s))
    }

    fn delta_d_mm(&self, _: &Place, r: &Reading, _: &IncidenceAngles, t: f64) -> Option<f64> {
        Some(AirRefraction::delta_d_mm(self, t, r.d))
    }
}

impl Effect for AirRefraction {
    const ID: &'static str = "air-refraction";
    const SUMMARY: &'static str =
        "air temperature drifting from the compensated one: Δd = −0.93e-6·(T − t0)·d";
    const NEEDS: Needs = Needs {
        time: false,
        temperature: true,
    };

    fn check(&self) -> Vec<(String, String)> {
        let mut out = Vec::new();
        for (f, v) in [
            ("t0_c", self.t0_c),
            ("offset_c", self.offset_c),
            ("amplitude_c", self.amplitude_c),
            ("period_s", self.period_s),
            ("phase_deg", self.phase_deg),
            ("drift_c_per_h", self.drift_c_per_h),
        ] {
            finite(&mut out, f, v);
        }
        if self.period_s.is_finite() && self.period_s <= 0.0 {
            out.push((
                "period_s".into(),
                format!("`period_s` must be > 0, got {}", self.period_s),
            ));
        }
        out
    }

    /// A scale that follows the recorded temperature (ppm/K), beside a
    /// constant scale the mean temperature sets.
    fn candidates(cx: &Context, out: &mut Found) {
        if !cx.readings.iter().all(|r| r.temperature_c.is_some()) {
            return out.skip(Self::ID, "readings.csv has no temperature_c for every reading");
        }
        let temperatures = cx.readings.iter().filter_map(|r| r.temperature_c);
        let mean = temperatures.sum::<f64>() / cx.readings.len() as f64;
        let mut c = Signature::new(2);
        for (i, r) in cx.readings.iter().enumerate() {
            let t = r.temperature_c.expect("checked");
            put_d(&mut c, i, r, 0, 1e-6 * (t - mean) * r.d);
            put_d(&mut c, i, r, 1, 1e-6 * r.d);
        }
        out.push(Self::ID, "all", c, Arc::new(first), "ppm/K");
    }

    /// A swing of 0.5–2.5 K over 10–40 min and a drift of up to 1.5 K/h;
    /// the physics fixes the coefficient the diagnosis reports: −0.93 ppm/K.
    fn draw(rng: &mut ChaCha8Rng, cx: &DrawContext) -> Drawn<Self> {
        let effect = AirRefraction {
            t0_c: 20.0,
            offset_c: 0.0,
            // Its magnitude is the fixed coefficient (ppm/°C): a larger
            // effect is a larger swing of the air's temperature.
            amplitude_c: cx.size * random::log_uniform(rng, 0.5, 2.5, false),
            period_s: random::between(rng, (600.0, 2400.0)),
            phase_deg: 360.0 * random::uniform(rng),
            drift_c_per_h: cx.size * random::between(rng, (-1.5, 1.5)),
        };
        Drawn {
            effect,
            place: "all".into(),
            magnitude: -0.93,
            has_place: false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn air_refraction_by_hand() {
        let a = AirRefraction {
            t0_c: 20.0,
            offset_c: 0.0,
            amplitude_c: 1.0,
            period_s: 400.0,
            phase_deg: 0.0,
            drift_c_per_h: 3.6,
        };
        // t = 100 s: sin(π/2) = 1, drift 0.1 K.
        assert!((a.temperature_c(100.0) - 21.1).abs() < 1e-12);
        assert!((a.delta_d_mm(21.0, 10000.0) + 0.0093).abs() < 1e-15);
    }
}
