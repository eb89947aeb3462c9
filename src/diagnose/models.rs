//! Which tracker model fits a campaign: every model ltcal knows
//! fitted to the same readings by the bundle adjustment, ranked by the
//! Bayesian information criterion and judged by the residual each predicts
//! on held-out readings.
//!
//! The station poses and reflector positions are the same unknowns for
//! every model, so they cancel in every comparison: a model's BIC here is
//! `χ² + k·ln m` with `k` the combinations of its parameters the campaign
//! determines (the rank of the identifiability analysis) and `m` the rows
//! of the adjustment (reading coordinates, gauge lengths, references). The
//! held-out residual is the diagnosis's ([`super::linear`]): each fold's
//! readings predicted by the model's linearised adjustment fitted to the
//! other folds. The ranking is by BIC; the held-out residual says how much
//! better the first predicts readings it did not see.
//!
//! The models are not nested (a mirror tracker's reflection has no DH
//! joint, a DH beam error no mirror), so there is no F test between them;
//! the BIC difference is the evidence. A model is mismatched
//! ([`mismatched`]) when another model explains at least
//! [`DETECTABLE_CHI2`] more χ² — the diagnosis's notion of a detectable
//! signal — and its BIC is lower by [`MISMATCH_BIC`] or more. Both are
//! needed: where the models fit equally well, the BIC alone prefers the
//! one with fewer determined combinations by `Δk·ln m` (≈ 20 between the
//! DH chain's 7 and the mirror's 10), which is parsimony, not a misfit.

use super::linear::LinearModel;
use crate::calibrate::bundle::Linearisation;
use crate::calibrate::{self, Calibration, Network, Settings as CalSettings};
use crate::campaign::Campaign;
use crate::error_model::{ErrorModel, ErrorParams};
use crate::kinematics::nominal_jacobian;
use crate::trackers::TrackerModel;
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

/// The bundle adjustment of `tracker`'s model, every coefficient free, and
/// its linearisation at the solution.
fn adjust(net: &Network, tracker: TrackerModel) -> Result<(Calibration, Linearisation)> {
    let start = ErrorParams::zero(&ErrorModel::of(tracker));
    let free = vec![true; start.coefs().len()];
    let cal = calibrate::calibrate(
        net,
        &start,
        &free,
        &CalSettings {
            // The former scaled covariance: the magnitudes' uncertainties and
            // verdicts stay those the blind and open-world checks scored.
            std: crate::calibrate::BundleStd::ScaledStatedNoise,
            ..CalSettings::bundle()
        },
    )?;
    let lin = cal
        .linearisation
        .clone()
        .ok_or_else(|| anyhow!("the bundle adjustment gave no linearisation"))?;
    Ok((cal, lin))
}

/// Fits `tracker`'s model, every coefficient free, to the network by the
/// bundle adjustment; the `rejected` reading coordinates (blunders the
/// network down-weights) count in no held-out residual.
pub fn fit(
    net: &Network,
    tracker: TrackerModel,
    fold_of: &[usize],
    n_folds: usize,
    rejected: &[(usize, usize)],
) -> Result<ModelFit> {
    let (cal, lin) = adjust(net, tracker)?;
    let mut to_mm: Vec<Matrix3<f64>> = net
        .obs
        .iter()
        .map(|o| nominal_jacobian(o.reading) * Matrix3::from_diagonal(&o.sigma))
        .collect();
    for &(i, c) in rejected {
        to_mm[i].column_mut(c).fill(0.0);
    }
    let cv_rms_um =
        LinearModel::held_out_rms_um(&lin.jacobian, &lin.residuals, fold_of, n_folds, &to_mm)?;
    let j = &lin.jacobian;
    Ok(summarise(
        tracker,
        cal.estimate.params.coefs().len(),
        &cal,
        lin.residuals.norm_squared(),
        (j.nrows(), j.nrows().saturating_sub(j.ncols()).max(1)),
        cv_rms_um,
    ))
}

/// A fit's numbers from its calibration, its χ², its rows `m` and degrees
/// of freedom of the linearised adjustment, and its held-out RMS.
pub fn summarise(
    model: TrackerModel,
    n_params: usize,
    cal: &Calibration,
    chi2: f64,
    (m, dof): (usize, usize),
    cv_rms_um: f64,
) -> ModelFit {
    let rank = cal.estimate.analysis.rank;
    ModelFit {
        model,
        n_params,
        rank,
        chi2,
        dof: cal.fit.dof.unwrap_or(dof),
        chi2_p: cal.fit.chi2_p.unwrap_or(f64::NAN),
        bic: chi2 + rank as f64 * (m as f64).ln(),
        cv_rms_um,
    }
}

/// Whether `alt` shows that `base` does not describe the tracker: `alt`
/// explains at least [`DETECTABLE_CHI2`] more χ² and its BIC is lower by
/// [`MISMATCH_BIC`] or more.
pub fn mismatched(base: &ModelFit, alt: &ModelFit) -> bool {
    base.chi2 - alt.chi2 >= DETECTABLE_CHI2 && base.bic - alt.bic >= MISMATCH_BIC
}

/// Fits, best (lowest BIC) first; a tie keeps the order given.
pub fn ranked(mut fits: Vec<ModelFit>) -> Vec<ModelFit> {
    fits.sort_by(|a, b| a.bic.total_cmp(&b.bic));
    fits
}

