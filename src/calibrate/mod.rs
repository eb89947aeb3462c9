//! Calibration with unknown station poses (Sections 5.2, 7, 8): the error
//! parameters from a campaign, where nobody knows the reflectors' true
//! positions.
//!
//! * [`distances`] — the paper's objectives: Eq. (13) (distances against
//!   reference distances), Eq. (14) (distances between stations only) and
//!   Eq. (15) (Eq. 14 plus the gauge), each in the paper's absolute-value
//!   (L1) form and in least-squares form. Distances measured within one
//!   station do not depend on its pose, so these objectives have the error
//!   parameters as their only unknowns; poses and positions are estimated
//!   afterwards by registration ([`register`]).
//! * [`bundle`] — the statistically proper alternative: a bundle adjustment
//!   on the readings themselves (residuals in az, el, d weighted by the
//!   stated noise) with station poses and reflector positions as unknowns
//!   beside the error parameters, gauge lengths and reference coordinates as
//!   observations.
//!
//! Both report which error-parameter combinations the campaign determines,
//! estimate only those (the rest keep their start values: the minimum-norm
//! solution), and say so.

pub mod bundle;
pub mod distances;
pub mod measurement;
pub mod monte_carlo;
pub mod register;
pub mod snooping;
pub mod sparse;

use crate::campaign::Campaign;
use crate::determined::Estimate;
use crate::error_model::{ErrorParams, Links};
use crate::kinematics::{Face, Joints, Reading};
use crate::noise::Noise;
use anyhow::{Result, anyhow, bail};
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};

/// Reading noise assumed when the campaign does not state it (FIELD.md,
/// typical indoor values).
pub const DEFAULT_NOISE: Noise = Noise {
    sigma_angle_urad: 1.0,
    sigma_range_um: 2.0,
    sigma_range_ppm: 0.0,
};

/// One reading, prepared for repeated evaluation.
#[derive(Clone, Debug)]
pub struct Observation {
    pub station: usize,
    pub target: usize,
    pub face: Face,
    pub reading: Reading,
    pub q: Joints,
    pub links: Links,
    /// 1 σ of az and el (rad) and d (mm).
    pub sigma: Vector3<f64>,
}

/// A calibrated length between two reflectors.
#[derive(Clone, Debug)]
pub struct Gauge {
    pub a: usize,
    pub b: usize,
    pub length_mm: f64,
    pub u_mm: f64,
}

/// A campaign as the calibration sees it: ids as indices, readings
/// prepared, references and gauge attached.
#[derive(Clone, Debug)]
pub struct Network {
    pub stations: Vec<String>,
    pub targets: Vec<String>,
    pub obs: Vec<Observation>,
    pub gauge: Vec<Gauge>,
    /// Reference coordinates and their standard uncertainty (mm), per target.
    pub references: Vec<Option<(Vector3<f64>, f64)>>,
    pub noise: Noise,
    /// Whether `noise` was stated in the campaign (rather than assumed).
    pub noise_stated: bool,
}

/// What a coordinate rejected as a blunder has its σ multiplied by: its
/// weight falls by 1e12, so a 1 000 σ blunder still pulls like 1e-3 σ.
pub const REJECTED_SIGMA_FACTOR: f64 = 1e6;

/// Standard uncertainty assumed for reference coordinates and gauge lengths
/// that give none (mm).
pub const DEFAULT_REFERENCE_U_MM: f64 = 0.001;

/// The uncertainty an exact value (`u_mm = 0`) is weighted with (mm): 1 nm,
/// far below any tracker's noise, so the value is held, without the
/// infinite weight a literal zero would give.
pub const EXACT_U_MM: f64 = 1e-6;

/// The standard uncertainty a stated `u_mm` is weighted with: the default
/// when not known, at least [`EXACT_U_MM`] when stated as exact.
fn weighting_u_mm(u_mm: Option<f64>) -> f64 {
    u_mm.map_or(DEFAULT_REFERENCE_U_MM, |u| u.max(EXACT_U_MM))
}

