//! The open-world blind check (issue 30, item 3): campaigns carrying an
//! effect *outside* the catalogue, diagnosed blind, and the diagnosis
//! scored on its honesty rather than on naming the effect.
//!
//! # Why a check of its own
//!
//! The catalogue blind check ([`super::blind`]) only ever hides effects
//! the diagnosis has a candidate for, so it cannot tell a diagnosis that
//! finds causes from one that always finds *some* cause. A real campaign
//! can carry physics no one has written down; then the right answer is not
//! an effect's name but "something is left, and it lies along this
//! factor". Here every case carries one effect of [`crate::open_world`] —
//! a generator that shares no code with the catalogue or the diagnosis —
//! and, in `unknown-and-effect` cases, one catalogue effect beside it. The
//! diagnosis cannot name the unknown effect; what is scored is whether it
//! says so:
//!
//! - `not_explained` — the residual the explanation set leaves is declared
//!   inconsistent with the stated noise (the right answer on a detectable
//!   case);
//! - `catalogue_as_cause` — catalogue effects presented as the whole
//!   explanation (a non-blunder member, and the rest consistent with noise):
//!   the dishonest answer, in both kinds, since the unknown effect remains;
//! - `factor_correct` — the first significant entry of
//!   [`super::Diagnosis::unexplained`] lies along the unknown effect's
//!   factor ([`crate::open_world::OpenEffect::factor`]);
//! - false blunders and spurious catalogue effects, which an unknown
//!   effect tempts the diagnosis into;
//! - in `unknown-and-effect` cases, whether the known effect is still
//!   named, and its magnitude within 3 standard uncertainties of the truth.
//!
//! # Detectable
//!
//! As in the catalogue check: the unknown effect's signature — the
//! noise-free campaign with it applied, minus without — left after
//! projecting off what the base adjustment absorbs, amounts to
//! Δχ² ≥ `detect_chi2` in units of the stated noise
//! ([`super::blind::signal_chi2`]). Rates are reported on detectable cases;
//! below the threshold "consistent with noise" is a fair answer.
//!
//! # Distinguishable
//!
//! Some physics outside the catalogue makes the same readings as an effect
//! inside it: a part that grows as the hall warms, measured station after
//! station, is a range scale (each station's pose absorbs the centre of
//! the growth), and if the part was warmer than when its reference lengths
//! were taken it is `range-scale` at every station. No diagnosis can tell
//! them apart from the readings. A detectable case is also
//! *distinguishable* when its signature, beyond the base adjustment *and*
//! beyond the catalogue's nearest single effect (the largest Δχ² one
//! candidate's columns absorb of it), still amounts to `detect_chi2`
//! ([`super::beyond_catalogue`]). The honesty rates are reported on both:
//! on the distinguishable cases they measure the diagnosis; on the rest
//! naming the catalogue effect is what the data say.
//!
//! # A wrong model under a large effect
//!
//! `wrong-model-and-effect` cases carry no open-world effect: their
//! trackers are of another model than the campaign declares (a mirror
//! tracker declared `api-tracker3`), measured in both faces, with a
//! catalogue effect at 2–4 times the blind check's size (`large_size`). A
//! large effect can hide a wrong model, and a wrong model can inflate an
//! effect or breed blunders; the right answer names the mismatch
//! ([`super::MODEL`] at the true model) and the effect at its magnitude,
//! and no blunder. Such a case is detectable when the declared model,
//! fitted to the noise-free campaign without the effect, leaves
//! χ² ≥ `detect_chi2`, and distinguishable when the mismatch's signature
//! beyond the catalogue's nearest single effect is still that large (a
//! one-station range scale can take up a weak mismatch); its rates
//! (`mismatch_named`, the effect's and the blunders') are counted apart
//! from the honesty rates above, which concern the open-world effects
//! alone.
//!
//! Cases draw their layout, stations, noise and kinematic errors as the
//! catalogue check does ([`super::blind::Setting`]), each from its own
//! stream (`open-world-<case>`), so the result does not depend on the number
//! of threads or on how the cases are split. Campaigns always record time
//! and temperature: three of the unknown effects need time, and so may the
//! catalogue effect.

use super::Diagnosis;
use super::blind::{self, Campaigns, Measuring, Setting};
use crate::campaign::Campaign;
use crate::effects::{self, DrawContext, Effects};
use crate::error_model::{ErrorModel, ErrorParams};
use crate::noise::Noise;
use crate::open_world::{self, OpenEffect};
use crate::random;
use crate::simulate::SimulatedCampaign;
use crate::trackers::TrackerModel;
use anyhow::{Result, anyhow};
use rand::rngs::ChaCha8Rng;
use rayon::prelude::*;

