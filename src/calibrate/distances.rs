//! The paper's distance objectives, Eq. (13)–(15).
//!
//! A *view* is the set of readings one station took in one face: its points,
//! corrected with the error parameters, are in one rigid frame, so the
//! distances between them are what a perfect tracker would measure there.
//! (The paper has one face per station, so its views are its stations.)
//!
//! ```text
//! Eq. 13:  Σ_views Σ_pairs (dᵛ_kl − d_kl^ref)         reference coordinates
//! Eq. 14:  Σ_{v<w} Σ_pairs (dᵛ_kl − dʷ_kl)            between views only
//! Eq. 15:  Eq. 14 + Σ_views Σ_gauge (dᵛ_kl − L_kl)     plus the gauge
//! ```
//!
//! each term in absolute value (the paper's L1 form, minimised by
//! iteratively reweighted least squares) or squared. Eq. (13) as printed
//! sums signed differences; as an objective it needs their absolute values
//! or squares (NOTES item 9).
//!
//! These objectives cannot be block-sparse like the bundle adjustment
//! ([`super::sparse`]): their residuals are distances between *pairs* of
//! reflectors seen from one station (and, for Eq. 14, from another too), so
//! their number grows with the square of the reflectors per station, and
//! each carries a dense row over the error parameters. A campaign whose
//! terms would pass [`MAX_TERMS`] is refused before any work, with the
//! count and the memory it would need; the bundle objective serves such
//! networks in time linear in the readings.

use super::register::align;
use super::{Calibration, FitSummary, Network, Norm, Objective, Settings, gauge_scale_ppm};
use crate::determined::Determined;
use crate::error_model::ErrorParams;
use crate::kinematics::nominal_jacobian;
use crate::solver::LevenbergMarquardt;
use anyhow::{Result, anyhow, bail};
use argmin::core::{Error as ArgminError, Jacobian, Operator};
use nalgebra::{DMatrix, DVector, Matrix3, Vector3};
use rayon::prelude::*;
use std::collections::BTreeMap;

/// One station in one face: target → readings (indices into `net.obs`).
struct View {
    targets: BTreeMap<usize, Vec<usize>>,
}

/// One term of an objective.
#[derive(Clone, Copy, Debug)]
enum Term {
    /// `dᵛ_kl − dʷ_kl`.
    Between {
        v: usize,
        w: usize,
        k: usize,
        l: usize,
    },
    /// `dᵛ_kl − length`.
    Against {
        v: usize,
        k: usize,
        l: usize,
        length_mm: f64,
        of: Length,
    },
}

/// Where a term's known length comes from, for its uncertainty.
#[derive(Clone, Copy, Debug)]
enum Length {
    /// Between the reference coordinates of `k` and `l` (Eq. 13).
    References,
    /// Gauge `g` of `net.gauge` (Eq. 15).
    Gauge(usize),
}

fn views(net: &Network) -> Vec<View> {
    let mut map: BTreeMap<(usize, i64), View> = BTreeMap::new();
    for (i, o) in net.obs.iter().enumerate() {
        map.entry((o.station, o.face.number()))
            .or_insert_with(|| View {
                targets: BTreeMap::new(),
            })
            .targets
            .entry(o.target)
            .or_default()
            .push(i);
    }
    map.into_values().collect()
}

fn pairs(v: &View) -> Vec<(usize, usize)> {
    let t: Vec<usize> = v.targets.keys().copied().collect();
    let mut out = Vec::new();
    for (i, &a) in t.iter().enumerate() {
        for &b in &t[i + 1..] {
            out.push((a, b));
        }
    }
    out
}

/// The most distance terms a fit takes on: 2 million rows over 18
/// parameters hold ~0.3 GB of Jacobian, ~1 s per iteration on one core.
pub const MAX_TERMS: usize = 2_000_000;

