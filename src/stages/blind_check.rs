//! `blind_check`: many campaigns simulated with an effect drawn at random
//! (or none) at a random magnitude and place, diagnosed blind, scored
//! against the truth (see [`crate::diagnose::blind`], which also defines
//! which cases are detectable at all).
//!
//! ```toml
//! [stages.blind]
//! kind = "blind_check"
//! cases = 200
//! first_case = 0                       # cases first_case … first_case + cases − 1
//! seed = 1
//! layouts = ["corner", "hall", "cmm-table"]
//! stations = [4, 6]                    # inclusive range
//! noise_angle_urad = [0.5, 1.5]        # range of σ
//! noise_range_um = [1.0, 3.0]
//! none_fraction = 0.25
//! effects = ["incidence", "incidence-table9", "range-scale", "air-refraction",
//!            "encoder-harmonic", "station-drift", "target-shift"]
//! kinds = ["single", "two-face", "no-time", "two-effects", "blunder",
//!          "blunders", "blunder-and-effect"]   # besides `none`
//! model = "api-tracker3"               # the trackers' model ("mirror-tracker"), diagnosed as theirs
//! tracker_sigma = 5.0                  # µm / µrad of the kinematic errors
//! detect_chi2 = 25.0
//! mc_draws = 20
//! ```
//!
//! A case is drawn from `seed` and its number alone, so a big check can be
//! split into blocks of cases — a sweep over `first_case`, each block a
//! sweep point that a cluster runs as a task of its own — and scored whole
//! by `blind_summary` on the gathered `cases`: the same cases and the same
//! scores as one check of them all.
//!
//! Outputs: `cases` (one row per campaign: `case`, `kind`, `layout`, `stations`,
//! `readings`, `sigma_angle_urad`, `sigma_range_um`, `true_effect`,
//! `true_where`, `true_magnitude`, `signal_chi2`, `detectable`,
//! `named_effect`, `named_where`, `named_magnitude`, `effect_correct`,
//! `where_correct`, `magnitude_ratio`, and the case as a set: `true_set`,
//! `named_set`, `members`, `members_detectable`, `members_found`,
//! `spurious`, `blunders`, `blunders_found`, `false_blunders`,
//! `time_effect_without_time`, `detectable_blunders`, `clean_readings`,
//! `not_explained` — the verdict declares the readings not (fully)
//! explained, a false flag on these campaigns of catalogue effects), `confusion` (single-effect kinds; `subset`
//! = all or detectable, `true_effect`, `named_effect`, `count`), `summary`
//! (single-effect kinds: `subset`, `cases`, `effect_accuracy_pct` over
//! campaigns with an effect, `where_accuracy_pct` over those with a station
//! or reflector, `none_accuracy_pct` over effect-free campaigns,
//! `median_magnitude_error_pct`), `kinds` (per kind and over all: `kind`,
//! `cases`, `detectable_cases`, `all_found_pct` — every member of a fully
//! detectable case in the explanation set — `spurious_free_pct`,
//! `detectable_blunders`, `blunders_found_pct`, `false_blunders_per_1000` clean
//! readings, `time_effects_without_time`, `not_explained_pct`) and the figure `confusion.svg`.

