//! The diagnosis: on the example campaigns of an independent generator
//! (their truth.json read only here, to score), and blind on simulated ones.

use ltcal::diagnose::blind::{self, CaseKind, Score, SetAccuracy};
use ltcal::diagnose::{self, Settings};
use ltcal::stages::StageKind;
use ltcal::stages::blind_check::BlindCheckStage;
use std::path::PathBuf;

fn examples() -> Vec<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("examples/campaigns");
    let mut v: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join("truth.json").exists())
        .collect();
    v.sort();
    v
}

/// The example campaign folder `name`.
fn example(name: &str) -> PathBuf {
    examples().into_iter().find(|p| p.ends_with(name)).unwrap()
}

/// The truth's comparable magnitude, in the diagnosis's unit.
fn true_magnitude(truth: &serde_json::Value) -> Option<f64> {
    let p = &truth["params"];
    let norm = |v: &serde_json::Value| {
        v.as_array().map(|a| {
            a.iter()
                .map(|x| x.as_f64().unwrap().powi(2))
                .sum::<f64>()
                .sqrt()
        })
    };
    match truth["effect"].as_str()? {
        "incidence" => p["e_axial_um"].as_f64(),
        "air-refraction" => Some(-0.93),
        "encoder-harmonic" => p["amplitude_urad"].as_f64(),
        "station-drift" => norm(&p["velocity_um_per_min"]),
        "target-shift" => norm(&p["shift_um"]),
        _ => None,
    }
}

/// The examples with one effect or none: 00–06 (effects.md version 1) and
/// 09, 10 (version 2: kinematic errors of the tracker, two faces, a big hall).
fn single_effect(truth: &serde_json::Value) -> bool {
    truth["blunders"].is_null() && truth["effects"].as_array().is_none_or(|e| e.len() == 1)
}

/// Each single-effect example named right, where the truth says, with a
/// magnitude within 25 % of the truth's and within 3 of its stated
/// standard uncertainties.
#[test]
fn every_single_effect_example_campaign_is_named_right() {
    let files = examples();
    assert_eq!(files.len(), 13);
    let mut checked = 0;
    let (mut sum_z2, mut with_truth) = (0.0, 0);
    for dir in files {
        let truth: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("truth.json")).unwrap())
                .unwrap();
        if !single_effect(&truth) {
            continue;
        }
        checked += 1;
        let c = ltcal::campaign::read(&dir).unwrap();
        let d = diagnose::diagnose(&c, &Settings::default()).unwrap();
        let best = d.best();
        let effect = truth["effect"].as_str().unwrap();
        assert_eq!(best.effect, effect, "{}: {:?}", dir.display(), best);
        match effect {
            "none" => assert!(best.significant, "none must be the accepted verdict"),
            "station-drift" | "target-shift" => {
                assert_eq!(best.place, truth["where"].as_str().unwrap())
            }
            "encoder-harmonic" => assert_eq!(best.place, truth["params"]["axis"].as_str().unwrap()),
            _ => {}
        }
        if let Some(m) = true_magnitude(&truth) {
            assert!(
                (best.magnitude / m - 1.0).abs() < 0.25,
                "{effect}: {} vs {m}",
                best.magnitude
            );
            // Issue 14: the stated uncertainty covers the truth.
            let z = (best.magnitude - m) / best.magnitude_u;
            assert!(
                z.abs() < 3.0,
                "{effect}: {} ± {} vs {m}",
                best.magnitude,
                best.magnitude_u
            );
            sum_z2 += z * z;
            with_truth += 1;
        }
        if effect != "none" {
            assert!(
                best.significant && best.gap_shrink_pct > 20.0,
                "{effect}: {best:?}"
            );
        }
    }
    assert_eq!(checked, 9);
    // Five magnitudes with a comparable truth (measured: Σz² = 7.3, z from
    // −1.9 to 0.8): their squared errors over u² add up as a χ² with 5
    // degrees of freedom, below its 99.9 % point.
    assert_eq!(with_truth, 5);
    assert!(sum_z2 < 20.52, "Σz² = {sum_z2}");
}

