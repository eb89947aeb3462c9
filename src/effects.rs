//! The unmodelled effects of `effects.md` (version 1), each implemented
//! exactly as that file defines it, so that a campaign simulated here and one
//! made by another generator from the same definitions agree.
//!
//! An effect's id (`incidence`, `range-scale`, …) is its key in TOML, its name
//! in tables and in reports. In a `simulate_campaign` stage:
//!
//! ```toml
//! [stages.sim.effects.incidence]
//! e_axial_um = 5.0
//! [stages.sim.effects.range-scale]
//! ppm = { S1 = 2.0, S3 = -1.5 }
//! ```
//!
//! Angles are radians inside formulas, lengths mm; parameters carry their unit.

use crate::kinematics::Reading;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Every effect id of `effects.md`, in its order.
pub const IDS: &[&str] = &[
    "incidence",
    "incidence-table9",
    "range-scale",
    "air-refraction",
    "encoder-harmonic",
    "station-drift",
    "target-shift",
    "noise",
    "none",
];

/// The SMR's acceptance: beyond it the beam does not return.
pub const DEFAULT_MAX_ANGLE_DEG: f64 = 30.0;

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
    DEFAULT_MAX_ANGLE_DEG
}

/// `incidence-table9` — the paper's measured incidence error.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IncidenceTable9 {}

/// `range-scale` — a scale error that differs between stations.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RangeScale {
    /// ppm per station id; stations not listed have none (unless `sigma_ppm`).
    #[serde(default)]
    pub ppm: BTreeMap<String, f64>,
    /// Draw one scale per station not listed in `ppm`, N(0, sigma_ppm).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma_ppm: Option<f64>,
}

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

/// `target-shift` — a reflector is knocked.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TargetShift {
    pub target: String,
    pub from_station: String,
    /// A vector in the campaign frame.
    pub shift_um: [f64; 3],
}

/// The coordinate of a reading a blunder moves.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Coordinate {
    Az,
    El,
    D,
}

fn face_one() -> u8 {
    1
}

/// `blunder` (effects.md version 2) — one reading off by a gross amount in
/// one coordinate: `Δaz = size_urad·1e-6`, `Δel = size_urad·1e-6` or
/// `Δd = size_um·1e-3`. Applied last, after the noise.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Blunder {
    pub station: String,
    pub target: String,
    /// 1 (front) or 2 (back).
    #[serde(default = "face_one")]
    pub face: u8,
    pub coordinate: Coordinate,
    /// For `coordinate = "az"` or `"el"`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub size_urad: Option<f64>,
    /// For `coordinate = "d"`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub size_um: Option<f64>,
}

impl Blunder {
    /// effects.md's name for the reading: `station/target/face`.
    pub fn place(&self) -> String {
        format!("{}/{}/{}", self.station, self.target, self.face)
    }

    /// The reading moved by the blunder.
    pub fn apply(&self, mut r: Reading) -> Reading {
        let (angle, range) = (self.size_urad.unwrap_or(0.0), self.size_um.unwrap_or(0.0));
        match self.coordinate {
            Coordinate::Az => r.az += angle * 1e-6,
            Coordinate::El => r.el += angle * 1e-6,
            Coordinate::D => r.d += range * 1e-3,
        }
        r
    }

    /// What is wrong with it, as `(field, message)` below `blunder[i]`.
    fn check(&self, i: usize, out: &mut Vec<(String, String)>) {
        let at = |f: &str| format!("blunder[{i}].{f}");
        if !(self.face == 1 || self.face == 2) {
            out.push((
                at("face"),
                format!("`face` must be 1 or 2, got {}", self.face),
            ));
        }
        let (wanted, other) = match self.coordinate {
            Coordinate::Az | Coordinate::El => {
                (("size_urad", self.size_urad), ("size_um", self.size_um))
            }
            Coordinate::D => (("size_um", self.size_um), ("size_urad", self.size_urad)),
        };
        match wanted.1 {
            None => out.push((
                at(wanted.0),
                format!("a blunder in this coordinate needs `{}`", wanted.0),
            )),
            Some(v) if !v.is_finite() => out.push((
                at(wanted.0),
                format!("`{}` must be finite, got {v}", wanted.0),
            )),
            Some(_) => {}
        }
        if other.1.is_some() {
            out.push((
                at(other.0),
                format!(
                    "`{}` does not apply to this coordinate (use `{}`)",
                    other.0, wanted.0
                ),
            ));
        }
    }
}