use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput};
use crate::diagnose::blind::{self, Campaigns, Case, CaseKind, Plan, Score, SetAccuracy};
use crate::effects;
use crate::layout::Kind;
use crate::plots;
use crate::table::TableBuilder;
use crate::trackers::TrackerModel;
use anyhow::Result;
use polars::prelude::DataFrame;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct BlindCheckStage {
    /// Number of campaigns simulated and diagnosed.
    #[serde(default = "default_cases")]
    pub cases: usize,
    /// The first case's number: cases `first_case … first_case + cases − 1`
    /// (blocks of a split check).
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
    /// Fraction of single-effect cases with no effect at all.
    #[serde(default = "default_none")]
    pub none_fraction: f64,
    /// Effect ids drawn from.
    #[serde(default = "default_effects")]
    pub effects: Vec<String>,
    /// Case kinds drawn besides `none`: `single`, `two-face`, `no-time`,
    /// `two-effects`, `blunder`, `blunders`, `blunder-and-effect`.
    #[serde(default = "default_kinds")]
    pub kinds: Vec<CaseKind>,
    /// The trackers' model, diagnosed as theirs.
    #[serde(default)]
    pub model: TrackerModel,
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

pub(super) fn default_cases() -> usize {
    200
}
pub(super) fn default_layouts() -> Vec<Kind> {
    vec![Kind::Corner, Kind::Hall, Kind::CmmTable]
}
pub(super) fn default_stations() -> [usize; 2] {
    [4, 6]
}
pub(super) fn default_angle() -> [f64; 2] {
    [0.5, 1.5]
}
pub(super) fn default_range() -> [f64; 2] {
    [1.0, 3.0]
}
fn default_none() -> f64 {
    0.25
}
pub(super) fn default_effects() -> Vec<String> {
    effects::kinds().iter().map(|k| k.id.to_string()).collect()
}
fn default_kinds() -> Vec<CaseKind> {
    CaseKind::ALL.to_vec()
}
pub(super) fn default_tracker() -> f64 {
    5.0
}
pub(super) fn default_detect() -> f64 {
    25.0
}
pub(super) fn default_draws() -> usize {
    20
}

impl BlindCheckStage {
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

    pub fn plan(&self) -> Plan {
        Plan {
            cases: self.cases,
            first: self.first_case,
            seed: self.seed,
            campaigns: self.campaign_settings().campaigns(),
            none_fraction: self.none_fraction,
            effects: self.effects.clone(),
            kinds: self.kinds.clone(),
            detect_chi2: self.detect_chi2,
            mc_draws: self.mc_draws,
        }
    }
}

impl StageKind for BlindCheckStage {
    const KIND: &'static str = "blind_check";
    const SUMMARY: &'static str =
        "simulated campaigns with a hidden effect, diagnosed blind and scored (confusion matrix)";
    const INPUTS: &'static [Slot] = &[];
    const OUTPUTS: &'static [&'static str] = &["summary", "cases", "confusion", "kinds"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "cases" => Some(&[
                "case",
                "layout",
                "stations",
                "readings",
                "sigma_angle_urad",
                "sigma_range_um",
                "true_effect",
                "true_where",
                "true_magnitude",
                "signal_chi2",
                "detectable",
                "named_effect",
                "named_where",
                "named_magnitude",
                "effect_correct",
                "where_correct",
                "magnitude_ratio",
                "kind",
                "true_set",
                "named_set",
                "members",
                "members_detectable",
                "members_found",
                "spurious",
                "blunders",
                "blunders_found",
                "false_blunders",
                "time_effect_without_time",
                "detectable_blunders",
                "clean_readings",
                "not_explained",
            ]),
            "kinds" => Some(&[
                "kind",
                "cases",
                "detectable_cases",
                "all_found_pct",
                "spurious_free_pct",
                "detectable_blunders",
                "blunders_found_pct",
                "false_blunders_per_1000",
                "time_effects_without_time",
                "not_explained_pct",
            ]),
            "confusion" => Some(&["subset", "true_effect", "named_effect", "count"]),
            "summary" => Some(&[
                "subset",
                "cases",
                "effect_accuracy_pct",
                "where_accuracy_pct",
                "none_accuracy_pct",
                "median_magnitude_error_pct",
                "with_effect",
                "with_place",
                "effect_free",
            ]),
            _ => None,
        }
    }

    fn validate(&self) -> Vec<Invalid> {
        let mut out = self.campaign_settings().invalid();
        if !(0.0..=1.0).contains(&self.none_fraction) {
            out.push(Invalid::new(
                "none_fraction",
                "`none_fraction` must lie in [0, 1]",
            ));
        }
        out.extend(invalid_effects(&self.effects));
        if self.kinds.is_empty() || self.kinds.contains(&CaseKind::None) {
            out.push(Invalid::new(
                "kinds",
                "`kinds` needs at least one kind, and not `none` (its share is `none_fraction`)",
            ));
        }
        out.extend(invalid_scoring(self.tracker_sigma, self.detect_chi2));
        out
    }

    fn run(&self, _: &Context, _: &StageInputs) -> Result<StageOutput> {
        let cases = blind::run(&self.plan())?;
        scored(&cases, &self.effects)
    }
}

