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
//!
//! The covariance is the inverse normal matrix of the weighting the
//! estimates come from (`std`, [`BundleStd`]). One global factor
//! `max(χ²/dof, 1)` on the stated-noise covariance — the former default —
//! misleads when only one group's σ is understated (the mix inflates what
//! the other group determines and not enough what that group does) and
//! inflates every fit whose χ²/dof exceeds 1 by chance. Instead, Helmert's
//! variance components of the groups — angles (az, el), ranges, and the
//! gauge and references where they have the redundancy — are estimated
//! from the residuals, in Förstner's iterated form shared with
//! [`crate::identify`] ([`variance_components`]). By default the stated
//! noise stands, unscaled, while the χ² test accepts it
//! ([`STATED_NOISE_ALPHA`]); when the test refutes it, the network is
//! re-weighted by the components and fitted again from the stated-noise
//! solution, and its covariance is that fit's. `chi2`, the residuals and
//! the linearisation (the w-tests of data snooping) stay those of the
//! stated noise: they are its test.

use super::register::{Rigid, align};
use super::sparse::{self, BlockJacobian, BlockShape, GroupedLayout, Normal, with_constant_width};
use super::{
    BundleStd, Calibration, FitSummary, Network, Norm, Settings, SigmaFactor, gauge_scale_ppm,
};
use crate::determined::Determined;
use crate::error_model::{ErrorParams, Evaluator};
use crate::identifiability::{Analysis, Combination, RowMajor};
use crate::identify::{VC_MAX_ITERS, VC_ROUND_OFF, helmert_round, helmert_u};
use crate::kinematics::nominal_jacobian;
use crate::solver::{LevenbergMarquardt, LmJacobian, NormalEquations};
use anyhow::{Result, anyhow, bail};
use argmin::core::{Error as ArgminError, Jacobian, Operator};
use nalgebra::{DMatrix, DVector, Matrix3, Rotation3, Vector3};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, OnceLock};

/// `W·J(q)⁻¹` for a reading `r` with the σ of observation `o`.
fn design_weight(o: &super::Observation, r: crate::kinematics::Reading) -> Matrix3<f64> {
    let jinv = nominal_jacobian(r)
        .try_inverse()
        .unwrap_or_else(Matrix3::zeros);
    Matrix3::from_diagonal(&o.sigma.map(|s| 1.0 / s)) * jinv
}

/// Every reading's [`design_weight`] at its measured reading, each its own:
/// in parallel, the same values (issue 34).
fn reading_weights(net: &Network) -> Vec<Matrix3<f64>> {
    net.obs
        .par_iter()
        .with_min_len(1024)
        .map(|o| design_weight(o, o.reading))
        .collect()
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
        // One pass over the gauge: a lookup per target was quadratic in a
        // campaign's rows.
        let mut coupled = vec![false; net.targets.len()];
        for g in &net.gauge {
            coupled[g.a] = true;
            coupled[g.b] = true;
        }
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

    /// A reading's Jacobian parts on its station's pose (width 0 when the
    /// station is fixed) and on its reflector, as `(first column, width)`
    /// with the columns counted from `first`: the fit's and the
    /// analysis's blocks alike ([`Bundle::jacobian_in`],
    /// [`Bundle::design_jacobian`]).
    fn reading_parts(&self, o: &super::Observation, first: usize) -> [(usize, usize); 2] {
        let (po, _) = self.point[o.target].expect("seen targets have positions");
        let station = match self.station[o.station] {
            Some(so) => (so - first, 6),
            None => (0, 0),
        };
        [station, (po - first, 3)]
    }
}

/// The bundle's normal equations, as the solver sees them.
pub struct BundleNormal(Arc<Normal>);

impl NormalEquations for BundleNormal {
    fn gradient(&self) -> &DVector<f64> {
        self.0.gradient()
    }

    fn damped_step(&self, lambda: f64) -> Option<DVector<f64>> {
        Some(-self.0.factor(lambda)?.solve(self.0.gradient()))
    }

    fn jacobian_norm2(&self, d: &DVector<f64>) -> f64 {
        self.0.quadratic(d)
    }
}

impl LmJacobian for BundleNormal {
    type Normal = BundleNormal;
    fn normal_equations(self, _: &DVector<f64>) -> BundleNormal {
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
    /// The basis row by row (free coefficient by free coefficient), for
    /// the Jacobian's inner loop.
    basis_rows: Vec<f64>,
    layout: &'a Layout,
    /// Initial pose of every station (the rotation updates are relative to it).
    poses0: &'a [Rigid],
    /// `W·J(q)⁻¹` per reading.
    weights: &'a [Matrix3<f64>],
    /// Reference coordinates used as observations (when they fix the frame).
    use_references: bool,
    /// Where the solver's last linearisation is kept, when asked.
    last: Option<&'a Mutex<Option<Linearised>>>,
    /// Residuals already computed at a point (the start, whose residuals
    /// the fit reports as "before"): the solver's first evaluation there
    /// reads them instead of recomputing.
    known: Option<(&'a DVector<f64>, &'a DVector<f64>)>,
    /// The readings' blocks as laid out at the first linearisation: every
    /// later one has the same shapes.
    grouped: OnceLock<GroupedLayout>,
}

/// The linearisation the solver built last. Its last iteration linearises
/// at the point it then returns (the step came out below tolerance), so
/// the covariances at the solution take it instead of building it again.
struct Linearised {
    x: DVector<f64>,
    jacobian: BlockJacobian,
    residuals: DVector<f64>,
    normal: Arc<Normal>,
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

    /// Each station's pose at `x`, with what every reading's derivatives
    /// by it share.
    fn stations(&self, x: &DVector<f64>) -> Vec<StationAt> {
        (0..self.net.stations.len())
            .map(|s| {
                let (r_s, c, w) = self.pose(x, s);
                StationAt {
                    to_station: *r_s.inverse().matrix(),
                    c,
                    free: self.layout.station[s],
                    from_start: *self.poses0[s].rotation.inverse().matrix(),
                    // ∂y/∂ω = Exp(−ω)·[v]×·J_r(−ω), v = R₀ᵀ(x − c).
                    exp_minus_w: *Rotation3::new(-w).matrix(),
                    jr_minus_w: right_jacobian(&(-w)),
                }
            })
            .collect()
    }

    /// One reading's residuals and, given `jac` (where its error-parameter
    /// rows go), its Jacobian blocks. With `design`, the Jacobian is that of
    /// a consistent network — the
    /// reading's predicted point taken equal to its corrected one — so that
    /// the model's exact redundancies with the poses show as exact zeros,
    /// whatever the current misfit.
    fn reading_block(
        &self,
        x: &DVector<f64>,
        station: &StationAt,
        eval: &Evaluator,
        i: usize,
        design: bool,
        jac: Option<Scratch<'_>>,
    ) -> ReadingBlock {
        let o = &self.net.obs[i];
        let xt = self.point(x, o.target);
        let y = station.to_station * (xt - station.c);
        // The design network reads exactly the predicted point: the joints
        // that reach `y` with the current parameters, with their link
        // rotations as the inverse left them.
        let design_q = design
            .then(|| eval.reading_and_links_of(&y, o.face).ok())
            .flatten()
            .map(|(r, links)| (r.joints(), links, design_weight(o, r)));
        let (q, links, m) = match &design_q {
            Some((q, l, m)) => (*q, l, *m),
            None => (o.q, &o.links, self.weights[i]),
        };
        let Some(Scratch { jz, cols }) = jac else {
            return ReadingBlock {
                r: m * (eval.point(q, links) - y),
                station: None,
                point: [0.0; 9],
            };
        };
        let p = eval.point_with_jacobian(q, links, cols);
        // Error-parameter coordinates: 3 × n_free, then onto the basis.
        let nz = self.layout.n_z;
        with_constant_width!(nz, K => self.onto_basis::<K>(jz, nz, &m, cols));
        let rt = &station.to_station;
        let station = station.free.map(|so| {
            let v = station.from_start * (xt - station.c);
            let dy_dw = station.exp_minus_w * v.cross_matrix() * station.jr_minus_w;
            let (a, b) = (-m * dy_dw, m * rt);
            let mut part = [0.0; 18];
            for row in 0..3 {
                for k in 0..3 {
                    part[row * 6 + k] = a[(row, k)];
                    part[row * 6 + 3 + k] = b[(row, k)];
                }
            }
            (so, part)
        });
        ReadingBlock {
            r: m * (p - y),
            station,
            point: row_major(&(-m * rt)),
        }
    }