/// What a `where` of truth.json is called in `diagnosis.csv`.
fn place_name(effect: &str, place: &str) -> String {
    match (effect, place) {
        ("range-scale", "all stations") => "all".into(),
        ("encoder-harmonic", "azimuth") => "az".into(),
        ("encoder-harmonic", "elevation") => "el".into(),
        _ => place.into(),
    }
}

/// The compound examples of effects.md version 2 — 07 station drift and
/// range scale, 08 an encoder harmonic and a knocked reflector, 11 three
/// blunders, 12 a blunder and a drift: the explanation set is exactly what
/// truth.json says was put in, each blunder named by its `readings.csv`
/// line, and once the set is modelled the residual is consistent with the
/// stated noise.
#[test]
fn compound_example_campaigns_are_explained_by_exactly_their_effects_and_blunders() {
    for name in [
        "example-07-drift-and-range-scale",
        "example-08-harmonic-and-target-shift",
        "example-11-three-blunders",
        "example-12-blunder-and-drift",
    ] {
        let dir = example(name);
        let truth: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.join("truth.json")).unwrap()).unwrap();
        let mut want: Vec<(String, String)> = match truth.get("items") {
            Some(items) => items
                .as_array()
                .unwrap()
                .iter()
                .map(|i| {
                    let e = i["effect"].as_str().unwrap();
                    (e.to_string(), place_name(e, i["where"].as_str().unwrap()))
                })
                .collect(),
            None => truth["where"]
                .as_object()
                .unwrap()
                .iter()
                .map(|(e, w)| (e.clone(), place_name(e, w.as_str().unwrap())))
                .collect(),
        };
        want.sort();
        let c = ltcal::campaign::read(&dir).unwrap();
        let d = diagnose::diagnose(&c, &Settings::default()).unwrap();
        let mut got: Vec<(String, String)> = d
            .explanation()
            .map(|r| (r.effect.clone(), r.place.clone()))
            .collect();
        got.sort();
        assert_eq!(got, want, "{name}");
        for b in truth["blunders"].as_array().into_iter().flatten() {
            let row = d
                .explanation()
                .find(|r| r.place == b["where"].as_str().unwrap())
                .unwrap();
            let line = format!("readings.csv line {}", b["line"]);
            assert!(row.detail.contains(&line), "{name}: {row:?}");
        }
        let none = d.rows.iter().find(|r| r.effect == "none").unwrap();
        assert!(none.significant, "{name}: {none:?}");
        assert_eq!(none.rank, got.len() + 1, "{name}");
        let (_, _, shrink) = diagnose::output::set_numbers(&d);
        assert!(
            shrink > 60.0,
            "{name}: the set removes {shrink:.1} % of the gap"
        );
    }
}

/// Before, a gap over the noise floor smaller than the floor's own Monte
/// Carlo error still had shares of it "removed": after example-08's
/// explanation set (gap 0.03 µm, floor known to ±0.06 µm) the rows read
/// −220 … +133 %, and on a big network with a gap of 4e-4 µm −4.9e6 %.
#[test]
fn a_gap_within_the_floors_monte_carlo_error_has_no_share_removed() {
    let dir = example("example-08-harmonic-and-target-shift");
    let c = ltcal::campaign::read(&dir).unwrap();
    let d = diagnose::diagnose(&c, &Settings::default()).unwrap();
    let floor = d.floor;
    // 100 draws of a floor of 11.24 µm, each varying by ~5 %.
    assert!(
        (11.0..11.5).contains(&floor.um) && (0.03..0.1).contains(&floor.u_um),
        "{floor:?}"
    );
    let within: Vec<_> = d
        .rows
        .iter()
        .filter(|r| r.gap_before_um.abs() <= floor.u_um)
        .collect();
    assert!(within.len() >= 5, "the case is exercised: {}", within.len());
    for r in &within {
        assert_eq!(r.gap_shrink_pct, 0.0, "{r:?}");
    }
    // The set's own gap is real and mostly removed.
    let (_, _, shrink) = diagnose::output::set_numbers(&d);
    assert!(shrink > 95.0, "{shrink}");
    // What the set leaves is within the floor's error: no localisation
    // basis removes a share of it.
    let rest_gap = d.explanation().last().unwrap().rms_after_um - floor.um;
    assert!(!floor.has_gap(rest_gap), "{rest_gap}");
    assert!(!d.unexplained.is_empty());
    for u in &d.unexplained {
        assert_eq!(u.gap_removed_pct, 0.0, "{}", u.basis);
    }
}

