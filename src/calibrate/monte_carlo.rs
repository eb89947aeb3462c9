//! Uncertainty by Monte Carlo, as GUM Supplement 1 (JCGM 101:2008) has it:
//! the inputs' stated uncertainties propagated through the full nonlinear
//! bundle adjustment, rather than through its linearisation.
//!
//! Each trial draws every input from its distribution — each reading's
//! az, el and d from a normal with its stated σ (the noise of the
//! campaign's `meta.json`), each gauge length and each reference
//! coordinate from a normal with its `u_mm` (exact values at 1 nm, unknown
//! ones at the 1 µm the adjustment weights them with) — and solves the
//! perturbed campaign ([`Repeated::solve`]: the nominal fit's frame,
//! determined directions and layout, started from its solution). The
//! outputs are every free error coefficient, every free station position
//! and every reflector position.
//!
//! The number of trials is GUM-S1's adaptive procedure (7.9.4): blocks of
//! `M` trials (`M ≥ 100/(1 − p)`); after each block from the second on,
//! the standard deviations of the block averages of each output's
//! estimate, standard uncertainty and coverage-interval endpoints; stop
//! when twice each is within the numerical tolerance δ of the standard
//! uncertainty stated to `digits` significant digits (7.9.2: u = c·10ˡ
//! with c of `digits` digits, δ = ½·10ˡ). The estimate and the standard
//! uncertainty are over all trials; the probabilistically symmetric
//! coverage interval (7.7) is the average of the blocks' — GUM-S1 sorts
//! all `h·M` values instead, which for a thousand reflectors would hold
//! gigabytes; with `M ≥ 10⁴` the two differ by far less than δ.
//!
//! Trial `t` draws from its own seeded stream, trials run in parallel and
//! every sum is taken in trial order: the same numbers whatever the thread
//! count.

use super::Network;
use super::bundle::{Repeated, Solved};
use crate::random;
use anyhow::{Result, anyhow, bail};
use nalgebra::{Rotation3, Vector3};
use rayon::prelude::*;

/// How to run the trials.
#[derive(Clone, Debug)]
pub struct Settings {
    /// Trials per block, `M`.
    pub block_trials: usize,
    /// Significant digits the standard uncertainties must be stable to.
    pub digits: u32,
    /// Trials at most, in whole blocks; the outcome says whether the
    /// results were stable.
    pub max_trials: usize,
    /// Coverage probability `p` of the intervals.
    pub coverage: f64,
    pub seed: u64,
}

/// GUM-S1's block size (7.9.4 b): `M = max(J, 10⁴)`, `J = ⌈100/(1 − p)⌉`.
pub const DEFAULT_BLOCK_TRIALS: usize = 10_000;

/// A standard uncertainty at or below this (µm, µrad or mm) is round-off:
/// the output is not watched by the stopping rule.
pub const NEGLIGIBLE_U: f64 = 1e-9;

/// The most values a block may hold (trials × outputs): 400 MB.
pub const MAX_BLOCK_VALUES: usize = 50_000_000;

/// The smallest block that still resolves a coverage interval of
/// probability `p` (7.9.4 b: `J = ⌈100/(1 − p)⌉`).
pub fn min_block_trials(coverage: f64) -> usize {
    // Less a hair: 100/(1 − 0.9) is 1000.0000000000001 in floating point.
    (100.0 / (1.0 - coverage) - 1e-9).ceil() as usize
}

/// The most blocks a run may hold statistics for (`max_trials /
/// block_trials`): each keeps four numbers per output.
pub const MAX_BLOCKS: usize = 1000;

/// What an output is.
#[derive(Clone, Debug, PartialEq)]
pub enum Output {
    /// Free error coefficient `i` (its index in the parameter vector).
    Param(usize),
    /// A coordinate (0 x, 1 y, 2 z) of a free station's position.
    Station(usize, usize),
    /// A component of a free station's rotation away from the nominal
    /// fit's, `Log(R_nominalᵀ·R)` (rad): the body-frame ω of the
    /// adjustment's pose update, whose covariance the linear propagation
    /// reports.
    StationRotation(usize, usize),
    /// A coordinate of a reflector's position.
    Target(usize, usize),
}