/// The effects a simulated campaign carries (at most one of each, and any
/// number of blunders).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Effects {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub incidence: Option<Incidence>,
    /// effects.md's `noise` is given by the stage's own `noise` table (the
    /// same field names), not here: kept only to say so where it was
    /// written, rather than to call a known id an unknown field.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise: Option<serde_json::Value>,
    #[serde(
        default,
        rename = "incidence-table9",
        skip_serializing_if = "Option::is_none"
    )]
    pub incidence_table9: Option<IncidenceTable9>,
    #[serde(
        default,
        rename = "range-scale",
        skip_serializing_if = "Option::is_none"
    )]
    pub range_scale: Option<RangeScale>,
    #[serde(
        default,
        rename = "air-refraction",
        skip_serializing_if = "Option::is_none"
    )]
    pub air_refraction: Option<AirRefraction>,
    #[serde(
        default,
        rename = "encoder-harmonic",
        skip_serializing_if = "Option::is_none"
    )]
    pub encoder_harmonic: Option<EncoderHarmonic>,
    #[serde(
        default,
        rename = "station-drift",
        skip_serializing_if = "Option::is_none"
    )]
    pub station_drift: Option<StationDrift>,
    #[serde(
        default,
        rename = "target-shift",
        skip_serializing_if = "Option::is_none"
    )]
    pub target_shift: Option<TargetShift>,
    /// Any number of gross errors, each on one reading.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub blunder: Vec<Blunder>,
    /// A researcher's hypotheses ([`crate::hypothesis`]), injected at their
    /// parameters' `value`s. Never written under `effects`: a stage sets
    /// them from its `hypotheses` file, whose content hash its cache key
    /// holds.
    #[serde(skip)]
    pub hypotheses: Injected,
}

/// Hypotheses to inject; equal when they are the same list (a file's
/// content is compared through its hash, not here).
#[derive(Clone, Debug, Default)]
pub struct Injected(pub std::sync::Arc<Vec<crate::hypothesis::Hypothesis>>);

impl PartialEq for Injected {
    fn eq(&self, other: &Self) -> bool {
        std::sync::Arc::ptr_eq(&self.0, &other.0) || (self.0.is_empty() && other.0.is_empty())
    }
}

impl Effects {
    /// The ids of the effects present.
    pub fn ids(&self) -> Vec<&'static str> {
        let mut v = Vec::new();
        if self.incidence.is_some() {
            v.push("incidence");
        }
        if self.incidence_table9.is_some() {
            v.push("incidence-table9");
        }
        if self.range_scale.is_some() {
            v.push("range-scale");
        }
        if self.air_refraction.is_some() {
            v.push("air-refraction");
        }
        if self.encoder_harmonic.is_some() {
            v.push("encoder-harmonic");
        }
        if self.station_drift.is_some() {
            v.push("station-drift");
        }
        if self.target_shift.is_some() {
            v.push("target-shift");
        }
        v.extend(self.blunder.iter().map(|_| "blunder"));
        v
    }

    /// Settings that cannot work, as `(field, message)` relative to `effects`.
    pub fn check(&self) -> Vec<(String, String)> {
        let mut out = Vec::new();
        if self.noise.is_some() {
            out.push((
                "noise".to_string(),
                "reading noise is the stage's `noise` table, not an entry of `effects`: \
                 write `noise = { sigma_angle_urad = …, sigma_range_um = …, sigma_range_ppm = … }` \
                 in the stage"
                    .to_string(),
            ));
        }
        let mut finite = |field: &str, v: f64| {
            if !v.is_finite() {
                out.push((
                    field.to_string(),
                    format!("`{field}` must be finite, got {v}"),
                ));
            }
        };
        if let Some(i) = &self.incidence {
            finite("incidence.e_axial_um", i.e_axial_um);
            finite("incidence.e_h_um", i.e_h_um);
            finite("incidence.e_v_um", i.e_v_um);
        }
        if let Some(a) = &self.air_refraction {
            finite("air-refraction.t0_c", a.t0_c);
            finite("air-refraction.offset_c", a.offset_c);
            finite("air-refraction.amplitude_c", a.amplitude_c);
            finite("air-refraction.period_s", a.period_s);
            finite("air-refraction.phase_deg", a.phase_deg);
            finite("air-refraction.drift_c_per_h", a.drift_c_per_h);
        }
        if let Some(e) = &self.encoder_harmonic {
            finite("encoder-harmonic.amplitude_urad", e.amplitude_urad);
            finite("encoder-harmonic.phase_deg", e.phase_deg);
        }
        if let Some(r) = &self.range_scale {
            for (station, ppm) in &r.ppm {
                finite(&format!("range-scale.ppm.{station}"), *ppm);
            }
        }
        if let Some(d) = &self.station_drift {
            if let Some(&v) = d.velocity_um_per_min.iter().find(|v| !v.is_finite()) {
                finite("station-drift.velocity_um_per_min", v);
            }
        }
        if let Some(t) = &self.target_shift {
            if let Some(&v) = t.shift_um.iter().find(|v| !v.is_finite()) {
                finite("target-shift.shift_um", v);
            }
        }
        for (i, b) in self.blunder.iter().enumerate() {
            b.check(i, &mut out);
        }
        if let Some(a) = self
            .air_refraction
            .as_ref()
            .filter(|a| a.period_s.is_finite())
        {
            if a.period_s <= 0.0 {
                out.push((
                    "air-refraction.period_s".into(),
                    format!("`period_s` must be > 0, got {}", a.period_s),
                ));
            }
        }
        if let Some(i) = &self.incidence {
            if !(i.max_angle_deg > 0.0 && i.max_angle_deg <= 90.0) {
                out.push((
                    "incidence.max_angle_deg".into(),
                    format!(
                        "`max_angle_deg` must lie in (0, 90], got {}",
                        i.max_angle_deg
                    ),
                ));
            }
        }
        if let Some(e) = &self.encoder_harmonic {
            if e.order < 2 {
                out.push((
                    "encoder-harmonic.order".into(),
                    format!(
                        "`order` must be ≥ 2 (a first harmonic is an eccentricity the kinematic model holds), got {}",
                        e.order
                    ),
                ));
            }
        }
        if let Some(r) = &self.range_scale {
            if r.sigma_ppm.is_some_and(|s| !(s >= 0.0 && s.is_finite())) {
                out.push((
                    "range-scale.sigma_ppm".into(),
                    "`sigma_ppm` must be ≥ 0".into(),
                ));
            }
        }
        out
    }
}