impl Network {
    pub fn from_campaign(c: &Campaign) -> Result<Network> {
        // What would break the adjustment's numerics is named here, by its
        // reading, rather than found as a singular or non-finite matrix.
        let issues = c.calibration_issues();
        if let Some(first) = issues.first() {
            bail!(
                "the campaign cannot be calibrated ({} problem{}); first: {first}",
                issues.len(),
                if issues.len() == 1 { "" } else { "s" }
            );
        }
        let stations = c.stations();
        let targets: Vec<String> = c.targets.iter().map(|t| t.id.clone()).collect();
        // Looked up once per reading: a map, so that thousands of
        // reflectors cost no more per reading than ten.
        let mut by_id: HashMap<&str, usize> = HashMap::with_capacity(targets.len());
        for (i, t) in targets.iter().enumerate() {
            by_id.entry(t.as_str()).or_insert(i);
        }
        let station_of: HashMap<&str, usize> = stations
            .iter()
            .enumerate()
            .map(|(i, s)| (s.as_str(), i))
            .collect();
        let index = |id: &str| by_id.get(id).copied();
        let t = &c.meta.tracker;
        let noise_stated = t.sigma_angle_urad.is_some() || t.sigma_range_um.is_some();
        let noise = Noise {
            sigma_angle_urad: t.sigma_angle_urad.unwrap_or(DEFAULT_NOISE.sigma_angle_urad),
            sigma_range_um: t.sigma_range_um.unwrap_or(DEFAULT_NOISE.sigma_range_um),
            sigma_range_ppm: t.sigma_range_ppm.unwrap_or(DEFAULT_NOISE.sigma_range_ppm),
        };
        // A noise-free campaign still needs weights: keep them finite.
        let floor = |v: f64, min: f64| if v > 0.0 { v } else { min };
        // Each reading's reflector found first: an unknown one is reported
        // for the first such reading, in order.
        let Some(target_of) = c
            .readings
            .par_iter()
            .with_min_len(1024)
            .map(|r| index(&r.target))
            .collect::<Option<Vec<usize>>>()
        else {
            let r = c.readings.iter().find(|r| index(&r.target).is_none());
            bail!(
                "reading of unknown reflector `{}`",
                r.map_or("", |r| r.target.as_str())
            );
        };
        // Then each reading on its own, in parallel (its link rotations cost
        // a sine and cosine each: a few ms at 24 000 readings), written
        // straight into the network's list: collected as results first and
        // then unwrapped, its 6 MB were copied again on one core (issue 34).
        let obs: Vec<Observation> = c
            .readings
            .par_iter()
            .zip(target_of)
            .with_min_len(1024)
            .map(|(r, target)| {
                let station = station_of[r.station.as_str()];
                let reading = r.reading();
                let q = reading.joints();
                Observation {
                    station,
                    target,
                    face: r.face,
                    reading,
                    q,
                    links: Links::new(q),
                    sigma: Vector3::new(
                        floor(noise.sigma_angle_urad, 1e-3) * 1e-6,
                        floor(noise.sigma_angle_urad, 1e-3) * 1e-6,
                        floor(noise.sigma_range_at_um(r.d_mm), 1e-3) * 1e-3,
                    ),
                }
            })
            .collect();
        let gauge = c
            .gauge
            .iter()
            .map(|g| {
                Ok(Gauge {
                    a: index(&g.target_a)
                        .ok_or_else(|| anyhow!("gauge names unknown `{}`", g.target_a))?,
                    b: index(&g.target_b)
                        .ok_or_else(|| anyhow!("gauge names unknown `{}`", g.target_b))?,
                    length_mm: g.distance_mm,
                    u_mm: weighting_u_mm(g.u_mm),
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let references = c
            .targets
            .iter()
            .map(|t| t.reference.map(|x| (x, weighting_u_mm(t.u_mm))))
            .collect();
        if obs.is_empty() {
            bail!("the campaign has no readings");
        }
        Ok(Network {
            stations,
            targets,
            obs,
            gauge,
            references,
            noise,
            noise_stated,
        })
    }

    /// The network with reading `i` moved by `−shift` for each `(i, shift)`
    /// (Δaz, Δel in rad, Δd in mm: what an effect added, taken off) and
    /// each `(i, coordinate)` of `rejected` down-weighted by
    /// [`REJECTED_SIGMA_FACTOR`]: a coordinate rejected as a blunder keeps
    /// its place (the readings keep their indices) but no longer pulls.
    pub fn adjusted(
        &self,
        shifts: &[(usize, Vector3<f64>)],
        rejected: &[(usize, usize)],
    ) -> Network {
        let mut net = self.clone();
        for &(i, s) in shifts {
            let o = &mut net.obs[i];
            o.reading.az -= s.x;
            o.reading.el -= s.y;
            o.reading.d -= s.z;
            o.q = o.reading.joints();
            o.links = Links::new(o.q);
        }
        for &(i, c) in rejected {
            net.obs[i].sigma[c] *= REJECTED_SIGMA_FACTOR;
        }
        net
    }

    /// The network with every σ scaled by the square root of its group's
    /// variance factor `s2`: `[angle, range, gauge, reference]`.
    pub fn scaled(&self, s2: &[f64; 4]) -> Network {
        let [a, r, g, x] = s2.map(f64::sqrt);
        let mut net = self.clone();
        for o in &mut net.obs {
            o.sigma.x *= a;
            o.sigma.y *= a;
            o.sigma.z *= r;
        }
        for l in &mut net.gauge {
            l.u_mm *= g;
        }
        for (_, u) in net.references.iter_mut().flatten() {
            *u *= x;
        }
        net
    }

    /// The network without the readings `drop` (indices, any order).
    pub fn without_readings(&self, drop: &[usize]) -> Network {
        let mut net = self.clone();
        let mut i = 0;
        net.obs.retain(|_| {
            i += 1;
            !drop.contains(&(i - 1))
        });
        net
    }

    /// Per station: target → mean corrected point (over faces and repeats).
    pub fn station_points(&self, params: &ErrorParams) -> Vec<BTreeMap<usize, Vector3<f64>>> {
        self.station_points_of(params, |_| true)
    }

    /// [`Self::station_points`] of the targets `keep` accepts, at the cost
    /// of their readings alone (the gauge check needs two reflectors of
    /// hundreds).
    pub fn station_points_of(
        &self,
        params: &ErrorParams,
        keep: impl Fn(usize) -> bool,
    ) -> Vec<BTreeMap<usize, Vector3<f64>>> {
        let eval = params.evaluator();
        let mut of_station = vec![Vec::new(); self.stations.len()];
        for o in self.obs.iter().filter(|o| keep(o.target)) {
            of_station[o.station].push(o);
        }
        // Each station's means on their own, in parallel (a serial pass over
        // every reading's map entry was milliseconds at 24 000 readings,
        // issue 34); a mean still sums its readings in their order.
        of_station
            .par_iter()
            .map(|obs| {
                let mut sums = vec![(Vector3::zeros(), 0usize); self.targets.len()];
                for o in obs {
                    let e = &mut sums[o.target];
                    e.0 += eval.point(o.q, &o.links);
                    e.1 += 1;
                }
                sums.into_iter()
                    .enumerate()
                    .filter(|(_, (_, n))| *n > 0)
                    .map(|(t, (v, n))| (t, v / n as f64))
                    .collect()
            })
            .collect()
    }

    /// Reference coordinates of the targets that have them.
    pub fn reference_points(&self) -> BTreeMap<usize, Vector3<f64>> {
        self.references
            .iter()
            .enumerate()
            .filter_map(|(i, r)| r.map(|(x, _)| (i, x)))
            .collect()
    }

    /// Whether the references fix the frame (≥ 3 not on a line).
    pub fn references_fix_frame(&self) -> bool {
        let r: Vec<Vector3<f64>> = self.reference_points().into_values().collect();
        register::fit(&r, &r).is_some()
    }
}

/// Which objective to minimise.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Objective {
    /// Eq. (13): distances against distances between reference coordinates.
    Eq13,
    /// Eq. (14): distances between stations only.
    Eq14,
    /// Eq. (15): Eq. (14) plus the gauge.
    Eq15,
    /// Bundle adjustment on the readings.
    Bundle,
}

impl Objective {
    pub fn name(self) -> &'static str {
        match self {
            Objective::Eq13 => "eq13",
            Objective::Eq14 => "eq14",
            Objective::Eq15 => "eq15",
            Objective::Bundle => "bundle",
        }
    }
}

/// Absolute values (the paper's form) or squares.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Norm {
    L1,
    #[default]
    L2,
}

impl Norm {
    /// The id used in pipeline files and tables.
    pub fn name(self) -> &'static str {
        match self {
            Norm::L1 => "l1",
            Norm::L2 => "l2",
        }
    }
}

