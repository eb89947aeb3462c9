//! The diagnosis on effects outside its catalogue (`ltcal::open_world`):
//! honest that the residual is not explained, pointing at the factor the
//! structure lies along, and writing it as a hypothesis to test next.

use ltcal::campaign::Aim;
use ltcal::diagnose::localise;
use ltcal::diagnose::open_check::{self, CaseKind, Rates};
use ltcal::diagnose::{self, Settings};
use ltcal::diagnostics::Source;
use ltcal::effects::Effects;
use ltcal::error_model::{ErrorModel, ErrorParams};
use ltcal::hypothesis::{self, Hypothesis};
use ltcal::kinematics::Face;
use ltcal::layout::{self, Kind as Layout, Spec};
use ltcal::noise::Noise;
use ltcal::open_world::{AdmCyclic, OpenEffect};
use ltcal::random;
use ltcal::simulate::{CampaignSpec, SimulatedCampaign, simulate_campaign};
use ltcal::stages::open_world_check::OpenWorldCheckStage;
use ltcal::trackers::TrackerModel;
use rayon::prelude::*;
use std::sync::Arc;

/// A campaign of `layout` by a tracker with `errors`, carrying `effects`:
/// time and temperature recorded, 1 µrad and 2 µm of noise.
fn campaign(
    layout: &layout::Layout,
    errors: &ErrorParams,
    faces: &[Face],
    effects: &Effects,
    seed: u64,
) -> SimulatedCampaign {
    simulate_campaign(&CampaignSpec {
        name: "open-world".into(),
        layout,
        errors: Some(errors),
        faces,
        aim: Aim::StationsCentroid,
        max_angle_deg: 30.0,
        noise: Noise {
            sigma_angle_urad: 1.0,
            sigma_range_um: 2.0,
            sigma_range_ppm: 0.3,
        },
        effects,
        gauge_u_mm: 0.0005,
        reference_u_mm: 0.002,
        level_urad: 1000.0,
        interval_s: 20.0,
        record_time: true,
        record_temperature: true,
        seed,
    })
    .unwrap()
}

fn simulate(seed: u64, errors: &ErrorParams) -> SimulatedCampaign {
    let layout = layout::build(&Spec::new(Layout::Corner));
    campaign(&layout, errors, &[Face::Front], &Effects::default(), seed)
}

/// The tracker of every campaign here: a few µm and µrad of kinematic errors.
fn tracker(seed: u64) -> ErrorParams {
    let mut rng = random::stream(seed, "open-world-tracker");
    let mut errors = ErrorParams::zero(&ErrorModel::of(TrackerModel::default()));
    for v in errors.values_mut() {
        *v = 5.0 * random::normal(&mut rng);
    }
    errors
}

/// A campaign with the ADM's cyclic error of `OpenEffect::AdmCyclic`.
fn cyclic(seed: u64, phase_deg: f64) -> SimulatedCampaign {
    let errors = tracker(1);
    let sim = simulate(seed, &errors);
    OpenEffect::AdmCyclic(AdmCyclic {
        amplitude_um: 12.0,
        period_m: 0.9,
        phase_deg,
    })
    .apply(&sim, Some(&errors))
    .unwrap()
}

fn settings(seed: u64, hypotheses: Vec<Hypothesis>) -> Settings {
    Settings {
        seed,
        hypotheses: Arc::new(hypotheses),
        ..Settings::default()
    }
}

