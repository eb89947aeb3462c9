//! Block-sparse least squares: the structure every bundle adjustment shares,
//! kept from the Jacobian to the last covariance.
//!
//! The unknowns split in two. The *dense part* `A` holds the error-parameter
//! coordinates `z`, the station poses and the few reflector positions a
//! gauge couples; its size grows with the number of stations. The
//! *eliminated part* `X` holds every other reflector position, three
//! unknowns each. A residual block — a reading's three rows, a gauge
//! length's one, a reference coordinate's three — touches `z`, at most one
//! station and one position, so the Jacobian is stored as those blocks
//! ([`BlockJacobian`]) and never as a matrix.
//!
//! The normal matrix `N = JᵀJ` then has the arrow structure
//!
//! ```text
//! N = | H_AA  H_AX |     H_XX block-diagonal, 3 × 3 per reflector,
//!     | H_XA  H_XX |     each H_AX non-zero only on z and the stations that see it
//! ```
//!
//! and every solve goes through the Schur complement
//! `S = H_AA − Σ H_AX·H_XX⁻¹·H_XA` (Triggs et al., *Bundle adjustment — a
//! modern synthesis*, 2000, §6.1; Ceres Solver's `SCHUR`), whose size is
//! that of `A`. Each reflector keeps its `H_AX` compact: only the columns of
//! `A` its readings touch. Assembly and every solve cost time linear in the
//! readings (plus `|A|³` once per factorisation), and memory linear in the
//! readings.
//!
//! Projections (`x − J·N⁻¹·Jᵀx`: what the model cannot absorb) use the
//! corrected semi-normal equations — the solve corrected once from the
//! unsquared residual (Å. Björck, *Numerical methods for least squares
//! problems*, 1996, §6.6.5) — so an exact redundancy of the model comes out
//! at the round-off level of `J`, as a QR factorisation would give, not at
//! that of `JᵀJ`.

use nalgebra::{DMatrix, DVector, Dyn, Matrix3, Vector3, linalg::Cholesky};

/// One Jacobian block of a residual block: `rows × width` values,
/// row-major, starting at column `col`.
#[derive(Clone, Copy, Debug)]
struct Part {
    col: usize,
    width: usize,
    at: usize,
}

/// A residual block: `rows` consecutive residuals and its parts.
#[derive(Clone, Copy, Debug)]
struct Block {
    row: usize,
    rows: usize,
    parts: (usize, usize),
}

/// The Jacobian of a bundle adjustment as its non-zero blocks.
#[derive(Clone, Debug)]
pub struct BlockJacobian {
    /// Columns `[0, n_a)` form the dense part; `[n_a, n)` are eliminated
    /// positions, three columns each.
    n_a: usize,
    n: usize,
    m: usize,
    blocks: Vec<Block>,
    parts: Vec<Part>,
    values: Vec<f64>,
}

impl BlockJacobian {
    /// An empty Jacobian over `n` unknowns whose first `n_a` form the dense
    /// part (`n − n_a` must be a multiple of 3).
    pub fn new(n_a: usize, n: usize) -> BlockJacobian {
        debug_assert_eq!((n - n_a) % 3, 0);
        BlockJacobian {
            n_a,
            n,
            m: 0,
            blocks: Vec::new(),
            parts: Vec::new(),
            values: Vec::new(),
        }
    }

    /// Appends a residual block of `rows` rows with its parts
    /// `(first column, rows × width values, row-major)`. An eliminated
    /// position's part must cover its three columns exactly.
    pub fn push(&mut self, rows: usize, parts: &[(usize, &[f64])]) {
        let p0 = self.parts.len();
        for &(col, v) in parts {
            let width = v.len() / rows;
            debug_assert_eq!(width * rows, v.len());
            debug_assert!(col + width <= self.n);
            debug_assert!(col + width <= self.n_a || (col >= self.n_a && width == 3));
            self.parts.push(Part {
                col,
                width,
                at: self.values.len(),
            });
            self.values.extend_from_slice(v);
        }
        self.blocks.push(Block {
            row: self.m,
            rows,
            parts: (p0, self.parts.len()),
        });
        self.m += rows;
    }