/// How many terms `objective` would have, counted without building them.
fn count_terms(net: &Network, views: &[View], objective: Objective) -> usize {
    let c2 = |n: usize| n * n.saturating_sub(1) / 2;
    match objective {
        Objective::Eq13 => views
            .iter()
            .map(|v| {
                c2(v.targets
                    .keys()
                    .filter(|&&k| net.references[k].is_some())
                    .count())
            })
            .sum(),
        _ => {
            let mut n = 0;
            for v in 0..views.len() {
                for w in v + 1..views.len() {
                    let common = views[v]
                        .targets
                        .keys()
                        .filter(|k| views[w].targets.contains_key(k))
                        .count();
                    n += c2(common);
                }
            }
            n + views.len() * net.gauge.len()
        }
    }
}

fn terms(net: &Network, views: &[View], objective: Objective) -> Result<Vec<Term>> {
    let n = count_terms(net, views, objective);
    if n > MAX_TERMS {
        bail!(
            "objective = \"{}\" on this campaign has {n} distance terms (they grow with the square of the \
             reflectors seen per station): about {:.1} GB of Jacobian, beyond the limit of {MAX_TERMS} \
             terms; use objective = \"bundle\", whose cost grows linearly with the readings",
            objective.name(),
            (n * 18 * 8) as f64 / 1e9
        );
    }
    let mut out = Vec::new();
    match objective {
        Objective::Eq13 => {
            for (v, view) in views.iter().enumerate() {
                for (k, l) in pairs(view) {
                    if let (Some((a, _)), Some((b, _))) = (net.references[k], net.references[l]) {
                        out.push(Term::Against {
                            v,
                            k,
                            l,
                            length_mm: (a - b).norm(),
                            of: Length::References,
                        });
                    }
                }
            }
            if out.is_empty() {
                bail!(
                    "Eq. (13) needs reflectors with reference coordinates; this campaign has none seen in pairs"
                );
            }
        }
        Objective::Eq14 | Objective::Eq15 => {
            for v in 0..views.len() {
                for w in v + 1..views.len() {
                    for (k, l) in pairs(&views[v]) {
                        if views[w].targets.contains_key(&k) && views[w].targets.contains_key(&l) {
                            out.push(Term::Between { v, w, k, l });
                        }
                    }
                }
            }
            if objective == Objective::Eq15 {
                let before = out.len();
                for (v, view) in views.iter().enumerate() {
                    for (i, g) in net.gauge.iter().enumerate() {
                        if view.targets.contains_key(&g.a) && view.targets.contains_key(&g.b) {
                            out.push(Term::Against {
                                v,
                                k: g.a,
                                l: g.b,
                                length_mm: g.length_mm,
                                of: Length::Gauge(i),
                            });
                        }
                    }
                }
                if out.len() == before {
                    bail!("Eq. (15) needs a gauge: no gauge length is seen from any station");
                }
            }
            if out.is_empty() {
                bail!("no reflector pair is seen from two stations");
            }
        }
        Objective::Bundle => unreachable!("the bundle adjustment is not a distance objective"),
    }
    Ok(out)
}

/// Per target of a view: the mean corrected point and its derivative with
/// respect to each listed coefficient.
type ViewPoints = BTreeMap<usize, (Vector3<f64>, Vec<Vector3<f64>>)>;

/// The objective's residuals (µm) and, when asked, their Jacobian with
/// respect to the listed coefficients (µm per display unit).
struct Evaluation {
    r: DVector<f64>,
    j: Option<DMatrix<f64>>,
}

