//! The blind check: many simulated campaigns, each with an effect drawn at
//! random (or none) at a random magnitude and place, diagnosed without
//! seeing the truth, then scored against it.
//!
//! Cases come in kinds ([`CaseKind`]): one effect; none; one effect seen
//! in two faces; one effect in a file without `time_s` and `temperature_c`;
//! two effects at once; one blunder; several blunders; a blunder and an
//! effect. Every tracker carries random kinematic errors (every parameter
//! of `Plan::tracker`'s model, `tracker_sigma` each). Single-effect kinds are scored as
//! before (the effect and place named first); every kind is also scored as
//! a set: each member put in found in the explanation set, and nothing
//! named that was not put in.
//!
//! # What counts as detectable
//!
//! An effect can only be found if the readings carry it in a form the base
//! model cannot absorb: station poses, reflector positions and the error
//! parameters soak up whatever part of an effect resembles them. A case is
//! *detectable* when the effect's signature on the readings — the same
//! campaign simulated with and without the effect, noise-free, differenced
//! — left after projecting out everything the base adjustment can absorb,
//! amounts to Δχ² ≥ `detect_chi2` (default 25, five standard deviations)
//! in units of the stated noise. Below that, no method can tell the effect
//! from noise reliably; accuracy is reported on detectable cases and on all.

use super::{Diagnosis, Settings as DiagnoseSettings, diagnose};
use crate::campaign::{Aim, Campaign, CampaignReading};
use crate::effects::{self, Blunder, Coordinate, DrawContext, Effects};
use crate::error_model::{ErrorModel, ErrorParams};
use crate::kinematics::Face;
use crate::layout::{self, Kind, Spec};
use crate::noise::Noise;
use crate::random;
use crate::simulate::{CampaignSpec, SimulatedCampaign, simulate_campaign};
use crate::trackers::TrackerModel;
use anyhow::{Result, anyhow};
use nalgebra::{DVector, Vector3};
use rand::rngs::ChaCha8Rng;
use rayon::prelude::*;
use std::collections::BTreeMap;

/// What a case holds.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum CaseKind {
    /// No effect, no blunder (drawn with the plan's `none_fraction`).
    None,
    Single,
    /// One effect, every reading taken in both faces.
    TwoFace,
    /// One effect (not one that needs time or temperature), in a file
    /// without `time_s` and `temperature_c`.
    NoTime,
    TwoEffects,
    Blunder,
    /// Two to four blunders.
    Blunders,
    BlunderAndEffect,
}

impl CaseKind {
    /// The kinds the plan draws from by default (`none` comes from the
    /// plan's `none_fraction`).
    pub const ALL: [CaseKind; 7] = [
        CaseKind::Single,
        CaseKind::TwoFace,
        CaseKind::NoTime,
        CaseKind::TwoEffects,
        CaseKind::Blunder,
        CaseKind::Blunders,
        CaseKind::BlunderAndEffect,
    ];

    pub fn name(self) -> &'static str {
        match self {
            CaseKind::None => "none",
            CaseKind::Single => "single",
            CaseKind::TwoFace => "two-face",
            CaseKind::NoTime => "no-time",
            CaseKind::TwoEffects => "two-effects",
            CaseKind::Blunder => "blunder",
            CaseKind::Blunders => "blunders",
            CaseKind::BlunderAndEffect => "blunder-and-effect",
        }
    }

    /// The kind a name (as [`CaseKind::name`] writes it) stands for.
    pub fn parse(name: &str) -> Option<CaseKind> {
        std::iter::once(CaseKind::None)
            .chain(CaseKind::ALL)
            .find(|k| k.name() == name)
    }

    /// One effect or none, no blunder: scored by what is named first.
    pub fn is_single(self) -> bool {
        matches!(
            self,
            CaseKind::None | CaseKind::Single | CaseKind::TwoFace | CaseKind::NoTime
        )
    }
}

/// How the cases are drawn.
#[derive(Clone, Debug)]
pub struct Plan {
    pub cases: usize,
    /// The number of the first case: cases `first … first + cases − 1`, each
    /// drawn from `(seed, its number)` alone, so a check split into blocks
    /// (a sweep over `first_case`, every block a sweep point) draws the
    /// same cases as one check of them all.
    pub first: usize,
    pub seed: u64,
    /// The campaigns' layouts, stations, noise and trackers.
    pub campaigns: Campaigns,
    /// Share of effect-free campaigns.
    pub none_fraction: f64,
    /// Effect ids to draw from.
    pub effects: Vec<String>,
    /// Kinds of case to draw from (besides `none`).
    pub kinds: Vec<CaseKind>,
    pub detect_chi2: f64,
    /// Monte Carlo draws per diagnosis.
    pub mc_draws: usize,
}

