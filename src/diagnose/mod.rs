//! Diagnosing the sim-to-real gap of a campaign: where the residual of the
//! base calibration lies, which unmodelled effect causes it, and how far the
//! gap shrinks once that effect is modelled.
//!
//! 1. The campaign is calibrated with the base model (a bundle adjustment;
//!    the paper's 18 constant parameters unless a pipeline says otherwise).
//! 2. **Where** — [`factors`]: residuals by station, reflector, incidence,
//!    range, azimuth, elevation, time, temperature.
//! 3. **Which** — [`candidates`], scored on the linearised adjustment
//!    ([`linear`]): for every effect of `effects.md` (and the per-station and
//!    per-reflector variants), the χ² it explains, its F test
//!    (Bonferroni-corrected over every alternative tried; [`f_test`], safe on
//!    any statistic), the Bayesian
//!    information criterion, and the share of *held-out* residual it
//!    predicts (k-fold cross-validation, the `score`). A candidate is
//!    significant when all three agree; significant candidates are ranked
//!    by the information criterion. With none significant, the answer is `none` — if the
//!    residual is consistent with the stated noise (χ² test); otherwise
//!    `none` with "unexplained structure" and where it lies.
//! 4. **How far** — the gap is the held-out residual (µm) minus the one
//!    noise alone leaves in the same geometry (Monte Carlo draws of the
//!    stated noise through the same linearised adjustment), before and
//!    after adding the effect.

pub mod blind;
pub mod candidates;
pub mod f_test;
pub mod factors;
pub mod linear;
pub mod output;

use crate::calibrate::{self, Calibration, Network, Norm, Objective, Settings as CalSettings};
use crate::campaign::{Aim, Campaign};
use crate::error_model::{ErrorModel, ErrorParams, ParamId};
use crate::kinematics::nominal_jacobian;
use crate::random;
use anyhow::{Result, anyhow};
use candidates::{Candidate, ReadingInfo, Skipped};
use factors::{FactorTest, ResidualRow};
use linear::LinearModel;
use nalgebra::{DVector, Matrix3, Vector3};
use rayon::prelude::*;

/// How to diagnose.
#[derive(Clone, Debug)]
pub struct Settings {
    /// The base model.
    pub model: ErrorModel,
    pub fixed: Vec<ParamId>,
    /// Cross-validation folds.
    pub folds: usize,
    /// Monte Carlo draws of the noise floor.
    pub mc_draws: usize,
    /// Family-wise significance level.
    pub alpha: f64,
    /// Effect ids to try (empty: all).
    pub effects: Vec<String>,
    pub seed: u64,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            model: ErrorModel::constant(),
            fixed: Vec::new(),
            folds: 5,
            mc_draws: 100,
            alpha: 0.01,
            effects: Vec::new(),
            seed: 0,
        }
    }
}

/// One row of `diagnosis.csv`.
#[derive(Clone, Debug, PartialEq)]
pub struct Row {
    pub rank: usize,
    pub effect: String,
    pub place: String,
    pub magnitude: f64,
    pub unit: String,
    /// Held-out mean-square residual explained, %.
    pub score: f64,
    pub significant: bool,
    pub rms_before_um: f64,
    pub rms_after_um: f64,
    pub gap_before_um: f64,
    pub gap_after_um: f64,
    pub gap_shrink_pct: f64,
    /// Supporting numbers: parameters added, χ² explained, F-test p
    /// (corrected), ΔBIC, and the chosen alternative.
    pub k: usize,
    pub delta_chi2: f64,
    pub p_corrected: f64,
    pub delta_bic: f64,
    pub detail: String,
}