    /// Whether every entry is finite.
    pub fn is_finite(&self) -> bool {
        self.values.iter().all(|v| v.is_finite())
    }

    /// Number of residuals.
    pub fn nrows(&self) -> usize {
        self.m
    }

    /// Number of unknowns.
    pub fn ncols(&self) -> usize {
        self.n
    }

    /// Number of residual blocks.
    pub fn blocks(&self) -> usize {
        self.blocks.len()
    }

    /// The first row and the row count of block `b`.
    pub fn block_rows(&self, b: usize) -> (usize, usize) {
        (self.blocks[b].row, self.blocks[b].rows)
    }

    fn parts_of(&self, b: &Block) -> impl Iterator<Item = (usize, usize, &[f64])> {
        self.parts[b.parts.0..b.parts.1]
            .iter()
            .map(move |p| (p.col, p.width, &self.values[p.at..p.at + b.rows * p.width]))
    }

    /// Block `b`'s rows times `x`, added to `out` (length `rows`).
    pub fn block_mul(&self, b: usize, x: &[f64], out: &mut [f64]) {
        let blk = &self.blocks[b];
        for (col, w, v) in self.parts_of(blk) {
            for (k, o) in out.iter_mut().enumerate().take(blk.rows) {
                let row = &v[k * w..(k + 1) * w];
                *o += row
                    .iter()
                    .zip(&x[col..col + w])
                    .map(|(a, b)| a * b)
                    .sum::<f64>();
            }
        }
    }

    /// Block `b`'s rows transposed times `r` (its `rows` residuals), added to `out` (length n).
    pub fn block_tr_mul(&self, b: usize, r: &[f64], out: &mut [f64]) {
        let blk = &self.blocks[b];
        for (col, w, v) in self.parts_of(blk) {
            for (k, rk) in r.iter().enumerate().take(blk.rows) {
                for (c, a) in v[k * w..(k + 1) * w].iter().enumerate() {
                    out[col + c] += a * rk;
                }
            }
        }
    }

    /// `J·x`.
    pub fn mul(&self, x: &DVector<f64>) -> DVector<f64> {
        let mut out = DVector::zeros(self.m);
        for (b, blk) in self.blocks.iter().enumerate() {
            self.block_mul(
                b,
                x.as_slice(),
                &mut out.as_mut_slice()[blk.row..blk.row + blk.rows],
            );
        }
        out
    }

    /// `Jᵀ·r`.
    pub fn tr_mul(&self, r: &DVector<f64>) -> DVector<f64> {
        let mut out = DVector::zeros(self.n);
        for (b, blk) in self.blocks.iter().enumerate() {
            self.block_tr_mul(
                b,
                &r.as_slice()[blk.row..blk.row + blk.rows],
                out.as_mut_slice(),
            );
        }
        out
    }

    /// The eliminated position a block touches, if any.
    pub fn block_point(&self, b: usize) -> Option<usize> {
        let blk = &self.blocks[b];
        self.parts[blk.parts.0..blk.parts.1]
            .iter()
            .find(|p| p.col >= self.n_a)
            .map(|p| (p.col - self.n_a) / 3)
    }

    /// Number of eliminated positions.
    pub fn points(&self) -> usize {
        (self.n - self.n_a) / 3
    }

    /// Size of the dense part.
    pub fn n_a(&self) -> usize {
        self.n_a
    }

    /// The columns of the dense part block `b` touches, ascending.
    fn dense_cols(&self, b: &Block, out: &mut Vec<usize>) {
        for p in &self.parts[b.parts.0..b.parts.1] {
            if p.col < self.n_a {
                out.extend(p.col..p.col + p.width);
            }
        }
    }

