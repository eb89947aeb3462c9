//! `range-scale` — a scale error of the distance meter that differs between
//! stations (a refractive index or a frequency set wrong at one station).

use super::{DrawContext, Drawn, Effect, Forward, IncidenceAngles, Place, Setup, finite};
use crate::diagnose::candidates::{Context, Found, first, largest, put_d};
use crate::diagnose::linear::Signature;
use crate::kinematics::Reading;
use crate::random;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;

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

impl RangeScale {
    /// `Δd = ppm[station]·1e-6·d`, in mm for `d` in mm.
    pub fn delta_d_mm(ppm: f64, d_mm: f64) -> f64 {
        ppm * 1e-6 * d_mm
    }
}

impl Forward for RangeScale {
    /// Draws `sigma_ppm`'s scales (one per station, in the measuring
    /// order, from the stream `range-scale`) into `ppm`: after it, `ppm`
    /// holds every station's scale as used.
    fn prepare(&mut self, setup: &Setup) -> Result<(), String> {
        let mut rng = random::stream(setup.seed, Self::ID);
        let mut used = BTreeMap::new();
        for s in setup.stations {
            let drawn = self.sigma_ppm.map(|sigma| sigma * random::normal(&mut rng));
            if let Some(v) = self.ppm.get(s).copied().or(drawn) {
                used.insert(s.clone(), v);
            }
        }
        if let Some(unknown) = self.ppm.keys().find(|s| !setup.stations.contains(s)) {
            return Err(format!(
                "range-scale names station `{unknown}`, which the layout does not have"
            ));
        }
        self.ppm = used;
        self.sigma_ppm = None;
        Ok(())
    }

    fn delta_d_mm(&self, at: &Place, r: &Reading, _: &IncidenceAngles, _: f64) -> Option<f64> {
        self.ppm
            .get(at.station)
            .map(|ppm| RangeScale::delta_d_mm(*ppm, r.d))
    }
}

impl Effect for RangeScale {
    const ID: &'static str = "range-scale";
    const SUMMARY: &'static str = "a distance scale error per station: Δd = ppm[station]·1e-6·d";

    fn check(&self) -> Vec<(String, String)> {
        let mut out = Vec::new();
        for (station, ppm) in &self.ppm {
            finite(&mut out, &format!("ppm.{station}"), *ppm);
        }
        if self.sigma_ppm.is_some_and(|s| !(s >= 0.0 && s.is_finite())) {
            out.push(("sigma_ppm".into(), "`sigma_ppm` must be ≥ 0".into()));
        }
        out
    }

    /// The scale of every station as used.
    fn truth(&self) -> Vec<(String, String, f64)> {
        self.ppm
            .iter()
            .map(|(station, ppm)| (station.clone(), "ppm".into(), *ppm))
            .collect()
    }

    /// Each station alone, and every station at once (one column each).
    fn candidates(cx: &Context, out: &mut Found) {
        // One ppm column per station that `col` maps to a column.
        let scale = |n: usize, col: &dyn Fn(usize) -> Option<usize>| {
            let mut c = Signature::new(n);
            for (i, r) in cx.readings.iter().enumerate() {
                if let Some(k) = col(r.station) {
                    put_d(&mut c, i, r, k, 1e-6 * r.d);
                }
            }
            c
        };
        for (s, id) in cx.stations.iter().enumerate() {
            let columns = scale(1, &|station| (station == s).then_some(0));
            out.push(Self::ID, id, columns, Arc::new(first), "ppm");
        }
        let columns = scale(cx.stations.len(), &Some);
        out.push(Self::ID, "all", columns, Arc::new(largest), "ppm (largest)");
    }

    /// One station, 2–12 ppm either way.
    fn draw(rng: &mut ChaCha8Rng, cx: &DrawContext) -> Drawn<Self> {
        let s = random::pick(rng, cx.stations).clone();
        let ppm = cx.size * random::log_uniform(rng, 2.0, 12.0, true);
        Drawn {
            effect: RangeScale {
                ppm: BTreeMap::from([(s.clone(), ppm)]),
                sigma_ppm: None,
            },
            place: s,
            magnitude: ppm,
            has_place: true,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn range_scale_by_hand_and_its_draws_fill_ppm() {
        assert_eq!(RangeScale::delta_d_mm(2.0, 5000.0), 0.01);
        let stations = ["S1".to_string(), "S2".to_string()];
        let mut rs = RangeScale {
            ppm: BTreeMap::from([("S2".to_string(), 3.0)]),
            sigma_ppm: Some(1.0),
        };
        let setup = Setup {
            stations: &stations,
            targets: &[],
            seed: 5,
        };
        rs.prepare(&setup).unwrap();
        assert_eq!(rs.ppm.len(), 2);
        assert_eq!(rs.ppm["S2"], 3.0);
        assert!(rs.ppm["S1"].abs() < 6.0 && rs.ppm["S1"] != 0.0);
        let mut bad = RangeScale {
            ppm: BTreeMap::from([("S9".to_string(), 3.0)]),
            sigma_ppm: None,
        };
        assert!(bad.prepare(&setup).unwrap_err().contains("`S9`"));
    }
}
