//! `simulate_campaign`: a campaign as a tracker with error parameters would
//! take it — a layout of reflectors, stations with unknown (to the
//! calibration) poses, SMR aim and acceptance, reading noise and any of the
//! effects of `effects.md`.
//!
//! ```toml
//! [stages.corner]
//! kind = "simulate_campaign"
//! inputs = { errors = "truth" }          # optional: the tracker's error parameters
//! layout = { kind = "corner" }           # "corner" (Section 7), "cmm-table" (5.2), "hall";
//!                                        # stations, pan_deg, levels, per_level, distance_mm, tracker_height_mm
//! faces = "front"                        # "front", "back" or "both"
//! aim = "stations-centroid"              # or "aim-columns" (written to targets.csv)
//! max_angle_deg = 30                     # SMR acceptance: readings beyond it are not taken
//!                                        # (the incidence effect's max_angle_deg also holds)
//! noise = { sigma_angle_urad = 1.0, sigma_range_um = 2.0, sigma_range_ppm = 0.3 }
//! seed = 1
//! hypotheses = "hypotheses/adm.toml"     # your own effects (crate::hypothesis), at their `value`s
//! [stages.corner.effects.incidence]     # any effect of effects.md, by its id
//! e_axial_um = 5.0
//! [stages.corner.hypothesis_values.adm-cyclic]
//! a = 6.0                                # a parameter's value, over the file's (a number, or per instance)
//! ```
//!
//! A hypothesis's injected values are rows of `truth_effects` too (`effect`
//! its name, `where` the instance, `parameter` the parameter's name).
//!
//! Outputs: the campaign (`readings`, `targets`, `gauge`, `meta`: a group
//! other stages take whole, e.g. `inputs = { campaign = "corner" }`) and the
//! truth a calibration must not see: `truth_stations` (`station`, `x_mm`,
//! `y_mm`, `z_mm`, `roll_urad`, `pitch_urad`, `yaw_deg`), `truth_targets`
//! (`target`, `x_mm`, `y_mm`, `z_mm`) and `truth_effects` (`effect`,
//! `where`, `parameter`, `value`; a blunder's `where` is its reading,
//! `station/target/face`, and its parameter `az_urad`, `el_urad` or `d_um`).

use super::measure::Faces;
use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput};
use crate::campaign::Aim;
use crate::effects::{self, Coordinate, Effects, Injected};
use crate::hypothesis::{Hypothesis, Value};
use crate::layout::{self, Spec};
use crate::noise::Noise;
use crate::schema;
use crate::simulate::{self, CampaignSpec, SimulatedCampaign};
use crate::table::TableBuilder;
use anyhow::{Result, anyhow};
use polars::prelude::DataFrame;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct SimulateCampaignStage {
    /// The campaign's name, written into its `meta`.
    #[serde(default = "default_name")]
    pub name: String,
    /// Stations and reflectors: `{ kind = "corner" | "cmm-table" | "hall",
    /// stations, pan_deg, levels, per_level, distance_mm, tracker_height_mm }`.
    pub layout: Spec,
    /// Which faces are read: `front`, `back` or `both`.
    #[serde(default)]
    pub faces: Faces,
    /// How each SMR faces: `stations-centroid` or `aim-columns` (written to
    /// targets.csv).
    #[serde(default = "Aim::simulated_default")]
    pub aim: Aim,
    /// SMR acceptance, degrees: readings beyond this incidence angle are not
    /// taken.
    #[serde(default = "default_max_angle")]
    pub max_angle_deg: f64,
    /// Reading noise, 1 σ: `{ sigma_angle_urad, sigma_range_um, sigma_range_ppm
    /// }`.
    #[serde(default)]
    pub noise: Noise,
    /// Effects of effects.md by id, each a table of its parameters
    /// (`[stages.<name>.effects.incidence]`).
    #[serde(default)]
    pub effects: Effects,
    /// Standard uncertainty of the gauge lengths, mm (a CMM-calibrated bar: 0.5
    /// µm).
    #[serde(default = "default_gauge_u")]
    pub gauge_u_mm: f64,
    /// Standard uncertainty of the reference coordinates, mm (CMM coordinates:
    /// 2 µm).
    #[serde(default = "default_reference_u")]
    pub reference_u_mm: f64,
    /// How far from level the stations stand, µrad (drawn within about this).
    #[serde(default = "default_level")]
    pub level_urad: f64,
    /// Seconds between two readings, for the time column and time-driven
    /// effects.
    #[serde(default = "default_interval")]
    pub interval_s: f64,
    /// Write each reading's time (`t_s`).
    #[serde(default = "yes")]
    pub record_time: bool,
    /// Write each reading's air temperature.
    #[serde(default = "yes")]
    pub record_temperature: bool,
    /// Seed of every random draw (poses, noise, effects).
    #[serde(default)]
    pub seed: u64,
    /// A hypothesis file whose hypotheses are injected.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hypotheses: Option<PathBuf>,
    /// Values over the file's: hypothesis → parameter → value.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub hypothesis_values: BTreeMap<String, BTreeMap<String, Value>>,
}

