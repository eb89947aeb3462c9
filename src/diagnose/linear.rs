//! Tests of added effects on the linearised bundle adjustment.
//!
//! At the base solution, the residual vector `r` (in units of σ) is
//! orthogonal to the columns of the base Jacobian `J`. An unmodelled effect
//! with parameters `β` adds `C·β` to the readings' residuals (`C`: its
//! signature, in units of σ per unit of β). Because the effects are small
//! (µm, µrad) against the geometry, the augmented fit is linear around the
//! base solution:
//!
//! ```text
//! Δχ² = ‖P⊥·C·β̂‖²,  β̂ = argmin ‖r − P⊥·C·β‖,  P⊥ = I − J·J⁺
//! ```
//!
//! — the part of the effect the base model cannot absorb (poses, positions,
//! error parameters) is what the data can see. Cross-validation refits both
//! models on each fold's training readings and predicts the held-out ones,
//! so a candidate is scored by what it predicts, not by what it fits.
//! Held-out residuals are reported in µm: each reading's residual in
//! (az, el, d), times its σ, mapped to the point through the reading
//! Jacobian.
//!
//! Everything stays block-sparse ([`crate::calibrate::sparse`]): `J` is
//! never formed, the full and each fold's normal matrix are factorised once
//! through their Schur complement, and a candidate — whose columns touch
//! only the readings it affects — costs time in proportion to those
//! readings and to the square of the dense part (error parameters and
//! poses), not to the size of the network:
//!
//! ```text
//! CᵀP⊥C = CᵀC − uᵀN⁻¹u,  u = JᵀC  (sparse: the affected readings' blocks)
//! uᵀN⁻¹u = Σₓ uₓᵀH_XX⁻¹uₓ + vᵀS⁻¹v,  v = u_A − Σₓ H_AX·H_XX⁻¹·uₓ
//! ```
//!
//! A fold's held-out residuals with a candidate added are the base model's
//! (`a_i`, computed once per fold) moved by the change of the base fit,
//! `K_i·δ_A` (`K_i = J_iA − J_iX·H_XX⁻¹·H_XA`: reading i's response to the
//! dense part once its reflector re-adjusts), plus terms on the affected
//! readings alone; the sum of squares over all held-out readings is a
//! quadratic form in `δ_A` whose matrix is accumulated once per fold.

use crate::calibrate::snooping::{self, Absorbed, WTest};
use crate::calibrate::sparse::{self, BlockJacobian, Factor, Normal, project_out};
use nalgebra::{DMatrix, DVector, Matrix3, Vector3};
use rayon::prelude::*;
use std::borrow::Cow;

/// A candidate's signature: `k` columns over the model's rows, non-zero
/// only on the readings it affects (never on gauge or reference rows).
#[derive(Clone, Debug)]
pub struct Signature {
    k: usize,
    /// Affected readings, ascending.
    readings: Vec<usize>,
    /// Per affected reading, its 3 × k block, row-major.
    values: Vec<f64>,
}

impl Signature {
    /// `k` empty columns.
    pub fn new(k: usize) -> Signature {
        Signature {
            k,
            readings: Vec::new(),
            values: Vec::new(),
        }
    }

    /// Number of columns (the effect's parameters).
    pub fn ncols(&self) -> usize {
        self.k
    }

    /// Adds `v` to row `axis` (0 az, 1 el, 2 d) of reading `i`, column
    /// `col`. Readings must be visited in non-decreasing order.
    pub fn add(&mut self, i: usize, axis: usize, col: usize, v: f64) {
        if self.readings.last() != Some(&i) {
            debug_assert!(self.readings.last().is_none_or(|&l| l < i));
            self.readings.push(i);
            self.values.extend(std::iter::repeat_n(0.0, 3 * self.k));
        }
        let at = self.values.len() - 3 * self.k;
        self.values[at + axis * self.k + col] += v;
    }

    /// Whether `self` is `wider` on some of its readings: the same columns,
    /// and on each of its readings the same values.
    pub fn narrows(&self, wider: &Signature) -> bool {
        if self.k != wider.k || self.readings.len() > wider.readings.len() {
            return false;
        }
        let mut theirs = wider.blocks().peekable();
        self.blocks().all(|(i, v)| {
            while theirs.next_if(|(j, _)| *j < i).is_some() {}
            theirs
                .next_if(|(j, _)| *j == i)
                .is_some_and(|(_, w)| w == v)
        })
    }

    /// `self` on the readings `keep` admits: their blocks as they are.
    pub fn on(&self, keep: impl Fn(usize) -> bool) -> Signature {
        let mut out = Signature::new(self.k);
        for (i, v) in self.blocks().filter(|(i, _)| keep(*i)) {
            out.readings.push(i);
            out.values.extend_from_slice(v);
        }
        out
    }

    /// `a`'s columns, then `b`'s.
    pub fn concat(a: &Signature, b: &Signature) -> Signature {
        let k = a.k + b.k;
        let mut out = Signature::new(k);
        let (mut ia, mut ib) = (a.blocks().peekable(), b.blocks().peekable());
        loop {
            let next = match (ia.peek(), ib.peek()) {
                (None, None) => break,
                (Some(x), Some(y)) => x.0.min(y.0),
                (Some(x), None) => x.0,
                (None, Some(y)) => y.0,
            };
            out.readings.push(next);
            let at = out.values.len();
            out.values.extend(std::iter::repeat_n(0.0, 3 * k));
            for (src, off, width) in [(&mut ia, 0, a.k), (&mut ib, a.k, b.k)] {
                if let Some((_, v)) = src.next_if(|(i, _)| *i == next) {
                    for row in 0..3 {
                        out.values[at + row * k + off..at + row * k + off + width]
                            .copy_from_slice(&v[row * width..(row + 1) * width]);
                    }
                }
            }
        }
        out
    }

    /// [`Signature::concat`] borrowing `b` when `a` has no columns (the
    /// first step's members): the same columns without a copy of every
    /// value — a localisation basis over every reading is megabytes, and
    /// each of its fits copied it.
    pub fn joined<'b>(a: &Signature, b: &'b Signature) -> Cow<'b, Signature> {
        if a.k == 0 {
            Cow::Borrowed(b)
        } else {
            Cow::Owned(Signature::concat(a, b))
        }
    }

    /// `C_i·β` for every affected reading `i` (units of σ).
    pub fn times(&self, beta: &[f64]) -> Vec<(usize, Vector3<f64>)> {
        self.blocks()
            .map(|(i, v)| {
                let dot = |row: usize| (0..self.k).map(|c| v[row * self.k + c] * beta[c]).sum();
                (i, Vector3::new(dot(0), dot(1), dot(2)))
            })
            .collect()
    }

    /// The columns over all `rows` rows, row-major (`k` values per row).
    fn dense_rows(&self, rows: usize) -> Vec<f64> {
        let mut out = vec![0.0; rows * self.k];
        for (i, v) in self.blocks() {
            out[3 * i * self.k..3 * (i + 1) * self.k].copy_from_slice(v);
        }
        out
    }

    /// Reading `i`'s block (3 × k, row-major) and the reading.
    fn blocks(&self) -> impl Iterator<Item = (usize, &[f64])> {
        self.readings
            .iter()
            .zip(self.values.chunks(3 * self.k.max(1)))
            .map(|(&i, v)| (i, v))
    }

    /// The largest squared column norm over the readings `keep` admits.
    fn column_scale(&self, keep: impl Fn(usize) -> bool) -> f64 {
        let mut n2 = vec![0.0; self.k];
        for (i, v) in self.blocks() {
            if keep(i) {
                // Row by row: each column's terms in the order the block
                // holds them, without a division per value.
                for row in v.chunks(self.k) {
                    for (n, x) in n2.iter_mut().zip(row) {
                        *n += x * x;
                    }
                }
            }
        }
        n2.into_iter().fold(0.0, f64::max)
    }

    /// A dense `rows × k` copy, for tests against the definition.
    #[cfg(test)]
    fn dense(&self, rows: usize) -> DMatrix<f64> {
        let mut c = DMatrix::zeros(rows, self.k);
        for (i, v) in self.blocks() {
            for a in 0..3 {
                for col in 0..self.k {
                    c[(3 * i + a, col)] = v[a * self.k + col];
                }
            }
        }
        c
    }
}

/// `JᵀC`, `CᵀC` and `Cᵀx` over the affected readings `keep` admits: the
/// dense part of `JᵀC` (n_a × k), its eliminated positions' parts, and the
/// two small products (`Cᵀx` zero without an `x`: the folds' shares,
/// [`Products::less`], sum their own).
struct Products {
    u_a: DMatrix<f64>,
    u_x: Vec<(usize, DMatrix<f64>)>,
    ctc: DMatrix<f64>,
    ctx: DVector<f64>,
}

