//! `open_world_check`: many campaigns simulated with an effect *outside*
//! the catalogue (and, in `unknown-and-effect` cases, one of the catalogue
//! beside it), diagnosed blind, and the diagnosis scored on its honesty:
//! does it say the residual is not explained, rather than present
//! catalogue effects as the cause? See [`crate::diagnose::open_check`],
//! which also defines which cases are detectable.
//!
//! ```toml
//! [stages.open]
//! kind = "open_world_check"
//! cases = 200
//! first_case = 0                       # cases first_case … first_case + cases − 1
//! seed = 0
//! layouts = ["corner", "hall", "cmm-table"]
//! stations = [4, 6]                    # inclusive range
//! noise_angle_urad = [0.5, 1.5]        # range of σ
//! noise_range_um = [1.0, 3.0]
//! kinds = ["unknown", "unknown-and-effect", "wrong-model-and-effect"]
//! unknowns = ["tripod-knock", "adm-cyclic", "part-expansion", "axis-wobble",
//!             "beam-bending", "two-smr-kinds", "adm-reset"]   # open_world's ids
//! effects = ["incidence", "range-scale", …]   # the catalogue's, but those drawn only alone
//! model = "api-tracker3"               # the model the campaigns declare
//! wrong_model = "mirror-tracker"       # the true model of wrong-model cases
//!                                      # (default: the first other model)
//! large_size = [2.0, 4.0]              # their effect, × the blind check's size
//! tracker_sigma = 5.0                  # µm / µrad of the kinematic errors
//! detect_chi2 = 25.0
//! mc_draws = 20
//! ```
//!
//! Outputs: `cases` (one row per campaign: `case`, `kind`, `layout`,
//! `stations`, `readings`, `sigma_angle_urad`, `sigma_range_um`,
//! `unknown`, `unknown_factor`, `unknown_description`, `signal_chi2`,
//! `detectable`, `signal_beyond_catalogue_chi2`, `distinguishable` (see
//! [`crate::diagnose::open_check`]); the catalogue effect `known_effect`, `known_where`,
//! `known_true_magnitude`, `known_signal_chi2`, `known_detectable`, `known_named`,
//! `known_named_magnitude`, `known_magnitude_u`, `known_unit`,
//! `magnitude_within_3u` (empty or null without one); `mismatch_named`
//! (wrong-model cases; null in others); the diagnosis
//! `not_explained`, `catalogue_as_cause`, `top_factor`, `factor_correct`,
//! `false_blunders`, `clean_readings`, `spurious_effects`, `named_set`,
//! `verdict`) and `summary` (rows per kind over every unknown, over all
//! cases, and per unknown over every kind: `kind`, `unknown`, `cases`,
//! `detectable_cases`, and on detectable cases with an open-world effect
//! `not_explained_pct`,
//! `catalogue_as_cause_pct`, `factor_correct_pct`,
//! `false_blunders_per_1000` clean readings, `spurious_effects_per_case`,
//! `with_known`, `catalogue_named_pct` of those with a catalogue effect,
//! `with_known_detectable`, `catalogue_named_detectable_pct` of those whose
//! catalogue effect is detectable on its own,
//! `magnitude_within_3u_pct` of those named; `distinguishable_cases` and on
//! them `not_explained_distinguishable_pct`,
//! `catalogue_as_cause_distinguishable_pct`,
//! `factor_correct_distinguishable_pct`; `mismatch_cases` — the detectable
//! wrong-model cases — and on them `mismatch_named_pct`;
//! `mismatch_distinguishable_cases` and on them
//! `mismatch_named_distinguishable_pct`; NaN where nothing is counted).
//!
//! A case is drawn from `seed` and its number alone, as in `blind_check`;
//! the check is not split into sweep blocks (no summary stage reads its
//! `cases` back).