/// The whole diagnosis.
#[derive(Clone, Debug)]
pub struct Diagnosis {
    pub campaign: String,
    pub rows: Vec<Row>,
    pub factors: Vec<FactorTest>,
    pub residuals: Vec<ResidualRow>,
    pub factor_defs: Vec<factors::Factor>,
    pub skipped: Vec<Skipped>,
    pub chi2: f64,
    pub dof: usize,
    pub chi2_p: f64,
    pub noise_stated: bool,
    /// The held-out RMS noise alone leaves (µm).
    pub noise_floor_um: f64,
    pub calibration: Calibration,
    /// Each reading's σ in az, el (rad) and d (mm), in reading order.
    pub sigma: Vec<Vector3<f64>>,
    /// Candidates tried, alternatives included (the Bonferroni factor).
    pub tried: usize,
}

impl Diagnosis {
    /// Rank 1.
    pub fn best(&self) -> &Row {
        &self.rows[0]
    }
}

/// Each station's earliest `time_s`, when its readings carry one.
fn first_times(c: &Campaign, stations: &[String]) -> Vec<Option<f64>> {
    stations
        .iter()
        .map(|id| {
            c.readings
                .iter()
                .filter(|r| &r.station == id)
                .filter_map(|r| r.time_s)
                .reduce(f64::min)
        })
        .collect()
}

/// The order in which stations measured: by their earliest `time_s` when
/// every station has one, else by their first reading in the file (times
/// and file positions are not compared with each other).
fn station_order(c: &Campaign, stations: &[String]) -> Vec<usize> {
    let first_row: Vec<usize> = stations
        .iter()
        .map(|id| {
            c.readings
                .iter()
                .position(|r| &r.station == id)
                .unwrap_or(usize::MAX)
        })
        .collect();
    let times: Option<Vec<f64>> = first_times(c, stations).into_iter().collect();
    let mut order: Vec<usize> = (0..stations.len()).collect();
    match times {
        Some(t) => {
            order.sort_by(|&a, &b| t[a].total_cmp(&t[b]).then(first_row[a].cmp(&first_row[b])))
        }
        None => order.sort_by_key(|&s| first_row[s]),
    }
    order
}

/// Diagnoses a campaign: the base calibration, then where, which and how
/// far (see the module doc), step by step.
pub fn diagnose(c: &Campaign, s: &Settings) -> Result<Diagnosis> {
    let net = Network::from_campaign(c)?;
    let cal = base_calibration(&net, s)?;
    let lin = cal
        .linearisation
        .clone()
        .ok_or_else(|| anyhow!("the bundle adjustment gave no linearisation"))?;
    let infos = reading_infos(c, &net, &cal);
    let (fold_of, n_folds) = folds(&net, s);
    let to_mm: Vec<Matrix3<f64>> = net
        .obs
        .iter()
        .map(|o| nominal_jacobian(o.reading) * Matrix3::from_diagonal(&o.sigma))
        .collect();
    let lm = LinearModel::new(lin.jacobian, lin.residuals, &fold_of, n_folds, to_mm)?;
    let chi2 = lm.chi2();
    let dof = cal.fit.dof.unwrap_or(lm.dof());
    let chi2_p = cal.fit.chi2_p.unwrap_or(1.0);
    let floor = noise_floor(&lm, s);

    // Which.
    let enabled = |id: &str| s.effects.is_empty() || s.effects.iter().any(|e| e == id);
    let (cands, skipped) = candidates::build(
        &infos,
        &net.stations,
        &net.targets,
        &station_order(c, &net.stations),
        &enabled,
    );
    let (mut rows, tried) = score(&lm, &cands, dof, floor, s.alpha);

    // Where.
    let residuals = residual_rows(c, &net, &cal, &infos);
    let factor_defs = factors::factors(&residuals);
    let factor_tests = factors::analyse(&residuals, &factor_defs, s.alpha);

    let rms_before = lm.cv_rms_um_base();
    rows.push(none_row(
        chi2,
        dof,
        chi2_p,
        s.alpha,
        rms_before,
        floor,
        &factor_tests,
    ));
    rank(&mut rows);
    Ok(Diagnosis {
        campaign: c.meta.name.clone(),
        rows,
        factors: factor_tests,
        residuals,
        factor_defs,
        skipped,
        chi2,
        dof,
        chi2_p,
        noise_stated: net.noise_stated,
        noise_floor_um: floor,
        calibration: cal,
        sigma: net.obs.iter().map(|o| o.sigma).collect(),
        tried,
    })
}

