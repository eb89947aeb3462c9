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

use nalgebra::{DMatrix, DVector, Matrix3, Vector3};

/// A thin orthonormal basis of a matrix's column space and its
/// pseudo-inverse, by QR then SVD of the triangular factor (rank-revealing
/// without squaring the matrix).
struct Basis {
    /// m × rank, orthonormal.
    u: DMatrix<f64>,
    /// n × rank: `V·S⁻¹`, so that `J⁺ = pinv·Uᵀ`.
    pinv: DMatrix<f64>,
}

impl Basis {
    fn new(j: &DMatrix<f64>) -> Basis {
        let n = j.ncols();
        let qr = j.clone().qr();
        let q = qr.q();
        let r = qr.r();
        let svd = r.svd(true, true);
        let (ur, vt) = (svd.u.expect("requested"), svd.v_t.expect("requested"));
        let smax = svd.singular_values.max();
        let keep: Vec<usize> = (0..svd.singular_values.len())
            .filter(|&i| svd.singular_values[i] > 1e-10 * smax)
            .collect();
        let u = &q * ur.select_columns(&keep);
        let mut pinv = DMatrix::zeros(n, keep.len());
        for (c, &i) in keep.iter().enumerate() {
            pinv.set_column(c, &(vt.row(i).transpose() / svd.singular_values[i]));
        }
        Basis { u, pinv }
    }

    /// `x − U·Uᵀ·x`.
    fn residual(&self, x: &DMatrix<f64>) -> DMatrix<f64> {
        x - &self.u * (self.u.transpose() * x)
    }

    /// The coefficients `J⁺·x`.
    fn coefficients(&self, x: &DMatrix<f64>) -> DMatrix<f64> {
        &self.pinv * (self.u.transpose() * x)
    }
}

struct Fold {
    train: Vec<usize>,
    /// Held-out readings (indices into the reading list).
    test: Vec<usize>,
    basis: Basis,
}

/// The base model linearised at its solution, with its cross-validation
/// folds prepared.
pub struct LinearModel {
    j: DMatrix<f64>,
    r: DVector<f64>,
    full: Basis,
    folds: Vec<Fold>,
    /// Per reading: `J_nom·diag(σ)` (mm per unit of σ), for µm.
    to_mm: Vec<Matrix3<f64>>,
    dof: usize,
}

/// What adding a candidate's columns does.
#[derive(Clone, Debug)]
pub struct Fit {
    pub beta: Vec<f64>,
    pub delta_chi2: f64,
}

