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

use multiversion::multiversion;
use nalgebra::{
    DMatrix, DVector, DVectorViewMut, Dyn, Matrix3, MatrixXx3, Vector3, linalg::Cholesky,
};
use rayon::prelude::*;

/// Calls `$call` with the const `$K` equal to `$k` for the widths a
/// product's right-hand sides usually have (the free coefficients of a
/// model, a handful of candidate columns), else with `$K = 0` (`$k` at
/// run time). With the width a constant, a row's loop of `k` entries is
/// unrolled and its bounds checks fold: the same operations on every entry
/// in the same order — the same numbers — at a fraction of the loop's
/// bookkeeping, which outweighed the arithmetic at `k = 7` (issue 34).
macro_rules! with_constant_width {
    ($k:expr, $K:ident => $call:expr) => {
        match $k {
            1 => {
                const $K: usize = 1;
                $call
            }
            2 => {
                const $K: usize = 2;
                $call
            }
            3 => {
                const $K: usize = 3;
                $call
            }
            4 => {
                const $K: usize = 4;
                $call
            }
            5 => {
                const $K: usize = 5;
                $call
            }
            6 => {
                const $K: usize = 6;
                $call
            }
            7 => {
                const $K: usize = 7;
                $call
            }
            8 => {
                const $K: usize = 8;
                $call
            }
            9 => {
                const $K: usize = 9;
                $call
            }
            10 => {
                const $K: usize = 10;
                $call
            }
            11 => {
                const $K: usize = 11;
                $call
            }
            12 => {
                const $K: usize = 12;
                $call
            }
            13 => {
                const $K: usize = 13;
                $call
            }
            14 => {
                const $K: usize = 14;
                $call
            }
            15 => {
                const $K: usize = 15;
                $call
            }
            16 => {
                const $K: usize = 16;
                $call
            }
            17 => {
                const $K: usize = 17;
                $call
            }
            18 => {
                const $K: usize = 18;
                $call
            }
            _ => {
                const $K: usize = 0;
                $call
            }
        }
    };
}
pub(crate) use with_constant_width;

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

/// The shape of a residual block [`BlockJacobian::push_grouped`] appends:
/// its rows, up to three parts `(first column, width)` (width 0: no part)
/// and the group it is stored with.
#[derive(Clone, Copy, Debug)]
pub struct BlockShape {
    pub rows: usize,
    pub parts: [(usize, usize); 3],
    pub group: usize,
}

/// Blocks of [`BlockShape`]s laid out as [`BlockJacobian::push_grouped`]
/// stores them, rows, parts and values counted from zero: a fit linearises
/// the same shapes at every iteration, and laying 24 000 readings' blocks
/// out is per-block bookkeeping on one core, so it is done once (issue 34).
#[derive(Clone, Debug)]
pub struct GroupedLayout {
    blocks: Vec<Block>,
    parts: Vec<Part>,
    rows: usize,
    /// Block indices in storage order, and each block's number of values.
    order: Vec<usize>,
    lens: Vec<usize>,
    total: usize,
}

