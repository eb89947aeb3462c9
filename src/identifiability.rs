//! Which error-parameter combinations a set of measurements can determine.
//!
//! The identification Jacobian of the 18-parameter model is rank-deficient
//! for any layout: εz3 moves nothing, δz1 and δy2 translate along the same
//! (vertical) axis, δz2 and δy3 along the elevation axis, εz1 and εy2 both
//! turn about the vertical, εz2 and εy3 about the elevation axis (NOTES item
//! 8: Table 3's odd values are one arbitrary point of this null space). This
//! module finds the rank from the singular values, a basis of what is
//! determined and of what is not, and names the undetermined directions in
//! words ("δz2 − δy3 is not determined; the data see only δz2 + δy3").
//!
//! Columns are compared in display units (µm, µrad), so "orthogonal" and
//! "minimum norm" are meant in those units.

use anyhow::{Result, anyhow, bail};
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

/// A bound on the SVD's sweeps, far above what a finite matrix of our size
/// needs (tens), so that a pathological one fails instead of hanging.
const MAX_SVD_ITERS: usize = 10_000;

/// The singular-value analysis of a Jacobian.
#[derive(Clone, Debug)]
pub struct Analysis {
    /// Singular values, largest first.
    pub singular_values: Vec<f64>,
    /// Number of singular values above `tol`.
    pub rank: usize,
    /// The absolute threshold used: `rel_tol · σ_max`.
    pub tol: f64,
    /// Orthonormal basis of the determined directions (n × rank).
    pub row_basis: DMatrix<f64>,
    /// Orthonormal basis of the undetermined directions (n × (n − rank)).
    pub null_basis: DMatrix<f64>,
}

/// Default relative threshold: singular values below `1e-9·σ_max` count as zero.
/// Exact redundancies of the model sit at ~1e-16; genuinely weak directions of
/// poor layouts stay well above 1e-9.
pub const DEFAULT_REL_TOL: f64 = 1e-9;

/// Singular values and bases of `j` (m × n, any m). Fails on a Jacobian
/// with NaN or infinite entries — degenerate data (a reading or gauge that
/// divides by zero) on which nalgebra's SVD would iterate forever.
pub fn analyse(j: &impl Tall, rel_tol: f64) -> Result<Analysis> {
    if let Some((row, col)) = j.first_non_finite() {
        bail!(
            "the Jacobian has a non-finite entry (row {row}, column {col}): the data are degenerate \
             (e.g. a reading or gauge length that divides by zero)"
        );
    }
    let n = j.shape().1;
    let svd = triangular_factor(j)
        .try_svd(false, true, 5.0 * f64::EPSILON, MAX_SVD_ITERS)
        .ok_or_else(|| anyhow!("the singular value decomposition did not converge"))?;
    let v_t = svd.v_t.expect("right singular vectors were requested");
    let mut order: Vec<usize> = (0..svd.singular_values.len()).collect();
    order.sort_by(|&a, &b| svd.singular_values[b].total_cmp(&svd.singular_values[a]));
    let mut sv: Vec<f64> = order.iter().map(|&i| svd.singular_values[i]).collect();
    // A wide Jacobian has fewer singular values than unknowns: the rest are zero.
    sv.resize(n, 0.0);
    let smax = sv.first().copied().unwrap_or(0.0);
    let tol = rel_tol * smax;
    let rank = sv.iter().filter(|&&s| s > tol).count();
    let mut basis: Vec<DVector<f64>> = order.iter().map(|&i| v_t.row(i).transpose()).collect();
    complete_basis(&mut basis, n);
    let row_basis = DMatrix::from_columns(&basis[..rank]);
    let null_basis = if rank < n {
        DMatrix::from_columns(&basis[rank..])
    } else {
        DMatrix::zeros(n, 0)
    };
    Ok(Analysis {
        singular_values: sv,
        rank,
        tol,
        row_basis,
        null_basis,
    })
}