/// Step 1: the bundle adjustment with the base model.
fn base_calibration(net: &Network, s: &Settings) -> Result<Calibration> {
    let start = ErrorParams::zero(&s.model);
    let free: Vec<bool> = start
        .coefs()
        .iter()
        .map(|k| !s.fixed.contains(&k.param))
        .collect();
    calibrate::calibrate(
        net,
        &start,
        &free,
        &CalSettings {
            objective: Objective::Bundle,
            norm: Norm::L2,
            rank_tol: crate::identifiability::DEFAULT_REL_TOL,
            max_iters: 100,
        },
    )
}

/// Per reading, what the candidates and the factors need: its geometry at
/// the base solution, its time since its station began, its incidence.
fn reading_infos(c: &Campaign, net: &Network, cal: &Calibration) -> Vec<ReadingInfo> {
    let first_time = first_times(c, &net.stations);
    let centroid = cal
        .poses
        .iter()
        .map(|p| p.translation)
        .sum::<Vector3<f64>>()
        / cal.poses.len() as f64;
    let axis = |t: usize| -> Option<Vector3<f64>> {
        let x = cal.points.get(&t)?;
        match c.meta.aim {
            Aim::StationsCentroid => Some((centroid - x).normalize()),
            // Aim points are given in the reference frame: usable when the
            // references define the adjustment's frame.
            Aim::AimColumns => net
                .references_fix_frame()
                .then(|| c.targets[t].aim.map(|a| (a - x).normalize()))
                .flatten(),
        }
    };
    net.obs
        .iter()
        .zip(&c.readings)
        .map(|(o, r)| {
            let j = nominal_jacobian(o.reading);
            let pose = &cal.poses[o.station];
            ReadingInfo {
                station: o.station,
                target: o.target,
                az: o.reading.az,
                el: o.reading.el,
                d: o.reading.d,
                sigma: o.sigma,
                jinv: j.try_inverse().unwrap_or_else(Matrix3::zeros),
                rotation: *pose.rotation.matrix(),
                since_station_s: r.time_s.zip(first_time[o.station]).map(|(t, t0)| t - t0),
                temperature_c: r.temperature_c,
                incidence: axis(o.target).and_then(|n| {
                    cal.points
                        .get(&o.target)
                        .map(|x| candidates::incidence(&n, x, &pose.translation))
                }),
            }
        })
        .collect()
}

/// Cross-validation folds (each reading's fold, and their number),
/// stratified by reflector: each reflector's
/// readings go round the folds from a random start, so no fold holds out
/// every reading of a reflector (which no model could predict).
fn folds(net: &Network, s: &Settings) -> (Vec<usize>, usize) {
    let folds = s.folds.clamp(2, net.obs.len().max(2));
    let mut rng = random::stream(s.seed, "diagnose-folds");
    let mut fold_of = vec![0; net.obs.len()];
    let mut next: std::collections::BTreeMap<usize, usize> = Default::default();
    for (i, o) in net.obs.iter().enumerate() {
        let k = next
            .entry(o.target)
            .or_insert_with(|| (random::uniform(&mut rng) * folds as f64) as usize % folds);
        fold_of[i] = *k;
        *k = (*k + 1) % folds;
    }
    (fold_of, folds)
}

/// How far, the reference: the held-out RMS the stated noise alone leaves,
/// by Monte Carlo draws through the same adjustment.
fn noise_floor(lm: &LinearModel, s: &Settings) -> f64 {
    let mut mc = random::stream(s.seed, "diagnose-noise");
    let draws: Vec<DVector<f64>> = (0..s.mc_draws)
        .map(|_| DVector::from_fn(lm.rows(), |_, _| random::normal(&mut mc)))
        .collect();
    lm.noise_floor_um(&draws)
}