    /// Splits off the first `k` columns (which no part may straddle): the
    /// Jacobian of the other columns, renumbered from 0, and the first `k`
    /// columns as a dense `m × k` matrix (m·k values: the error-parameter
    /// coordinates, a handful of columns).
    pub fn split_leading(&self, k: usize) -> (BlockJacobian, DMatrix<f64>) {
        let mut rest = BlockJacobian::new(self.n_a - k, self.n - k);
        let mut lead = DMatrix::zeros(self.m, k);
        let mut parts: Vec<(usize, &[f64])> = Vec::new();
        for blk in &self.blocks {
            parts.clear();
            for (col, w, v) in self.parts_of(blk) {
                if col + w <= k {
                    for r in 0..blk.rows {
                        for c in 0..w {
                            lead[(blk.row + r, col + c)] += v[r * w + c];
                        }
                    }
                } else {
                    debug_assert!(col >= k, "a part straddles the split");
                    parts.push((col - k, v));
                }
            }
            rest.push(blk.rows, &parts);
        }
        (rest, lead)
    }

    /// The whole matrix, densely: for tests against a dense reference only.
    #[cfg(test)]
    pub fn to_dense(&self) -> DMatrix<f64> {
        let mut d = DMatrix::zeros(self.m, self.n);
        for blk in &self.blocks {
            for (col, w, v) in self.parts_of(blk) {
                for r in 0..blk.rows {
                    for c in 0..w {
                        d[(blk.row + r, col + c)] += v[r * w + c];
                    }
                }
            }
        }
        d
    }

    /// Block `b`'s part on the eliminated position: `rows × 3`, row-major.
    pub fn point_part(&self, b: usize) -> Option<&[f64]> {
        let blk = &self.blocks[b];
        self.parts_of(blk)
            .find(|(c, _, _)| *c >= self.n_a)
            .map(|(_, _, v)| v)
    }

    /// Block `b`'s parts on the dense part: `(first column, width, values)`.
    pub fn dense_parts(&self, b: usize) -> impl Iterator<Item = (usize, usize, &[f64])> {
        let blk = &self.blocks[b];
        self.parts_of(blk).filter(|(c, _, _)| *c < self.n_a)
    }
}

/// Where a block's local column lands in the normal equations: a dense
/// column (and its place among the block's position's columns), or one of
/// the position's three.
#[derive(Clone, Copy, Debug)]
enum Dest {
    Dense(usize, Option<usize>),
    Point(usize),
}

/// One eliminated position's share of the normal equations.
#[derive(Clone, Debug)]
struct PointBlock {
    /// The dense-part columns its blocks touch, ascending.
    cols: Vec<usize>,
    /// `H_AX` on those columns: `cols.len() × 3`.
    h_ax: DMatrix<f64>,
    h_xx: Matrix3<f64>,
    /// Whether any admitted block touches it.
    seen: bool,
}

/// The normal equations `JᵀJ·δ = −Jᵀr` in arrow form.
#[derive(Clone, Debug)]
pub struct Normal {
    n_a: usize,
    h_aa: DMatrix<f64>,
    points: Vec<PointBlock>,
    /// `Jᵀr` (zero when assembled without residuals).
    g: DVector<f64>,
}