impl GroupedLayout {
    /// Lays out a block per shape, stored by `group` (below `groups`).
    pub fn new(shapes: impl Iterator<Item = BlockShape>, groups: usize) -> GroupedLayout {
        let n = shapes.size_hint().0;
        let (mut blocks, mut parts, mut rows) =
            (Vec::with_capacity(n), Vec::with_capacity(3 * n), 0);
        // Each block's group and number of values; each group's total.
        let mut sized = Vec::with_capacity(n);
        let mut per_group = vec![0usize; groups + 1];
        for shape in shapes {
            let p0 = parts.len();
            let mut len = 0;
            for &(col, width) in shape.parts.iter().filter(|(_, w)| *w > 0) {
                parts.push(Part {
                    col,
                    width,
                    at: len,
                });
                len += shape.rows * width;
            }
            blocks.push(Block {
                row: rows,
                rows: shape.rows,
                parts: (p0, parts.len()),
            });
            rows += shape.rows;
            debug_assert!(shape.group < groups);
            per_group[shape.group + 1] += len;
            sized.push((shape.group, len));
        }
        // Where each group starts, then each block within it.
        for g in 1..=groups {
            per_group[g] += per_group[g - 1];
        }
        for (blk, &(g, len)) in blocks.iter().zip(&sized) {
            per_group[g] += len;
            let start = per_group[g] - len;
            for p in &mut parts[blk.parts.0..blk.parts.1] {
                p.at += start;
            }
        }
        // The blocks in storage order: group by group, in block order.
        let mut first = vec![0usize; groups + 1];
        for &(g, _) in &sized {
            first[g + 1] += 1;
        }
        for g in 1..=groups {
            first[g] += first[g - 1];
        }
        let mut order = vec![0; sized.len()];
        for (b, &(g, _)) in sized.iter().enumerate() {
            order[first[g]] = b;
            first[g] += 1;
        }
        let lens: Vec<usize> = sized.iter().map(|&(_, len)| len).collect();
        GroupedLayout {
            blocks,
            parts,
            rows,
            order,
            total: lens.iter().sum(),
            lens,
        }
    }
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
        BlockJacobian::with_capacity(n_a, n, [0; 3])
    }

    /// [`Self::new`] with room for `[blocks, parts, values]`: a bundle's
    /// Jacobian holds millions of values, which growing by doubling copied
    /// twice over and faulted in page by page (issue 34).
    pub fn with_capacity(
        n_a: usize,
        n: usize,
        [blocks, parts, values]: [usize; 3],
    ) -> BlockJacobian {
        debug_assert_eq!((n - n_a) % 3, 0);
        BlockJacobian {
            n_a,
            n,
            m: 0,
            blocks: Vec::with_capacity(blocks),
            parts: Vec::with_capacity(parts),
            values: Vec::with_capacity(values),
        }
    }

    /// This Jacobian emptied and made [`Self::with_capacity`]`(n_a, n,
    /// room)` again, keeping its storage (grown where `room` asks more):
    /// a bundle's is rebuilt at every linearisation, and refilling memory
    /// already faulted in spares the kernel's zeroing of fresh pages.
    pub fn recycle(mut self, n_a: usize, n: usize, room: [usize; 3]) -> BlockJacobian {
        debug_assert_eq!((n - n_a) % 3, 0);
        let [blocks, parts, values] = room;
        (self.n_a, self.n, self.m) = (n_a, n, 0);
        self.blocks.clear();
        self.parts.clear();
        self.values.clear();
        self.blocks.reserve(blocks);
        self.parts.reserve(parts);
        self.values.reserve(values);
        self
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

    /// Appends a block per shape, in order, with their values zeroed, and
    /// returns each block's values (`rows × width` per part, row-major,
    /// part after part) in block order, to be filled in place — in
    /// parallel, with no copy. The values are *stored* group by group
    /// (blocks of one group in block order, groups ascending): a bundle's
    /// readings come station by station, but the Schur assembly visits
    /// them reflector by reflector, and with the reflector as the group it
    /// reads them from consecutive memory instead of a cache miss per
    /// block (issue 34). Where a value is stored changes no number: every
    /// product still visits the blocks in the order it did.
    pub fn push_grouped(
        &mut self,
        shapes: impl Iterator<Item = BlockShape>,
        groups: usize,
    ) -> Vec<&mut [f64]> {
        self.push_laid_out(&GroupedLayout::new(shapes, groups))
    }

    /// [`Self::push_grouped`] of shapes laid out before.
    pub fn push_laid_out(&mut self, laid: &GroupedLayout) -> Vec<&mut [f64]> {
        let (m0, p0, base) = (self.m, self.parts.len(), self.values.len());
        debug_assert!(laid.parts.iter().all(|p| p.col + p.width <= self.n
            && (p.col + p.width <= self.n_a || (p.col >= self.n_a && p.width == 3))));
        self.blocks.extend(laid.blocks.iter().map(|b| Block {
            row: m0 + b.row,
            rows: b.rows,
            parts: (p0 + b.parts.0, p0 + b.parts.1),
        }));
        self.parts.extend(laid.parts.iter().map(|p| Part {
            at: base + p.at,
            ..*p
        }));
        self.m += laid.rows;
        extend_with_zeros(&mut self.values, laid.total);
        // The storage cut into the blocks' ranges in storage order, then
        // handed out in block order.
        let mut out: Vec<&mut [f64]> = Vec::with_capacity(laid.lens.len());
        out.resize_with(laid.lens.len(), Default::default);
        let mut rest = &mut self.values[base..];
        for &b in &laid.order {
            let (head, tail) = std::mem::take(&mut rest).split_at_mut(laid.lens[b]);
            out[b] = head;
            rest = tail;
        }
        out
    }

    /// Whether every entry is finite (in parallel: millions of values).
    pub fn is_finite(&self) -> bool {
        all_finite(&self.values)
    }

    /// Number of residuals.
    pub fn nrows(&self) -> usize {
        self.m
    }

    /// Number of unknowns.
    pub fn ncols(&self) -> usize {
        self.n
    }

    #[inline]
    fn parts_of(&self, b: &Block) -> impl Iterator<Item = (usize, usize, &[f64])> {
        self.parts[b.parts.0..b.parts.1]
            .iter()
            .map(move |p| (p.col, p.width, &self.values[p.at..p.at + b.rows * p.width]))
    }

    /// `Jᵀ·X` over the blocks `keep` admits, for the `k` columns of `X`
    /// (m × k, row-major: a row's `k` values side by side); n × k, row-major.
    ///
    /// The output's rows are split into ranges of about equal work, filled
    /// in parallel; each range visits every block in order and keeps the
    /// columns that fall in it, so every entry is summed in block order —
    /// the same numbers as one pass, whatever the number of threads.
    pub fn tr_mul_rows(
        &self,
        x: &[f64],
        k: usize,
        keep: impl Fn(usize) -> bool + Sync,
    ) -> Vec<f64> {
        with_constant_width!(k, K => self.tr_mul_rows_of::<K>(x, k, keep))
    }

    /// [`Self::tr_mul_rows`] with `k = K` known at compile time (`K = 0`:
    /// `k` as given).
    fn tr_mul_rows_of<const K: usize>(
        &self,
        x: &[f64],
        k: usize,
        keep: impl Fn(usize) -> bool + Sync,
    ) -> Vec<f64> {
        let k = if K == 0 { k } else { K };
        let mut g = vec![0.0; self.n * k];
        let ranges = self.balanced_column_ranges(tasks_for(k));
        let mut outs: Vec<(usize, usize, &mut [f64])> = Vec::with_capacity(ranges.len());
        let mut rest = g.as_mut_slice();
        for &(lo, hi) in &ranges {
            let (head, tail) = rest.split_at_mut((hi - lo) * k);
            outs.push((lo, hi, head));
            rest = tail;
        }
        outs.into_par_iter()
            .for_each(|(lo, hi, out)| tr_mul_columns::<K>(self, x, k, &keep, (lo, hi), out));
        g
    }

    /// At most `parts` ranges `[lo, hi)` covering the columns in order,
    /// each holding about the same number of Jacobian values.
    fn balanced_column_ranges(&self, parts: usize) -> Vec<(usize, usize)> {
        if parts <= 1 {
            return vec![(0, self.n)];
        }
        // Counted over the blocks on every core (whole numbers: any order
        // gives the same counts).
        let per_col = self
            .blocks
            .par_chunks(4096)
            .map(|blocks| {
                let mut per_col = vec![0usize; self.n];
                for blk in blocks {
                    for p in &self.parts[blk.parts.0..blk.parts.1] {
                        per_col[p.col..p.col + p.width]
                            .iter_mut()
                            .for_each(|w| *w += blk.rows);
                    }
                }
                per_col
            })
            .reduce(
                || vec![0usize; self.n],
                |mut a, b| {
                    a.iter_mut().zip(&b).for_each(|(a, b)| *a += b);
                    a
                },
            );
        let total: usize = per_col.iter().sum();
        let target = total.div_ceil(parts.max(1)).max(1);
        let mut ranges = Vec::with_capacity(parts);
        let (mut lo, mut acc) = (0, 0);
        for (c, w) in per_col.iter().enumerate() {
            acc += w;
            if acc >= target {
                ranges.push((lo, c + 1));
                (lo, acc) = (c + 1, 0);
            }
        }
        // Columns left after the last full range join it (they hold less
        // than a range's share), so there are never more than `parts`.
        let full = ranges.len() == parts;
        match ranges.last_mut() {
            Some(last) if lo < self.n && full => last.1 = self.n,
            None => ranges.push((0, self.n)),
            Some(_) if lo < self.n => ranges.push((lo, self.n)),
            Some(_) => {}
        }
        ranges
    }

    /// `out −= J·Y` for the `k` columns of `Y` (n × k) and `out` (m × k),
    /// both row-major.
    pub fn sub_mul_rows(&self, y: &[f64], k: usize, out: &mut [f64]) {
        self.sub_mul_rows_where(y, k, out, |_| true);
    }

    /// [`BlockJacobian::sub_mul_rows`] on the blocks `keep` admits; the
    /// other blocks' rows of `out` are left as they are (for a sum that
    /// reads only the kept rows next).
    pub fn sub_mul_rows_where(
        &self,
        y: &[f64],
        k: usize,
        out: &mut [f64],
        keep: impl Fn(usize) -> bool + Sync,
    ) {
        // Each block writes its own rows: in parallel, the same numbers.
        let mut rows: Vec<&mut [f64]> = Vec::with_capacity(self.blocks.len());
        let mut rest = out;
        for blk in &self.blocks {
            let (head, tail) = rest.split_at_mut(blk.rows * k);
            rows.push(head);
            rest = tail;
        }
        rows.into_par_iter()
            .enumerate()
            .with_min_len(256)
            .filter(|(b, _)| keep(*b))
            .for_each(|(b, o)| self.block_sub_mul_rows(b, y, k, o));
    }

    /// `out −= J_b·Y`: block `b`'s rows only (`out` is rows × k).
    pub fn block_sub_mul_rows(&self, b: usize, y: &[f64], k: usize, out: &mut [f64]) {
        with_constant_width!(k, K => self.block_sub_mul_rows_of::<K>(b, y, k, out))
    }

    /// [`Self::block_sub_mul_rows`] with `k = K` known at compile time
    /// (`K = 0`: `k` as given).
    fn block_sub_mul_rows_of<const K: usize>(
        &self,
        b: usize,
        y: &[f64],
        k: usize,
        out: &mut [f64],
    ) {
        let k = if K == 0 { k } else { K };
        let blk = &self.blocks[b];
        for (col, w, v) in self.parts_of(blk) {
            for row in 0..blk.rows {
                let o = &mut out[row * k..(row + 1) * k];
                let coefs = &v[row * w..(row + 1) * w];
                // Three columns in one pass over the row, `((o − p₀) − p₁)
                // − p₂`: the sums one pass per column forms, with a third
                // of the loads and stores of `o` (issue 34); the columns
                // left over one at a time.
                let mut triples = coefs.chunks_exact(3);
                for (t, c) in triples.by_ref().enumerate() {
                    let ys = &y[(col + 3 * t) * k..(col + 3 * t + 3) * k];
                    let (y0, rest) = ys.split_at(k);
                    let (y1, y2) = rest.split_at(k);
                    for (((o, y0), y1), y2) in o.iter_mut().zip(y0).zip(y1).zip(y2) {
                        *o = *o - c[0] * y0 - c[1] * y1 - c[2] * y2;
                    }
                }
                let done = w - triples.remainder().len();
                for (a, &coef) in triples.remainder().iter().enumerate() {
                    let ya = &y[(col + done + a) * k..(col + done + a + 1) * k];
                    for (o, x) in o.iter_mut().zip(ya) {
                        *o -= coef * x;
                    }
                }
            }
        }
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

    /// The columns of the dense part block `b` touches that `seen` has not
    /// marked yet, appended to `out` and marked.
    fn new_dense_cols(&self, b: &Block, seen: &mut [bool], out: &mut Vec<usize>) {
        for p in &self.parts[b.parts.0..b.parts.1] {
            if p.col < self.n_a {
                let cols = p.col..p.col + p.width;
                for (c, seen) in cols.clone().zip(&mut seen[cols]) {
                    if !std::mem::replace(seen, true) {
                        out.push(c);
                    }
                }
            }
        }
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

    /// The eliminated position block `b` touches and its part there
    /// (`rows × 3`, row-major), if any: [`Self::block_point`] and
    /// [`Self::point_part`] in one scan of the block's parts, the values
    /// sliced for that part alone (the diagnosis asks it per reading of
    /// every candidate).
    pub fn point_of(&self, b: usize) -> Option<(usize, &[f64])> {
        let blk = &self.blocks[b];
        self.parts[blk.parts.0..blk.parts.1]
            .iter()
            .find(|p| p.col >= self.n_a)
            .map(|p| {
                let values = &self.values[p.at..p.at + blk.rows * p.width];
                ((p.col - self.n_a) / 3, values)
            })
    }

    /// Block `b`'s parts on the dense part: `(first column, width, values)`.
    pub fn dense_parts(&self, b: usize) -> impl Iterator<Item = (usize, usize, &[f64])> {
        let blk = &self.blocks[b];
        self.parts_of(blk).filter(|(c, _, _)| *c < self.n_a)
    }
}

/// One eliminated position's share of the normal equations.
#[derive(Clone, Debug)]
struct PointBlock {
    /// The dense-part columns its blocks touch, ascending.
    cols: Vec<usize>,
    /// `H_AX` on those columns: one row of three per column.
    h_ax: Vec<[f64; 3]>,
    h_xx: Matrix3<f64>,
    /// Its three entries of `Jᵀr`.
    g_x: [f64; 3],
    /// Whether any admitted block touches it.
    seen: bool,
}

/// Parallel assembly and factorisation split the positions into this many
/// chunks: fixed, so that the sums do not depend on the thread count.
const CHUNKS: usize = 16;

/// Rows `lo..hi` of `Jᵀ·X` ([`BlockJacobian::tr_mul_rows`], `k = K` when
/// `K > 0`) into `out`, over the blocks `keep` admits in order. Compiled
/// also for wider vectors, chosen at run time (a row of `X`'s `k` columns
/// is what they widen): the same sums in the same order (Rust never fuses
/// a multiply and an add; issue 34).
#[multiversion(targets("x86_64+avx512f+avx512vl", "x86_64+avx2+fma"))]
fn tr_mul_columns<const K: usize>(
    j: &BlockJacobian,
    x: &[f64],
    k: usize,
    keep: &impl Fn(usize) -> bool,
    (lo, hi): (usize, usize),
    out: &mut [f64],
) {
    let k = if K == 0 { k } else { K };
    for (b, blk) in j.blocks.iter().enumerate() {
        if !keep(b) {
            continue;
        }
        for (col, w, v) in j.parts_of(blk) {
            let (a0, a1) = (lo.max(col), hi.min(col + w));
            if blk.rows == 3 {
                // A reading's three rows in one pass over each output
                // row: `((o + p₀) + p₁) + p₂`, the sum the row-by-row
                // passes below form (issue 34).
                let xb = &x[blk.row * k..(blk.row + 3) * k];
                let (x0, rest) = xb.split_at(k);
                let (x1, x2) = rest.split_at(k);
                for c in a0..a1 {
                    let (c0, c1, c2) = (v[c - col], v[w + c - col], v[2 * w + c - col]);
                    let o = &mut out[(c - lo) * k..(c - lo + 1) * k];
                    for (((o, x0), x1), x2) in o.iter_mut().zip(x0).zip(x1).zip(x2) {
                        *o = *o + c0 * x0 + c1 * x1 + c2 * x2;
                    }
                }
                continue;
            }
            for row in 0..blk.rows {
                let xr = &x[(blk.row + row) * k..(blk.row + row + 1) * k];
                for c in a0..a1 {
                    let coef = v[row * w + c - col];
                    let o = &mut out[(c - lo) * k..(c - lo + 1) * k];
                    for (o, x) in o.iter_mut().zip(xr) {
                        *o += coef * x;
                    }
                }
            }
        }
    }
}

/// [`Factor::solve_rows`]' reduction of the dense part's right-hand side,
/// `b_A −= Σ W_x·b_x`, on its rows from `lo` (`out`, `k = K` columns when
/// `K > 0`), `rx` the positions' rows of the right-hand side: every row
/// summed in position order. Compiled also for wider vectors, chosen at
/// run time: the same sums in the same order (issue 34).
#[multiversion(targets("x86_64+avx512f+avx512vl", "x86_64+avx2+fma"))]
fn reduce_rows<const K: usize>(
    points: &[FactorPoint],
    rx: &[f64],
    k: usize,
    lo: usize,
    out: &mut [f64],
) {
    let k = if K == 0 { k } else { K };
    let hi = lo + out.len() / k;
    for (i, p) in points.iter().enumerate() {
        let rx = &rx[3 * i * k..(3 * i + 3) * k];
        let (r0, r12) = rx.split_at(k);
        let (r1, r2) = r12.split_at(k);
        let first = p.cols.partition_point(|&c| c < lo);
        for (row, &c) in p.cols.iter().enumerate().skip(first) {
            if c >= hi {
                break;
            }
            let w = [p.w[(row, 0)], p.w[(row, 1)], p.w[(row, 2)]];
            let o = &mut out[(c - lo) * k..(c - lo + 1) * k];
            for (((o, x0), x1), x2) in o.iter_mut().zip(r0).zip(r1).zip(r2) {
                *o -= w[0] * x0 + w[1] * x1 + w[2] * x2;
            }
        }
    }
}

/// [`Factor::solve_rows`]' back-substitution of one position, `out =
/// H_XX⁻¹·b_x − Wᵀ·x_A` (`k = K` columns when `K > 0`). Compiled also for
/// wider vectors, chosen at run time: the same sums in the same order
/// (issue 34).
#[multiversion(targets("x86_64+avx512f+avx512vl", "x86_64+avx2+fma"))]
fn back_substitute<const K: usize>(
    p: &FactorPoint,
    rx: &[f64],
    xa: &[f64],
    k: usize,
    out: &mut [f64],
) {
    let k = if K == 0 { k } else { K };
    for a in 0..3 {
        let inv = [p.inv[(a, 0)], p.inv[(a, 1)], p.inv[(a, 2)]];
        for col in 0..k {
            out[a * k + col] = inv[0] * rx[col] + inv[1] * rx[k + col] + inv[2] * rx[2 * k + col];
        }
    }
    for (row, &c) in p.cols.iter().enumerate() {
        let xc = &xa[c * k..(c + 1) * k];
        for a in 0..3 {
            let w = p.w[(row, a)];
            for (o, v) in out[a * k..(a + 1) * k].iter_mut().zip(xc) {
                *o -= w * v;
            }
        }
    }
}

/// Adds `blocks`' `JᵀJ` and `Jᵀr` to `acc` ([`Accumulator::add`]), `pb`
/// their position's share. Compiled also for wider vectors, chosen at run
/// time: the products of a reading's columns, each row of `H_AA` one loop
/// over consecutive entries, are what they widen; each entry's sum keeps
/// its order (Rust never fuses a multiply and an add), so every CPU gets
/// the same numbers (issue 34).
#[multiversion(targets("x86_64+avx512f+avx512vl", "x86_64+avx2+fma"))]
fn add_blocks<'a>(acc: &mut Accumulator<'a>, blocks: &[usize], mut pb: Option<&mut PointBlock>) {
    if let Some(pb) = &pb {
        acc.place(pb);
    }
    for &b in blocks {
        acc.add(b, pb.as_deref_mut());
    }
}

/// One chunk's share of the assembly: `H_AA` (column-major, lower
/// triangle: a block's columns ascend, so a row of its products lands in
/// consecutive entries) and the dense part of `Jᵀr`, and the scratch space
/// of a block.
struct Accumulator<'a> {
    j: &'a BlockJacobian,
    r: Option<&'a DVector<f64>>,
    h_aa: Vec<f64>,
    g_a: Vec<f64>,
    /// The block's parts on the dense part: `(first column, width,
    /// values)`, a part's rows side by side.
    dense: Vec<(usize, usize, &'a [f64])>,
    /// One dense column of the block (`rows` values).
    column: Vec<f64>,
    /// The block's position part by columns (`rows` values each), so that
    /// every product with it is one [`dot`] of two contiguous columns.
    x_cols: Vec<f64>,
    /// Per dense column, its row in the `H_AX` of the position being
    /// added ([`Self::place`]): looked up, not searched for, twice per
    /// reading (a binary search each was 2 % of a 24 000-reading run's
    /// time, issue 34).
    slot: Vec<usize>,
}

impl<'a> Accumulator<'a> {
    fn new(j: &'a BlockJacobian, r: Option<&'a DVector<f64>>) -> Accumulator<'a> {
        Accumulator {
            j,
            r,
            h_aa: vec![0.0; j.n_a * j.n_a],
            g_a: vec![0.0; j.n_a],
            dense: Vec::new(),
            column: Vec::new(),
            x_cols: Vec::new(),
            slot: vec![0; j.n_a],
        }
    }

    /// Makes `pb`'s dense columns the ones [`Self::add`] finds rows of
    /// `H_AX` for: to be called before a position's blocks are added.
    fn place(&mut self, pb: &PointBlock) {
        for (i, &c) in pb.cols.iter().enumerate() {
            self.slot[c] = i;
        }
    }

    /// Adds block `b`'s `JᵀJ` and `Jᵀr`; `pb` is its position's share
    /// (`None` for a block on the dense part alone), [`Self::place`]d.
    ///
    /// Every entry receives one [`dot`] of two of the block's columns, as
    /// the plain double loop over column pairs forms it; the products of a
    /// column with a part lying after it are formed side by side
    /// ([`add_products`]) — the same sums, in a loop the compiler
    /// vectorises instead of a scattered update per pair (issue 34). A
    /// reading's block whose parts ascend takes [`Self::add_reading`]
    /// instead: the same sums, without this path's column gathers.
    #[inline(always)]
    fn add(&mut self, b: usize, mut pb: Option<&mut PointBlock>) {
        let (j, n_a) = (self.j, self.j.n_a);
        let blk = &j.blocks[b];
        let rows = blk.rows;
        let res = self.r.map(|r| &r.as_slice()[blk.row..blk.row + rows]);
        self.dense.clear();
        let mut x_part: Option<&[f64]> = None;
        for (col, w, v) in j.parts_of(blk) {
            if col >= n_a {
                x_part = Some(v);
            } else {
                self.dense.push((col, w, v));
            }
        }
        if rows == 3 && self.add_reading(res, x_part, pb.as_deref_mut()) {
            return;
        }
        let mut point = pb.zip(x_part);
        if let Some((_, x)) = point {
            self.x_cols.clear();
            for c in 0..3 {
                self.x_cols.extend((0..rows).map(|k| x[k * 3 + c]));
            }
        }
        for (i, &(col_a, w_a, v_a)) in self.dense.iter().enumerate() {
            let first = h_ax_first(&point, &self.slot, col_a);
            for a in 0..w_a {
                let ga = col_a + a;
                self.column.clear();
                self.column.extend((0..rows).map(|k| v_a[k * w_a + a]));
                let la = self.column.as_slice();
                if let Some(res) = res {
                    self.g_a[ga] += dot(la, res);
                }
                for (i_c, &(col_c, w_c, v_c)) in self.dense.iter().enumerate().skip(i) {
                    // The same part from this column on, or a part after
                    // it: row `ga` of the lower triangle, side by side.
                    let from = if i_c == i { a } else { 0 };
                    if i_c == i || col_a + w_a <= col_c {
                        let at = ga * n_a + col_c;
                        add_products(&mut self.h_aa[at + from..at + w_c], la, v_c, w_c, from);
                    } else {
                        for c in from..w_c {
                            let (lo, hi) = min_max(ga, col_c + c);
                            self.h_aa[lo * n_a + hi] += column_dot(la, v_c, w_c, c);
                        }
                    }
                }
                if let Some((pb, _)) = point.as_mut() {
                    let xc = |c: usize| &self.x_cols[c * rows..(c + 1) * rows];
                    for (c, out) in pb.h_ax[first + a].iter_mut().enumerate() {
                        *out += dot(la, xc(c));
                    }
                }
            }
        }
        if let Some((pb, _)) = point {
            let xc = |c: usize| &self.x_cols[c * rows..(c + 1) * rows];
            for a in 0..3 {
                if let Some(res) = res {
                    pb.g_x[a] += dot(xc(a), res);
                }
                for c in a..3 {
                    let h = dot(xc(a), xc(c));
                    pb.h_xx[(a, c)] += h;
                    if a != c {
                        pb.h_xx[(c, a)] += h;
                    }
                }
            }
        }
    }

    /// [`Self::add`] for a reading's block — three rows whose dense parts
    /// (already in `self.dense`) ascend without overlapping and fit
    /// [`READING_WIDTH`] columns; `false` (nothing added) for any other.
    ///
    /// The block's rows are copied side by side onto the stack once, so
    /// that each column is three loads and each row of its products in
    /// `H_AA` one loop over consecutive entries, with no gather, no
    /// closure and no bounds check per product: the assembly's cost was in
    /// that bookkeeping, not in its ~450 multiply-adds a reading (issue 34).
    /// Every entry receives the very sum [`Self::add`] gives it —
    /// `a₀·x₀ + a₁·x₁ + a₂·x₂`, rows in order — once per block, in block
    /// order: the same numbers, bit for bit.
    #[inline(always)]
    fn add_reading(
        &mut self,
        res: Option<&[f64]>,
        x_part: Option<&[f64]>,
        pb: Option<&mut PointBlock>,
    ) -> bool {
        let n_a = self.j.n_a;
        let mut width = 0;
        for (i, &(col, w, _)) in self.dense.iter().enumerate() {
            let ascends = i == 0 || {
                let (prev, pw, _) = self.dense[i - 1];
                prev + pw <= col
            };
            if !ascends || width + w > READING_WIDTH {
                return false;
            }
            width += w;
        }
        // The usual shapes — the coordinates then a pose, either alone —
        // at widths known at compile time.
        let mut point = pb.zip(x_part);
        let fixed = match *self.dense.as_slice() {
            [(c1, w1, v1), (c2, POSE, v2)] => with_constant_width!(w1, A => {
                self.add_reading_of::<A, POSE>([(c1, v1), (c2, v2)], res, &mut point)
            }),
            [(c1, w1, v1)] => with_constant_width!(w1, A => {
                self.add_reading_of::<A, 0>([(c1, v1), (0, &[])], res, &mut point)
            }),
            _ => false,
        };
        if fixed {
            return true;
        }
        // The rows side by side; each local column's global one, where its
        // part ends, and its row of the position's `H_AX`.
        let mut r = [[0.0; READING_WIDTH]; 3];
        let mut global = [0usize; READING_WIDTH];
        let mut part_end = [0usize; READING_WIDTH];
        let mut h_ax_row = [0usize; READING_WIDTH];
        let mut at = 0;
        for &(col, w, v) in &self.dense {
            for (row, out) in r.iter_mut().enumerate() {
                out[at..at + w].copy_from_slice(&v[row * w..(row + 1) * w]);
            }
            let first = h_ax_first(&point, &self.slot, col);
            for k in 0..w {
                global[at + k] = col + k;
                part_end[at + k] = at + w;
                h_ax_row[at + k] = first + k;
            }
            at += w;
        }
        let [r0, r1, r2] = &r;
        for a in 0..width {
            let (a0, a1, a2) = (r0[a], r1[a], r2[a]);
            let ga = global[a];
            if let Some(res) = res {
                self.g_a[ga] += a0 * res[0] + a1 * res[1] + a2 * res[2];
            }
            // Row `ga` of the lower triangle: this part from column `a`,
            // then each later part whole, each over consecutive entries.
            let mut c = a;
            while c < width {
                let end = part_end[c];
                let at = ga * n_a + global[c];
                let out = &mut self.h_aa[at..at + (end - c)];
                for (((o, x0), x1), x2) in out
                    .iter_mut()
                    .zip(&r0[c..end])
                    .zip(&r1[c..end])
                    .zip(&r2[c..end])
                {
                    *o += a0 * x0 + a1 * x1 + a2 * x2;
                }
                c = end;
            }
            if let Some((pb, x)) = point.as_mut() {
                add_cross(&mut pb.h_ax[h_ax_row[a]], [a0, a1, a2], x);
            }
        }
        if let Some((pb, x)) = point {
            add_position(pb, x, res);
        }
        true
    }

    /// [`Self::add_reading`] for a reading whose dense parts are `A`
    /// columns from `c1` and, when `B > 0`, `B` from `c2 ≥ c1 + A` (the
    /// error-parameter coordinates and a station's pose; a pose alone),
    /// `parts` their `(first column, rows side by side)`.
    ///
    /// With both widths constants every loop below has fixed bounds: the
    /// compiler unrolls them and folds their bounds checks, and no table
    /// of global columns is built per reading — that bookkeeping was most
    /// of the assembly's instructions (issue 34). Every entry receives the
    /// very sum the general path gives it, `a₀·x₀ + a₁·x₁ + a₂·x₂`, once
    /// per block: the same numbers, bit for bit (test).
    #[inline(always)]
    fn add_reading_of<const A: usize, const B: usize>(
        &mut self,
        parts: [(usize, &[f64]); 2],
        res: Option<&[f64]>,
        point: &mut Option<(&mut PointBlock, &[f64])>,
    ) -> bool {
        if A == 0 {
            // The first part's width is not one of the constants.
            return false;
        }
        let [(c1, v1), (c2, v2)] = parts;
        let (p, q) = (rows_of::<A>(v1), rows_of::<B>(v2));
        let f1 = h_ax_first(point, &self.slot, c1);
        self.add_part_of::<A, B>((c1, p), (c2, q), f1, res, point);
        if B > 0 {
            let f2 = h_ax_first(point, &self.slot, c2);
            self.add_part_of::<B, 0>((c2, q), (0, [&[0.0; 0]; 3]), f2, res, point);
        }
        if let Some((pb, x)) = point {
            add_position(pb, x, res);
        }
        true
    }

    /// The products of one part of a reading's block (`W` columns from
    /// `own.0`, its three rows `own.1`): `g_A`, its rows of the lower
    /// triangle — its own part from the diagonal on, then the part after
    /// it whole (`next`, `N` columns) — and its rows of `H_AX` from row
    /// `h_ax_first`.
    #[inline(always)]
    fn add_part_of<const W: usize, const N: usize>(
        &mut self,
        own: (usize, [&[f64; W]; 3]),
        next: (usize, [&[f64; N]; 3]),
        h_ax_first: usize,
        res: Option<&[f64]>,
        point: &mut Option<(&mut PointBlock, &[f64])>,
    ) {
        let n_a = self.j.n_a;
        let ((col, [r0, r1, r2]), (next_col, [s0, s1, s2])) = (own, next);
        for a in 0..W {
            let (a0, a1, a2) = (r0[a], r1[a], r2[a]);
            let ga = col + a;
            if let Some(res) = res {
                self.g_a[ga] += a0 * res[0] + a1 * res[1] + a2 * res[2];
            }
            let row = &mut self.h_aa[ga * n_a..(ga + 1) * n_a];
            let own_row: &mut [f64; W] = (&mut row[col..col + W]).try_into().unwrap();
            for c in a..W {
                own_row[c] += a0 * r0[c] + a1 * r1[c] + a2 * r2[c];
            }
            if N > 0 {
                let next_row: &mut [f64; N] =
                    (&mut row[next_col..next_col + N]).try_into().unwrap();
                for c in 0..N {
                    next_row[c] += a0 * s0[c] + a1 * s1[c] + a2 * s2[c];
                }
            }
            if let Some((pb, x)) = point.as_mut() {
                add_cross(&mut pb.h_ax[h_ax_first + a], [a0, a1, a2], x);
            }
        }
    }
}

