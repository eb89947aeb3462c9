//! Bundle adjustment: the error parameters, every station pose and every
//! reflector position estimated together from the readings themselves.
//!
//! Each reading gives three residuals in reading space, weighted by the
//! stated noise:
//!
//! ```text
//! e = P(q; p) − R_sᵀ·(X_t − c_s)          corrected minus predicted point, mm
//! r = W·J(q)⁻¹·e,  W = diag(1/σ_az, 1/σ_el, 1/σ_d)
//! ```
//!
//! `J(q)` maps reading increments to point increments, so `J⁻¹·e` is the
//! error in (az, el, d) to first order in the (µm-level) model error —
//! exactly zero at a perfect fit, and the statistically proper weighting of
//! what the tracker actually reads. Gauge lengths add `(‖X_a − X_b‖ − L)/u`,
//! reference coordinates `(X_t − X_ref)/u`.
//!
//! The frame: with ≥ 3 reference points (not on a line) the references fix
//! it and every station is free; otherwise station 1 defines it.
//!
//! The normal equations have the structure of every bundle adjustment: a
//! reflector's position touches only that reflector's readings. Positions
//! are eliminated first (a 3 × 3 block each, Schur complement), leaving a
//! small dense system in the error parameters, the poses and the few
//! positions a gauge couples.

use super::register::{Rigid, align};
use super::{Calibration, FitSummary, Network, Norm, Settings, gauge_scale_ppm};
use crate::error_model::{ErrorParams, Links};
use crate::identifiability::{self, Analysis, Combination};
use crate::kinematics::nominal_jacobian;
use crate::solver::{LevenbergMarquardt, LmJacobian, NormalEquations};
use anyhow::{Result, anyhow, bail};
use argmin::core::{Error as ArgminError, Jacobian, Operator};
use nalgebra::{DMatrix, DVector, Matrix3, Rotation3, Vector3};
use std::collections::BTreeMap;

/// `W·J(q)⁻¹` for a reading `r` with the σ of observation `o`.
fn design_weight(o: &super::Observation, r: crate::kinematics::Reading) -> Matrix3<f64> {
    let jinv = nominal_jacobian(r)
        .try_inverse()
        .unwrap_or_else(Matrix3::zeros);
    Matrix3::from_diagonal(&o.sigma.map(|s| 1.0 / s)) * jinv
}

/// `J_r(φ)`, the right Jacobian of SO(3): `Exp(φ + δ) ≈ Exp(φ)·Exp(J_r(φ)·δ)`.
fn right_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
    let t = phi.norm();
    let k = phi.cross_matrix();
    if t < 1e-6 {
        return Matrix3::identity() - 0.5 * k + k * k / 6.0;
    }
    Matrix3::identity() - (1.0 - t.cos()) / (t * t) * k + (t - t.sin()) / (t * t * t) * k * k
}

/// Where each unknown sits in the parameter vector.
struct Layout {
    /// Number of error-parameter coordinates (columns of the basis).
    n_z: usize,
    /// Per station: the offset of its `(ω, c)` block, `None` when fixed.
    station: Vec<Option<usize>>,
    /// Per target: `(offset, in the dense part?)`, `None` when unseen.
    point: Vec<Option<(usize, bool)>>,
    /// Size of the dense part: z, poses, gauge points.
    n_a: usize,
    n: usize,
}

impl Layout {
    fn new(net: &Network, n_z: usize, fixed_station: Option<usize>) -> Layout {
        let mut seen = vec![false; net.targets.len()];
        for o in &net.obs {
            seen[o.target] = true;
        }
        let mut off = n_z;
        let station = (0..net.stations.len())
            .map(|s| {
                (Some(s) != fixed_station).then(|| {
                    off += 6;
                    off - 6
                })
            })
            .collect();
        let coupled: Vec<bool> = (0..net.targets.len())
            .map(|t| net.gauge.iter().any(|g| g.a == t || g.b == t))
            .collect();
        let mut point = vec![None; net.targets.len()];
        for t in 0..net.targets.len() {
            if seen[t] && coupled[t] {
                point[t] = Some((off, true));
                off += 3;
            }
        }
        let n_a = off;
        for t in 0..net.targets.len() {
            if seen[t] && !coupled[t] {
                point[t] = Some((off, false));
                off += 3;
            }
        }
        Layout {
            n_z,
            station,
            point,
            n_a,
            n: off,
        }
    }
}