/// Issue 30, item 4: the structure the diagnosis finds is written as a
/// hypothesis (`discovered.toml`) which, fed back on a fresh campaign of
/// the same effect, removes it.
#[test]
fn a_discovered_cyclic_error_written_as_a_hypothesis_removes_it_on_a_fresh_campaign() {
    let found = diagnose::diagnose(&cyclic(1, 40.0).campaign, &settings(1, Vec::new())).unwrap();
    let top = found.unexplained.iter().find(|l| l.significant).unwrap();
    assert_eq!(top.factor, "range", "{:?}", found.unexplained.first());
    assert!(top.basis.starts_with("periodic in d"), "{}", top.basis);
    let period: f64 = top
        .basis
        .rsplit("period ")
        .next()
        .unwrap()
        .trim_end_matches(" mm")
        .parse()
        .unwrap();
    assert!((period - 900.0).abs() < 0.05 * 900.0, "{period}");
    // … drawn: the fitted cycle over one period, its title naming it.
    let figures = diagnose::output::figures(&found).unwrap();
    let (_, svg) = figures
        .files
        .iter()
        .find(|(name, _)| name == "unexplained.svg")
        .expect("a figure of what is left");
    let svg = String::from_utf8_lossy(svg);
    assert!(svg.contains("what is left along range"), "{svg}");
    assert!(svg.contains("d mod period (mm)"));
    let text = localise::discovered(&found.campaign, &found.unexplained).unwrap();
    let hyps = hypothesis::parse(Source::new("discovered.toml", text.as_str())).unwrap();
    assert_eq!(hyps.len(), 1);
    // A fresh campaign: other noise, another phase.
    let fresh = cyclic(2, 200.0);
    let without = diagnose::diagnose(&fresh.campaign, &settings(2, Vec::new())).unwrap();
    let structure = without
        .unexplained
        .iter()
        .find(|l| l.factor == "range")
        .unwrap();
    assert!(structure.significant);
    let with = diagnose::diagnose(&fresh.campaign, &settings(2, hyps)).unwrap();
    let row = with
        .rows
        .iter()
        .find(|r| r.effect == "discovered-range")
        .unwrap();
    let removed = row.delta_chi2 / structure.delta_chi2;
    eprintln!(
        "discovered: {}; on a fresh campaign the hypothesis takes Δχ² {:.0} of the structure's {:.0} ({:.0} %), magnitude {:.2} ± {:.2} µm (true 12)",
        top.basis,
        row.delta_chi2,
        structure.delta_chi2,
        100.0 * removed,
        row.magnitude,
        row.magnitude_u
    );
    assert!(row.step.is_some(), "{row:?}");
    assert!(removed >= 0.8, "{removed}");
    assert!((row.magnitude - 12.0).abs() <= 3.0 * row.magnitude_u + 0.5);
    let none = with.rows.iter().find(|r| r.effect == "none").unwrap();
    assert!(none.significant, "{}", none.place);
}

/// Issue 30's measures, on the open-world blind check's campaigns: the
/// residual declared not explained, the structure's factor named, no false
/// blunders, and a catalogue effect beside the unknown one at its
/// magnitude. The honesty rates are taken on the *distinguishable* cases:
/// those whose unknown effect the catalogue's nearest single effect does
/// not reproduce to within the detection threshold (a part warming
/// station after station is a range scale; no diagnosis can tell them
/// apart). That no effect is excluded by name is checked too: part of
/// every effect but the two indistinguishable ones is kept.
#[test]
fn an_effect_outside_the_catalogue_is_declared_not_explained_and_localised() {
    let stage = OpenWorldCheckStage {
        cases: 120,
        seed: 7,
        mc_draws: 5,
        kinds: vec![CaseKind::Unknown, CaseKind::UnknownAndEffect],
        ..toml::from_str("").unwrap()
    };
    let cases = open_check::run(&stage.plan()).unwrap();
    let all = Rates::of(cases.iter());
    eprintln!(
        "{} distinguishable of {} detectable cases: not explained {:.1} %, catalogue as cause {:.1} %, factor right {:.1} %; \
         false blunders {:.2}/1000, catalogue named {:.1} % (detectable alone), within 3u {:.1} %",
        all.distinguishable_cases,
        all.detectable_cases,
        100.0 * all.distinguishable_not_explained_rate(),
        100.0 * all.distinguishable_catalogue_as_cause_rate(),
        100.0 * all.distinguishable_factor_correct_rate(),
        all.false_blunders_per_1000(),
        100.0 * all.catalogue_named_detectable_rate(),
        100.0 * all.magnitude_within_3u_rate(),
    );
    assert!(
        all.distinguishable_cases >= 50,
        "{}",
        all.distinguishable_cases
    );
    for unknown in ["tripod-knock", "adm-cyclic", "axis-wobble", "adm-reset"] {
        assert!(
            cases
                .iter()
                .any(|c| c.unknown == unknown && c.distinguishable),
            "{unknown}"
        );
    }
    assert!(all.distinguishable_not_explained_rate() >= 0.9);
    assert!(all.distinguishable_catalogue_as_cause_rate() <= 0.1);
    assert!(all.distinguishable_factor_correct_rate() >= 0.8);
    assert!(all.false_blunders_per_1000() <= 3.0);
    // Estimated beside the structure the unknown effect leaves (93 % of
    // the pipeline's 500 cases before, 99 % after).
    assert!(all.magnitude_within_3u_rate() >= 0.95);
}

