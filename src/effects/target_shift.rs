//! `target-shift` — a reflector is knocked: from one station on, it sits
//! somewhere else.

use super::{DrawContext, Drawn, Effect, Forward, Place, Setup, finite};
use crate::diagnose::candidates::{Candidate, Context, Found, norm, put_point};
use crate::diagnose::linear::Signature;
use crate::random;
use nalgebra::Vector3;
use rand::rngs::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// `target-shift` — a reflector is knocked.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TargetShift {
    pub target: String,
    pub from_station: String,
    /// A vector in the campaign frame.
    pub shift_um: [f64; 3],
}

impl TargetShift {
    pub fn shift_mm(&self) -> Vector3<f64> {
        Vector3::from(self.shift_um) * 1e-3
    }
}

impl Forward for TargetShift {
    fn prepare(&mut self, setup: &Setup) -> Result<(), String> {
        if !setup.targets.contains(&self.target) {
            return Err(format!(
                "target-shift names reflector `{}`, which the layout does not have",
                self.target
            ));
        }
        if !setup.stations.contains(&self.from_station) {
            return Err(format!(
                "target-shift names station `{}`, which the layout does not have",
                self.from_station
            ));
        }
        Ok(())
    }

    /// The shift holds for `from_station` and every station measuring after it.
    fn reflector_shift_mm(&self, at: &Place) -> Option<Vector3<f64>> {
        let from = at.stations.iter().position(|s| *s == self.from_station)?;
        (at.target == self.target && at.rank >= from).then(|| self.shift_mm())
    }
}

impl Effect for TargetShift {
    const ID: &'static str = "target-shift";
    const SUMMARY: &'static str = "a reflector knocked: from one station on, it sits elsewhere";

    fn check(&self) -> Vec<(String, String)> {
        let mut out = Vec::new();
        if let Some(&v) = self.shift_um.iter().find(|v| !v.is_finite()) {
            finite(&mut out, "shift_um", v);
        }
        out
    }

    /// Each reflector, from each station but the first (which one is
    /// chosen later, counted in the multiple-testing correction): three
    /// columns (µm along x, y, z of the campaign frame).
    fn candidates(cx: &Context, out: &mut Found) {
        let order = cx.station_order;
        let n_from = order.len().saturating_sub(1);
        // Each reflector's readings, ascending: a candidate visits its own.
        let mut of_target: Vec<Vec<usize>> = vec![Vec::new(); cx.targets.len()];
        for (i, r) in cx.readings.iter().enumerate() {
            of_target[r.target].push(i);
        }
        // Each station's place in the measuring order.
        let mut rank = vec![usize::MAX; cx.stations.len()];
        for (k, &s) in order.iter().enumerate() {
            rank[s] = k;
        }
        // Each reflector's candidates are their own: the reflectors in
        // parallel, joined in their order. A reading's block (the shift
        // along x, y, z) is the same in every candidate that holds it —
        // from any station measuring no later than the reading's — so it
        // is formed once per reading (`all`: from the first station on)
        // and each candidate keeps the blocks of the readings from its
        // station on: the same numbers.
        let per_target: Vec<Vec<Candidate>> = cx
            .targets
            .par_iter()
            .enumerate()
            .map(|(t, id)| {
                if of_target[t].is_empty() {
                    return Vec::new();
                }
                let mut all = Signature::new(3);
                for &i in &of_target[t] {
                    let r = &cx.readings[i];
                    for a in 0..3 {
                        let mut s = Vector3::zeros();
                        s[a] = 1e-3;
                        put_point(&mut all, i, r, a, s);
                    }
                }
                order
                    .iter()
                    .enumerate()
                    .skip(1)
                    .map(|(k, &from)| Candidate {
                        effect: Self::ID.into(),
                        place: id.clone(),
                        columns: all.on(|i| rank[cx.readings[i].station] >= k),
                        magnitude: Arc::new(norm),
                        unit: "µm".into(),
                        alternatives: n_from,
                        detail: format!("from station {}", cx.stations[from]),
                    })
                    .collect()
            })
            .collect();
        out.candidates.extend(per_target.into_iter().flatten());
    }

    /// One reflector, from a station but the first, 30–200 µm in a random
    /// direction.
    fn draw(rng: &mut ChaCha8Rng, cx: &DrawContext) -> Drawn<Self> {
        let t = random::pick(rng, cx.targets).clone();
        let from = random::pick(rng, &cx.stations[1..]).clone();
        let s = random::direction(rng) * (cx.size * random::log_uniform(rng, 30.0, 200.0, false));
        Drawn {
            effect: TargetShift {
                target: t.clone(),
                from_station: from,
                shift_um: [s.x, s.y, s.z],
            },
            place: t,
            magnitude: s.norm(),
            has_place: true,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diagnose::candidates::ReadingInfo;
    use nalgebra::{Matrix3, Rotation3};

    /// The candidates keep the blocks formed once per reading: each is the
    /// signature the definition builds for it (a shift along x, y, z on the
    /// reflector's readings from its station on), bit for bit, in the same
    /// order, with the reflectors in parallel.
    #[test]
    fn target_shift_blocks_formed_once_are_each_candidates_own() {
        let stations: Vec<String> = (1..=4).map(|s| format!("S{s}")).collect();
        let targets: Vec<String> = (1..=3).map(|t| format!("T{t}")).collect();
        let order = vec![2, 0, 3, 1];
        let mut readings = Vec::new();
        for s in 0..4 {
            for t in 0..3 {
                for face in [1.0, 2.0] {
                    let x = (s * 3 + t) as f64 + face;
                    readings.push(ReadingInfo {
                        station: s,
                        target: t,
                        az: 0.1 * x,
                        el: 0.05 * x,
                        d: 1000.0 + x,
                        sigma: Vector3::new(1e-6, 2e-6, 1e-2 + 1e-4 * x),
                        jinv: Matrix3::new(1.0, 0.1 * x, 0.0, 0.2, 1.5, 0.3 * x, 0.0, 0.1, 2.0),
                        rotation: Rotation3::from_euler_angles(0.1, 0.2, 0.3 * x).into_inner(),
                        since_station_s: None,
                        temperature_c: None,
                        incidence: None,
                        face,
                        time_s: None,
                        point: Vector3::zeros(),
                        station_pos: Vector3::zeros(),
                    });
                }
            }
        }
        let cx = Context {
            readings: &readings,
            stations: &stations,
            targets: &targets,
            station_order: &order,
        };
        let mut found = Found::default();
        TargetShift::candidates(&cx, &mut found);
        let mut rank = vec![0; stations.len()];
        for (k, &s) in order.iter().enumerate() {
            rank[s] = k;
        }
        let mut expected = Vec::new();
        for (t, id) in targets.iter().enumerate() {
            for (k, &from) in order.iter().enumerate().skip(1) {
                let mut c = Signature::new(3);
                for (i, r) in readings.iter().enumerate() {
                    if r.target == t && rank[r.station] >= k {
                        for a in 0..3 {
                            let mut s = Vector3::zeros();
                            s[a] = 1e-3;
                            put_point(&mut c, i, r, a, s);
                        }
                    }
                }
                expected.push((id.clone(), format!("from station {}", stations[from]), c));
            }
        }
        assert_eq!(found.candidates.len(), expected.len());
        for (got, (place, detail, c)) in found.candidates.iter().zip(&expected) {
            assert_eq!((&got.place, &got.detail), (place, detail));
            assert!(got.columns.narrows(c) && c.narrows(&got.columns), "{place} {detail}");
            assert_eq!(got.columns.ncols(), 3);
        }
    }
}