/// The incidence geometry of one reading (effects.md, `incidence`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IncidenceAngles {
    /// `acos(r·n)`.
    pub alpha: f64,
    pub alpha_h: f64,
    pub alpha_v: f64,
}

/// `n`: unit SMR axis (centre → aim point); `r`: unit vector from the
/// reflector's centre to the tracker. `h = normalize(ẑ × n)` (`x̂` if `n` is
/// vertical), `v = n × h`.
pub fn incidence_angles(n: &Vector3<f64>, r: &Vector3<f64>) -> IncidenceAngles {
    let z = Vector3::z();
    let c = z.cross(n);
    let h = if c.norm() < 1e-12 {
        Vector3::x()
    } else {
        c.normalize()
    };
    let v = n.cross(&h);
    let rn = r.dot(n);
    IncidenceAngles {
        alpha: rn.clamp(-1.0, 1.0).acos(),
        alpha_h: r.dot(&h).atan2(rn),
        alpha_v: r.dot(&v).atan2(rn),
    }
}

impl Incidence {
    /// `Δd` in µm.
    pub fn delta_d_um(&self, a: &IncidenceAngles) -> f64 {
        self.e_axial_um * (1.0 - a.alpha.cos())
            + self.e_h_um * a.alpha_h.sin()
            + self.e_v_um * a.alpha_v.sin()
    }
}

/// The paper's Table 9 (µm): rows α_v, columns α_h, both −30° … 30° in 7.5°
/// steps. The same numbers, with their provenance, are in
/// `pipelines/data/table9.csv`; a test keeps the two identical.
pub const TABLE9_UM: [[f64; 9]; 9] = [
    [13.4, 13.0, 12.4, 11.5, 10.0, 8.3, 6.5, 4.3, 2.6],
    [8.1, 7.9, 7.6, 6.9, 6.2, 4.3, 3.2, 1.6, 0.0],
    [5.0, 4.8, 4.5, 3.8, 3.0, 2.1, 0.8, -0.5, -1.6],
    [2.4, 2.2, 2.0, 1.5, 0.9, -0.2, -1.1, -1.8, -2.8],
    [1.2, 1.0, 0.8, 0.4, 0.0, -0.7, -1.5, -2.4, -3.4],
    [0.8, 0.6, 0.4, 0.0, -0.5, -1.1, -1.8, -2.6, -3.6],
    [0.3, 0.0, -0.2, -0.5, -1.0, -1.7, -2.4, -3.0, -3.9],
    [0.0, -0.2, -0.5, -0.8, -1.3, -2.0, -2.7, -3.3, -4.1],
    [-0.2, -0.5, -0.8, -1.0, -1.6, -2.4, -3.1, -3.6, -4.4],
];

/// The angles of Table 9's rows and columns, degrees.
pub fn table9_angles_deg() -> [f64; 9] {
    std::array::from_fn(|i| -30.0 + 7.5 * i as f64)
}