/// The reduced system of [`BlockNormal::reduce`]: `S`, `b` and each
/// eliminated point's damped `H_XX⁻¹`.
type Reduced = (DMatrix<f64>, DVector<f64>, Vec<Matrix3<f64>>);

/// Normal equations with the reflector positions as 3 × 3 diagonal blocks.
#[derive(Clone, Debug)]
pub struct BlockNormal {
    n_a: usize,
    h_aa: DMatrix<f64>,
    /// Per eliminated point: `(offset, H_AX (n_a × 3), H_XX)`.
    points: Vec<(usize, DMatrix<f64>, Matrix3<f64>)>,
    g: DVector<f64>,
}

impl BlockNormal {
    fn new(n_a: usize, n: usize, layout: &Layout) -> BlockNormal {
        let points = layout
            .point
            .iter()
            .filter_map(|p| match p {
                Some((off, false)) => Some((*off, DMatrix::zeros(n_a, 3), Matrix3::zeros())),
                _ => None,
            })
            .collect();
        BlockNormal {
            n_a,
            h_aa: DMatrix::zeros(n_a, n_a),
            points,
            g: DVector::zeros(n),
        }
    }

    /// Adds one residual block `r` (k rows) with its non-zero Jacobian
    /// blocks `(offset, k × w matrix)`.
    fn add(
        &mut self,
        r: &[f64],
        blocks: &[(usize, DMatrix<f64>)],
        point_index: &BTreeMap<usize, usize>,
    ) {
        let n_a = self.n_a;
        for (oi, ji) in blocks {
            let jtr = ji.tr_mul(&DVector::from_column_slice(r));
            for (k, v) in jtr.iter().enumerate() {
                self.g[oi + k] += v;
            }
            for (oj, jj) in blocks {
                let h = ji.tr_mul(jj);
                match (*oi < n_a, *oj < n_a) {
                    (true, true) => {
                        let mut v = self.h_aa.view_mut((*oi, *oj), (h.nrows(), h.ncols()));
                        v += &h;
                    }
                    (true, false) => {
                        let p = &mut self.points[point_index[oj]].1;
                        let mut v = p.view_mut((*oi, 0), (h.nrows(), 3));
                        v += &h;
                    }
                    (false, false) => {
                        let p = &mut self.points[point_index[oi]].2;
                        *p += Matrix3::from_iterator(h.iter().copied());
                    }
                    (false, true) => {} // the transpose of (true, false)
                }
            }
        }
    }

    /// `S = H_AA − Σ H_AX·H_XX⁻¹·H_XA` and `b = g_A − Σ H_AX·H_XX⁻¹·g_X`,
    /// with the diagonal damped by `1 + λ`.
    fn reduce(&self, lambda: f64) -> Option<Reduced> {
        let mut s = self.h_aa.clone();
        for i in 0..self.n_a {
            s[(i, i)] += lambda * self.h_aa[(i, i)].max(1e-300);
        }
        let mut b = self.g.rows(0, self.n_a).into_owned();
        let mut inverses = Vec::with_capacity(self.points.len());
        for (off, hax, hxx) in &self.points {
            let mut d = *hxx;
            for i in 0..3 {
                d[(i, i)] += lambda * hxx[(i, i)].max(1e-300);
            }
            let inv = d.try_inverse()?;
            let w = hax * inv; // n_a × 3
            s -= &w * hax.transpose();
            b -= &w * self.g.fixed_rows::<3>(*off);
            inverses.push(inv);
        }
        Some((s, b, inverses))
    }
}

impl NormalEquations for BlockNormal {
    fn gradient(&self) -> &DVector<f64> {
        &self.g
    }