/// Settings common to every objective.
#[derive(Clone, Debug)]
pub struct Settings {
    pub objective: Objective,
    pub norm: Norm,
    /// Relative singular-value threshold for what the data determine.
    pub rank_tol: f64,
    pub max_iters: u64,
    /// Where the bundle adjustment's standard uncertainties come from
    /// (ignored by Eq. 13–15, whose sandwich takes the stated noise).
    pub std: BundleStd,
}

/// How the bundle adjustment's standard uncertainties are had (the
/// `calibrate` stage's `std`; see [`bundle`]'s doc).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum BundleStd {
    /// The stated noise when the χ² test accepts it
    /// ([`bundle::STATED_NOISE_ALPHA`]), else the variance components.
    #[default]
    Auto,
    /// The stated noise, never scaled.
    StatedNoise,
    /// The angle and range groups (and the gauge and references, where
    /// they have redundancy) re-weighted by their Helmert variance
    /// components, always.
    VarianceComponents,
    /// The stated noise scaled by one global `max(χ²/dof, 1)`: the former
    /// default, kept on request only — it mixes the groups.
    ScaledStatedNoise,
}

/// One variance component of the bundle adjustment: the factor by which a
/// group's σ was understated (estimated σ / stated σ, dimensionless), its
/// Helmert standard uncertainty, and the group's redundancy number.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SigmaFactor {
    pub factor: f64,
    pub u: f64,
    pub redundancy: f64,
}