// The same defaults and checks as `blind_check`'s, so that the two checks
// draw comparable campaigns.
use super::blind_check::{
    CampaignSettings, default_angle, default_cases, default_detect, default_draws, default_layouts,
    default_range, default_stations, default_tracker, invalid_effects, invalid_scoring,
};
use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput};
use crate::diagnose::open_check::{self, Case, CaseKind, Plan, Rates};
use crate::effects;
use crate::layout::Kind;
use crate::open_world;
use crate::table::TableBuilder;
use crate::trackers::TrackerModel;
use anyhow::Result;
use polars::prelude::DataFrame;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct OpenWorldCheckStage {
    /// Number of campaigns simulated and diagnosed.
    #[serde(default = "default_cases")]
    pub cases: usize,
    /// The first case's number: cases `first_case … first_case + cases − 1`.
    #[serde(default)]
    pub first_case: usize,
    /// Seed of the whole check: a case is drawn from it and its number alone.
    #[serde(default)]
    pub seed: u64,
    /// Layouts drawn from: `corner`, `hall`, `cmm-table`.
    #[serde(default = "default_layouts")]
    pub layouts: Vec<Kind>,
    /// Range of station counts `[low, high]`, inclusive.
    #[serde(default = "default_stations")]
    pub stations: [usize; 2],
    /// Range of the angle noise σ, µrad.
    #[serde(default = "default_angle")]
    pub noise_angle_urad: [f64; 2],
    /// Range of the range noise σ, µm.
    #[serde(default = "default_range")]
    pub noise_range_um: [f64; 2],
    /// Case kinds: `unknown`, `unknown-and-effect`, `wrong-model-and-effect`.
    #[serde(default = "default_kinds")]
    pub kinds: Vec<CaseKind>,
    /// Open-world effect ids drawn from (`tripod-knock`, `adm-cyclic`, …).
    #[serde(default = "default_unknowns")]
    pub unknowns: Vec<String>,
    /// Catalogue effect ids drawn beside an unknown one.
    #[serde(default = "default_effects")]
    pub effects: Vec<String>,
    /// The model the campaigns declare.
    #[serde(default)]
    pub model: TrackerModel,
    /// The true model of wrong-model cases (default: the first other model).
    #[serde(default)]
    pub wrong_model: Option<TrackerModel>,
    /// Range of the wrong-model cases' effect size, × the blind check's.
    #[serde(default = "default_large_size")]
    pub large_size: [f64; 2],
    /// 1 σ of the trackers' kinematic errors, µm and µrad.
    #[serde(default = "default_tracker")]
    pub tracker_sigma: f64,
    /// Δχ² above which a case's effect counts as detectable.
    #[serde(default = "default_detect")]
    pub detect_chi2: f64,
    /// Monte Carlo draws of each diagnosis's noise floor.
    #[serde(default = "default_draws")]
    pub mc_draws: usize,
}

fn default_kinds() -> Vec<CaseKind> {
    CaseKind::ALL.to_vec()
}
fn default_large_size() -> [f64; 2] {
    [2.0, 4.0]
}
fn default_unknowns() -> Vec<String> {
    open_world::KINDS.iter().map(|k| k.to_string()).collect()
}
/// An effect drawn only alone (a second model of another effect's error)
/// is not drawn beside an unknown one.
fn default_effects() -> Vec<String> {
    effects::kinds()
        .iter()
        .filter(|k| !k.alone)
        .map(|k| k.id.to_string())
        .collect()
}
impl OpenWorldCheckStage {
    fn campaign_settings(&self) -> CampaignSettings<'_> {
        CampaignSettings {
            cases: self.cases,
            first_case: self.first_case,
            layouts: &self.layouts,
            stations: self.stations,
            noise_angle_urad: self.noise_angle_urad,
            noise_range_um: self.noise_range_um,
            model: self.model,
            tracker_sigma: self.tracker_sigma,
        }
    }

    /// The true model of wrong-model cases: as set, or the registry's
    /// first model other than the declared one.
    fn wrong_model(&self) -> TrackerModel {
        self.wrong_model.unwrap_or_else(|| {
            TrackerModel::ALL
                .into_iter()
                .find(|&m| m != self.model)
                .unwrap_or(self.model)
        })
    }

    /// The plan of the settings (after [`StageKind::validate`]: every
    /// unknown id parses).
    pub fn plan(&self) -> Plan {
        Plan {
            cases: self.cases,
            first: self.first_case,
            seed: self.seed,
            campaigns: self.campaign_settings().campaigns(),
            kinds: self.kinds.clone(),
            unknowns: self
                .unknowns
                .iter()
                .filter_map(|u| open_world::parse(u))
                .collect(),
            effects: self.effects.clone(),
            wrong_model: self.wrong_model(),
            large_size: (self.large_size[0], self.large_size[1]),
            detect_chi2: self.detect_chi2,
            mc_draws: self.mc_draws,
        }
    }
}