fn evaluate(
    net: &Network,
    views: &[View],
    terms: &[Term],
    params: &ErrorParams,
    cols: &[usize],
    jac: bool,
) -> Evaluation {
    let eval = params.evaluator();
    let n = cols.len();
    // Per view and target: the mean corrected point and its derivative.
    let mut pts: Vec<ViewPoints> = Vec::with_capacity(views.len());
    let mut buf = Vec::new();
    for view in views {
        let mut m = BTreeMap::new();
        for (&t, idx) in &view.targets {
            let mut p = Vector3::zeros();
            let mut d = vec![Vector3::zeros(); if jac { n } else { 0 }];
            for &i in idx {
                let o = &net.obs[i];
                if jac {
                    p += eval.point_with_jacobian(o.q, &o.links, &mut buf);
                    for (k, &c) in cols.iter().enumerate() {
                        d[k] += buf[c];
                    }
                } else {
                    p += eval.point(o.q, &o.links);
                }
            }
            let w = 1.0 / idx.len() as f64;
            d.iter_mut().for_each(|x| *x *= w);
            m.insert(t, (p * w, d));
        }
        pts.push(m);
    }
    let dist = |v: usize, k: usize, l: usize| {
        let (a, da) = &pts[v][&k];
        let (b, db) = &pts[v][&l];
        let u = a - b;
        let d = u.norm();
        let u = u / d;
        let grad: Vec<f64> = if jac {
            (0..n).map(|c| u.dot(&(da[c] - db[c]))).collect()
        } else {
            Vec::new()
        };
        (d, grad)
    };
    let mut r = DVector::zeros(terms.len());
    let mut j = jac.then(|| DMatrix::zeros(terms.len(), n));
    for (i, t) in terms.iter().enumerate() {
        let (value, grad) = match *t {
            Term::Between { v, w, k, l } => {
                let (dv, gv) = dist(v, k, l);
                let (dw, gw) = dist(w, k, l);
                (
                    dv - dw,
                    gv.iter().zip(&gw).map(|(a, b)| a - b).collect::<Vec<_>>(),
                )
            }
            Term::Against {
                v, k, l, length_mm, ..
            } => {
                let (dv, gv) = dist(v, k, l);
                (dv - length_mm, gv)
            }
        };
        r[i] = value * 1e3;
        if let Some(j) = j.as_mut() {
            for (c, g) in grad.iter().enumerate() {
                j[(i, c)] = g * 1e3;
            }
        }
    }
    Evaluation { r, j }
}

/// Weighted least squares in the coordinates `z` of the determined
/// directions: `p = p₀ + S·B·z`.
struct Weighted<'a> {
    net: &'a Network,
    views: &'a [View],
    terms: &'a [Term],
    start: &'a ErrorParams,
    det: &'a Determined,
    /// √w per term.
    sqrt_w: &'a DVector<f64>,
}

impl Weighted<'_> {
    fn params(&self, z: &DVector<f64>) -> ErrorParams {
        self.det.params(self.start, z)
    }
}

impl Operator for Weighted<'_> {
    type Param = DVector<f64>;
    type Output = DVector<f64>;
    fn apply(&self, z: &DVector<f64>) -> Result<DVector<f64>, ArgminError> {
        let e = evaluate(
            self.net,
            self.views,
            self.terms,
            &self.params(z),
            &self.det.free_index,
            false,
        );
        Ok(e.r.component_mul(self.sqrt_w))
    }
}

impl Jacobian for Weighted<'_> {
    type Param = DVector<f64>;
    type Jacobian = DMatrix<f64>;
    fn jacobian(&self, z: &DVector<f64>) -> Result<DMatrix<f64>, ArgminError> {
        let e = evaluate(
            self.net,
            self.views,
            self.terms,
            &self.params(z),
            &self.det.free_index,
            true,
        );
        let mut j = e.j.expect("requested") * self.det.basis();
        for (i, mut row) in j.row_iter_mut().enumerate() {
            row *= self.sqrt_w[i];
        }
        Ok(j)
    }
}

/// The most IRLS rounds for the L1 form.
const MAX_IRLS: usize = 60;