    /// A reading's rows on the error-parameter coordinates into `jz`
    /// (zeroed), `Σ_k (M·∂p/∂k)·B_k` over the free coefficients `k` in
    /// order (`B_k` the basis's row of `k`), with `nz = K` known at compile
    /// time (`K = 0`: `nz` as given) so that a row's loop unrolls: the same
    /// sums.
    fn onto_basis<const K: usize>(
        &self,
        jz: &mut [f64],
        nz: usize,
        m: &Matrix3<f64>,
        cols: &[Vector3<f64>],
    ) {
        let nz = if K == 0 { nz } else { K };
        // At a constant width the three rows are summed in registers and
        // stored once: stored after every coefficient, they went through
        // memory 3·K times a reading at every linearisation (issue 34).
        // They start from zero, as `jz` does: the same sums either way.
        let mut acc = [[0.0; K]; 3];
        let mut rows: [&mut [f64]; 3] = if K == 0 {
            let (r0, rest) = jz.split_at_mut(nz);
            let (r1, r2) = rest.split_at_mut(nz);
            [r0, r1, r2]
        } else {
            let [r0, r1, r2] = &mut acc;
            [r0, r1, r2]
        };
        // (`max(1)`: with no coordinate there is nothing to fill.)
        for (&ci, basis_row) in self
            .free_index
            .iter()
            .zip(self.basis_rows.chunks_exact(nz.max(1)))
        {
            let jk = m * cols[ci];
            for (row, out) in rows.iter_mut().enumerate() {
                for (o, b) in out.iter_mut().zip(basis_row) {
                    *o += jk[row] * b;
                }
            }
        }
        if K > 0 {
            // Row by row, each a copy of a size the compiler knows: as one
            // loop they became a call to `memcpy` per reading (1–2 % of a
            // 24 000-reading run's time, issue 34).
            let [a0, a1, a2] = &acc;
            jz[..K].copy_from_slice(a0);
            jz[K..2 * K].copy_from_slice(a1);
            jz[2 * K..3 * K].copy_from_slice(a2);
        }
    }

    /// Visits the residual blocks after the readings' — each gauge length,
    /// then each reference coordinate — in order, as `(rows, residuals,
    /// parts)` with the parts `(first column, rows × width values,
    /// row-major)` when `jac`, none otherwise. The rows come readings
    /// first (three each, [`Self::fill_readings`]), then these.
    fn visit_others(
        &self,
        x: &DVector<f64>,
        jac: bool,
        mut f: impl FnMut(usize, &[f64], &[(usize, &[f64])]),
    ) {
        for g in &self.net.gauge {
            let (Some((oa, _)), Some((ob, _))) = (self.layout.point[g.a], self.layout.point[g.b])
            else {
                continue;
            };
            let d = self.point(x, g.a) - self.point(x, g.b);
            let len = d.norm();
            let r = [(len - g.length_mm) / g.u_mm];
            if jac {
                let u = d / (len * g.u_mm);
                let (ua, ub) = ([u.x, u.y, u.z], [-u.x, -u.y, -u.z]);
                f(1, &r, &[(oa, &ua), (ob, &ub)]);
            } else {
                f(1, &r, &[]);
            }
        }
        if self.use_references {
            for (t, rf) in self.net.references.iter().enumerate() {
                let (Some((xr, u)), Some((o, _))) = (rf, self.layout.point[t]) else {
                    continue;
                };
                let r = (self.point(x, t) - xr) / *u;
                if jac {
                    let id = row_major(&(Matrix3::identity() / *u));
                    f(3, r.as_slice(), &[(o, &id)]);
                } else {
                    f(3, r.as_slice(), &[]);
                }
            }
        }
    }

    /// The Jacobian, as its blocks, and the residuals of the network at `x`
    /// (`design`: of the consistent network, see [`Self::reading_block`]).
    fn jacobian_at(&self, x: &DVector<f64>, design: bool) -> (BlockJacobian, DVector<f64>) {
        self.jacobian_in(x, design, None)
    }

    /// [`Self::jacobian_at`] in the storage of `spare`, a Jacobian no
    /// longer needed, when given: the fit's Jacobian is built anew at every
    /// linearisation (12 MB at 24 000 readings), and storage already
    /// faulted in costs nothing to fill again (issue 34).
    fn jacobian_in(
        &self,
        x: &DVector<f64>,
        design: bool,
        spare: Option<BlockJacobian>,
    ) -> (BlockJacobian, DVector<f64>) {
        // Room for every block: a reading's three rows on the coordinates,
        // its station and its reflector; a gauge length's row on two
        // reflectors; a reference's three rows on one.
        let (n_obs, n_gauge, n_refs) = self.row_groups();
        let room = [
            n_obs + n_gauge + n_refs,
            3 * n_obs + 2 * n_gauge + n_refs,
            3 * (self.layout.n_z + 9) * n_obs + 6 * n_gauge + 9 * n_refs,
        ];
        let (n_a, n) = (self.layout.n_a, self.layout.n);
        let mut j = match spare {
            Some(j) => j.recycle(n_a, n, room),
            None => BlockJacobian::with_capacity(n_a, n, room),
        };
        // The readings' blocks stored reflector by reflector, for the Schur
        // assembly ([`BlockJacobian::push_grouped`]).
        let nz = self.layout.n_z;
        let laid = self.grouped.get_or_init(|| {
            let shapes = self.net.obs.iter().map(|o| {
                let [station, point] = self.layout.reading_parts(o, 0);
                BlockShape {
                    rows: 3,
                    parts: [(0, nz), station, point],
                    group: point.0,
                }
            });
            GroupedLayout::new(shapes, n)
        });
        let mut r = vec![0.0; 3 * n_obs];
        let (jz, rest): (Vec<_>, Vec<_>) = j
            .push_laid_out(laid)
            .into_iter()
            .map(|v| v.split_at_mut(3 * nz))
            .unzip();
        self.fill_readings(x, design, jz, rest, &mut r);
        self.visit_others(x, true, |rows, res, parts| {
            j.push(rows, parts);
            r.extend_from_slice(res);
        });
        (j, DVector::from_vec(r))
    }

    /// How many readings, gauge lengths and reference points give rows:
    /// what a Jacobian's blocks are reserved for.
    fn row_groups(&self) -> (usize, usize, usize) {
        let n_refs = if self.use_references {
            self.net.references.iter().flatten().count()
        } else {
            0
        };
        (self.net.obs.len(), self.net.gauge.len(), n_refs)
    }