/// Issue 30: air-refraction's constant scale is the sum of range-scale's
/// per-station columns; side by side in the set they made `magnitude_u`
/// 981 ppm for an 8 ppm scale. A candidate collinear with the set is not
/// added beside it.
#[test]
fn collinear_candidates_are_not_added_side_by_side() {
    let fx: Effects = toml::from_str(
        "[range-scale]\nsigma_ppm = 8.0\n[air-refraction]\namplitude_c = 1.5\nperiod_s = 1800.0\ndrift_c_per_h = 1.0\n",
    )
    .unwrap();
    let layout = layout::build(&Spec::new(Layout::Hall));
    for seed in 1..=6 {
        let sim = campaign(&layout, &tracker(seed), &[Face::Front], &fx, seed);
        let d = diagnose::diagnose(&sim.campaign, &settings(seed, Vec::new())).unwrap();
        let set: Vec<&diagnose::Row> = d.explanation().collect();
        eprintln!(
            "seed {seed}: {}",
            set.iter()
                .map(|r| format!(
                    "{} at {}: {:.2} ± {:.2} {}",
                    r.effect, r.place, r.magnitude, r.magnitude_u, r.unit
                ))
                .collect::<Vec<_>>()
                .join(" + ")
        );
        let has = |e: &str, p: &str| set.iter().any(|r| r.effect == e && r.place == p);
        assert!(!(has("range-scale", "all") && has("air-refraction", "all")));
        for r in &set {
            assert!(
                r.magnitude_u.is_finite() && r.magnitude_u < r.magnitude.abs().max(1.0),
                "{r:?}"
            );
        }
    }
}