/// The settings a check draws its campaigns with, as `blind_check` and
/// `open_world_check` both write them: one checking and one conversion for
/// both.
pub(super) struct CampaignSettings<'a> {
    pub cases: usize,
    pub first_case: usize,
    pub layouts: &'a [Kind],
    pub stations: [usize; 2],
    pub noise_angle_urad: [f64; 2],
    pub noise_range_um: [f64; 2],
    pub model: TrackerModel,
    pub tracker_sigma: f64,
}

impl CampaignSettings<'_> {
    /// The problems of the case range, layouts, station range and noise
    /// ranges (`tracker_sigma`'s: [`invalid_scoring`]).
    pub(super) fn invalid(&self) -> Vec<Invalid> {
        let mut out = Vec::new();
        if !(1..=100_000).contains(&self.cases) {
            out.push(Invalid::new("cases", "`cases` must be 1 … 100000"));
        }
        if self.first_case > 100_000_000 {
            out.push(Invalid::new(
                "first_case",
                "`first_case` must be 0 … 100000000",
            ));
        }
        if self.layouts.is_empty() {
            out.push(Invalid::new(
                "layouts",
                "`layouts` needs at least one layout",
            ));
        }
        if !(2 <= self.stations[0]
            && self.stations[0] <= self.stations[1]
            && self.stations[1] <= 20)
        {
            out.push(Invalid::new(
                "stations",
                "`stations` must be [lo, hi] with 2 ≤ lo ≤ hi ≤ 20",
            ));
        }
        for (f, r) in [
            ("noise_angle_urad", self.noise_angle_urad),
            ("noise_range_um", self.noise_range_um),
        ] {
            if !(r[0] > 0.0 && r[0] <= r[1] && r[1].is_finite()) {
                out.push(Invalid::new(
                    f,
                    format!("`{f}` must be [lo, hi] with 0 < lo ≤ hi"),
                ));
            }
        }
        out
    }

    pub(super) fn campaigns(&self) -> Campaigns {
        Campaigns {
            layouts: self.layouts.to_vec(),
            stations: (self.stations[0], self.stations[1]),
            noise_angle_urad: (self.noise_angle_urad[0], self.noise_angle_urad[1]),
            noise_range_um: (self.noise_range_um[0], self.noise_range_um[1]),
            tracker: self.model,
            tracker_sigma: self.tracker_sigma,
        }
    }
}

/// The problems of the kinematic errors' σ and the detection threshold.
pub(super) fn invalid_scoring(tracker_sigma: f64, detect_chi2: f64) -> Vec<Invalid> {
    let mut out = Vec::new();
    if !(tracker_sigma >= 0.0 && tracker_sigma.is_finite()) {
        out.push(Invalid::new("tracker_sigma", "`tracker_sigma` must be ≥ 0"));
    }
    if detect_chi2.is_nan() || detect_chi2 <= 0.0 {
        out.push(Invalid::new("detect_chi2", "`detect_chi2` must be > 0"));
    }
    out
}

/// The effect ids that are not effects a blind check hides, at their place.
pub(super) fn invalid_effects(ids: &[String]) -> Vec<Invalid> {
    ids.iter()
        .enumerate()
        .filter(|(_, e)| effects::kind(e).is_none())
        .map(|(i, e)| {
            Invalid::new(
                format!("effects.{i}"),
                format!(
                    "`{e}` is not an effect to hide; one of {}",
                    effects::ids_joined()
                ),
            )
        })
        .collect()
}

