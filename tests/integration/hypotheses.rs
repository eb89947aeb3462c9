//! A researcher's own effects (`crate::hypothesis`): written in TOML,
//! injected by the simulation, recovered by the diagnosis — and refused at
//! their place when they cannot work.

use crate::cli::ltcal;
use crate::util::root;
use ltcal::campaign::Aim;
use ltcal::diagnose::{self, Settings};
use ltcal::diagnostics::Source;
use ltcal::effects::{Effects, Injected};
use ltcal::hypothesis::{self, Hypothesis};
use ltcal::kinematics::Face;
use ltcal::layout::{self, Spec};
use ltcal::noise::Noise;
use ltcal::simulate::{CampaignSpec, SimulatedCampaign, simulate_campaign};
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// An ADM's cyclic error of period 0.8 m, an effect effects.md lacks.
const CYCLIC: &str = r#"
[adm-cyclic]
doc = "the ADM's cyclic error, period 0.8 m"
acts_on = "d"
unit = "um"
expr = "a*sin(2*PI*d/800) + b*cos(2*PI*d/800)"
magnitude = "sqrt(a^2 + b^2)"
magnitude_unit = "µm"

[adm-cyclic.params]
a = { unit = "µm", value = 6.0 }
b = { unit = "µm", value = 0.0 }
"#;

fn write(path: &Path, text: &str) {
    std::fs::write(path, text).unwrap();
}

fn example(name: &str) -> PathBuf {
    root().join("examples/campaigns").join(name)
}

fn cyclic() -> Vec<Hypothesis> {
    hypothesis::parse(Source::new("cyclic.toml", CYCLIC)).unwrap()
}