/// Issue 30, item 2: a mirror tracker declared `api-tracker3`, with a range
/// scale at one station of 2–4 times the blind check's size: the model
/// mismatch is named, and the scale beside it at its magnitude.
#[test]
fn a_wrong_model_under_a_large_effect_is_named() {
    const CASES: u64 = 24;
    let layout = layout::build(&Spec::new(Layout::Corner));
    let out: Vec<(bool, bool, usize, usize, String)> = (1..=CASES)
        .into_par_iter()
        .map(|seed| {
            let mut rng = random::stream(seed, "wrong-model");
            let mut errors = ErrorParams::zero(&ErrorModel::of(
                TrackerModel::parse("mirror-tracker").unwrap(),
            ));
            for v in errors.values_mut() {
                *v = 5.0 * random::normal(&mut rng);
            }
            let stations: Vec<String> = layout.stations.iter().map(|s| s.0.clone()).collect();
            let station = random::pick(&mut rng, &stations).clone();
            let ppm = random::log_uniform(&mut rng, 8.0, 40.0, true);
            let fx: Effects =
                toml::from_str(&format!("[range-scale]\nppm = {{ {station} = {ppm} }}\n")).unwrap();
            let faces = [Face::Front, Face::Back];
            let mut sim = campaign(&layout, &errors, &faces, &fx, seed);
            sim.campaign.meta.tracker.model = TrackerModel::default().id().into();
            let d = diagnose::diagnose(&sim.campaign, &settings(seed, Vec::new())).unwrap();
            let set: Vec<&diagnose::Row> = d.explanation().collect();
            let mismatch = set
                .iter()
                .any(|r| r.effect == diagnose::MODEL && r.place == "mirror-tracker");
            let scale = set
                .iter()
                .find(|r| r.effect == "range-scale" && r.place == station);
            let within = scale.is_some_and(|r| (r.magnitude - ppm).abs() <= 3.0 * r.magnitude_u);
            let blunders = set.iter().filter(|r| r.effect == "blunder").count();
            (
                mismatch,
                within,
                blunders,
                sim.campaign.readings.len(),
                format!(
                    "{ppm:.1} ppm at {station}: {}",
                    diagnose::output::verdict(&d)
                ),
            )
        })
        .collect();
    for o in out.iter().filter(|o| !o.0) {
        eprintln!("missed: {}", o.4);
    }
    let named = out.iter().filter(|o| o.0).count();
    let within = out.iter().filter(|o| o.1).count();
    let blunders: usize = out.iter().map(|o| o.2).sum();
    let readings: usize = out.iter().map(|o| o.3).sum();
    eprintln!(
        "mismatch named {named}/{CASES}, the scale within 3 u {within}/{CASES}, \
         {blunders} blunders in {readings} clean readings"
    );
    assert!(named as f64 >= 0.9 * CASES as f64);
    assert!(within as f64 >= 0.8 * CASES as f64);
    assert!(1000.0 * blunders as f64 / readings as f64 <= 1.0);
}

/// Issue 30, item 3: the open-world check's `wrong-model-and-effect`
/// cases — a mirror tracker declared `api-tracker3`, both faces, a range
/// scale or a drift at 2–4 times the blind check's size, on every layout.
/// The mismatch is named wherever the readings can tell it from the
/// catalogue (its signature beyond the nearest single effect still
/// Δχ² ≥ 25; a one-station scale can take up a weak mismatch), the effect
/// at its magnitude, no blunder bred.
#[test]
fn the_open_world_checks_wrong_model_cases_name_the_mismatch_and_the_effect() {
    let stage = OpenWorldCheckStage {
        cases: 30,
        seed: 2030,
        mc_draws: 5,
        kinds: vec![CaseKind::WrongModelAndEffect],
        effects: vec!["range-scale".into(), "station-drift".into()],
        ..toml::from_str("").unwrap()
    };
    let cases = open_check::run(&stage.plan()).unwrap();
    let all = Rates::of(cases.iter());
    eprintln!(
        "{} detectable, {} distinguishable: mismatch named {:.1} % / {:.1} %, effect within 3u {:.1} %, \
         false blunders {:.2}/1000",
        all.mismatch_cases,
        all.mismatch_distinguishable_cases,
        100.0 * all.mismatch_named_rate(),
        100.0 * all.mismatch_named_distinguishable_rate(),
        100.0 * all.magnitude_within_3u_rate(),
        all.false_blunders_per_1000(),
    );
    assert_eq!(all.mismatch_cases, all.detectable_cases);
    assert!(all.mismatch_cases >= 25, "{}", all.mismatch_cases);
    assert!(all.mismatch_distinguishable_cases >= 20);
    assert!(all.mismatch_named_distinguishable_rate() >= 0.9);
    assert!(all.mismatch_named_rate() >= 0.8);
    assert!(all.catalogue_named_rate() >= 0.9);
    assert!(all.magnitude_within_3u_rate() >= 0.8);
    assert!(all.false_blunders_per_1000() <= 1.0);
    // The honesty rates concern the open-world effects alone.
    assert!(all.not_explained_rate().is_nan() && all.distinguishable_cases == 0);
}