/// What a case holds besides the campaign's setting.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum CaseKind {
    /// One open-world effect, no catalogue effect.
    Unknown,
    /// One open-world effect and one catalogue effect.
    UnknownAndEffect,
    /// Trackers of another model than declared, and a large catalogue
    /// effect (see the module doc).
    WrongModelAndEffect,
}

impl CaseKind {
    pub const ALL: [CaseKind; 3] = [
        CaseKind::Unknown,
        CaseKind::UnknownAndEffect,
        CaseKind::WrongModelAndEffect,
    ];

    pub fn name(self) -> &'static str {
        match self {
            CaseKind::Unknown => "unknown",
            CaseKind::UnknownAndEffect => "unknown-and-effect",
            CaseKind::WrongModelAndEffect => "wrong-model-and-effect",
        }
    }

    /// Whether its cases carry a catalogue effect (drawn from the plan's
    /// `effects`).
    fn has_effect(self) -> bool {
        self != CaseKind::Unknown
    }
}

/// How the cases are drawn (the catalogue check's plan, less what does not
/// apply: no effect-free share, no blunders, always timed, one face).
#[derive(Clone, Debug)]
pub struct Plan {
    pub cases: usize,
    /// The number of the first case: each case is drawn from `(seed, its
    /// number)` alone.
    pub first: usize,
    pub seed: u64,
    /// The campaigns' layouts, stations, noise and trackers, drawn as the
    /// catalogue check draws them.
    pub campaigns: Campaigns,
    pub kinds: Vec<CaseKind>,
    /// Open-world effects to draw from.
    pub unknowns: Vec<open_world::Kind>,
    /// Catalogue effect ids to draw from in `unknown-and-effect` and
    /// `wrong-model-and-effect` cases.
    pub effects: Vec<String>,
    /// The trackers' true model in `wrong-model-and-effect` cases (the
    /// campaigns declare `campaigns.tracker`), and the range of their
    /// effect's size, in multiples of the blind check's.
    pub wrong_model: TrackerModel,
    pub large_size: (f64, f64),
    pub detect_chi2: f64,
    /// Monte Carlo draws per diagnosis.
    pub mc_draws: usize,
}

/// The catalogue effect put into an `unknown-and-effect` case, and what the
/// diagnosis made of it.
#[derive(Clone, Debug)]
pub struct Known {
    pub effect: String,
    /// As the diagnosis names it: a station or reflector id, an axis, `all`.
    pub place: String,
    /// Whether `place` must match too (a single station, reflector or axis).
    pub has_place: bool,
    /// True magnitude, in the diagnosis's unit for the effect.
    pub magnitude: f64,
    /// Δχ² of its unabsorbed signature, alone, and whether that reaches
    /// the plan's `detect_chi2`.
    pub signal_chi2: f64,
    pub detectable: bool,
    /// It is a member of the explanation set.
    pub named: bool,
    /// The diagnosis's row for it (the set member when named, else its
    /// best-ranked row): magnitude, standard uncertainty and unit.
    pub named_magnitude: Option<f64>,
    pub named_magnitude_u: Option<f64>,
    pub unit: String,
    /// Named, and |named − true| ≤ 3·u; `None` when not named.
    pub within_3u: Option<bool>,
}

/// One case, scored.
#[derive(Clone, Debug)]
pub struct Case {
    pub case: usize,
    pub kind: CaseKind,
    pub layout: String,
    pub stations: usize,
    pub readings: usize,
    pub sigma_angle_urad: f64,
    pub sigma_range_um: f64,
    /// The open-world effect: id, factor, and its drawn values in words.
    pub unknown: &'static str,
    pub unknown_factor: &'static str,
    pub unknown_description: String,
    /// Δχ² of the unknown effect's unabsorbed signature.
    pub signal_chi2: f64,
    pub detectable: bool,
    /// Δχ² of the signature beyond the base adjustment and the
    /// catalogue's nearest single effect; `distinguishable` when a
    /// detectable case's is at least `detect_chi2`.
    pub signal_beyond_catalogue_chi2: f64,
    pub distinguishable: bool,
    pub known: Option<Known>,
    /// In `wrong-model-and-effect` cases: the mismatch named at the true
    /// model.
    pub mismatch_named: Option<bool>,
    pub not_explained: bool,
    pub catalogue_as_cause: bool,
    /// The first significant entry of `unexplained` (empty: none).
    pub top_factor: String,
    pub factor_correct: bool,
    /// Blunders in the explanation set (none were put in).
    pub false_blunders: usize,
    /// Readings of the campaign: none carries a blunder.
    pub clean_readings: usize,
    /// Non-blunder members of the set other than the known effect.
    pub spurious_effects: usize,
    pub named_set: String,
    pub verdict: String,
}