    /// The consistent network's Jacobian at `x` (see [`Self::reading_block`])
    /// as the identifiability analysis takes it: the poses' and positions'
    /// blocks, renumbered from 0, and the error-parameter coordinates'
    /// columns, row-major (a row's `n_z` values side by side): the values
    /// of [`Self::jacobian_at`] with `design`, put where the analysis needs
    /// them as they come, instead of building the whole Jacobian and
    /// splitting a copy off it (9 MB at 24 000 readings, issue 34).
    fn design_jacobian(&self, x: &DVector<f64>) -> (BlockJacobian, Vec<f64>) {
        let k = self.layout.n_z;
        let (n_obs, n_gauge, n_refs) = self.row_groups();
        let room = [
            n_obs + n_gauge + n_refs,
            2 * n_obs + 2 * n_gauge + n_refs,
            27 * n_obs + 6 * n_gauge + 9 * n_refs,
        ];
        let mut nuisance =
            BlockJacobian::with_capacity(self.layout.n_a - k, self.layout.n - k, room);
        let mut lead = Vec::with_capacity((3 * n_obs + n_gauge + 3 * n_refs) * k);
        sparse::extend_with_zeros(&mut lead, 3 * n_obs * k);
        // The readings' blocks stored in reading order: the analysis's
        // projection reads them block by block.
        let shapes = self.net.obs.iter().map(|o| {
            let [station, point] = self.layout.reading_parts(o, k);
            BlockShape {
                rows: 3,
                parts: [station, point, (0, 0)],
                group: 0,
            }
        });
        let rest = nuisance.push_grouped(shapes, 1);
        let jz = rows_of(&mut lead, 3 * k, n_obs);
        self.fill_readings(x, true, jz, rest, &mut vec![0.0; 3 * n_obs]);
        self.visit_others(x, true, |rows, _, parts| {
            // Gauge lengths and references touch no coordinate.
            debug_assert!(parts.iter().all(|&(col, _)| col >= k));
            let mut rest: [(usize, &[f64]); 2] = [(0, &[]); 2];
            for (out, &(col, v)) in rest.iter_mut().zip(parts) {
                *out = (col - k, v);
            }
            lead.resize(lead.len() + rows * k, 0.0);
            nuisance.push(rows, &rest[..parts.len()]);
        });
        (nuisance, lead)
    }

    /// Every reading's residuals and Jacobian blocks at `x` (`design`: see
    /// [`Self::reading_block`]), written where they are kept: reading `i`'s
    /// rows on the error-parameter coordinates into `jz[i]` (3 × n_z,
    /// zeroed), its station's part (when free) then its reflector's into
    /// `rest[i]`, its residuals into `r[3i..3i + 3]`. The readings are
    /// evaluated in parallel, each on its own: the same numbers whatever
    /// the number of threads, and no reading's blocks collected and copied
    /// into the Jacobian (issue 34).
    fn fill_readings(
        &self,
        x: &DVector<f64>,
        design: bool,
        jz: Vec<&mut [f64]>,
        rest: Vec<&mut [f64]>,
        r: &mut [f64],
    ) {
        let params = self.params(x);
        let eval = params.evaluator();
        let stations = self.stations(x);
        jz.into_par_iter()
            .zip(rest)
            .zip(r.par_chunks_exact_mut(3))
            .enumerate()
            .with_min_len(256)
            .for_each_init(Vec::new, |cols, (i, ((jz, mut rest), res))| {
                let s = &stations[self.net.obs[i].station];
                let b = self.reading_block(x, s, &eval, i, design, Some(Scratch { jz, cols }));
                if let Some((_, part)) = &b.station {
                    let (head, tail) = rest.split_at_mut(part.len());
                    head.copy_from_slice(part);
                    rest = tail;
                }
                rest.copy_from_slice(&b.point);
                res.copy_from_slice(b.r.as_slice());
            });
    }

    fn residuals(&self, x: &DVector<f64>) -> DVector<f64> {
        let params = self.params(x);
        let eval = params.evaluator();
        let stations = self.stations(x);
        let mut out = vec![0.0; 3 * self.net.obs.len()];
        out.par_chunks_exact_mut(3)
            .enumerate()
            .with_min_len(256)
            .for_each(|(i, res)| {
                let s = &stations[self.net.obs[i].station];
                let b = self.reading_block(x, s, &eval, i, false, None);
                res.copy_from_slice(b.r.as_slice());
            });
        self.visit_others(x, false, |_, r, _| out.extend_from_slice(r));
        DVector::from_vec(out)
    }
}

/// A station's pose at the current unknowns: `y = R_sᵀ·(x − c)` with
/// `R_s = R₀·Exp(ω)`.
struct StationAt {
    /// `R_sᵀ`.
    to_station: Matrix3<f64>,
    c: Vector3<f64>,
    /// The offset of its `(ω, c)` block, `None` when fixed.
    free: Option<usize>,
    /// `R₀ᵀ`.
    from_start: Matrix3<f64>,
    exp_minus_w: Matrix3<f64>,
    jr_minus_w: Matrix3<f64>,
}

/// Where [`Bundle::reading_block`] writes: the reading's rows on the
/// error-parameter coordinates (3 × n_z, row-major, zeroed; empty when no
/// coefficient is free) and a buffer for the model's columns, one per
/// parallel task.
struct Scratch<'a> {
    jz: &'a mut [f64],
    cols: &'a mut Vec<Vector3<f64>>,
}

/// One reading's residuals (units of σ) and Jacobian blocks, row-major, on
/// its station's pose (3 × 6, when free) and its reflector (3 × 3); its
/// rows on the error-parameter coordinates went to its [`Scratch`].
struct ReadingBlock {
    r: Vector3<f64>,
    station: Option<(usize, [f64; 18])>,
    point: [f64; 9],
}

/// The first `n · len` values of `buf` as `n` consecutive slices of `len`
/// (empty ones when `len` is 0).
fn rows_of(buf: &mut [f64], len: usize, n: usize) -> Vec<&mut [f64]> {
    if len == 0 {
        return (0..n).map(|_| &mut [][..]).collect();
    }
    buf[..n * len].chunks_exact_mut(len).collect()
}

/// A 3 × 3 matrix's entries, row by row.
fn row_major(m: &Matrix3<f64>) -> [f64; 9] {
    [
        m[(0, 0)],
        m[(0, 1)],
        m[(0, 2)],
        m[(1, 0)],
        m[(1, 1)],
        m[(1, 2)],
        m[(2, 0)],
        m[(2, 1)],
        m[(2, 2)],
    ]
}

impl Operator for Bundle<'_> {
    type Param = DVector<f64>;
    type Output = DVector<f64>;
    fn apply(&self, x: &DVector<f64>) -> Result<DVector<f64>, ArgminError> {
        Ok(match self.known {
            Some((at, r)) if at == x => r.clone(),
            _ => self.residuals(x),
        })
    }
}

impl Jacobian for Bundle<'_> {
    type Param = DVector<f64>;
    type Jacobian = BundleNormal;
    fn jacobian(&self, x: &DVector<f64>) -> Result<BundleNormal, ArgminError> {
        // The previous linearisation is replaced below: its Jacobian's
        // storage serves this one.
        let spare = self
            .last
            .and_then(|l| l.lock().unwrap_or_else(|e| e.into_inner()).take())
            .map(|l| l.jacobian);
        let (j, r) = self.jacobian_in(x, false, spare);
        let normal = Arc::new(Normal::assemble(&j, Some(&r), |_| true));
        if let Some(last) = self.last {
            *last.lock().unwrap_or_else(|e| e.into_inner()) = Some(Linearised {
                x: x.clone(),
                jacobian: j,
                residuals: r,
                normal: Arc::clone(&normal),
            });
        }
        Ok(BundleNormal(normal))
    }
}