/// A reading's part from dense column `col`: its first row of the
/// position's `H_AX` (0 without a position), from `slot`
/// ([`Accumulator::place`]). Forced inline, like the
/// other helpers of the assembly's kernel ([`add_blocks`]): its copy for
/// wider vectors called them, and inlining them took 9 % off the
/// assembly's time (issue 34).
#[inline(always)]
fn h_ax_first(point: &Option<(&mut PointBlock, &[f64])>, slot: &[usize], col: usize) -> usize {
    match point {
        Some((pb, _)) => {
            let row = slot[col];
            debug_assert_eq!(pb.cols.get(row), Some(&col), "not placed");
            row
        }
        None => 0,
    }
}

/// A part's three rows (`W` values each, side by side in `v`) as arrays.
#[inline(always)]
fn rows_of<const W: usize>(v: &[f64]) -> [&[f64; W]; 3] {
    let row = |r: usize| <&[f64; W]>::try_from(&v[r * W..(r + 1) * W]).unwrap();
    [row(0), row(1), row(2)]
}

/// `out += (column a of a reading's block)ᵀ·x`: a row of `H_AX` from the
/// column's three entries `a` and the position's part `x` (row-major).
#[inline(always)]
fn add_cross(out: &mut [f64; 3], a: [f64; 3], x: &[f64]) {
    let [a0, a1, a2] = a;
    for (c, out) in out.iter_mut().enumerate() {
        *out += a0 * x[c] + a1 * x[3 + c] + a2 * x[6 + c];
    }
}

/// A reading's `H_XX` and `g_X` from its position's part `x` (row-major)
/// and its residuals.
#[inline(always)]
fn add_position(pb: &mut PointBlock, x: &[f64], res: Option<&[f64]>) {
    for a in 0..3 {
        let (a0, a1, a2) = (x[a], x[3 + a], x[6 + a]);
        if let Some(res) = res {
            pb.g_x[a] += a0 * res[0] + a1 * res[1] + a2 * res[2];
        }
        for c in a..3 {
            let h = a0 * x[c] + a1 * x[3 + c] + a2 * x[6 + c];
            pb.h_xx[(a, c)] += h;
            if a != c {
                pb.h_xx[(c, a)] += h;
            }
        }
    }
}

/// The columns of a station's pose on the dense part: its rotation `ω`
/// then its position `c`.
const POSE: usize = 6;

/// The widest dense part (error-parameter coordinates and a station's
/// pose) [`Accumulator::add_reading`] holds on the stack: all 18
/// coefficients and a pose fit with room for shape terms; a wider block
/// takes the general path.
const READING_WIDTH: usize = 32;

/// `out[c − from] += la·(column c of v)` for `c` in `from..w`, `v` a
/// part's rows side by side (`la.len()` rows of `w`): each entry the
/// [`dot`] of the two columns, its products summed in row order from the
/// first. A reading's three rows get a loop over the entries with the
/// rows as three slices, which the compiler vectorises.
#[inline]
fn add_products(out: &mut [f64], la: &[f64], v: &[f64], w: usize, from: usize) {
    if let [a0, a1, a2] = *la {
        let (r0, r1, r2) = (&v[from..w], &v[w + from..2 * w], &v[2 * w + from..3 * w]);
        for (((o, x0), x1), x2) in out.iter_mut().zip(r0).zip(r1).zip(r2) {
            *o += a0 * x0 + a1 * x1 + a2 * x2;
        }
    } else {
        for (c, o) in (from..w).zip(out) {
            *o += column_dot(la, v, w, c);
        }
    }
}