/// Runs every case (in parallel; each case has its own random stream, so
/// the result does not depend on the number of threads).
pub fn run(plan: &Plan) -> Result<Vec<Case>> {
    (plan.first..plan.first + plan.cases)
        .into_par_iter()
        .map(|k| run_case(plan, k))
        .collect()
}

/// Runs one case.
fn run_case(plan: &Plan, case: usize) -> Result<Case> {
    let needs_effects = plan.kinds.iter().any(|k| k.has_effect());
    if plan.kinds.is_empty() || plan.unknowns.is_empty() || needs_effects && plan.effects.is_empty()
    {
        return Err(anyhow!(
            "an open-world check needs kinds, unknowns and (for a kind with a catalogue effect) effects"
        ));
    }
    let mut rng = random::stream(plan.seed, &format!("open-world-{case}"));
    let setting = Setting::draw(&mut rng, &plan.campaigns);
    let kind = *random::pick(&mut rng, &plan.kinds);
    let unknown_kind = *random::pick(&mut rng, &plan.unknowns);
    if kind == CaseKind::WrongModelAndEffect {
        return wrong_model_case(plan, case, &setting, rng);
    }
    let how = Measuring {
        two_face: false,
        timed: true,
    };
    let seed = blind::case_seed(plan.seed, case);
    let mut fx = Effects::default();
    let known = if kind == CaseKind::UnknownAndEffect {
        Some(draw_known(&mut rng, plan, &setting, 1.0, &mut fx)?)
    } else {
        None
    };
    let sim = |noise: Noise, fx: &Effects| {
        blind::simulate(&setting.spec, &setting.errors, noise, fx, seed, how)
    };
    let clean = sim(Noise::default(), &Effects::default())?;
    let measured = sim(setting.noise, &fx)?;
    // The unknown effect, placed in the campaign as measured and applied
    // through the tracker's kinematic errors.
    let unknown = OpenEffect::draw(unknown_kind, &mut rng, &open_world::Context::of(&measured))
        .map_err(|e| anyhow!(e))?;
    let apply = |c: &SimulatedCampaign| {
        unknown
            .apply(c, Some(&setting.errors))
            .map_err(|e| anyhow!(e))
    };
    let noisy = apply(&measured)?;
    let d = blind::diagnose_blind(&noisy.campaign, plan.campaigns.tracker, plan.mc_draws, seed)?;
    let readings = &noisy.campaign.readings;
    let unknown_clean = apply(&clean)?;
    let delta = blind::signal(&unknown_clean.campaign, &clean.campaign, readings);
    let signal = blind::signal_chi2(&d, &delta);
    let beyond = super::beyond_catalogue(
        &noisy.campaign,
        &blind::settings(plan.campaigns.tracker, plan.mc_draws, seed),
        &delta,
    )?;
    let known = match known {
        Some(truth) => {
            let with = sim(Noise::default(), &fx.only(&truth.0))?;
            let delta = blind::signal(&with.campaign, &clean.campaign, readings);
            let signal_chi2 = blind::signal_chi2(&d, &delta);
            Some(score_known(&d, truth, signal_chi2, plan.detect_chi2))
        }
        None => None,
    };
    let named: Vec<&super::Row> = d.explanation().collect();
    let not_explained = !d.explained();
    let is_known = |r: &super::Row| {
        known
            .as_ref()
            .is_some_and(|k| r.effect == k.effect && (!k.has_place || r.place == k.place))
    };
    let effects_named = named.iter().filter(|r| r.effect != "blunder").count();
    let top_factor = top_factor(&d);
    Ok(Case {
        case,
        kind,
        layout: setting.layout_name(),
        stations: setting.stations,
        readings: readings.len(),
        sigma_angle_urad: setting.noise.sigma_angle_urad,
        sigma_range_um: setting.noise.sigma_range_um,
        unknown: unknown.id(),
        unknown_factor: unknown.factor(),
        unknown_description: unknown.describe(),
        signal_chi2: signal,
        detectable: signal >= plan.detect_chi2,
        signal_beyond_catalogue_chi2: beyond,
        distinguishable: signal >= plan.detect_chi2 && beyond >= plan.detect_chi2,
        not_explained,
        catalogue_as_cause: effects_named > 0 && d.explained(),
        factor_correct: top_factor == unknown.factor(),
        top_factor,
        false_blunders: named.iter().filter(|r| r.effect == "blunder").count(),
        clean_readings: readings.len(),
        spurious_effects: named
            .iter()
            .filter(|r| r.effect != "blunder" && !is_known(r))
            .count(),
        named_set: super::output::explanation(&d),
        verdict: super::output::verdict(&d),
        known,
        mismatch_named: None,
    })
}

