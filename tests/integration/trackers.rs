//! Other trackers (issue 15): each tracker model fitted to campaigns its own
//! construction took, and to campaigns the other one took.

use ltcal::calibrate::{self, Calibration, Network, Norm, Objective, Settings};
use ltcal::campaign::Aim;
use ltcal::criteria;
use ltcal::effects::Effects;
use ltcal::error_model::{ErrorModel, ErrorParams};
use ltcal::kinematics::Face;
use ltcal::layout::{self, Kind, Spec};
use ltcal::noise::Noise;
use ltcal::simulate::{CampaignSpec, SimulatedCampaign, simulate_campaign};
use ltcal::trackers::TrackerModel;
use nalgebra::DVector;

const BOTH: [Face; 2] = [Face::Front, Face::Back];

const REALISTIC: Noise = Noise {
    sigma_angle_urad: 1.0,
    sigma_range_um: 2.0,
    sigma_range_ppm: 0.3,
};

/// Every parameter of `model` at 10 µm or 10 µrad (Table 2's magnitude).
fn ten(model: TrackerModel) -> ErrorParams {
    let mut p = ErrorParams::zero(&ErrorModel::of(model));
    p.values_mut().iter_mut().for_each(|v| *v = 10.0);
    p
}

fn simulate(noise: Noise, errors: &ErrorParams, seed: u64) -> SimulatedCampaign {
    simulate_with(noise, errors, &Effects::default(), seed)
}

fn simulate_with(
    noise: Noise,
    errors: &ErrorParams,
    effects: &Effects,
    seed: u64,
) -> SimulatedCampaign {
    let layout = layout::build(&Spec::new(Kind::Corner));
    simulate_campaign(&CampaignSpec {
        name: "corner".into(),
        layout: &layout,
        errors: Some(errors),
        faces: &BOTH,
        aim: Aim::StationsCentroid,
        max_angle_deg: 30.0,
        noise,
        effects,
        gauge_u_mm: if noise.is_zero() { 0.0 } else { 0.0005 },
        reference_u_mm: 0.002,
        level_urad: 1000.0,
        interval_s: 20.0,
        record_time: true,
        record_temperature: true,
        seed,
    })
    .unwrap()
}

fn bundle(net: &Network, start: &ErrorParams) -> Calibration {
    let free = vec![true; start.coefs().len()];
    let s = Settings {
        objective: Objective::Bundle,
        norm: Norm::L2,
        rank_tol: 1e-9,
        max_iters: 200,
        std: ltcal::calibrate::BundleStd::Auto,
    };
    calibrate::calibrate(net, start, &free, &s).unwrap()
}

#[test]
fn a_simulated_campaign_names_the_model_of_its_errors() {
    for model in TrackerModel::ALL {
        let sim = simulate(Noise::default(), &ten(model), 1);
        assert_eq!(sim.campaign.meta.tracker.model, model.id());
        assert_eq!(sim.campaign.tracker_model(), model);
    }
}

/// Noise-free, for each model: with the undetermined directions set to the
/// truth's own component (iterated, the null space turning slightly with the
/// point), the bundle adjustment returns every parameter — hence every
/// determined combination — to 1e-6, and removes more than 99.9 % of the
/// coordinate error.
#[test]
fn noise_free_validation_recovers_each_model_to_1e_6_and_removes_999_permille() {
    for model in TrackerModel::ALL {
        let truth = ten(model);
        let sim = simulate(Noise::default(), &truth, 3);
        let net = Network::from_campaign(&sim.campaign).unwrap();
        let zero = ErrorParams::zero(&ErrorModel::of(model));
        let mut cal = bundle(&net, &zero);
        let c0 = criteria::coordinates(&net, &zero).unwrap().overall.mean_um;
        let c1 = criteria::coordinates(&net, &cal.estimate.params)
            .unwrap()
            .overall
            .mean_um;
        let removed = criteria::improvement_pct(c0, c1);
        assert!(removed > 99.9, "{model}: {removed} % of {c0} µm removed");
        let t = DVector::from_column_slice(truth.values());
        for _ in 0..4 {
            let n = &cal.estimate.analysis.null_basis;
            let start = ErrorParams::from_parts(
                zero.coefs().to_vec(),
                (n * (n.transpose() * &t)).iter().copied().collect(),
            );
            cal = bundle(&net, &start);
        }
        for (c, (a, b)) in truth
            .coefs()
            .iter()
            .zip(cal.estimate.params.values().iter().zip(truth.values()))
        {
            assert!((a - b).abs() < 1e-6, "{model} {}: {a} vs {b}", c.name());
        }
        eprintln!(
            "{model}: rank {} of {}, {removed:.6} % removed",
            cal.estimate.analysis.rank,
            truth.coefs().len()
        );
    }
}