impl Settings {
    /// The bundle adjustment (Eq. 17) in L2 with the default rank threshold
    /// and iteration limit: what every caller that is not a stage with its
    /// own settings fits with.
    pub fn bundle() -> Self {
        Settings {
            objective: Objective::Bundle,
            norm: Norm::L2,
            rank_tol: crate::identifiability::DEFAULT_REL_TOL,
            max_iters: 100,
            std: BundleStd::Auto,
        }
    }
}

/// A calibration's outcome.
#[derive(Clone, Debug)]
pub struct Calibration {
    /// The error parameters; the analysis is of their Jacobian with
    /// whatever the objective also estimates projected out.
    pub estimate: Estimate,
    /// Station → campaign frame.
    pub poses: Vec<register::Rigid>,
    /// Standard uncertainty of each pose: position (mm) and rotation (rad),
    /// when the objective estimates them.
    pub pose_std: Vec<Option<(f64, f64)>>,
    pub points: BTreeMap<usize, Vector3<f64>>,
    pub point_std: BTreeMap<usize, f64>,
    /// Each position's 3×3 covariance (mm², campaign frame) when the
    /// objective estimates positions with their uncertainty (the bundle);
    /// `point_std` is the root mean square of its diagonal.
    pub point_cov: BTreeMap<usize, Matrix3<f64>>,
    pub fit: FitSummary,
    /// Per reading: residuals in az, el, d against the estimated network,
    /// in µrad, µrad, µm and in units of σ.
    pub residuals: Vec<ReadingResidual>,
    /// The bundle adjustment's linearised problem at its solution.
    pub linearisation: Option<bundle::Linearisation>,
}