/// The first significant entry of the diagnosis's `unexplained` (empty:
/// none), as both kinds of case report it.
fn top_factor(d: &Diagnosis) -> String {
    d.unexplained
        .iter()
        .find(|l| l.significant)
        .map_or(String::new(), |l| l.factor.to_string())
}

/// The catalogue effect of a case, drawn through its plug-in as the
/// catalogue check draws it, at `size` times its size: its id, place,
/// magnitude and whether it has a place.
fn draw_known(
    rng: &mut ChaCha8Rng,
    plan: &Plan,
    setting: &Setting,
    size: f64,
    fx: &mut Effects,
) -> Result<(String, String, f64, bool)> {
    let id = random::pick(rng, &plan.effects).clone();
    let draw = effects::kind(&id)
        .ok_or_else(|| anyhow!("`{id}` is not an effect of the catalogue"))?
        .draw;
    let cx = DrawContext {
        stations: &setting.station_ids,
        targets: &setting.target_ids,
        size,
    };
    let (place, magnitude, has_place) = draw(rng, &cx, fx);
    Ok((id, place, magnitude, has_place))
}

/// A `wrong-model-and-effect` case (see the module doc): the trackers'
/// kinematic errors drawn for the true model at the plan's σ, the campaign
/// declaring the plan's tracker model, both faces measured.
fn wrong_model_case(
    plan: &Plan,
    case: usize,
    setting: &Setting,
    mut rng: ChaCha8Rng,
) -> Result<Case> {
    let declared = plan.campaigns.tracker;
    let mut errors = ErrorParams::zero(&ErrorModel::of(plan.wrong_model));
    for v in errors.values_mut() {
        *v = plan.campaigns.tracker_sigma * random::normal(&mut rng);
    }
    let size = random::between(&mut rng, plan.large_size);
    let mut fx = Effects::default();
    let truth = draw_known(&mut rng, plan, setting, size, &mut fx)?;
    let how = Measuring {
        two_face: true,
        timed: true,
    };
    let seed = blind::case_seed(plan.seed, case);
    let simulate = |errors: &ErrorParams, noise: Noise, fx: &Effects| -> Result<Campaign> {
        let mut c = blind::simulate(&setting.spec, errors, noise, fx, seed, how)?.campaign;
        c.meta.tracker.model = declared.id().into();
        Ok(c)
    };
    let noisy = simulate(&errors, setting.noise, &fx)?;
    // Noise-free campaigns read with the stated σ, as the diagnosis reads
    // the noisy one.
    let clean_of = |errors: &ErrorParams, fx: &Effects| -> Result<Campaign> {
        let mut c = simulate(errors, Noise::default(), fx)?;
        c.meta.tracker = noisy.meta.tracker.clone();
        Ok(c)
    };
    let clean = clean_of(&errors, &Effects::default())?;
    let d = blind::diagnose_blind(&noisy, declared, plan.mc_draws, seed)?;
    let signal = super::models::model_leaves_chi2(&clean, declared)?;
    let with = clean_of(&errors, &fx.only(&truth.0))?;
    let readings = &noisy.readings;
    // The mismatch's signature — what the true model's errors change in
    // the readings — beyond the declared model's base adjustment and the
    // catalogue's nearest single effect: a one-station range scale can
    // take up a weak mismatch, and then the readings say no more.
    let ideal = clean_of(
        &ErrorParams::zero(&ErrorModel::of(plan.wrong_model)),
        &Effects::default(),
    )?;
    let beyond = super::beyond_catalogue(
        &noisy,
        &blind::settings(declared, plan.mc_draws, seed),
        &blind::signal(&clean, &ideal, readings),
    )?;
    let known_chi2 = blind::signal_chi2(&d, &blind::signal(&with, &clean, readings));
    let known = score_known(&d, truth, known_chi2, plan.detect_chi2);
    let named: Vec<&super::Row> = d.explanation().collect();
    let is_mismatch = |r: &super::Row| r.effect == super::MODEL;
    let is_known =
        |r: &super::Row| r.effect == known.effect && (!known.has_place || r.place == known.place);
    let effects_named = named
        .iter()
        .filter(|r| r.effect != "blunder" && !is_mismatch(r))
        .count();
    Ok(Case {
        case,
        kind: CaseKind::WrongModelAndEffect,
        layout: setting.layout_name(),
        stations: setting.stations,
        readings: readings.len(),
        sigma_angle_urad: setting.noise.sigma_angle_urad,
        sigma_range_um: setting.noise.sigma_range_um,
        unknown: plan.wrong_model.id(),
        // A model, not a structure along one factor.
        unknown_factor: "",
        unknown_description: format!(
            "a {} tracker declared {}, its errors 1 σ = {} µm and µrad; {} at {:.1} × the blind check's size",
            plan.wrong_model.id(),
            declared.id(),
            plan.campaigns.tracker_sigma,
            known.effect,
            size
        ),
        signal_chi2: signal,
        detectable: signal >= plan.detect_chi2,
        signal_beyond_catalogue_chi2: beyond,
        distinguishable: signal >= plan.detect_chi2 && beyond >= plan.detect_chi2,
        mismatch_named: Some(
            named
                .iter()
                .any(|r| is_mismatch(r) && r.place == plan.wrong_model.id()),
        ),
        not_explained: !d.explained(),
        catalogue_as_cause: effects_named > 0
            && d.explained()
            && !named.iter().any(|r| is_mismatch(r)),
        top_factor: top_factor(&d),
        factor_correct: false,
        false_blunders: named.iter().filter(|r| r.effect == "blunder").count(),
        clean_readings: readings.len(),
        spurious_effects: named
            .iter()
            .filter(|r| r.effect != "blunder" && !is_mismatch(r) && !is_known(r))
            .count(),
        named_set: super::output::explanation(&d),
        verdict: super::output::verdict(&d),
        known: Some(known),
    })
}