fn campaign(seed: u64, inject: Vec<Hypothesis>) -> SimulatedCampaign {
    let spec: Spec = serde_json::from_str(r#"{"kind": "corner"}"#).unwrap();
    let layout = layout::build(&spec);
    let effects = Effects {
        hypotheses: Injected(Arc::new(inject)),
        ..Effects::default()
    };
    simulate_campaign(&CampaignSpec {
        name: "cyclic".into(),
        layout: &layout,
        errors: None,
        faces: &[Face::Front],
        aim: Aim::StationsCentroid,
        max_angle_deg: 30.0,
        noise: Noise {
            sigma_angle_urad: 1.0,
            sigma_range_um: 2.0,
            sigma_range_ppm: 0.3,
        },
        effects: &effects,
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

fn settings() -> Settings {
    Settings {
        hypotheses: Arc::new(cyclic()),
        ..Settings::default()
    }
}

/// The hypothesis's row: (a member?, magnitude, u, Δχ²).
fn row(d: &diagnose::Diagnosis) -> (bool, f64, f64, f64) {
    let r = d
        .rows
        .iter()
        .find(|r| r.effect == "adm-cyclic")
        .expect("the hypothesis is tried");
    (r.step.is_some(), r.magnitude, r.magnitude_u, r.delta_chi2)
}

#[test]
fn a_cyclic_range_error_written_in_toml_is_injected_and_recovered_within_3u() {
    let seeds: Vec<u64> = (1..=200).collect();
    let out: Vec<(bool, f64, f64, bool)> = seeds
        .par_iter()
        .map(|&seed| {
            let sim = campaign(seed, cyclic());
            let d = diagnose::diagnose(&sim.campaign, &Settings { seed, ..settings() }).unwrap();
            let (member, m, u, _) = row(&d);
            let none = d.rows.iter().find(|r| r.effect == "none").unwrap();
            (member, m, u, none.significant)
        })
        .collect();
    let named = out.iter().filter(|o| o.0).count();
    let within = out
        .iter()
        .filter(|o| o.0 && (o.1 - 6.0).abs() <= 3.0 * o.2)
        .count();
    let noise_back = out.iter().filter(|o| o.3).count();
    eprintln!(
        "adm-cyclic at 6 µm, 200 seeds: a member in {named}, within 3 u in {within}, \
         χ² back to the noise in {noise_back}"
    );
    // ≥ 99 % of 200 seeds: at most 2 misses.
    assert!(named >= 198, "named in {named} of 200");
    assert!(within >= 198, "within 3 u in {within} of 200: {out:?}");
    // With it, the residual is the noise again (the χ² test at α = 0.01).
    assert!(
        noise_back >= 190,
        "χ² back to the noise in {noise_back} of 200"
    );
}

#[test]
fn the_same_hypothesis_on_a_campaign_without_it_is_not_significant() {
    let seeds: Vec<u64> = (1001..=1100).collect();
    let named: Vec<bool> = seeds
        .par_iter()
        .map(|&seed| {
            let sim = campaign(seed, Vec::new());
            let d = diagnose::diagnose(&sim.campaign, &Settings { seed, ..settings() }).unwrap();
            row(&d).0
        })
        .collect();
    let false_alarms = named.iter().filter(|n| **n).count();
    eprintln!("adm-cyclic offered to 100 effect-free campaigns: a member in {false_alarms}");
    assert!(
        false_alarms <= 5,
        "named in {false_alarms} of 100 effect-free campaigns"
    );
}

#[test]
fn a_hypothesis_jacobian_equals_finite_differences() {
    let text = r#"
[sag]
acts_on = "reflector"
unit = "um"
shift = { z = "k*exp(-((x-c)/w)^2)*(1 + g*(temperature_c - 20))" }
[sag.params]
k = { value = 5.0 }
c = { value = 300.0, start = 300.0 }
w = { value = 900.0, start = 900.0 }
g = { value = 0.1 }
"#;
    let h = &hypothesis::parse(Source::new("sag.toml", text)).unwrap()[0];
    let cov = ltcal::hypothesis::covariates::Covariates {
        point: nalgebra::Vector3::new(850.0, -200.0, 1200.0),
        temperature_c: Some(21.3),
        ..ltcal::hypothesis::covariates::Covariates::dummy()
    };
    // k, c, w, g: the parameters in the order written.
    let theta = [4.0, 250.0, 1000.0, 0.2];
    let jac = h.jacobian(&cov, &theta, "S1/T1/1").unwrap();
    for k in 0..4 {
        let step = 1e-5 * theta[k].abs().max(1.0);
        let (mut up, mut dn) = (theta, theta);
        up[k] += step;
        dn[k] -= step;
        let fd = (h.apply(&cov, &up, "").unwrap() - h.apply(&cov, &dn, "").unwrap()) / (2.0 * step);
        let rel = (jac[k] - fd).norm() / fd.norm().max(1e-300);
        assert!(
            rel < 1e-6,
            "parameter {k}: {:?} vs {fd:?} ({rel:e})",
            jac[k]
        );
    }
}

#[test]
fn simulate_campaign_injects_a_hypothesis_file_and_reports_its_truth() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write(&dir.join("cyclic.toml"), CYCLIC);
    write(
        &dir.join("p.toml"),
        r#"
[stages.sim]
kind = "simulate_campaign"
layout = { kind = "corner" }
noise = { sigma_angle_urad = 1.0, sigma_range_um = 2.0, sigma_range_ppm = 0.3 }
seed = 3
hypotheses = "cyclic.toml"
[stages.sim.hypothesis_values.adm-cyclic]
a = 8.0

[stages.diagnosis]
kind = "diagnose"
inputs = { campaign = "sim" }
hypotheses = "cyclic.toml"
"#,
    );
    let out = ltcal(dir, &["run", "p.toml"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let show = ltcal(dir, &["show", "p.toml", "sim.truth_effects"]);
    let text = String::from_utf8_lossy(&show.stdout);
    assert!(text.contains("adm-cyclic") && text.contains("8"), "{text}");
    let show = ltcal(dir, &["show", "p.toml", "diagnosis.diagnosis"]);
    let text = String::from_utf8_lossy(&show.stdout);
    assert!(text.contains("adm-cyclic"), "{text}");
}

#[test]
fn a_hypothesis_with_an_unknown_variable_is_refused_with_its_line_and_caret() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write(
        &dir.join("h.toml"),
        "[h]\nacts_on = \"d\"\nunit = \"um\"\nexpr = \"a*cos(elevation)\"\n[h.params]\na = {}\n",
    );
    let campaign = example("example-00-none");
    let out = ltcal(
        dir,
        &[
            "diagnose",
            campaign.to_str().unwrap(),
            "--out",
            "d",
            "--hypotheses",
            "h.toml",
        ],
    );
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("h.toml:4:15"), "{err}");
    assert!(err.contains("unknown variable `elevation`"), "{err}");
    assert!(err.contains("^^^^^^^^^"), "{err}");
    assert!(!dir.join("d").exists());
}

#[test]
fn a_hypothesis_dividing_by_zero_at_a_reading_is_refused_naming_the_reading() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    // Every reading's face is 1: 1/(face − 1) is infinite everywhere.
    write(
        &dir.join("h.toml"),
        "[h]\nacts_on = \"d\"\nunit = \"um\"\nexpr = \"a/(face - 1)\"\n[h.params]\na = {}\n",
    );
    let campaign = example("example-00-none");
    let out = ltcal(
        dir,
        &[
            "diagnose",
            campaign.to_str().unwrap(),
            "--out",
            "d",
            "--hypotheses",
            "h.toml",
        ],
    );
    assert_eq!(
        out.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("h.toml:4:"), "{err}");
    assert!(err.contains("readings.csv line"), "{err}");
}

#[test]
fn a_hypothesis_value_for_a_parameter_it_lacks_is_refused_at_load() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write(&dir.join("cyclic.toml"), CYCLIC);
    write(
        &dir.join("p.toml"),
        "[stages.sim]\nkind = \"simulate_campaign\"\nlayout = { kind = \"corner\" }\nhypotheses = \"cyclic.toml\"\n[stages.sim.hypothesis_values.adm-cyclic]\nperiod = 800.0\n",
    );
    let out = ltcal(dir, &["run", "p.toml"]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("p.toml:6:1") && err.contains("no parameter `period`"),
        "{err}"
    );
}

/// Issue 30 (first step): a campaign whose gap comes from an effect the
/// catalogue lacks — the ADM cyclic error, diagnosed *without* its
/// hypothesis — must not get a verdict presenting a catalogue effect as
/// the whole cause.
#[test]
fn an_effect_outside_the_catalogue_is_not_presented_as_the_whole_cause() {
    let seeds: Vec<u64> = (2001..=2040).collect();
    let out: Vec<(String, usize, usize)> = seeds
        .par_iter()
        .map(|&seed| {
            let mut h = cyclic();
            h[0].params[0].value = ltcal::hypothesis::Value::Same(10.0);
            let sim = campaign(seed, h);
            let d = diagnose::diagnose(
                &sim.campaign,
                &Settings {
                    seed,
                    ..Settings::default()
                },
            )
            .unwrap();
            let blunders = d.explanation().filter(|r| r.effect == "blunder").count();
            (
                ltcal::diagnose::output::verdict(&d),
                blunders,
                sim.campaign.readings.len(),
            )
        })
        .collect();
    let verdicts: Vec<String> = out.iter().map(|o| o.0.clone()).collect();
    let blunders: usize = out.iter().map(|o| o.1).sum();
    let readings: usize = out.iter().map(|o| o.2).sum();
    let per_1000 = 1000.0 * blunders as f64 / readings as f64;
    eprintln!("false blunders: {blunders} in {readings} readings ({per_1000:.2} per 1 000)");
    // Before the robust scale of the w-tests: 6–8 in every campaign (~55 per 1 000).
    assert!(
        per_1000 <= 2.0,
        "{per_1000:.2} false blunders per 1 000 readings"
    );
    let honest = verdicts
        .iter()
        .filter(|v| {
            v.starts_with("partly explained") || v.contains("not consistent with the stated noise")
        })
        .count();
    eprintln!(
        "an ADM cyclic error of 10 µm, no hypothesis: said not (fully) explained in {honest} of 40"
    );
    for v in verdicts.iter().take(5) {
        eprintln!("  {v}");
    }
    assert!(honest >= 36, "honest in {honest} of 40: {verdicts:#?}");
}
