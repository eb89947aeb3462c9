//! `model_blind_check`: the blind check of the model choice — campaigns made
//! by a tracker model drawn at random, each compared without knowing which
//! ([`crate::diagnose::models::blind_check`]).
//!
//! ```toml
//! [stages.model_blind]
//! kind = "model_blind_check"
//! layout = { kind = "corner" }       # as `simulate_campaign`'s (both faces)
//! noise = { sigma_angle_urad = 1.0, sigma_range_um = 2.0, sigma_range_ppm = 0.3 }
//! cases = 100
//! seed = 1
//! ```
//!
//! Outputs: `cases` (`case`, `truth`, `scale` — the errors' 1 σ, µm and
//! µrad —, `chosen`, `right`, `noise_free_chi2` — what the other model leaves
//! without noise —, `detectable` (≥ 25), `delta_bic`) and `summary` (one
//! row: `cases`, `detectable`, `right_detectable`, `rate_detectable_pct`,
//! `right_all`, `rate_all_pct`).

use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput};
use crate::diagnose::models::{self, BlindCase};
use crate::layout::{self, Spec};
use crate::noise::Noise;
use crate::table::TableBuilder;
use anyhow::Result;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct ModelBlindCheckStage {
    /// The layout, as `simulate_campaign`'s (both faces).
    pub layout: Spec,
    /// Reading noise, 1 σ.
    #[serde(default)]
    pub noise: Noise,
    /// Number of campaigns.
    #[serde(default = "default_cases")]
    pub cases: usize,
    /// Seed of the check.
    #[serde(default)]
    pub seed: u64,
}

fn default_cases() -> usize {
    100
}

/// `right` of `of` over `n`, in %.
fn pct(of: usize, n: usize) -> f64 {
    if n == 0 {
        f64::NAN
    } else {
        100.0 * of as f64 / n as f64
    }
}

impl StageKind for ModelBlindCheckStage {
    const KIND: &'static str = "model_blind_check";
    const SUMMARY: &'static str = "blind check of the model choice: campaigns of a random tracker model, compared without knowing which";
    const INPUTS: &'static [Slot] = &[];
    const OUTPUTS: &'static [&'static str] = &["cases", "summary"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "cases" => Some(&[
                "case",
                "truth",
                "scale",
                "chosen",
                "right",
                "noise_free_chi2",
                "detectable",
                "delta_bic",
            ]),
            "summary" => Some(&[
                "cases",
                "detectable",
                "right_detectable",
                "rate_detectable_pct",
                "right_all",
                "rate_all_pct",
            ]),
            _ => None,
        }
    }

    fn validate(&self) -> Vec<Invalid> {
        let mut out = Invalid::layout(&self.layout);
        if !(1..=100_000).contains(&self.cases) {
            out.push(Invalid::new(
                "cases",
                format!("`cases` must be 1 … 100000, got {}", self.cases),
            ));
        }
        out.extend(Invalid::noise(&self.noise));
        out
    }

    fn run(&self, _: &Context, _: &StageInputs) -> Result<StageOutput> {
        let layout = layout::build(&self.layout);
        let cases = models::blind_check(&layout, self.noise, self.cases, self.seed)?;
        let detectable: Vec<&BlindCase> = cases.iter().filter(|c| c.detectable).collect();
        let right_det = detectable.iter().filter(|c| c.chosen == c.truth).count();
        let right_all = cases.iter().filter(|c| c.chosen == c.truth).count();
        let table = TableBuilder::new()
            .i64("case", cases.iter().map(|c| c.case as i64).collect())
            .str(
                "truth",
                &cases.iter().map(|c| c.truth.id()).collect::<Vec<_>>(),
            )
            .f64("scale", cases.iter().map(|c| c.scale).collect())
            .str(
                "chosen",
                &cases.iter().map(|c| c.chosen.id()).collect::<Vec<_>>(),
            )
            .bool("right", cases.iter().map(|c| c.chosen == c.truth).collect())
            .f64(
                "noise_free_chi2",
                cases.iter().map(|c| c.noise_free_chi2).collect(),
            )
            .bool("detectable", cases.iter().map(|c| c.detectable).collect())
            .f64("delta_bic", cases.iter().map(|c| c.delta_bic).collect())
            .build()?;
        let summary = TableBuilder::new()
            .i64("cases", vec![cases.len() as i64])
            .i64("detectable", vec![detectable.len() as i64])
            .i64("right_detectable", vec![right_det as i64])
            .f64(
                "rate_detectable_pct",
                vec![pct(right_det, detectable.len())],
            )
            .i64("right_all", vec![right_all as i64])
            .f64("rate_all_pct", vec![pct(right_all, cases.len())])
            .build()?;
        Ok(StageOutput::default()
            .table("cases", table)
            .table("summary", summary))
    }
}