/// The outputs of a blind check of `cases`, `effects` the ids its
/// confusion matrix has rows and columns for (with `none`): what
/// `blind_check` writes, and `blind_summary` of the same cases gathered.
pub(super) fn scored(cases: &[Case], effects: &[String]) -> Result<StageOutput> {
    let labels: Vec<String> = std::iter::once("none".to_string())
        .chain(effects.iter().cloned())
        .collect();
    // The single-effect kinds are scored by what is named first.
    let single: Vec<&Case> = cases.iter().filter(|c| c.kind.is_single()).collect();
    let detectable: Vec<&Case> = single.iter().copied().filter(|c| c.detectable).collect();
    let matrix = |subset: &[&Case]| -> Vec<Vec<usize>> {
        labels
            .iter()
            .map(|t| {
                labels
                    .iter()
                    .map(|n| {
                        subset
                            .iter()
                            .filter(|c| &c.truth.effect == t && &c.named_effect == n)
                            .count()
                    })
                    .collect()
            })
            .collect()
    };
    let all = single;
    let svg = plots::confusion_matrix(
        "Blind check: true effect (rows) against the diagnosis (columns), detectable cases",
        &labels,
        &matrix(&detectable),
    )?;
    Ok(StageOutput::default()
        .table("summary", summary(&all, &detectable)?)
        .table("cases", cases_table(cases)?)
        .table(
            "confusion",
            confusion_table(
                &labels,
                &[("all", matrix(&all)), ("detectable", matrix(&detectable))],
            )?,
        )
        .table("kinds", kinds_table(cases)?)
        .file("confusion.svg".into(), svg.into_bytes()))
}

/// Set-level accuracy per kind drawn, then over every case.
fn kinds_table(cases: &[Case]) -> Result<DataFrame> {
    let mut kinds: Vec<CaseKind> = cases.iter().map(|c| c.kind).collect();
    kinds.sort();
    kinds.dedup();
    let mut rows: Vec<(&str, SetAccuracy)> = kinds
        .iter()
        .map(|k| {
            (
                k.name(),
                SetAccuracy::of(cases.iter().filter(|c| c.kind == *k)),
            )
        })
        .collect();
    rows.push(("all", SetAccuracy::of(cases.iter())));
    let pct = |f: fn(&SetAccuracy) -> f64| rows.iter().map(|r| 100.0 * f(&r.1)).collect();
    TableBuilder::new()
        .str("kind", &rows.iter().map(|r| r.0).collect::<Vec<_>>())
        .i64("cases", rows.iter().map(|r| r.1.cases as i64).collect())
        .i64(
            "detectable_cases",
            rows.iter().map(|r| r.1.detectable_cases as i64).collect(),
        )
        .f64("all_found_pct", pct(SetAccuracy::all_found_rate))
        .f64("spurious_free_pct", pct(SetAccuracy::spurious_free_rate))
        .i64(
            "detectable_blunders",
            rows.iter()
                .map(|r| r.1.detectable_blunders as i64)
                .collect(),
        )
        .f64("blunders_found_pct", pct(SetAccuracy::blunder_rate))
        .f64(
            "false_blunders_per_1000",
            rows.iter().map(|r| r.1.false_blunders_per_1000()).collect(),
        )
        .i64(
            "time_effects_without_time",
            rows.iter()
                .map(|r| r.1.time_effects_without_time as i64)
                .collect(),
        )
        .f64("not_explained_pct", pct(SetAccuracy::not_explained_rate))
        .build()
}

fn summary(all: &[&Case], detectable: &[&Case]) -> Result<DataFrame> {
    let rows: Vec<(&str, Score)> = vec![
        ("all", Score::of(all.iter().copied())),
        ("detectable", Score::of(detectable.iter().copied())),
    ];
    TableBuilder::new()
        .str("subset", &rows.iter().map(|r| r.0).collect::<Vec<_>>())
        .i64("cases", rows.iter().map(|r| r.1.cases as i64).collect())
        .f64(
            "effect_accuracy_pct",
            rows.iter().map(|r| 100.0 * r.1.effect_rate()).collect(),
        )
        .f64(
            "where_accuracy_pct",
            rows.iter().map(|r| 100.0 * r.1.place_rate()).collect(),
        )
        .f64(
            "none_accuracy_pct",
            rows.iter().map(|r| 100.0 * r.1.none_rate()).collect(),
        )
        .f64(
            "median_magnitude_error_pct",
            rows.iter()
                .map(|r| 100.0 * r.1.median_magnitude_error)
                .collect(),
        )
        .i64(
            "with_effect",
            rows.iter().map(|r| r.1.with_effect as i64).collect(),
        )
        .i64(
            "with_place",
            rows.iter().map(|r| r.1.with_place as i64).collect(),
        )
        .i64(
            "effect_free",
            rows.iter().map(|r| r.1.effect_free as i64).collect(),
        )
        .build()
}