impl LinearModel {
    /// `j`, `r`: the base Jacobian and residuals (readings' three rows each
    /// first, then other observations). `fold_of[i]`: the fold of reading
    /// `i`. `to_mm[i]`: reading i's `J_nom·diag(σ)`.
    pub fn new(
        j: DMatrix<f64>,
        r: DVector<f64>,
        fold_of: &[usize],
        n_folds: usize,
        to_mm: Vec<Matrix3<f64>>,
    ) -> LinearModel {
        let n_read = fold_of.len();
        let full = Basis::new(&j);
        let folds = (0..n_folds)
            .map(|f| {
                let test: Vec<usize> = (0..n_read).filter(|&i| fold_of[i] == f).collect();
                let train: Vec<usize> = (0..j.nrows())
                    .filter(|&row| row >= 3 * n_read || fold_of[row / 3] != f)
                    .collect();
                let basis = Basis::new(&j.select_rows(&train));
                Fold { train, test, basis }
            })
            .collect();
        let dof = j.nrows().saturating_sub(full.u.ncols()).max(1);
        LinearModel {
            j,
            r,
            full,
            folds,
            to_mm,
            dof,
        }
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

    /// The fit of `c` (rows × k) to the residuals over all data.
    pub fn fit(&self, c: &DMatrix<f64>) -> Fit {
        let cp = self.full.residual(c);
        let beta = lstsq(&cp, &self.r, column_scale(c));
        let delta_chi2 = (&cp * &beta).norm_squared();
        Fit {
            beta: beta.iter().copied().collect(),
            delta_chi2,
        }
    }

    /// Root mean square of the held-out residuals in µm, with `c` added to
    /// the model (`None`: the base model), for the residual vector `r`.
    pub fn cv_rms_um(&self, c: Option<&DMatrix<f64>>, r: &DVector<f64>) -> f64 {
        let mut sum = 0.0;
        let mut n = 0usize;
        for f in &self.folds {
            let rt =
                DMatrix::from_column_slice(f.train.len(), 1, r.select_rows(&f.train).as_slice());
            let (beta_c, base_target) = match c {
                Some(c) => {
                    let ct = c.select_rows(&f.train);
                    let cp = f.basis.residual(&ct);
                    let rp = f.basis.residual(&rt);
                    let bc = lstsq(&cp, &rp.column(0).into_owned(), column_scale(&ct));
                    let fitted = &ct * &bc;
                    let target =
                        &rt - DMatrix::from_column_slice(fitted.len(), 1, fitted.as_slice());
                    (Some(bc), target)
                }
                None => (None, rt),
            };
            let beta_b = f.basis.coefficients(&base_target);
            for &i in &f.test {
                let rows = [3 * i, 3 * i + 1, 3 * i + 2];
                let jt = self.j.select_rows(&rows);
                let mut pred = &jt * &beta_b;
                if let (Some(c), Some(bc)) = (c, &beta_c) {
                    pred += c.select_rows(&rows) * bc;
                }
                let res = Vector3::new(
                    r[rows[0]] - pred[0],
                    r[rows[1]] - pred[1],
                    r[rows[2]] - pred[2],
                );
                sum += (self.to_mm[i] * res).norm_squared() * 1e6;
                n += 1;
            }
        }
        (sum / n.max(1) as f64).sqrt()
    }

    pub fn residuals(&self) -> &DVector<f64> {
        &self.r
    }

    /// The held-out RMS (µm) that noise alone leaves in this geometry:
    /// the mean over `draws` of the base model's cross-validated RMS for
    /// noise `ε ~ N(0, I)` in units of σ, its base fit removed.
    pub fn noise_floor_um(&self, draws: &[DVector<f64>]) -> f64 {
        if draws.is_empty() {
            return 0.0;
        }
        let sum: f64 = draws
            .iter()
            .map(|e| {
                let em = DMatrix::from_column_slice(e.len(), 1, e.as_slice());
                let res = self.full.residual(&em).column(0).into_owned();
                self.cv_rms_um(None, &res)
            })
            .sum();
        sum / draws.len() as f64
    }
}

/// `‖(I − J·J⁺)·x‖²`: the part of `x` no combination of `j`'s columns
/// reproduces.
pub fn unabsorbed_norm2(j: &DMatrix<f64>, x: &DVector<f64>) -> f64 {
    let b = Basis::new(j);
    let xm = DMatrix::from_column_slice(x.len(), 1, x.as_slice());
    b.residual(&xm).norm_squared()
}

/// The largest squared column norm of a signature before projection.
fn column_scale(c: &DMatrix<f64>) -> f64 {
    c.column_iter()
        .map(|x| x.norm_squared())
        .fold(0.0, f64::max)
}

/// Least squares by the normal equations of a few projected columns, with a
/// ridge of 1e-10 of the columns' size before projection: what the base
/// model absorbs entirely (to round-off) gets β = 0, not a huge β fitting
/// round-off.
fn lstsq(a: &DMatrix<f64>, b: &DVector<f64>, scale: f64) -> DVector<f64> {
    let mut ata = a.tr_mul(a);
    for i in 0..ata.nrows() {
        ata[(i, i)] += 1e-10 * scale.max(1e-300);
    }
    ata.cholesky()
        .map(|c| c.solve(&a.tr_mul(b)))
        .unwrap_or_else(|| DVector::zeros(a.ncols()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A signature the base model cannot absorb is found exactly; one it
    /// can absorb adds nothing.
    #[test]
    fn projects_out_what_the_base_absorbs() {
        let m = 30;
        let j = DMatrix::from_fn(m, 2, |i, k| if k == 0 { 1.0 } else { i as f64 });
        let c_new = DMatrix::from_fn(m, 1, |i, _| ((i * i) % 7) as f64);
        let c_absorbed = DMatrix::from_fn(m, 1, |i, _| 2.0 + 3.0 * i as f64);
        // Residuals: 0.5 of the new signature, made orthogonal to J.
        let full = Basis::new(&j);
        let r = full.residual(&(&c_new * 0.5)).column(0).into_owned();
        let fold_of: Vec<usize> = (0..m / 3).map(|i| i % 2).collect();
        let lm = LinearModel::new(j, r, &fold_of, 2, vec![Matrix3::identity(); m / 3]);
        let f = lm.fit(&c_new);
        assert!((f.beta[0] - 0.5).abs() < 1e-9, "{f:?}");
        assert!((f.delta_chi2 - lm.chi2()).abs() < 1e-9 * lm.chi2());
        let g = lm.fit(&c_absorbed);
        assert!(g.delta_chi2 < 1e-12 * lm.chi2(), "{g:?}");
        // The true signature predicts held-out readings perfectly.
        assert!(lm.cv_rms_um(Some(&c_new), lm.residuals()) < 1e-6);
        assert!(lm.cv_rms_um(None, lm.residuals()) > 1.0);
    }
}