#[test]
fn effects_that_need_time_or_temperature_are_skipped_with_a_reason_when_absent() {
    let dir = example("example-00-none");
    let mut c = ltcal::campaign::read(&dir).unwrap();
    for r in &mut c.readings {
        r.time_s = None;
        r.temperature_c = None;
    }
    let d = diagnose::diagnose(&c, &Settings::default()).unwrap();
    let skipped: Vec<&str> = d.skipped.iter().map(|s| s.effect.as_str()).collect();
    assert_eq!(skipped, ["air-refraction", "station-drift"]);
    assert!(
        d.skipped
            .iter()
            .all(|s| s.reason.contains("readings.csv has no"))
    );
    assert!(
        d.rows
            .iter()
            .all(|r| r.effect != "air-refraction" && r.effect != "station-drift")
    );
    assert_eq!(d.best().effect, "none");
}

/// The acceptance of issues 9 and 13: on detectable single-effect cases
/// the right effect and the right station or reflector in ≥ 95 %, `none`
/// in ≥ 95 % of effect-free campaigns; over every kind, no spurious member
/// in ≥ 95 % of campaigns, ≥ 95 % of detectable blunders found with ≤ 1
/// false blunder per 1 000 clean readings, and no time-based effect named
/// in a file without time.
#[test]
fn blind_check_meets_its_targets() {
    let stage = BlindCheckStage {
        cases: 320,
        seed: 77,
        ..toml::from_str("").unwrap()
    };
    assert!(stage.validate().is_empty());
    let cases = blind::run(&stage.plan()).unwrap();
    // Single effects (and none): what is named first.
    let single = || cases.iter().filter(|c| c.kind.is_single());
    let det = Score::of(single().filter(|c| c.detectable));
    let all = Score::of(single());
    eprintln!("detectable: {det:?}\nall: {all:?}");
    assert!(det.with_effect >= 60 && det.effect_free >= 50, "{det:?}");
    assert!(
        det.effect_rate() >= 0.95,
        "effect named right in {:.1} %",
        100.0 * det.effect_rate()
    );
    assert!(
        det.place_rate() >= 0.95,
        "place named right in {:.1} %",
        100.0 * det.place_rate()
    );
    assert!(
        det.none_rate() >= 0.95,
        "none on {:.1} % of effect-free",
        100.0 * det.none_rate()
    );
    assert!(det.median_magnitude_error < 0.15, "{det:?}");
    // Every kind as a set.
    let kind = |k: CaseKind| SetAccuracy::of(cases.iter().filter(|c| c.kind == k));
    let two = kind(CaseKind::TwoEffects);
    eprintln!("two effects: {two:?}");
    assert!(two.all_found_rate() >= 0.8, "{two:?}");
    let every = SetAccuracy::of(cases.iter());
    eprintln!("all kinds: {every:?}");
    assert!(every.spurious_free_rate() >= 0.95, "{every:?}");
    assert!(every.detectable_blunders >= 40, "{every:?}");
    assert!(every.blunder_rate() >= 0.95, "{every:?}");
    assert!(every.false_blunders_per_1000() <= 1.0, "{every:?}");
    let no_time = kind(CaseKind::NoTime);
    assert!(no_time.cases >= 20, "{no_time:?}");
    assert_eq!(no_time.time_effects_without_time, 0, "{no_time:?}");
}