const CASES: &[&str] = &[
    "case",
    "kind",
    "layout",
    "stations",
    "readings",
    "sigma_angle_urad",
    "sigma_range_um",
    "unknown",
    "unknown_factor",
    "unknown_description",
    "signal_chi2",
    "detectable",
    "signal_beyond_catalogue_chi2",
    "distinguishable",
    "known_effect",
    "known_where",
    "known_true_magnitude",
    "known_signal_chi2",
    "known_detectable",
    "known_named",
    "known_named_magnitude",
    "known_magnitude_u",
    "known_unit",
    "magnitude_within_3u",
    "mismatch_named",
    "not_explained",
    "catalogue_as_cause",
    "top_factor",
    "factor_correct",
    "false_blunders",
    "clean_readings",
    "spurious_effects",
    "named_set",
    "verdict",
];

const SUMMARY: &[&str] = &[
    "kind",
    "unknown",
    "cases",
    "detectable_cases",
    "not_explained_pct",
    "catalogue_as_cause_pct",
    "factor_correct_pct",
    "false_blunders_per_1000",
    "spurious_effects_per_case",
    "with_known",
    "catalogue_named_pct",
    "with_known_detectable",
    "catalogue_named_detectable_pct",
    "magnitude_within_3u_pct",
    "distinguishable_cases",
    "not_explained_distinguishable_pct",
    "catalogue_as_cause_distinguishable_pct",
    "factor_correct_distinguishable_pct",
    "mismatch_cases",
    "mismatch_named_pct",
    "mismatch_distinguishable_cases",
    "mismatch_named_distinguishable_pct",
];

impl StageKind for OpenWorldCheckStage {
    const KIND: &'static str = "open_world_check";
    const SUMMARY: &'static str = "simulated campaigns with an effect outside the catalogue, \
         diagnosed blind and scored on honesty (is the residual left unexplained?)";
    const INPUTS: &'static [Slot] = &[];
    const OUTPUTS: &'static [&'static str] = &["summary", "cases"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "cases" => Some(CASES),
            "summary" => Some(SUMMARY),
            _ => None,
        }
    }

    fn validate(&self) -> Vec<Invalid> {
        let mut out = self.campaign_settings().invalid();
        if self.kinds.is_empty() {
            out.push(Invalid::new("kinds", "`kinds` needs at least one kind"));
        }
        if self.unknowns.is_empty() {
            out.push(Invalid::new(
                "unknowns",
                "`unknowns` needs at least one effect",
            ));
        }
        for (i, u) in self.unknowns.iter().enumerate() {
            if open_world::parse(u).is_none() {
                out.push(Invalid::new(
                    format!("unknowns.{i}"),
                    format!(
                        "`{u}` is not an open-world effect; one of {}",
                        open_world::KINDS.join(", ")
                    ),
                ));
            }
        }
        out.extend(invalid_effects(&self.effects));
        if self.effects.is_empty() && self.kinds.iter().any(|k| *k != CaseKind::Unknown) {
            out.push(Invalid::new(
                "effects",
                "`effects` needs at least one effect for `unknown-and-effect` and `wrong-model-and-effect` cases",
            ));
        }
        if self.kinds.contains(&CaseKind::WrongModelAndEffect) && self.wrong_model() == self.model {
            out.push(Invalid::new(
                "wrong_model",
                format!(
                    "`wrong_model` must differ from `model` (`{}`): the campaigns declare `model`",
                    self.model
                ),
            ));
        }
        let [lo, hi] = self.large_size;
        if !(lo.is_finite() && hi.is_finite() && 0.0 < lo && lo <= hi) {
            out.push(Invalid::new(
                "large_size",
                "`large_size` must be two finite sizes 0 < low ≤ high",
            ));
        }
        out.extend(invalid_scoring(self.tracker_sigma, self.detect_chi2));
        out
    }

    fn run(&self, _: &Context, _: &StageInputs) -> Result<StageOutput> {
        let cases = open_check::run(&self.plan())?;
        Ok(StageOutput::default()
            .table("summary", summary_table(&cases)?)
            .table("cases", cases_table(&cases)?))
    }
}