/// With noise, each model fitted to its own tracker's campaign leaves the
/// noise (χ² consistent with its degrees of freedom); fitted to the other
/// tracker's campaign it does not.
#[test]
fn each_model_fits_its_own_tracker_and_not_the_other() {
    for truth_model in TrackerModel::ALL {
        let sim = simulate(REALISTIC, &ten(truth_model), 5);
        let net = Network::from_campaign(&sim.campaign).unwrap();
        for fit_model in TrackerModel::ALL {
            let cal = bundle(&net, &ErrorParams::zero(&ErrorModel::of(fit_model)));
            let (chi2, dof) = (cal.fit.chi2.unwrap(), cal.fit.dof.unwrap() as f64);
            eprintln!("{truth_model} fitted with {fit_model}: χ² {chi2:.1} on {dof}");
            if fit_model == truth_model {
                assert!(
                    (chi2 / dof - 1.0).abs() < 4.0 * (2.0 / dof).sqrt(),
                    "{truth_model}: χ² {chi2} on {dof}"
                );
            } else {
                assert!(
                    cal.fit.chi2_p.unwrap() < 1e-6,
                    "{truth_model} by {fit_model}: χ² {chi2} on {dof}"
                );
            }
        }
    }
}

/// The must-show of issue 15: a campaign the mirror tracker took, diagnosed
/// with the head-laser model, is called a model mismatch naming the mirror
/// tracker — no effect is blamed — and the other way round.
#[test]
fn a_campaign_diagnosed_with_the_other_trackers_model_is_called_a_model_mismatch() {
    use ltcal::diagnose::{self, Settings, output};
    for truth_model in TrackerModel::ALL {
        let sim = simulate(REALISTIC, &ten(truth_model), 7);
        for base in TrackerModel::ALL {
            let s = Settings {
                model: ErrorModel::of(base),
                mc_draws: 20,
                ..Settings::default()
            };
            let d = diagnose::diagnose(&sim.campaign, &s).unwrap();
            let verdict = output::verdict(&d);
            eprintln!("{truth_model} diagnosed with {base}: {verdict}");
            assert_eq!(d.models[0].model, truth_model, "{:?}", d.models);
            let model_row = d.rows.iter().find(|r| r.effect == "model").unwrap();
            if base == truth_model {
                assert!(!model_row.significant, "{model_row:?}");
                assert!(verdict.starts_with("none:"), "{verdict}");
            } else {
                assert_eq!(d.best().effect, "model");
                assert_eq!(d.best().place, truth_model.id());
                assert!(d.best().delta_bic > 1000.0, "{:?}", d.best());
                assert_eq!(d.explanation().count(), 1, "{verdict}");
                assert!(
                    verdict.starts_with(&format!(
                        "model mismatch: the readings fit the {truth_model} model"
                    )),
                    "{verdict}"
                );
            }
        }
    }
}

/// The blind check of the model choice: where the models differ detectably
/// (the other model leaves χ² ≥ 25 on the noise-free campaign), the model
/// ranked first is the one that made the campaign in ≥ 90 % of cases.
#[test]
fn blind_model_choice_is_right_on_90_percent_of_detectable_campaigns() {
    let layout = layout::build(&Spec::new(Kind::Corner));
    let cases = ltcal::diagnose::models::blind_check(&layout, REALISTIC, 60, 3).unwrap();
    let detectable: Vec<_> = cases.iter().filter(|c| c.detectable).collect();
    let right = detectable.iter().filter(|c| c.chosen == c.truth).count();
    eprintln!("{right} of {} detectable cases right", detectable.len());
    assert!(detectable.len() >= 20, "{cases:?}");
    assert!(right as f64 >= 0.9 * detectable.len() as f64, "{cases:?}");
    // Both models made detectable campaigns.
    for m in TrackerModel::ALL {
        assert!(detectable.iter().any(|c| c.truth == m));
    }
}