    fn damped_step(&self, lambda: f64) -> Option<DVector<f64>> {
        let (s, b, inverses) = self.reduce(lambda)?;
        let da = scaled_solve(&s, &(-b))?;
        let mut step = DVector::zeros(self.g.len());
        step.rows_mut(0, self.n_a).copy_from(&da);
        for ((off, hax, _), inv) in self.points.iter().zip(&inverses) {
            let rhs = -(self.g.fixed_rows::<3>(*off) + hax.tr_mul(&da));
            step.fixed_rows_mut::<3>(*off).copy_from(&(inv * rhs));
        }
        Some(step)
    }

    fn jacobian_norm2(&self, d: &DVector<f64>) -> f64 {
        let da = d.rows(0, self.n_a);
        let mut q = da.dot(&(&self.h_aa * da));
        for (off, hax, hxx) in &self.points {
            let dx = d.fixed_rows::<3>(*off);
            q += 2.0 * da.dot(&(hax * dx)) + dx.dot(&(hxx * dx));
        }
        q
    }
}

impl LmJacobian for BlockNormal {
    type Normal = BlockNormal;
    fn normal_equations(self, _: &DVector<f64>) -> BlockNormal {
        self
    }
}

/// The bundle-adjustment problem in the coordinates of its parameter vector.
struct Bundle<'a> {
    net: &'a Network,
    start: &'a ErrorParams,
    free_index: &'a [usize],
    /// Error-parameter coordinates → free coefficients.
    basis: &'a DMatrix<f64>,
    layout: &'a Layout,
    /// Initial pose of every station (the rotation updates are relative to it).
    poses0: &'a [Rigid],
    /// `W·J(q)⁻¹` per reading.
    weights: &'a [Matrix3<f64>],
    /// Reference coordinates used as observations (when they fix the frame).
    use_references: bool,
    /// Offset of each eliminated point among `BlockNormal::points`.
    point_index: BTreeMap<usize, usize>,
}

impl<'a> Bundle<'a> {
    fn params(&self, x: &DVector<f64>) -> ErrorParams {
        self.start
            .plus(self.free_index, &(self.basis * x.rows(0, self.layout.n_z)))
    }

    fn pose(&self, x: &DVector<f64>, s: usize) -> (Rotation3<f64>, Vector3<f64>, Vector3<f64>) {
        match self.layout.station[s] {
            Some(o) => {
                let w = Vector3::new(x[o], x[o + 1], x[o + 2]);
                let c = Vector3::new(x[o + 3], x[o + 4], x[o + 5]);
                (self.poses0[s].rotation * Rotation3::new(w), c, w)
            }
            None => (
                self.poses0[s].rotation,
                self.poses0[s].translation,
                Vector3::zeros(),
            ),
        }
    }

    fn point(&self, x: &DVector<f64>, t: usize) -> Vector3<f64> {
        let (o, _) = self.layout.point[t].expect("seen targets have positions");
        Vector3::new(x[o], x[o + 1], x[o + 2])
    }