impl Normal {
    /// `JᵀJ` and `Jᵀr` over the blocks `keep` admits (every block: `|_| true`).
    pub fn assemble(
        j: &BlockJacobian,
        r: Option<&DVector<f64>>,
        keep: impl Fn(usize) -> bool,
    ) -> Normal {
        let n_a = j.n_a;
        // Which dense columns each position's blocks touch.
        let mut cols: Vec<Vec<usize>> = vec![Vec::new(); j.points()];
        let mut seen = vec![false; j.points()];
        for (b, blk) in j.blocks.iter().enumerate() {
            if !keep(b) {
                continue;
            }
            if let Some(p) = j.block_point(b) {
                j.dense_cols(blk, &mut cols[p]);
                seen[p] = true;
            }
        }
        for c in &mut cols {
            c.sort_unstable();
            c.dedup();
        }
        let mut points: Vec<PointBlock> = cols
            .into_iter()
            .zip(seen)
            .map(|(cols, seen)| PointBlock {
                h_ax: DMatrix::zeros(cols.len(), 3),
                cols,
                h_xx: Matrix3::zeros(),
                seen,
            })
            .collect();
        let mut h_aa = DMatrix::zeros(n_a, n_a);
        let mut g = DVector::zeros(j.n);
        // Per block: its parts side by side (rows × w, row-major), where
        // each local column goes, and the upper triangle of its JᵀJ.
        let mut local: Vec<f64> = Vec::new();
        let mut dest: Vec<Dest> = Vec::new();
        for (b, blk) in j.blocks.iter().enumerate() {
            if !keep(b) {
                continue;
            }
            let rows = blk.rows;
            if let Some(r) = r {
                j.block_tr_mul(b, &r.as_slice()[blk.row..blk.row + rows], g.as_mut_slice());
            }
            dest.clear();
            let point = j.block_point(b);
            for (col, w, _) in j.parts_of(blk) {
                if col < n_a {
                    let first =
                        point.map(|p| points[p].cols.binary_search(&col).expect("collected above"));
                    dest.extend((0..w).map(|c| Dest::Dense(col + c, first.map(|f| f + c))));
                } else {
                    dest.extend((0..3).map(Dest::Point));
                }
            }
            let w = dest.len();
            local.clear();
            local.resize(rows * w, 0.0);
            let mut at = 0;
            for (_, pw, v) in j.parts_of(blk) {
                for k in 0..rows {
                    local[k * w + at..k * w + at + pw].copy_from_slice(&v[k * pw..(k + 1) * pw]);
                }
                at += pw;
            }
            for a in 0..w {
                for c in a..w {
                    let mut h = 0.0;
                    for k in 0..rows {
                        h += local[k * w + a] * local[k * w + c];
                    }
                    match (dest[a], dest[c]) {
                        (Dest::Dense(ga, _), Dest::Dense(gc, _)) => {
                            h_aa[(ga, gc)] += h;
                            if ga != gc {
                                h_aa[(gc, ga)] += h;
                            }
                        }
                        (Dest::Dense(_, Some(la)), Dest::Point(pc)) => {
                            points[point.expect("a point column")].h_ax[(la, pc)] += h;
                        }
                        (Dest::Point(pa), Dest::Dense(_, Some(lc))) => {
                            points[point.expect("a point column")].h_ax[(lc, pa)] += h;
                        }
                        (Dest::Point(pa), Dest::Point(pc)) => {
                            let hx = &mut points[point.expect("a point column")].h_xx;
                            hx[(pa, pc)] += h;
                            if pa != pc {
                                hx[(pc, pa)] += h;
                            }
                        }
                        _ => unreachable!("a dense column beside a point has its local place"),
                    }
                }
            }
        }
        Normal {
            n_a,
            h_aa,
            points,
            g,
        }
    }

    /// `Jᵀr`.
    pub fn gradient(&self) -> &DVector<f64> {
        &self.g
    }

    /// `‖J·d‖² = dᵀ·N·d`.
    pub fn quadratic(&self, d: &DVector<f64>) -> f64 {
        let n_a = self.n_a;
        let da = d.rows(0, n_a);
        let mut q = da.dot(&(&self.h_aa * da));
        for (i, p) in self.points.iter().enumerate() {
            let dx = d.fixed_rows::<3>(n_a + 3 * i);
            let hx = &p.h_ax * dx;
            let cross: f64 = p.cols.iter().zip(hx.iter()).map(|(&c, v)| d[c] * v).sum();
            q += 2.0 * cross + dx.dot(&(p.h_xx * dx));
        }
        q
    }

