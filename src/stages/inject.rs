//! `inject`: the error parameters of a simulated tracker.
//!
//! ```toml
//! [stages.truth]
//! kind = "inject"
//! model = "api-tracker3"     # the tracker model ("mirror-tracker": its ten misalignments)
//! preset = "table2"          # "table2" (every parameter 10 µm / 10 µrad) or "zero"
//! scale = 1.0                # multiplies the preset (e.g. 0.2 for a compensated tracker)
//! shapes = { ez1 = "fourier:2", dz3 = "poly:1" }   # Eq. (9) / Eq. (10) per parameter
//! values = { dx1 = 5.0, "ez1.sin2" = 3.0 }         # set single coefficients (µm, µrad, µm/mᵏ)
//! random = { sigma_um = 5.0, sigma_urad = 5.0, seed = 7 }   # optional: add Gaussian draws
//! ```
//!
//! Output `params` (see [`crate::schema`]).

use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput, fitting};
use crate::error_model::{Coef, ErrorParams, ParamId, Shape, Term};
use crate::random;
use crate::schema;
use crate::trackers::TrackerModel;
use anyhow::Result;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// Table 2: every parameter 10 µm or 10 µrad.
    #[default]
    Table2,
    Zero,
}

/// Gaussian draws added to every coefficient.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Random {
    pub sigma_um: f64,
    pub sigma_urad: f64,
    pub seed: u64,
}

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct InjectStage {
    /// The tracker model: `api-tracker3` (the paper's DH chain) or
    /// `mirror-tracker` (its ten misalignments).
    #[serde(default)]
    pub model: TrackerModel,
    /// `table2` (every parameter 10 µm / 10 µrad, Table 2) or `zero`.
    #[serde(default)]
    pub preset: Preset,
    /// Multiplies the preset (e.g. 0.2 for a compensated tracker).
    #[serde(default = "one")]
    pub scale: f64,
    /// Per parameter, its shape: `fourier:k` (Eq. 9) or `poly:k` (Eq. 10);
    /// constants by default.
    #[serde(default)]
    pub shapes: BTreeMap<ParamId, Shape>,
    /// Single coefficients set by id (`dx1`, `"ez1.sin2"`), in µm, µrad or
    /// µm/mᵏ.
    #[serde(default)]
    pub values: BTreeMap<String, f64>,
    /// Gaussian draws added to the preset: `{ sigma_um, sigma_urad, seed }`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub random: Option<Random>,
}

fn one() -> f64 {
    1.0
}

impl InjectStage {
    /// The parameter set these settings describe.
    pub fn params(&self) -> Result<ErrorParams, Invalid> {
        let model = fitting::model(self.model, &self.shapes, &[])?;
        let mut p = ErrorParams::zero(&model);
        let coefs = p.coefs().to_vec();
        let preset = match self.preset {
            Preset::Table2 => 10.0,
            Preset::Zero => 0.0,
        };
        for (c, v) in coefs.iter().zip(p.values_mut()) {
            if c.term == Term::Const {
                *v = preset * self.scale;
            }
        }
        if let Some(r) = &self.random {
            let mut rng = random::stream(r.seed, "inject");
            for (c, v) in coefs.iter().zip(p.values_mut()) {
                let sigma = if c.param.is_angular() {
                    r.sigma_urad
                } else {
                    r.sigma_um
                };
                *v += sigma * random::normal(&mut rng);
            }
        }
        for (name, &value) in &self.values {
            let field = format!("values.{name}");
            let c = Coef::parse(name).ok_or_else(|| {
                Invalid::new(
                    &field,
                    format!("`{name}` is not a coefficient: use dx1 … ez3, with .sinK/.cosK (Fourier) or .dK (polynomial), or a mirror tracker's misalignment"),
                )
            })?;
            if c.param.tracker() != self.model {
                return Err(Invalid::new(
                    &field,
                    format!(
                        "`{name}` is a parameter of the {} model; this stage's `model` is {}",
                        c.param.tracker(),
                        self.model
                    ),
                ));
            }
            let i = coefs.iter().position(|x| *x == c).ok_or_else(|| {
                Invalid::new(
                    &field,
                    format!(
                        "`{name}` is not in the model: {} has shape \"{}\"",
                        c.param.id(),
                        model.shape(c.param)
                    ),
                )
            })?;
            p.values_mut()[i] = value;
        }
        Ok(p)
    }
}

impl StageKind for InjectStage {
    const KIND: &'static str = "inject";
    const SUMMARY: &'static str =
        "the error parameters of a simulated tracker (Table 2 by default; shapes of Eq. 9 and 10)";
    const INPUTS: &'static [Slot] = &[];
    const OUTPUTS: &'static [&'static str] = &["params"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "params" => Some(&["coef", "param", "symbol", "unit", "value"]),
            _ => None,
        }
    }

    fn validate(&self) -> Vec<Invalid> {
        let mut out = Vec::new();
        if !self.scale.is_finite() {
            out.push(Invalid::new("scale", "`scale` must be finite"));
        }
        if let Some(r) = &self.random {
            for (f, v) in [("sigma_um", r.sigma_um), ("sigma_urad", r.sigma_urad)] {
                if !(v.is_finite() && v >= 0.0) {
                    out.push(Invalid::new(
                        format!("random.{f}"),
                        format!("`random.{f}` must be ≥ 0, got {v}"),
                    ));
                }
            }
        }
        for (k, v) in &self.values {
            if !v.is_finite() {
                out.push(Invalid::new(format!("values.{k}"), "value must be finite"));
            }
        }
        if let Err(e) = self.params() {
            out.push(e);
        }
        out
    }

    fn run(&self, _: &Context, _: &StageInputs) -> Result<StageOutput> {
        let p = self.params().map_err(|e| anyhow::anyhow!(e.message))?;
        Ok(StageOutput::default().table("params", schema::params_table(&p, None)?))
    }
}
