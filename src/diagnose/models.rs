//! Which tracker model fits a campaign (issue 15): every model ltcal knows
//! fitted to the same readings by the bundle adjustment, ranked by the
//! Bayesian information criterion and judged by the residual each predicts
//! on held-out readings.
//!
//! The station poses and reflector positions are the same unknowns for
//! every model, so they cancel in every comparison: a model's BIC here is
//! `χ² + k·ln m` with `k` the combinations of its parameters the campaign
//! determines (the rank of the identifiability analysis) and `m` the
//! reading coordinates. The held-out residual is the diagnosis's
//! ([`super::linear`]): each fold's readings predicted by the model's
//! linearised adjustment fitted to the other folds.
//!
//! The models are not nested (a mirror tracker's reflection has no DH
//! joint, a DH beam error no mirror), so there is no F test between them;
//! the BIC difference is the evidence. The diagnosis calls a model
//! mismatch when another model's BIC is lower than the base model's by
//! [`MISMATCH_BIC`] or more.

use super::linear::LinearModel;
use crate::calibrate::{self, Calibration, Network, Norm, Objective, Settings as CalSettings};
use crate::error_model::{ErrorModel, ErrorParams};
use crate::kinematics::nominal_jacobian;
use crate::tracker::TrackerModel;
use anyhow::{Result, anyhow};
use nalgebra::Matrix3;

/// The BIC difference from which the diagnosis calls a model mismatch: "very
/// strong" evidence on Kass and Raftery's scale (a Bayes factor above 150).
pub const MISMATCH_BIC: f64 = 10.0;

/// One model fitted to a campaign.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelFit {
    pub model: TrackerModel,
    /// Coefficients fitted, and the combinations of them the campaign determines.
    pub n_params: usize,
    pub rank: usize,
    pub chi2: f64,
    pub dof: usize,
    pub chi2_p: f64,
    /// `χ² + rank·ln m` (the unknowns every model shares left out).
    pub bic: f64,
    /// Held-out RMS residual, µm.
    pub cv_rms_um: f64,
}

/// Fits `model` (coefficients `free`) to the network by the bundle adjustment.
pub fn fit(
    net: &Network,
    model: &ErrorModel,
    free: &[bool],
    fold_of: &[usize],
    n_folds: usize,
) -> Result<ModelFit> {
    let start = ErrorParams::zero(model);
    let cal = calibrate::calibrate(
        net,
        &start,
        free,
        &CalSettings {
            objective: Objective::Bundle,
            norm: Norm::L2,
            rank_tol: crate::identifiability::DEFAULT_REL_TOL,
            max_iters: 100,
        },
    )?;
    let lin = cal
        .linearisation
        .clone()
        .ok_or_else(|| anyhow!("the bundle adjustment gave no linearisation"))?;
    let to_mm: Vec<Matrix3<f64>> = net
        .obs
        .iter()
        .map(|o| nominal_jacobian(o.reading) * Matrix3::from_diagonal(&o.sigma))
        .collect();
    let lm = LinearModel::new(lin.jacobian, lin.residuals, fold_of, n_folds, to_mm)?;
    let n_free = free.iter().filter(|&&f| f).count();
    Ok(summarise(model.tracker(), n_free, &cal, &lm))
}

/// A fit's numbers from its calibration and linearised adjustment.
pub fn summarise(
    model: TrackerModel,
    n_params: usize,
    cal: &Calibration,
    lm: &LinearModel,
) -> ModelFit {
    let rank = cal.estimate.analysis.rank;
    let chi2 = lm.chi2();
    ModelFit {
        model,
        n_params,
        rank,
        chi2,
        dof: cal.fit.dof.unwrap_or(lm.dof()),
        chi2_p: cal.fit.chi2_p.unwrap_or(f64::NAN),
        bic: chi2 + rank as f64 * (lm.rows() as f64).ln(),
        cv_rms_um: lm.cv_rms_um_base(),
    }
}

/// Fits, best (lowest BIC) first; a tie keeps the order given.
pub fn ranked(mut fits: Vec<ModelFit>) -> Vec<ModelFit> {
    fits.sort_by(|a, b| a.bic.total_cmp(&b.bic));
    fits
}