fn default_name() -> String {
    "simulated".into()
}
fn default_max_angle() -> f64 {
    crate::effects::DEFAULT_MAX_ANGLE_DEG
}
/// A CMM-calibrated gauge: 0.5 µm (as in the example campaigns).
fn default_gauge_u() -> f64 {
    0.0005
}
/// CMM coordinates: 2 µm.
fn default_reference_u() -> f64 {
    0.002
}
/// Stations levelled within about 1 mrad.
fn default_level() -> f64 {
    1000.0
}
fn default_interval() -> f64 {
    20.0
}
fn yes() -> bool {
    true
}

impl SimulateCampaignStage {
    /// A campaign of this geometry without noise, effects, times or
    /// temperatures, every other setting at this stage's default: what
    /// `layout_design` evaluates, so that the two stages simulate one way.
    pub fn noise_free(
        name: &str,
        layout: &Spec,
        faces: Faces,
        aim: Aim,
        max_angle_deg: f64,
        seed: u64,
    ) -> Self {
        SimulateCampaignStage {
            name: name.to_string(),
            layout: layout.clone(),
            faces,
            aim,
            max_angle_deg,
            noise: Noise::default(),
            effects: Effects::default(),
            gauge_u_mm: default_gauge_u(),
            reference_u_mm: default_reference_u(),
            level_urad: default_level(),
            interval_s: default_interval(),
            record_time: false,
            record_temperature: false,
            seed,
            hypotheses: None,
            hypothesis_values: BTreeMap::new(),
        }
    }

    /// The hypotheses to inject, with `hypothesis_values` over the file's.
    pub fn injected(&self) -> Result<Vec<Hypothesis>> {
        let Some(path) = &self.hypotheses else {
            return Ok(Vec::new());
        };
        let mut hyps = super::diagnose::load_hypotheses(path).map_err(|e| anyhow!(e))?;
        for h in &mut hyps {
            if let Some(values) = self.hypothesis_values.get(&h.name) {
                for p in &mut h.params {
                    if let Some(v) = values.get(&p.name) {
                        p.value = v.clone();
                    }
                }
            }
        }
        Ok(hyps)
    }

    pub fn simulate(
        &self,
        errors: Option<&crate::error_model::ErrorParams>,
    ) -> Result<SimulatedCampaign> {
        let layout = layout::build(&self.layout);
        let effects = Effects {
            hypotheses: Injected(Arc::new(self.injected()?)),
            ..self.effects.clone()
        };
        simulate::simulate_campaign(&CampaignSpec {
            name: self.name.clone(),
            layout: &layout,
            errors,
            faces: self.faces.list(),
            aim: self.aim,
            max_angle_deg: self.max_angle_deg,
            noise: self.noise,
            effects: &effects,
            gauge_u_mm: self.gauge_u_mm,
            reference_u_mm: self.reference_u_mm,
            level_urad: self.level_urad,
            interval_s: self.interval_s,
            record_time: self.record_time,
            record_temperature: self.record_temperature,
            seed: self.seed,
        })
        .map_err(|e| anyhow!(e))
    }
}