    /// Visits every residual block: `(residuals, Jacobian blocks)` when
    /// `jac`, residuals alone otherwise. With `design`, the Jacobian is that
    /// of a consistent network — each reading's predicted point taken equal
    /// to its corrected one — so that the model's exact redundancies with
    /// the poses show as exact zeros, whatever the current misfit.
    fn visit(
        &self,
        x: &DVector<f64>,
        jac: bool,
        design: bool,
        mut f: impl FnMut(&[f64], &[(usize, DMatrix<f64>)]),
    ) {
        let params = self.params(x);
        let eval = params.evaluator();
        let mut cols = Vec::new();
        let nz = self.layout.n_z;
        for (i, o) in self.net.obs.iter().enumerate() {
            let (r_s, c, w) = self.pose(x, o.station);
            let xt = self.point(x, o.target);
            let y = r_s.inverse() * (xt - c);
            let v = self.poses0[o.station].rotation.inverse() * (xt - c);
            // The design network reads exactly the predicted point: the
            // joints that reach `y` with the current parameters.
            let design_q = design
                .then(|| params.reading_of(&y, o.face).ok())
                .flatten()
                .map(|r| (r.joints(), Links::new(r.joints()), design_weight(o, r)));
            let (q, links, m) = match &design_q {
                Some((q, l, m)) => (*q, l, *m),
                None => (o.q, &o.links, self.weights[i]),
            };
            let p = if jac {
                eval.point_with_jacobian(q, links, &mut cols)
            } else {
                eval.point(q, links)
            };
            let r = m * (p - y);
            let mut blocks = Vec::new();
            if jac {
                if nz > 0 {
                    // 3 × n_free, then onto the basis.
                    let mut jp = DMatrix::zeros(3, self.free_index.len());
                    for (k, &ci) in self.free_index.iter().enumerate() {
                        jp.set_column(k, &(m * cols[ci]));
                    }
                    blocks.push((0, jp * self.basis));
                }
                if let Some(so) = self.layout.station[o.station] {
                    // ∂y/∂ω = Exp(−ω)·[v]×·J_r(−ω); ∂y/∂c = −R_sᵀ.
                    let dy_dw =
                        Rotation3::new(-w).matrix() * v.cross_matrix() * right_jacobian(&(-w));
                    let mut jb = DMatrix::zeros(3, 6);
                    jb.view_mut((0, 0), (3, 3)).copy_from(&(-m * dy_dw));
                    jb.view_mut((0, 3), (3, 3))
                        .copy_from(&(m * r_s.inverse().matrix()));
                    blocks.push((so, jb));
                }
                let (po, _) = self.layout.point[o.target].expect("seen");
                let jx = -m * r_s.inverse().matrix();
                blocks.push((po, DMatrix::from_iterator(3, 3, jx.iter().copied())));
            }
            f(r.as_slice(), &blocks);
        }
        for g in &self.net.gauge {
            let (Some((oa, _)), Some((ob, _))) = (self.layout.point[g.a], self.layout.point[g.b])
            else {
                continue;
            };
            let d = self.point(x, g.a) - self.point(x, g.b);
            let len = d.norm();
            let r = [(len - g.length_mm) / g.u_mm];
            let mut blocks = Vec::new();
            if jac {
                let u = d.transpose() / (len * g.u_mm);
                blocks.push((oa, DMatrix::from_row_slice(1, 3, u.as_slice())));
                blocks.push((ob, DMatrix::from_row_slice(1, 3, (-u).as_slice())));
            }
            f(&r, &blocks);
        }
        if self.use_references {
            for (t, rf) in self.net.references.iter().enumerate() {
                let (Some((xr, u)), Some((o, _))) = (rf, self.layout.point[t]) else {
                    continue;
                };
                let r = (self.point(x, t) - xr) / *u;
                let blocks = if jac {
                    vec![(o, DMatrix::identity(3, 3) / *u)]
                } else {
                    Vec::new()
                };
                f(r.as_slice(), &blocks);
            }
        }
    }

    /// The whole Jacobian, densely, of the network at `x` (`design`: of the
    /// consistent network, see [`Self::visit`]).
    fn dense_jacobian(&self, x: &DVector<f64>, design: bool) -> DMatrix<f64> {
        let mut rows: Vec<Vec<f64>> = Vec::new();
        self.visit(x, true, design, |r, blocks| {
            for k in 0..r.len() {
                let mut row = vec![0.0; self.layout.n];
                for (off, b) in blocks {
                    for c in 0..b.ncols() {
                        row[off + c] = b[(k, c)];
                    }
                }
                rows.push(row);
            }
        });
        DMatrix::from_fn(rows.len(), self.layout.n, |i, j| rows[i][j])
    }

    fn residuals(&self, x: &DVector<f64>) -> DVector<f64> {
        let mut out = Vec::new();
        self.visit(x, false, false, |r, _| out.extend_from_slice(r));
        DVector::from_vec(out)
    }

    fn normal(&self, x: &DVector<f64>) -> BlockNormal {
        let mut n = BlockNormal::new(self.layout.n_a, self.layout.n, self.layout);
        self.visit(x, true, false, |r, blocks| {
            n.add(r, blocks, &self.point_index)
        });
        n
    }
}

impl Operator for Bundle<'_> {
    type Param = DVector<f64>;
    type Output = DVector<f64>;
    fn apply(&self, x: &DVector<f64>) -> Result<DVector<f64>, ArgminError> {
        Ok(self.residuals(x))
    }
}