/// How a check draws each case's campaign (this check's and the
/// open-world check's, [`super::open_check`]).
#[derive(Clone, Debug)]
pub struct Campaigns {
    pub layouts: Vec<Kind>,
    /// Station counts, drawn uniformly from this inclusive range.
    pub stations: (usize, usize),
    pub noise_angle_urad: (f64, f64),
    pub noise_range_um: (f64, f64),
    /// The trackers' model, which the diagnosis fits (its default: the
    /// campaign's `[tracker] model`).
    pub tracker: TrackerModel,
    /// Kinematic error parameters of each tracker: Gaussian, this σ in µm
    /// and µrad (a factory-compensated tracker has a few).
    pub tracker_sigma: f64,
}

/// One thing put into a case: an effect or a blunder.
#[derive(Clone, Debug)]
pub struct Member {
    pub effect: String,
    /// As the diagnosis names it: a station or reflector id, an axis,
    /// `all`, or `station/target/face` for a blunder.
    pub place: String,
    pub has_place: bool,
    /// Δχ² of its unabsorbed signature, alone.
    pub signal_chi2: f64,
}

/// A case scored as a set.
#[derive(Clone, Debug, Default)]
pub struct SetScore {
    /// Members put in, and how many of them are detectable.
    pub members: usize,
    pub detectable: usize,
    /// Detectable members found in the explanation set.
    pub found: usize,
    /// Explanation-set members that match nothing put in.
    pub spurious: usize,
    pub true_blunders: usize,
    pub detectable_blunders: usize,
    pub blunders_found: usize,
    pub false_blunders: usize,
    /// Readings without a blunder.
    pub clean_readings: usize,
    /// `station-drift` or `air-refraction` named in a file without the
    /// columns they need.
    pub time_effect_without_time: bool,
    /// The verdict says the readings are not (fully) explained
    /// ([`Diagnosis::explained`]): a false flag, when every effect put in
    /// is in the catalogue.
    pub not_explained: bool,
    pub true_set: String,
    pub named_set: String,
}

/// The truth of one case.
#[derive(Clone, Debug)]
pub struct Truth {
    pub effect: String,
    /// A station or reflector id, an axis, or `all`.
    pub place: String,
    /// Comparable with the diagnosis's magnitude (same unit).
    pub magnitude: f64,
    /// Whether `place` is a single station or reflector to be named.
    pub has_place: bool,
    pub effects: Effects,
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
    pub truth: Truth,
    /// Δχ² of the unabsorbed signature.
    pub signal_chi2: f64,
    pub detectable: bool,
    pub named_effect: String,
    pub named_place: String,
    pub named_magnitude: f64,
    pub effect_correct: bool,
    /// `None` when the truth has no single place to name.
    pub place_correct: Option<bool>,
    pub magnitude_ratio: Option<f64>,
    pub set: SetScore,
}

/// Draws the effect `id` of the catalogue into `fx`.
fn draw_effect(rng: &mut ChaCha8Rng, id: &str, cx: &DrawContext, fx: &mut Effects) -> Truth {
    let (place, magnitude, has_place) = match effects::kind(id) {
        Some(kind) => (kind.draw)(rng, cx, fx),
        None => ("all".to_string(), 0.0, false),
    };
    Truth {
        effect: if fx.ids().is_empty() {
            "none".into()
        } else {
            id.into()
        },
        place,
        magnitude,
        has_place,
        effects: fx.clone(),
    }
}

/// Draws `n` blunders on distinct readings of `readings`: a random
/// coordinate, off by 6 to 40 σ either way.
fn draw_blunders(
    rng: &mut ChaCha8Rng,
    n: usize,
    readings: &[CampaignReading],
    noise: Noise,
) -> Vec<Blunder> {
    let mut taken: Vec<usize> = Vec::new();
    let mut out = Vec::new();
    while out.len() < n.min(readings.len()) {
        let i = ((random::uniform(rng) * readings.len() as f64) as usize).min(readings.len() - 1);
        if taken.contains(&i) {
            continue;
        }
        taken.push(i);
        let r = &readings[i];
        let coordinate = *random::pick(rng, &[Coordinate::Az, Coordinate::El, Coordinate::D]);
        let sigmas = random::log_uniform(rng, 6.0, 40.0, true);
        let (size_urad, size_um) = match coordinate {
            Coordinate::D => (None, Some(sigmas * noise.sigma_range_at_um(r.d_mm))),
            _ => (Some(sigmas * noise.sigma_angle_urad), None),
        };
        out.push(Blunder {
            station: r.station.clone(),
            target: r.target.clone(),
            face: r.face.number() as u8,
            coordinate,
            size_urad,
            size_um,
        });
    }
    out
}