/// Per kind (every unknown), over all, then per unknown (every kind).
fn summary_table(cases: &[Case]) -> Result<DataFrame> {
    let mut rows: Vec<(&str, &str, Rates)> = Vec::new();
    for k in CaseKind::ALL {
        if cases.iter().any(|c| c.kind == k) {
            let of_kind = cases.iter().filter(|c| c.kind == k);
            rows.push((k.name(), "all", Rates::of(of_kind)));
        }
    }
    rows.push(("all", "all", Rates::of(cases.iter())));
    for u in open_world::KINDS {
        if cases.iter().any(|c| c.unknown == *u) {
            rows.push((
                "all",
                u,
                Rates::of(cases.iter().filter(|c| c.unknown == *u)),
            ));
        }
    }
    let n = |f: fn(&Rates) -> usize| rows.iter().map(|r| f(&r.2) as i64).collect();
    let x = |f: fn(&Rates) -> f64| rows.iter().map(|r| f(&r.2)).collect();
    let pct = |f: fn(&Rates) -> f64| rows.iter().map(|r| 100.0 * f(&r.2)).collect();
    TableBuilder::new()
        .str("kind", &rows.iter().map(|r| r.0).collect::<Vec<_>>())
        .str("unknown", &rows.iter().map(|r| r.1).collect::<Vec<_>>())
        .i64("cases", n(|r| r.cases))
        .i64("detectable_cases", n(|r| r.detectable_cases))
        .f64("not_explained_pct", pct(Rates::not_explained_rate))
        .f64(
            "catalogue_as_cause_pct",
            pct(Rates::catalogue_as_cause_rate),
        )
        .f64("factor_correct_pct", pct(Rates::factor_correct_rate))
        .f64("false_blunders_per_1000", x(Rates::false_blunders_per_1000))
        .f64(
            "spurious_effects_per_case",
            x(Rates::spurious_effects_per_case),
        )
        .i64("with_known", n(|r| r.with_known))
        .f64("catalogue_named_pct", pct(Rates::catalogue_named_rate))
        .i64("with_known_detectable", n(|r| r.with_known_detectable))
        .f64(
            "catalogue_named_detectable_pct",
            pct(Rates::catalogue_named_detectable_rate),
        )
        .f64(
            "magnitude_within_3u_pct",
            pct(Rates::magnitude_within_3u_rate),
        )
        .i64("distinguishable_cases", n(|r| r.distinguishable_cases))
        .f64(
            "not_explained_distinguishable_pct",
            pct(Rates::distinguishable_not_explained_rate),
        )
        .f64(
            "catalogue_as_cause_distinguishable_pct",
            pct(Rates::distinguishable_catalogue_as_cause_rate),
        )
        .f64(
            "factor_correct_distinguishable_pct",
            pct(Rates::distinguishable_factor_correct_rate),
        )
        .i64("mismatch_cases", n(|r| r.mismatch_cases))
        .f64("mismatch_named_pct", pct(Rates::mismatch_named_rate))
        .i64(
            "mismatch_distinguishable_cases",
            n(|r| r.mismatch_distinguishable_cases),
        )
        .f64(
            "mismatch_named_distinguishable_pct",
            pct(Rates::mismatch_named_distinguishable_rate),
        )
        .build()
}