/// Row blocks a tall matrix is reduced in, in parallel: a fixed number, so
/// that the factor is the same whatever the number of threads.
const TSQR_BLOCKS: usize = 8;
/// Below this many rows one QR is cheaper than eight in parallel (the
/// sphere of Section 5.1, 1 440 rows, and the paper's campaigns factorise
/// as one; the 600-reflector hall's 14 400 in blocks).
const TSQR_MIN_ROWS: usize = 4096;

/// A tall matrix reduced to its triangular factor `R` (`JᵀJ = RᵀR`): the
/// same singular values and right vectors, a fraction of the SVD's work.
/// A tall-skinny QR: each block of rows factorised on its own (in
/// parallel), their `R`s stacked and factorised once more (Demmel et al.,
/// 2012) — the bundle adjustment's projected Jacobian has thousands of rows
/// and a handful of columns.
fn triangular_factor(j: &impl Tall) -> DMatrix<f64> {
    let (m, n) = j.shape();
    if m <= n {
        return j.rows(0, m);
    }
    let per = m.div_ceil(TSQR_BLOCKS);
    if m < TSQR_MIN_ROWS || per < 4 * n {
        return j.rows(0, m).qr().r();
    }
    let rs: Vec<DMatrix<f64>> = (0..m.div_ceil(per))
        .into_par_iter()
        .map(|b| {
            let first = b * per;
            j.rows(first, per.min(m - first)).qr().r()
        })
        .collect();
    // (The last block may hold fewer than n rows, and its factor as many.)
    let mut stacked = DMatrix::zeros(rs.iter().map(|r| r.nrows()).sum(), n);
    let mut at = 0;
    for r in &rs {
        stacked.rows_mut(at, r.nrows()).copy_from(r);
        at += r.nrows();
    }
    stacked.qr().r()
}

/// A tall matrix as the analysis reads it: its shape, a block of its rows
/// as a matrix of their own, and where it is not finite. A dense matrix
/// is one; so is a matrix given row-major ([`RowMajor`]), as the bundle
/// adjustment's projected Jacobian comes — its row blocks are taken
/// straight from the rows, with no transposed copy of the whole (10 MB at
/// 24 000 readings, made on one core; issue 34).
pub trait Tall: Sync {
    /// (rows, columns).
    fn shape(&self) -> (usize, usize);
    /// Rows `first..first + rows`, column-major.
    fn rows(&self, first: usize, rows: usize) -> DMatrix<f64>;
    /// The first entry, in column-major order, that is NaN or infinite.
    fn first_non_finite(&self) -> Option<(usize, usize)>;
}

impl Tall for DMatrix<f64> {
    fn shape(&self) -> (usize, usize) {
        self.shape()
    }

    fn rows(&self, first: usize, rows: usize) -> DMatrix<f64> {
        DMatrix::rows(self, first, rows).into_owned()
    }

    fn first_non_finite(&self) -> Option<(usize, usize)> {
        let k = self.iter().position(|x| !x.is_finite())?;
        Some((k % self.nrows(), k / self.nrows()))
    }
}

/// An `nrows` × `ncols` matrix whose rows lie side by side in `values`.
#[derive(Clone, Copy, Debug)]
pub struct RowMajor<'a> {
    pub values: &'a [f64],
    pub nrows: usize,
    pub ncols: usize,
}

impl Tall for RowMajor<'_> {
    fn shape(&self) -> (usize, usize) {
        (self.nrows, self.ncols)
    }

    fn rows(&self, first: usize, rows: usize) -> DMatrix<f64> {
        let n = self.ncols;
        DMatrix::from_row_slice(rows, n, &self.values[first * n..(first + rows) * n])
    }

    fn first_non_finite(&self) -> Option<(usize, usize)> {
        if self.values.iter().all(|x| x.is_finite()) {
            return None;
        }
        let (m, n) = self.shape();
        (0..n)
            .flat_map(|col| (0..m).map(move |row| (row, col)))
            .find(|&(row, col)| !self.values[row * n + col].is_finite())
    }
}