impl Jacobian for Bundle<'_> {
    type Param = DVector<f64>;
    type Jacobian = BlockNormal;
    fn jacobian(&self, x: &DVector<f64>) -> Result<BlockNormal, ArgminError> {
        Ok(self.normal(x))
    }
}

fn point_index(layout: &Layout) -> BTreeMap<usize, usize> {
    layout
        .point
        .iter()
        .filter_map(|p| match p {
            Some((off, false)) => Some(*off),
            _ => None,
        })
        .enumerate()
        .map(|(i, off)| (off, i))
        .collect()
}

/// The unknowns mix mm, rad and µm-level parameters, so the normal matrix
/// spans many decades; equilibrating it (`D^{-1/2}·S·D^{-1/2}`, D its
/// diagonal) before the Cholesky factorisation keeps the solve accurate.
fn equilibrate(s: &DMatrix<f64>) -> (DMatrix<f64>, DVector<f64>) {
    let d = s.diagonal().map(|v| 1.0 / v.abs().max(1e-300).sqrt());
    let mut e = s.clone();
    for i in 0..e.nrows() {
        for j in 0..e.ncols() {
            e[(i, j)] *= d[i] * d[j];
        }
    }
    (e, d)
}

fn scaled_solve(s: &DMatrix<f64>, b: &DVector<f64>) -> Option<DVector<f64>> {
    let (e, d) = equilibrate(s);
    let y = e.cholesky()?.solve(&b.component_mul(&d));
    Some(y.component_mul(&d))
}

fn scaled_inverse(s: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    let (e, d) = equilibrate(s);
    let mut inv = e.cholesky()?.inverse();
    for i in 0..inv.nrows() {
        for j in 0..inv.ncols() {
            inv[(i, j)] *= d[i] * d[j];
        }
    }
    Some(inv)
}

/// The first `k` columns of `j` with the span of the other columns removed:
/// what is left of the error parameters' effect once poses and positions
/// absorb all they can. Computed by QR of the (equilibrated) nuisance
/// columns, never by squaring `j`: the exact redundancies of the model must
/// come out at round-off level to be told from weak but real directions.
fn project_out(j: &DMatrix<f64>, k: usize) -> Result<DMatrix<f64>> {
    let n = j.ncols();
    let jp = j.columns(0, k).into_owned();
    if k == n {
        return Ok(jp);
    }
    let mut jx = j.columns(k, n - k).into_owned();
    for mut c in jx.column_iter_mut() {
        let norm = c.norm();
        if norm > 0.0 {
            c /= norm;
        }
    }

    let q = jx.qr().q();
    Ok(&jp - &q * (q.transpose() * &jp))
}

/// What the analysis and the fit share: the free coefficients, the frame,
/// the first guess of every pose and position, the reading weights.
struct Setup {
    free_index: Vec<usize>,
    use_references: bool,
    fixed_station: Option<usize>,
    poses0: Vec<Rigid>,
    points0: BTreeMap<usize, Vector3<f64>>,
    weights: Vec<Matrix3<f64>>,
}

impl Setup {
    fn new(net: &Network, start: &ErrorParams, free: &[bool]) -> Result<Setup> {
        let use_references = net.references_fix_frame();
        let anchor = use_references.then(|| net.reference_points());
        let alignment = align(&net.station_points(start), anchor.as_ref())
            .ok_or_else(|| anyhow!("the stations cannot be registered: some station shares fewer than 3 reflectors (not on a line) with the others"))?;
        Ok(Setup {
            free_index: (0..free.len()).filter(|&i| free[i]).collect(),
            use_references,
            fixed_station: (!use_references).then_some(0),
            poses0: alignment.poses,
            points0: alignment.points,
            weights: net
                .obs
                .iter()
                .map(|o| design_weight(o, o.reading))
                .collect(),
        })
    }

    fn layout(&self, net: &Network, n_z: usize) -> Layout {
        Layout::new(net, n_z, self.fixed_station)
    }