impl StageKind for SimulateCampaignStage {
    const KIND: &'static str = "simulate_campaign";
    const SUMMARY: &'static str = "a simulated campaign: layout, stations, SMR aim and acceptance, noise and the effects of effects.md";
    const INPUTS: &'static [Slot] = &[Slot::table(
        "errors",
        false,
        "the tracker's error parameters (an `inject` stage); none: a perfect tracker",
    )];
    const OUTPUTS: &'static [&'static str] = &[
        "readings",
        "targets",
        "gauge",
        "meta",
        "truth_stations",
        "truth_targets",
        "truth_effects",
    ];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "truth_effects" => Some(&["effect", "where", "parameter", "value"]),
            "truth_stations" => Some(&[
                "station",
                "x_mm",
                "y_mm",
                "z_mm",
                "roll_urad",
                "pitch_urad",
                "yaw_deg",
            ]),
            "truth_targets" => Some(&["target", "x_mm", "y_mm", "z_mm"]),
            _ => super::campaign_tables::columns(table),
        }
    }

    fn file(&self) -> Option<super::StageFile<'_>> {
        self.hypotheses.as_deref().map(|path| super::StageFile {
            field: "hypotheses",
            path,
            check: super::diagnose::check_hypotheses,
        })
    }

    fn validate(&self) -> Vec<Invalid> {
        let mut out = Invalid::layout(&self.layout);
        // Values for hypotheses and parameters the file has (checked
        // against it when the file loads).
        if let Some(path) = &self.hypotheses {
            if let Ok(hyps) = super::diagnose::load_hypotheses(path) {
                for (name, values) in &self.hypothesis_values {
                    match hyps.iter().find(|h| &h.name == name) {
                        None => out.push(Invalid::new(
                            format!("hypothesis_values.{name}"),
                            format!("{} has no hypothesis `{name}`", path.display()),
                        )),
                        Some(h) => {
                            for (p, v) in values {
                                if !h.params.iter().any(|q| &q.name == p) {
                                    out.push(Invalid::new(
                                        format!("hypothesis_values.{name}.{p}"),
                                        format!("hypothesis `{name}` has no parameter `{p}`"),
                                    ));
                                }
                                let finite = match v {
                                    Value::Same(x) => x.is_finite(),
                                    Value::Each(m) => m.values().all(|x| x.is_finite()),
                                };
                                if !finite {
                                    out.push(Invalid::new(
                                        format!("hypothesis_values.{name}.{p}"),
                                        "values must be finite",
                                    ));
                                }
                            }
                        }
                    }
                }
            }
        } else if !self.hypothesis_values.is_empty() {
            out.push(Invalid::new(
                "hypothesis_values",
                "`hypothesis_values` without `hypotheses = \"file.toml\"`",
            ));
        }
        out.extend(
            self.effects
                .check()
                .into_iter()
                .map(|(f, m)| Invalid::new(format!("effects.{f}"), m)),
        );
        out.extend(Invalid::noise(&self.noise));
        for (f, v, lo, hi) in [
            ("max_angle_deg", self.max_angle_deg, 0.0, 90.0),
            ("gauge_u_mm", self.gauge_u_mm, 0.0, 1.0),
            ("reference_u_mm", self.reference_u_mm, 0.0, 1.0),
            ("level_urad", self.level_urad, 0.0, 100_000.0),
            ("interval_s", self.interval_s, 0.0, 86_400.0),
        ] {
            if !(v >= lo && v <= hi) {
                out.push(Invalid::new(
                    f,
                    format!("`{f}` must lie in [{lo}, {hi}], got {v}"),
                ));
            }
        }
        if self.max_angle_deg == 0.0 {
            out.push(Invalid::new("max_angle_deg", "`max_angle_deg` must be > 0"));
        }
        // effects.md: station-drift "needs time_s"; air-refraction's readings
        // "carry the true temperature_c column".
        let needing = |what: fn(effects::Needs) -> bool| {
            let present = self.effects.present().into_iter().map(|(id, _)| id);
            present.filter(move |id| effects::kind(id).is_some_and(|k| what(k.needs)))
        };
        if !self.record_time {
            for id in needing(|n| n.time) {
                out.push(Invalid::new(
                    "record_time",
                    format!("{id} needs `time_s` in the readings: `record_time` must be true"),
                ));
            }
        }
        if !self.record_temperature {
            for id in needing(|n| n.temperature) {
                out.push(Invalid::new(
                    "record_temperature",
                    format!(
                        "{id}'s readings carry the true `temperature_c`: \
                         `record_temperature` must be true"
                    ),
                ));
            }
        }
        out
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let errors = inputs
            .optional("errors")
            .map(|t| schema::params_from(&t))
            .transpose()?;
        let sim = self.simulate(errors.as_ref())?;
        let mut out = StageOutput::default();
        for (name, df) in sim.campaign.to_tables()? {
            out = out.table(&name, df);
        }
        Ok(out
            .table("truth_stations", truth_stations(&sim)?)
            .table("truth_targets", truth_targets(&sim)?)
            .table("truth_effects", truth_effects(self, &sim)?))
    }
}