    /// Factorises `N + λ·diag(N)` (Marquardt's damping; `λ = 0`: `N`
    /// itself); `None` when it is singular. A position no admitted block
    /// touches (a reflector all of whose readings a cross-validation fold
    /// holds out) is left out: its solution is zero, the minimum-norm
    /// choice.
    pub fn factor(&self, lambda: f64) -> Option<Factor> {
        let n_a = self.n_a;
        let mut s = self.h_aa.clone();
        for i in 0..n_a {
            s[(i, i)] += lambda * self.h_aa[(i, i)].max(1e-300);
        }
        let mut points = Vec::with_capacity(self.points.len());
        for p in &self.points {
            if !p.seen {
                points.push(FactorPoint {
                    cols: Vec::new(),
                    inv: Matrix3::zeros(),
                    w: DMatrix::zeros(0, 3),
                });
                continue;
            }
            let mut d = p.h_xx;
            for i in 0..3 {
                d[(i, i)] += lambda * p.h_xx[(i, i)].max(1e-300);
            }
            let inv = d.try_inverse()?;
            if !inv.iter().all(|v| v.is_finite()) {
                return None;
            }
            // W = H_AX·H_XX⁻¹ (cols × 3), then S −= W·H_XA on the upper
            // triangle, mirrored: the small products written out, as they
            // run once per reflector per factorisation.
            let nc = p.cols.len();
            let mut w = DMatrix::zeros(nc, 3);
            for a in 0..nc {
                for c in 0..3 {
                    w[(a, c)] = (0..3).map(|k| p.h_ax[(a, k)] * inv[(k, c)]).sum();
                }
            }
            for a in 0..nc {
                let (wa0, wa1, wa2) = (w[(a, 0)], w[(a, 1)], w[(a, 2)]);
                for b in a..nc {
                    let v = wa0 * p.h_ax[(b, 0)] + wa1 * p.h_ax[(b, 1)] + wa2 * p.h_ax[(b, 2)];
                    let (ca, cb) = (p.cols[a], p.cols[b]);
                    s[(ca, cb)] -= v;
                    if a != b {
                        s[(cb, ca)] -= v;
                    }
                }
            }
            points.push(FactorPoint {
                cols: p.cols.clone(),
                inv,
                w,
            });
        }
        if !s.iter().all(|v| v.is_finite()) {
            return None;
        }
        let (e, d) = equilibrate(&s);
        let chol = e.cholesky()?;
        Some(Factor {
            n_a,
            chol,
            d,
            points,
        })
    }
}

/// One eliminated position in a factorisation.
#[derive(Clone, Debug)]
struct FactorPoint {
    cols: Vec<usize>,
    /// `H_XX⁻¹` (damped).
    inv: Matrix3<f64>,
    /// `H_AX·H_XX⁻¹` on `cols`.
    w: DMatrix<f64>,
}

/// A factorised normal matrix: the Cholesky factor of the equilibrated
/// Schur complement and each position's inverse block.
#[derive(Clone, Debug)]
pub struct Factor {
    n_a: usize,
    chol: Cholesky<f64, Dyn>,
    /// Equilibration: `S = D⁻¹·E·D⁻¹` with `E` factorised.
    d: DVector<f64>,
    points: Vec<FactorPoint>,
}

impl Factor {
    /// `S⁻¹·b` for the dense part.
    pub fn solve_schur(&self, b: &DVector<f64>) -> DVector<f64> {
        self.chol
            .solve(&b.component_mul(&self.d))
            .component_mul(&self.d)
    }