/// Marquardt's damping at the first step. The registration starts every
/// pose and position close to the solution, where Gauss–Newton converges in
/// two or three steps; a larger start (1e-4) damps the weakly determined
/// directions — whose curvature lies decades below the diagonal — and
/// stretches the fit to six to eight slowly converging steps (measured on
/// the 605-reflector network). The damping still grows when a step fails.
const INITIAL_LAMBDA: f64 = 1e-10;

/// How closely the registration that starts the adjustment is refined: the
/// adjustment itself takes the poses the rest of the way.
const FIRST_GUESS_TOL_MM: f64 = 1e-4;

/// What the analysis and the fit share: the free coefficients, the frame,
/// the first guess of every pose and position, the reading weights.
#[derive(Clone)]
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
        let alignment = align(&net.station_points(start), anchor.as_ref(), FIRST_GUESS_TOL_MM)
            .ok_or_else(|| anyhow!("the stations cannot be registered: some station shares fewer than 3 reflectors (not on a line) with the others"))?;
        Ok(Setup {
            free_index: (0..free.len()).filter(|&i| free[i]).collect(),
            use_references,
            fixed_station: (!use_references).then_some(0),
            poses0: alignment.poses,
            points0: alignment.points,
            weights: reading_weights(net),
        })
    }

    /// The same setup with the readings weighted by `net`'s σ (the
    /// network re-weighted by its variance components).
    fn reweighted(&self, net: &Network) -> Setup {
        Setup {
            weights: reading_weights(net),
            ..self.clone()
        }
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
            basis_rows: basis.transpose().as_slice().to_vec(),
            layout,
            poses0: &self.poses0,
            weights: &self.weights,
            use_references: self.use_references,
            last: None,
            known: None,
            grouped: OnceLock::new(),
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
    let det = analyse_setup(net, start, &setup, rank_tol)?;
    Ok((det.analysis, det.combinations))
}

/// The projection of the error-parameter columns never forms the whole
/// Jacobian: poses and positions (the nuisance) are factorised block-sparse
/// and projected out of the few parameter columns by the corrected
/// semi-normal equations ([`sparse::project_out`]), which leaves exact
/// redundancies at round-off level as a QR factorisation would. The result
/// has as many columns as free coefficients, so its SVD is cheap.
fn analyse_setup(
    net: &Network,
    start: &ErrorParams,
    setup: &Setup,
    rank_tol: f64,
) -> Result<Determined> {
    let n = setup.free_index.len();
    let identity = DMatrix::identity(n, n);
    let layout = setup.layout(net, n);
    let probe = setup.problem(net, start, &identity, &layout);
    let (nuisance, jz) = probe.design_jacobian(&setup.initial(&layout));
    if !nuisance.is_finite() || !sparse::all_finite(&jz) {
        bail!(
            "the Jacobian has a non-finite entry: the data are degenerate \
             (e.g. a reading or gauge length that divides by zero)"
        );
    }
    let projected = if nuisance.ncols() == 0 {
        jz
    } else {
        let f = Normal::assemble(&nuisance, None, |_| true)
            .factor(0.0)
            .ok_or_else(|| {
                anyhow!(
                    "station poses and reflector positions are not determined by the readings \
                     (singular normal matrix): check that every station sees at least 3 \
                     reflectors not on a line"
                )
            })?;
        sparse::project_out_rows_in(&nuisance, &f, jz, n)
    };
    let free: Vec<bool> = (0..start.coefs().len())
        .map(|i| setup.free_index.contains(&i))
        .collect();
    // Row-major as projected: the analysis reads it in blocks of rows.
    let projected = RowMajor {
        values: &projected,
        nrows: nuisance.nrows(),
        ncols: n,
    };
    Determined::analyse(&projected, start, &free, rank_tol)
}

/// The linearised problem at a bundle adjustment's solution, for tests of
/// added effects: the Jacobian of all residuals (readings first, three rows
/// each in units of σ; then gauge and reference rows) with respect to every
/// unknown, as its blocks, and the residuals.
#[derive(Clone, Debug)]
pub struct Linearisation {
    pub jacobian: BlockJacobian,
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
    let det = analyse_setup(net, start, &setup, settings.rank_tol)?;
    let basis = det.basis().clone();
    let layout = setup.layout(net, basis.ncols());
    let x0 = setup.initial(&layout);
    let r0 = setup.problem(net, start, &basis, &layout).residuals(&x0);
    let stated = solve(
        &setup,
        net,
        start,
        &basis,
        &layout,
        &x0,
        Some(&r0),
        settings,
    )?;
    let m = stated.r.len();
    let chi2 = stated.r.norm_squared();
    let dof = m.saturating_sub(layout.n).max(1);
    let chi2_p = statrs::distribution::ChiSquared::new(dof as f64)
        .ok()
        .map(|d| statrs::distribution::ContinuousCDF::sf(&d, chi2));
    // Which covariance: the stated noise unless asked otherwise or refuted
    // by the χ² test; the variance components where they are to be used
    // and could be estimated; else the former global scaling. The
    // components cost a hat-matrix diagonal per round (5× the adjustment
    // itself on a 16-station hall), so they are estimated only where used.
    let refuted = chi2_p.is_some_and(|p| p < STATED_NOISE_ALPHA);
    let use_components = match settings.std {
        BundleStd::StatedNoise | BundleStd::ScaledStatedNoise => false,
        BundleStd::VarianceComponents => true,
        BundleStd::Auto => refuted,
    };
    let components = use_components.then(|| {
        let groups = RowGroups::new(net, &layout, setup.use_references);
        variance_components(&setup, net, start, &basis, &layout, &stated, &groups)
    });
    let (std_from, var_factor, reweighted) = match (&components, settings.std) {
        (Some(Ok(c)), _) => {
            // The estimates and their covariance from the fit weighted by
            // the estimated σ, started at the stated-noise solution.
            let net_w = net.scaled(&c.s2);
            let setup_w = setup.reweighted(&net_w);
            let fit = solve(
                &setup_w, &net_w, start, &basis, &layout, &stated.x, None, settings,
            )?;
            ("variance-components", 1.0, Some(fit))
        }
        (Some(Err(_)), _) | (None, BundleStd::ScaledStatedNoise) => {
            ("scaled-stated-noise", (chi2 / dof as f64).max(1.0), None)
        }
        (None, _) => ("stated-noise", 1.0, None),
    };
    let last = reweighted.as_ref().unwrap_or(&stated);
    let problem = setup.problem(net, start, &basis, &layout);
    let x = &last.x;
    let params = problem.params(x);
    let factor = last
        .normal
        .factor(0.0)
        .ok_or_else(|| anyhow!("singular normal matrix at the solution"))?;
    let cov_a = factor.dense_covariance() * var_factor;
    let nz = layout.n_z;
    let cov_z = cov_a.view((0, 0), (nz, nz)).into_owned();
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
    let eliminated = factor.point_covariances(&cov_a, var_factor);
    let estimated: Vec<(usize, Vector3<f64>, Matrix3<f64>)> = layout
        .point
        .iter()
        .enumerate()
        .filter_map(|(t, off)| {
            let (o, dense) = (*off)?;
            let cov = if dense {
                Matrix3::from_fn(|i, j| cov_a[(o + i, o + j)])
            } else {
                eliminated[(o - layout.n_a) / 3]
            };
            Some((t, problem.point(x, t), cov))
        })
        .collect();
    let mut points = BTreeMap::new();
    let mut point_std = BTreeMap::new();
    let mut point_cov = BTreeMap::new();
    for (t, p, cov) in estimated {
        points.insert(t, p);
        point_std.insert(t, (cov.trace() / 3.0).max(0.0).sqrt());
        point_cov.insert(t, cov);
    }
    let poses: Vec<Rigid> = (0..net.stations.len())
        .map(|s| {
            let (rotation, translation, _) = problem.pose(x, s);
            Rigid {
                rotation,
                translation,
            }
        })
        .collect();
    let residuals = super::reading_residuals(net, &params, &poses, &points);
    let rms = |r: &DVector<f64>| (r.norm_squared() / m as f64).sqrt();
    let mean_abs = |r: &DVector<f64>| r.iter().map(|v| v.abs()).sum::<f64>() / m as f64;
    let (rms_after, mean_abs_after) = (rms(&stated.r), mean_abs(&stated.r));
    let (rank, gauge_scale_ppm) = (det.analysis.rank, gauge_scale_ppm(net, &params));
    let factor_of = |g: usize| {
        components.as_ref().and_then(|c| c.as_ref().ok()).map(|c| {
            let f = c.s2[g].sqrt();
            SigmaFactor {
                factor: f,
                u: helmert_u(f, c.redundancy[g]),
                redundancy: c.redundancy[g],
            }
        })
    };
    Ok(Calibration {
        estimate: det.estimate(params, free, Some(&cov_z)),
        poses,
        pose_std,
        points,
        point_std,
        point_cov,
        fit: FitSummary {
            objective: super::Objective::Bundle,
            norm: Norm::L2,
            n_readings: net.obs.len(),
            n_residuals: m,
            n_unknowns: layout.n,
            rank,
            iterations: stated.iterations,
            stop: stated.stop,
            std_from,
            sigma_angle_factor: factor_of(ANGLE),
            sigma_range_factor: factor_of(RANGE),
            rms_before: rms(&r0),
            rms_after,
            mean_abs_before: mean_abs(&r0),
            mean_abs_after,
            chi2: Some(chi2),
            dof: Some(dof),
            chi2_p,
            gauge_scale_ppm,
        },
        residuals,
        linearisation: Some(Linearisation {
            jacobian: stated.jacobian,
            residuals: stated.r,
        }),
    })
}