/// The known effect against the diagnosis: named when a set member has its
/// id (and its place, when it has one); its magnitude compared as the
/// catalogue check compares it, on the diagnosis's row for the effect.
/// `truth` is the effect's id, place, magnitude and whether it has a place.
fn score_known(
    d: &Diagnosis,
    (effect, place, magnitude, has_place): (String, String, f64, bool),
    signal_chi2: f64,
    detect_chi2: f64,
) -> Known {
    let same = |r: &&super::Row| r.effect == effect && (!has_place || r.place == place);
    let member = d.explanation().find(same);
    // Not named: its best-ranked row, for the table (rows are in rank order).
    let row = member.or_else(|| d.rows.iter().find(same));
    let within_3u = member.map(|r| (r.magnitude - magnitude).abs() <= 3.0 * r.magnitude_u);
    Known {
        named: member.is_some(),
        named_magnitude: row.map(|r| r.magnitude),
        named_magnitude_u: row.map(|r| r.magnitude_u),
        unit: row.map_or(String::new(), |r| r.unit.clone()),
        within_3u,
        effect,
        place,
        has_place,
        magnitude,
        signal_chi2,
        detectable: signal_chi2 >= detect_chi2,
    }
}

/// The honesty figures of a group of cases: counts over every case, rates
/// over the detectable ones.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Rates {
    pub cases: usize,
    pub detectable_cases: usize,
    /// Of the detectable cases: those carrying an open-world effect, and
    /// of them …
    pub unknown_cases: usize,
    pub not_explained: usize,
    pub catalogue_as_cause: usize,
    pub factor_correct: usize,
    /// … of every detectable case: …
    pub false_blunders: usize,
    pub clean_readings: usize,
    pub spurious_effects: usize,
    /// … those with a known effect, and how many of them name it;
    pub with_known: usize,
    pub known_named: usize,
    /// … the same where the known effect is detectable on its own (an
    /// undetectable one is rightly not named);
    pub with_known_detectable: usize,
    pub known_detectable_named: usize,
    /// … and of those named, how many within 3 u.
    pub within_3u: usize,
    /// The detectable cases also distinguishable from the catalogue, and
    /// the first three counts on them.
    pub distinguishable_cases: usize,
    pub distinguishable_not_explained: usize,
    pub distinguishable_catalogue_as_cause: usize,
    pub distinguishable_factor_correct: usize,
    /// The detectable `wrong-model-and-effect` cases, and how many name
    /// the mismatch; the same on those also distinguishable.
    pub mismatch_cases: usize,
    pub mismatch_named: usize,
    pub mismatch_distinguishable_cases: usize,
    pub mismatch_distinguishable_named: usize,
}