fn cases_table(cases: &[Case]) -> Result<DataFrame> {
    let s = |f: fn(&Case) -> String| cases.iter().map(f).collect::<Vec<String>>();
    let x = |f: fn(&Case) -> f64| cases.iter().map(f).collect::<Vec<f64>>();
    let n = |f: fn(&Case) -> usize| cases.iter().map(|c| f(c) as i64).collect::<Vec<i64>>();
    let b = |f: fn(&Case) -> bool| cases.iter().map(f).collect::<Vec<bool>>();
    // The catalogue effect's columns: empty, NaN or null without one.
    let known_s = |f: fn(&open_check::Known) -> String| {
        cases
            .iter()
            .map(|c| c.known.as_ref().map_or(String::new(), f))
            .collect::<Vec<String>>()
    };
    let known_x = |f: fn(&open_check::Known) -> f64| {
        cases
            .iter()
            .map(|c| c.known.as_ref().map_or(f64::NAN, f))
            .collect::<Vec<f64>>()
    };
    let known_opt = |f: fn(&open_check::Known) -> Option<f64>| {
        cases
            .iter()
            .map(|c| c.known.as_ref().and_then(f))
            .collect::<Vec<Option<f64>>>()
    };
    let known_flag = |f: fn(&open_check::Known) -> Option<bool>| {
        cases
            .iter()
            .map(|c| c.known.as_ref().and_then(f))
            .collect::<Vec<Option<bool>>>()
    };
    TableBuilder::new()
        .i64("case", n(|c| c.case))
        .str("kind", &s(|c| c.kind.name().to_string()))
        .str("layout", &s(|c| c.layout.clone()))
        .i64("stations", n(|c| c.stations))
        .i64("readings", n(|c| c.readings))
        .f64("sigma_angle_urad", x(|c| c.sigma_angle_urad))
        .f64("sigma_range_um", x(|c| c.sigma_range_um))
        .str("unknown", &s(|c| c.unknown.to_string()))
        .str("unknown_factor", &s(|c| c.unknown_factor.to_string()))
        .str("unknown_description", &s(|c| c.unknown_description.clone()))
        .f64("signal_chi2", x(|c| c.signal_chi2))
        .bool("detectable", b(|c| c.detectable))
        .f64(
            "signal_beyond_catalogue_chi2",
            x(|c| c.signal_beyond_catalogue_chi2),
        )
        .bool("distinguishable", b(|c| c.distinguishable))
        .str("known_effect", &known_s(|k| k.effect.clone()))
        .str("known_where", &known_s(|k| k.place.clone()))
        .f64("known_true_magnitude", known_x(|k| k.magnitude))
        .f64("known_signal_chi2", known_x(|k| k.signal_chi2))
        .opt_bool("known_detectable", known_flag(|k| Some(k.detectable)))
        .opt_bool("known_named", known_flag(|k| Some(k.named)))
        .opt_f64("known_named_magnitude", known_opt(|k| k.named_magnitude))
        .opt_f64("known_magnitude_u", known_opt(|k| k.named_magnitude_u))
        .str("known_unit", &known_s(|k| k.unit.clone()))
        .opt_bool("magnitude_within_3u", known_flag(|k| k.within_3u))
        .opt_bool(
            "mismatch_named",
            cases.iter().map(|c| c.mismatch_named).collect(),
        )
        .bool("not_explained", b(|c| c.not_explained))
        .bool("catalogue_as_cause", b(|c| c.catalogue_as_cause))
        .str("top_factor", &s(|c| c.top_factor.clone()))
        .bool("factor_correct", b(|c| c.factor_correct))
        .i64("false_blunders", n(|c| c.false_blunders))
        .i64("clean_readings", n(|c| c.clean_readings))
        .i64("spurious_effects", n(|c| c.spurious_effects))
        .str("named_set", &s(|c| c.named_set.clone()))
        .str("verdict", &s(|c| c.verdict.clone()))
        .build()
}