/// Issue 13's two-effect target on a sample of its own (the mixed sample
/// above holds only 18 detectable two-effect campaigns): both effects in
/// the explanation set in ≥ 90 % of the detectable ones, no spurious member
/// in ≥ 95 % of all. The committed pipeline's 2 000 cases give 91.0 % of
/// 111 (`ltcal show pipelines/blind-check.toml blind.kinds`).
#[test]
fn blind_two_effect_campaigns_are_explained_by_both() {
    let stage = BlindCheckStage {
        cases: 200,
        seed: 78,
        none_fraction: 0.0,
        kinds: vec![CaseKind::TwoEffects],
        ..toml::from_str("").unwrap()
    };
    assert!(stage.validate().is_empty());
    let cases = blind::run(&stage.plan()).unwrap();
    let two = SetAccuracy::of(cases.iter());
    eprintln!("two effects: {two:?}");
    assert!(two.detectable_cases >= 80, "{two:?}");
    assert!(two.all_found_rate() >= 0.9, "{two:?}");
    assert!(two.spurious_free_rate() >= 0.95, "{two:?}");
}

/// The paper's gap (issue: diagnosis, item 7): the pure model removes
/// everything on both tables; with realistic noise the improvement falls to
/// the paper's real-data level; a compensated tracker leaves almost nothing
/// to remove.
#[test]
fn paper_gap_scenarios_account_for_the_shortfall() {
    let dir = tempfile::tempdir().unwrap();
    crate::util::run_pipeline(
        &crate::util::pipeline_path("paper-gap.toml"),
        dir.path(),
        &[],
    );
    let gap = crate::util::table(dir.path(), "paper-gap", "gap", "gap");
    let get = |scenario: &str, col: &str| crate::util::cell(&gap, "scenario", scenario, col);
    for c in [
        "table7_coordinates",
        "table7_distances",
        "table8_coordinates",
        "table8_distances",
    ] {
        assert!(get("pure model", &format!("{c}_pct")) >= 98.0, "{c}");
        assert!(
            get("compensated + noise + table9", &format!("{c}_pct")) < 10.0,
            "{c}"
        );
    }
    // Noise alone already accounts for most of the corner campaign's shortfall.
    assert!(get("noise", "table7_coordinates_share_pct") > 80.0);
    // Paper-sized errors reach the paper's initial error within a factor 1.5.
    let init = get(
        "paper-sized errors + noise + all",
        "table7_coordinates_initial_um",
    );
    assert!((46.0 / 1.5..46.0 * 1.5).contains(&init), "{init}");
}

/// Regression: with two folds, a fold left reflectors with one training
/// reading each, its normal matrix was singular, and the diagnosis stopped
/// ("singular on a cross-validation fold") where the dense core had taken
/// the minimum-norm fit.
#[test]
fn two_folds_that_leave_a_pose_undetermined_still_diagnose() {
    for (name, effect) in [
        ("example-00-none", "none"),
        ("example-05-station-drift", "station-drift"),
    ] {
        let dir = example(name);
        let c = ltcal::campaign::read(&dir).unwrap();
        let s = Settings {
            folds: 2,
            ..Settings::default()
        };
        let d = diagnose::diagnose(&c, &s).unwrap();
        assert_eq!(d.best().effect, effect, "{name}: {:?}", d.best());
    }
}

/// `calibrate` with `reject_blunders = true` on example 11: iterated data
/// snooping removes exactly the three readings truth.json lists, by their
/// lines, and what is left is consistent with the stated noise; without
/// the option the blunders stay in and the χ² test fails.
#[test]
fn calibrate_rejects_exactly_the_blunders_of_example_11() {
    use ltcal::stages::calibrate::CalibrateStage;
    let dir = example("example-11-three-blunders");
    let c = ltcal::campaign::read(&dir).unwrap();
    let stage: CalibrateStage =
        toml::from_str("objective = \"bundle\"\nreject_blunders = true").unwrap();
    let (net, cal, rejected) = stage.calibrate(&c, None).unwrap();
    let mut lines: Vec<usize> = rejected
        .iter()
        .map(|r| c.readings[r.test.obs].line.unwrap())
        .collect();
    lines.sort();
    assert_eq!(lines, [68, 71, 104]);
    assert_eq!(net.obs.len(), c.readings.len() - 3);
    assert!(cal.fit.chi2_p.unwrap() > 0.01, "{:?}", cal.fit);
    for r in &rejected {
        assert!(r.test.w.abs() > r.critical_w && r.critical_w > 3.5, "{r:?}");
    }
    let plain: CalibrateStage = toml::from_str("objective = \"bundle\"").unwrap();
    let (_, cal, none) = plain.calibrate(&c, None).unwrap();
    assert!(none.is_empty());
    assert!(cal.fit.chi2_p.unwrap() < 1e-6, "{:?}", cal.fit);
}

