//! `identify`: the error parameters from readings of known points, Eq. (11)
//! (Section 5.1).
//!
//! ```toml
//! [stages.identify_sphere]
//! kind = "identify"
//! inputs = { readings = "measure_sphere" }   # start = "…": optional start values
//! model = "api-tracker3"          # the tracker model ("mirror-tracker": its misalignments)
//! fixed = ["dz1", "dy2", "ez3"]    # held at their start value (0), as in Table 3
//! shapes = { ez1 = "fourier:1" }   # the model to fit; constants by default
//! rank_tol = 1e-9                  # relative singular-value threshold
//! noise = { sigma_angle_urad = 1.0, sigma_range_um = 2.0 }   # the readings' noise, when known
//! weighting = "unweighted"         # Eq. (11) as printed; "noise": weighted by the noise
//! std = "noise"                    # "residual-scatter": the textbook s²(JᵀJ)⁻¹, on request
//! ```
//!
//! The reported `std` is that of the estimator used — the sandwich
//! covariance of the unweighted fit, or the weighted fit's inverse normal
//! matrix — given the reading noise, and holds against the spread over
//! noise seeds. The noise is, first, the stage's `noise`; else the one the
//! readings carry from their `measure` stage (its `sigma_*` columns, when
//! not all zero: a noise-free simulation says nothing of what a model
//! mismatch leaves); else it is estimated from the residuals by variance
//! components, one σ for the angles and one for the ranges, each with its
//! own uncertainty (see [`crate::identify`]). `std_from` says which:
//! `sandwich` or `stated-noise` (a known noise), `variance-components` (the
//! estimated one), `residual-scatter-fallback` (it could not be estimated:
//! `note` says why), `residual-scatter` (requested by `std`, which pools the
//! angular and range noise into one scatter and misstates the uncertainty
//! by up to 1.7×).
//!
//! Outputs: `params` (the estimate with `free`, `std`, `determined`),
//! `singular_values` (`index`, `sigma`, `sigma_rel`, `determined`),
//! `combinations` (`direction`, `determined`, `value`, `sentence`: what the
//! data cannot separate) and `fit` (one row: `n_readings`, `n_free`, `rank`,
//! `iterations`, `stop`, `rms_before_um`, `rms_after_um`, `weighting`,
//! `std_from`; `noise_from` — `stage`, `readings`, `residuals` or `none` —
//! and the noise used, `sigma_angle_urad`, `sigma_range_um`,
//! `sigma_range_ppm`, with the standard uncertainties of the estimated
//! ones, `sigma_angle_urad_u`, `sigma_range_um_u` (empty when stated);
//! `vc_iterations`, the rounds of variance component estimation (empty
//! when none ran); `note`).

use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput, fitting};
use crate::error_model::{ParamId, Shape};
use crate::identify::{self, KnownPoint, Settings, StdMethod, Weighting};
use crate::noise::Noise;
use crate::schema;
use crate::table::TableBuilder;
use crate::trackers::TrackerModel;
use anyhow::Result;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct IdentifyStage {
    /// The tracker model to fit: `api-tracker3` or `mirror-tracker`.
    #[serde(default)]
    pub model: TrackerModel,
    /// Parameters held at their start value (0 without a `start` input), e.g.
    /// Table 3's `dz1`, `dy2`, `ez3`.
    #[serde(default)]
    pub fixed: Vec<ParamId>,
    /// Per parameter, the shape to fit: `fourier:k` or `poly:k`; constants by
    /// default.
    #[serde(default)]
    pub shapes: BTreeMap<ParamId, Shape>,
    /// Relative singular-value threshold below which a direction counts as not
    /// determined.
    #[serde(default = "fitting::default_rank_tol")]
    pub rank_tol: f64,
    /// Iteration limit of the nonlinear least squares.
    #[serde(default = "fitting::default_max_iters")]
    pub max_iters: u64,
    /// `unweighted` (Eq. 11 as printed) or `noise` (weighted by the readings'
    /// noise: maximum likelihood).
    #[serde(default)]
    pub weighting: Weighting,
    /// The readings' noise, 1 σ, when known (over what the readings carry).
    #[serde(default)]
    pub noise: Option<Noise>,
    /// Where `std` comes from: `noise` (the known or estimated noise) or
    /// `residual-scatter` (the textbook s²(JᵀJ)⁻¹, on request).
    #[serde(default)]
    pub std: StdMethod,
}