/// Step 3, which: every candidate's fit, the best alternative of each
/// (effect, place) by χ², and its row — F test (Bonferroni over every
/// alternative tried), ΔBIC, held-out score and gap. Also returns the
/// number of alternatives tried.
fn score(
    lm: &LinearModel,
    cands: &[Candidate],
    dof: usize,
    floor: f64,
    alpha: f64,
) -> (Vec<Row>, usize) {
    let chi2 = lm.chi2();
    let rms_before = lm.cv_rms_um_base();
    let fits: Vec<linear::Fit> = cands.par_iter().map(|c| lm.fit(&c.columns)).collect();
    let mut best: Vec<(usize, f64)> = Vec::new();
    for (i, (c, f)) in cands.iter().zip(&fits).enumerate() {
        match best
            .iter_mut()
            .find(|(j, _)| cands[*j].effect == c.effect && cands[*j].place == c.place)
        {
            Some(b) if f.delta_chi2 > b.1 => *b = (i, f.delta_chi2),
            Some(_) => {}
            None => best.push((i, f.delta_chi2)),
        }
    }
    let tried: usize = best.iter().map(|(i, _)| cands[*i].alternatives).sum();
    let m = lm.rows() as f64;
    let rows = best
        .par_iter()
        .map(|&(i, _)| {
            let cand: &Candidate = &cands[i];
            let fit = &fits[i];
            let k = cand.columns.ncols();
            let rest = (chi2 - fit.delta_chi2).max(1e-300);
            let dof_aug = dof.saturating_sub(k).max(1);
            let f_stat = (fit.delta_chi2 / k as f64) / (rest / dof_aug as f64);
            let p = f_test::p_value(k as f64, dof_aug as f64, f_stat);
            let p_corrected = (p * tried as f64).min(1.0);
            let delta_bic = fit.delta_chi2 - k as f64 * m.ln();
            let rms_after = lm.cv_rms_um(&cand.columns);
            let score = 100.0 * (1.0 - (rms_after / rms_before).powi(2));
            let (gb, ga) = (rms_before - floor, rms_after - floor);
            Row {
                rank: 0,
                effect: cand.effect.to_string(),
                place: cand.place.clone(),
                magnitude: (cand.magnitude)(&fit.beta),
                unit: cand.unit.to_string(),
                score,
                significant: p_corrected < alpha && delta_bic > 0.0 && score > 0.0,
                rms_before_um: rms_before,
                rms_after_um: rms_after,
                gap_before_um: gb,
                gap_after_um: ga,
                gap_shrink_pct: if gb > 0.0 {
                    100.0 * (1.0 - ga / gb)
                } else {
                    0.0
                },
                k,
                delta_chi2: fit.delta_chi2,
                p_corrected,
                delta_bic,
                detail: cand.detail.clone(),
            }
        })
        .collect();
    (rows, tried)
}

/// Step 2, where: each reading's residual with what the factors group by.
fn residual_rows(
    c: &Campaign,
    net: &Network,
    cal: &Calibration,
    infos: &[ReadingInfo],
) -> Vec<ResidualRow> {
    cal.residuals
        .iter()
        .map(|rr| {
            let o = &net.obs[rr.obs];
            let r = &c.readings[rr.obs];
            ResidualRow {
                sigma_units: [rr.normalized.x, rr.normalized.y, rr.normalized.z],
                physical: [rr.az_urad, rr.el_urad, rr.d_um],
                station: net.stations[o.station].clone(),
                target: net.targets[o.target].clone(),
                face: o.face.number(),
                incidence_deg: infos[rr.obs].incidence.map(|a| a.alpha.to_degrees()),
                range_mm: o.reading.d,
                azimuth_deg: crate::kinematics::wrap_angle(o.reading.az).to_degrees(),
                elevation_deg: o.reading.el.to_degrees(),
                time_s: r.time_s,
                temperature_c: r.temperature_c,
            }
        })
        .collect()
}