pub fn calibrate(
    net: &Network,
    start: &ErrorParams,
    free: &[bool],
    settings: &Settings,
) -> Result<Calibration> {
    let views = views(net);
    let terms = terms(net, &views, settings.objective)?;
    let free_index: Vec<usize> = (0..free.len()).filter(|&i| free[i]).collect();
    let e0 = evaluate(net, &views, &terms, start, &free_index, true);
    let det = Determined::analyse(
        e0.j.as_ref().expect("requested"),
        start,
        free,
        settings.rank_tol,
    )?;
    let basis = det.basis();
    let rank = det.rank();
    let mut sqrt_w = DVector::from_element(terms.len(), 1.0);
    let mut z = DVector::zeros(rank);
    let mut iterations = 0;
    let mut stop = "nothing-to-estimate";
    if rank > 0 {
        let rounds = if settings.norm == Norm::L1 {
            MAX_IRLS
        } else {
            1
        };
        let mut last_l1 = f64::INFINITY;
        for _ in 0..rounds {
            let problem = Weighted {
                net,
                views: &views,
                terms: &terms,
                start,
                det: &det,
                sqrt_w: &sqrt_w,
            };
            let fit = LevenbergMarquardt::new()
                .with_initial_lambda(1e-6)
                .and_then(|lm| lm.minimize(problem, z.clone(), settings.max_iters))
                .map_err(|e| anyhow!("calibration failed: {e}"))?;
            iterations += fit.iterations;
            stop = fit.reason;
            z = fit.x;
            if settings.norm == Norm::L2 {
                break;
            }
            // IRLS: weight each term by 1/|r| so that Σ w·r² ≈ Σ |r|.
            let params = det.params(start, &z);
            let r = evaluate(net, &views, &terms, &params, &free_index, false).r;
            let l1 = r.iter().map(|x| x.abs()).sum::<f64>();
            let eps = (1e-6 * l1 / r.len() as f64).max(1e-9);
            sqrt_w = r.map(|x| 1.0 / x.abs().max(eps).sqrt());
            if (last_l1 - l1).abs() <= 1e-10 * l1.max(1e-300) {
                stop = "irls-converged";
                break;
            }
            last_l1 = l1;
        }
    }
    let params = det.params(start, &z);
    let e1 = evaluate(net, &views, &terms, &params, &free_index, true);
    let m = terms.len() as f64;
    let rms = |r: &DVector<f64>| (r.norm_squared() / m).sqrt();
    let mean_abs = |r: &DVector<f64>| r.iter().map(|x| x.abs()).sum::<f64>() / m;

    // Standard uncertainties of the estimator actually used, propagated from
    // the stated noise of the readings, gauge and references: the terms
    // share readings, so `s²·(JᵀJ)⁻¹`, which takes them as independent,
    // would not hold.
    let cov_z = (rank > 0)
        .then(|| {
            let jz = e1.j.as_ref().expect("requested") * basis;
            sandwich(
                &jz,
                &noise_rows(net, &views, &terms, &params),
                settings.norm,
            )
        })
        .flatten();
    let station_pts = net.station_points(&params);
    let anchor = net.references_fix_frame().then(|| net.reference_points());
    let alignment = align(&station_pts, anchor.as_ref(), 1e-10)
        .ok_or_else(|| anyhow!("the stations cannot be registered: some station shares fewer than 3 reflectors (not on a line) with the others"))?;
    let gauge_scale_ppm = gauge_scale_ppm(net, &params);
    let residuals = super::reading_residuals(net, &params, &alignment.poses, &alignment.points);
    Ok(Calibration {
        estimate: det.estimate(params, free, cov_z.as_ref()),
        pose_std: vec![None; alignment.poses.len()],
        poses: alignment.poses.clone(),
        points: alignment.points.clone(),
        point_std: BTreeMap::new(),
        point_cov: BTreeMap::new(),
        fit: FitSummary {
            objective: settings.objective,
            norm: settings.norm,
            n_readings: net.obs.len(),
            n_residuals: terms.len(),
            n_unknowns: rank,
            rank,
            iterations,
            stop,
            std_from: match settings.norm {
                Norm::L1 => "sandwich-l1",
                Norm::L2 => "sandwich",
            },
            sigma_angle_factor: None,
            sigma_range_factor: None,
            rms_before: rms(&e0.r),
            rms_after: rms(&e1.r),
            mean_abs_before: mean_abs(&e0.r),
            mean_abs_after: mean_abs(&e1.r),
            chi2: None,
            dof: None,
            chi2_p: None,
            gauge_scale_ppm,
        },
        residuals,
        linearisation: None,
    })
}