/// The χ² test's level below which the stated noise is taken as refuted
/// and `std = "auto"` uses the variance components: at 1 %, one fit in a
/// hundred whose noise is stated right is re-weighted by its (then close
/// to one) components; below it, the stated σ stand as they are — a χ²/dof
/// a little above 1 by chance no longer inflates every uncertainty.
pub const STATED_NOISE_ALPHA: f64 = 0.01;

/// A fit at one weighting, with its linearisation at the solution.
struct Solution {
    x: DVector<f64>,
    iterations: u64,
    stop: &'static str,
    jacobian: BlockJacobian,
    /// Residuals at `x`, in units of the weighting's σ.
    r: DVector<f64>,
    normal: Arc<Normal>,
}

/// Levenberg–Marquardt from `x0` (with its residuals `r0` when known) on
/// the network as `setup` weighs it; the solver's last linearisation is
/// kept when it is at the solution, built there otherwise.
#[allow(clippy::too_many_arguments)]
fn solve(
    setup: &Setup,
    net: &Network,
    start: &ErrorParams,
    basis: &DMatrix<f64>,
    layout: &Layout,
    x0: &DVector<f64>,
    r0: Option<&DVector<f64>>,
    settings: &Settings,
) -> Result<Solution> {
    let last = Mutex::new(None);
    let problem = Bundle {
        last: Some(&last),
        known: r0.map(|r| (x0, r)),
        ..setup.problem(net, start, basis, layout)
    };
    let fit = LevenbergMarquardt::new()
        .with_initial_lambda(INITIAL_LAMBDA)
        .and_then(|lm| lm.minimize(problem, x0.clone(), settings.max_iters))
        .map_err(|e| anyhow!("bundle adjustment failed: {e}"))?;
    let x = fit.x;
    let (jacobian, r, normal) = match last.into_inner().unwrap_or_else(|e| e.into_inner()) {
        Some(l) if l.x == x => (l.jacobian, l.residuals, l.normal),
        _ => {
            let (j, r) = setup
                .problem(net, start, basis, layout)
                .jacobian_at(&x, false);
            let normal = Arc::new(Normal::assemble(&j, None, |_| true));
            (j, r, normal)
        }
    };
    Ok(Solution {
        x,
        iterations: fit.iterations,
        stop: fit.reason,
        jacobian,
        r,
        normal,
    })
}

/// The observation groups whose σ the variance components estimate, in
/// [`RowGroups`]' numbering.
const ANGLE: usize = 0;
const RANGE: usize = 1;
const GAUGE: usize = 2;
const REFERENCE: usize = 3;
const GROUP_NAMES: [&str; 4] = ["angle", "range", "gauge", "reference"];

/// Which group each residual row belongs to, block by block in the order
/// [`Bundle::fill_readings`] and [`Bundle::visit_others`] make them: a
/// reading's az and el rows are angles, its d row a range; then one row
/// per gauge length both of whose reflectors are read; then three per
/// reference coordinate used.
struct RowGroups {
    /// Per residual block: its first row and its number of rows.
    blocks: Vec<(usize, usize)>,
    /// Per residual row.
    group: Vec<usize>,
}

impl RowGroups {
    fn new(net: &Network, layout: &Layout, use_references: bool) -> RowGroups {
        let mut out = RowGroups {
            blocks: Vec::new(),
            group: Vec::new(),
        };
        let mut push = |groups: &[usize]| {
            out.blocks.push((out.group.len(), groups.len()));
            out.group.extend_from_slice(groups);
        };
        for _ in &net.obs {
            push(&[ANGLE, ANGLE, RANGE]);
        }
        for g in &net.gauge {
            if layout.point[g.a].is_some() && layout.point[g.b].is_some() {
                push(&[GAUGE]);
            }
        }
        if use_references {
            for (t, rf) in net.references.iter().enumerate() {
                if rf.is_some() && layout.point[t].is_some() {
                    push(&[REFERENCE; 3]);
                }
            }
        }
        out
    }
}

/// The Helmert variance components of a bundle adjustment.
struct Components {
    /// Per group: the factor on its stated variance (1 where held).
    s2: [f64; 4],
    /// Per group: its redundancy number at the last round.
    redundancy: [f64; 4],
}