/// Every model on a campaign, with the diagnosis's folds (`folds`, `seed`).
pub fn compare_campaign(c: &Campaign, folds: usize, seed: u64) -> Result<Vec<ModelFit>> {
    let net = Network::from_campaign(c)?;
    let settings = super::Settings {
        folds,
        seed,
        ..super::Settings::default()
    };
    let (fold_of, n_folds) = super::folds(&net, &settings);
    let fits = TrackerModel::ALL
        .iter()
        .map(|&t| fit(&net, t, &fold_of, n_folds, &[]))
        .collect::<Result<Vec<_>>>()?;
    Ok(ranked(fits))
}

/// One case of the blind check of the model choice.
#[derive(Clone, Debug, PartialEq)]
pub struct BlindCase {
    pub case: usize,
    /// The model that made the campaign, and the scale of its errors (µm, µrad).
    pub truth: TrackerModel,
    pub scale: f64,
    /// The model ranked first, not knowing the truth.
    pub chosen: TrackerModel,
    /// χ² the closest other model leaves on the same campaign without
    /// noise: the models differ detectably from 25 (the diagnosis's notion).
    pub noise_free_chi2: f64,
    pub detectable: bool,
    /// BIC of the runner-up minus the chosen one's.
    pub delta_bic: f64,
}

/// The χ² from which two models differ detectably on a campaign: the
/// diagnosis's Δχ² ≥ 25 (a five-σ signal).
pub const DETECTABLE_CHI2: f64 = 25.0;

/// The χ² `tracker`'s model, every coefficient free, leaves on a
/// noise-free campaign read with its stated σ: how far the campaign's
/// readings lie from any that model can make (Δχ² ≥ [`DETECTABLE_CHI2`]:
/// another model made them, detectably).
pub(super) fn model_leaves_chi2(clean: &Campaign, tracker: TrackerModel) -> Result<f64> {
    let net = Network::from_campaign(clean)?;
    Ok(adjust(&net, tracker)?.1.residuals.norm_squared())
}

/// The blind check of the model choice: `cases` campaigns of `layout`, each
/// made by a tracker model drawn at random with every parameter drawn from
/// N(0, s²), the scale `s` log-uniform in 0.03 … 10 µm / µrad (from errors
/// no campaign sees to Table 2's), read with `noise`; each compared without
/// knowing its model. A case is detectable when every other model, fitted
/// to the same campaign without noise, leaves χ² ≥ [`DETECTABLE_CHI2`].
pub fn blind_check(
    layout: &crate::layout::Layout,
    noise: crate::noise::Noise,
    cases: usize,
    seed: u64,
) -> Result<Vec<BlindCase>> {
    use crate::effects::Effects;
    use crate::kinematics::Face;
    use crate::simulate::{CampaignSpec, simulate_campaign};
    use rayon::prelude::*;
    (0..cases)
        .into_par_iter()
        .map(|case| {
            let mut rng = crate::random::stream(seed, &format!("model-blind-{case}"));
            let n = TrackerModel::ALL.len();
            let truth =
                TrackerModel::ALL[(crate::random::uniform(&mut rng) * n as f64) as usize % n];
            let scale = 10f64.powf(-1.5 + 2.5 * crate::random::uniform(&mut rng));
            let mut errors = ErrorParams::zero(&ErrorModel::of(truth));
            for v in errors.values_mut() {
                *v = scale * crate::random::normal(&mut rng);
            }
            let effects = Effects::default();
            let campaign = |noise: crate::noise::Noise| {
                simulate_campaign(&CampaignSpec {
                    name: format!("model-blind-{case}"),
                    layout,
                    errors: Some(&errors),
                    faces: &[Face::Front, Face::Back],
                    aim: crate::campaign::Aim::StationsCentroid,
                    max_angle_deg: crate::effects::DEFAULT_MAX_ANGLE_DEG,
                    noise,
                    effects: &effects,
                    gauge_u_mm: 0.0005,
                    reference_u_mm: 0.002,
                    level_urad: 1000.0,
                    interval_s: 20.0,
                    record_time: false,
                    record_temperature: false,
                    seed: seed.wrapping_add(case as u64),
                })
                .map_err(|e| anyhow!(e))
            };
            let noisy = campaign(noise)?;
            let fits = compare_campaign(&noisy.campaign, 5, seed)?;
            // Without noise, with the stated σ still weighting the readings.
            let mut clean = campaign(crate::noise::Noise::default())?.campaign;
            clean.meta.tracker = noisy.campaign.meta.tracker.clone();
            // The closest other model's χ² alone: no held-out residual is
            // needed.
            let mut noise_free_chi2 = f64::INFINITY;
            for other in TrackerModel::ALL.into_iter().filter(|&m| m != truth) {
                noise_free_chi2 = noise_free_chi2.min(model_leaves_chi2(&clean, other)?);
            }
            Ok(BlindCase {
                case,
                truth,
                scale,
                chosen: fits[0].model,
                noise_free_chi2,
                detectable: noise_free_chi2 >= DETECTABLE_CHI2,
                delta_bic: fits[1].bic - fits[0].bic,
            })
        })
        .collect()
}