/// One term's row of `A`: its residual (µm) per unit standard-normal draw
/// of each source of noise it touches, as `(source, ∂r/∂ξ)`. Sources:
/// three per reflector seen in a view — its mean point's noise, whitened
/// (`3·s..3·s+3`, `s` counting the (view, reflector) pairs) —, then each
/// gauge length, then each reference coordinate (`3k..3k+3` after the
/// gauges). A term reads its readings only through such means, so three
/// whitened sources per mean carry exactly the covariance of all its
/// readings' az, el and d, and a row holds at most 12 entries (+ 6 for
/// references) however often a reflector was read.
type NoiseRow = Vec<(usize, f64)>;

/// `A`, term by term, at `params`: a term touches only the readings of its
/// two reflectors in its one or two views, and its length's source.
fn noise_rows(
    net: &Network,
    views: &[View],
    terms: &[Term],
    params: &ErrorParams,
) -> Vec<NoiseRow> {
    let eval = params.evaluator();
    // Per view and reflector: the mean point, a square root `L` of its
    // covariance — each reading moved by `J(q)·diag(σ)·ξ` (Eq. 1
    // linearised at the reading), `C = Σ J·diag(σ²)·Jᵀ / n²` — and its
    // source index.
    let mut n_means = 0;
    let means: Vec<BTreeMap<usize, Mean>> = views
        .iter()
        .map(|view| {
            view.targets
                .iter()
                .map(|(&t, idx)| {
                    let n = idx.len() as f64;
                    let mut sum = Vector3::zeros();
                    let mut cov = Matrix3::zeros();
                    for &i in idx {
                        let o = &net.obs[i];
                        sum += eval.point(o.q, &o.links);
                        let j = nominal_jacobian(o.reading) * Matrix3::from_diagonal(&o.sigma);
                        cov += j * j.transpose();
                    }
                    n_means += 1;
                    (t, (sum / n, square_root(&(cov / (n * n))), n_means - 1))
                })
                .collect()
        })
        .collect();
    let reference_col = |k: usize| 3 * n_means + net.gauge.len() + 3 * k;
    let gauge_col = |g: usize| 3 * n_means + g;
    // `sign · ∂dᵛ_kl` through the two means' whitened sources.
    let distance = |row: &mut NoiseRow, v: usize, k: usize, l: usize, sign: f64| {
        let u = (means[v][&k].0 - means[v][&l].0).normalize();
        for (t, s) in [(k, 1.0), (l, -1.0)] {
            let (_, root, source) = &means[v][&t];
            let g = root.transpose() * u * (sign * s * 1e3);
            for c in 0..3 {
                row.push((3 * source + c, g[c]));
            }
        }
    };
    terms
        .iter()
        .map(|t| {
            let mut row = NoiseRow::new();
            match *t {
                Term::Between { v, w, k, l } => {
                    distance(&mut row, v, k, l, 1.0);
                    distance(&mut row, w, k, l, -1.0);
                }
                Term::Against { v, k, l, of, .. } => {
                    distance(&mut row, v, k, l, 1.0);
                    match of {
                        Length::Gauge(g) => row.push((gauge_col(g), -1e3 * net.gauge[g].u_mm)),
                        Length::References => {
                            if let (Some((a, ua)), Some((b, ub))) =
                                (net.references[k], net.references[l])
                            {
                                let u = (a - b).normalize();
                                for c in 0..3 {
                                    row.push((reference_col(k) + c, -1e3 * ua * u[c]));
                                    row.push((reference_col(l) + c, 1e3 * ub * u[c]));
                                }
                            }
                        }
                    }
                }
            }
            row
        })
        .collect()
}

/// A reflector's mean point in one view, a square root of its covariance
/// and the index of its three whitened noise sources.
type Mean = (Vector3<f64>, Matrix3<f64>, usize);

/// A square root `L` of a covariance, `L·Lᵀ = C` (by its eigenvectors:
/// a noise-free reading gives a singular `C`, which Cholesky refuses).
fn square_root(c: &Matrix3<f64>) -> Matrix3<f64> {
    let e = c.symmetric_eigen();
    e.eigenvectors * Matrix3::from_diagonal(&e.eigenvalues.map(|l| l.max(0.0).sqrt()))
}