/// How a case's campaign is measured.
#[derive(Clone, Copy)]
pub(super) struct Measuring {
    pub two_face: bool,
    pub timed: bool,
}

/// What every case of a check draws first, in this order from its stream:
/// the layout, the station count, the noise and the tracker's kinematic
/// errors. Shared with the open-world check ([`super::open_check`]) so
/// that both checks draw their campaigns alike.
pub(super) struct Setting {
    pub layout: Kind,
    pub stations: usize,
    pub spec: Spec,
    pub noise: Noise,
    pub errors: ErrorParams,
    /// Station and reflector ids of the layout, for the effects' draws.
    pub station_ids: Vec<String>,
    pub target_ids: Vec<String>,
}

impl Setting {
    pub(super) fn draw(rng: &mut ChaCha8Rng, how: &Campaigns) -> Setting {
        let layout_kind = *random::pick(rng, &how.layouts);
        let (lo, hi) = how.stations;
        let n_st = lo + ((random::uniform(rng) * (hi - lo + 1) as f64) as usize).min(hi - lo);
        let mut spec = Spec::new(layout_kind);
        spec.stations = n_st;
        let noise = Noise {
            sigma_angle_urad: random::between(rng, how.noise_angle_urad),
            sigma_range_um: random::between(rng, how.noise_range_um),
            sigma_range_ppm: 0.3,
        };
        let mut errors = ErrorParams::zero(&ErrorModel::of(how.tracker));
        for v in errors.values_mut() {
            *v = how.tracker_sigma * random::normal(rng);
        }
        let lay = layout::build(&spec);
        Setting {
            layout: layout_kind,
            stations: n_st,
            spec,
            noise,
            errors,
            station_ids: lay.stations.iter().map(|s| s.0.clone()).collect(),
            target_ids: lay.targets.iter().map(|t| t.0.clone()).collect(),
        }
    }

    /// The layout's name as tables write it.
    pub(super) fn layout_name(&self) -> String {
        format!("{:?}", self.layout).to_lowercase()
    }
}

/// The seed of case `case`'s simulation and diagnosis.
pub(super) fn case_seed(seed: u64, case: usize) -> u64 {
    seed.wrapping_mul(1_000_003).wrapping_add(case as u64)
}

/// A case's campaign diagnosed blind: the default settings but the
/// trackers' model, the Monte Carlo draws and the seed.
pub(super) fn diagnose_blind(
    c: &Campaign,
    tracker: TrackerModel,
    mc_draws: usize,
    seed: u64,
) -> Result<Diagnosis> {
    diagnose(c, &settings(tracker, mc_draws, seed))
}

/// The settings of [`diagnose_blind`].
pub(super) fn settings(tracker: TrackerModel, mc_draws: usize, seed: u64) -> DiagnoseSettings {
    DiagnoseSettings {
        model: ErrorModel::of(tracker),
        mc_draws,
        seed,
        ..DiagnoseSettings::default()
    }
}

pub(super) fn simulate(
    spec: &Spec,
    errors: &ErrorParams,
    noise: Noise,
    fx: &Effects,
    seed: u64,
    how: Measuring,
) -> Result<SimulatedCampaign> {
    let layout = layout::build(spec);
    simulate_campaign(&CampaignSpec {
        name: "blind".into(),
        layout: &layout,
        errors: Some(errors),
        faces: if how.two_face {
            &[Face::Front, Face::Back]
        } else {
            &[Face::Front]
        },
        aim: Aim::StationsCentroid,
        max_angle_deg: crate::effects::DEFAULT_MAX_ANGLE_DEG,
        noise,
        effects: fx,
        gauge_u_mm: 0.0005,
        reference_u_mm: 0.002,
        level_urad: 1000.0,
        interval_s: 20.0,
        record_time: how.timed,
        record_temperature: how.timed,
        seed,
    })
    .map_err(|e| anyhow!(e))
}

type Key = (String, String, i64);