/// Regression (issue 13): the diagnosis chose greedily, and per-station
/// range scales at every station — one broad candidate — absorbed air
/// refraction and one station's scale together (Δχ² 5 446 against 5 376
/// for the station's scale alone); once in, it blocked range-scale at the
/// right station and left too little for air refraction. The first step's
/// best candidates now each start a path, and the set with the lowest BIC
/// wins.
#[test]
fn a_broad_range_scale_no_longer_hides_air_refraction_and_one_stations_scale() {
    use ltcal::campaign::Aim;
    use ltcal::effects::{AirRefraction, Effects, RangeScale};
    use ltcal::kinematics::Face;
    use ltcal::layout::{self, Kind, Spec};
    use ltcal::noise::Noise;
    use ltcal::simulate::{CampaignSpec, simulate_campaign};

    let spec = Spec {
        stations: 4,
        ..Spec::new(Kind::Hall)
    };
    let layout = layout::build(&spec);
    let effects = Effects {
        air_refraction: Some(AirRefraction {
            t0_c: 20.0,
            offset_c: 0.0,
            amplitude_c: 0.62,
            period_s: 2205.0,
            phase_deg: 200.7,
            drift_c_per_h: 1.26,
        }),
        range_scale: Some(RangeScale {
            ppm: [("S3".to_string(), -6.2)].into(),
            sigma_ppm: None,
        }),
        ..Effects::default()
    };
    let sim = simulate_campaign(&CampaignSpec {
        name: "broad-range-scale".into(),
        layout: &layout,
        errors: None,
        faces: &[Face::Front],
        aim: Aim::StationsCentroid,
        max_angle_deg: 30.0,
        noise: Noise {
            sigma_angle_urad: 0.56,
            sigma_range_um: 1.68,
            sigma_range_ppm: 0.3,
        },
        effects: &effects,
        gauge_u_mm: 0.0005,
        reference_u_mm: 0.002,
        level_urad: 1000.0,
        interval_s: 20.0,
        record_time: true,
        record_temperature: true,
        seed: 402,
    })
    .unwrap();
    let d = diagnose::diagnose(&sim.campaign, &Settings::default()).unwrap();
    let mut set: Vec<(&str, &str, f64)> = d
        .explanation()
        .map(|r| (r.effect.as_str(), r.place.as_str(), r.magnitude))
        .collect();
    set.sort_by(|a, b| a.0.cmp(b.0));
    let named: Vec<(&str, &str)> = set.iter().map(|m| (m.0, m.1)).collect();
    assert_eq!(
        named,
        [("air-refraction", "all"), ("range-scale", "S3")],
        "{:#?}",
        &d.rows[..4]
    );
    // Each member's magnitude is read from the joint refit of the set:
    // the coefficient of effects.md (−0.93 ppm/K) and the station's scale.
    assert!((set[0].2 - -0.93).abs() < 0.2, "{set:?}");
    assert!((set[1].2 - -6.2).abs() < 0.3, "{set:?}");
}

/// `ltcal diagnose` on example-00 with `edit` applied to readings.csv: the
/// exit code, stdout and stderr, and diagnosis.csv when written.
fn diagnose_edited(edit: impl FnOnce(&str) -> String) -> (i32, String, String, String) {
    let tmp = tempfile::tempdir().unwrap();
    let dir = crate::hostile::mutated_example(tmp.path(), "example-00-none", "readings.csv", edit);
    let o = crate::cli::ltcal(
        tmp.path(),
        &["diagnose", dir.to_str().unwrap(), "--out", "out"],
    );
    let csv = std::fs::read_to_string(tmp.path().join("out/diagnosis.csv")).unwrap_or_default();
    (
        o.status.code().unwrap_or(-1),
        crate::cli::stdout(&o),
        crate::cli::stderr(&o),
        csv,
    )
}