fn products(
    j: &BlockJacobian,
    c: &Signature,
    x: Option<&DVector<f64>>,
    keep: impl Fn(usize) -> bool,
) -> Products {
    let k = c.k;
    let n_a = j.n_a();
    let mut u_a = DMatrix::zeros(n_a, k);
    let mut u_x: Vec<(usize, DMatrix<f64>)> = Vec::new();
    // Each position's entry in `u_x` (in order of first appearance, which
    // the reduction's sums follow): a search of `u_x` per reading was
    // quadratic in the positions a broad candidate touches.
    let mut slot_of: Vec<u32> = Vec::new();
    let mut ctc = DMatrix::zeros(k, k);
    let mut ctx = DVector::zeros(k);
    // Every product below is the one nalgebra's `tr_mul` of the reading's
    // 3-row blocks forms (each entry a three-term sum from zero, `x`'s
    // three-row case as `(a + b) + c`), written out: no matrix allocated
    // per reading, the same numbers.
    let col3 = |m: &[f64], w: usize, a: usize| [m[a], m[w + a], m[2 * w + a]];
    let dot3 = |a: [f64; 3], b: [f64; 3]| {
        let mut s = 0.0;
        for (x, y) in a.iter().zip(&b) {
            s += x * y;
        }
        s
    };
    // The columns not zero on the reading, each with its values there,
    // gathered once per reading. A zero column adds `+0` to every sum
    // (each a three-term sum from `+0`), which leaves an accumulator that
    // started at `+0` as it was: it is skipped, the same numbers. A
    // localisation basis touches a reading in a few of its columns (a
    // smooth function's two knots of eight, an offset's one station of
    // twenty): its products cost those columns, not all of them.
    //
    // Per such column, too, the rows (az, el, d) not zero on the reading.
    // A zero row's term in a three-term sum from `+0` is `±0`, which
    // leaves the sum as the other terms make it (up to the sign of a
    // zero, which an accumulator that started at `+0` never keeps): each
    // sum below runs over those rows only, the same numbers. Most bases
    // touch one row of a reading (a cyclic error of the range, a smooth
    // function or a Fourier series on one coordinate, an offset): their
    // `u_A` is one row of each part times a number, contiguous, not a
    // gather of three strided values per entry.
    let mut nz: Vec<(usize, [f64; 3], Rows)> = Vec::with_capacity(k);
    for (i, v) in c.blocks() {
        if !keep(i) {
            continue;
        }
        nz.clear();
        nz.extend(
            (0..k)
                .map(|b| (b, col3(v, k, b)))
                .filter(|(_, cb)| *cb != [0.0; 3])
                .map(|(b, cb)| (b, cb, Rows::of(cb))),
        );
        for (at, &(a, ca, _)) in nz.iter().enumerate() {
            // `CᵀC` is symmetric: each pair's product once, added to both
            // entries (`x·y` is `y·x`, the same three-term sum).
            for &(b, cb, _) in &nz[at..] {
                let d = dot3(ca, cb);
                ctc[(a, b)] += d;
                if b != a {
                    ctc[(b, a)] += d;
                }
            }
            if let Some(x) = x {
                ctx[a] += ca[0] * x[3 * i] + ca[1] * x[3 * i + 1] + ca[2] * x[3 * i + 2];
            }
        }
        for (col, w, part) in j.dense_parts(i) {
            // A column of `u_a` at a time: contiguous (column-major), each
            // entry still one addition per part.
            for &(b, cb, rows) in &nz {
                let out = &mut u_a.as_mut_slice()[b * n_a + col..b * n_a + col + w];
                rows.add_part_product(out, part, w, cb);
            }
        }
        if let Some((p, part)) = j.point_of(i) {
            if slot_of.is_empty() {
                slot_of = vec![u32::MAX; j.points()];
            }
            let at = match slot_of[p] {
                u32::MAX => {
                    slot_of[p] = u_x.len() as u32;
                    u_x.push((p, DMatrix::zeros(3, k)));
                    u_x.len() - 1
                }
                at => at as usize,
            };
            // A new position's entries are their first terms added to
            // `+0`: the same numbers as formed directly.
            // Its 3 × k matrix is column-major: a column is `u_a`'s sum
            // on the position's part.
            let m = u_x[at].1.as_mut_slice();
            let part: &[f64; 9] = part.try_into().expect("a reading's position part is 3 × 3");
            for &(b, cb, rows) in &nz {
                let out: &mut [f64; 3] = (&mut m[3 * b..3 * b + 3]).try_into().expect("3 rows");
                rows.add_point_product(out, part, cb);
            }
        }
    }
    Products { u_a, u_x, ctc, ctx }
}

/// The rows (az, el, d) of a reading on which a column is not zero
/// ([`products`]); `Three` also for a column zero on every row (never
/// asked: such a column is skipped).
#[derive(Clone, Copy)]
enum Rows {
    One(usize),
    Two(usize, usize),
    Three,
}

impl Rows {
    fn of(c: [f64; 3]) -> Rows {
        match c.map(|v| v != 0.0) {
            [true, false, false] => Rows::One(0),
            [false, true, false] => Rows::One(1),
            [false, false, true] => Rows::One(2),
            [true, true, false] => Rows::Two(0, 1),
            [true, false, true] => Rows::Two(0, 2),
            [false, true, true] => Rows::Two(1, 2),
            _ => Rows::Three,
        }
    }

    /// `out += partᵀ·c` (`part`: 3 × w, row-major; `c`: a column's values
    /// on the reading's rows, not zero on these rows): each entry the
    /// three-term sum from `+0` without its zero terms — the same number,
    /// up to the sign of a zero.
    #[inline]
    fn add_part_product(self, out: &mut [f64], part: &[f64], w: usize, c: [f64; 3]) {
        let row = |r: usize| &part[r * w..(r + 1) * w];
        match self {
            Rows::One(r) => {
                for (o, p) in out.iter_mut().zip(row(r)) {
                    *o += p * c[r];
                }
            }
            Rows::Two(r, s) => {
                for ((o, p), q) in out.iter_mut().zip(row(r)).zip(row(s)) {
                    *o += p * c[r] + q * c[s];
                }
            }
            Rows::Three => {
                for (a, o) in out.iter_mut().enumerate() {
                    let mut s = 0.0;
                    for (r, cr) in c.iter().enumerate() {
                        s += part[r * w + a] * cr;
                    }
                    *o += s;
                }
            }
        }
    }

    /// [`Rows::add_part_product`] on a position's part (3 × 3): the same
    /// sums, of fixed length — a call per column for three products each
    /// was most of their cost.
    #[inline(always)]
    fn add_point_product(self, out: &mut [f64; 3], part: &[f64; 9], c: [f64; 3]) {
        match self {
            Rows::One(r) => {
                for (a, o) in out.iter_mut().enumerate() {
                    *o += part[3 * r + a] * c[r];
                }
            }
            Rows::Two(r, s) => {
                for (a, o) in out.iter_mut().enumerate() {
                    *o += part[3 * r + a] * c[r] + part[3 * s + a] * c[s];
                }
            }
            Rows::Three => {
                for (a, o) in out.iter_mut().enumerate() {
                    let mut s = 0.0;
                    for (r, cr) in c.iter().enumerate() {
                        s += part[3 * r + a] * cr;
                    }
                    *o += s;
                }
            }
        }
    }
}

impl Products {
    /// The products over the readings of `self` less those of `held` (a
    /// subset of them), with `ctx` summed afresh from `x` over the readings
    /// `keep` admits (the rest): `CᵀC`, `u_A` and each position's `uₓ` are
    /// sums over readings, so the rest's are the difference.
    fn less(
        &self,
        held: &Products,
        c: &Signature,
        x: &DVector<f64>,
        keep: impl Fn(usize) -> bool,
    ) -> Products {
        let mut u_x = self.u_x.clone();
        // Each position's entry found by index (a search per position was
        // quadratic in the positions a broad candidate touches).
        let mut slot_of = vec![usize::MAX; u_x.iter().map(|(p, _)| p + 1).max().unwrap_or(0)];
        for (at, (p, _)) in u_x.iter().enumerate() {
            slot_of[*p] = at;
        }
        for (p, h) in &held.u_x {
            u_x[slot_of[*p]].1 -= h;
        }
        let mut ctx = DVector::zeros(c.k);
        for (i, v) in c.blocks() {
            if keep(i) {
                // The block's three rows side by side: the same sums,
                // several columns at a time.
                let (r0, rest) = v.split_at(c.k);
                let (r1, r2) = rest.split_at(c.k);
                let (x0, x1, x2) = (x[3 * i], x[3 * i + 1], x[3 * i + 2]);
                for (((o, a), b), d) in ctx.iter_mut().zip(r0).zip(r1).zip(r2) {
                    *o += a * x0 + b * x1 + d * x2;
                }
            }
        }
        Products {
            u_a: &self.u_a - &held.u_a,
            u_x,
            ctc: &self.ctc - &held.ctc,
            ctx,
        }
    }