/// The observability indices of robot calibration, computed over the
/// determined singular values σ₁ ≥ … ≥ σ_L of a Jacobian with `m` rows:
/// O1 = (σ₁⋯σ_L)^(1/L)/√m (Borm & Menq), O2 = σ_L/σ₁ (the inverse
/// condition number), O3 = σ_L (minimum singular value, Nahvi & Hollerbach),
/// O4 = σ_L²/σ₁ (noise amplification index), O5 = 1/Σ 1/σᵢ (Sun &
/// Hollerbach). Larger is better for all five.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observability {
    pub o1: f64,
    pub o2: f64,
    pub o3: f64,
    pub o4: f64,
    pub o5: f64,
}

impl Analysis {
    pub fn observability(&self, m: usize) -> Observability {
        let sv = &self.singular_values[..self.rank];
        if sv.is_empty() {
            return Observability {
                o1: 0.0,
                o2: 0.0,
                o3: 0.0,
                o4: 0.0,
                o5: 0.0,
            };
        }
        let (first, last) = (sv[0], sv[sv.len() - 1]);
        let log_mean = sv.iter().map(|s| s.ln()).sum::<f64>() / sv.len() as f64;
        Observability {
            o1: log_mean.exp() / (m.max(1) as f64).sqrt(),
            o2: last / first,
            o3: last,
            o4: last * last / first,
            o5: 1.0 / sv.iter().map(|s| 1.0 / s).sum::<f64>(),
        }
    }

    /// σ_max/σ_min over the determined directions.
    pub fn condition_number(&self) -> f64 {
        match self.rank {
            0 => f64::INFINITY,
            r => self.singular_values[0] / self.singular_values[r - 1],
        }
    }
}

/// Extends orthonormal vectors to a basis of ℝⁿ (Gram–Schmidt on unit vectors).
fn complete_basis(basis: &mut Vec<DVector<f64>>, n: usize) {
    let mut k = 0;
    while basis.len() < n && k < n {
        let mut e = DVector::zeros(n);
        e[k] = 1.0;
        for b in basis.iter() {
            e -= b * b.dot(&e);
        }
        if e.norm() > 1e-6 {
            basis.push(e.normalize());
        }
        k += 1;
    }
}

/// One undetermined direction, in a readable form.
#[derive(Clone, Debug, PartialEq)]
pub struct Combination {
    /// The direction the data cannot see, as `(index, coefficient)` with the
    /// first coefficient 1.
    pub direction: Vec<(usize, f64)>,
    /// E.g. `δz2 − δy3`.
    pub direction_text: String,
    /// The combination of the same parameters that *is* determined, when the
    /// direction involves two parameters (`δz2 + δy3`), with its coefficients.
    pub determined: Option<Vec<(usize, f64)>>,
    pub determined_text: Option<String>,
}

impl Combination {
    /// What a user reads: "εz3 has no effect" or "δz2 − δy3 is not determined
    /// (only δz2 + δy3 is)".
    pub fn sentence(&self) -> String {
        match (&self.determined_text, self.direction.len()) {
            (_, 1) => format!("{} has no effect on the data", self.direction_text),
            (Some(d), _) => format!(
                "{} is not determined by the data (only {d} is)",
                self.direction_text
            ),
            (None, _) => format!("{} is not determined by the data", self.direction_text),
        }
    }

    /// The value of the determined combination for a parameter vector.
    pub fn determined_value(&self, x: &[f64]) -> Option<f64> {
        self.determined
            .as_ref()
            .map(|d| d.iter().map(|&(i, c)| c * x[i]).sum())
    }
}

