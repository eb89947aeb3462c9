//! The candidate explanations as signatures on the readings: each effect's
//! own file ([`crate::effects`]) builds its candidates (every place and
//! variant it can have) from a [`Context`]; this module holds what they
//! share and iterates the catalogue.
//!
//! A signature is how the effect's parameters move each reading, in units
//! of the reading's σ (see [`super::linear`]): an effect that adds Δ to a
//! reading moves its residual by `W·Δ`; one that moves the reflector or the
//! station by `s` moves it by `W·J⁻¹·R_sᵀ·s`. Effects whose inputs the
//! campaign lacks are skipped, with the reason.

use super::linear::Signature;
use crate::effects::{IncidenceAngles, incidence_angles};
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use std::sync::Arc;

/// What the candidates need to know about one reading.
#[derive(Clone, Debug)]
pub struct ReadingInfo {
    pub station: usize,
    pub target: usize,
    /// Reading az and el (rad), d (mm).
    pub az: f64,
    pub el: f64,
    pub d: f64,
    /// 1 σ of az, el (rad) and d (mm).
    pub sigma: Vector3<f64>,
    /// `J_nom(q)⁻¹`: point increments (mm) → reading increments.
    pub jinv: Matrix3<f64>,
    /// Station → campaign rotation of the reading's station.
    pub rotation: Matrix3<f64>,
    /// Seconds since the station's first reading.
    pub since_station_s: Option<f64>,
    pub temperature_c: Option<f64>,
    pub incidence: Option<IncidenceAngles>,
    /// What a hypothesis may read besides: the face (1, 2), `time_s` as
    /// recorded, and the reflector's centre and the station's origin at
    /// the base solution (campaign frame, mm).
    pub face: f64,
    pub time_s: Option<f64>,
    pub point: Vector3<f64>,
    pub station_pos: Vector3<f64>,
}

/// One candidate explanation.
#[derive(Clone)]
pub struct Candidate {
    /// The id of `effects.md`, or a hypothesis's name.
    pub effect: String,
    /// `all`, a station or reflector id, or an axis.
    pub place: String,
    /// Signature columns, one per parameter, on the readings it affects.
    pub columns: Signature,
    /// The magnitude reported from the fitted parameters, and its unit.
    pub magnitude: Magnitude,
    pub unit: String,
    /// Alternatives this candidate was chosen from (orders, stations):
    /// counted in the multiple-testing correction.
    pub alternatives: usize,
    /// Details of the chosen alternative (e.g. `order 3`).
    pub detail: String,
}

/// A candidate that could not be tried, and why.
#[derive(Clone, Debug)]
pub struct Skipped {
    pub effect: String,
    pub reason: String,
}

/// Magnitudes: the norm of the parameters (a vector, a sine and cosine pair).
pub fn norm(b: &[f64]) -> f64 {
    b.iter().map(|x| x * x).sum::<f64>().sqrt()
}
/// … the first parameter (the others are nuisance).
pub fn first(b: &[f64]) -> f64 {
    b[0]
}
/// … the largest in absolute value (one per station).
pub fn largest(b: &[f64]) -> f64 {
    b.iter().fold(0.0, |m: f64, x| m.max(x.abs()))
}

/// How a candidate's magnitude is read from its fitted parameters: a
/// closure, since a hypothesis's is an expression of its own.
pub type Magnitude = Arc<dyn Fn(&[f64]) -> f64 + Send + Sync>;

/// Adds `w_d·value` to reading i's range row of column `col`.
pub fn put_d(c: &mut Signature, i: usize, r: &ReadingInfo, col: usize, value_mm: f64) {
    c.add(i, 2, col, value_mm / r.sigma.z);
}

/// Adds a point displacement `s_mm` (campaign frame, per unit of the
/// column's parameter) to reading i.
pub fn put_point(c: &mut Signature, i: usize, r: &ReadingInfo, col: usize, s_mm: Vector3<f64>) {
    let dq = r.jinv * (r.rotation.transpose() * s_mm);
    for a in 0..3 {
        c.add(i, a, col, dq[a] / r.sigma[a]);
    }
}

/// What an effect's candidates are built from.
pub struct Context<'a> {
    pub readings: &'a [ReadingInfo],
    /// Station and reflector ids by index.
    pub stations: &'a [String],
    pub targets: &'a [String],
    /// Stations in the order they measured.
    pub station_order: &'a [usize],
}

impl Context<'_> {
    /// How many readings know their incidence (their SMR's axis).
    pub fn incidence_known(&self) -> usize {
        self.readings
            .iter()
            .filter(|r| r.incidence.is_some())
            .count()
    }

    /// The detail of a candidate fitted on the readings whose incidence
    /// is known, when that is not all of them.
    pub fn incidence_detail(&self) -> String {
        let known = self.incidence_known();
        if known < self.readings.len() {
            format!(
                "fitted on the {known} of {} readings whose SMR axis is known",
                self.readings.len()
            )
        } else {
            String::new()
        }
    }
}

/// The candidates built so far, and those that could not be tried.
#[derive(Default)]
pub struct Found {
    pub candidates: Vec<Candidate>,
    pub skipped: Vec<Skipped>,
}

impl Found {
    /// A candidate of one place and one alternative.
    pub fn push(
        &mut self,
        effect: &str,
        place: &str,
        columns: Signature,
        magnitude: Magnitude,
        unit: &str,
    ) {
        self.candidates.push(Candidate {
            effect: effect.into(),
            place: place.into(),
            columns,
            magnitude,
            unit: unit.into(),
            alternatives: 1,
            detail: String::new(),
        });
    }

    /// `effect` could not be tried, because `reason`.
    pub fn skip(&mut self, effect: &str, reason: &str) {
        self.skipped.push(Skipped {
            effect: effect.into(),
            reason: reason.into(),
        });
    }
}

/// Every candidate of the catalogue's effects that `enabled` lets through,
/// in the catalogue's order.
pub fn build(cx: &Context, enabled: &dyn Fn(&str) -> bool) -> (Vec<Candidate>, Vec<Skipped>) {
    // Each effect's candidates are its own (built from `cx` alone): the
    // effects in parallel, each into its own list, joined in the
    // catalogue's order — the same candidates in the same order. One after
    // another they were the main thread's work while the other waited.
    let kinds: Vec<&crate::effects::Kind> = crate::effects::kinds()
        .iter()
        .filter(|k| enabled(k.id))
        .collect();
    let each: Vec<Found> = kinds
        .par_iter()
        .map(|kind| {
            let mut found = Found::default();
            (kind.candidates)(cx, &mut found);
            found
        })
        .collect();
    let mut found = Found::default();
    for f in each {
        found.candidates.extend(f.candidates);
        found.skipped.extend(f.skipped);
    }
    (found.candidates, found.skipped)
}

/// The incidence geometry of a reading from estimated positions: `n` the
/// SMR axis, the tracker at `station_mm`, the reflector at `target_mm`.
pub fn incidence(
    n: &Vector3<f64>,
    target_mm: &Vector3<f64>,
    station_mm: &Vector3<f64>,
) -> IncidenceAngles {
    incidence_angles(n, &(station_mm - target_mm).normalize())
}