/// The Monte Carlo result of one output.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Estimate {
    /// The nominal fit's value.
    pub nominal: f64,
    /// Average over the trials.
    pub mean: f64,
    /// Standard uncertainty: the trials' standard deviation.
    pub u: f64,
    /// The probabilistically symmetric coverage interval.
    pub low: f64,
    pub high: f64,
}

/// Progress after one block.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Block {
    /// Trials so far.
    pub trials: usize,
    /// The largest `2·s/δ` over the outputs and their four results (≤ 1:
    /// stable); `NaN` after the first block.
    pub worst_ratio: f64,
}

/// The outcome of the propagation.
#[derive(Clone, Debug)]
pub struct Outcome {
    pub outputs: Vec<Output>,
    pub estimates: Vec<Estimate>,
    pub blocks: Vec<Block>,
    pub trials: usize,
    /// Whether the stopping rule was met before `max_trials`.
    pub stable: bool,
}

/// The outputs of a network, in order: free coefficients, free stations'
/// coordinates and rotations, reflectors' coordinates.
fn outputs(
    net: &Network,
    free: &[bool],
    nominal: &Solved,
    fixed_station: Option<usize>,
) -> Vec<Output> {
    let params = (0..free.len()).filter(|&i| free[i]).map(Output::Param);
    let stations = (0..net.stations.len())
        .filter(|&s| Some(s) != fixed_station)
        .flat_map(|s| {
            (0..3)
                .map(move |k| Output::Station(s, k))
                .chain((0..3).map(move |k| Output::StationRotation(s, k)))
        });
    let targets = (0..net.targets.len())
        .filter(|&t| nominal.points[t].is_some())
        .flat_map(|t| (0..3).map(move |k| Output::Target(t, k)));
    params.chain(stations).chain(targets).collect()
}

/// Output `o` of solution `s`, whose rotations are measured from those of
/// `nominal`.
fn value(s: &Solved, nominal: &Solved, o: &Output) -> f64 {
    match *o {
        Output::Param(i) => s.params.values()[i],
        Output::Station(st, k) => s.poses[st].translation[k],
        Output::StationRotation(st, k) => {
            rotation_vector(&(nominal.poses[st].rotation.inverse() * s.poses[st].rotation))[k]
        }
        Output::Target(t, k) => s.points[t].map_or(f64::NAN, |p| p[k]),
    }
}

/// `Log(R)`, the rotation vector of `r` (rad), from its skew part and its
/// trace by `atan2`: exact for the micro-radian rotations a trial moves a
/// station by, where `acos` of the trace (nalgebra's `scaled_axis`) loses
/// every digit or gives NaN.
fn rotation_vector(r: &Rotation3<f64>) -> Vector3<f64> {
    let m = r.matrix();
    let v = Vector3::new(
        m[(2, 1)] - m[(1, 2)],
        m[(0, 2)] - m[(2, 0)],
        m[(1, 0)] - m[(0, 1)],
    ) / 2.0;
    let sin = v.norm();
    if sin == 0.0 {
        return v;
    }
    v * (sin.atan2((m.trace() - 1.0) / 2.0) / sin)
}

/// The campaign as trial `t` draws it.
fn perturbed(net: &Network, seed: u64, t: usize) -> Network {
    let mut rng = random::stream(seed, &format!("gum-s1-trial-{t}"));
    let mut draw = |s: f64| s * random::normal(&mut rng);
    // `adjusted` takes a shift off each reading.
    let shifts: Vec<(usize, Vector3<f64>)> = net
        .obs
        .iter()
        .enumerate()
        .map(|(i, o)| {
            (
                i,
                -Vector3::new(draw(o.sigma.x), draw(o.sigma.y), draw(o.sigma.z)),
            )
        })
        .collect();
    let mut p = net.adjusted(&shifts, &[]);
    for g in &mut p.gauge {
        g.length_mm += draw(g.u_mm);
    }
    for (x, u) in p.references.iter_mut().flatten() {
        *x += Vector3::new(draw(*u), draw(*u), draw(*u));
    }
    p
}