/// The covariance of `z`, the fit's determined directions, from the noise
/// rows `A` of its terms (`None` when the fit's normal matrix is singular).
///
/// L2: `z` moves by `−(JᵀJ)⁻¹·Jᵀ·A·ξ`, so `cov = H⁻¹·(JᵀA)(JᵀA)ᵀ·H⁻¹`.
///
/// L1 (Huber's M-estimator sandwich, `ψ = sign`): the term errors
/// `e = A·ξ` are normal with `sᵢ² = (AAᵀ)ᵢᵢ`, so `E ψ'(eᵢ) = 2fᵢ(0) =
/// 2/(√(2π)·sᵢ)` and `cov(sign eᵢ, sign eⱼ) = (2/π)·asin ρᵢⱼ`;
/// `cov = B⁻¹·M·B⁻¹` with `B = Jᵀ·diag(2fᵢ(0))·J` and `M = Jᵀ·R·J`. The
/// IRLS weights do not enter: they are the algorithm, not the estimator.
/// Only terms sharing a source correlate, so `R·J` is built row by row
/// from the sources each term touches, never as a terms × terms matrix.
fn sandwich(jz: &DMatrix<f64>, rows: &[NoiseRow], norm: Norm) -> Option<DMatrix<f64>> {
    let n_sources = rows
        .iter()
        .flat_map(|r| r.iter().map(|&(s, _)| s + 1))
        .max()
        .unwrap_or(0);
    let rank = jz.ncols();
    match norm {
        Norm::L2 => {
            let h_inv = (jz.transpose() * jz).try_inverse()?;
            let mut g = DMatrix::<f64>::zeros(rank, n_sources);
            for (i, row) in rows.iter().enumerate() {
                for &(s, a) in row {
                    for c in 0..rank {
                        g[(c, s)] += jz[(i, c)] * a;
                    }
                }
            }
            Some(&h_inv * (&g * g.transpose()) * &h_inv)
        }
        Norm::L1 => {
            let s: Vec<f64> = rows
                .iter()
                .map(|r| r.iter().map(|&(_, a)| a * a).sum::<f64>().sqrt())
                .collect();
            let mut b = DMatrix::<f64>::zeros(rank, rank);
            for (i, &si) in s.iter().enumerate() {
                if si > 0.0 {
                    let ji = jz.row(i);
                    b += ji.transpose() * ji * (2.0 / ((2.0 * std::f64::consts::PI).sqrt() * si));
                }
            }
            let mut by_source: Vec<Vec<(usize, f64)>> = vec![Vec::new(); n_sources];
            for (i, row) in rows.iter().enumerate() {
                for &(src, a) in row {
                    by_source[src].push((i, a));
                }
            }
            let m = rows.len();
            // Row i of R·J; each row is summed in a fixed order, whatever
            // the thread count.
            let rj: Vec<DVector<f64>> = (0..m)
                .into_par_iter()
                .map_init(
                    || (vec![0.0; m], vec![usize::MAX; m], Vec::new()),
                    |(acc, mark, touched), i| {
                        touched.clear();
                        for &(src, a) in &rows[i] {
                            for &(j, bj) in &by_source[src] {
                                if mark[j] != i {
                                    mark[j] = i;
                                    acc[j] = 0.0;
                                    touched.push(j);
                                }
                                acc[j] += a * bj;
                            }
                        }
                        let mut out = DVector::zeros(rank);
                        for &j in touched.iter() {
                            if s[i] > 0.0 && s[j] > 0.0 {
                                let rho = (acc[j] / (s[i] * s[j])).clamp(-1.0, 1.0);
                                out += jz.row(j).transpose()
                                    * (std::f64::consts::FRAC_2_PI * rho.asin());
                            }
                        }
                        out
                    },
                )
                .collect();
            let mut meat = DMatrix::<f64>::zeros(rank, rank);
            for (i, t) in rj.iter().enumerate() {
                meat += jz.row(i).transpose() * t.transpose();
            }
            let b_inv = b.try_inverse()?;
            Some(&b_inv * meat * &b_inv)
        }
    }
}
