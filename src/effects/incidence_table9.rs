//! `incidence-table9` — the paper's measured incidence error (Table 9),
//! interpolated: the incidence error as it was measured rather than as a
//! vertex offset modelled.

use super::incidence::NO_AXES;
use super::{DrawContext, Drawn, Effect, Forward, IncidenceAngles, Place};
use crate::diagnose::candidates::{Context, Found, first, put_d};
use crate::diagnose::linear::Signature;
use crate::kinematics::Reading;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// `incidence-table9` — no settings: the table is the paper's.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IncidenceTable9 {}

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

/// Bilinear interpolation of Table 9 at `(α_v, α_h)`; `None` outside ±30°
/// (the reading is not taken).
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

impl Forward for IncidenceTable9 {
    /// The table ends at ±30°: beyond it the reading is not taken.
    fn takes(&self, a: &IncidenceAngles) -> bool {
        table9_delta_d_um(a.alpha_v, a.alpha_h).is_some()
    }

    fn delta_d_mm(&self, _: &Place, _: &Reading, a: &IncidenceAngles, _: f64) -> Option<f64> {
        table9_delta_d_um(a.alpha_v, a.alpha_h).map(|um| um * 1e-3)
    }
}

impl Effect for IncidenceTable9 {
    const ID: &'static str = "incidence-table9";
    const SUMMARY: &'static str = "the paper's measured incidence error, Table 9 interpolated";
    const ALONE: bool = true;

    /// One column: Table 9 at each reading's incidence, its multiple fitted.
    fn candidates(cx: &Context, out: &mut Found) {
        if cx.incidence_known() == 0 {
            return out.skip(Self::ID, NO_AXES);
        }
        let mut c = Signature::new(1);
        for (i, r) in cx.readings.iter().enumerate() {
            let Some(a) = r.incidence else { continue };
            if let Some(um) = table9_delta_d_um(a.alpha_v, a.alpha_h) {
                put_d(&mut c, i, r, 0, 1e-3 * um);
            }
        }
        out.push(Self::ID, "all", c, Arc::new(first), "× Table 9");
        if let Some(last) = out.candidates.last_mut() {
            last.detail = cx.incidence_detail();
        }
    }

    /// The table itself: its magnitude is 1 (× Table 9).
    fn draw(_: &mut ChaCha8Rng, _: &DrawContext) -> Drawn<Self> {
        Drawn {
            effect: IncidenceTable9 {},
            place: "all".into(),
            magnitude: 1.0,
            has_place: false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