/// Helmert's variance component estimation, in Förstner's iterated form
/// (as [`crate::identify`] does for known points): at the stated-noise
/// solution, the linear step re-solved with each group's σ scaled by its
/// current component, each group's `vᵀPv` over its redundancy number
/// `r_g = n_g − tr(N_g·N⁻¹)` the factor by which the component was off,
/// until none moves by more than [`crate::identify::VC_TOL`]. The
/// redundancy numbers come from the factorised normal matrix, reflector
/// blocks through the Schur complement ([`hat_diagonal`]). The angle and
/// range groups must have redundancy (at least
/// [`crate::identify::VC_MIN_REDUNDANCY`]); the gauge and the references
/// keep their stated σ when theirs is below [`HELD_BELOW_REDUNDANCY`] at
/// the first round.
fn variance_components(
    setup: &Setup,
    net: &Network,
    start: &ErrorParams,
    basis: &DMatrix<f64>,
    layout: &Layout,
    stated: &Solution,
    groups: &RowGroups,
) -> Result<Components> {
    let mut s2 = [1.0; 4];
    let mut estimated: Option<Vec<usize>> = None;
    let mut redundancy = [0.0; 4];
    for _ in 0..VC_MAX_ITERS {
        let net_k = net.scaled(&s2);
        let setup_k = setup.reweighted(&net_k);
        let problem = setup_k.problem(&net_k, start, basis, layout);
        let (j, r) = problem.jacobian_at(&stated.x, false);
        let normal = Normal::assemble(&j, Some(&r), |_| true);
        let factor = normal
            .factor(0.0)
            .ok_or_else(|| anyhow!("the re-weighted normal matrix is singular"))?;
        // The linear step at the solution: v = r + J·δ, δ = −N⁻¹·Jᵀr.
        let y = factor.solve(normal.gradient());
        let mut v = r;
        j.sub_mul_rows(y.as_slice(), 1, v.as_mut_slice());
        let sinv = factor.dense_covariance();
        let hat: Vec<[f64; 3]> = groups
            .blocks
            .par_iter()
            .enumerate()
            .with_min_len(256)
            .map(|(b, &(_, rows))| hat_diagonal(&j, &factor, &sinv, b, rows))
            .collect();
        let mut q = [0.0; 4];
        redundancy = [0.0; 4];
        for (&(row, rows), h) in groups.blocks.iter().zip(&hat) {
            for k in 0..rows {
                let g = groups.group[row + k];
                q[g] += v[row + k] * v[row + k];
                redundancy[g] += 1.0 - h[k];
            }
        }
        let which = estimated.get_or_insert_with(|| {
            (0..4)
                .filter(|&g| g <= RANGE || redundancy[g] >= HELD_BELOW_REDUNDANCY)
                .collect()
        });
        let mut now: Vec<f64> = which.iter().map(|&g| s2[g]).collect();
        let sums: Vec<(&str, f64, f64)> = which
            .iter()
            .map(|&g| (GROUP_NAMES[g], q[g], redundancy[g]))
            .collect();
        let converged = helmert_round(&mut now, &sums)?;
        for (&g, v) in which.iter().zip(&now) {
            s2[g] = *v;
        }
        // Exact readings: the residuals are round-off, which never settles.
        let round_off = now.iter().all(|v| *v < VC_ROUND_OFF * VC_ROUND_OFF);
        if converged || round_off {
            break;
        }
    }
    Ok(Components { s2, redundancy })
}

/// The redundancy below which the gauge's or the references' σ is held at
/// its stated value rather than estimated: their component's uncertainty
/// `u(σ)/σ = 1/√(2r)` is then above 22 % — a few gauge lengths, or
/// references that do little more than fix the frame, cannot say how far
/// their σ was off.
const HELD_BELOW_REDUNDANCY: f64 = 10.0;

/// The diagonal of block `b`'s share of the hat matrix `J_b·N⁻¹·J_bᵀ`
/// (its first `rows` entries), from the dense part's covariance `S⁻¹`
/// (`sinv`) and the block's reflector through its Schur blocks:
/// `u = J_b,Aᵀ − W·J_b,xᵀ` on the reflector's dense columns,
/// `h = uᵀ·S⁻¹·u + J_b,x·H_xx⁻¹·J_b,xᵀ` ([`sparse::leverage`] with `S⁻¹`
/// formed once for every block).
fn hat_diagonal(
    j: &BlockJacobian,
    f: &sparse::Factor,
    sinv: &DMatrix<f64>,
    b: usize,
    rows: usize,
) -> [f64; 3] {
    let point = j.block_point(b);
    let cols: Vec<usize> = match point {
        Some(p) => f.point_coupling(p).0.to_vec(),
        None => {
            let mut c: Vec<usize> = j
                .dense_parts(b)
                .flat_map(|(col, w, _)| col..col + w)
                .collect();
            c.sort_unstable();
            c.dedup();
            c
        }
    };
    // u (cols × rows), row-major.
    let mut u = vec![0.0; cols.len() * rows];
    for (col, w, values) in j.dense_parts(b) {
        for c in 0..w {
            let Ok(a) = cols.binary_search(&(col + c)) else {
                continue;
            };
            for r in 0..rows {
                u[a * rows + r] += values[r * w + c];
            }
        }
    }
    let mut h = [0.0; 3];
    if let (Some(p), Some(part)) = (point, j.point_part(b)) {
        let w = f.point_coupling(p).1;
        let inv = f.point_inverse(p);
        for r in 0..rows {
            let jx = Vector3::new(part[r * 3], part[r * 3 + 1], part[r * 3 + 2]);
            h[r] = jx.dot(&(inv * jx));
            for a in 0..cols.len() {
                u[a * rows + r] -= w[(a, 0)] * jx[0] + w[(a, 1)] * jx[1] + w[(a, 2)] * jx[2];
            }
        }
    }
    for (r, h) in h.iter_mut().enumerate().take(rows) {
        for (a, &ca) in cols.iter().enumerate() {
            let ua = u[a * rows + r];
            if ua == 0.0 {
                continue;
            }
            let s: f64 = cols
                .iter()
                .enumerate()
                .map(|(bb, &cb)| sinv[(ca, cb)] * u[bb * rows + r])
                .sum();
            *h += ua * s;
        }
    }
    h
}

/// A bundle adjustment solved once, then again on perturbed copies of its
/// network — the trials of a Monte Carlo propagation (GUM Supplement 1,
/// [`super::monte_carlo`]). The frame, the determined directions and the
/// layout of the unknowns are the nominal fit's, and every trial starts
/// from its solution: two or three Gauss–Newton steps, without the
/// identifiability analysis or the covariances a full calibration adds.
pub struct Repeated {
    setup: Setup,
    basis: DMatrix<f64>,
    layout: Layout,
    start: ErrorParams,
    /// The nominal solution.
    x: DVector<f64>,
    max_iters: u64,
}

/// What one trial estimates.
#[derive(Clone, Debug)]
pub struct Solved {
    pub params: ErrorParams,
    /// Station → campaign frame.
    pub poses: Vec<Rigid>,
    /// Per target, its position; `None` when no reading sees it.
    pub points: Vec<Option<Vector3<f64>>>,
}

impl Repeated {
    /// Fits the nominal network.
    pub fn new(
        net: &Network,
        start: &ErrorParams,
        free: &[bool],
        settings: &Settings,
    ) -> Result<Repeated> {
        let setup = Setup::new(net, start, free)?;
        let det = analyse_setup(net, start, &setup, settings.rank_tol)?;
        let basis = det.basis().clone();
        let layout = setup.layout(net, basis.ncols());
        let x0 = setup.initial(&layout);
        let x = LevenbergMarquardt::new()
            .with_initial_lambda(INITIAL_LAMBDA)
            .and_then(|lm| {
                lm.minimize(
                    setup.problem(net, start, &basis, &layout),
                    x0,
                    settings.max_iters,
                )
            })
            .map_err(|e| anyhow!("bundle adjustment failed: {e}"))?
            .x;
        Ok(Repeated {
            setup,
            basis,
            layout,
            start: start.clone(),
            x,
            max_iters: settings.max_iters,
        })
    }

    /// The station that defines the frame, if one does (no references).
    pub fn fixed_station(&self) -> Option<usize> {
        self.setup.fixed_station
    }

    /// The nominal solution.
    pub fn nominal(&self, net: &Network) -> Solved {
        self.solved(net, &self.x)
    }