    fn initial(&self, layout: &Layout) -> DVector<f64> {
        let mut x = DVector::zeros(layout.n);
        for (s, off) in layout.station.iter().enumerate() {
            if let Some(o) = off {
                x.fixed_rows_mut::<3>(o + 3)
                    .copy_from(&self.poses0[s].translation);
            }
        }
        for (t, off) in layout.point.iter().enumerate() {
            if let Some((o, _)) = off {
                x.fixed_rows_mut::<3>(*o).copy_from(&self.points0[&t]);
            }
        }
        x
    }

    fn problem<'a>(
        &'a self,
        net: &'a Network,
        start: &'a ErrorParams,
        basis: &'a DMatrix<f64>,
        layout: &'a Layout,
    ) -> Bundle<'a> {
        Bundle {
            net,
            start,
            free_index: &self.free_index,
            basis,
            layout,
            poses0: &self.poses0,
            weights: &self.weights,
            use_references: self.use_references,
            point_index: point_index(layout),
        }
    }
}

/// What a campaign determines about the free coefficients once station
/// poses and reflector positions are free: the singular values of their
/// Jacobian with everything poses and positions can absorb projected out,
/// and the undetermined directions in words.
pub fn analyse(
    net: &Network,
    start: &ErrorParams,
    free: &[bool],
    rank_tol: f64,
) -> Result<(Analysis, Vec<Combination>)> {
    let setup = Setup::new(net, start, free)?;
    analyse_setup(net, start, &setup, rank_tol)
}

fn analyse_setup(
    net: &Network,
    start: &ErrorParams,
    setup: &Setup,
    rank_tol: f64,
) -> Result<(Analysis, Vec<Combination>)> {
    let n = setup.free_index.len();
    let identity = DMatrix::identity(n, n);
    let layout = setup.layout(net, n);
    let probe = setup.problem(net, start, &identity, &layout);
    let j = probe.dense_jacobian(&setup.initial(&layout), true);
    let analysis = identifiability::analyse(&project_out(&j, n)?, rank_tol)?;
    let names: Vec<String> = setup
        .free_index
        .iter()
        .map(|&i| start.coefs()[i].symbol())
        .collect();
    let combinations = identifiability::describe_null_space(&analysis.null_basis, &names);
    Ok((analysis, combinations))
}

/// The linearised problem at a bundle adjustment's solution, for tests of
/// added effects: the Jacobian of all residuals (readings first, three rows
/// each in units of σ; then gauge and reference rows) with respect to every
/// unknown, and the residuals.
#[derive(Clone, Debug)]
pub struct Linearisation {
    pub jacobian: DMatrix<f64>,
    pub residuals: DVector<f64>,
}

