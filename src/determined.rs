//! Fitting in the determined directions: what identification (Eq. 11) and
//! every calibration objective (Eq. 13–15, the bundle adjustment) share.
//!
//! The data never determine all 18 DH error parameters (Table 3's null
//! space, NOTES item 8; a campaign can determine all ten of a mirror
//! tracker's misalignments, but not every layout does). Each fit therefore analyses the Jacobian of its free
//! coefficients ([`identifiability`]), estimates coordinates `z` along the
//! determined directions only — `p(z) = p₀ + B·z`, `B` the row basis — and
//! leaves the undetermined directions at their start value: the
//! minimum-norm solution, with the undetermined combinations named in
//! words. The covariance of `z` maps back to the free coefficients as
//! `B·C_z·Bᵀ`. Every such fit returns an [`Estimate`].

use crate::error_model::ErrorParams;
use crate::identifiability::{self, Analysis, Combination};
use anyhow::Result;
use nalgebra::{DMatrix, DVector};

/// What every fit in the determined directions returns — identification
/// and each calibration objective alike: the estimate, each coefficient's
/// standard uncertainty and what the data determined.
#[derive(Clone, Debug)]
pub struct Estimate {
    /// Free coefficients fitted, fixed ones at their start value.
    pub params: ErrorParams,
    pub free: Vec<bool>,
    /// Standard uncertainty of each free coefficient's minimum-norm
    /// estimate; `None` when fixed (or not estimable).
    pub std: Vec<Option<f64>>,
    /// Covariance of the free coefficients, in `free_index` order (`B·C_z·Bᵀ`;
    /// `None` when no uncertainty could be formed): what propagates the
    /// calibration into a corrected measurement, correlations included.
    pub cov: Option<DMatrix<f64>>,
    /// Singular values of what determines the free coefficients.
    pub analysis: Analysis,
    /// The free-coefficient indices the analysis columns refer to.
    pub free_index: Vec<usize>,
    /// Undetermined directions, in free-coefficient indices.
    pub combinations: Vec<Combination>,
}

impl Estimate {
    /// Whether coefficient `i` is determined: free and in no undetermined
    /// direction.
    pub fn determined(&self) -> Vec<bool> {
        let mut determined = self.free.clone();
        for c in &self.combinations {
            for &(k, _) in &c.direction {
                determined[self.free_index[k]] = false;
            }
        }
        determined
    }

    /// A combination's determined value for `params`, its free
    /// coefficients mapped back to the full vector.
    pub fn determined_value(&self, c: &Combination, params: &ErrorParams) -> Option<f64> {
        let x: Vec<f64> = self
            .free_index
            .iter()
            .map(|&i| params.values()[i])
            .collect();
        c.determined_value(&x)
    }
}

/// The determined directions of a fit's free coefficients.
#[derive(Clone, Debug)]
pub struct Determined {
    /// Indices of the free coefficients among all of them.
    pub free_index: Vec<usize>,
    pub analysis: Analysis,
    /// The undetermined directions, in words.
    pub combinations: Vec<Combination>,
}

impl Determined {
    /// From an analysis of the free coefficients' (projected) Jacobian.
    pub fn new(analysis: Analysis, start: &ErrorParams, free: &[bool]) -> Determined {
        let free_index: Vec<usize> = (0..free.len()).filter(|&i| free[i]).collect();
        let names: Vec<String> = free_index
            .iter()
            .map(|&i| start.coefs()[i].symbol())
            .collect();
        let combinations = identifiability::describe_null_space(&analysis.null_basis, &names);
        Determined {
            free_index,
            analysis,
            combinations,
        }
    }

    /// Analyses `j`, the Jacobian of the free coefficients (columns in
    /// their order), at the relative threshold `rank_tol`.
    pub fn analyse(
        j: &impl identifiability::Tall,
        start: &ErrorParams,
        free: &[bool],
        rank_tol: f64,
    ) -> Result<Determined> {
        Ok(Determined::new(
            identifiability::analyse(j, rank_tol)?,
            start,
            free,
        ))
    }

    /// `B`: free coefficients × determined directions.
    pub fn basis(&self) -> &DMatrix<f64> {
        &self.analysis.row_basis
    }

    /// Number of determined directions.
    pub fn rank(&self) -> usize {
        self.analysis.rank
    }

    /// The [`Estimate`] these directions give `params`, with the
    /// covariance `cov_z` of `z` when there is one.
    pub fn estimate(
        self,
        params: ErrorParams,
        free: &[bool],
        cov_z: Option<&DMatrix<f64>>,
    ) -> Estimate {
        let cov = cov_z
            .filter(|_| self.rank() > 0)
            .map(|c| self.basis() * c * self.basis().transpose());
        let mut std = vec![None; free.len()];
        if let Some(cov) = &cov {
            for (k, &i) in self.free_index.iter().enumerate() {
                std[i] = Some(cov[(k, k)].max(0.0).sqrt());
            }
        }
        Estimate {
            params,
            free: free.to_vec(),
            std,
            cov,
            analysis: self.analysis,
            free_index: self.free_index,
            combinations: self.combinations,
        }
    }

    /// `p₀ + B·z` on the free coefficients.
    pub fn params(&self, start: &ErrorParams, z: &DVector<f64>) -> ErrorParams {
        start.plus(&self.free_index, &(self.basis() * z))
    }

    /// The covariance of `z` of an unweighted least-squares fit whose
    /// Jacobian on `z` is `jz` and residuals `r`: `s²·(JᵀJ)⁻¹`, `s²` the
    /// residuals' scatter (`None` when `JᵀJ` is singular).
    pub fn scatter_covariance(&self, jz: &DMatrix<f64>, r: &DVector<f64>) -> Option<DMatrix<f64>> {
        let dof = r.len().saturating_sub(self.rank()).max(1);
        let s2 = r.norm_squared() / dof as f64;
        (jz.transpose() * jz).try_inverse().map(|inv| inv * s2)
    }
}