fn key(r: &CampaignReading) -> Key {
    (r.station.clone(), r.target.clone(), r.face.number())
}

/// The noise-free change an effect makes to each of `readings` (az, el in
/// rad, d in mm): the difference of the campaigns with and without it.
pub(super) fn signal(
    with: &Campaign,
    without: &Campaign,
    readings: &[CampaignReading],
) -> Vec<Vector3<f64>> {
    let base: BTreeMap<Key, &CampaignReading> =
        without.readings.iter().map(|r| (key(r), r)).collect();
    let eff: BTreeMap<Key, &CampaignReading> = with.readings.iter().map(|r| (key(r), r)).collect();
    readings
        .iter()
        .map(|r| {
            let k = key(r);
            match (eff.get(&k), base.get(&k)) {
                (Some(a), Some(b)) => Vector3::new(
                    crate::kinematics::wrap_angle((a.az_deg - b.az_deg).to_radians()),
                    (a.el_deg - b.el_deg).to_radians(),
                    a.d_mm - b.d_mm,
                ),
                _ => Vector3::zeros(),
            }
        })
        .collect()
}

/// The effect's Δχ² on the readings once the base adjustment has absorbed
/// what it can: `‖P⊥·W·Δ‖²` with Δ its [`signal`], the noise-free
/// difference of the readings with and without the effect.
pub(super) fn signal_chi2(d: &Diagnosis, signal: &[Vector3<f64>]) -> f64 {
    let Some(lin) = &d.calibration.linearisation else {
        return 0.0;
    };
    let mut delta = DVector::zeros(lin.jacobian.nrows());
    for (i, x) in signal.iter().enumerate() {
        let s = d.sigma[i];
        delta[3 * i] = x.x / s.x;
        delta[3 * i + 1] = x.y / s.y;
        delta[3 * i + 2] = x.z / s.z;
    }
    super::linear::unabsorbed_norm2(&lin.jacobian, &delta)
}