/// Names the null space: reduces its basis to echelon form so that each
/// direction involves as few parameters as possible.
pub fn describe_null_space(null_basis: &DMatrix<f64>, names: &[String]) -> Vec<Combination> {
    let k = null_basis.ncols();
    if k == 0 {
        return Vec::new();
    }
    let mut m = null_basis.transpose(); // k × n
    let n = m.ncols();
    let mut row = 0;
    for col in 0..n {
        if row == k {
            break;
        }
        let (piv, val) = (row..k)
            .map(|r| (r, m[(r, col)].abs()))
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap();
        if val < 1e-9 {
            continue;
        }
        m.swap_rows(row, piv);
        let p = m[(row, col)];
        for c in 0..n {
            m[(row, c)] /= p;
        }
        for r in 0..k {
            if r != row {
                let f = m[(r, col)];
                if f != 0.0 {
                    for c in 0..n {
                        m[(r, c)] -= f * m[(row, c)];
                    }
                }
            }
        }
        row += 1;
    }
    (0..k)
        .map(|r| {
            let direction: Vec<(usize, f64)> = (0..n)
                .filter_map(|c| {
                    let v = m[(r, c)];
                    (v.abs() > 1e-6).then_some((c, clean(v)))
                })
                .collect();
            let determined = (direction.len() == 2).then(|| {
                let (i, a) = direction[0];
                let (j, b) = direction[1];
                // Orthogonal to (a, b) within the pair, scaled to lead with 1.
                vec![(i, 1.0), (j, clean(-a / b))]
            });
            Combination {
                direction_text: linear_text(&direction, names),
                determined_text: determined.as_ref().map(|d| linear_text(d, names)),
                direction,
                determined,
            }
        })
        .collect()
}

/// Rounds coefficients that are ±1 (or 0) up to numerical noise.
fn clean(v: f64) -> f64 {
    let r = (v * 1e6).round() / 1e6;
    if r == 0.0 { 0.0 } else { r }
}

/// `a·x + b·y` with unit coefficients written plainly: `δz2 − δy3`.
pub fn linear_text(terms: &[(usize, f64)], names: &[String]) -> String {
    let mut out = String::new();
    for (k, &(i, c)) in terms.iter().enumerate() {
        let mag = c.abs();
        let sign = if c < 0.0 { "−" } else { "+" };
        if k == 0 {
            if c < 0.0 {
                out.push('−');
            }
        } else {
            out.push_str(&format!(" {sign} "));
        }
        if (mag - 1.0).abs() > 1e-9 {
            out.push_str(&format!("{}·", trim_number(mag)));
        }
        out.push_str(&names[i]);
    }
    out
}