fn truth_stations(sim: &SimulatedCampaign) -> Result<DataFrame> {
    let ids: Vec<&str> = sim.poses.iter().map(|p| p.id.as_str()).collect();
    let e: Vec<(f64, f64, f64)> = sim
        .poses
        .iter()
        .map(|p| p.rotation.euler_angles())
        .collect();
    TableBuilder::new()
        .str("station", &ids)
        .f64("x_mm", sim.poses.iter().map(|p| p.position.x).collect())
        .f64("y_mm", sim.poses.iter().map(|p| p.position.y).collect())
        .f64("z_mm", sim.poses.iter().map(|p| p.position.z).collect())
        .f64("roll_urad", e.iter().map(|a| a.0 * 1e6).collect())
        .f64("pitch_urad", e.iter().map(|a| a.1 * 1e6).collect())
        .f64("yaw_deg", e.iter().map(|a| a.2.to_degrees()).collect())
        .build()
}

fn truth_targets(sim: &SimulatedCampaign) -> Result<DataFrame> {
    let ids: Vec<&str> = sim.targets.iter().map(|t| t.0.as_str()).collect();
    TableBuilder::new()
        .str("target", &ids)
        .f64("x_mm", sim.targets.iter().map(|t| t.1.x).collect())
        .f64("y_mm", sim.targets.iter().map(|t| t.1.y).collect())
        .f64("z_mm", sim.targets.iter().map(|t| t.1.z).collect())
        .build()
}

/// Every numeric parameter of every effect, one row each; `where` is a
/// station or reflector id, or `all`.
fn truth_effects(stage: &SimulateCampaignStage, sim: &SimulatedCampaign) -> Result<DataFrame> {
    let mut rows: Vec<(String, String, String, f64)> = Vec::new();
    for b in &stage.effects.blunder {
        let (parameter, value) = match b.coordinate {
            Coordinate::Az => ("az_urad", b.size_urad),
            Coordinate::El => ("el_urad", b.size_urad),
            Coordinate::D => ("d_um", b.size_um),
        };
        rows.push((
            "blunder".into(),
            b.place(),
            parameter.into(),
            value.unwrap_or(f64::NAN),
        ));
    }
    rows.extend(sim.effects.truth());
    for h in stage.injected()? {
        for p in &h.params {
            match &p.value {
                Value::Same(v) => rows.push((h.name.clone(), "all".into(), p.name.clone(), *v)),
                Value::Each(m) => rows.extend(
                    m.iter()
                        .map(|(at, v)| (h.name.clone(), at.clone(), p.name.clone(), *v)),
                ),
            }
        }
    }
    if rows.is_empty() {
        rows.push(("none".into(), "all".into(), String::new(), 0.0));
    }
    TableBuilder::new()
        .str(
            "effect",
            &rows.iter().map(|r| r.0.as_str()).collect::<Vec<_>>(),
        )
        .str(
            "where",
            &rows.iter().map(|r| r.1.as_str()).collect::<Vec<_>>(),
        )
        .str(
            "parameter",
            &rows.iter().map(|r| r.2.as_str()).collect::<Vec<_>>(),
        )
        .f64("value", rows.iter().map(|r| r.3).collect())
        .build()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn invalid_fields(toml: &str) -> Vec<String> {
        let toml = format!("layout = {{ kind = \"corner\" }}\n{toml}");
        let stage: SimulateCampaignStage = toml::from_str(&toml).unwrap();
        stage.validate().into_iter().map(|i| i.field).collect()
    }

    #[test]
    fn effects_that_need_time_or_temperature_require_them_recorded() {
        let fields = invalid_fields(
            "record_time = false\nrecord_temperature = false\n\
             [effects.station-drift]\nvelocity_um_per_min = [1.0, 0.0, 0.0]\n\
             [effects.air-refraction]\namplitude_c = 0.5\n",
        );
        assert_eq!(fields, ["record_time", "record_temperature"]);
    }

    #[test]
    fn a_non_finite_effect_parameter_is_named() {
        let fields = invalid_fields(
            "[effects.station-drift]\nvelocity_um_per_min = [1.0, nan, 0.0]\n\
             [effects.encoder-harmonic]\norder = 3\namplitude_urad = 2.0\nphase_deg = inf\n",
        );
        assert_eq!(
            fields,
            [
                "effects.encoder-harmonic.phase_deg",
                "effects.station-drift.velocity_um_per_min"
            ]
        );
    }

    #[test]
    fn noise_under_effects_points_to_the_stages_noise_table() {
        let fields = invalid_fields("[effects.noise]\nsigma_angle_urad = 1.0\n");
        assert_eq!(fields, ["effects.noise"]);
    }

    #[test]
    fn campaign_tables_are_the_campaign_group() {
        assert_eq!(
            &SimulateCampaignStage::OUTPUTS[..4],
            crate::campaign::TABLES
        );
    }
}
