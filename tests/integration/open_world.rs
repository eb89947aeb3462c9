//! The diagnosis on effects outside its catalogue (`ltcal::open_world`):
//! honest that the residual is not explained, and pointing at the factor
//! the structure lies along.

use ltcal::campaign::Aim;
use ltcal::diagnose::{self, Settings};
use ltcal::effects::Effects;
use ltcal::error_model::{ErrorModel, ErrorParams};
use ltcal::kinematics::Face;
use ltcal::layout::{self, Kind as Layout, Spec};
use ltcal::noise::Noise;
use ltcal::open_world::{Context, Kind, OpenEffect};
use ltcal::random;
use ltcal::simulate::{CampaignSpec, SimulatedCampaign, simulate_campaign};
use ltcal::tracker::TrackerModel;
use rayon::prelude::*;

fn simulate(seed: u64, errors: &ErrorParams) -> SimulatedCampaign {
    let layout = layout::build(&Spec::new(Layout::Corner));
    simulate_campaign(&CampaignSpec {
        name: "open-world".into(),
        layout: &layout,
        errors: Some(errors),
        faces: &[Face::Front],
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
        seed,
    })
    .unwrap()
}

/// One campaign carrying `kind`, diagnosed: (top significant factor,
/// not explained, verdict).
fn case(kind: Kind, seed: u64) -> (String, bool, String, String) {
    let mut rng = random::stream(seed, "open-world-test");
    let mut errors = ErrorParams::zero(&ErrorModel::of(TrackerModel::ApiTracker3));
    for v in errors.values_mut() {
        *v = 5.0 * random::normal(&mut rng);
    }
    let sim = simulate(seed, &errors);
    let effect = OpenEffect::draw(kind, &mut rng, &Context::of(&sim)).unwrap();
    let sim = effect.apply(&sim, Some(&errors)).unwrap();
    let d = diagnose::diagnose(
        &sim.campaign,
        &Settings {
            seed,
            ..Settings::default()
        },
    )
    .unwrap();
    let top = d
        .unexplained
        .iter()
        .find(|l| l.significant)
        .map(|l| format!("{} ({}, {:.0} %)", l.factor, l.basis, 100.0 * l.share))
        .unwrap_or_default();
    let none = d.rows.iter().find(|r| r.effect == "none").unwrap();
    (
        top,
        !none.significant,
        diagnose::output::verdict(&d),
        effect.describe(),
    )
}

#[test]
#[ignore = "exploration"]
fn explore_open_world() {
    let cases: Vec<(Kind, u64)> = Kind::ALL
        .iter()
        .flat_map(|&k| (1..=4).map(move |s| (k, s)))
        .collect();
    let out: Vec<_> = cases.par_iter().map(|&(k, s)| (k, case(k, s))).collect();
    for (k, (top, not_explained, verdict, what)) in out {
        eprintln!(
            "{} [{}] | top: {top} | not explained: {not_explained}\n   {what}\n   {verdict}",
            k.id(),
            k.factor()
        );
    }
}