fn cases_table(cases: &[Case]) -> Result<DataFrame> {
    let s = |f: fn(&Case) -> String| cases.iter().map(f).collect::<Vec<String>>();
    let x = |f: fn(&Case) -> f64| cases.iter().map(f).collect::<Vec<f64>>();
    let n = |f: fn(&Case) -> usize| cases.iter().map(|c| f(c) as i64).collect::<Vec<i64>>();
    TableBuilder::new()
        .i64("case", cases.iter().map(|c| c.case as i64).collect())
        .str("layout", &s(|c| c.layout.clone()))
        .i64(
            "stations",
            cases.iter().map(|c| c.stations as i64).collect(),
        )
        .i64(
            "readings",
            cases.iter().map(|c| c.readings as i64).collect(),
        )
        .f64("sigma_angle_urad", x(|c| c.sigma_angle_urad))
        .f64("sigma_range_um", x(|c| c.sigma_range_um))
        .str("true_effect", &s(|c| c.truth.effect.clone()))
        .str("true_where", &s(|c| c.truth.place.clone()))
        .f64("true_magnitude", x(|c| c.truth.magnitude))
        .f64("signal_chi2", x(|c| c.signal_chi2))
        .bool("detectable", cases.iter().map(|c| c.detectable).collect())
        .str("named_effect", &s(|c| c.named_effect.clone()))
        .str("named_where", &s(|c| c.named_place.clone()))
        .f64("named_magnitude", x(|c| c.named_magnitude))
        .bool(
            "effect_correct",
            cases.iter().map(|c| c.effect_correct).collect(),
        )
        .opt_bool(
            "where_correct",
            cases.iter().map(|c| c.place_correct).collect(),
        )
        .opt_f64(
            "magnitude_ratio",
            cases.iter().map(|c| c.magnitude_ratio).collect(),
        )
        .str(
            "kind",
            &cases.iter().map(|c| c.kind.name()).collect::<Vec<_>>(),
        )
        .str("true_set", &s(|c| c.set.true_set.clone()))
        .str("named_set", &s(|c| c.set.named_set.clone()))
        .i64("members", n(|c| c.set.members))
        .i64("members_detectable", n(|c| c.set.detectable))
        .i64("members_found", n(|c| c.set.found))
        .i64("spurious", n(|c| c.set.spurious))
        .i64("blunders", n(|c| c.set.true_blunders))
        .i64("blunders_found", n(|c| c.set.blunders_found))
        .i64("false_blunders", n(|c| c.set.false_blunders))
        .bool(
            "time_effect_without_time",
            cases
                .iter()
                .map(|c| c.set.time_effect_without_time)
                .collect(),
        )
        .i64("detectable_blunders", n(|c| c.set.detectable_blunders))
        .i64("clean_readings", n(|c| c.set.clean_readings))
        .bool(
            "not_explained",
            cases.iter().map(|c| c.set.not_explained).collect(),
        )
        .build()
}

fn confusion_table(labels: &[String], matrices: &[(&str, Vec<Vec<usize>>)]) -> Result<DataFrame> {
    let mut rows: Vec<(&str, &str, &str, i64)> = Vec::new();
    for (subset, m) in matrices {
        for (i, t) in labels.iter().enumerate() {
            for (j, n) in labels.iter().enumerate() {
                rows.push((subset, t, n, m[i][j] as i64));
            }
        }
    }
    TableBuilder::new()
        .str("subset", &rows.iter().map(|r| r.0).collect::<Vec<_>>())
        .str("true_effect", &rows.iter().map(|r| r.1).collect::<Vec<_>>())
        .str(
            "named_effect",
            &rows.iter().map(|r| r.2).collect::<Vec<_>>(),
        )
        .i64("count", rows.iter().map(|r| r.3).collect())
        .build()
}