/// The explanation set's blunder rows of a diagnosis.csv: (where, detail).
fn blunder_members(csv: &str) -> Vec<String> {
    csv.lines()
        .filter(|l| l.contains(",blunder,") && !l.contains(",false,"))
        .map(str::to_string)
        .collect()
}

/// Regression (issue 28): one azimuth of example-00 set to 0 (a 42°
/// blunder on S2/T02, line 27) made `ltcal diagnose` exit 1 with "normal
/// matrix is singular on a cross-validation fold", naming no reading — the
/// one case blunder detection exists for. Now the gross blunder is found
/// before the folds and named with its readings.csv line.
#[test]
fn a_gross_azimuth_blunder_is_named_with_its_readings_line_not_a_singular_fold() {
    let (code, out, err, csv) = diagnose_edited(|t| crate::hostile::replace_cell(t, 27, 2, "0"));
    assert_eq!(code, 0, "{err}");
    let members = blunder_members(&csv);
    assert!(
        members.iter().any(|l| l.contains("S2/T02/1")
            && l.contains("az")
            && l.contains("readings.csv line 27")),
        "{csv}"
    );
    assert!(out.contains("S2/T02/1"), "{out}");
}

/// Variants of the gross blunder (issue 28): an elevation set to 0, and a
/// distance of 0 (not valid per the format: refused at its place).
#[test]
fn gross_elevation_and_zero_distance_blunders_are_named_with_their_readings_line() {
    let (code, _, err, csv) = diagnose_edited(|t| crate::hostile::replace_cell(t, 27, 3, "0"));
    assert_eq!(code, 0, "{err}");
    assert!(
        blunder_members(&csv).iter().any(|l| l.contains("S2/T02/1")
            && l.contains("el,")
            && l.contains("readings.csv line 27")),
        "{csv}"
    );
    let (code, _, err, _) = diagnose_edited(|t| crate::hostile::replace_cell(t, 27, 4, "0"));
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("readings.csv:27:"), "{err}");
    assert!(err.contains("d_mm"), "{err}");
}

/// Regression (issue 28): `sigma_angle_urad = 0` gave a verdict of 8
/// blunders and "−72.8 % of the gap removed" on a clean campaign: every
/// residual was tested against a noise floor of 1e-3 µrad. A diagnosis now
/// refuses a stated noise of 0 at its place (a calibration still takes it).
#[test]
fn a_stated_noise_of_zero_is_refused_by_the_diagnosis_at_its_place() {
    let tmp = tempfile::tempdir().unwrap();
    let dir =
        crate::hostile::mutated_example(tmp.path(), "example-00-none", "campaign.toml", |t| {
            t.replace("sigma_angle_urad = 0.635", "sigma_angle_urad = 0")
        });
    let o = crate::cli::ltcal(
        tmp.path(),
        &["diagnose", dir.to_str().unwrap(), "--out", "out"],
    );
    crate::cli::assert_code(&o, 2);
    let err = crate::cli::stderr(&o);
    assert!(err.contains("campaign.toml:7:"), "{err}");
    assert!(
        err.contains("a stated noise of 0 cannot be diagnosed"),
        "{err}"
    );
    assert!(!tmp.path().join("out").exists());
    assert!(ltcal::campaign::read_for_calibration(&dir).is_ok());
}