/// Per output of a block: average, standard deviation, interval ends.
fn block_stats(values: &[Vec<f64>], q: usize, coverage: f64) -> [f64; 4] {
    let m = values.len();
    let mut v: Vec<f64> = values.iter().map(|row| row[q]).collect();
    let mean = v.iter().sum::<f64>() / m as f64;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (m - 1).max(1) as f64;
    v.sort_by(f64::total_cmp);
    // 7.7: [ỹ₍ᵣ₎, ỹ₍ᵣ₊q₎] with q = pM, r = (M − q)/2 (1-based).
    let qn = ((coverage * m as f64).round() as usize).clamp(1, m);
    let r = ((m - qn) / 2).max(1);
    [mean, var.sqrt(), v[r - 1], v[(r + qn - 1).min(m - 1)]]
}

/// The numerical tolerance of a standard uncertainty `u` stated to
/// `digits` significant digits (7.9.2).
pub fn tolerance(u: f64, digits: u32) -> f64 {
    let l = u.log10().floor() - (digits as f64 - 1.0);
    0.5 * 10f64.powf(l)
}

/// Propagates the inputs' uncertainty through the bundle adjustment of
/// `net` (see the module doc).
pub fn run(net: &Network, repeated: &Repeated, free: &[bool], s: &Settings) -> Result<Outcome> {
    let nominal = repeated.nominal(net);
    let outs = outputs(net, free, &nominal, repeated.fixed_station());
    let n_q = outs.len();
    if s.block_trials < min_block_trials(s.coverage) {
        bail!(
            "a block of {} trials cannot resolve a {} % coverage interval: at least {}",
            s.block_trials,
            100.0 * s.coverage,
            min_block_trials(s.coverage)
        );
    }
    if s.max_trials / s.block_trials.max(1) > MAX_BLOCKS {
        bail!(
            "{} trials in blocks of {} would be {} blocks (at most {MAX_BLOCKS}): raise `block_trials` or lower `max_trials`",
            s.max_trials,
            s.block_trials,
            s.max_trials / s.block_trials.max(1)
        );
    }
    if s.block_trials.saturating_mul(n_q) > MAX_BLOCK_VALUES {
        bail!(
            "{} trials × {n_q} outputs would hold {} values per block (at most {MAX_BLOCK_VALUES}): lower `block_trials`",
            s.block_trials,
            s.block_trials.saturating_mul(n_q)
        );
    }
    let mut sum = vec![0.0; n_q];
    let mut sum2 = vec![0.0; n_q];
    let mut per_block: Vec<Vec<[f64; 4]>> = Vec::new();
    let mut blocks = Vec::new();
    let mut trials = 0;
    let mut stable = false;
    // Shifted sums: the nominal value taken off first, so that positions
    // of tens of metres keep their micrometres in the variance.
    let centre: Vec<f64> = outs.iter().map(|o| value(&nominal, &nominal, o)).collect();
    // Whole blocks only: a short last block would pull the averaged
    // interval ends inwards (its extreme order statistics are nearer).
    while trials + s.block_trials <= s.max_trials {
        let m = s.block_trials;
        let values: Vec<Vec<f64>> = (trials..trials + m)
            .into_par_iter()
            .map(|t| {
                let sol = repeated
                    .solve(&perturbed(net, s.seed, t))
                    .map_err(|e| anyhow!("Monte Carlo trial {t}: {e}"))?;
                Ok(outs
                    .iter()
                    .zip(&centre)
                    .map(|(o, c)| value(&sol, &nominal, o) - c)
                    .collect())
            })
            .collect::<Result<_>>()?;
        for row in &values {
            for q in 0..n_q {
                sum[q] += row[q];
                sum2[q] += row[q] * row[q];
            }
        }
        trials += m;
        per_block.push(
            (0..n_q)
                .map(|q| block_stats(&values, q, s.coverage))
                .collect(),
        );
        let h = per_block.len();
        let worst_ratio = if h < 2 {
            f64::NAN
        } else {
            (0..n_q)
                .map(|q| {
                    let mean = sum[q] / trials as f64;
                    let u = (sum2[q] / trials as f64 - mean * mean).max(0.0).sqrt();
                    // Round-off spread of an output the data hold
                    // fixed (an undetermined coefficient at its start).
                    if u <= NEGLIGIBLE_U {
                        return 0.0;
                    }
                    let delta = tolerance(u, s.digits);
                    (0..4)
                        .map(|k| {
                            let avg = per_block.iter().map(|b| b[q][k]).sum::<f64>() / h as f64;
                            let var = per_block
                                .iter()
                                .map(|b| (b[q][k] - avg).powi(2))
                                .sum::<f64>()
                                / (h * (h - 1)) as f64;
                            2.0 * var.sqrt() / delta
                        })
                        .fold(0.0, f64::max)
                })
                .fold(0.0, f64::max)
        };
        blocks.push(Block {
            trials,
            worst_ratio,
        });
        if worst_ratio <= 1.0 {
            stable = true;
            break;
        }
    }
    let n = trials.max(1) as f64;
    let h = per_block.len().max(1) as f64;
    let estimates = (0..n_q)
        .map(|q| {
            let mean = sum[q] / n;
            let var = (sum2[q] - n * mean * mean).max(0.0) / (n - 1.0).max(1.0);
            let end = |k: usize| per_block.iter().map(|b| b[q][k]).sum::<f64>() / h;
            Estimate {
                nominal: centre[q],
                mean: centre[q] + mean,
                u: var.sqrt(),
                low: centre[q] + end(2),
                high: centre[q] + end(3),
            }
        })
        .collect();
    Ok(Outcome {
        outputs: outs,
        estimates,
        blocks,
        trials,
        stable,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Regression: a station's rotation away from the nominal one came
    /// out NaN in some trials (`acos` of a trace just above 3).
    #[test]
    fn rotation_vector_of_micro_and_large_rotations() {
        let axis = Vector3::new(1.0, -2.0, 3.0).normalize();
        for angle in [1e-9, 3e-7, 0.5, 3.0] {
            let r = Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), angle);
            let w = rotation_vector(&r);
            assert!((w - axis * angle).norm() <= 1e-12 * angle, "{angle}: {w}");
        }
        assert_eq!(rotation_vector(&Rotation3::identity()), Vector3::zeros());
    }

    /// 7.9.2's example: u = 0.0123 to two digits is 12 × 10⁻³, δ = 0.0005.
    #[test]
    fn tolerance_is_half_a_unit_of_the_last_stated_digit() {
        assert!((tolerance(0.0123, 2) - 0.0005).abs() < 1e-15);
        assert!((tolerance(0.0123, 1) - 0.005).abs() < 1e-15);
        assert!((tolerance(4.7, 2) - 0.05).abs() < 1e-15);
    }

    #[test]
    fn a_block_resolves_the_coverage_it_is_asked_for() {
        assert_eq!(min_block_trials(0.95), 2000);
        assert_eq!(min_block_trials(0.9), 1000);
        assert_eq!(min_block_trials(0.99), 10_000);
    }

    /// A block of standard normal draws: mean ≈ 0, σ ≈ 1, 95 % interval
    /// ≈ ±1.96.
    #[test]
    fn block_statistics_of_a_standard_normal() {
        let mut rng = random::stream(5, "block");
        let values: Vec<Vec<f64>> = (0..40_000)
            .map(|_| vec![random::normal(&mut rng)])
            .collect();
        let [mean, sd, low, high] = block_stats(&values, 0, 0.95);
        assert!(mean.abs() < 0.02, "{mean}");
        assert!((sd - 1.0).abs() < 0.02, "{sd}");
        assert!(
            (low + 1.96).abs() < 0.05 && (high - 1.96).abs() < 0.05,
            "{low} {high}"
        );
    }
}