/// `la·(column c of v)`, `v` rows of `w` side by side: [`dot`]'s sum.
fn column_dot(la: &[f64], v: &[f64], w: usize, c: usize) -> f64 {
    la.iter().enumerate().map(|(k, a)| a * v[k * w + c]).sum()
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
    ///
    /// The positions are split into a fixed number of chunks ([`CHUNKS`])
    /// assembled in parallel, each with its own share of `H_AA` and of the
    /// dense gradient, added in chunk order: the same sums, in the same
    /// order, whatever the number of threads.
    pub fn assemble(
        j: &BlockJacobian,
        r: Option<&DVector<f64>>,
        keep: impl Fn(usize) -> bool + Sync,
    ) -> Normal {
        let n_a = j.n_a;
        // Each position's admitted blocks, in order; blocks on the dense
        // part alone (gauge lengths between coupled reflectors, their
        // readings and references) apart.
        // (Each block's position found on every core, then counted and
        // placed: a serial pass pushing 24 000 blocks one by one cost
        // milliseconds per linearisation, issue 34.)
        let point_of: Vec<Option<Option<usize>>> = (0..j.blocks.len())
            .into_par_iter()
            .with_min_len(4096)
            .map(|b| keep(b).then(|| j.block_point(b)))
            .collect();
        let mut count = vec![0usize; j.points()];
        for p in point_of.iter().flatten().flatten() {
            count[*p] += 1;
        }
        let mut by_point: Vec<Vec<usize>> = count.into_iter().map(Vec::with_capacity).collect();
        let mut dense_only = Vec::new();
        for (b, p) in point_of.into_iter().enumerate() {
            match p {
                Some(Some(p)) => by_point[p].push(b),
                Some(None) => dense_only.push(b),
                None => {}
            }
        }
        let chunk = by_point.len().div_ceil(CHUNKS).max(1);
        let shares: Vec<(Vec<f64>, Vec<f64>, Vec<PointBlock>)> = by_point
            .par_chunks(chunk)
            .map(|blocks_of| {
                let mut acc = Accumulator::new(j, r);
                // A position's dense columns, each once: its readings
                // share the coordinates and their stations' poses, so
                // marking them leaves a handful to sort, not every
                // reading's (issue 34).
                let mut seen = vec![false; n_a];
                let points = blocks_of
                    .iter()
                    .map(|blocks| {
                        let mut cols = Vec::new();
                        for &b in blocks {
                            j.new_dense_cols(&j.blocks[b], &mut seen, &mut cols);
                        }
                        cols.sort_unstable();
                        for &c in &cols {
                            seen[c] = false;
                        }
                        let mut pb = PointBlock {
                            h_ax: vec![[0.0; 3]; cols.len()],
                            cols,
                            h_xx: Matrix3::zeros(),
                            g_x: [0.0; 3],
                            seen: !blocks.is_empty(),
                        };
                        add_blocks(&mut acc, blocks, Some(&mut pb));
                        pb
                    })
                    .collect();
                (acc.h_aa, acc.g_a, points)
            })
            .collect();
        let mut acc = Accumulator::new(j, r);
        add_blocks(&mut acc, &dense_only, None);
        let h_aa_shares: Vec<&[f64]> = shares.iter().map(|(h, _, _)| h.as_slice()).collect();
        combine_shares(&mut acc.h_aa, n_a, &h_aa_shares, |a, b| *a += b);
        let mut points = Vec::with_capacity(j.points());
        for (_, g_a, pts) in shares {
            acc.g_a.iter_mut().zip(&g_a).for_each(|(a, b)| *a += b);
            points.extend(pts);
        }
        mirror_lower(&mut acc.h_aa, n_a);
        let mut g = DVector::zeros(j.n);
        g.rows_mut(0, n_a).copy_from_slice(&acc.g_a);
        for (i, p) in points.iter().enumerate() {
            g.fixed_rows_mut::<3>(n_a + 3 * i).copy_from_slice(&p.g_x);
        }
        Normal {
            n_a,
            h_aa: DMatrix::from_vec(n_a, n_a, acc.h_aa),
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
            let cross: f64 = p
                .cols
                .iter()
                .zip(&p.h_ax)
                .map(|(&c, h)| d[c] * (h[0] * dx[0] + h[1] * dx[1] + h[2] * dx[2]))
                .sum();
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
        let chunk = self.points.len().div_ceil(CHUNKS).max(1);
        // Each chunk of positions: their inverse blocks and their share of
        // Σ H_AX·H_XX⁻¹·H_XA (lower triangle), subtracted in chunk order.
        let shares: Vec<Option<(Vec<f64>, Vec<FactorPoint>)>> = self
            .points
            .par_chunks(chunk)
            .map(|pts| {
                let mut share = vec![0.0; n_a * n_a];
                let mut factored = Vec::with_capacity(pts.len());
                for group in same_columns(pts) {
                    factored.extend(eliminate(group, lambda, &mut share, n_a)?);
                }
                Some((share, factored))
            })
            .collect();
        let shares: Vec<(Vec<f64>, Vec<FactorPoint>)> =
            shares.into_iter().collect::<Option<_>>()?;
        let mut s = self.h_aa.clone();
        for i in 0..n_a {
            s[(i, i)] += lambda * self.h_aa[(i, i)].max(1e-300);
        }
        let schur_shares: Vec<&[f64]> = shares.iter().map(|(s, _)| s.as_slice()).collect();
        combine_shares(s.as_mut_slice(), n_a, &schur_shares, |a, b| *a -= b);
        let points = shares.into_iter().flat_map(|(_, f)| f).collect();
        mirror_lower(s.as_mut_slice(), n_a);
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

/// How many positions on the same columns [`eliminate`] takes at once.
const GROUP: usize = 4;

/// `pts` cut, in order, into runs of at most [`GROUP`] positions that
/// are seen and on the same columns (every reflector of a hall seen from
/// every station), any other position alone.
fn same_columns(pts: &[PointBlock]) -> impl Iterator<Item = &[PointBlock]> {
    let mut rest = pts;
    std::iter::from_fn(move || {
        let first = rest.first()?;
        let n = if first.seen {
            rest.iter()
                .take(GROUP)
                .take_while(|p| p.seen && p.cols == first.cols)
                .count()
        } else {
            1
        };
        let (group, tail) = rest.split_at(n);
        rest = tail;
        Some(group)
    })
}

/// Eliminates a group of positions (one, or up to [`GROUP`] seen on the
/// same columns: [`same_columns`]): each one's damped inverse block and
/// `W = H_AX·H_XX⁻¹`, with `W·H_XA` added to `share` (column-major, lower
/// triangle: the columns ascend, so the inner loop writes consecutive
/// entries where they are consecutive); `None` when a block is singular.
/// The small products are written out, as they run once per reflector per
/// factorisation.
fn eliminate(
    group: &[PointBlock],
    lambda: f64,
    share: &mut [f64],
    n_a: usize,
) -> Option<Vec<FactorPoint>> {
    let p = &group[0];
    if !p.seen {
        return Some(vec![FactorPoint {
            cols: Vec::new(),
            runs: Vec::new(),
            inv: Matrix3::zeros(),
            w: DMatrix::zeros(0, 3),
        }]);
    }
    let parts = group
        .iter()
        .map(|p| eliminated_parts(p, lambda))
        .collect::<Option<Vec<_>>>()?;
    let mut runs = Vec::new();
    consecutive_runs(&p.cols, &mut runs);
    const _: () = assert!(
        GROUP <= 4,
        "add_updates is dispatched for one to four positions"
    );
    match parts.as_slice() {
        [a] => add_updates::<1>(&[a], &p.cols, &runs, share, n_a),
        [a, b] => add_updates::<2>(&[a, b], &p.cols, &runs, share, n_a),
        [a, b, c] => add_updates::<3>(&[a, b, c], &p.cols, &runs, share, n_a),
        [a, b, c, d] => add_updates::<4>(&[a, b, c, d], &p.cols, &runs, share, n_a),
        _ => unreachable!("groups hold 1 to GROUP positions"),
    }
    Some(
        parts
            .into_iter()
            .map(|e| FactorPoint {
                cols: p.cols.clone(),
                runs: runs.clone(),
                inv: e.inv,
                w: DMatrix::from_fn(e.w.len(), 3, |a, c| e.w[a][c]),
            })
            .collect(),
    )
}

/// One position's share of the elimination: `H_XX⁻¹` (damped), `W` by
/// rows, and `H_AX` by its three columns.
struct Eliminated {
    inv: Matrix3<f64>,
    w: Vec<[f64; 3]>,
    h: [Vec<f64>; 3],
}

fn eliminated_parts(p: &PointBlock, lambda: f64) -> Option<Eliminated> {
    let mut d = p.h_xx;
    for i in 0..3 {
        d[(i, i)] += lambda * p.h_xx[(i, i)].max(1e-300);
    }
    let inv = d.try_inverse()?;
    if !inv.iter().all(|v| v.is_finite()) {
        return None;
    }
    let w = p
        .h_ax
        .iter()
        .map(|h| {
            let mut row = [0.0; 3];
            for (c, out) in row.iter_mut().enumerate() {
                *out = h[0] * inv[(0, c)] + h[1] * inv[(1, c)] + h[2] * inv[(2, c)];
            }
            row
        })
        .collect();
    // `H_AX` by its three columns: a row of the update reads each side by
    // side.
    let h = std::array::from_fn(|c| p.h_ax.iter().map(|hb| hb[c]).collect());
    Some(Eliminated { inv, w, h })
}

/// `share += Σ_g W_g·H_XA,g` over `G` positions on the same `cols`, on the
/// lower triangle, run by run of consecutive columns. Each entry is loaded
/// once, receives the positions' terms `w₀·h₀ + w₁·h₁ + w₂·h₂` one after
/// another in their order, and is stored once: the sums the positions give
/// one at a time, bit for bit, with a `G`-th of the trips through memory —
/// the Schur complement of a 20-station hall is 127 × 127, larger than a
/// core's first-level cache, and each reflector updates all of its lower
/// triangle (issue 34). Compiled also for wider vectors, chosen at run
/// time: the loop over `i` is what they widen, and each entry's sum keeps
/// its order (Rust never fuses a multiply and an add).
#[multiversion(targets("x86_64+avx512f+avx512vl", "x86_64+avx2+fma"))]
fn add_updates<const G: usize>(
    parts: &[&Eliminated; G],
    cols: &[usize],
    runs: &[(usize, usize)],
    share: &mut [f64],
    n_a: usize,
) {
    for a in 0..cols.len() {
        let wa: [[f64; 3]; G] = std::array::from_fn(|g| parts[g].w[a]);
        let row = &mut share[cols[a] * n_a..(cols[a] + 1) * n_a];
        for &(lo, hi) in runs {
            let lo = lo.max(a);
            if lo >= hi {
                continue;
            }
            let out = &mut row[cols[lo]..cols[lo] + hi - lo];
            let hs: [[&[f64]; 3]; G] = std::array::from_fn(|g| {
                let h = &parts[g].h;
                [&h[0][lo..hi], &h[1][lo..hi], &h[2][lo..hi]]
            });
            for (i, o) in out.iter_mut().enumerate() {
                let mut v = *o;
                for g in 0..G {
                    let ([w0, w1, w2], [h0, h1, h2]) = (wa[g], hs[g]);
                    v += w0 * h0[i] + w1 * h1[i] + w2 * h2[i];
                }
                *o = v;
            }
        }
    }
}

/// How much more padded work a dense product over a chunk of positions
/// may do than their own products and still be taken: `matrixmultiply`'s
/// blocked kernel (nalgebra's `*` on matrices wider than five) does ~4× the
/// multiply-adds per cycle of the per-position loops, whose rows are a
/// station's six columns long (issue 34).
const PANEL_GAIN: usize = 3;

/// The union `U` of a chunk of positions' columns (ascending) when one
/// dense product on `U` — `|U|²` entries per position's three columns —
/// costs at most [`PANEL_GAIN`] times the positions' own products (`c²`
/// entries for `c` columns); `None` otherwise. In a hall every station
/// sees nearly every reflector and `U` is each position's own columns; in
/// a network where each reflector is seen from a few of many stations, `U`
/// is mostly padding and the positions go one by one.
fn panel_columns<'a>(cols: impl Iterator<Item = &'a [usize]>, n_a: usize) -> Option<Vec<usize>> {
    let mut seen = vec![false; n_a];
    let (mut exact, mut m) = (0usize, 0usize);
    for c in cols.filter(|c| !c.is_empty()) {
        c.iter().for_each(|&x| seen[x] = true);
        exact += c.len() * c.len();
        m += 1;
    }
    let u: Vec<usize> = (0..n_a).filter(|&c| seen[c]).collect();
    (m > 0 && u.len() * u.len() * m <= PANEL_GAIN * exact).then_some(u)
}

/// A `c × 3` block per position (`value(position, row, column)` on its
/// `cols`), scattered onto the union `u` of their columns side by side:
/// `|u| × 3m`, column-major, zero where a position has no column.
fn scatter(
    u: &[usize],
    n_a: usize,
    cols: &[&[usize]],
    value: impl Fn(usize, usize, usize) -> f64,
) -> DMatrix<f64> {
    let mut at = vec![usize::MAX; n_a];
    for (i, &c) in u.iter().enumerate() {
        at[c] = i;
    }
    let mut out = DMatrix::zeros(u.len(), 3 * cols.len());
    for (j, cj) in cols.iter().enumerate() {
        for (a, &c) in cj.iter().enumerate() {
            for l in 0..3 {
                out[(at[c], 3 * j + l)] = value(j, a, l);
            }
        }
    }
    out
}

/// The maximal ranges `[lo, hi)` of `cols` (ascending) whose columns are
/// consecutive, into `runs` (cleared first: a caller per reading keeps one).
pub fn consecutive_runs(cols: &[usize], runs: &mut Vec<(usize, usize)>) {
    runs.clear();
    let mut lo = 0;
    for i in 1..=cols.len() {
        if i == cols.len() || cols[i] != cols[i - 1] + 1 {
            runs.push((lo, i));
            lo = i;
        }
    }
}

/// One eliminated position in a factorisation.
#[derive(Clone, Debug)]
struct FactorPoint {
    cols: Vec<usize>,
    /// The runs of consecutive columns in `cols` ([`consecutive_runs`]),
    /// kept for [`Factor::point_covariance`].
    runs: Vec<(usize, usize)>,
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
        DVector::from_vec(self.solve_rows(rhs.as_slice(), 1))
    }

    /// `N⁻¹·B` with `B` (n × k) and the result row-major: a row's `k`
    /// values side by side, so every inner loop runs over contiguous
    /// memory.
    pub fn solve_rows(&self, rhs: &[f64], k: usize) -> Vec<f64> {
        with_constant_width!(k, K => self.solve_rows_of::<K>(rhs, k))
    }

    /// [`Self::solve_rows`] with `k = K` known at compile time (`K = 0`:
    /// `k` as given).
    fn solve_rows_of<const K: usize>(&self, rhs: &[f64], k: usize) -> Vec<f64> {
        let k = if K == 0 { k } else { K };
        if k == 0 {
            return Vec::new();
        }
        let n_a = self.n_a;
        // The dense part's right-hand side, reduced: b_A − Σ W_x·b_x.
        // Rows of `b` split into ranges filled in parallel, each visiting
        // the positions in order: every row summed in position order, the
        // same numbers whatever the number of threads.
        // A single right-hand side (the fit's step) splits too once the
        // dense part is wide: its positions × columns pairs are the work,
        // and each task's scan of the positions is small beside its share.
        let mut b = rhs[..n_a * k].to_vec();
        let tasks = if n_a >= SPLIT_DENSE_ROWS {
            rayon::current_num_threads()
        } else {
            tasks_for(k)
        };
        let per = n_a.div_ceil(tasks).max(1);
        b.par_chunks_mut(per * k).enumerate().for_each(|(t, out)| {
            reduce_rows::<K>(&self.points, &rhs[n_a * k..], k, t * per, out);
        });
        let scaled = DMatrix::from_fn(n_a, k, |r, c| b[r * k + c] * self.d[r]);
        let xa = self.chol.solve(&scaled);
        let mut x = vec![0.0; rhs.len()];
        for r in 0..n_a {
            for c in 0..k {
                x[r * k + c] = xa[(r, c)] * self.d[r];
            }
        }
        let (xa, xx) = x.split_at_mut(n_a * k);
        let xa = &*xa;
        // Each position's back-substitution is its own: in parallel, the
        // same numbers.
        let positions = xx.par_chunks_mut(3 * k).zip(self.points.par_iter());
        positions
            .enumerate()
            .with_min_len(64)
            .for_each(|(i, (out, p))| {
                let rx = &rhs[(n_a + 3 * i) * k..(n_a + 3 * i + 3) * k];
                back_substitute::<K>(p, rx, xa, k, out);
            });
        x
    }

    /// `S⁻¹`: the covariance of the dense part (in units of the residuals' variance).
    pub fn dense_covariance(&self) -> DMatrix<f64> {
        // `L⁻ᵀ·L⁻¹`, the identity's columns solved each on its own (as
        // `Cholesky::inverse` solves them one after another): in parallel,
        // the same numbers (issue 34).
        let n = self.n_a;
        let mut inv = DMatrix::identity(n, n);
        inv.as_mut_slice().par_chunks_mut(n.max(1)).for_each(|col| {
            let mut col = DVectorViewMut::from_slice(col, n);
            self.chol.solve_mut(&mut col);
        });
        for (j, col) in inv.column_iter_mut().enumerate() {
            for (i, v) in col.into_iter().enumerate() {
                *v *= self.d[i] * self.d[j];
            }
        }
        inv
    }

    /// Every eliminated position's 3 × 3 covariance ([`Self::point_covariance`]),
    /// given the dense part's covariance `C = v·S⁻¹`: in parallel, a chunk
    /// of positions at a time, each chunk's `Cᵀ·W` one dense product on the
    /// union of its positions' columns where they share most of them
    /// ([`panel_columns`]) — the same sums in another order, equal at
    /// round-off — else position by position. (What the stage reports; no
    /// fit or decision depends on it, so the order may change.)
    pub fn point_covariances(&self, dense_cov: &DMatrix<f64>, v: f64) -> Vec<Matrix3<f64>> {
        let n_a = self.n_a;
        let rows = dense_cov.transpose();
        let chunk = self.points.len().div_ceil(CHUNKS).max(1);
        let per_chunk: Vec<Vec<Matrix3<f64>>> = self
            .points
            .par_chunks(chunk)
            .enumerate()
            .map(|(c, pts)| {
                let cols: Vec<&[usize]> = pts.iter().map(|p| p.cols.as_slice()).collect();
                let Some(u) = panel_columns(cols.iter().copied(), n_a) else {
                    return (c * chunk..c * chunk + pts.len())
                        .map(|i| self.point_covariance(i, &rows, v))
                        .collect();
                };
                let w = scatter(&u, n_a, &cols, |j, a, l| pts[j].w[(a, l)]);
                let c_t = DMatrix::from_fn(u.len(), u.len(), |i, j| rows[(u[i], u[j])]);
                let cw = c_t * &w;
                (0..pts.len())
                    .map(|j| {
                        let (cw_j, w_j) = (cw.columns(3 * j, 3), w.columns(3 * j, 3));
                        let add = Matrix3::from_fn(|k, l| cw_j.column(k).dot(&w_j.column(l)));
                        pts[j].inv * v + add
                    })
                    .collect()
            })
            .collect();
        per_chunk.into_iter().flatten().collect()
    }

    /// The 3 × 3 covariance of eliminated position `i`, given the dense
    /// part's covariance `C = v·S⁻¹` with variance factor `v` by its rows
    /// (`dense_cov_rows = Cᵀ`, so that a row of `C` is contiguous):
    /// `v·H_XX⁻¹ + Wᵀ·C·W` with `W = H_AX·H_XX⁻¹` (the Schur blocks).
    pub fn point_covariance(
        &self,
        i: usize,
        dense_cov_rows: &DMatrix<f64>,
        v: f64,
    ) -> Matrix3<f64> {
        let p = &self.points[i];
        let n = p.cols.len();
        // `C·W` on the position's columns, a row of `C` at a time: each
        // entry summed over the columns in order. The row's entries on the
        // position's columns are gathered first (a copy per run of
        // consecutive columns), so that an entry's three products go in one
        // loop over contiguous memory: a run is a station's six pose
        // columns, too short a loop to pay (issue 34).
        let mut cw: [Vec<f64>; 3] = std::array::from_fn(|_| vec![0.0; n]);
        let mut row_at = vec![0.0; n];
        for (a, &ca) in p.cols.iter().enumerate() {
            let row = dense_cov_rows.column(ca);
            let row = row.as_slice();
            for &(lo, hi) in &p.runs {
                row_at[lo..hi].copy_from_slice(&row[p.cols[lo]..p.cols[lo] + hi - lo]);
            }
            let (w0, w1, w2) = (p.w[(a, 0)], p.w[(a, 1)], p.w[(a, 2)]);
            let [cw0, cw1, cw2] = &mut cw;
            for (((o0, o1), o2), c) in cw0
                .iter_mut()
                .zip(cw1.iter_mut())
                .zip(cw2.iter_mut())
                .zip(&row_at)
            {
                *o0 += c * w0;
                *o1 += c * w1;
                *o2 += c * w2;
            }
        }
        let mut add = Matrix3::<f64>::zeros();
        for (b, cw_b) in (0..n).map(|b| (b, [cw[0][b], cw[1][b], cw[2][b]])) {
            for (k, cw_bk) in cw_b.iter().enumerate() {
                for l in 0..3 {
                    add[(k, l)] += cw_bk * p.w[(b, l)];
                }
            }
        }
        p.inv * v + add
    }

    /// `wᵀ·S⁻¹·v` pieces for sparse right-hand sides: the dense-part
    /// reduction `u_A − Σ_x W_x·u_x` of a right-hand side given on the
    /// dense part and a few positions.
    pub fn reduce_sparse(&self, u_a: &DMatrix<f64>, u_x: &[(usize, DMatrix<f64>)]) -> DMatrix<f64> {
        let mut v = u_a.clone();
        let n = v.nrows();
        for (i, ux) in u_x {
            let p = &self.points[*i];
            // `W`'s three columns as slices (column-major), walked beside
            // the position's columns: no index checked per product.
            let m = p.cols.len();
            let (w0, rest) = p.w.as_slice().split_at(m);
            let (w1, w2) = rest.split_at(m);
            // `W·uₓ` written out as nalgebra's product of a 3-column
            // matrix forms it (a sum from the first term, in column
            // order), without a matrix allocated per position; a column
            // of `v` at a time (contiguous). A zero column of `uₓ` (a
            // column none of the position's readings touch) takes `±0`
            // off entries that are never `−0` (sums from `+0`): skipped,
            // the same numbers.
            // The position's columns in runs of consecutive ones (its
            // stations' poses, the error parameters; kept with its factor):
            // a run's entries of `v` are contiguous, as are its values of
            // `W`, so the products go several entries at a time — each
            // entry the same sum, taken off once.
            for col in 0..v.ncols() {
                let u = [ux[(0, col)], ux[(1, col)], ux[(2, col)]];
                if u == [0.0; 3] {
                    continue;
                }
                let out = &mut v.as_mut_slice()[col * n..(col + 1) * n];
                for &(lo, hi) in &p.runs {
                    let out = &mut out[p.cols[lo]..p.cols[lo] + hi - lo];
                    let (w0, w1, w2) = (&w0[lo..hi], &w1[lo..hi], &w2[lo..hi]);
                    for (((o, a), b), d) in out.iter_mut().zip(w0).zip(w1).zip(w2) {
                        *o -= a * u[0] + b * u[1] + d * u[2];
                    }
                }
            }
        }
        v
    }

    /// `Vᵀ·S⁻¹·V`, the quadratic form of the dense part's inverse, as the
    /// Gram matrix of `L⁻¹·D·V` (`S = D⁻¹·L·Lᵀ·D⁻¹`): one triangular solve
    /// per column instead of the two of `S⁻¹·V` followed by a product (the
    /// back-substitution was a third of a candidate's cost), and symmetric
    /// to the last bit. What every candidate's and every reading's
    /// projection (`CᵀP⊥C`, the hat matrix's blocks) is made of.
    pub fn schur_quadratic_form(&self, v: &DMatrix<f64>) -> DMatrix<f64> {
        let w = self.whitened(v.clone());
        w.tr_mul(&w)
    }

    /// `L⁻¹·D·V` (`S = D⁻¹·L·Lᵀ·D⁻¹`, so `S⁻¹ = (L⁻¹·D)ᵀ·(L⁻¹·D)`): the
    /// one triangular solve both a quadratic form of `S⁻¹`
    /// ([`Factor::schur_quadratic_form`]) and the whitened factor itself
    /// (`V = I`, [`leverages`]) are made of.
    fn whitened(&self, mut v: DMatrix<f64>) -> DMatrix<f64> {
        for mut c in v.column_iter_mut() {
            c.component_mul_assign(&self.d);
        }
        self.chol
            .l_dirty()
            .solve_lower_triangular_unchecked_mut(&mut v);
        v
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

/// `J_i·N⁻¹·J_iᵀ` of each of the first `readings` blocks (three rows
/// each): the diagonal blocks of the hat matrix, the share of a reading's
/// own residuals the fit absorbs. One minus it is the reading's redundancy
/// (Baarda's `Q_vv` in units of the a-priori variance).
///
/// With the reflector eliminated, `J_i·N⁻¹·J_iᵀ = vᵢᵀ·S⁻¹·vᵢ +
/// X_i·H_XX⁻¹·X_iᵀ`, `vᵢ = A_iᵀ − W_p·X_iᵀ` (`A_i`, `X_i` the reading's
/// dense and position parts, `W_p = H_AX·H_XX⁻¹` of its reflector). With
/// `S⁻¹ = Mᵀ·M`, `M = L⁻¹·D` formed once, `M·vᵢ = M·A_iᵀ − (M·W_p)·X_iᵀ`:
/// `M·W_p` once per reflector, `M·A_iᵀ` from the few columns of `M` the
/// reading's station and error parameters touch — about `16·3·n_A`
/// products per reading instead of three triangular solves (`3·n_A²/2`).
/// The network's size does not enter.
pub fn leverages(j: &BlockJacobian, f: &Factor, readings: usize) -> Vec<Matrix3<f64>> {
    let n_a = j.n_a;
    let m = f.whitened(DMatrix::identity(n_a, n_a));
    let m_w: Vec<MatrixXx3<f64>> = f
        .points
        .par_iter()
        .map(|p| {
            let mut z = MatrixXx3::zeros(n_a);
            for (k, &c) in p.cols.iter().enumerate() {
                for a in 0..3 {
                    z.column_mut(a).axpy(p.w[(k, a)], &m.column(c), 1.0);
                }
            }
            z
        })
        .collect();
    (0..readings)
        .into_par_iter()
        .map(|i| {
            let mut y = MatrixXx3::zeros(n_a);
            for (col, w, part) in j.dense_parts(i) {
                for r in 0..3 {
                    for c in 0..w {
                        y.column_mut(r)
                            .axpy(part[r * w + c], &m.column(col + c), 1.0);
                    }
                }
            }
            match (j.block_point(i), j.point_part(i)) {
                (Some(p), Some(part)) => {
                    let x = Matrix3::from_row_slice(part);
                    y -= &m_w[p] * x.transpose();
                    y.tr_mul(&y) + x * f.points[p].inv * x.transpose()
                }
                _ => y.tr_mul(&y),
            }
        })
        .collect()
}

/// `v` grown by `n` zeros, written in parallel. A Jacobian's storage is
/// tens of megabytes, and the kernel zeroes a fresh page when it is first
/// written: on every core this way, not on one (issue 34).
pub fn extend_with_zeros(v: &mut Vec<f64>, n: usize) {
    v.par_extend(rayon::iter::repeat_n(0.0, n));
}

/// `x − J·N⁻¹·Jᵀ·x`: what of `x` no combination of `J`'s columns
/// reproduces, by the corrected semi-normal equations (see the module doc).
pub fn project_out(j: &BlockJacobian, f: &Factor, x: &DVector<f64>) -> DVector<f64> {
    DVector::from_vec(project_out_rows(j, f, x.as_slice(), 1))
}

/// [`project_out`] for the `k` columns of `x` (m × k) at once: one pass
/// over the blocks serves every column, which is what makes the
/// identifiability analysis (18 columns) cost a few passes, not 18 × a few.
pub fn project_out_columns(j: &BlockJacobian, f: &Factor, x: &DMatrix<f64>) -> DMatrix<f64> {
    let k = x.ncols();
    let r = project_out_rows_in(j, f, x.transpose().data.into(), k);
    DMatrix::from_row_slice(j.m, k, &r)
}

/// [`project_out`] for the `k` columns of `x` given row-major (a row's
/// `k` values side by side), the result likewise.
pub fn project_out_rows(j: &BlockJacobian, f: &Factor, x: &[f64], k: usize) -> Vec<f64> {
    project_out_rows_in(j, f, x.to_vec(), k)
}

/// [`project_out_rows`] in `x`'s own storage: no copy of a matrix that is
/// not needed afterwards (the identifiability analysis's, 10 MB at 24 000
/// readings).
pub fn project_out_rows_in(j: &BlockJacobian, f: &Factor, x: Vec<f64>, k: usize) -> Vec<f64> {
    let mut r = x;
    // The solve, then one correction from the unsquared residual.
    for _ in 0..2 {
        let y = f.solve_rows(&j.tr_mul_rows(&r, k, |_| true), k);
        j.sub_mul_rows(&y, k, &mut r);
    }
    r
}

/// `N⁻¹·Jᵀ·x` over the blocks `keep` admits (the normal matrix `f`
/// factorises), for the `k` columns of `x` given row-major, refined once
/// from the unsquared residual: the least-squares fit to `x` by the
/// corrected semi-normal equations.
pub fn solve_ls_rows(
    j: &BlockJacobian,
    f: &Factor,
    x: &[f64],
    k: usize,
    keep: impl Fn(usize) -> bool + Sync,
) -> Vec<f64> {
    let mut y = f.solve_rows(&j.tr_mul_rows(x, k, &keep), k);
    let mut res = x.to_vec();
    j.sub_mul_rows(&y, k, &mut res);
    let dy = f.solve_rows(&j.tr_mul_rows(&res, k, &keep), k);
    y.iter_mut().zip(dy).for_each(|(a, b)| *a += b);
    y
}

/// `a·b`, summed in order. A reading's block has three rows: that length
/// gets its own unrolled loop (the same sum, in the same order), as the
/// assembly runs it a hundred times per reading.
#[inline]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    if let (Ok(a), Ok(b)) = (<&[f64; 3]>::try_from(a), <&[f64; 3]>::try_from(b)) {
        return a.iter().zip(b).map(|(x, y)| x * y).sum();
    }
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// How wide a dense part [`Factor::solve_rows`] splits by rows whatever the
/// number of right-hand sides: 96 pose columns of a 16-station hall make
/// a single solve's reduction ~6 M instructions on one core (issue 34).
const SPLIT_DENSE_ROWS: usize = 48;

/// How many parallel tasks a product with `k` right-hand sides is split
/// into: each task visits every block, which pays only when the blocks
/// carry several columns' work. (Any split gives the same numbers.)
fn tasks_for(k: usize) -> usize {
    if k >= 4 {
        rayon::current_num_threads()
    } else {
        1
    }
}

/// Whether every value is finite, checked on every core: a bundle's
/// Jacobian holds millions, a serial scan milliseconds (issue 34).
pub fn all_finite(values: &[f64]) -> bool {
    values
        .par_iter()
        .with_min_len(1 << 14)
        .all(|v| v.is_finite())
}

/// `out` (column-major, `n` rows) combined with each chunk's share in
/// turn by `op`, every entry its shares in chunk order, a column per task:
/// the same numbers on any number of cores. Sixteen shares of a 121-wide
/// dense part are 0.2 M operations, once per assembly and factorisation,
/// that ran on one core while the other waited (issue 34).
fn combine_shares(out: &mut [f64], n: usize, shares: &[&[f64]], op: impl Fn(&mut f64, f64) + Sync) {
    out.par_chunks_mut(n.max(1))
        .enumerate()
        .with_min_len(8)
        .for_each(|(c, col)| {
            for share in shares {
                let share = &share[c * n..(c + 1) * n];
                col.iter_mut().zip(share).for_each(|(a, &b)| op(a, b));
            }
        });
}

fn min_max(a: usize, b: usize) -> (usize, usize) {
    if a <= b { (a, b) } else { (b, a) }
}

/// Copies the lower triangle of a column-major `n × n` matrix onto its
/// upper one.
fn mirror_lower(m: &mut [f64], n: usize) {
    for c in 0..n {
        for r in c + 1..n {
            m[r * n + c] = m[c * n + r];
        }
    }
}

/// The unknowns mix mm, rad and µm-level parameters, so the normal matrix
/// spans many decades; equilibrating it (`D^{-1/2}·S·D^{-1/2}`, D its
/// diagonal) before the Cholesky factorisation keeps the solve accurate.
fn equilibrate(s: &DMatrix<f64>) -> (DMatrix<f64>, DVector<f64>) {
    let d = s.diagonal().map(|v| 1.0 / v.abs().max(1e-300).sqrt());
    let mut e = s.clone();
    // Column by column, down the stored order.
    for (j, col) in e.column_iter_mut().enumerate() {
        for (i, v) in col.into_iter().enumerate() {
            *v *= d[i] * d[j];
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

/// The tests' deterministic stream of values in (−0.5, 0.5): a linear
/// congruential generator from `seed` in (0, 1) — the same numbers on
/// every platform, with no random-number state to seed.
#[cfg(test)]
fn lcg(seed: f64) -> impl FnMut() -> f64 {
    let mut s = seed;
    move || {
        s = (s * 9301.0 + 49297.0) % 233280.0;
        s / 233280.0 - 0.5
    }
}

/// A random-ish arrow-structured problem for tests here and in the
/// diagnosis: 2 dense unknowns, `n_pts` positions seen by three blocks of
/// three rows each (`interleaved`: the blocks cycle through the positions;
/// otherwise each position's three come together), every block touching
/// the dense part and one position; `seed` in (0, 1), `boost` added to the
/// position parts' diagonal. With its dense twin.
#[cfg(test)]
pub(crate) fn random_arrow(
    n_pts: usize,
    seed: f64,
    boost: f64,
    interleaved: bool,
) -> (BlockJacobian, DMatrix<f64>) {
    let n_a = 2;
    let n = n_a + 3 * n_pts;
    let mut j = BlockJacobian::new(n_a, n);
    let mut rows = Vec::new();
    let mut next = lcg(seed);
    for i in 0..3 * n_pts {
        let p = if interleaved { i % n_pts } else { i / 3 };
        let a: Vec<f64> = (0..3 * n_a).map(|_| next()).collect();
        let x: Vec<f64> = (0..9)
            .map(|k| next() + if k % 4 == 0 { boost } else { 0.0 })
            .collect();
        j.push(3, &[(0, &a), (n_a + 3 * p, &x)]);
        for k in 0..3 {
            let mut row = vec![0.0; n];
            row[0] = a[2 * k];
            row[1] = a[2 * k + 1];
            for c in 0..3 {
                row[n_a + 3 * p + c] = x[3 * k + c];
            }
            rows.push(row);
        }
    }
    let jd = DMatrix::from_fn(rows.len(), n, |i, k| rows[i][k]);
    (j, jd)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A random-ish arrow-structured problem: 2 dense unknowns, 4 positions,
    /// blocks touching the dense part and one position each.
    fn problem() -> (BlockJacobian, DMatrix<f64>) {
        random_arrow(4, 0.37, 2.0, false)
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
        let cp = f.point_covariance(2, &f.dense_covariance().transpose(), 1.0);
        assert!((cp - inv.fixed_view::<3, 3>(2 + 6, 2 + 6)).norm() < 1e-10);
    }

    #[test]
    fn products_by_fused_rows_and_columns_are_the_one_at_a_time_products_bit_for_bit() {
        // The same matrix twice: as three-row blocks with parts seven wide
        // (`tr_mul_rows` fuses a block's three rows, `sub_mul_rows` three
        // columns at a time, then one) and as one-row blocks of one-column
        // parts (neither fuses). Every product must agree to the last bit.
        let (n, k) = (16, 7);
        let (mut fused, mut single) = (BlockJacobian::new(n, n), BlockJacobian::new(n, n));
        let mut next = lcg(0.53);
        for b in 0..9 {
            // Two parts on columns apart (0–8 and 8–16), so that both
            // orders visit each entry's terms in the same order.
            let (c0, c1) = (b % 2, 8 + b % 2);
            let (u, v): (Vec<f64>, Vec<f64>) = (0..21).map(|_| (next(), next() * 1e3)).unzip();
            fused.push(3, &[(c0, &u[..]), (c1, &v[..])]);
            for row in 0..3 {
                let mut parts: Vec<(usize, &[f64])> = Vec::new();
                for a in 0..7 {
                    parts.push((c0 + a, &u[row * 7 + a..row * 7 + a + 1]));
                }
                for a in 0..7 {
                    parts.push((c1 + a, &v[row * 7 + a..row * 7 + a + 1]));
                }
                single.push(1, &parts);
            }
        }
        let bits = |m: &[f64]| m.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        let x: Vec<f64> = (0..fused.nrows() * k)
            .map(|i| (i as f64 * 0.9).sin())
            .collect();
        assert_eq!(
            bits(&fused.tr_mul_rows(&x, k, |_| true)),
            bits(&single.tr_mul_rows(&x, k, |_| true))
        );
        let y: Vec<f64> = (0..n * k).map(|i| (i as f64 * 0.4).cos()).collect();
        let (mut a, mut b) = (x.clone(), x);
        fused.sub_mul_rows(&y, k, &mut a);
        single.sub_mul_rows(&y, k, &mut b);
        assert_eq!(bits(&a), bits(&b));
    }

    #[test]
    fn a_reading_assembled_on_the_stack_is_the_general_assembly_bit_for_bit() {
        // Coordinates (n_z columns), three stations (6 each), five
        // reflectors; readings with the coordinates and a pose, the
        // coordinates alone (a fixed station) and a pose alone, each
        // block pushed twice over: its parts in ascending order (the
        // stack paths, `Accumulator::add_reading` — at widths known at
        // compile time up to 18 coordinates, at run time beyond) and
        // backwards (the general path). Both must give the same normal
        // equations to the last bit, with and without residuals.
        for n_z in [1, 4, 7, 18, 20] {
            let (n_st, n_pts) = (3, 5);
            let n_a = n_z + 6 * n_st;
            let n = n_a + 3 * n_pts;
            let (mut fwd, mut bwd) = (BlockJacobian::new(n_a, n), BlockJacobian::new(n_a, n));
            let mut next = lcg(0.37);
            for p in 0..n_pts {
                for (k, st) in [p % n_st, (p + 1) % n_st, p % n_st].into_iter().enumerate() {
                    let z: Vec<f64> = (0..3 * n_z).map(|_| next()).collect();
                    let pose: Vec<f64> = (0..18).map(|_| next() * 1e3).collect();
                    let x: Vec<f64> = (0..9).map(|_| next() + 1.5).collect();
                    let (sc, pc) = (n_z + 6 * st, n_a + 3 * p);
                    let (z, pose, x) = ((0, &z[..]), (sc, &pose[..]), (pc, &x[..]));
                    let parts = match k {
                        0 => vec![z, pose, x],
                        1 => vec![z, x],
                        _ => vec![pose, x],
                    };
                    fwd.push(3, &parts);
                    bwd.push(3, &parts.into_iter().rev().collect::<Vec<_>>());
                }
            }
            let r = DVector::from_fn(fwd.nrows(), |i, _| (i as f64 * 1.3).cos());
            for r in [None, Some(&r)] {
                let (a, b) = (
                    Normal::assemble(&fwd, r, |_| true),
                    Normal::assemble(&bwd, r, |_| true),
                );
                let bits = |m: &[f64]| m.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                assert_eq!(
                    bits(a.h_aa.as_slice()),
                    bits(b.h_aa.as_slice()),
                    "n_z {n_z}"
                );
                assert_eq!(bits(a.g.as_slice()), bits(b.g.as_slice()));
                for (pa, pb) in a.points.iter().zip(&b.points) {
                    assert_eq!(pa.cols, pb.cols);
                    assert_eq!(bits(pa.h_ax.as_flattened()), bits(pb.h_ax.as_flattened()));
                    assert_eq!(bits(pa.h_xx.as_slice()), bits(pb.h_xx.as_slice()));
                }
            }
        }
    }

    /// Issue 34: the assembly forms a column's products with the parts
    /// after it side by side, the elimination and the positions'
    /// covariances a run of consecutive columns at a time. A network whose
    /// reflectors see stations with gaps between their columns, and blocks
    /// whose parts come in any order, against the dense normal equations.
    #[test]
    fn assembly_with_parts_in_any_order_and_columns_with_gaps_matches_the_dense_one() {
        // Dense part: 2 "parameters", then three "stations" of 3 columns.
        let (n_a, n_pts) = (11, 4);
        let n = n_a + 3 * n_pts;
        let mut j = BlockJacobian::new(n_a, n);
        let mut dense = Vec::new();
        let mut next = lcg(0.61);
        for p in 0..n_pts {
            // Reflector p is seen from stations p % 3 and (p + 2) % 3:
            // its columns have a gap; each reading a few times.
            for (k, st) in [p % 3, (p + 2) % 3, p % 3, (p + 2) % 3]
                .into_iter()
                .enumerate()
            {
                let a: Vec<f64> = (0..6).map(|_| next()).collect();
                let b: Vec<f64> = (0..9).map(|_| next()).collect();
                let x: Vec<f64> = (0..9)
                    .map(|i| next() + if i % 4 == 0 { 2.0 } else { 0.0 })
                    .collect();
                let (sc, pc) = (2 + 3 * st, n_a + 3 * p);
                // Every other block lists its parts backwards.
                if k % 2 == 0 {
                    j.push(3, &[(0, &a), (sc, &b), (pc, &x)]);
                } else {
                    j.push(3, &[(pc, &x), (sc, &b), (0, &a)]);
                }
                for r in 0..3 {
                    let mut row = vec![0.0; n];
                    row[..2].copy_from_slice(&a[2 * r..2 * r + 2]);
                    row[sc..sc + 3].copy_from_slice(&b[3 * r..3 * r + 3]);
                    row[pc..pc + 3].copy_from_slice(&x[3 * r..3 * r + 3]);
                    dense.push(row);
                }
            }
        }
        // A fixed "station" would leave columns 8..11 unseen: tie them.
        for c in 8..11 {
            let one = [1.0];
            j.push(1, &[(c, &one)]);
            let mut row = vec![0.0; n];
            row[c] = 1.0;
            dense.push(row);
        }
        let jd = DMatrix::from_fn(dense.len(), n, |i, k| dense[i][k]);
        let f = Normal::assemble(&j, None, |_| true).factor(0.0).unwrap();
        let nd = jd.transpose() * &jd;
        let rhs = DVector::from_fn(n, |i, _| (i as f64 * 0.7).sin());
        let x = f.solve(&rhs);
        let xd = nd.clone().cholesky().unwrap().solve(&rhs);
        assert!((&x - &xd).norm() < 1e-9 * xd.norm(), "{x} vs {xd}");
        let inv = nd.try_inverse().unwrap();
        let rows = f.dense_covariance().transpose();
        for p in 0..n_pts {
            let cp = f.point_covariance(p, &rows, 1.0);
            let o = n_a + 3 * p;
            assert!((cp - inv.fixed_view::<3, 3>(o, o)).norm() < 1e-9 * inv.norm());
        }
    }

    #[test]
    fn leverage_is_the_hat_matrix_block() {
        let (j, jd) = problem();
        let f = Normal::assemble(&j, None, |_| true).factor(0.0).unwrap();
        let hat = &jd * (jd.transpose() * &jd).try_inverse().unwrap() * jd.transpose();
        let all = leverages(&j, &f, 12);
        for (b, h) in all.iter().enumerate() {
            assert!((h - hat.fixed_view::<3, 3>(3 * b, 3 * b)).norm() < 1e-10);
        }
    }

    /// Issue 34: the whitened factor `L⁻¹·D` the leverages use is the
    /// one the quadratic forms of `S⁻¹` are made of (`V = I`), bit for
    /// bit the solve it was: `S⁻¹ = (L⁻¹·D)ᵀ·(L⁻¹·D)` to rounding.
    #[test]
    fn whitened_identity_is_the_whitened_factor_and_squares_to_the_inverse() {
        let (j, _) = problem();
        let f = Normal::assemble(&j, None, |_| true).factor(0.0).unwrap();
        let n_a = j.n_a();
        let mut m = DMatrix::from_diagonal(&f.d);
        f.chol
            .l_dirty()
            .solve_lower_triangular_unchecked_mut(&mut m);
        assert_eq!(f.whitened(DMatrix::identity(n_a, n_a)), m);
        let q = f.schur_quadratic_form(&DMatrix::identity(n_a, n_a));
        assert!((q - f.dense_covariance()).norm() < 1e-10);
    }

    /// Issue 34: `J·Y` taken off the kept blocks' rows only — those
    /// rows as the whole product leaves them, the others untouched.
    #[test]
    fn subtracting_on_kept_blocks_leaves_the_others_and_matches_on_the_kept() {
        let (j, _) = problem();
        let k = 2;
        let y: Vec<f64> = (0..j.ncols() * k).map(|i| (i as f64 * 0.3).sin()).collect();
        let x: Vec<f64> = (0..j.nrows() * k).map(|i| (i as f64 * 0.9).cos()).collect();
        let mut all = x.clone();
        j.sub_mul_rows(&y, k, &mut all);
        let mut some = x.clone();
        j.sub_mul_rows_where(&y, k, &mut some, |b| b % 3 != 0);
        for b in 0..j.blocks.len() {
            let rows = j.blocks[b].row * k..(j.blocks[b].row + j.blocks[b].rows) * k;
            let want = if b % 3 != 0 {
                &all[rows.clone()]
            } else {
                &x[rows.clone()]
            };
            assert_eq!(&some[rows], want, "block {b}");
        }
    }

    /// Regression: splitting the Schur reduction into row ranges of `k`
    /// values each made a chunk size of zero, and rayon panics on it, when
    /// every error parameter is fixed (no column to project).
    #[test]
    fn projecting_no_column_returns_none_instead_of_panicking() {
        let (j, _) = problem();
        let f = Normal::assemble(&j, None, |_| true).factor(0.0).unwrap();
        assert!(f.solve_rows(&[], 0).is_empty());
        let none = DMatrix::zeros(j.nrows(), 0);
        assert_eq!(project_out_columns(&j, &f, &none).shape(), (j.nrows(), 0));
    }

    #[test]
    fn a_recycled_jacobian_is_the_one_built_afresh() {
        // Issue 34: the bundle refills its previous linearisation's
        // Jacobian; nothing of the old one may show, whatever its shape.
        let fill = |j: &mut BlockJacobian| {
            for i in 0..6 {
                let a: Vec<f64> = (0..6).map(|k| (i * 6 + k) as f64 - 7.5).collect();
                let x: Vec<f64> = (0..9)
                    .map(|k| if k % 4 == 0 { 3.0 } else { 0.1 * k as f64 })
                    .collect();
                j.push(3, &[(0, &a), (2 + 3 * (i % 2), &x)]);
            }
        };
        let mut fresh = BlockJacobian::new(2, 8);
        fill(&mut fresh);
        let (old, _) = random_arrow(4, 0.3, 2.0, false);
        assert!(old.ncols() > 8 && old.nrows() > 18);
        let mut recycled = old.recycle(2, 8, [6, 12, 90]);
        fill(&mut recycled);
        assert_eq!(
            (
                recycled.nrows(),
                recycled.ncols(),
                recycled.n_a(),
                recycled.points()
            ),
            (18, 8, 2, 2)
        );
        assert_eq!(recycled.to_dense(), fresh.to_dense());
        let (a, b) = (
            Normal::assemble(&recycled, None, |_| true),
            Normal::assemble(&fresh, None, |_| true),
        );
        let d = DVector::from_fn(8, |i, _| i as f64 - 2.5);
        assert_eq!(a.quadratic(&d), b.quadratic(&d));
    }

    /// The shape of each of `j`'s blocks, grouped by its position.
    fn shapes_of(j: &BlockJacobian) -> impl Iterator<Item = BlockShape> + '_ {
        j.blocks.iter().enumerate().map(|(b, blk)| {
            let mut parts = [(0, 0); 3];
            for (out, p) in parts.iter_mut().zip(&j.parts[blk.parts.0..blk.parts.1]) {
                *out = (p.col, p.width);
            }
            BlockShape {
                rows: blk.rows,
                parts,
                group: j.block_point(b).expect("every block on a position"),
            }
        })
    }

    /// Fills blocks pushed with [`shapes_of`]`(j)` with `j`'s values.
    fn fill_from(j: &BlockJacobian, outs: Vec<&mut [f64]>) {
        for (blk, out) in j.blocks.iter().zip(outs) {
            let values: Vec<f64> = j.parts_of(blk).flat_map(|(_, _, v)| v.to_vec()).collect();
            out.copy_from_slice(&values);
        }
    }

    /// Issue 34: blocks pushed with their values stored position by
    /// position and filled in place are the blocks pushed one by one: the
    /// same matrix, and the same assembly and solve, bit for bit.
    #[test]
    fn blocks_stored_by_group_are_the_blocks_pushed_in_order() {
        let (j, _) = random_arrow(5, 0.43, 2.0, true);
        let mut g = BlockJacobian::new(j.n_a(), j.ncols());
        fill_from(&j, g.push_grouped(shapes_of(&j), j.points()));
        assert_ne!(g.values, j.values, "stored in another order");
        assert_eq!(g.to_dense(), j.to_dense());
        let r = DVector::from_fn(j.nrows(), |i, _| (i as f64 * 1.3).sin());
        let (a, b) = (
            Normal::assemble(&g, Some(&r), |_| true),
            Normal::assemble(&j, Some(&r), |_| true),
        );
        assert_eq!(a.gradient(), b.gradient());
        let d = DVector::from_fn(j.ncols(), |i, _| i as f64 - 4.5);
        assert_eq!(a.quadratic(&d), b.quadratic(&d));
        let (fa, fb) = (a.factor(0.0).unwrap(), b.factor(0.0).unwrap());
        assert_eq!(fa.solve(a.gradient()), fb.solve(b.gradient()));
        assert_eq!(
            g.tr_mul_rows(r.as_slice(), 1, |_| true),
            j.tr_mul_rows(r.as_slice(), 1, |_| true)
        );
    }

    /// Issue 34: a fit lays its readings' blocks out once and pushes that
    /// layout at every linearisation; pushed after other blocks and into a
    /// recycled Jacobian, it is the grouped push of its shapes.
    #[test]
    fn a_layout_pushed_again_is_the_grouped_push_of_its_shapes() {
        let (j, _) = random_arrow(5, 0.43, 2.0, true);
        assert!(j.n_a() > 0);
        let mut grouped = BlockJacobian::new(j.n_a(), j.ncols());
        grouped.push(1, &[(0, &[1.5])]);
        fill_from(&j, grouped.push_grouped(shapes_of(&j), j.points()));
        let laid = GroupedLayout::new(shapes_of(&j), j.points());
        let mut again = BlockJacobian::new(j.n_a(), j.ncols());
        for _ in 0..2 {
            again = again.recycle(j.n_a(), j.ncols(), [0; 3]);
            again.push(1, &[(0, &[1.5])]);
            fill_from(&j, again.push_laid_out(&laid));
            assert_eq!(again.values, grouped.values);
            assert_eq!(again.to_dense(), grouped.to_dense());
        }
        assert_eq!(grouped.nrows(), j.nrows() + 1);
        assert_eq!(grouped.to_dense().rows(1, j.nrows()), j.to_dense());
    }

    /// Issue 34: the dense part's covariance solved column by column in
    /// parallel is `Cholesky::inverse`'s, scaled, bit for bit.
    #[test]
    fn the_covariance_solved_by_columns_is_the_cholesky_inverse() {
        let (j, _) = random_arrow(5, 0.43, 2.0, true);
        let f = Normal::assemble(&j, None, |_| true).factor(0.0).unwrap();
        let mut inv = f.chol.inverse();
        for i in 0..inv.nrows() {
            for k in 0..inv.ncols() {
                inv[(i, k)] *= f.d[i] * f.d[k];
            }
        }
        assert_eq!(f.dense_covariance(), inv);
    }

    /// Issue 34: the chunks' shares combined column by column in parallel
    /// are the serial pass's, entry by entry in chunk order — with values
    /// whose sum depends on that order.
    /// A network in a hall's shape: 4 error coordinates, `stations` poses
    /// (6 columns each) and `n_pts` reflectors, each read three times from
    /// every station `sees(point, station)` admits.
    fn station_network(
        n_pts: usize,
        stations: usize,
        sees: impl Fn(usize, usize) -> bool,
    ) -> (BlockJacobian, DMatrix<f64>) {
        let n_a = 4 + 6 * stations;
        let n = n_a + 3 * n_pts;
        let mut j = BlockJacobian::new(n_a, n);
        let mut rows = Vec::new();
        let mut next = lcg(0.61);
        for p in 0..n_pts {
            for st in (0..stations).filter(|&st| sees(p, st)) {
                let z: Vec<f64> = (0..12).map(|_| next()).collect();
                let pose: Vec<f64> = (0..18).map(|_| next()).collect();
                let x: Vec<f64> = (0..9)
                    .map(|k| next() + if k % 4 == 0 { 2.0 } else { 0.0 })
                    .collect();
                let (c_s, c_x) = (4 + 6 * st, n_a + 3 * p);
                j.push(3, &[(0, &z), (c_s, &pose), (c_x, &x)]);
                for k in 0..3 {
                    let mut row = vec![0.0; n];
                    row[..4].copy_from_slice(&z[4 * k..4 * k + 4]);
                    row[c_s..c_s + 6].copy_from_slice(&pose[6 * k..6 * k + 6]);
                    row[c_x..c_x + 3].copy_from_slice(&x[3 * k..3 * k + 3]);
                    rows.push(row);
                }
            }
        }
        // A little of every column on the diagonal: the poses and the
        // coordinates determined whatever the visibility.
        for c in 0..n_a {
            let mut row = vec![0.0; n];
            row[c] = 1.0;
            j.push(1, &[(c, &[1.0])]);
            rows.push(row);
        }
        (j, DMatrix::from_fn(rows.len(), n, |i, k| rows[i][k]))
    }

    fn max_rel_diff(a: &[f64], b: &[f64]) -> f64 {
        let scale = a.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
        a.iter()
            .zip(b)
            .fold(0.0, |m, (x, y)| m.max((x - y).abs() / scale))
    }

    #[test]
    fn batched_point_covariances_are_the_one_by_one_ones_and_the_dense_inverse() {
        // A hall (every station sees every reflector: chunks as panels) and
        // a sparse network (two of twelve stations each: one by one).
        for (stations, sees) in [
            (
                5,
                Box::new(|_, _| true) as Box<dyn Fn(usize, usize) -> bool>,
            ),
            (12, Box::new(|p, s| s == p % 12 || s == (p * 5 + 1) % 12)),
        ] {
            let (j, jd) = station_network(40, stations, sees);
            let f = Normal::assemble(&j, None, |_| true).factor(0.0).unwrap();
            let dense = f.dense_covariance() * 1.7;
            let batched = f.point_covariances(&dense, 1.7);
            let inv = (jd.transpose() * &jd).try_inverse().unwrap() * 1.7;
            let n_a = j.n_a;
            for (i, b) in batched.iter().enumerate() {
                let one = f.point_covariance(i, &dense.transpose(), 1.7);
                let d = max_rel_diff(one.as_slice(), b.as_slice());
                assert!(d < 1e-12, "position {i}: {d:e}");
                let want = inv
                    .fixed_view::<3, 3>(n_a + 3 * i, n_a + 3 * i)
                    .into_owned();
                assert!(max_rel_diff(want.as_slice(), b.as_slice()) < 1e-9);
            }
        }
    }

    #[test]
    fn a_group_s_updates_are_its_positions_one_at_a_time_bit_for_bit() {
        // Two runs of columns (a gap at 5), as a station not seen leaves.
        let cols: Vec<usize> = (0..5).chain(6..13).collect();
        let n_a = 14;
        let mut runs = Vec::new();
        consecutive_runs(&cols, &mut runs);
        let parts: Vec<Eliminated> = (0..GROUP)
            .map(|g| {
                let v = |a: usize, c: usize| ((g * 131 + a * 17 + c * 7) as f64 * 0.37).sin();
                Eliminated {
                    inv: Matrix3::identity(),
                    w: (0..cols.len())
                        .map(|a| [v(a, 0), v(a, 1), v(a, 2)])
                        .collect(),
                    h: std::array::from_fn(|c| (0..cols.len()).map(|a| v(a + 40, c)).collect()),
                }
            })
            .collect();
        let start: Vec<f64> = (0..n_a * n_a).map(|i| (i as f64 * 0.11).cos()).collect();
        let mut grouped = start.clone();
        add_updates::<4>(
            &[&parts[0], &parts[1], &parts[2], &parts[3]],
            &cols,
            &runs,
            &mut grouped,
            n_a,
        );
        let mut single = start;
        for p in &parts {
            add_updates::<1>(&[p], &cols, &runs, &mut single, n_a);
        }
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&grouped), bits(&single));
    }

    /// Issue 34: the assembly's, the elimination's and the projection's
    /// kernels are compiled also for AVX2 and AVX-512 and chosen at run
    /// time. Whichever this
    /// CPU takes must give the numbers of the plain code, compiled for the
    /// baseline in this test, to the last bit: a wider vector does the same
    /// operations in the same order, and Rust never fuses a multiply and
    /// an add.
    #[test]
    fn kernels_chosen_at_run_time_give_the_baseline_s_numbers_bit_for_bit() {
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        // The elimination's update: each entry of the lower triangle, the
        // positions' terms one after another.
        let cols: Vec<usize> = (0..9).chain(11..30).collect();
        let n_a = 31;
        let mut runs = Vec::new();
        consecutive_runs(&cols, &mut runs);
        let mut next = lcg(0.61);
        let parts: Vec<Eliminated> = (0..3)
            .map(|_| Eliminated {
                inv: Matrix3::identity(),
                w: (0..cols.len()).map(|_| [next(), next(), next()]).collect(),
                h: std::array::from_fn(|_| (0..cols.len()).map(|_| next() * 1e3).collect()),
            })
            .collect();
        let start: Vec<f64> = (0..n_a * n_a).map(|_| next()).collect();
        let mut chosen = start.clone();
        add_updates::<3>(
            &[&parts[0], &parts[1], &parts[2]],
            &cols,
            &runs,
            &mut chosen,
            n_a,
        );
        let mut plain = start;
        for a in 0..cols.len() {
            for c in a..cols.len() {
                let o = &mut plain[cols[a] * n_a + cols[c]];
                for p in &parts {
                    let ([w0, w1, w2], h) = (p.w[a], &p.h);
                    *o += w0 * h[0][c] + w1 * h[1][c] + w2 * h[2][c];
                }
            }
        }
        assert_eq!(bits(&chosen), bits(&plain));
        // The assembly: one position's readings added through the chosen
        // kernel and one by one here.
        let (n_z, n_st) = (7, 4);
        let n_a = n_z + 6 * n_st;
        let mut j = BlockJacobian::new(n_a, n_a + 3);
        for st in 0..n_st {
            let z: Vec<f64> = (0..3 * n_z).map(|_| next()).collect();
            let pose: Vec<f64> = (0..18).map(|_| next() * 1e3).collect();
            let x: Vec<f64> = (0..9).map(|_| next() + 1.5).collect();
            j.push(3, &[(0, &z), (n_z + 6 * st, &pose), (n_a, &x)]);
        }
        let r = DVector::from_fn(j.nrows(), |i, _| (i as f64 * 1.3).cos());
        let blocks: Vec<usize> = (0..n_st).collect();
        let point = || PointBlock {
            h_ax: vec![[0.0; 3]; n_a],
            cols: (0..n_a).collect(),
            h_xx: Matrix3::zeros(),
            g_x: [0.0; 3],
            seen: true,
        };
        let (mut a, mut pa) = (Accumulator::new(&j, Some(&r)), point());
        add_blocks(&mut a, &blocks, Some(&mut pa));
        let (mut b, mut pb) = (Accumulator::new(&j, Some(&r)), point());
        b.place(&pb);
        for &k in &blocks {
            b.add(k, Some(&mut pb));
        }
        assert_eq!(bits(&a.h_aa), bits(&b.h_aa));
        assert_eq!(bits(&a.g_a), bits(&b.g_a));
        assert_eq!(bits(pa.h_ax.as_flattened()), bits(pb.h_ax.as_flattened()));
        assert_eq!(bits(pa.h_xx.as_slice()), bits(pb.h_xx.as_slice()));
        assert_eq!(bits(&pa.g_x), bits(&pb.g_x));
        // The projection's transposed product: each entry the blocks'
        // three-row sums `((o + p₀) + p₁) + p₂` in block order (a block
        // off the column adds zeros, which leave the sum as it is).
        let (j, jd) = random_arrow(6, 0.29, 2.0, true);
        let k = 7;
        let x: Vec<f64> = (0..jd.nrows() * k).map(|_| next()).collect();
        let mut plain = vec![0.0; jd.ncols() * k];
        for row in (0..jd.nrows()).step_by(3) {
            for c in 0..jd.ncols() {
                for l in 0..k {
                    let o = &mut plain[c * k + l];
                    *o = *o
                        + jd[(row, c)] * x[row * k + l]
                        + jd[(row + 1, c)] * x[(row + 1) * k + l]
                        + jd[(row + 2, c)] * x[(row + 2) * k + l];
                }
            }
        }
        assert_eq!(bits(&j.tr_mul_rows(&x, k, |_| true)), bits(&plain));
    }

    #[test]
    fn panels_are_taken_in_a_hall_and_not_where_few_stations_see_each_reflector() {
        let hall: Vec<Vec<usize>> = (0..60).map(|_| (0..100).collect()).collect();
        let refs = hall.iter().map(Vec::as_slice);
        assert!(panel_columns(refs, 100).is_some());
        // 24 stations, each reflector seen from two: the union is the whole
        // dense part, twelve times each reflector's columns.
        let sparse: Vec<Vec<usize>> = (0..60)
            .map(|p| {
                let (a, b) = (p % 24, (p * 7 + 3) % 24);
                let (a, b) = (a.min(b), a.max(b));
                (0..4)
                    .chain(4 + 6 * a..10 + 6 * a)
                    .chain(4 + 6 * b..10 + 6 * b)
                    .collect()
            })
            .collect();
        let refs = sparse.iter().map(Vec::as_slice);
        assert!(panel_columns(refs, 4 + 6 * 24).is_none());
    }

    #[test]
    fn products_at_a_constant_width_are_the_run_time_width_s_bit_for_bit() {
        let (j, _) = station_network(12, 3, |p, s| (p + s) % 4 != 0);
        let f = Normal::assemble(&j, None, |_| true).factor(0.0).unwrap();
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for k in [1, 3, 7, 18] {
            let x: Vec<f64> = (0..j.nrows() * k)
                .map(|i| (i as f64 * 0.37).sin())
                .collect();
            let y: Vec<f64> = (0..j.ncols() * k)
                .map(|i| (i as f64 * 0.53).cos())
                .collect();
            assert_eq!(
                bits(&j.tr_mul_rows(&x, k, |_| true)),
                bits(&j.tr_mul_rows_of::<0>(&x, k, |_| true)),
                "k = {k}"
            );
            let (mut a, mut b) = (x.clone(), x.clone());
            j.sub_mul_rows(&y, k, &mut a);
            let mut rest = b.as_mut_slice();
            for blk in 0..j.blocks.len() {
                let (head, tail) = rest.split_at_mut(j.blocks[blk].rows * k);
                j.block_sub_mul_rows_of::<0>(blk, &y, k, head);
                rest = tail;
            }
            assert_eq!(bits(&a), bits(&b), "k = {k}");
            assert_eq!(
                bits(&f.solve_rows(&y, k)),
                bits(&f.solve_rows_of::<0>(&y, k)),
                "k = {k}"
            );
        }
    }

    #[test]
    fn shares_combined_by_columns_are_the_serial_pass_s() {
        let n = 23;
        let shares: Vec<Vec<f64>> = (0..5)
            .map(|k| {
                (0..n * n)
                    .map(|i| match (i + k) % 3 {
                        0 => 1e16,
                        1 => -1e16,
                        _ => 1.0 + (i * k) as f64 * 0.1,
                    })
                    .collect()
            })
            .collect();
        let refs: Vec<&[f64]> = shares.iter().map(Vec::as_slice).collect();
        let start: Vec<f64> = (0..n * n).map(|i| i as f64 * 0.37).collect();
        let mut serial = start.clone();
        for share in &shares {
            serial.iter_mut().zip(share).for_each(|(a, b)| *a -= b);
        }
        let mut combined = start;
        combine_shares(&mut combined, n, &refs, |a, b| *a -= b);
        assert_eq!(combined, serial);
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
        let mut minus_jd = DVector::zeros(j.nrows());
        j.sub_mul_rows(d.as_slice(), 1, minus_jd.as_mut_slice());
        assert!((minus_jd + &jd * &d).norm() < 1e-12);
        let r = DVector::from_fn(j.nrows(), |i, _| (i as f64).sin());
        let jt_r = DVector::from_vec(j.tr_mul_rows(r.as_slice(), 1, |_| true));
        assert!((jt_r - jd.transpose() * r).norm() < 1e-12);
    }

    /// Issue 34: `reduce_sparse` written out (no matrix per position) is
    /// nalgebra's `u_A − Σ W·uₓ` bit for bit.
    #[test]
    fn reduce_sparse_written_out_is_nalgebras_product_bit_for_bit() {
        let (j, _) = random_arrow(6, 0.61, 1.5, true);
        let f = Normal::assemble(&j, None, |_| true).factor(0.0).unwrap();
        let k = 4;
        let u_a = DMatrix::from_fn(j.n_a(), k, |r, c| ((5 * r + 3 * c) as f64 * 0.29).cos());
        let u_x: Vec<(usize, DMatrix<f64>)> = (0..j.points())
            .rev()
            .map(|p| {
                (
                    p,
                    // Every other position's column 1 zero: skipped.
                    DMatrix::from_fn(3, k, |r, c| {
                        if c == 1 && p % 2 == 0 {
                            0.0
                        } else {
                            ((p + 7 * r + 11 * c) as f64).sin()
                        }
                    }),
                )
            })
            .collect();
        let mut want = u_a.clone();
        for (i, ux) in &u_x {
            let (cols, w) = f.point_coupling(*i);
            let wu = w * ux;
            for (r, &c) in cols.iter().enumerate() {
                for col in 0..k {
                    want[(c, col)] -= wu[(r, col)];
                }
            }
        }
        assert!(u_x.iter().any(|(p, _)| !f.point_coupling(*p).0.is_empty()));
        assert_eq!(f.reduce_sparse(&u_a, &u_x), want);
    }
}