/// The `none` row: accepted when the residual is consistent with the
/// stated noise (χ² test); otherwise "unexplained structure" and where the
/// factors say it lies.
fn none_row(
    chi2: f64,
    dof: usize,
    chi2_p: f64,
    alpha: f64,
    rms_before: f64,
    floor: f64,
    factor_tests: &[FactorTest],
) -> Row {
    let noise_ok = chi2_p >= alpha;
    let place = if noise_ok {
        "all".to_string()
    } else {
        let top = factor_tests
            .iter()
            .filter(|t| t.significant)
            .max_by(|a, b| a.eta2.total_cmp(&b.eta2));
        match top {
            Some(t) => format!(
                "unexplained structure: {} residual by {} (η² = {:.2}, worst {})",
                t.component, t.factor, t.eta2, t.worst_group
            ),
            None => "unexplained structure: residual above the stated noise, no factor stands out"
                .into(),
        }
    };
    Row {
        rank: 0,
        effect: "none".into(),
        place,
        magnitude: chi2 / dof as f64,
        unit: "χ²/dof".into(),
        score: 0.0,
        significant: noise_ok,
        rms_before_um: rms_before,
        rms_after_um: rms_before,
        gap_before_um: rms_before - floor,
        gap_after_um: rms_before - floor,
        gap_shrink_pct: 0.0,
        k: 0,
        delta_chi2: 0.0,
        p_corrected: chi2_p,
        delta_bic: 0.0,
        detail: format!("χ² = {chi2:.1} on {dof} degrees of freedom, p = {chi2_p:.3}"),
    }
}

/// The ranking: the significant first, then `none`, then the rest. Within
/// a class the information criterion orders: it weighs what a candidate
/// explains against its parameters, so the one station that drifts beats
/// "every station", and a reflector knocked between stations is not
/// out-scored by cross-validation, which cannot predict a held-out reading
/// from before the knock.
fn rank(rows: &mut [Row]) {
    let class = |r: &Row| match (r.effect.as_str(), r.significant) {
        ("none", _) => 1,
        (_, true) => 0,
        _ => 2,
    };
    rows.sort_by(|a, b| {
        class(a)
            .cmp(&class(b))
            .then(b.delta_bic.total_cmp(&a.delta_bic))
            .then(a.effect.cmp(&b.effect))
            .then(a.place.cmp(&b.place))
    });
    for (i, r) in rows.iter_mut().enumerate() {
        r.rank = i + 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::campaign::CampaignReading;
    use crate::kinematics::Face;

    fn campaign(rows: &[(&str, Option<f64>)]) -> Campaign {
        let readings = rows
            .iter()
            .map(|&(station, time_s)| CampaignReading {
                station: station.into(),
                target: "T01".into(),
                az_deg: 0.0,
                el_deg: 0.0,
                d_mm: 1000.0,
                face: Face::Front,
                time_s,
                temperature_c: None,
                pressure_hpa: None,
                humidity_pct: None,
            })
            .collect();
        Campaign {
            readings,
            ..Campaign::default()
        }
    }

    /// Regression: the order came from the time of each station's first
    /// row in the file, and compared file positions with times when only
    /// some readings had a time.
    #[test]
    fn stations_are_ordered_by_their_earliest_time_else_by_the_file() {
        let ids = ["S1".to_string(), "S2".to_string()];
        // S2's rows come first in the file but S1 measured first.
        let timed = campaign(&[("S2", Some(500.0)), ("S1", Some(900.0)), ("S1", Some(10.0))]);
        assert_eq!(station_order(&timed, &ids), [0, 1]);
        let partly = campaign(&[("S2", Some(500.0)), ("S1", None)]);
        assert_eq!(station_order(&partly, &ids), [1, 0]);
    }
}