/// Runs one case.
///
/// Long on purpose (issue 31): one case from its draw to its score —
/// simulate, diagnose, compare with the truth — in sequence, each step
/// reading what the one before produced.
fn run_case(plan: &Plan, case: usize) -> Result<Case> {
    let mut rng = random::stream(plan.seed, &format!("blind-check-{case}"));
    let setting = Setting::draw(&mut rng, &plan.campaigns);
    let Setting {
        stations: n_st,
        spec,
        noise,
        errors,
        station_ids: stations,
        target_ids: targets,
        ..
    } = &setting;
    let (n_st, noise) = (*n_st, *noise);
    let kind = if random::uniform(&mut rng) < plan.none_fraction || plan.effects.is_empty() {
        CaseKind::None
    } else {
        *random::pick(&mut rng, &plan.kinds)
    };
    let how = Measuring {
        two_face: kind == CaseKind::TwoFace,
        timed: kind != CaseKind::NoTime,
    };
    let seed = case_seed(plan.seed, case);
    // The effects: ids drawn without repeats, from those the file can
    // carry (none that needs time or temperature without them), and an
    // effect drawn only alone not beside another.
    let n_effects = match kind {
        CaseKind::None | CaseKind::Blunder | CaseKind::Blunders => 0,
        CaseKind::TwoEffects => 2,
        _ => 1,
    };
    let mut fx = Effects::default();
    let mut truths: Vec<Truth> = Vec::new();
    for _ in 0..n_effects {
        let kind_of = |e: &str| effects::kind(e);
        let allowed: Vec<String> = plan
            .effects
            .iter()
            .filter(|e| how.timed || !kind_of(e).is_some_and(|k| k.needs.any()))
            .filter(|e| !truths.iter().any(|t| &t.effect == *e))
            .filter(|e| !(n_effects > 1 && kind_of(e).is_some_and(|k| k.alone)))
            .cloned()
            .collect();
        if allowed.is_empty() {
            break;
        }
        let id = random::pick(&mut rng, &allowed).clone();
        let cx = DrawContext {
            stations,
            targets,
            size: 1.0,
        };
        truths.push(draw_effect(&mut rng, &id, &cx, &mut fx));
    }
    let clean_without = simulate(
        spec,
        errors,
        Noise::default(),
        &Effects::default(),
        seed,
        how,
    )?;
    let n_blunders = match kind {
        CaseKind::Blunder | CaseKind::BlunderAndEffect => 1,
        CaseKind::Blunders => 2 + (random::uniform(&mut rng) * 3.0) as usize % 3,
        _ => 0,
    };
    fx.blunder = draw_blunders(
        &mut rng,
        n_blunders,
        &clean_without.campaign.readings,
        noise,
    );
    let noisy = simulate(spec, errors, noise, &fx, seed, how)?;
    let d = diagnose_blind(&noisy.campaign, plan.campaigns.tracker, plan.mc_draws, seed)?;
    // Each member's signal, alone.
    let readings = &noisy.campaign.readings;
    let signal_of = |one: &Effects| -> Result<f64> {
        let with = simulate(spec, errors, Noise::default(), one, seed, how)?;
        Ok(signal_chi2(
            &d,
            &signal(&with.campaign, &clean_without.campaign, readings),
        ))
    };
    let mut members: Vec<Member> = Vec::new();
    for t in &truths {
        let one = t.effects.only(&t.effect);
        members.push(Member {
            effect: t.effect.clone(),
            place: t.place.clone(),
            has_place: t.has_place,
            signal_chi2: signal_of(&one)?,
        });
    }
    for b in &fx.blunder {
        let one = Effects {
            blunder: vec![b.clone()],
            ..Effects::default()
        };
        members.push(Member {
            effect: "blunder".into(),
            place: b.place(),
            has_place: true,
            signal_chi2: signal_of(&one)?,
        });
    }
    let truth = truths.first().cloned().unwrap_or_else(|| Truth {
        effect: "none".into(),
        place: "all".into(),
        magnitude: 0.0,
        has_place: false,
        effects: Effects::default(),
    });
    let signal = members.first().map_or(0.0, |m| m.signal_chi2);
    let best = d.best();
    let effect_correct = best.effect == truth.effect;
    let place_correct = truth
        .has_place
        .then(|| effect_correct && best.place == truth.place);
    let magnitude_ratio = (effect_correct && truth.effect != "none" && truth.magnitude != 0.0)
        .then(|| best.magnitude / truth.magnitude);
    let set = score_set(&d, &members, plan.detect_chi2, readings.len(), how.timed);
    Ok(Case {
        case,
        kind,
        layout: setting.layout_name(),
        stations: n_st,
        readings: readings.len(),
        sigma_angle_urad: noise.sigma_angle_urad,
        sigma_range_um: noise.sigma_range_um,
        signal_chi2: signal,
        detectable: members.iter().all(|m| m.signal_chi2 >= plan.detect_chi2),
        named_effect: best.effect.clone(),
        named_place: best.place.clone(),
        named_magnitude: best.magnitude,
        effect_correct,
        place_correct,
        magnitude_ratio,
        truth,
        set,
    })
}

/// The explanation set against what was put in: an effect is found when
/// the set names its id, a blunder when the set names its reading.
fn score_set(
    d: &Diagnosis,
    members: &[Member],
    detect_chi2: f64,
    readings: usize,
    timed: bool,
) -> SetScore {
    let named: Vec<&super::Row> = d.explanation().collect();
    let matches = |m: &Member, r: &super::Row| {
        r.effect == m.effect && (m.effect != "blunder" || r.place == m.place)
    };
    let detectable: Vec<&Member> = members
        .iter()
        .filter(|m| m.signal_chi2 >= detect_chi2)
        .collect();
    let blunders = |v: &[&Member]| v.iter().filter(|m| m.effect == "blunder").count();
    let all: Vec<&Member> = members.iter().collect();
    let name = |e: &str, p: &str| format!("{e} at {p}");
    SetScore {
        members: members.len(),
        detectable: detectable.len(),
        found: detectable
            .iter()
            .filter(|m| named.iter().any(|r| matches(m, r)))
            .count(),
        spurious: named
            .iter()
            .filter(|r| !members.iter().any(|m| matches(m, r)))
            .count(),
        true_blunders: blunders(&all),
        detectable_blunders: blunders(&detectable),
        blunders_found: detectable
            .iter()
            .filter(|m| m.effect == "blunder" && named.iter().any(|r| matches(m, r)))
            .count(),
        false_blunders: named
            .iter()
            .filter(|r| r.effect == "blunder" && !members.iter().any(|m| matches(m, r)))
            .count(),
        clean_readings: readings - blunders(&all),
        time_effect_without_time: !timed
            && named
                .iter()
                .any(|r| effects::kind(&r.effect).is_some_and(|k| k.needs.any())),
        not_explained: !d.explained(),
        true_set: if members.is_empty() {
            "none".into()
        } else {
            members
                .iter()
                .map(|m| name(&m.effect, &m.place))
                .collect::<Vec<_>>()
                .join(" + ")
        },
        named_set: super::output::explanation(d),
    }
}