impl StageKind for IdentifyStage {
    const KIND: &'static str = "identify";
    const SUMMARY: &'static str =
        "error parameters from readings of known points (Eq. 11), with the null space named";
    const INPUTS: &'static [Slot] = &[
        Slot::table(
            "readings",
            true,
            "readings with reference coordinates (a `measure` stage)",
        ),
        fitting::START,
    ];
    const OUTPUTS: &'static [&'static str] = &["params", "singular_values", "combinations", "fit"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "fit" => Some(&[
                "n_readings",
                "n_free",
                "rank",
                "iterations",
                "stop",
                "rms_before_um",
                "rms_after_um",
                "weighting",
                "std_from",
                "noise_from",
                "sigma_angle_urad",
                "sigma_angle_urad_u",
                "sigma_range_um",
                "sigma_range_um_u",
                "sigma_range_ppm",
                "vc_iterations",
                "note",
            ]),
            _ => fitting::columns(table),
        }
    }

    fn validate(&self) -> Vec<Invalid> {
        let mut out = fitting::check(
            Some(self.model),
            &self.shapes,
            &self.fixed,
            self.rank_tol,
            self.max_iters,
        );
        out.extend(self.noise.as_ref().and_then(Invalid::noise));
        // Without a stated noise the weights come from the readings' or the
        // estimated one; a stated one must be usable as weights.
        if self.weighting == Weighting::Noise
            && let Some(n) = self.noise
            && (n.sigma_angle_urad <= 0.0 || (n.sigma_range_um <= 0.0 && n.sigma_range_ppm <= 0.0))
        {
            out.push(Invalid::new(
                "noise",
                "`weighting = \"noise\"` needs a σ above zero for the angles and for the range",
            ));
        }
        out
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let table = inputs.get("readings")?;
        let readings = schema::readings_from(&table)?;
        // The stage's own noise wins; a carried noise of zero is no noise
        // known (it would report an exact fit whatever the model misses).
        let carried = schema::readings_noise(&table)?.filter(|n| !n.is_zero());
        let (noise, noise_from) = match (self.noise, carried) {
            (Some(n), _) => (Some(n), "stage"),
            (None, Some(n)) => (Some(n), "readings"),
            (None, None) => (None, "residuals"),
        };
        let model = fitting::run_model(self.model, &self.shapes, &self.fixed)?;
        let start = fitting::start(&model, Some(inputs))?;
        let free = fitting::free(&start, &self.fixed);
        let obs: Vec<KnownPoint> = readings
            .iter()
            .map(|r| KnownPoint {
                reading: r.reading,
                reference: r.reference,
            })
            .collect();
        let settings = Settings {
            rank_tol: self.rank_tol,
            max_iters: self.max_iters,
            weighting: self.weighting,
            noise,
            std: self.std,
        };
        let id = identify::identify(&obs, &start, &free, &settings)?;
        let noise_from = match (&id.noise, &id.components) {
            (None, _) => "none",
            (Some(_), Some(_)) => "residuals",
            (Some(_), None) => noise_from,
        };
        tables(&id, noise_from)
    }
}

/// The four output tables of an identification.
fn tables(id: &identify::Identification, noise_from: &str) -> Result<StageOutput> {
    let c = id.components.as_ref();
    let [params, singular_values, combinations] = fitting::tables(&id.estimate)?;
    let fit = TableBuilder::new()
        .i64("n_readings", vec![id.n_observations as i64])
        .i64("n_free", vec![id.estimate.free_index.len() as i64])
        .i64("rank", vec![id.estimate.analysis.rank as i64])
        .i64("iterations", vec![id.iterations as i64])
        .str("stop", &[id.stop_reason])
        .f64("rms_before_um", vec![id.rms_before_um])
        .f64("rms_after_um", vec![id.rms_after_um])
        .str("weighting", &[id.weighting.as_str()])
        .str("std_from", &[id.std_from.as_str()])
        .str("noise_from", &[noise_from])
        .opt_f64(
            "sigma_angle_urad",
            vec![id.noise.map(|n| n.sigma_angle_urad)],
        )
        .opt_f64("sigma_angle_urad_u", vec![c.map(|c| c.sigma_angle_urad_u)])
        .opt_f64("sigma_range_um", vec![id.noise.map(|n| n.sigma_range_um)])
        .opt_f64("sigma_range_um_u", vec![c.map(|c| c.sigma_range_um_u)])
        .opt_f64("sigma_range_ppm", vec![id.noise.map(|n| n.sigma_range_ppm)])
        .opt_i64("vc_iterations", vec![c.map(|c| c.iterations as i64)])
        .str("note", &[id.note.as_deref().unwrap_or("")])
        .build()?;
    Ok(StageOutput::default()
        .table("params", params)
        .table("singular_values", singular_values)
        .table("combinations", combinations)
        .table("fit", fit))
}