    /// `CᵀP⊥C = CᵀC − uᵀN⁻¹u` and `v = u_A − Σ W·uₓ` (for later solves).
    fn projected_gram(&self, f: &Factor) -> (DMatrix<f64>, DMatrix<f64>) {
        let v = f.reduce_sparse(&self.u_a, &self.u_x);
        let mut q = f.schur_quadratic_form(&v);
        add_point_forms(&mut q, f, &self.u_x);
        (&self.ctc - q, v)
    }
}

/// The fit of `c` to `r_perp` (the residuals, `J`'s span removed) on the
/// factor `full` of all data.
fn fit_with(j: &BlockJacobian, full: &Factor, r_perp: &DVector<f64>, c: &Signature) -> Fit {
    fit_keeping(j, full, r_perp, c).0
}

/// [`fit_with`] and the products it formed over every reading.
fn fit_keeping(
    j: &BlockJacobian,
    full: &Factor,
    r_perp: &DVector<f64>,
    c: &Signature,
) -> (Fit, AllProducts) {
    let pr = products(j, c, Some(r_perp), |_| true);
    let (gram, _) = pr.projected_gram(full);
    let fit = fit_of(&gram, &pr.ctx, c.column_scale(|_| true));
    (fit, AllProducts(pr))
}

/// A signature's `u_A`, `uₓ` and `CᵀC` over every reading, as its fit on
/// all data formed them ([`LinearModel::fit_keeping`]): what
/// [`LinearModel::cv_rms_um_given`] starts from. `Cᵀx` is not read there
/// (each fold sums its own), and the other sums do not depend on `x`: they
/// are the products [`LinearModel::cv_rms_um`] forms, the same numbers.
pub struct AllProducts(Products);

/// The fits of the nested signatures `chain` (each the one before on
/// fewer of its readings, the same values there: a station's steps at
/// later and later times) to `r_perp` on the factor `full`, in the order of
/// `chain`. `CᵀC`, `Cᵀr⊥`, `v = u_A − Σₓ W·uₓ` and each position's `uₓ`
/// are linear in the readings' terms: the readings only `chain[g]` has
/// (not `chain[g + 1]`) form a segment, and `chain[g]`'s sums are its
/// segment's plus `chain[g + 1]`'s — one pass over the first signature's
/// readings instead of one per signature (a station's 24 steps each over
/// about half its readings were 12 passes). Only the quadratic forms
/// (`vᵀS⁻¹v`, `Σₓ uₓᵀH_XX⁻¹uₓ`) are formed per signature. The sums run in
/// another order than [`fit_with`]'s, so the fits equal its to round-off.
fn fit_nested(
    j: &BlockJacobian,
    full: &Factor,
    r_perp: &DVector<f64>,
    chain: &[&Signature],
) -> Vec<Fit> {
    let mut fits = Vec::with_capacity(chain.len());
    let Some(last) = chain.last() else {
        return fits;
    };
    let k = last.k;
    let mut ctc = DMatrix::zeros(k, k);
    let mut ctx = DVector::zeros(k);
    let mut v = DMatrix::zeros(j.n_a(), k);
    let mut u_x: Vec<(usize, DMatrix<f64>)> = Vec::new();
    let mut slot_of: Vec<usize> = Vec::new();
    for g in (0..chain.len()).rev() {
        let c = chain[g];
        debug_assert_eq!(c.k, k);
        let seg = match chain.get(g + 1) {
            Some(next) => products(j, c, Some(r_perp), |i| {
                next.readings.binary_search(&i).is_err()
            }),
            None => products(j, c, Some(r_perp), |_| true),
        };
        ctc += &seg.ctc;
        ctx += &seg.ctx;
        v += full.reduce_sparse(&seg.u_a, &seg.u_x);
        for (p, m) in seg.u_x {
            if slot_of.len() <= p {
                slot_of.resize(p + 1, usize::MAX);
            }
            match slot_of[p] {
                usize::MAX => {
                    slot_of[p] = u_x.len();
                    u_x.push((p, m));
                }
                at => u_x[at].1 += m,
            }
        }
        let mut q = full.schur_quadratic_form(&v);
        add_point_forms(&mut q, full, &u_x);
        fits.push(fit_of(&(&ctc - q), &ctx, c.column_scale(|_| true)));
    }
    fits.reverse();
    fits
}

/// The fit from the projected Gram matrix `CᵀP⊥C` and `Cᵀr⊥` of columns
/// whose largest squared norm is `scale`.
fn fit_of(gram: &DMatrix<f64>, ctx: &DVector<f64>, scale: f64) -> Fit {
    let (beta, cov) = lstsq(gram, ctx, scale);
    let delta_chi2 = beta.dot(&(gram * &beta)).max(0.0);
    // 1 − R² of each column on the others: `1 / (G⁻¹)ⱼⱼ / Gⱼⱼ`.
    let independence = (0..gram.nrows())
        .map(|j| 1.0 / (cov[(j, j)] * gram[(j, j)]))
        .collect();
    Fit {
        beta: beta.iter().copied().collect(),
        delta_chi2,
        cov,
        independence,
    }
}

/// The most of `r` that any one of `columns` explains beside the model
/// linearised as `j` (the largest Δχ² of their fits), the normal matrix
/// factored once for them all.
pub fn most_absorbed(
    j: &BlockJacobian,
    r: &DVector<f64>,
    columns: &[&Signature],
) -> Result<f64, Singular> {
    let full = Normal::assemble(j, None, |_| true)
        .factor(0.0)
        .ok_or(Singular(""))?;
    let r_perp = project_out(j, &full, r);
    Ok(columns
        .iter()
        .map(|c| fit_with(j, &full, &r_perp, c).delta_chi2)
        .fold(0.0, f64::max))
}

/// The fit of `c` to the residuals `r` of the model linearised as `j`,
/// without the cross-validation folds: what a refit needs.
pub fn fit_once(j: &BlockJacobian, r: &DVector<f64>, c: &Signature) -> Result<Fit, Singular> {
    let full = Normal::assemble(j, None, |_| true)
        .factor(0.0)
        .ok_or(Singular(""))?;
    Ok(fit_with(j, &full, &project_out(j, &full, r), c))
}

/// Least squares by the normal equations of a few projected columns, with a
/// ridge of 1e-10 of the columns' size before projection: what the base
/// model absorbs entirely (to round-off) gets β = 0, not a huge β fitting
/// round-off. Also the solution's covariance, the inverse of that matrix
/// (NaN where it is singular: no uncertainty to claim).
fn lstsq(gram: &DMatrix<f64>, rhs: &DVector<f64>, scale: f64) -> (DVector<f64>, DMatrix<f64>) {
    let mut a = gram.clone();
    for i in 0..a.nrows() {
        a[(i, i)] += 1e-10 * scale.max(1e-300);
    }
    let n = gram.nrows();
    a.cholesky()
        .map(|c| (c.solve(rhs), c.inverse()))
        // Not solvable: no estimate, and no uncertainty to claim for it.
        .unwrap_or_else(|| (DVector::zeros(n), DMatrix::from_element(n, n, f64::NAN)))
}

/// `N⁻¹·Jᵀ·x` over the blocks `keep` admits, refined once from the
/// unsquared residual ([`sparse::solve_ls_rows`] for one column).
fn solve_ls(
    j: &BlockJacobian,
    f: &Factor,
    x: &DVector<f64>,
    keep: &(dyn Fn(usize) -> bool + Sync),
) -> DVector<f64> {
    DVector::from_vec(sparse::solve_ls_rows(j, f, x.as_slice(), 1, keep))
}

/// Monte Carlo draws go through the folds this many at a time: one pass
/// over the Jacobian serves them all, and a fixed batch keeps the sums the
/// same on any number of threads.
const DRAW_BATCH: usize = 16;

struct Fold {
    /// Held-out readings (indices into the reading list, ascending).
    test: Vec<usize>,
    factor: Factor,
    /// `r − J·y_f` with `y_f` the base fit to the training rows of the
    /// model's residuals: training residuals on training rows, the
    /// held-out residuals `a_i` on test rows.
    res: DVector<f64>,
    /// `Σ_test K_iᵀ·L_iᵀL_i·K_i`, `Σ_test K_iᵀ·L_iᵀL_i·a_i`, `Σ_test ‖L_i·a_i‖²`
    /// with `L_i` reading i's map to µm.
    g_k: DMatrix<f64>,
    h_k: DVector<f64>,
    base_sum: f64,
}