/// Runs every case (in parallel; the result does not depend on the
/// number of threads: each case has its own random stream).
pub fn run(plan: &Plan) -> Result<Vec<Case>> {
    (plan.first..plan.first + plan.cases)
        .into_par_iter()
        .map(|k| run_case(plan, k))
        .collect()
}

/// Accuracy figures.
#[derive(Clone, Debug, Default)]
pub struct Score {
    pub cases: usize,
    pub with_effect: usize,
    pub effect_correct: usize,
    pub with_place: usize,
    pub place_correct: usize,
    pub effect_free: usize,
    pub none_correct: usize,
    /// Median of |named/true − 1| over correctly named effects.
    pub median_magnitude_error: f64,
}

/// Set-level accuracy of a group of cases (of one kind, or all).
#[derive(Clone, Debug, Default)]
pub struct SetAccuracy {
    pub cases: usize,
    /// Cases whose every member is detectable.
    pub detectable_cases: usize,
    /// … whose every member was found.
    pub all_found: usize,
    /// Cases (any) with no spurious member.
    pub spurious_free: usize,
    pub detectable_blunders: usize,
    pub blunders_found: usize,
    pub false_blunders: usize,
    pub clean_readings: usize,
    /// Cases without time columns where a time-based effect was named.
    pub time_effects_without_time: usize,
    /// Cases declared not (fully) explained.
    pub not_explained: usize,
}

impl SetAccuracy {
    pub fn of<'a>(cases: impl Iterator<Item = &'a Case>) -> SetAccuracy {
        let mut a = SetAccuracy::default();
        for c in cases {
            let s = &c.set;
            a.cases += 1;
            if s.detectable == s.members {
                a.detectable_cases += 1;
                a.all_found += (s.found == s.members) as usize;
            }
            a.spurious_free += (s.spurious == 0) as usize;
            a.detectable_blunders += s.detectable_blunders;
            a.blunders_found += s.blunders_found;
            a.false_blunders += s.false_blunders;
            a.clean_readings += s.clean_readings;
            a.time_effects_without_time += s.time_effect_without_time as usize;
            a.not_explained += s.not_explained as usize;
        }
        a
    }

    /// Share of fully detectable cases whose every member was found.
    pub fn all_found_rate(&self) -> f64 {
        self.all_found as f64 / self.detectable_cases.max(1) as f64
    }
    pub fn spurious_free_rate(&self) -> f64 {
        self.spurious_free as f64 / self.cases.max(1) as f64
    }
    pub fn blunder_rate(&self) -> f64 {
        self.blunders_found as f64 / self.detectable_blunders.max(1) as f64
    }
    /// False blunders per 1 000 clean readings.
    pub fn false_blunders_per_1000(&self) -> f64 {
        1000.0 * self.false_blunders as f64 / self.clean_readings.max(1) as f64
    }
    /// Share of cases declared not (fully) explained.
    pub fn not_explained_rate(&self) -> f64 {
        self.not_explained as f64 / self.cases.max(1) as f64
    }
}

impl Score {
    pub fn of<'a>(cases: impl Iterator<Item = &'a Case>) -> Score {
        let mut s = Score::default();
        let mut errs = Vec::new();
        for c in cases {
            s.cases += 1;
            if c.truth.effect == "none" {
                s.effect_free += 1;
                s.none_correct += c.effect_correct as usize;
            } else {
                s.with_effect += 1;
                s.effect_correct += c.effect_correct as usize;
            }
            if let Some(p) = c.place_correct {
                s.with_place += 1;
                s.place_correct += p as usize;
            }
            if let Some(r) = c.magnitude_ratio {
                errs.push((r - 1.0).abs());
            }
        }
        errs.sort_by(f64::total_cmp);
        s.median_magnitude_error = errs.get(errs.len() / 2).copied().unwrap_or(f64::NAN);
        s
    }

    pub fn effect_rate(&self) -> f64 {
        self.effect_correct as f64 / self.with_effect.max(1) as f64
    }
    pub fn place_rate(&self) -> f64 {
        self.place_correct as f64 / self.with_place.max(1) as f64
    }
    pub fn none_rate(&self) -> f64 {
        self.none_correct as f64 / self.effect_free.max(1) as f64
    }
}