    /// `N⁻¹·rhs`.
    pub fn solve(&self, rhs: &DVector<f64>) -> DVector<f64> {
        let n_a = self.n_a;
        let mut b = rhs.rows(0, n_a).into_owned();
        for (i, p) in self.points.iter().enumerate() {
            let rx = rhs.fixed_rows::<3>(n_a + 3 * i);
            let wr = &p.w * rx;
            for (k, &c) in p.cols.iter().enumerate() {
                b[c] -= wr[k];
            }
        }
        let xa = self.solve_schur(&b);
        let mut x = DVector::zeros(rhs.len());
        x.rows_mut(0, n_a).copy_from(&xa);
        for (i, p) in self.points.iter().enumerate() {
            let rx = rhs.fixed_rows::<3>(n_a + 3 * i);
            let mut xx = p.inv * rx;
            for (k, &c) in p.cols.iter().enumerate() {
                for a in 0..3 {
                    xx[a] -= p.w[(k, a)] * xa[c];
                }
            }
            x.fixed_rows_mut::<3>(n_a + 3 * i).copy_from(&xx);
        }
        x
    }

    /// `N⁻¹·B` for the columns of `B` (n × k).
    pub fn solve_columns(&self, rhs: &DMatrix<f64>) -> DMatrix<f64> {
        let n_a = self.n_a;
        let k = rhs.ncols();
        let mut b = rhs.rows(0, n_a).into_owned();
        for (i, p) in self.points.iter().enumerate() {
            if p.cols.is_empty() {
                continue;
            }
            let wr = &p.w * rhs.rows(n_a + 3 * i, 3);
            for (row, &c) in p.cols.iter().enumerate() {
                for col in 0..k {
                    b[(c, col)] -= wr[(row, col)];
                }
            }
        }
        for mut c in b.column_iter_mut() {
            c.component_mul_assign(&self.d);
        }
        let mut xa = self.chol.solve(&b);
        for mut c in xa.column_iter_mut() {
            c.component_mul_assign(&self.d);
        }
        let mut x = DMatrix::zeros(rhs.nrows(), k);
        x.rows_mut(0, n_a).copy_from(&xa);
        for (i, p) in self.points.iter().enumerate() {
            let mut xx = p.inv * rhs.rows(n_a + 3 * i, 3);
            if !p.cols.is_empty() {
                xx -= p.w.transpose() * xa.select_rows(&p.cols);
            }
            x.rows_mut(n_a + 3 * i, 3).copy_from(&xx);
        }
        x
    }

    /// `S⁻¹`: the covariance of the dense part (in units of the residuals' variance).
    pub fn dense_covariance(&self) -> DMatrix<f64> {
        let mut inv = self.chol.inverse();
        for i in 0..inv.nrows() {
            for j in 0..inv.ncols() {
                inv[(i, j)] *= self.d[i] * self.d[j];
            }
        }
        inv
    }

    /// The 3 × 3 covariance of eliminated position `i`, given the dense
    /// part's covariance `C = v·S⁻¹` with variance factor `v`:
    /// `v·H_XX⁻¹ + Wᵀ·C·W` with `W = H_AX·H_XX⁻¹` (the Schur blocks).
    pub fn point_covariance(&self, i: usize, dense_cov: &DMatrix<f64>, v: f64) -> Matrix3<f64> {
        let p = &self.points[i];
        let sub = dense_cov.select_rows(&p.cols).select_columns(&p.cols);
        let add = p.w.transpose() * sub * &p.w;
        p.inv * v + Matrix3::from_iterator(add.iter().copied())
    }

    /// `wᵀ·S⁻¹·v` pieces for sparse right-hand sides: the dense-part
    /// reduction `u_A − Σ_x W_x·u_x` of a right-hand side given on the
    /// dense part and a few positions.
    pub fn reduce_sparse(&self, u_a: &DMatrix<f64>, u_x: &[(usize, DMatrix<f64>)]) -> DMatrix<f64> {
        let mut v = u_a.clone();
        for (i, ux) in u_x {
            let p = &self.points[*i];
            let wu = &p.w * ux;
            for (k, &c) in p.cols.iter().enumerate() {
                for col in 0..v.ncols() {
                    v[(c, col)] -= wu[(k, col)];
                }
            }
        }
        v
    }