    /// Solves `net` — the nominal network with its readings, gauge lengths
    /// or reference coordinates perturbed, same readings in the same order —
    /// from the nominal solution. The readings' weights `W·J(q)⁻¹` are
    /// those of the perturbed readings, as a calibration of them would use.
    pub fn solve(&self, net: &Network) -> Result<Solved> {
        debug_assert_eq!(net.obs.len(), self.setup.weights.len());
        let weights: Vec<Matrix3<f64>> = net
            .obs
            .iter()
            .map(|o| design_weight(o, o.reading))
            .collect();
        let problem = Bundle {
            weights: &weights,
            ..self
                .setup
                .problem(net, &self.start, &self.basis, &self.layout)
        };
        let fit = LevenbergMarquardt::new()
            .with_initial_lambda(INITIAL_LAMBDA)
            .and_then(|lm| lm.minimize(problem, self.x.clone(), self.max_iters))
            .map_err(|e| anyhow!("bundle adjustment failed: {e}"))?;
        Ok(self.solved(net, &fit.x))
    }

    fn solved(&self, net: &Network, x: &DVector<f64>) -> Solved {
        let problem = self
            .setup
            .problem(net, &self.start, &self.basis, &self.layout);
        Solved {
            params: problem.params(x),
            poses: (0..net.stations.len())
                .map(|s| {
                    let (rotation, translation, _) = problem.pose(x, s);
                    Rigid {
                        rotation,
                        translation,
                    }
                })
                .collect(),
            points: (0..net.targets.len())
                .map(|t| self.layout.point[t].map(|_| problem.point(x, t)))
                .collect(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error_model::ErrorModel;
    use crate::identifiability;

    fn corner_network() -> Network {
        Network::from_campaign(&super::super::tests::corner_campaign()).unwrap()
    }

    /// Issue 34: the stations' means are formed per station in parallel,
    /// and the gauge check forms its reflectors' alone; both are the means
    /// one serial pass over the readings forms, bit for bit.
    #[test]
    fn station_means_per_station_are_the_serial_pass_s() {
        let net = corner_network();
        let params = ErrorParams::table2();
        let eval = params.evaluator();
        let mut serial: Vec<BTreeMap<usize, (Vector3<f64>, usize)>> =
            vec![BTreeMap::new(); net.stations.len()];
        for o in &net.obs {
            let e = serial[o.station]
                .entry(o.target)
                .or_insert((Vector3::zeros(), 0));
            e.0 += eval.point(o.q, &o.links);
            e.1 += 1;
        }
        let serial: Vec<BTreeMap<usize, Vector3<f64>>> = serial
            .into_iter()
            .map(|m| m.into_iter().map(|(t, (v, n))| (t, v / n as f64)).collect())
            .collect();
        assert_eq!(net.station_points(&params), serial);
        let kept = |t: usize| t % 3 == 1;
        let some: Vec<BTreeMap<usize, Vector3<f64>>> = serial
            .iter()
            .map(|m| {
                m.iter()
                    .filter(|(t, _)| kept(**t))
                    .map(|(t, v)| (*t, *v))
                    .collect()
            })
            .collect();
        assert_eq!(net.station_points_of(&params, kept), some);
        assert!(some.iter().any(|m| !m.is_empty()));
    }

    /// The bundle with the whole Jacobian formed densely: the reference the
    /// block-sparse path is checked against.
    struct Dense<'a>(Bundle<'a>);

    impl Operator for Dense<'_> {
        type Param = DVector<f64>;
        type Output = DVector<f64>;
        fn apply(&self, x: &DVector<f64>) -> Result<DVector<f64>, ArgminError> {
            Ok(self.0.residuals(x))
        }
    }

    impl Jacobian for Dense<'_> {
        type Param = DVector<f64>;
        type Jacobian = DMatrix<f64>;
        fn jacobian(&self, x: &DVector<f64>) -> Result<DMatrix<f64>, ArgminError> {
            Ok(self.0.jacobian_at(x, false).0.to_dense())
        }
    }

    /// The error-parameter columns with the span of the others removed, by
    /// QR of the whole dense Jacobian (the method before the sparse core).
    fn dense_projection(j: &DMatrix<f64>, k: usize) -> DMatrix<f64> {
        let jp = j.columns(0, k).into_owned();
        let q = j.columns(k, j.ncols() - k).into_owned().qr().q();
        &jp - &q * (q.transpose() * &jp)
    }

    #[test]
    fn the_analysis_jacobian_built_apart_is_the_whole_design_jacobian_split() {
        // Issue 34: the analysis no longer builds the whole Jacobian and
        // copies its coordinates' columns off; the same values, bit for bit,
        // gauge lengths' rows (no coordinates' part) included.
        let net = corner_network();
        let start = ErrorParams::zero(&ErrorModel::constant());
        let setup = Setup::new(&net, &start, &[true; 18]).unwrap();
        let identity = DMatrix::identity(18, 18);
        let layout = setup.layout(&net, 18);
        let probe = setup.problem(&net, &start, &identity, &layout);
        let x0 = setup.initial(&layout);
        let whole = probe.jacobian_at(&x0, true).0.to_dense();
        let (nuisance, lead) = probe.design_jacobian(&x0);
        let m = whole.nrows();
        assert_eq!((nuisance.nrows(), lead.len()), (m, m * 18));
        assert!(m > 3 * net.obs.len(), "rows beside the readings'");
        let bits = |v: &mut dyn Iterator<Item = f64>| v.map(f64::to_bits).collect::<Vec<_>>();
        assert_eq!(
            bits(&mut DMatrix::from_row_slice(m, 18, &lead).iter().copied()),
            bits(&mut whole.columns(0, 18).iter().copied())
        );
        assert_eq!(
            bits(&mut nuisance.to_dense().iter().copied()),
            bits(&mut whole.columns(18, whole.ncols() - 18).iter().copied())
        );
    }

