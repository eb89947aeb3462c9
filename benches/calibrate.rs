//! `calibrate_corner`: the bundle adjustment of the corner campaign of
//! Section 7 — 24 reflectors, 5 stations, the 18 error parameters with the
//! station poses and reflector positions — as the `calibrate` stage runs it
//! (identifiability analysis included).
//!
//! `monte_carlo_corner`: GUM-S1 Monte Carlo of the same calibration, one
//! block of 10 000 trials (issue 14's target: ≤ 10 s on 2 cores).
//!
//!     cargo bench --bench calibrate

use criterion::{Criterion, criterion_group, criterion_main};
use ltcal::calibrate::bundle::Repeated;
use ltcal::calibrate::{Network, Norm, Objective, Settings, calibrate, monte_carlo};
use ltcal::campaign::Aim;
use ltcal::effects::Effects;
use ltcal::error_model::{ErrorModel, ErrorParams};
use ltcal::kinematics::Face;
use ltcal::layout::{self, Kind, Spec};
use ltcal::noise::Noise;
use ltcal::simulate::{CampaignSpec, simulate_campaign};
use std::hint::black_box;

fn corner() -> Network {
    let layout = layout::build(&Spec::new(Kind::Corner));
    let sim = simulate_campaign(&CampaignSpec {
        name: "corner".into(),
        layout: &layout,
        errors: Some(&ErrorParams::table2()),
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
        seed: 7,
    })
    .unwrap();
    Network::from_campaign(&sim.campaign).unwrap()
}

const SETTINGS: Settings = Settings {
    objective: Objective::Bundle,
    norm: Norm::L2,
    rank_tol: 1e-9,
    max_iters: 100,
    std: ltcal::calibrate::BundleStd::Auto,
};

fn calibrate_corner(c: &mut Criterion) {
    let net = corner();
    let start = ErrorParams::zero(&ErrorModel::constant());
    c.bench_function("calibrate_corner", |b| {
        b.iter(|| calibrate(black_box(&net), &start, &[true; 18], &SETTINGS).unwrap())
    });
}

fn monte_carlo_corner(c: &mut Criterion) {
    let net = corner();
    let start = ErrorParams::zero(&ErrorModel::constant());
    let free = [true; 18];
    let mc = monte_carlo::Settings {
        block_trials: 10_000,
        digits: 1,
        max_trials: 10_000,
        coverage: 0.95,
        seed: 1,
    };
    let mut g = c.benchmark_group("monte_carlo_corner");
    g.sample_size(10);
    g.bench_function("10000_trials", |b| {
        b.iter(|| {
            let repeated = Repeated::new(black_box(&net), &start, &free, &SETTINGS).unwrap();
            monte_carlo::run(&net, &repeated, &free, &mc).unwrap()
        })
    });
    g.finish();
}

criterion_group!(benches, calibrate_corner, monte_carlo_corner);
criterion_main!(benches);