    /// `S⁻¹·V` for several columns.
    pub fn solve_schur_columns(&self, v: &DMatrix<f64>) -> DMatrix<f64> {
        let mut out = v.clone();
        for mut c in out.column_iter_mut() {
            let x = self.solve_schur(&c.clone_owned());
            c.copy_from(&x);
        }
        out
    }

    /// `H_XX⁻¹` of eliminated position `i`.
    pub fn point_inverse(&self, i: usize) -> &Matrix3<f64> {
        &self.points[i].inv
    }

    /// `(columns, H_AX·H_XX⁻¹)` of eliminated position `i`.
    pub fn point_coupling(&self, i: usize) -> (&[usize], &DMatrix<f64>) {
        (&self.points[i].cols, &self.points[i].w)
    }
}

/// `x − J·N⁻¹·Jᵀ·x`: what of `x` no combination of `J`'s columns
/// reproduces, by the corrected semi-normal equations (see the module doc).
pub fn project_out(j: &BlockJacobian, f: &Factor, x: &DVector<f64>) -> DVector<f64> {
    let mut r = x.clone();
    // The solve, then one correction from the unsquared residual.
    for _ in 0..2 {
        let y = f.solve(&j.tr_mul(&r));
        r -= j.mul(&y);
    }
    r
}