/// Regression (issue 28): a SIGTERM during a diagnosis left its temporary
/// folder (1.8 GB for a million readings) beside `--out`, and no later run
/// removed it. A later `diagnose --out` removes its own stale temporaries —
/// of the same `--out`, made by a process that has ended — and nothing else.
#[test]
fn a_later_diagnosis_removes_the_temporary_a_killed_one_left_beside_out() {
    let tmp = tempfile::tempdir().unwrap();
    let host = ltcal::fs::host();
    // A pid that has ended: a child that ran and was waited for.
    let mut child = std::process::Command::new("true").spawn().unwrap();
    let dead = child.id();
    child.wait().unwrap();
    let stale = tmp.path().join(format!(".out.{dead}-0-{host}.tmp"));
    let stale_old = tmp.path().join(format!(".out.{dead}-1-{host}.old"));
    // A live owner's (this test's), another --out's, another machine's.
    let live = tmp
        .path()
        .join(format!(".out.{}-0-{host}.tmp", std::process::id()));
    let other = tmp.path().join(format!(".other.{dead}-0-{host}.tmp"));
    let foreign = tmp.path().join(format!(".out.{dead}-0-0123456789ab.tmp"));
    for d in [&stale, &stale_old, &live, &other, &foreign] {
        std::fs::create_dir(d).unwrap();
        std::fs::write(d.join("residuals-az.svg"), "partial").unwrap();
    }
    let good = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("examples/campaigns/example-00-none");
    let o = crate::cli::ltcal(
        tmp.path(),
        &["diagnose", good.to_str().unwrap(), "--out", "out"],
    );
    crate::cli::assert_code(&o, 0);
    assert!(!stale.exists() && !stale_old.exists());
    assert!(live.exists() && other.exists() && foreign.exists());
    assert!(tmp.path().join("out/diagnosis.csv").is_file());
    assert!(crate::cli::stderr(&o).contains("left by a diagnosis that was stopped"));
}

/// The first member of a diagnosis.csv's explanation set (rank 1).
fn first_member(csv: &str) -> &str {
    csv.lines().nth(1).unwrap_or("")
}

/// Regression (issue 28, item 7): a distance of example-00 ten times too
/// long (line 27) made `ltcal diagnose` exit 1 with "normal matrix is
/// singular on a cross-validation fold": the base adjustment passed, but
/// the gross reading dragged it (100 iterations, not converged) so far that
/// the blunders named next were its neighbours', each down-weighted
/// reading still pulled, and a fold of a later step could not be fitted.
/// Other variants exited 0 with chains of innocent readings named, up to
/// 1e26 µm. Now a gross blunder (|w| > 1e4, or a fold that cannot be
/// fitted) is screened out as a whole reading on all data first, and named
/// with its readings.csv line as the set's first member — for every
/// variant below, two at once, and on the mirror tracker.
#[test]
fn every_gross_blunder_variant_is_named_with_its_readings_line_never_a_singular_fold() {
    let scale = |line: usize, col: usize, f: fn(f64) -> f64| {
        move |t: &str| {
            let cell = t
                .lines()
                .nth(line - 1)
                .unwrap()
                .split(',')
                .nth(col)
                .unwrap();
            let v: f64 = cell.parse().unwrap();
            crate::hostile::replace_cell(t, line, col, &format!("{}", f(v)))
        }
    };
    // (name, edit, the coordinates the blunder may be named by).
    type Edit = Box<dyn Fn(&str) -> String>;
    let variants: Vec<(&str, Edit, &[&str])> = vec![
        (
            "d × 10",
            Box::new(scale(27, 4, |d| d * 10.0)),
            &["az,", "el,", "d,"],
        ),
        ("d × 0.1", Box::new(scale(27, 4, |d| d * 0.1)), &["d,"]),
        (
            "d + 1000 mm",
            Box::new(scale(27, 4, |d| d + 1000.0)),
            &["d,"],
        ),
        (
            "az + 180°",
            Box::new(scale(27, 2, |a| a + 180.0)),
            &["az,", "el,", "d,"],
        ),
        ("el = −89.9°", Box::new(scale(27, 3, |_| -89.9)), &["el,"]),
    ];
    for (name, edit, coordinates) in variants {
        let (code, out, err, csv) = diagnose_edited(edit);
        assert_eq!(code, 0, "{name}: {err}");
        let first = first_member(&csv);
        assert!(
            first.contains(",blunder,S2/T02/1,")
                && first.contains("readings.csv line 27; gross")
                && coordinates
                    .iter()
                    .any(|c| first.contains(&format!("\"{c}"))),
            "{name}: {csv}"
        );
        assert!(out.contains("readings.csv line 27"), "{name}: {out}");
    }
    // el = 89.9°: the reading drags its reflector so far that another of
    // its readings (S4/T02, line 75) is screened too — never the blunder
    // missed.
    let (code, _, err, csv) = diagnose_edited(scale(27, 3, |_| 89.9));
    assert_eq!(code, 0, "{err}");
    let gross: Vec<&str> = csv.lines().filter(|l| l.contains("; gross")).collect();
    assert!(gross.len() <= 2, "{csv}");
    assert!(
        gross
            .iter()
            .any(|l| l.contains(",blunder,S2/T02/1,") && l.contains("readings.csv line 27;")),
        "{csv}"
    );
    // Two gross blunders in different stations at once: both named.
    let (code, _, err, csv) = diagnose_edited(|t| {
        let t = scale(27, 4, |d| d * 10.0)(t);
        scale(52, 2, |a| a + 180.0)(&t)
    });
    assert_eq!(code, 0, "{err}");
    let gross: Vec<&str> = csv.lines().filter(|l| l.contains("; gross")).collect();
    assert_eq!(gross.len(), 2, "{csv}");
    assert!(gross[0].contains(",blunder,S2/T02/1,") && gross[0].contains("line 27;"));
    assert!(gross[1].contains(",blunder,S3/T03/1,") && gross[1].contains("line 52;"));
    // A campaign without a gross blunder screens nothing.
    let (code, _, err, csv) = diagnose_edited(str::to_string);
    assert_eq!(code, 0, "{err}");
    assert!(!csv.contains("gross"), "{csv}");
}