pub fn calibrate(
    net: &Network,
    start: &ErrorParams,
    free: &[bool],
    settings: &Settings,
) -> Result<Calibration> {
    if settings.norm == Norm::L1 {
        bail!("the bundle adjustment is a least-squares fit: use norm = \"l2\"");
    }
    let setup = Setup::new(net, start, free)?;
    let free_index = setup.free_index.clone();
    let (analysis, combinations) = analyse_setup(net, start, &setup, settings.rank_tol)?;
    let basis = analysis.row_basis.clone();
    let layout = setup.layout(net, basis.ncols());
    let problem = setup.problem(net, start, &basis, &layout);
    let x0 = setup.initial(&layout);
    let r0 = problem.residuals(&x0);
    let fit = LevenbergMarquardt::new()
        .with_initial_lambda(1e-4)
        .and_then(|lm| lm.minimize(problem, x0, settings.max_iters))
        .map_err(|e| anyhow!("bundle adjustment failed: {e}"))?;
    let problem = setup.problem(net, start, &basis, &layout);
    let x = fit.x;
    let params = problem.params(&x);
    let r = problem.residuals(&x);
    let m = r.len();
    let chi2 = r.norm_squared();
    let dof = m.saturating_sub(layout.n).max(1);
    let chi2_p = statrs::distribution::ChiSquared::new(dof as f64)
        .ok()
        .map(|d| statrs::distribution::ContinuousCDF::sf(&d, chi2));
    // Covariance with the a-priori noise, inflated when the fit says the
    // noise was understated.
    let var_factor = (chi2 / dof as f64).max(1.0);
    let normal = problem.normal(&x);
    let (s_a, _, inverses) = normal
        .reduce(0.0)
        .ok_or_else(|| anyhow!("singular normal matrix at the solution"))?;
    let cov_a = scaled_inverse(&s_a)
        .map(|c| c * var_factor)
        .ok_or_else(|| anyhow!("singular normal matrix at the solution"))?;
    let mut std = vec![None; free.len()];
    let nz = layout.n_z;
    if nz > 0 {
        let cov_z = cov_a.view((0, 0), (nz, nz));
        let cov_p = &basis * cov_z * basis.transpose();
        for (k, &i) in free_index.iter().enumerate() {
            std[i] = Some(cov_p[(k, k)].max(0.0).sqrt());
        }
    }
    let pose_std = layout
        .station
        .iter()
        .map(|o| {
            o.map(|o| {
                let rot = (0..3).map(|k| cov_a[(o + k, o + k)]).sum::<f64>() / 3.0;
                let pos = (3..6).map(|k| cov_a[(o + k, o + k)]).sum::<f64>() / 3.0;
                (pos.max(0.0).sqrt(), rot.max(0.0).sqrt())
            })
        })
        .collect();
    let mut points = BTreeMap::new();
    let mut point_std = BTreeMap::new();
    let idx = point_index(&layout);
    for (t, off) in layout.point.iter().enumerate() {
        let Some((o, dense)) = off else { continue };
        points.insert(t, problem.point(&x, t));
        let var = if *dense {
            (0..3).map(|k| cov_a[(o + k, o + k)]).sum::<f64>()
        } else {
            let i = idx[o];
            let (_, hax, _) = &normal.points[i];
            let inv = &inverses[i];
            let w = inv * hax.transpose();
            let cov = inv * var_factor + &w * &cov_a * w.transpose();
            cov.trace()
        };
        point_std.insert(t, (var / 3.0).max(0.0).sqrt());
    }
    let poses: Vec<Rigid> = (0..net.stations.len())
        .map(|s| {
            let (rotation, translation, _) = problem.pose(&x, s);
            Rigid {
                rotation,
                translation,
            }
        })
        .collect();
    let residuals = super::reading_residuals(net, &params, &poses, &points);
    let linearisation = Linearisation {
        jacobian: problem.dense_jacobian(&x, false),
        residuals: r.clone(),
    };
    let rms = |r: &DVector<f64>| (r.norm_squared() / m as f64).sqrt();
    let mean_abs = |r: &DVector<f64>| r.iter().map(|v| v.abs()).sum::<f64>() / m as f64;
    Ok(Calibration {
        free: free.to_vec(),
        std,
        free_index,
        combinations,
        poses,
        pose_std,
        points,
        point_std,
        fit: FitSummary {
            objective: "bundle".into(),
            norm: "l2".into(),
            n_readings: net.obs.len(),
            n_residuals: m,
            n_unknowns: layout.n,
            rank: analysis.rank,
            iterations: fit.iterations,
            stop: fit.reason.into(),
            rms_before: rms(&r0),
            rms_after: rms(&r),
            mean_abs_before: mean_abs(&r0),
            mean_abs_after: mean_abs(&r),
            chi2: Some(chi2),
            dof: Some(dof),
            chi2_p,
            gauge_scale_ppm: gauge_scale_ppm(net, &params),
        },
        analysis,
        params,
        residuals,
        linearisation: Some(linearisation),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn right_jacobian_matches_finite_differences() {
        let phi = Vector3::new(0.3, -0.2, 0.5);
        let v = Vector3::new(1.0, 2.0, -0.5);
        let jr = right_jacobian(&phi);
        let h = 1e-7;
        for k in 0..3 {
            let mut d = Vector3::zeros();
            d[k] = h;
            let fd = (Rotation3::new(phi + d) * v - Rotation3::new(phi - d) * v) / (2.0 * h);
            let an = -(Rotation3::new(phi).matrix() * v.cross_matrix() * jr)
                .column(k)
                .into_owned();
            assert!((fd - an).norm() < 1e-7, "{fd} vs {an}");
        }
    }
}
