//! `compare_models`: which tracker model fits a campaign — every model ltcal
//! knows fitted to its readings by the bundle adjustment, ranked by BIC,
//! with the residual each predicts on held-out readings (see
//! [`crate::diagnose::models`]).
//!
//! ```toml
//! [stages.which_tracker]
//! kind = "compare_models"
//! inputs = { campaign = "mirror" }   # a whole campaign (import or simulate)
//! folds = 5                          # cross-validation, as the diagnosis's
//! seed = 0
//! ```
//!
//! Output `models`, best first: `rank`, `model`, `n_params`, `determined`
//! (combinations the campaign determines), `chi2`, `dof`, `chi2_p`, `bic`,
//! `delta_bic` (above the best), `cv_rms_um` (held-out RMS), `mismatch`
//! (the best model explains ≥ 25 more χ² and its BIC is lower by ≥ 10:
//! this model does not describe the tracker, [`models::mismatched`]).

use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput, fitting};
use crate::campaign::Campaign;
use crate::diagnose::models::{self, ModelFit};
use crate::table::TableBuilder;
use anyhow::Result;
use polars::prelude::DataFrame;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct CompareModelsStage {
    /// Cross-validation folds, as the diagnosis's.
    #[serde(default = "default_folds")]
    pub folds: usize,
    /// Seed of the folds.
    #[serde(default)]
    pub seed: u64,
}

fn default_folds() -> usize {
    5
}

/// The `models` table of ranked fits.
pub fn models_table(fits: &[ModelFit]) -> Result<DataFrame> {
    let best = fits.first().map_or(0.0, |f| f.bic);
    TableBuilder::new()
        .i64("rank", (1..=fits.len() as i64).collect())
        .str(
            "model",
            &fits.iter().map(|f| f.model.id()).collect::<Vec<_>>(),
        )
        .i64("n_params", fits.iter().map(|f| f.n_params as i64).collect())
        .i64("determined", fits.iter().map(|f| f.rank as i64).collect())
        .f64("chi2", fits.iter().map(|f| f.chi2).collect())
        .i64("dof", fits.iter().map(|f| f.dof as i64).collect())
        .f64("chi2_p", fits.iter().map(|f| f.chi2_p).collect())
        .f64("bic", fits.iter().map(|f| f.bic).collect())
        .f64("delta_bic", fits.iter().map(|f| f.bic - best).collect())
        .f64("cv_rms_um", fits.iter().map(|f| f.cv_rms_um).collect())
        .bool(
            "mismatch",
            fits.iter()
                .map(|f| fits.first().is_some_and(|b| models::mismatched(f, b)))
                .collect(),
        )
        .build()
}

impl StageKind for CompareModelsStage {
    const KIND: &'static str = "compare_models";
    const SUMMARY: &'static str = "which tracker model fits a campaign: each model's bundle adjustment ranked by BIC and held-out residual";
    const INPUTS: &'static [Slot] = &[fitting::CAMPAIGN];
    const OUTPUTS: &'static [&'static str] = &["models"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "models" => Some(&[
                "rank",
                "model",
                "n_params",
                "determined",
                "chi2",
                "dof",
                "chi2_p",
                "bic",
                "delta_bic",
                "cv_rms_um",
                "mismatch",
            ]),
            _ => None,
        }
    }

    fn validate(&self) -> Vec<Invalid> {
        if (2..=20).contains(&self.folds) {
            Vec::new()
        } else {
            vec![Invalid::new(
                "folds",
                format!("`folds` must be 2 … 20, got {}", self.folds),
            )]
        }
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let c = Campaign::from_inputs(inputs, "campaign")?;
        let fits = models::compare_campaign(&c, self.folds, self.seed)?;
        Ok(StageOutput::default().table("models", models_table(&fits)?))
    }
}