fn trim_number(v: f64) -> String {
    let s = format!("{v:.4}");
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_tall_skinny_factor_has_the_singular_values_of_the_matrix() {
        // 57 × 2: one QR, as below TSQR_MIN_ROWS.
        let j = DMatrix::from_fn(57, 2, |i, k| ((i * 7 + k * 13) % 17) as f64 - 8.0);
        let (jtj, r) = (j.transpose() * &j, triangular_factor(&j));
        assert_eq!(r.shape(), (2, 2));
        assert!((&jtj - r.transpose() * &r).amax() <= 1e-12 * jtj.amax());
        // 4 099 × 5: eight blocks of 513 rows, the last of 508.
        let j = DMatrix::from_fn(4099, 5, |i, k| {
            ((i * 7 + k * 13) % 17) as f64 - 8.0 + k as f64 * 1e-3
        });
        let r = triangular_factor(&j);
        assert_eq!(r.shape(), (5, 5));
        let (a, b) = (j.singular_values(), r.singular_values());
        let (mut a, mut b): (Vec<f64>, Vec<f64>) =
            (a.iter().copied().collect(), b.iter().copied().collect());
        a.sort_by(f64::total_cmp);
        b.sort_by(f64::total_cmp);
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() <= 1e-10 * a[4], "{x} vs {y}");
        }
        assert!(
            (j.transpose() * &j - r.transpose() * &r).amax() <= 1e-9 * (j.transpose() * &j).amax()
        );
    }

    #[test]
    fn a_non_finite_jacobian_is_an_error_not_a_hang() {
        let mut j = DMatrix::from_element(6, 3, 1.0);
        j[(4, 2)] = f64::NAN;
        let e = analyse(&j, DEFAULT_REL_TOL).unwrap_err().to_string();
        assert!(e.contains("row 4, column 2"), "{e}");
    }

    /// The bundle adjustment hands its projected Jacobian over row-major
    /// (issue 34): the analysis of it must be the dense matrix's bit for
    /// bit — one QR, eight blocks, or a wide matrix — and a non-finite
    /// entry reported at the same place.
    #[test]
    fn a_row_major_matrix_is_analysed_as_its_dense_copy_bit_for_bit() {
        for (m, n) in [(57, 2), (4099, 5), (3, 4)] {
            let dense = DMatrix::from_fn(m, n, |i, k| {
                ((i * 7 + k * 13) % 17) as f64 - 8.0 + (i * k) as f64 * 1e-4
            });
            let values: Vec<f64> = dense.transpose().as_slice().to_vec();
            let rows = RowMajor {
                values: &values,
                nrows: m,
                ncols: n,
            };
            assert_eq!(triangular_factor(&rows), triangular_factor(&dense));
            let (a, b) = (
                analyse(&rows, DEFAULT_REL_TOL).unwrap(),
                analyse(&dense, DEFAULT_REL_TOL).unwrap(),
            );
            assert_eq!(a.singular_values, b.singular_values);
            assert_eq!(a.row_basis, b.row_basis);
        }
        let mut dense = DMatrix::from_element(6, 3, 1.0);
        dense[(4, 2)] = f64::NAN;
        dense[(5, 1)] = f64::INFINITY;
        let values: Vec<f64> = dense.transpose().as_slice().to_vec();
        let rows = RowMajor {
            values: &values,
            nrows: 6,
            ncols: 3,
        };
        assert_eq!(rows.first_non_finite(), Some((5, 1)));
        assert_eq!(rows.first_non_finite(), dense.first_non_finite());
    }

    #[test]
    fn finds_and_names_a_duplicated_and_a_dead_column() {
        // Columns: a, b (= a), c (zero), d.
        let j = DMatrix::from_row_slice(
            4,
            4,
            &[
                1.0, 1.0, 0.0, 0.0, //
                2.0, 2.0, 0.0, 1.0, //
                0.0, 0.0, 0.0, 3.0, //
                1.0, 1.0, 0.0, -1.0,
            ],
        );
        let a = analyse(&j, DEFAULT_REL_TOL).unwrap();
        assert_eq!(a.rank, 2);
        let names: Vec<String> = ["a", "b", "c", "d"].iter().map(|s| s.to_string()).collect();
        let combos = describe_null_space(&a.null_basis, &names);
        let texts: Vec<String> = combos.iter().map(Combination::sentence).collect();
        assert!(
            texts.contains(&"a − b is not determined by the data (only a + b is)".to_string()),
            "{texts:?}"
        );
        assert!(
            texts.contains(&"c has no effect on the data".to_string()),
            "{texts:?}"
        );
        let ab = combos.iter().find(|c| c.direction.len() == 2).unwrap();
        assert_eq!(ab.determined_value(&[3.0, 4.0, 0.0, 0.0]), Some(7.0));
        let o = a.observability(4);
        let (s1, s2) = (a.singular_values[0], a.singular_values[1]);
        assert!((o.o1 - (s1 * s2).sqrt() / 2.0).abs() < 1e-12);
        assert!((o.o2 - s2 / s1).abs() < 1e-12 && (o.o3 - s2).abs() < 1e-12);
        assert!((o.o4 - s2 * s2 / s1).abs() < 1e-12);
        assert!((o.o5 - 1.0 / (1.0 / s1 + 1.0 / s2)).abs() < 1e-12);
        assert!((a.condition_number() - s1 / s2).abs() < 1e-12);
    }
}