impl Rates {
    pub fn of<'a>(cases: impl Iterator<Item = &'a Case>) -> Rates {
        let mut a = Rates::default();
        for c in cases {
            a.cases += 1;
            if !c.detectable {
                continue;
            }
            a.detectable_cases += 1;
            a.false_blunders += c.false_blunders;
            a.clean_readings += c.clean_readings;
            a.spurious_effects += c.spurious_effects;
            if let Some(named) = c.mismatch_named {
                a.mismatch_cases += 1;
                a.mismatch_named += named as usize;
                if c.distinguishable {
                    a.mismatch_distinguishable_cases += 1;
                    a.mismatch_distinguishable_named += named as usize;
                }
            } else {
                a.unknown_cases += 1;
                a.not_explained += c.not_explained as usize;
                a.catalogue_as_cause += c.catalogue_as_cause as usize;
                a.factor_correct += c.factor_correct as usize;
                if c.distinguishable {
                    a.distinguishable_cases += 1;
                    a.distinguishable_not_explained += c.not_explained as usize;
                    a.distinguishable_catalogue_as_cause += c.catalogue_as_cause as usize;
                    a.distinguishable_factor_correct += c.factor_correct as usize;
                }
            }
            if let Some(k) = &c.known {
                a.with_known += 1;
                a.known_named += k.named as usize;
                a.with_known_detectable += k.detectable as usize;
                a.known_detectable_named += (k.detectable && k.named) as usize;
                a.within_3u += (k.within_3u == Some(true)) as usize;
            }
        }
        a
    }

    /// `n / of`, NaN when there is nothing to divide.
    fn share(n: usize, of: usize) -> f64 {
        if of == 0 {
            f64::NAN
        } else {
            n as f64 / of as f64
        }
    }
    /// Of the detectable cases with an open-world effect.
    pub fn not_explained_rate(&self) -> f64 {
        Rates::share(self.not_explained, self.unknown_cases)
    }
    pub fn catalogue_as_cause_rate(&self) -> f64 {
        Rates::share(self.catalogue_as_cause, self.unknown_cases)
    }
    pub fn factor_correct_rate(&self) -> f64 {
        Rates::share(self.factor_correct, self.unknown_cases)
    }
    /// Of the detectable wrong-model cases.
    pub fn mismatch_named_rate(&self) -> f64 {
        Rates::share(self.mismatch_named, self.mismatch_cases)
    }
    /// Of the distinguishable wrong-model cases.
    pub fn mismatch_named_distinguishable_rate(&self) -> f64 {
        Rates::share(
            self.mismatch_distinguishable_named,
            self.mismatch_distinguishable_cases,
        )
    }
    /// The three rates above on the distinguishable cases.
    pub fn distinguishable_not_explained_rate(&self) -> f64 {
        Rates::share(
            self.distinguishable_not_explained,
            self.distinguishable_cases,
        )
    }
    pub fn distinguishable_catalogue_as_cause_rate(&self) -> f64 {
        Rates::share(
            self.distinguishable_catalogue_as_cause,
            self.distinguishable_cases,
        )
    }
    pub fn distinguishable_factor_correct_rate(&self) -> f64 {
        Rates::share(
            self.distinguishable_factor_correct,
            self.distinguishable_cases,
        )
    }
    /// False blunders per 1 000 clean readings.
    pub fn false_blunders_per_1000(&self) -> f64 {
        1000.0 * Rates::share(self.false_blunders, self.clean_readings)
    }
    pub fn spurious_effects_per_case(&self) -> f64 {
        Rates::share(self.spurious_effects, self.detectable_cases)
    }
    /// Of detectable cases with a known effect.
    pub fn catalogue_named_rate(&self) -> f64 {
        Rates::share(self.known_named, self.with_known)
    }
    /// Of detectable cases with a known effect detectable on its own.
    pub fn catalogue_named_detectable_rate(&self) -> f64 {
        Rates::share(self.known_detectable_named, self.with_known_detectable)
    }
    /// Of the known effects named.
    pub fn magnitude_within_3u_rate(&self) -> f64 {
        Rates::share(self.within_3u, self.known_named)
    }
}
