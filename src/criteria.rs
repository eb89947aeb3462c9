//! The evaluation criteria of Sections 5.2, 8 and 9: how well the stations
//! of a campaign agree with each other, and with reference data, before and
//! after a calibration.
//!
//! * Eq. (16), distances criterion: the difference between the distance of
//!   a reflector pair measured from one station and from another,
//!   `|dᵐ_ij − dⁿ_ij|`, averaged over pairs and station pairs.
//! * Eq. (17), coordinates criterion: after a best-fit registration of all
//!   stations into one frame, the distance between the coordinates of the
//!   same reflector from two stations, `‖Xᵐ_i − Xⁿ_i‖`.
//! * Against references (Table 4, Table 8): distances against the
//!   distances of the reference coordinates, and coordinates after each
//!   station's best fit onto the reference coordinates.
//!
//! Eq. (16) and (17) as printed divide signed sums by the number of terms;
//! they are means of absolute differences (a signed mean would cancel).
//! Per-station columns (Tables 5, 6: LT1 … LT5) average the terms in which
//! that station takes part; the overall column averages all terms once.
//! A station's point for a reflector is the mean of its readings of it
//! (both faces, repeats).

use crate::calibrate::Network;
use crate::calibrate::register::{align, fit};
use crate::error_model::ErrorParams;
use nalgebra::Vector3;
use std::collections::BTreeMap;

/// Mean and maximum of a set of errors (µm).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Stat {
    pub mean_um: f64,
    pub max_um: f64,
    pub count: usize,
}

impl Stat {
    fn of(v: &[f64]) -> Stat {
        if v.is_empty() {
            return Stat::default();
        }
        Stat {
            mean_um: v.iter().sum::<f64>() / v.len() as f64,
            max_um: v.iter().copied().fold(0.0, f64::max),
            count: v.len(),
        }
    }
}

/// A criterion per station and overall.
#[derive(Clone, Debug, Default)]
pub struct Criterion {
    pub per_station: Vec<Stat>,
    pub overall: Stat,
    /// Every term: `(station m, station n, reflectors…, error µm)`, for plots.
    pub terms: Vec<Term>,
    /// Eq. (17) only: whether the registration it compares after reached
    /// its tolerance ([`crate::calibrate::register::Alignment::converged`]);
    /// `None` for criteria without a registration.
    pub registration_converged: Option<bool>,
}

/// One compared quantity.
#[derive(Clone, Debug, PartialEq)]
pub struct Term {
    pub stations: (usize, usize),
    /// One reflector (coordinates) or two (distances).
    pub targets: (usize, Option<usize>),
    pub error_um: f64,
}

fn summarise(n_stations: usize, terms: Vec<Term>) -> Criterion {
    let mut per: Vec<Vec<f64>> = vec![Vec::new(); n_stations];
    for t in &terms {
        per[t.stations.0].push(t.error_um);
        if t.stations.1 != t.stations.0 {
            per[t.stations.1].push(t.error_um);
        }
    }
    let all: Vec<f64> = terms.iter().map(|t| t.error_um).collect();
    Criterion {
        per_station: per.iter().map(|v| Stat::of(v)).collect(),
        overall: Stat::of(&all),
        terms,
        registration_converged: None,
    }
}

/// Eq. (16): distances between stations.
pub fn distances(net: &Network, params: &ErrorParams) -> Criterion {
    let pts = net.station_points(params);
    let mut terms = Vec::new();
    for m in 0..pts.len() {
        for n in m + 1..pts.len() {
            let common: Vec<usize> = pts[m]
                .keys()
                .filter(|k| pts[n].contains_key(k))
                .copied()
                .collect();
            for (a, &i) in common.iter().enumerate() {
                for &j in &common[a + 1..] {
                    let dm = (pts[m][&i] - pts[m][&j]).norm();
                    let dn = (pts[n][&i] - pts[n][&j]).norm();
                    terms.push(Term {
                        stations: (m, n),
                        targets: (i, Some(j)),
                        error_um: (dm - dn).abs() * 1e3,
                    });
                }
            }
        }
    }
    summarise(pts.len(), terms)
}

/// Eq. (17): coordinates between stations after registration into one
/// frame. `None` when the stations cannot be registered.
pub fn coordinates(net: &Network, params: &ErrorParams) -> Option<Criterion> {
    let pts = net.station_points(params);
    let a = align(&pts, None, 1e-10)?;
    let reg: Vec<BTreeMap<usize, Vector3<f64>>> = pts
        .iter()
        .zip(&a.poses)
        .map(|(p, pose)| p.iter().map(|(k, x)| (*k, pose.apply(x))).collect())
        .collect();
    let mut terms = Vec::new();
    for m in 0..reg.len() {
        for n in m + 1..reg.len() {
            for (i, xm) in &reg[m] {
                if let Some(xn) = reg[n].get(i) {
                    terms.push(Term {
                        stations: (m, n),
                        targets: (*i, None),
                        error_um: (xm - xn).norm() * 1e3,
                    });
                }
            }
        }
    }
    Some(Criterion {
        registration_converged: Some(a.converged),
        ..summarise(reg.len(), terms)
    })
}

/// Distances against the distances of the reference coordinates (Table 4,
/// Table 8 "Distances"): `|dᵏ_ij − d_ij^ref|` for every station.
pub fn reference_distances(net: &Network, params: &ErrorParams) -> Criterion {
    let pts = net.station_points(params);
    let refs = net.reference_points();
    let mut terms = Vec::new();
    for (k, p) in pts.iter().enumerate() {
        let ids: Vec<usize> = p.keys().filter(|i| refs.contains_key(i)).copied().collect();
        for (a, &i) in ids.iter().enumerate() {
            for &j in &ids[a + 1..] {
                let d = (p[&i] - p[&j]).norm();
                let dr = (refs[&i] - refs[&j]).norm();
                terms.push(Term {
                    stations: (k, k),
                    targets: (i, Some(j)),
                    error_um: (d - dr).abs() * 1e3,
                });
            }
        }
    }
    summarise(pts.len(), terms)
}

/// Coordinates against the reference coordinates after each station's best
/// fit onto them (Table 8 "Coordinates"). Stations with fewer than three
/// referenced reflectors (not on a line) are left out.
pub fn reference_coordinates(net: &Network, params: &ErrorParams) -> Criterion {
    let pts = net.station_points(params);
    let refs = net.reference_points();
    let mut terms = Vec::new();
    for (k, p) in pts.iter().enumerate() {
        let ids: Vec<usize> = p.keys().filter(|i| refs.contains_key(i)).copied().collect();
        let from: Vec<Vector3<f64>> = ids.iter().map(|i| p[i]).collect();
        let to: Vec<Vector3<f64>> = ids.iter().map(|i| refs[i]).collect();
        let Some(pose) = fit(&from, &to) else {
            continue;
        };
        for (i, x) in ids.iter().zip(&from) {
            terms.push(Term {
                stations: (k, k),
                targets: (*i, None),
                error_um: (pose.apply(x) - refs[i]).norm() * 1e3,
            });
        }
    }
    summarise(pts.len(), terms)
}

/// `100·(1 − after/before)`.
pub fn improvement_pct(before: f64, after: f64) -> f64 {
    if before > 0.0 {
        100.0 * (1.0 - after / before)
    } else {
        0.0
    }
}