    #[test]
    fn sparse_analysis_and_fit_match_a_dense_reference() {
        let net = corner_network();
        let start = ErrorParams::zero(&ErrorModel::constant());
        let free = [true; 18];
        let setup = Setup::new(&net, &start, &free).unwrap();
        let tol = crate::identifiability::DEFAULT_REL_TOL;
        let det = analyse_setup(&net, &start, &setup, tol).unwrap();
        let (a, combinations) = (&det.analysis, &det.combinations);
        let identity = DMatrix::identity(18, 18);
        let layout = setup.layout(&net, 18);
        let probe = setup.problem(&net, &start, &identity, &layout);
        let (j, _) = probe.jacobian_at(&setup.initial(&layout), true);
        let reference =
            identifiability::analyse(&dense_projection(&j.to_dense(), 18), tol).unwrap();
        assert_eq!(a.rank, reference.rank);
        assert_eq!(a.rank, 7, "the corner determines 7 combinations");
        for (s, r) in a
            .singular_values
            .iter()
            .zip(&reference.singular_values)
            .take(a.rank)
        {
            assert!((s / r - 1.0).abs() < 1e-9, "{s} vs {r}");
        }
        // The undetermined directions sit at round-off in both.
        let smax = a.singular_values[0];
        assert!(
            a.singular_values[a.rank..]
                .iter()
                .all(|s| *s < 1e-12 * smax),
            "{:?}",
            a.singular_values
        );
        let names: Vec<String> = start.coefs().iter().map(|c| c.symbol()).collect();
        let want: Vec<String> = identifiability::describe_null_space(&reference.null_basis, &names)
            .iter()
            .map(|c| c.sentence())
            .collect();
        let got: Vec<String> = combinations.iter().map(|c| c.sentence()).collect();
        assert_eq!(got, want);

        // The fit: Levenberg–Marquardt on the dense Jacobian from the same start.
        let settings = Settings {
            objective: crate::calibrate::Objective::Bundle,
            norm: Norm::L2,
            rank_tol: tol,
            max_iters: 100,
            std: BundleStd::StatedNoise,
        };
        let cal = calibrate(&net, &start, &free, &settings).unwrap();
        let basis = a.row_basis.clone();
        let layout = setup.layout(&net, basis.ncols());
        let dense = Dense(setup.problem(&net, &start, &basis, &layout));
        let fit = LevenbergMarquardt::new()
            .with_initial_lambda(INITIAL_LAMBDA)
            .and_then(|lm| lm.minimize(dense, setup.initial(&layout), 100))
            .unwrap();
        let problem = setup.problem(&net, &start, &basis, &layout);
        let params = problem.params(&fit.x);
        let scale = params.values().iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (p, q) in cal.estimate.params.values().iter().zip(params.values()) {
            assert!((p - q).abs() < 1e-9 * scale, "{p} vs {q}");
        }
        // Standard uncertainties from the dense inverse of JᵀJ.
        let (jac, r) = problem.jacobian_at(&fit.x, false);
        let jd = jac.to_dense();
        // The stated noise, unscaled.
        assert_eq!(cal.fit.std_from, "stated-noise");
        assert_eq!(r.len(), cal.fit.n_residuals);
        let cov = (jd.transpose() * &jd).try_inverse().unwrap();
        let cov_p = &basis * cov.view((0, 0), (basis.ncols(), basis.ncols())) * basis.transpose();
        for (k, s) in cal.estimate.std.iter().enumerate() {
            let want = cov_p[(k, k)].max(0.0).sqrt();
            let got = s.unwrap();
            assert!(
                (got - want).abs() <= 1e-6 * want.max(1e-12),
                "{k}: {got} vs {want}"
            );
        }
        // Each reflector's 3 × 3 block from the Schur blocks.
        for (t, sd) in &cal.point_std {
            let (o, _) = layout.point[*t].unwrap();
            let want = ((0..3).map(|k| cov[(o + k, o + k)]).sum::<f64>() / 3.0).sqrt();
            assert!((sd / want - 1.0).abs() < 1e-6, "{t}: {sd} vs {want}");
        }
    }

    /// The assembly and the factorisation split the reflectors into a
    /// fixed number of chunks and the readings are evaluated in parallel:
    /// the numbers must not depend on how many threads do it.
    #[test]
    fn bundle_results_do_not_depend_on_the_number_of_threads() {
        let net = corner_network();
        let start = ErrorParams::zero(&ErrorModel::constant());
        let settings = Settings {
            objective: super::super::Objective::Bundle,
            norm: Norm::L2,
            rank_tol: crate::identifiability::DEFAULT_REL_TOL,
            max_iters: 100,
            std: BundleStd::Auto,
        };
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| calibrate(&net, &start, &[true; 18], &settings).unwrap())
        };
        let (one, three) = (run(1), run(3));
        assert_eq!(one.estimate.params.values(), three.estimate.params.values());
        assert_eq!(one.estimate.std, three.estimate.std);
        assert_eq!(one.fit.chi2, three.fit.chi2);
        assert_eq!(one.point_std, three.point_std);
    }

    /// The redundancy numbers behind the variance components come from the
    /// factorised normal matrix, each reflector through its Schur blocks:
    /// they must be the dense hat matrix's, row by row, and sum to the
    /// degrees of freedom.
    #[test]
    fn redundancy_numbers_from_the_schur_blocks_match_the_dense_hat_matrix() {
        let net = corner_network();
        let start = ErrorParams::zero(&ErrorModel::constant());
        let setup = Setup::new(&net, &start, &[true; 18]).unwrap();
        let det = analyse_setup(&net, &start, &setup, identifiability::DEFAULT_REL_TOL).unwrap();
        let basis = det.basis().clone();
        let layout = setup.layout(&net, basis.ncols());
        let problem = setup.problem(&net, &start, &basis, &layout);
        let (j, _) = problem.jacobian_at(&setup.initial(&layout), false);
        let f = Normal::assemble(&j, None, |_| true).factor(0.0).unwrap();
        let sinv = f.dense_covariance();
        let groups = RowGroups::new(&net, &layout, setup.use_references);
        let jd = j.to_dense();
        assert_eq!(groups.group.len(), jd.nrows());
        let q = (jd.transpose() * &jd).try_inverse().unwrap();
        let (mut total, mut reflector_blocks) = (0.0, 0);
        for (b, &(row, rows)) in groups.blocks.iter().enumerate() {
            reflector_blocks += usize::from(j.block_point(b).is_some());
            let h = hat_diagonal(&j, &f, &sinv, b, rows);
            for (k, &h) in h.iter().enumerate().take(rows) {
                let want = jd
                    .row(row + k)
                    .dot(&(&q * jd.row(row + k).transpose()).transpose());
                assert!((h - want).abs() < 1e-8, "row {}: {} vs {want}", row + k, h);
                total += 1.0 - h;
            }
        }
        assert!(reflector_blocks > 0);
        let dof = (jd.nrows() - layout.n) as f64;
        assert!((total - dof).abs() < 1e-6, "{total} vs {dof}");
    }

    /// Issue 31: with the angles' σ stated three times too small and the
    /// ranges' right, the χ² test refutes the stated noise and the
    /// default re-weights by the components, which find the 3 and the 1.
    #[test]
    fn variance_components_find_the_understated_angle_group() {
        let net = corner_network().scaled(&[1.0 / 9.0, 1.0, 1.0, 1.0]);
        let start = ErrorParams::zero(&ErrorModel::constant());
        let settings = Settings {
            objective: super::super::Objective::Bundle,
            norm: Norm::L2,
            rank_tol: identifiability::DEFAULT_REL_TOL,
            max_iters: 100,
            std: BundleStd::Auto,
        };
        let cal = calibrate(&net, &start, &[true; 18], &settings).unwrap();
        assert_eq!(cal.fit.std_from, "variance-components");
        assert!(cal.fit.chi2_p.unwrap() < STATED_NOISE_ALPHA);
        let (a, r) = (
            cal.fit.sigma_angle_factor.unwrap(),
            cal.fit.sigma_range_factor.unwrap(),
        );
        assert!((a.factor - 3.0).abs() < 3.0 * a.u, "{a:?}");
        assert!((r.factor - 1.0).abs() < 3.0 * r.u, "{r:?}");
        assert!(a.u > 0.0 && a.u < 0.1 * a.factor, "{a:?}");
        // The same network with its noise stated right keeps it, and
        // estimates no components it would not use.
        let right = calibrate(&corner_network(), &start, &[true; 18], &settings).unwrap();
        assert_eq!(right.fit.std_from, "stated-noise");
        assert!(right.fit.sigma_angle_factor.is_none());
        // Asked for, they find the stated σ.
        let asked = Settings {
            std: BundleStd::VarianceComponents,
            ..settings.clone()
        };
        let right = calibrate(&corner_network(), &start, &[true; 18], &asked).unwrap();
        assert_eq!(right.fit.std_from, "variance-components");
        let a = right.fit.sigma_angle_factor.unwrap();
        assert!((a.factor - 1.0).abs() < 3.0 * a.u, "{a:?}");
    }

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
