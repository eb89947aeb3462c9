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