/// A mirror campaign with an unmodelled effect too, diagnosed with the
/// head-laser model: the model mismatch first, then the effect on top of the
/// model that fits.
#[test]
fn a_mirror_campaign_with_an_effect_is_a_model_mismatch_and_the_effect() {
    use ltcal::diagnose::{self, Settings, output};
    use ltcal::effects::RangeScale;
    let effects = Effects {
        range_scale: Some(RangeScale {
            ppm: [("S2".to_string(), 8.0)].into(),
            sigma_ppm: None,
        }),
        ..Effects::default()
    };
    let sim = simulate_with(
        REALISTIC,
        &ten(TrackerModel::parse("mirror-tracker").unwrap()),
        &effects,
        7,
    );
    let s = Settings {
        model: ErrorModel::constant(),
        mc_draws: 20,
        ..Settings::default()
    };
    let d = diagnose::diagnose(&sim.campaign, &s).unwrap();
    let verdict = output::verdict(&d);
    let set: Vec<(&str, &str)> = d
        .explanation()
        .map(|r| (r.effect.as_str(), r.place.as_str()))
        .collect();
    assert_eq!(
        set,
        [("model", "mirror-tracker"), ("range-scale", "S2")],
        "{verdict}"
    );
    assert!(
        verdict.starts_with("model mismatch: the readings fit the mirror-tracker model")
            && verdict.ends_with("on top of it: range-scale at S2"),
        "{verdict}"
    );
}

/// Regression: where the models fit equally well (a mirror tracker with
/// errors no campaign sees), the BIC prefers the DH chain's fewer determined
/// combinations by about 20 — parsimony, not a misfit — and the diagnosis
/// of a mirror campaign with its own model called that a model mismatch.
#[test]
fn models_that_fit_equally_well_are_not_a_model_mismatch() {
    use ltcal::diagnose::{self, Settings, output};
    let mut tiny = ten(TrackerModel::parse("mirror-tracker").unwrap());
    tiny.values_mut().iter_mut().for_each(|v| *v = 0.01);
    let sim = simulate(REALISTIC, &tiny, 9);
    let s = Settings {
        model: ErrorModel::of(TrackerModel::parse("mirror-tracker").unwrap()),
        mc_draws: 20,
        ..Settings::default()
    };
    let d = diagnose::diagnose(&sim.campaign, &s).unwrap();
    let m = &d.models;
    assert_eq!(m[0].model, TrackerModel::default(), "{m:?}");
    assert!(
        m[1].bic - m[0].bic > 10.0 && (m[1].chi2 - m[0].chi2).abs() < 25.0,
        "{m:?}"
    );
    let row = d.rows.iter().find(|r| r.effect == "model").unwrap();
    assert!(!row.significant, "{row:?}");
    assert!(
        output::verdict(&d).starts_with("none:"),
        "{}",
        output::verdict(&d)
    );
}

/// Regression: the model row is a member like any other — with
/// `max_steps = 0` the explanation set stays empty; with `max_steps = 1` the
/// model is its one member and no effect is searched on top.
#[test]
fn the_model_row_counts_against_max_steps() {
    use ltcal::diagnose::{self, Settings};
    let sim = simulate(
        REALISTIC,
        &ten(TrackerModel::parse("mirror-tracker").unwrap()),
        7,
    );
    for steps in [0, 1] {
        let s = Settings {
            model: ErrorModel::constant(),
            mc_draws: 20,
            max_steps: steps,
            ..Settings::default()
        };
        let d = diagnose::diagnose(&sim.campaign, &s).unwrap();
        assert_eq!(d.explanation().count(), steps, "max_steps {steps}");
        let model = d.rows.iter().find(|r| r.effect == "model").unwrap();
        assert_eq!(model.significant, steps == 1, "{model:?}");
    }
}