/// The base model linearised at its solution, with its cross-validation
/// folds prepared.
pub struct LinearModel {
    j: BlockJacobian,
    r: DVector<f64>,
    /// `P⊥·r` over all data.
    r_perp: DVector<f64>,
    full: Factor,
    fold_of: Vec<usize>,
    folds: Vec<Fold>,
    /// Per eliminated position: the readings that see it.
    readings_of_point: Vec<Vec<usize>>,
    /// Per reading: `1e3·J_nom·diag(σ)` (µm per unit of σ).
    to_um: Vec<Matrix3<f64>>,
    dof: usize,
}

/// What adding a candidate's columns does.
#[derive(Clone, Debug)]
pub struct Fit {
    pub beta: Vec<f64>,
    pub delta_chi2: f64,
    /// Covariance of `beta` for unit-variance (whitened) readings:
    /// `(CᵀP⊥C)⁻¹`, ridged as the fit is.
    pub cov: DMatrix<f64>,
    /// Per column, the share of it (after what the base model absorbs)
    /// that the other columns do not reproduce, `1 − R²`: near 0 for a
    /// column collinear with the others (NaN where the fit is singular).
    pub independence: Vec<f64>,
}

/// The model was not determined enough to test anything.
#[derive(Debug, thiserror::Error)]
#[error("the base adjustment's normal matrix is singular{0}")]
pub struct Singular(&'static str);

/// Fold `f`'s fit: its test readings, the factor of its training rows'
/// normal equations, and every row's residual after the training fit.
fn fold_fit(
    j: &BlockJacobian,
    r: &DVector<f64>,
    fold_of: &[usize],
    f: usize,
) -> Result<(Vec<usize>, Factor, DVector<f64>), Singular> {
    let n_read = fold_of.len();
    let train = |b: usize| b >= n_read || fold_of[b] != f;
    let test: Vec<usize> = (0..n_read).filter(|&i| fold_of[i] == f).collect();
    let factor = fold_factor(&Normal::assemble(j, None, train))
        .ok_or(Singular(" on a cross-validation fold"))?;
    let y = solve_ls(j, &factor, r, &train);
    let mut res = r.clone();
    j.sub_mul_rows(y.as_slice(), 1, res.as_mut_slice());
    Ok((test, factor, res))
}

impl LinearModel {
    /// `j`, `r`: the base Jacobian and residuals (readings' three rows each
    /// first, one block per reading, then other observations). `fold_of[i]`:
    /// the fold of reading `i`. `to_mm[i]`: reading i's `J_nom·diag(σ)`.
    pub fn new(
        j: BlockJacobian,
        r: DVector<f64>,
        fold_of: &[usize],
        n_folds: usize,
        to_mm: Vec<Matrix3<f64>>,
    ) -> Result<LinearModel, Singular> {
        let n_read = fold_of.len();
        let full = Normal::assemble(&j, None, |_| true)
            .factor(0.0)
            .ok_or(Singular(""))?;
        let r_perp = project_out(&j, &full, &r);
        let to_um: Vec<Matrix3<f64>> = to_mm.into_iter().map(|m| m * 1e3).collect();
        let mut readings_of_point = vec![Vec::new(); j.points()];
        for i in 0..n_read {
            if let Some(p) = j.block_point(i) {
                readings_of_point[p].push(i);
            }
        }
        // The folds are independent (each its own sums, in its own order):
        // in parallel, the same numbers.
        let folds = (0..n_folds)
            .into_par_iter()
            .map(|f| {
                let (test, factor, res) = fold_fit(&j, &r, fold_of, f)?;
                let n_a = j.n_a();
                let mut g_k = DMatrix::zeros(n_a, n_a);
                let mut h_k = DVector::zeros(n_a);
                let mut base_sum = 0.0;
                let mut kr = DMatrix::zeros(3, n_a);
                let mut nz = Vec::new();
                let mut merged = Vec::new();
                let mut lk_rows: [Vec<f64>; 3] = Default::default();
                let mut runs: Vec<(usize, usize)> = Vec::new();
                for &i in &test {
                    let l = to_um[i];
                    let a = l * Vector3::new(res[3 * i], res[3 * i + 1], res[3 * i + 2]);
                    base_sum += a.norm_squared();
                    k_rows(&j, &factor, i, &mut kr, &mut nz, &mut merged);
                    let lk = l * kr.select_columns(&nz);
                    let lkt_a = lk.tr_mul(&a);
                    // `lkᵀ·lk` (as `tr_mul` sums it: three terms from
                    // zero, the `+0` dropped — it changes no sum but the
                    // sign of a zero, which an accumulator from `+0` never
                    // keeps), each pair once, into the lower triangle:
                    // column `cx` is contiguous. The upper triangle is its
                    // mirror (each pair's two entries were the same sum of
                    // the same products). `lk`'s rows side by side and `nz`
                    // in runs of consecutive columns (a reflector's
                    // stations' poses, the error parameters): each run's
                    // entries of a column are contiguous, and so are the
                    // three rows' values they read, so the sums go several
                    // entries at a time — each entry the same three-term
                    // sum, added in the same order of readings.
                    for (row, out) in lk_rows.iter_mut().enumerate() {
                        out.clear();
                        out.extend(lk.row(row).iter());
                    }
                    sparse::consecutive_runs(&nz, &mut runs);
                    let [k0, k1, k2] = &lk_rows;
                    let mut first_run = 0;
                    for (x, &cx) in nz.iter().enumerate() {
                        h_k[cx] += lkt_a[x];
                        let (a0, a1, a2) = (k0[x], k1[x], k2[x]);
                        let column = &mut g_k.as_mut_slice()[cx * n_a..(cx + 1) * n_a];
                        while runs[first_run].1 <= x {
                            first_run += 1;
                        }
                        for &(s, e) in &runs[first_run..] {
                            let s = s.max(x);
                            let out = &mut column[nz[s]..nz[s] + (e - s)];
                            for (((o, b0), b1), b2) in
                                out.iter_mut().zip(&k0[s..e]).zip(&k1[s..e]).zip(&k2[s..e])
                            {
                                *o += a0 * b0 + a1 * b1 + a2 * b2;
                            }
                        }
                    }
                }
                g_k.fill_upper_triangle_with_lower_triangle();
                Ok(Fold {
                    test,
                    factor,
                    res,
                    g_k,
                    h_k,
                    base_sum,
                })
            })
            .collect::<Result<Vec<_>, Singular>>()?;
        let dof = j.nrows().saturating_sub(j.ncols()).max(1);
        Ok(LinearModel {
            j,
            r,
            r_perp,
            full,
            fold_of: fold_of.to_vec(),
            folds,
            readings_of_point,
            to_um,
            dof,
        })
    }

    /// [`LinearModel::cv_rms_um_base`] alone, without what scoring
    /// candidates needs: the held-out RMS (µm) of the model whose Jacobian
    /// and residuals these are (comparing tracker models needs no more).
    pub fn held_out_rms_um(
        j: &BlockJacobian,
        r: &DVector<f64>,
        fold_of: &[usize],
        n_folds: usize,
        to_mm: &[Matrix3<f64>],
    ) -> Result<f64, Singular> {
        // Each fold's held-out terms in parallel, summed in fold order as
        // one running sum: the same number.
        let terms = (0..n_folds)
            .into_par_iter()
            .map(|f| {
                let (test, _, res) = fold_fit(j, r, fold_of, f)?;
                Ok(test
                    .into_iter()
                    .map(|i| {
                        let a = to_mm[i]
                            * 1e3
                            * Vector3::new(res[3 * i], res[3 * i + 1], res[3 * i + 2]);
                        a.norm_squared()
                    })
                    .collect::<Vec<f64>>())
            })
            .collect::<Result<Vec<_>, Singular>>()?;
        let mut sum = 0.0;
        for t in terms.iter().flatten() {
            sum += t;
        }
        Ok((sum / fold_of.len().max(1) as f64).sqrt())
    }

    pub fn rows(&self) -> usize {
        self.j.nrows()
    }

    pub fn chi2(&self) -> f64 {
        self.r.norm_squared()
    }

    pub fn dof(&self) -> usize {
        self.dof
    }

    pub fn residuals(&self) -> &DVector<f64> {
        &self.r
    }

    /// The fit of `c` to the residuals over all data.
    pub fn fit(&self, c: &Signature) -> Fit {
        fit_with(&self.j, &self.full, &self.r_perp, c)
    }

    /// [`LinearModel::fit`] and the products over every reading it formed.
    pub fn fit_keeping(&self, c: &Signature) -> (Fit, AllProducts) {
        fit_keeping(&self.j, &self.full, &self.r_perp, c)
    }

    /// [`LinearModel::fit`] of each of `cs`, in parallel, in their order: a
    /// run of nested signatures (each [`Signature::narrows`] the one before:
    /// a station's steps at later and later times, a reflector's shift from
    /// later and later stations) as one chain ([`fit_nested`], equal to the
    /// fits one by one to round-off), every other signature on its own.
    pub fn fit_each(&self, cs: &[&Signature]) -> Vec<Fit> {
        self.fit_runs(cs, |c| self.fit(c), |fit| fit)
    }

    /// [`LinearModel::fit_each`], each fit with the products over every
    /// reading it formed, where it formed them (a chain's fits have none):
    /// a candidate's held-out RMS ([`LinearModel::cv_rms_um_given`]) need
    /// not form them again.
    pub fn fit_each_keeping(&self, cs: &[&Signature]) -> Vec<(Fit, Option<AllProducts>)> {
        self.fit_runs(
            cs,
            |c| {
                let (fit, all) = self.fit_keeping(c);
                (fit, Some(all))
            },
            |fit| (fit, None),
        )
    }

    /// [`LinearModel::fit_each`]'s runs, a lone signature fitted by `lone`,
    /// a chain's fits passed through `chained`: a caller that does not keep
    /// the products never holds them (the localisation's ~127 broad bases
    /// at once would be ~100 MB at 24 000 readings).
    fn fit_runs<T: Send>(
        &self,
        cs: &[&Signature],
        lone: impl Fn(&Signature) -> T + Sync,
        chained: impl Fn(Fit) -> T + Sync,
    ) -> Vec<T> {
        let mut runs: Vec<std::ops::Range<usize>> = Vec::new();
        for (i, c) in cs.iter().enumerate() {
            match runs.last_mut() {
                Some(run) if c.narrows(cs[i - 1]) => run.end = i + 1,
                _ => runs.push(i..i + 1),
            }
        }
        runs.par_iter()
            .map(|run| match run.len() {
                1 => vec![lone(cs[run.start])],
                _ => fit_nested(&self.j, &self.full, &self.r_perp, &cs[run.clone()])
                    .into_iter()
                    .map(&chained)
                    .collect(),
            })
            .collect::<Vec<_>>()
            .into_iter()
            .flatten()
            .collect()
    }

    /// Baarda's w-test of every reading coordinate ([`snooping`]) against
    /// the base model with the columns of `members` fitted beside it.
    pub fn w_tests(&self, members: &Signature) -> Vec<[WTest; 3]> {
        let n_read = self.fold_of.len();
        if members.k == 0 {
            return snooping::w_tests(&self.j, &self.full, self.r_perp.as_slice(), n_read, None);
        }
        let k = members.k;
        let pc = sparse::project_out_rows(&self.j, &self.full, &members.dense_rows(self.rows()), k);
        let pcm = DMatrix::from_row_slice(self.rows(), k, &pc);
        let gram = pcm.tr_mul(&pcm);
        let scale = members.column_scale(|_| true);
        let mut ridged = gram.clone();
        for i in 0..k {
            ridged[(i, i)] += 1e-10 * scale.max(1e-300);
        }
        let Some(inverse) = ridged.try_inverse() else {
            return snooping::w_tests(&self.j, &self.full, self.r_perp.as_slice(), n_read, None);
        };
        let beta = &inverse * pcm.tr_mul(&self.r_perp);
        let v = &self.r_perp - &pcm * beta;
        let absorbed = Absorbed {
            projected: &pc,
            k,
            gram_inverse: &inverse,
        };
        snooping::w_tests(&self.j, &self.full, v.as_slice(), n_read, Some(&absorbed))
    }

    /// Root mean square of the held-out residuals in µm of the base model
    /// (for the model's own residuals).
    pub fn cv_rms_um_base(&self) -> f64 {
        let sum: f64 = self.folds.iter().map(|f| f.base_sum).sum();
        (sum / self.fold_of.len().max(1) as f64).sqrt()
    }

    /// Root mean square of the held-out residuals in µm with `c` added to
    /// the model, for the model's own residuals.
    pub fn cv_rms_um(&self, c: &Signature) -> f64 {
        self.cv_rms_um_given(c, None)
    }

    /// [`LinearModel::cv_rms_um`] from `c`'s products over every reading
    /// where its fit formed them already ([`LinearModel::fit_keeping`]),
    /// the same numbers.
    pub fn cv_rms_um_given(&self, c: &Signature, all: Option<&AllProducts>) -> f64 {
        // The products over every reading once; a fold's training share is
        // them less its held-out readings' (a fifth of the readings per
        // fold instead of four fifths). `ctx` depends on the fold's
        // residuals: it is summed over the training readings themselves
        // (neither the whole products' nor the held-out ones' is read).
        let own;
        let all = match all {
            Some(AllProducts(all)) => all,
            None => {
                own = products(&self.j, c, None, |_| true);
                &own
            }
        };
        let c_rows: Vec<(usize, &[f64])> = c.blocks().collect();
        // Each fold's part is its own (its sums in its own order): the
        // folds in parallel — a broad candidate was one thread's work
        // while the other waited — and the parts summed in fold order,
        // the same number.
        let parts: Vec<f64> = (0..self.folds.len())
            .into_par_iter()
            .map(|fi| self.cv_part(c, all, &c_rows, fi))
            .collect();
        let mut sum = 0.0;
        for part in parts {
            sum += part;
        }
        (sum.max(0.0) / self.fold_of.len().max(1) as f64).sqrt()
    }

    /// Fold `fi`'s sum of squared held-out residuals (µm²) with `c` added
    /// ([`LinearModel::cv_rms_um`]); `all`: `c`'s products over every
    /// reading, `c_rows`: its blocks.
    fn cv_part(&self, c: &Signature, all: &Products, c_rows: &[(usize, &[f64])], fi: usize) -> f64 {
        let f = &self.folds[fi];
        let train = |i: usize| self.fold_of[i] != fi;
        let pr = all.less(&products(&self.j, c, None, |i| !train(i)), c, &f.res, train);
        let (gram, v) = pr.projected_gram(&f.factor);
        let (bc, _) = lstsq(&gram, &pr.ctx, c.column_scale(train));
        // The base fit moves by −δ, δ = N_f⁻¹·u·β_c.
        let d_a = f.factor.solve_schur(&(&v * &bc));
        let mut part = f.base_sum + 2.0 * d_a.dot(&f.h_k) + d_a.dot(&(&f.g_k * &d_a));
        // Held-out readings where more than K_i·δ_A changes: those the
        // candidate touches, and those of reflectors whose fit it moves.
        let mut extra: Vec<usize> = c.readings.iter().copied().filter(|&i| !train(i)).collect();
        // Per position the candidate touches, `H_XX⁻¹·u_x·β_c`: the same
        // product for each of its readings, formed once (and found by
        // index, not by a search per reading).
        let mut shift_of: Vec<Option<Vector3<f64>>> = Vec::new();
        if !pr.u_x.is_empty() {
            shift_of = vec![None; self.j.points()];
        }
        for (p, ux) in &pr.u_x {
            let w = times_3(|a, col| ux[(a, col)], &bc);
            shift_of[*p] = Some(f.factor.point_inverse(*p) * w);
            extra.extend(self.readings_of_point[*p].iter().filter(|&&i| !train(i)));
        }
        ascending_once(&mut extra, self.fold_of.len());
        // `W_pᵀ·δ_A` per position, shared by its readings' `K_i·δ_A`.
        let mut wd_of: Vec<Option<Vector3<f64>>> = Vec::new();
        if !extra.is_empty() {
            wd_of = vec![None; self.j.points()];
        }
        // `c`'s blocks walked beside the ascending readings (a search per
        // reading before).
        let mut next_row = 0;
        for i in extra {
            let a = Vector3::new(f.res[3 * i], f.res[3 * i + 1], f.res[3 * i + 2]);
            let kd = k_times(&self.j, &f.factor, i, &d_a, &mut wd_of);
            let mut s = Vector3::zeros();
            if let Some((p, jx)) = self.j.point_of(i)
                && let Some(Some(shift)) = shift_of.get(p)
            {
                s += crate::calibrate::sparse::part3_mul(jx, shift);
            }
            while next_row < c_rows.len() && c_rows[next_row].0 < i {
                next_row += 1;
            }
            if let Some(&(r, ci)) = c_rows.get(next_row)
                && r == i
            {
                s -= times_3(|a, col| ci[a * c.k + col], &bc);
            }
            let l = self.to_um[i];
            let base = l * (a + kd);
            part += (base + l * s).norm_squared() - base.norm_squared();
        }
        part
    }

    /// Root mean square of the held-out residuals in µm of the base model
    /// for each of the `k` residual vectors `r` holds (row-major: a
    /// residual's `k` values side by side; each with `J`'s span removed),
    /// refitting each fold.
    fn cv_rms_um_of(&self, r: &[f64], k: usize) -> Vec<f64> {
        let mut sums = vec![0.0; k];
        let n_read = self.fold_of.len();
        let mut pred = vec![0.0; 3 * k];
        for (fi, f) in self.folds.iter().enumerate() {
            let train = |b: usize| b >= n_read || self.fold_of[b] != fi;
            // The fold's fit to `r` by the corrected semi-normal equations
            // ([`sparse::solve_ls_rows`]), its first solve from the
            // held-out rows alone: `r` is orthogonal to `J`'s columns, so
            // `J_trainᵀ·r = −J_testᵀ·r` (a fifth of the rows instead of
            // four fifths); the correction from the unsquared residual on
            // the training rows removes that identity's round-off.
            let mut y = f
                .factor
                .solve_rows(&self.j.tr_mul_rows(r, k, |b| !train(b)), k);
            y.iter_mut().for_each(|v| *v = -*v);
            // The unsquared residual on the training rows, all the
            // correction reads (the held-out rows are formed below from
            // the corrected fit).
            let mut res = r.to_vec();
            self.j.sub_mul_rows_where(&y, k, &mut res, train);
            let dy = f.factor.solve_rows(&self.j.tr_mul_rows(&res, k, train), k);
            y.iter_mut().zip(dy).for_each(|(a, b)| *a += b);
            for &i in &f.test {
                // The held-out residual: r − J·y on reading i's rows.
                pred.copy_from_slice(&r[3 * i * k..(3 * i + 3) * k]);
                self.j.block_sub_mul_rows(i, &y, k, &mut pred);
                for (c, sum) in sums.iter_mut().enumerate() {
                    let res = Vector3::new(pred[c], pred[k + c], pred[2 * k + c]);
                    *sum += (self.to_um[i] * res).norm_squared();
                }
            }
        }
        sums.into_iter()
            .map(|s| (s / n_read.max(1) as f64).sqrt())
            .collect()
    }

    /// What the held-out RMS (µm) is for noise alone in this geometry, one
    /// value per draw: the base model's cross-validated RMS for each of
    /// `draws`, noise `ε ~ N(0, I)` in units of σ, its base fit removed
    /// (the noise floor is their mean). Draws go through in batches of
    /// [`DRAW_BATCH`] from the first: the same batches, the same numbers,
    /// whether the draws come in one call or in several of multiples of it.
    pub fn noise_floor_draws_um(&self, draws: &[DVector<f64>]) -> Vec<f64> {
        let m = self.j.nrows();
        // Each batch its own values, in draw order whatever the threads:
        // the same numbers on any machine.
        let each: Vec<Vec<f64>> = draws
            .par_chunks(DRAW_BATCH)
            .map(|batch| {
                let k = batch.len();
                let mut x = vec![0.0; m * k];
                for (c, e) in batch.iter().enumerate() {
                    for (i, v) in e.iter().enumerate() {
                        x[i * k + c] = *v;
                    }
                }
                let e_perp = sparse::project_out_rows(&self.j, &self.full, &x, k);
                self.cv_rms_um_of(&e_perp, k)
            })
            .collect();
        each.into_iter().flatten().collect()
    }
}

/// A fold's factorisation. Holding readings out can leave a direction
/// undetermined — with two folds, reflectors left with one training reading
/// each tell nothing of their station's pose — where the full model was
/// determined. The fit is then the damped (ridge) limit of the
/// minimum-norm one: `N + 1e-12·diag(N)`, which moves determined
/// directions by 1e-12 of themselves and holds the undetermined ones at
/// the base solution.
fn fold_factor(n: &Normal) -> Option<Factor> {
    n.factor(0.0).or_else(|| n.factor(FOLD_RIDGE))
}

/// The relative ridge of [`fold_factor`].
const FOLD_RIDGE: f64 = 1e-12;

/// Reading i's `K_i = J_iA − J_iX·H_XX⁻¹·H_XA` on the fold's factor, into
/// `out` (3 × n_a, zero outside `nz`), and its non-zero columns `nz`
/// (ascending; `merged`: scratch space).
fn k_rows(
    j: &BlockJacobian,
    f: &Factor,
    i: usize,
    out: &mut DMatrix<f64>,
    nz: &mut Vec<usize>,
    merged: &mut Vec<usize>,
) {
    for &c in nz.iter() {
        for a in 0..3 {
            out[(a, c)] = 0.0;
        }
    }
    nz.clear();
    for (col, w, part) in j.dense_parts(i) {
        for c in 0..w {
            for a in 0..3 {
                out[(a, col + c)] += part[a * w + c];
            }
            nz.push(col + c);
        }
    }
    let dense = nz.len();
    if let Some((p, jx)) = j.point_of(i) {
        // H_XX⁻¹·H_XA = Wᵀ on the position's columns.
        let (cols, w) = f.point_coupling(p);
        let jx = Matrix3::from_row_slice(jx);
        let t = jx * w.transpose(); // 3 × cols
        for (k, &c) in cols.iter().enumerate() {
            for a in 0..3 {
                out[(a, c)] -= t[(a, k)];
            }
            nz.push(c);
        }
    }
    // The block's parts and the position's columns each ascend as a rule:
    // merged, the order a sort gives, without one per reading.
    let (a, b) = nz.split_at(dense);
    if a.is_sorted() && b.is_sorted() {
        merged.clear();
        let (mut a, mut b) = (a.iter().peekable(), b.iter().peekable());
        while let (Some(&&x), Some(&&y)) = (a.peek(), b.peek()) {
            if x <= y {
                merged.push(x);
                a.next();
            } else {
                merged.push(y);
                b.next();
            }
        }
        merged.extend(a.chain(b));
        std::mem::swap(nz, merged);
    } else {
        nz.sort_unstable();
    }
    nz.dedup();
}

/// `K_i·δ_A` without forming `K_i`; `wd_of` caches each position's
/// `W_pᵀ·δ_A` (the same for every reading of the position).
fn k_times(
    j: &BlockJacobian,
    f: &Factor,
    i: usize,
    d_a: &DVector<f64>,
    wd_of: &mut [Option<Vector3<f64>>],
) -> Vector3<f64> {
    let mut out = [0.0; 3];
    for (col, w, part) in j.dense_parts(i) {
        for a in 0..3 {
            out[a] += (0..w).map(|c| part[a * w + c] * d_a[col + c]).sum::<f64>();
        }
    }
    let mut v = Vector3::from(out);
    if let Some((p, jx)) = j.point_of(i) {
        let wd = *wd_of[p].get_or_insert_with(|| {
            let (cols, w) = f.point_coupling(p);
            let mut wd = Vector3::zeros();
            for (k, &c) in cols.iter().enumerate() {
                for a in 0..3 {
                    wd[a] += w[(k, a)] * d_a[c];
                }
            }
            wd
        });
        v -= crate::calibrate::sparse::part3_mul(jx, &wd);
    }
    v
}

/// `q += Σₓ uₓᵀ·H_XX⁻¹·uₓ` over the positions of `u_x`, each term the
/// numbers nalgebra's `ux.tr_mul(&(H_XX⁻¹ * ux))` gives — `H_XX⁻¹·uₓ` a
/// column at a time from the first column's term, each entry of the form
/// a three-term dot product — written out without the two matrices it
/// allocated per position.
fn add_point_forms(q: &mut DMatrix<f64>, f: &Factor, u_x: &[(usize, DMatrix<f64>)]) {
    let k = q.ncols();
    let mut t = vec![[0.0; 3]; k];
    for (p, ux) in u_x {
        let inv = f.point_inverse(*p);
        for (b, tb) in t.iter_mut().enumerate() {
            let u = [ux[(0, b)], ux[(1, b)], ux[(2, b)]];
            *tb = [0, 1, 2].map(|a| inv[(a, 0)] * u[0] + inv[(a, 1)] * u[1] + inv[(a, 2)] * u[2]);
        }
        for (j, tj) in t.iter().enumerate() {
            for i in 0..k {
                q[(i, j)] += ux[(0, i)] * tj[0] + ux[(1, i)] * tj[1] + ux[(2, i)] * tj[2];
            }
        }
    }
}

/// `M·β` for a 3 × k matrix `M` (`m(a, col)` its entries), summed as
/// nalgebra's product of a `DMatrix` and a vector sums it — from the
/// first column's term, the others added in column order — without the
/// two matrices allocated per reading.
fn times_3(m: impl Fn(usize, usize) -> f64, beta: &DVector<f64>) -> Vector3<f64> {
    Vector3::from_fn(|a, _| {
        let mut s = m(a, 0) * beta[0];
        for (col, b) in beta.iter().enumerate().skip(1) {
            s += m(a, col) * b;
        }
        s
    })
}

/// `list` (readings below `n`) sorted ascending without repeats: by a
/// mark per reading when it holds more than an eighth of them (a broad
/// candidate's, which a sort took `n·log n` for), else by a sort; the same
/// list either way.
fn ascending_once(list: &mut Vec<usize>, n: usize) {
    if list.len() > n / 8 {
        let mut mark = vec![false; n];
        for &i in list.iter() {
            mark[i] = true;
        }
        list.clear();
        list.extend((0..n).filter(|&i| mark[i]));
    } else {
        list.sort_unstable();
        list.dedup();
    }
}

/// `‖(I − J·J⁺)·x‖²`: the part of `x` no combination of `j`'s columns
/// reproduces (zero when `j`'s normal matrix is singular: nothing to test).
pub fn unabsorbed_norm2(j: &BlockJacobian, x: &DVector<f64>) -> f64 {
    Normal::assemble(j, None, |_| true)
        .factor(0.0)
        .map(|f| project_out(j, &f, x).norm_squared())
        .unwrap_or(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small network: 2 dense unknowns (an offset per axis pair), 6
    /// reflectors seen by 3 readings each, 3 rows per reading.
    fn network() -> (BlockJacobian, DMatrix<f64>) {
        crate::calibrate::sparse::random_arrow(6, 0.61, 1.5, true)
    }

    fn projector(j: &DMatrix<f64>) -> DMatrix<f64> {
        let q = j.clone().qr().q();
        DMatrix::identity(j.nrows(), j.nrows()) - &q * q.transpose()
    }

    /// The definition, densely: cross-validated RMS with `c` added.
    fn dense_cv(
        jd: &DMatrix<f64>,
        r: &DVector<f64>,
        c: Option<&DMatrix<f64>>,
        fold_of: &[usize],
        n_folds: usize,
    ) -> f64 {
        let mut sum = 0.0;
        for f in 0..n_folds {
            let train: Vec<usize> = (0..jd.nrows())
                .filter(|&row| fold_of[row / 3] != f)
                .collect();
            let jt = jd.select_rows(&train);
            let p = projector(&jt);
            let rt = r.select_rows(&train);
            let (bc, target) = match c {
                Some(c) => {
                    let ct = c.select_rows(&train);
                    let cp = &p * &ct;
                    let scale = ct
                        .column_iter()
                        .map(|x| x.norm_squared())
                        .fold(0.0, f64::max);
                    let (bc, _) = lstsq(&cp.tr_mul(&cp), &cp.tr_mul(&(&p * &rt)), scale);
                    let target = &rt - &ct * &bc;
                    (Some(bc), target)
                }
                None => (None, rt),
            };
            let beta_b = jt.clone().svd(true, true).solve(&target, 1e-12).unwrap();
            for i in (0..fold_of.len()).filter(|&i| fold_of[i] == f) {
                let rows = [3 * i, 3 * i + 1, 3 * i + 2];
                let mut pred = jd.select_rows(&rows) * &beta_b;
                if let (Some(c), Some(bc)) = (c, &bc) {
                    pred += c.select_rows(&rows) * bc;
                }
                sum += (r.select_rows(&rows) - pred).norm_squared() * 1e6;
            }
        }
        (sum / fold_of.len() as f64).sqrt()
    }

    /// A signature the base model cannot absorb is found exactly; one it
    /// can absorb adds nothing; the sparse cross-validation equals the
    /// dense definition.
    #[test]
    fn projects_out_what_the_base_absorbs_and_matches_the_dense_definition() {
        let (j, jd) = network();
        let m = j.nrows();
        let n_read = m / 3;
        let mut c_new = Signature::new(1);
        for i in 0..n_read {
            for a in 0..3 {
                c_new.add(i, a, 0, ((i * 3 + a) * (i + a) % 7) as f64 - 3.0);
            }
        }
        // Absorbed: a combination of the model's own columns.
        let beta = DVector::from_fn(j.ncols(), |i, _| i as f64 * 0.1);
        let jb = &jd * beta;
        let mut c_abs = Signature::new(1);
        for i in 0..n_read {
            for a in 0..3 {
                c_abs.add(i, a, 0, jb[3 * i + a]);
            }
        }
        let p = projector(&jd);
        let r = &p * (c_new.dense(m) * 0.5).column(0);
        let fold_of: Vec<usize> = (0..n_read).map(|i| (i / 6 + i) % 3).collect();
        let to_mm = vec![Matrix3::identity(); n_read];
        let held_out = LinearModel::held_out_rms_um(&j, &r, &fold_of, 3, &to_mm).unwrap();
        let lm = LinearModel::new(j, r.clone(), &fold_of, 3, to_mm).unwrap();
        // The light path (comparing tracker models) is the same number.
        assert_eq!(held_out, lm.cv_rms_um_base());
        let f = lm.fit(&c_new);
        assert!((f.beta[0] - 0.5).abs() < 1e-9, "{f:?}");
        assert!((f.delta_chi2 - lm.chi2()).abs() < 1e-9 * lm.chi2());
        let g = lm.fit(&c_abs);
        assert!(g.delta_chi2 < 1e-12 * lm.chi2(), "{g:?}");
        // The true signature predicts held-out readings perfectly: to the
        // round-off of the sum of squares, √ε of the base residual, since
        // the candidate's held-out sum is the base sum plus its change.
        assert!(lm.cv_rms_um(&c_new) < 1e-7 * lm.cv_rms_um_base());
        assert!(lm.cv_rms_um_base() > 1.0);
        // Against the definition, for the base model and a partial signature.
        let base = dense_cv(&jd, &r, None, &fold_of, 3);
        assert!(
            (lm.cv_rms_um_base() - base).abs() < 1e-9 * base,
            "{} vs {base}",
            lm.cv_rms_um_base()
        );
        let mut c_part = Signature::new(2);
        for i in (0..n_read).filter(|i| i % 4 == 1) {
            c_part.add(i, 2, 0, 1.0 + i as f64);
            c_part.add(i, 0, 1, (i as f64).sin());
        }
        let want = dense_cv(&jd, &r, Some(&c_part.dense(m)), &fold_of, 3);
        let got = lm.cv_rms_um(&c_part);
        assert!((got - want).abs() < 1e-9 * want, "{got} vs {want}");
        assert!((lm.cv_rms_um_of(r.as_slice(), 1)[0] - base).abs() < 1e-9 * base);
    }

    /// [`products`] as it was, with nalgebra's products and a search of
    /// `u_x` per reading: the reference the written-out one must equal.
    fn products_by_nalgebra(j: &BlockJacobian, c: &Signature, x: &DVector<f64>) -> Products {
        let k = c.k;
        let mut u_a = DMatrix::zeros(j.n_a(), k);
        let mut u_x: Vec<(usize, DMatrix<f64>)> = Vec::new();
        let mut ctc = DMatrix::zeros(k, k);
        let mut ctx = DVector::zeros(k);
        for (i, v) in c.blocks() {
            let ci = DMatrix::from_row_slice(3, k, v);
            ctc += ci.tr_mul(&ci);
            ctx += ci.tr_mul(&x.fixed_rows::<3>(3 * i));
            for (col, w, part) in j.dense_parts(i) {
                let ji = DMatrix::from_row_slice(3, w, part);
                let mut view = u_a.view_mut((col, 0), (w, k));
                view += ji.tr_mul(&ci);
            }
            if let Some((p, part)) = j.point_of(i) {
                let add = DMatrix::from_row_slice(3, 3, part).tr_mul(&ci);
                match u_x.iter_mut().find(|(q, _)| *q == p) {
                    Some((_, m)) => *m += add,
                    None => u_x.push((p, add)),
                }
            }
        }
        Products { u_a, u_x, ctc, ctx }
    }

    /// Issue 34: a broad candidate (every reading, every reflector) made
    /// `products` allocate matrices per reading and search its positions
    /// per reading — quadratic in the reflectors. Written out, every
    /// product is bit for bit nalgebra's, the positions in the same order;
    /// their quadratic form in `S⁻¹` is the two solves' to rounding.
    #[test]
    fn broad_candidate_products_are_nalgebras_bit_for_bit_without_a_search_per_reading() {
        let (j, _) = network();
        let n_read = j.nrows() / 3;
        let mut broad = Signature::new(3);
        for i in 0..n_read {
            for a in 0..3 {
                for col in 0..3 {
                    broad.add(i, a, col, ((7 * i + 3 * a + col) as f64).sin());
                }
            }
        }
        let x = DVector::from_fn(j.nrows(), |r, _| (r as f64 * 0.37).cos());
        // And a basis touching each reading in two of its six columns, on
        // one coordinate (a smooth function's hats): the zero columns
        // skipped, the same numbers.
        let mut hats = Signature::new(6);
        for i in 0..n_read {
            let at = i % 5;
            hats.add(i, i % 3, at, 0.25 + (i as f64 * 0.3).sin());
            hats.add(i, i % 3, at + 1, -0.5 - (i as f64 * 0.7).cos());
        }
        for c in [&broad, &hats] {
            let got = products(&j, c, Some(&x), |_| true);
            let want = products_by_nalgebra(&j, c, &x);
            assert!(want.u_x.len() > 1 && got.u_x.len() == want.u_x.len());
            for ((p, a), (q, b)) in got.u_x.iter().zip(&want.u_x) {
                assert_eq!((p, a), (q, b));
            }
            assert_eq!(got.u_a, want.u_a);
            assert_eq!(got.ctc, want.ctc);
            assert_eq!(got.ctx, want.ctx);
        }
        let got = products(&j, &broad, Some(&x), |_| true);
        let f = Normal::assemble(&j, None, |_| true).factor(0.0).unwrap();
        let v = f.reduce_sparse(&got.u_a, &got.u_x);
        // `Vᵀ·S⁻¹·V` by one triangular solve per column: symmetric to the
        // bit, and the two solves' `Vᵀ·(S⁻¹·V)` to rounding.
        let q = f.schur_quadratic_form(&v);
        assert_eq!(q, q.transpose());
        for a in 0..v.ncols() {
            for b in 0..v.ncols() {
                let two = v.column(a).dot(&f.solve_schur(&v.column(b).into_owned()));
                assert!((q[(a, b)] - two).abs() <= 1e-12 * q[(a, a)].abs().max(q[(b, b)].abs()));
            }
        }
    }

    /// Issue 34: a held-out reading's `C_i·β` and a position's `uₓ·β`
    /// were nalgebra products of a matrix allocated per reading; written
    /// out, they are those products bit for bit.
    #[test]
    fn a_blocks_product_written_out_is_nalgebras_bit_for_bit() {
        for k in 1..7 {
            let m = DMatrix::from_fn(3, k, |a, c| ((5 * a + 3 * c) as f64 * 0.71).sin() * 1e3);
            let beta = DVector::from_fn(k, |c, _| ((c as f64) * 1.3 + 0.2).cos() / 7.0);
            let want = &m * &beta;
            let got = times_3(|a, c| m[(a, c)], &beta);
            assert_eq!(got.as_slice(), want.as_slice(), "k = {k}");
        }
    }

    /// Issue 34: `Σₓ uₓᵀ·H_XX⁻¹·uₓ` allocated two matrices per position;
    /// written out it is nalgebra's sum bit for bit.
    #[test]
    fn point_forms_written_out_are_nalgebras_bit_for_bit() {
        let (j, _) = network();
        let f = Normal::assemble(&j, None, |_| true).factor(0.0).unwrap();
        for k in 1..5 {
            let u_x: Vec<(usize, DMatrix<f64>)> = (0..j.points())
                .rev()
                .map(|p| {
                    let m =
                        DMatrix::from_fn(3, k, |a, c| ((p * 9 + 4 * a + c) as f64 * 0.83).sin());
                    (p, m * 1e2)
                })
                .collect();
            let start = DMatrix::from_fn(k, k, |a, c| (a * k + c) as f64 * 0.1);
            let mut want = start.clone();
            for (p, ux) in &u_x {
                want += ux.tr_mul(&(f.point_inverse(*p) * ux));
            }
            let mut got = start;
            add_point_forms(&mut got, &f, &u_x);
            assert_eq!(got, want, "k = {k}");
        }
    }

    /// Issue 34: the held-out readings a broad candidate moves were sorted
    /// (`n·log n` per fold and candidate); by a mark per reading they come
    /// out the same, ascending and once each.
    #[test]
    fn held_out_readings_in_order_once_by_marks_or_by_a_sort() {
        for (len, n) in [(5, 100), (80, 100), (300, 100)] {
            let list: Vec<usize> = (0..len).map(|i| (i * 37 + 11) % n).collect();
            let mut want = list.clone();
            want.sort_unstable();
            want.dedup();
            let mut got = list;
            ascending_once(&mut got, n);
            assert_eq!(got, want);
        }
    }

    /// Issue 34: a candidate's folds are scored in parallel; the held-out
    /// RMS is the same number on one thread as on several.
    #[test]
    fn held_out_rms_with_a_candidate_is_the_same_on_any_number_of_threads() {
        let (j, jd) = network();
        let n_read = j.nrows() / 3;
        let r = projector(&jd) * DVector::from_fn(j.nrows(), |i, _| ((i * 7) % 5) as f64 - 2.0);
        let fold_of: Vec<usize> = (0..n_read).map(|i| (i / 6 + i) % 3).collect();
        let lm = LinearModel::new(j, r, &fold_of, 3, vec![Matrix3::identity(); n_read]).unwrap();
        let mut c = Signature::new(2);
        for i in (0..n_read).filter(|i| i % 3 != 1) {
            c.add(i, 1, 0, 1.0 + (i as f64).cos());
            c.add(i, 2, 1, (i as f64 * 0.4).sin());
        }
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| lm.cv_rms_um(&c))
        };
        let one = on(1);
        assert!(one > 0.0);
        assert_eq!(one.to_bits(), on(3).to_bits());
    }

    /// Issue 34: a station's steps at later and later times (nested
    /// signatures) fitted as one chain — each segment's sums once, added
    /// up — are each step's own fit, to round-off.
    #[test]
    fn nested_steps_fitted_as_one_chain_are_each_steps_own_fit() {
        let (j, jd) = network();
        let n_read = j.nrows() / 3;
        let r = projector(&jd) * DVector::from_fn(j.nrows(), |i, _| ((i * 7) % 5) as f64 - 2.0);
        let fold_of: Vec<usize> = (0..n_read).map(|i| (i / 6 + i) % 3).collect();
        let lm = LinearModel::new(j, r, &fold_of, 3, vec![Matrix3::identity(); n_read]).unwrap();
        // A step from reading `t0` on, two columns on every coordinate, and
        // a third on every other reading only.
        let step = |t0: usize| {
            let mut c = Signature::new(3);
            for i in t0..n_read {
                for a in 0..3 {
                    c.add(i, a, 0, ((i * 3 + a) as f64 * 0.7).sin());
                    c.add(i, a, 1, 1.0 + ((i + 2 * a) % 4) as f64);
                    if i % 2 == 0 {
                        c.add(i, a, 2, ((i * 5 + a) as f64 * 0.3).cos());
                    }
                }
            }
            c
        };
        let steps: Vec<Signature> = (1..n_read - 2).step_by(2).map(step).collect();
        assert!(steps.len() > 3);
        let chain: Vec<&Signature> = steps.iter().collect();
        assert!(
            chain
                .windows(2)
                .all(|w| w[1].narrows(w[0]) && !w[0].narrows(w[1]))
        );
        let got = lm.fit_each(&chain);
        assert_eq!(got.len(), steps.len());
        let close = |a: f64, b: f64, scale: f64| (a - b).abs() <= 1e-9 * scale.max(1e-300);
        for (g, c) in got.iter().zip(&steps) {
            let want = lm.fit(c);
            assert!(want.delta_chi2 > 0.0);
            assert!(
                close(g.delta_chi2, want.delta_chi2, want.delta_chi2),
                "{g:?} vs {want:?}"
            );
            let b_max = want.beta.iter().fold(0.0f64, |m, b| m.max(b.abs()));
            for (x, y) in g.beta.iter().zip(&want.beta) {
                assert!(close(*x, *y, b_max), "{g:?} vs {want:?}");
            }
            let c_max = want.cov.amax();
            for (x, y) in g.cov.iter().zip(want.cov.iter()) {
                assert!(close(*x, *y, c_max), "{g:?} vs {want:?}");
            }
        }
    }

    /// Issue 34: the noise floor's draws come in two calls (its first
    /// draws, then the rest only when their error asks for them); each
    /// draw's value is the one a single call over all the draws gives, bit
    /// for bit, so a floor that takes every draw is the number it was.
    #[test]
    fn noise_floor_draws_in_two_calls_are_one_calls_bit_for_bit() {
        let (j, jd) = network();
        let n_read = j.nrows() / 3;
        let r = projector(&jd) * DVector::from_fn(j.nrows(), |i, _| ((i * 7) % 5) as f64 - 2.0);
        let fold_of: Vec<usize> = (0..n_read).map(|i| (i / 6 + i) % 3).collect();
        let lm = LinearModel::new(j, r, &fold_of, 3, vec![Matrix3::identity(); n_read]).unwrap();
        let draws: Vec<DVector<f64>> = (0..40)
            .map(|d| DVector::from_fn(lm.rows(), |i, _| ((i * 31 + d * 17) as f64 * 0.7).sin()))
            .collect();
        let all = lm.noise_floor_draws_um(&draws);
        let mut parts = lm.noise_floor_draws_um(&draws[..32]);
        parts.extend(lm.noise_floor_draws_um(&draws[32..]));
        assert_eq!(all.len(), 40);
        assert_eq!(all, parts);
        assert!(all.iter().all(|v| *v > 0.0), "{all:?}");
    }
}
