//! The candidate explanations: every effect of `effects.md`, and the
//! per-station and per-reflector variants of `range-scale`, `station-drift`
//! and `target-shift`, as signatures on the readings.
//!
//! A signature is how the effect's parameters move each reading, in units
//! of the reading's σ (see [`super::linear`]): an effect that adds Δ to a
//! reading moves its residual by `W·Δ`; one that moves the reflector or the
//! station by `s` moves it by `W·J⁻¹·R_sᵀ·s`. Effects whose inputs the
//! campaign lacks are skipped, with the reason.

use super::linear::Signature;
use crate::effects::{IncidenceAngles, incidence_angles, table9_delta_d_um};
use nalgebra::{Matrix3, Vector3};
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

fn norm(b: &[f64]) -> f64 {
    b.iter().map(|x| x * x).sum::<f64>().sqrt()
}
fn first(b: &[f64]) -> f64 {
    b[0]
}
fn largest(b: &[f64]) -> f64 {
    b.iter().fold(0.0, |m: f64, x| m.max(x.abs()))
}

/// How a candidate's magnitude is read from its fitted parameters: a
/// closure, since a hypothesis's is an expression of its own.
pub type Magnitude = Arc<dyn Fn(&[f64]) -> f64 + Send + Sync>;

/// Adds `w_d·value` to reading i's range row of column `col`.
pub(super) fn put_d(c: &mut Signature, i: usize, r: &ReadingInfo, col: usize, value_mm: f64) {
    c.add(i, 2, col, value_mm / r.sigma.z);
}

/// Adds a point displacement `s_mm` (campaign frame, per unit of the
/// column's parameter) to reading i.
pub(super) fn put_point(
    c: &mut Signature,
    i: usize,
    r: &ReadingInfo,
    col: usize,
    s_mm: Vector3<f64>,
) {
    let dq = r.jinv * (r.rotation.transpose() * s_mm);
    for a in 0..3 {
        c.add(i, a, col, dq[a] / r.sigma[a]);
    }
}