/// One reading's residual after a bundle adjustment.
#[derive(Clone, Copy, Debug)]
pub struct ReadingResidual {
    pub obs: usize,
    pub az_urad: f64,
    pub el_urad: f64,
    pub d_um: f64,
    /// `(az, el, d)` divided by their σ.
    pub normalized: Vector3<f64>,
}

/// Numbers that describe a fit.
#[derive(Clone, Debug)]
pub struct FitSummary {
    pub objective: Objective,
    pub norm: Norm,
    pub n_readings: usize,
    pub n_residuals: usize,
    pub n_unknowns: usize,
    pub rank: usize,
    pub iterations: u64,
    /// Why the solver stopped: one of [`crate::solver::Fit::reason`]'s
    /// words, `nothing-to-estimate` or `irls-converged`.
    pub stop: &'static str,
    /// Where the standard uncertainties come from: for the bundle,
    /// `stated-noise` (its inverse normal matrix weighted by the stated σ,
    /// unscaled), `variance-components` (weighted by the σ its variance
    /// components estimate) or `scaled-stated-noise` (the stated σ scaled
    /// by `max(χ²/dof, 1)`, on request, or when the χ² test refutes the
    /// stated noise and the components cannot be estimated); for Eq. 13–15,
    /// `sandwich` (L2) or `sandwich-l1` (L1), both from the stated noise of
    /// the readings, gauge and references.
    pub std_from: &'static str,
    /// Bundle: the Helmert variance components of the angle (az, el) and
    /// range readings, as factors on the stated σ; `None` when they could
    /// not be estimated (or for Eq. 13–15).
    pub sigma_angle_factor: Option<SigmaFactor>,
    pub sigma_range_factor: Option<SigmaFactor>,
    /// Root mean square of the objective's residuals before and after
    /// (µm for the distance objectives; units of σ for the bundle).
    pub rms_before: f64,
    pub rms_after: f64,
    /// Mean absolute residual before and after (the L1 objective / count).
    pub mean_abs_before: f64,
    pub mean_abs_after: f64,
    /// Bundle: Σ r², its degrees of freedom and the χ² upper-tail probability.
    pub chi2: Option<f64>,
    pub dof: Option<usize>,
    pub chi2_p: Option<f64>,
    /// Gauge lengths as measured after calibration, mean of `d/L − 1` (ppm).
    pub gauge_scale_ppm: Option<f64>,
}

/// Runs the chosen objective.
pub fn calibrate(
    net: &Network,
    start: &ErrorParams,
    free: &[bool],
    settings: &Settings,
) -> Result<Calibration> {
    match settings.objective {
        Objective::Bundle => bundle::calibrate(net, start, free, settings),
        _ => distances::calibrate(net, start, free, settings),
    }
}

/// Per reading, the residual of the corrected reading against the
/// estimated network: `J(q)⁻¹·(P(q; p) − R_sᵀ·(X_t − c_s))` in µrad, µrad,
/// µm, and divided by the reading's σ. Readings of reflectors without an
/// estimated position are left out.
pub fn reading_residuals(
    net: &Network,
    params: &ErrorParams,
    poses: &[register::Rigid],
    points: &BTreeMap<usize, Vector3<f64>>,
) -> Vec<ReadingResidual> {
    let eval = params.evaluator();
    net.obs
        .par_iter()
        .enumerate()
        .filter_map(|(i, o)| {
            let x = points.get(&o.target)?;
            let pose = &poses[o.station];
            let y = pose.rotation.inverse() * (x - pose.translation);
            let e = eval.point(o.q, &o.links) - y;
            let jinv = crate::kinematics::nominal_jacobian(o.reading).try_inverse()?;
            let phys = jinv * e;
            Some(ReadingResidual {
                obs: i,
                az_urad: phys.x * 1e6,
                el_urad: phys.y * 1e6,
                d_um: phys.z * 1e3,
                normalized: phys.component_div(&o.sigma),
            })
        })
        .collect()
}

