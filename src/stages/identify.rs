//! `identify`: the error parameters from readings of known points, Eq. (11)
//! (Section 5.1).
//!
//! ```toml
//! [stages.identify_sphere]
//! kind = "identify"
//! inputs = { readings = "measure_sphere" }   # start = "…": optional start values
//! fixed = ["dz1", "dy2", "ez3"]    # held at their start value (0), as in Table 3
//! shapes = { ez1 = "fourier:1" }   # the model to fit; constants by default
//! rank_tol = 1e-9                  # relative singular-value threshold
//! ```
//!
//! Outputs: `params` (the estimate with `free`, `std`, `determined`),
//! `singular_values` (`index`, `sigma`, `sigma_rel`, `determined`),
//! `combinations` (`direction`, `determined`, `value`, `sentence`: what the
//! data cannot separate) and `fit` (one row: `n_readings`, `n_free`, `rank`,
//! `iterations`, `stop`, `rms_before_um`, `rms_after_um`).

use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput};
use crate::error_model::{ErrorModel, ErrorParams, ParamId, Shape};
use crate::identifiability;
use crate::identify::{self, KnownPoint, Settings};
use crate::schema::{self, IdentifiedColumns};
use crate::table::TableBuilder;
use anyhow::Result;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IdentifyStage {
    #[serde(default)]
    pub fixed: Vec<ParamId>,
    #[serde(default)]
    pub shapes: BTreeMap<ParamId, Shape>,
    #[serde(default = "default_rank_tol")]
    pub rank_tol: f64,
    #[serde(default = "default_max_iters")]
    pub max_iters: u64,
}

fn default_rank_tol() -> f64 {
    identifiability::DEFAULT_REL_TOL
}
fn default_max_iters() -> u64 {
    100
}

impl IdentifyStage {
    fn model(&self) -> Result<ErrorModel, Invalid> {
        let mut m = ErrorModel::constant();
        for (&p, &s) in &self.shapes {
            m = m
                .with_shape(p, s)
                .map_err(|e| Invalid::new(format!("shapes.{}", p.id()), e))?;
        }
        Ok(m)
    }
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
        Slot::table(
            "start",
            false,
            "start values (a params table); fixed and undetermined coefficients keep them",
        ),
    ];
    const OUTPUTS: &'static [&'static str] = &["params", "singular_values", "combinations", "fit"];

    fn validate(&self) -> Vec<Invalid> {
        let mut out = Vec::new();
        if !(self.rank_tol > 0.0 && self.rank_tol < 1.0) {
            out.push(Invalid::new(
                "rank_tol",
                format!("`rank_tol` must lie in (0, 1), got {}", self.rank_tol),
            ));
        }
        if self.max_iters == 0 {
            out.push(Invalid::new("max_iters", "`max_iters` must be at least 1"));
        }
        if let Err(e) = self.model() {
            out.push(e);
        }
        out
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let readings = schema::readings_from(&inputs.get("readings")?)?;
        let model = self.model().map_err(|e| anyhow::anyhow!(e.message))?;
        let mut start = ErrorParams::zero(&model);
        if let Some(t) = inputs.optional("start") {
            let given = schema::params_from(&t)?;
            let coefs = start.coefs().to_vec();
            for (c, v) in coefs.iter().zip(start.values_mut()) {
                if let Some(g) = given.get(c) {
                    *v = g;
                }
            }
        }
        let free: Vec<bool> = start
            .coefs()
            .iter()
            .map(|c| !self.fixed.contains(&c.param))
            .collect();
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
        };
        let id = identify::identify(&obs, &start, &free, &settings)?;
        tables(&id)
    }
}

/// The four output tables of an identification.
fn tables(id: &identify::Identification) -> Result<StageOutput> {
    let n = id.params.coefs().len();
    let mut determined = id.free.clone();
    for c in &id.combinations {
        for &(k, _) in &c.direction {
            determined[id.free_index[k]] = false;
        }
    }
    let params = schema::params_table(
        &id.params,
        Some(&IdentifiedColumns {
            free: id.free.clone(),
            std: id.std.clone(),
            determined,
        }),
    )?;
    debug_assert_eq!(params.height(), n);

    let sv = &id.analysis.singular_values;
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
            (0..sv.len()).map(|i| i < id.analysis.rank).collect(),
        )
        .build()?;

    let combos = &id.combinations;
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
            combos
                .iter()
                .map(|c| id.determined_value(c, &id.params))
                .collect(),
        )
        .str(
            "sentence",
            &combos.iter().map(|c| c.sentence()).collect::<Vec<_>>(),
        )
        .build()?;

    let fit = TableBuilder::new()
        .i64("n_readings", vec![id.n_observations as i64])
        .i64("n_free", vec![id.free_index.len() as i64])
        .i64("rank", vec![id.analysis.rank as i64])
        .i64("iterations", vec![id.iterations as i64])
        .str("stop", &[id.stop_reason])
        .f64("rms_before_um", vec![id.rms_before_um])
        .f64("rms_after_um", vec![id.rms_after_um])
        .build()?;

    Ok(StageOutput::default()
        .table("params", params)
        .table("singular_values", singular_values)
        .table("combinations", combinations)
        .table("fit", fit))
}