/// Every candidate for these readings. `stations`, `targets`: ids by
/// index; `station_order`: stations in the order they measured.
pub fn build(
    readings: &[ReadingInfo],
    stations: &[String],
    targets: &[String],
    station_order: &[usize],
    enabled: &dyn Fn(&str) -> bool,
) -> (Vec<Candidate>, Vec<Skipped>) {
    let mut out = Vec::new();
    let mut skipped = Vec::new();
    let skip = |effect: &str, reason: &str, skipped: &mut Vec<Skipped>| {
        skipped.push(Skipped {
            effect: effect.to_string(),
            reason: reason.to_string(),
        })
    };

    // incidence and incidence-table9: the SMR axes. A reflector whose axis
    // is not known (no aim point) contributes nothing to these columns: the
    // effect is fitted on the readings whose incidence is known.
    let known = readings.iter().filter(|r| r.incidence.is_some()).count();
    let has_incidence = known > 0;
    let incidence_detail = if known < readings.len() {
        format!(
            "fitted on the {known} of {} readings whose SMR axis is known",
            readings.len()
        )
    } else {
        String::new()
    };
    if enabled("incidence") {
        if has_incidence {
            let mut c = Signature::new(3);
            for (i, r) in readings.iter().enumerate() {
                let Some(a) = r.incidence else { continue };
                put_d(&mut c, i, r, 0, 1e-3 * (1.0 - a.alpha.cos()));
                put_d(&mut c, i, r, 1, 1e-3 * a.alpha_h.sin());
                put_d(&mut c, i, r, 2, 1e-3 * a.alpha_v.sin());
            }
            out.push(Candidate {
                effect: "incidence".into(),
                place: "all".into(),
                columns: c,
                magnitude: Arc::new(first),
                unit: "µm".into(),
                alternatives: 1,
                detail: incidence_detail.clone(),
            });
        } else {
            skip(
                "incidence",
                "the SMR axes are unknown: no aim point usable in this frame and no aim rule",
                &mut skipped,
            );
        }
    }
    if enabled("incidence-table9") {
        if has_incidence {
            let mut c = Signature::new(1);
            for (i, r) in readings.iter().enumerate() {
                let Some(a) = r.incidence else { continue };
                if let Some(um) = table9_delta_d_um(a.alpha_v, a.alpha_h) {
                    put_d(&mut c, i, r, 0, 1e-3 * um);
                }
            }
            out.push(Candidate {
                effect: "incidence-table9".into(),
                place: "all".into(),
                columns: c,
                magnitude: Arc::new(first),
                unit: "× Table 9".into(),
                alternatives: 1,
                detail: incidence_detail.clone(),
            });
        } else {
            skip(
                "incidence-table9",
                "the SMR axes are unknown: no aim point usable in this frame and no aim rule",
                &mut skipped,
            );
        }
    }

    // range-scale: each station alone, and every station at once.
    if enabled("range-scale") {
        // One ppm column per station that `col` maps to a column.
        let scale = |n: usize, col: &dyn Fn(usize) -> Option<usize>| {
            let mut c = Signature::new(n);
            for (i, r) in readings.iter().enumerate() {
                if let Some(k) = col(r.station) {
                    put_d(&mut c, i, r, k, 1e-6 * r.d);
                }
            }
            c
        };
        for (s, id) in stations.iter().enumerate() {
            out.push(Candidate {
                effect: "range-scale".into(),
                place: id.clone(),
                columns: scale(1, &|station| (station == s).then_some(0)),
                magnitude: Arc::new(first),
                unit: "ppm".into(),
                alternatives: 1,
                detail: String::new(),
            });
        }
        out.push(Candidate {
            effect: "range-scale".into(),
            place: "all".into(),
            columns: scale(stations.len(), &Some),
            magnitude: Arc::new(largest),
            unit: "ppm (largest)".into(),
            alternatives: 1,
            detail: String::new(),
        });
    }

    // air-refraction: a scale that follows the recorded temperature.
    if enabled("air-refraction") {
        if readings.iter().all(|r| r.temperature_c.is_some()) {
            let mean = readings.iter().filter_map(|r| r.temperature_c).sum::<f64>()
                / readings.len() as f64;
            let mut c = Signature::new(2);
            for (i, r) in readings.iter().enumerate() {
                let t = r.temperature_c.expect("checked");
                put_d(&mut c, i, r, 0, 1e-6 * (t - mean) * r.d);
                put_d(&mut c, i, r, 1, 1e-6 * r.d);
            }
            out.push(Candidate {
                effect: "air-refraction".into(),
                place: "all".into(),
                columns: c,
                magnitude: Arc::new(first),
                unit: "ppm/K".into(),
                alternatives: 1,
                detail: String::new(),
            });
        } else {
            skip(
                "air-refraction",
                "readings.csv has no temperature_c for every reading",
                &mut skipped,
            );
        }
    }

    // encoder-harmonic: orders 2–4 on each axis; the order is chosen later.
    if enabled("encoder-harmonic") {
        for (axis, a) in [("az", 0usize), ("el", 1usize)] {
            for order in 2..=4u32 {
                let mut c = Signature::new(2);
                for (i, r) in readings.iter().enumerate() {
                    let angle = if a == 0 { r.az } else { r.el };
                    let k = order as f64 * angle;
                    c.add(i, a, 0, 1e-6 * k.sin() / r.sigma[a]);
                    c.add(i, a, 1, 1e-6 * k.cos() / r.sigma[a]);
                }
                out.push(Candidate {
                    effect: "encoder-harmonic".into(),
                    place: axis.into(),
                    columns: c,
                    magnitude: Arc::new(norm),
                    unit: "µrad".into(),
                    alternatives: 3,
                    detail: format!("order {order}"),
                });
            }
        }
    }

    // station-drift: each station, and one velocity for all.
    if enabled("station-drift") {
        if readings.iter().all(|r| r.since_station_s.is_some()) {
            let drift = |c: &mut Signature, i: usize, r: &ReadingInfo| {
                let minutes = r.since_station_s.expect("checked") / 60.0;
                for a in 0..3 {
                    let mut s = Vector3::zeros();
                    // The origin moves by v·τ: the reflector seems to move by −v·τ.
                    s[a] = -1e-3 * minutes;
                    put_point(c, i, r, a, s);
                }
            };
            for (s, id) in stations.iter().enumerate() {
                let mut c = Signature::new(3);
                for (i, r) in readings.iter().enumerate().filter(|(_, r)| r.station == s) {
                    drift(&mut c, i, r);
                }
                out.push(Candidate {
                    effect: "station-drift".into(),
                    place: id.clone(),
                    columns: c,
                    magnitude: Arc::new(norm),
                    unit: "µm/min".into(),
                    alternatives: 1,
                    detail: String::new(),
                });
            }
            let mut c = Signature::new(3);
            for (i, r) in readings.iter().enumerate() {
                drift(&mut c, i, r);
            }
            out.push(Candidate {
                effect: "station-drift".into(),
                place: "all".into(),
                columns: c,
                magnitude: Arc::new(norm),
                unit: "µm/min".into(),
                alternatives: 1,
                detail: String::new(),
            });
        } else {
            skip(
                "station-drift",
                "readings.csv has no time_s for every reading",
                &mut skipped,
            );
        }
    }

    // target-shift: each reflector, from each station but the first.
    if enabled("target-shift") {
        let n_from = station_order.len().saturating_sub(1);
        // Each reflector's readings, ascending: a candidate visits its own.
        let mut of_target: Vec<Vec<usize>> = vec![Vec::new(); targets.len()];
        for (i, r) in readings.iter().enumerate() {
            of_target[r.target].push(i);
        }
        // Each station's place in the measuring order.
        let mut rank = vec![usize::MAX; stations.len()];
        for (k, &s) in station_order.iter().enumerate() {
            rank[s] = k;
        }
        for (t, id) in targets.iter().enumerate() {
            if of_target[t].is_empty() {
                continue;
            }
            for k in 1..station_order.len() {
                let mut c = Signature::new(3);
                for &i in &of_target[t] {
                    let r = &readings[i];
                    if rank[r.station] >= k {
                        for a in 0..3 {
                            let mut s = Vector3::zeros();
                            s[a] = 1e-3;
                            put_point(&mut c, i, r, a, s);
                        }
                    }
                }
                out.push(Candidate {
                    effect: "target-shift".into(),
                    place: id.clone(),
                    columns: c,
                    magnitude: Arc::new(norm),
                    unit: "µm".into(),
                    alternatives: n_from,
                    detail: format!("from station {}", stations[station_order[k]]),
                });
            }
        }
    }
    (out, skipped)
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