/// The gross blunder of the test above on a campaign the mirror tracker
/// took, diagnosed with its own model: screened and named (a simulated
/// campaign's readings have no file line: by their number).
#[test]
fn a_gross_blunder_on_the_mirror_tracker_is_named_never_a_singular_fold() {
    use ltcal::campaign::Aim;
    use ltcal::effects::Effects;
    use ltcal::error_model::{ErrorModel, ErrorParams};
    use ltcal::kinematics::Face;
    use ltcal::layout::{self, Kind, Spec};
    use ltcal::noise::Noise;
    use ltcal::simulate::{CampaignSpec, simulate_campaign};
    use ltcal::trackers::TrackerModel;
    let model = ErrorModel::of(TrackerModel::parse("mirror-tracker").unwrap());
    let mut errors = ErrorParams::zero(&model);
    errors.values_mut().iter_mut().for_each(|v| *v = 10.0);
    let layout = layout::build(&Spec::new(Kind::Corner));
    let mut sim = simulate_campaign(&CampaignSpec {
        name: "corner".into(),
        layout: &layout,
        errors: Some(&errors),
        faces: &[Face::Front, Face::Back],
        aim: Aim::StationsCentroid,
        max_angle_deg: 30.0,
        noise: Noise {
            sigma_angle_urad: 1.0,
            sigma_range_um: 2.0,
            sigma_range_ppm: 0.3,
        },
        effects: &Effects::default(),
        gauge_u_mm: 0.0005,
        reference_u_mm: 0.002,
        level_urad: 1000.0,
        interval_s: 20.0,
        record_time: true,
        record_temperature: true,
        seed: 7,
    })
    .unwrap();
    sim.campaign.readings[10].d_mm *= 10.0;
    let r = &sim.campaign.readings[10];
    let place = format!("{}/{}/{}", r.station, r.target, r.face.number());
    let s = Settings {
        model,
        mc_draws: 20,
        ..Settings::default()
    };
    let d = diagnose::diagnose(&sim.campaign, &s).unwrap();
    let first = d.explanation().next().unwrap();
    assert_eq!(
        (first.effect.as_str(), first.place.as_str()),
        ("blunder", place.as_str())
    );
    assert!(first.detail.contains("reading 11; gross"), "{first:?}");
    assert_eq!(d.residuals.len(), sim.campaign.readings.len() - 1);
}
