//! What the fitting stages (`identify`, `calibrate`, `monte_carlo`,
//! `measurement_uncertainty`, `diagnose`) share: the slots they take, the
//! model they estimate (tracker model, shapes, fixed parameters, start
//! values) and the tables that say what the data determined.
//!
//! The tracker model a fit of a campaign uses is its `model` setting, else
//! the campaign's own `[tracker] model`: a campaign names its tracker, and
//! fitting it with another model is a choice the pipeline writes down.

use super::{Invalid, Slot, StageInputs};
use crate::campaign;
use crate::determined::Estimate;
use crate::error_model::{ErrorModel, ErrorParams, ParamId, Shape};
use crate::schema::{self, IdentifiedColumns};
use crate::table::TableBuilder;
use crate::trackers::TrackerModel;
use anyhow::Result;
use polars::prelude::DataFrame;
use std::collections::BTreeMap;

/// The slot of a whole campaign every fit of one takes.
pub const CAMPAIGN: Slot = Slot::group(
    "campaign",
    true,
    "a campaign (`import_campaign` or `simulate_campaign`)",
    campaign::TABLES,
);

/// The optional slot of start values every fit takes.
pub const START: Slot = Slot::table(
    "start",
    false,
    "start values (a params table); fixed and undetermined coefficients keep them",
);

/// The default relative singular-value threshold of a fit's `rank_tol`.
pub fn default_rank_tol() -> f64 {
    crate::identifiability::DEFAULT_REL_TOL
}

/// The default `max_iters` of a fit.
pub fn default_max_iters() -> u64 {
    100
}

/// The tracker model a fit uses: the stage's `model`, else the campaign's.
pub fn tracker(setting: Option<TrackerModel>, campaign: &campaign::Campaign) -> TrackerModel {
    setting.unwrap_or_else(|| campaign.tracker_model())
}

/// The error model of a tracker with the given shapes (constants
/// elsewhere); `fixed` parameters must be the model's too.
pub fn model(
    tracker: TrackerModel,
    shapes: &BTreeMap<ParamId, Shape>,
    fixed: &[ParamId],
) -> Result<ErrorModel, Invalid> {
    let mut m = ErrorModel::of(tracker);
    for (&p, &s) in shapes {
        m = m
            .with_shape(p, s)
            .map_err(|e| Invalid::new(format!("shapes.{}", p.id()), e))?;
    }
    if let Some(p) = fixed.iter().find(|p| p.tracker() != tracker) {
        return Err(Invalid::new(
            "fixed",
            format!(
                "`{}` is a parameter of the {} model, but this fit uses the {tracker} model",
                p.id(),
                p.tracker()
            ),
        ));
    }
    Ok(m)
}

/// [`model`] as a run-time error (the tracker model came from the campaign).
pub fn run_model(
    tracker: TrackerModel,
    shapes: &BTreeMap<ParamId, Shape>,
    fixed: &[ParamId],
) -> Result<ErrorModel> {
    model(tracker, shapes, fixed).map_err(|e| anyhow::anyhow!("`{}`: {}", e.field, e.message))
}

/// Start values: zero, or those of the optional `start` input where it has
/// the same coefficient (zero throughout without inputs: a stage called
/// from the library). A start table of another tracker model is an error.
pub fn start(model: &ErrorModel, inputs: Option<&StageInputs>) -> Result<ErrorParams> {
    let mut start = ErrorParams::zero(model);
    if let Some(t) = inputs.and_then(|i| i.optional("start")) {
        let given = schema::params_from(&t)?;
        if !given.coefs().is_empty() && given.tracker() != model.tracker() {
            anyhow::bail!(
                "the start values (`{}`) are parameters of the {} model, but this fit uses the {} model",
                t.name,
                given.tracker(),
                model.tracker()
            );
        }
        let coefs = start.coefs().to_vec();
        for (c, v) in coefs.iter().zip(start.values_mut()) {
            if let Some(g) = given.get(c) {
                *v = g;
            }
        }
    }
    Ok(start)
}

/// Which coefficients are free: all but those of the fixed parameters.
pub fn free(start: &ErrorParams, fixed: &[ParamId]) -> Vec<bool> {
    start
        .coefs()
        .iter()
        .map(|c| !fixed.contains(&c.param))
        .collect()
}

/// Checks the settings every fitting stage has: the shapes and fixed
/// parameters belong to the `model` when it is given (else to one model,
/// checked against the campaign's when the stage runs).
pub fn check(
    tracker: Option<TrackerModel>,
    shapes: &BTreeMap<ParamId, Shape>,
    fixed: &[ParamId],
    rank_tol: f64,
    max_iters: u64,
) -> Vec<Invalid> {
    let mut out = Vec::new();
    if !(rank_tol > 0.0 && rank_tol < 1.0) {
        out.push(Invalid::new(
            "rank_tol",
            format!("`rank_tol` must lie in (0, 1), got {rank_tol}"),
        ));
    }
    if max_iters == 0 {
        out.push(Invalid::new("max_iters", "`max_iters` must be at least 1"));
    }
    let named = shapes.keys().chain(fixed).map(|p| p.tracker());
    let tracker = tracker.or_else(|| named.clone().next()).unwrap_or_default();
    if let Err(e) = model(tracker, shapes, fixed) {
        out.push(e);
    }
    out
}

/// The columns of the tables [`tables`] makes, by table name.
pub fn columns(table: &str) -> Option<&'static [&'static str]> {
    match table {
        "params" => Some(&[
            "coef",
            "param",
            "symbol",
            "unit",
            "value",
            "free",
            "std",
            "determined",
        ]),
        "singular_values" => Some(&["index", "sigma", "sigma_rel", "determined"]),
        "combinations" => Some(&["direction", "determined", "value", "sentence"]),
        _ => None,
    }
}

/// `params`, `singular_values` and `combinations` (see the `identify` stage).
pub fn tables(d: &Estimate) -> Result<[DataFrame; 3]> {
    let params = schema::params_table(
        &d.params,
        Some(&IdentifiedColumns {
            free: d.free.clone(),
            std: d.std.clone(),
            determined: d.determined(),
        }),
    )?;
    let sv = &d.analysis.singular_values;
    let smax = sv.first().copied().unwrap_or(0.0);
    let singular_values = TableBuilder::new()
        .i64("index", (1..=sv.len() as i64).collect())
        .f64("sigma", sv.clone())
        .f64(
            "sigma_rel",
            sv.iter()
                .map(|s| if smax > 0.0 { s / smax } else { 0.0 })
                .collect(),
        )
        .bool(
            "determined",
            (0..sv.len()).map(|i| i < d.analysis.rank).collect(),
        )
        .build()?;
    let x: Vec<f64> = d.free_index.iter().map(|&i| d.params.values()[i]).collect();
    let combos = &d.combinations;
    let combinations = TableBuilder::new()
        .str(
            "direction",
            &combos
                .iter()
                .map(|c| c.direction_text.clone())
                .collect::<Vec<_>>(),
        )
        .str(
            "determined",
            &combos
                .iter()
                .map(|c| c.determined_text.clone().unwrap_or_default())
                .collect::<Vec<_>>(),
        )
        .opt_f64(
            "value",
            combos.iter().map(|c| c.determined_value(&x)).collect(),
        )
        .str(
            "sentence",
            &combos.iter().map(|c| c.sentence()).collect::<Vec<_>>(),
        )
        .build()?;
    Ok([params, singular_values, combinations])
}