/// `incidence-table9`: bilinear interpolation of Table 9 at `(α_v, α_h)`;
/// `None` outside ±30° (the reading is not taken).
pub fn table9_delta_d_um(alpha_v: f64, alpha_h: f64) -> Option<f64> {
    let (v, h) = (alpha_v.to_degrees(), alpha_h.to_degrees());
    let tol = 1e-9;
    if v.abs() > 30.0 + tol || h.abs() > 30.0 + tol {
        return None;
    }
    let pos = |x: f64| {
        let f = ((x.clamp(-30.0, 30.0) + 30.0) / 7.5).min(8.0);
        let i = (f.floor() as usize).min(7);
        (i, f - i as f64)
    };
    let (i, fv) = pos(v);
    let (j, fh) = pos(h);
    let t = &TABLE9_UM;
    let top = t[i][j] * (1.0 - fh) + t[i][j + 1] * fh;
    let bottom = t[i + 1][j] * (1.0 - fh) + t[i + 1][j + 1] * fh;
    Some(top * (1.0 - fv) + bottom * fv)
}

impl RangeScale {
    /// `Δd = ppm[station]·1e-6·d`, in mm for `d` in mm.
    pub fn delta_d_mm(ppm: f64, d_mm: f64) -> f64 {
        ppm * 1e-6 * d_mm
    }
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

impl EncoderHarmonic {
    /// `amplitude_urad·1e-6·sin(order·angle + phase_deg)`, rad, where `angle`
    /// is the reading's az (or el) in radians.
    pub fn delta_rad(&self, angle: f64) -> f64 {
        self.amplitude_urad * 1e-6 * (self.order as f64 * angle + self.phase_deg.to_radians()).sin()
    }
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

impl TargetShift {
    pub fn shift_mm(&self) -> Vector3<f64> {
        Vector3::from(self.shift_um) * 1e-3
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn incidence_angles_by_hand() {
        // SMR facing +x; tracker up and to the side.
        let n = Vector3::x();
        let r = Vector3::new(1.0, 1.0, 1.0).normalize();
        let a = incidence_angles(&n, &r);
        // h = ẑ × x̂ = ŷ, v = x̂ × ŷ = ẑ.
        assert!((a.alpha - (1.0f64 / 3f64.sqrt()).acos()).abs() < 1e-15);
        assert!((a.alpha_h - std::f64::consts::FRAC_PI_4).abs() < 1e-15);
        assert!((a.alpha_v - std::f64::consts::FRAC_PI_4).abs() < 1e-15);
        // Vertical axis: h = x̂, v = ẑ × x̂ = ŷ.
        let a = incidence_angles(&Vector3::z(), &Vector3::new(0.0, 0.1, 1.0).normalize());
        assert!(a.alpha_h.abs() < 1e-15);
        assert!((a.alpha_v - 0.1f64.atan()).abs() < 1e-12, "{a:?}");
    }

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

    #[test]
    fn table9_interpolation_hits_the_nodes_and_interpolates_between() {
        let ang = table9_angles_deg();
        for (i, v) in ang.iter().enumerate() {
            for (j, h) in ang.iter().enumerate() {
                let d = table9_delta_d_um(v.to_radians(), h.to_radians()).unwrap();
                assert!((d - TABLE9_UM[i][j]).abs() < 1e-12);
            }
        }
        // Halfway between rows −30 and −22.5 at column 0: (10 + 6.2)/2.
        let d = table9_delta_d_um((-26.25f64).to_radians(), 0.0).unwrap();
        assert!((d - 8.1).abs() < 1e-12);
        // A quarter of the way along a cell diagonal.
        let d = table9_delta_d_um(1.875f64.to_radians(), 1.875f64.to_radians()).unwrap();
        let expect = 0.75 * (0.75 * 0.0 + 0.25 * -0.7) + 0.25 * (0.75 * -0.5 + 0.25 * -1.1);
        assert!((d - expect).abs() < 1e-12);
        assert!(table9_delta_d_um(0.0, 31f64.to_radians()).is_none());
    }

    #[test]
    fn scalar_effects_by_hand() {
        assert_eq!(RangeScale::delta_d_mm(2.0, 5000.0), 0.01);
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
        let e = EncoderHarmonic {
            axis: Axis::Az,
            order: 3,
            amplitude_urad: 12.0,
            phase_deg: 90.0,
        };
        assert!((e.delta_rad(0.0) - 12e-6).abs() < 1e-18);
        let d = StationDrift {
            station: Some("S4".into()),
            velocity_um_per_min: [6.0, 0.0, -3.0],
        };
        assert!(d.applies_to("S4") && !d.applies_to("S1"));
        assert!((d.displacement_mm(30.0) - Vector3::new(0.003, 0.0, -0.0015)).norm() < 1e-15);
    }
}