/// Mean of `d/L − 1` over the gauge lengths seen, with the corrected
/// points of every station (ppm): how far the calibrated scale is off.
pub fn gauge_scale_ppm(net: &Network, params: &ErrorParams) -> Option<f64> {
    let mut joined = vec![false; net.targets.len()];
    for g in &net.gauge {
        (joined[g.a], joined[g.b]) = (true, true);
    }
    let pts = net.station_points_of(params, |t| joined[t]);
    let mut sum = 0.0;
    let mut n = 0;
    for g in &net.gauge {
        for s in &pts {
            if let (Some(a), Some(b)) = (s.get(&g.a), s.get(&g.b)) {
                sum += ((a - b).norm() / g.length_mm - 1.0) * 1e6;
                n += 1;
            }
        }
    }
    (n > 0).then(|| sum / n as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Regression: a stated `u_mm = 0` (an exact reference or gauge) was
    /// weighted as if no uncertainty were given (1 µm).
    #[test]
    fn an_exact_value_is_held_and_an_unknown_one_gets_the_default() {
        assert_eq!(weighting_u_mm(Some(0.0)), EXACT_U_MM);
        assert_eq!(weighting_u_mm(None), DEFAULT_REFERENCE_U_MM);
        assert_eq!(weighting_u_mm(Some(0.002)), 0.002);
    }

    /// The laboratory corner of Figures 13–14, simulated with Table 2's
    /// errors in both faces: the calibration's tests share it.
    pub(super) fn corner_campaign() -> Campaign {
        use crate::layout::{self, Kind, Spec};
        use crate::simulate::{CampaignSpec, simulate_campaign};
        let layout = layout::build(&Spec::new(Kind::Corner));
        simulate_campaign(&CampaignSpec {
            name: "corner".into(),
            layout: &layout,
            errors: Some(&ErrorParams::table2()),
            faces: &[Face::Front, Face::Back],
            aim: crate::campaign::Aim::StationsCentroid,
            max_angle_deg: 30.0,
            noise: Noise {
                sigma_angle_urad: 1.0,
                sigma_range_um: 2.0,
                sigma_range_ppm: 0.3,
            },
            effects: &crate::effects::Effects::default(),
            gauge_u_mm: 0.0005,
            reference_u_mm: 0.002,
            level_urad: 1000.0,
            interval_s: 20.0,
            record_time: true,
            record_temperature: true,
            seed: 3,
        })
        .unwrap()
        .campaign
    }

    /// Issue 34: the readings' reflectors are looked up apart from the
    /// readings themselves, which are collected straight into the list;
    /// each reading keeps its reflector, and an unknown reflector is still
    /// reported for the first such reading in order.
    #[test]
    fn each_reading_keeps_its_reflector_and_the_first_unknown_one_is_named() {
        let mut c = corner_campaign();
        let net = Network::from_campaign(&c).unwrap();
        assert_eq!(net.obs.len(), c.readings.len());
        for (o, r) in net.obs.iter().zip(&c.readings) {
            assert_eq!(net.targets[o.target], r.target);
            assert_eq!(net.stations[o.station], r.station);
        }
        let last = c.readings.len() - 1;
        c.readings[last].target = "nowhere-2".into();
        c.readings[7].target = "nowhere-1".into();
        let err = Network::from_campaign(&c).unwrap_err().to_string();
        assert_eq!(err, "reading of unknown reflector `nowhere-1`");
    }
}