/// [`project_out`] for the `k` columns of `x` (m × k) at once: one pass
/// over the blocks serves every column, which is what makes the
/// identifiability analysis (18 columns) cost a few passes, not 18 × a few.
pub fn project_out_columns(j: &BlockJacobian, f: &Factor, x: &DMatrix<f64>) -> DMatrix<f64> {
    let k = x.ncols();
    // Row-major copies: a row's k values side by side.
    let mut r: Vec<f64> = x.transpose().as_slice().to_vec();
    for _ in 0..2 {
        // Jᵀ·r, n × k row-major.
        let mut g = vec![0.0; j.n * k];
        for blk in &j.blocks {
            for (col, w, v) in j.parts_of(blk) {
                for row in 0..blk.rows {
                    let rr = &r[(blk.row + row) * k..(blk.row + row + 1) * k];
                    for a in 0..w {
                        let coef = v[row * w + a];
                        let out = &mut g[(col + a) * k..(col + a + 1) * k];
                        for (o, x) in out.iter_mut().zip(rr) {
                            *o += coef * x;
                        }
                    }
                }
            }
        }
        let g = DMatrix::from_row_slice(j.n, k, &g);
        let y = f.solve_columns(&g).transpose();
        let y = y.as_slice(); // n × k row-major
        // r −= J·y
        for blk in &j.blocks {
            for (col, w, v) in j.parts_of(blk) {
                for row in 0..blk.rows {
                    let out = &mut r[(blk.row + row) * k..(blk.row + row + 1) * k];
                    for a in 0..w {
                        let coef = v[row * w + a];
                        let ya = &y[(col + a) * k..(col + a + 1) * k];
                        for (o, x) in out.iter_mut().zip(ya) {
                            *o -= coef * x;
                        }
                    }
                }
            }
        }
    }
    DMatrix::from_row_slice(j.m, k, &r)
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

/// The vector `(x, y, z)` of a row-major 3 × 3 part times `v`.
pub fn part3_mul(part: &[f64], v: &Vector3<f64>) -> Vector3<f64> {
    Vector3::new(
        part[0] * v.x + part[1] * v.y + part[2] * v.z,
        part[3] * v.x + part[4] * v.y + part[5] * v.z,
        part[6] * v.x + part[7] * v.y + part[8] * v.z,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A random-ish arrow-structured problem: 2 dense unknowns, 4 positions,
    /// blocks touching the dense part and one position each.
    fn problem() -> (BlockJacobian, DMatrix<f64>) {
        let (n_a, n) = (2, 2 + 12);
        let mut j = BlockJacobian::new(n_a, n);
        let mut dense = Vec::new();
        let mut s = 0.37_f64;
        let mut next = || {
            s = (s * 9301.0 + 49297.0) % 233280.0;
            s / 233280.0 - 0.5
        };
        for p in 0..4 {
            for _ in 0..3 {
                let a: Vec<f64> = (0..3 * 2).map(|_| next()).collect();
                let x: Vec<f64> = (0..9)
                    .map(|k| next() + if k % 4 == 0 { 2.0 } else { 0.0 })
                    .collect();
                j.push(3, &[(0, &a), (n_a + 3 * p, &x)]);
                for k in 0..3 {
                    let mut row = vec![0.0; n];
                    row[0] = a[2 * k];
                    row[1] = a[2 * k + 1];
                    for c in 0..3 {
                        row[n_a + 3 * p + c] = x[3 * k + c];
                    }
                    dense.push(row);
                }
            }
        }
        let jd = DMatrix::from_fn(dense.len(), n, |i, k| dense[i][k]);
        (j, jd)
    }

    #[test]
    fn schur_solve_matches_the_dense_normal_equations() {
        let (j, jd) = problem();
        let rhs = DVector::from_fn(j.ncols(), |i, _| (i as f64 * 0.7).sin());
        let x = Normal::assemble(&j, None, |_| true)
            .factor(0.0)
            .unwrap()
            .solve(&rhs);
        let xd = (jd.transpose() * &jd).cholesky().unwrap().solve(&rhs);
        assert!((x - xd).norm() < 1e-10);
    }

    #[test]
    fn covariances_match_the_dense_inverse() {
        let (j, jd) = problem();
        let f = Normal::assemble(&j, None, |_| true).factor(0.0).unwrap();
        let inv = (jd.transpose() * &jd).try_inverse().unwrap();
        let ca = f.dense_covariance();
        assert!((ca - inv.view((0, 0), (2, 2))).norm() < 1e-10);
        let cp = f.point_covariance(2, &f.dense_covariance(), 1.0);
        assert!((cp - inv.fixed_view::<3, 3>(2 + 6, 2 + 6)).norm() < 1e-10);
    }

    #[test]
    fn projection_removes_exactly_the_span() {
        let (j, jd) = problem();
        let f = Normal::assemble(&j, None, |_| true).factor(0.0).unwrap();
        let inside = &jd * DVector::from_fn(j.ncols(), |i, _| i as f64 - 3.0);
        assert!(project_out(&j, &f, &inside).norm() < 1e-12 * inside.norm());
        let x = DVector::from_fn(j.nrows(), |i, _| ((i * i) % 5) as f64);
        let p = project_out(&j, &f, &x);
        assert!((jd.transpose() * &p).norm() < 1e-10);
        let q = jd.clone().qr().q();
        let reference = &x - &q * (q.transpose() * &x);
        assert!((p - reference).norm() < 1e-10);
        let xs = DMatrix::from_fn(j.nrows(), 3, |i, c| ((i * (c + 2)) % 7) as f64 - c as f64);
        let ps = project_out_columns(&j, &f, &xs);
        for c in 0..3 {
            let one = project_out(&j, &f, &xs.column(c).into_owned());
            assert!((ps.column(c) - one).norm() < 1e-12 * xs.norm());
        }
    }

    #[test]
    fn quadratic_form_is_the_squared_norm_of_j_d() {
        let (j, jd) = problem();
        let n = Normal::assemble(&j, None, |_| true);
        let d = DVector::from_fn(j.ncols(), |i, _| (i as f64).cos());
        assert!((n.quadratic(&d) - (&jd * &d).norm_squared()).abs() < 1e-10);
        assert!(((j.mul(&d)) - &jd * &d).norm() < 1e-12);
        let r = DVector::from_fn(j.nrows(), |i, _| (i as f64).sin());
        assert!((j.tr_mul(&r) - jd.transpose() * r).norm() < 1e-12);
    }
}
