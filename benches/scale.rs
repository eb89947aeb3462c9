//! How the bundle adjustment and the diagnosis grow with the network:
//! `calibrate_scale` and `diagnose_scale` over the `network` layout from
//! 33 to 1 100 reflectors and 8 to 20 stations, one face and two. Each
//! case's id is `<reflectors>x<stations>x<faces>f/<readings>`, so the
//! medians can be read against the readings (the README's log–log slope
//! comes from these medians).
//!
//! `calibrate_hall` is issue 10's own case: the `hall` layout with 200
//! reflectors per level (600 in all) read from 8 stations, every reflector
//! from every station (4 800 readings), as the issue timed it.
//! `mirror_hall` is the same hall read by a mirror tracker (every
//! misalignment 10 µm or 10 µrad): its bundle adjustment with its own model
//! (analytic derivatives of the beam path) and `compare_models` on it (both
//! models, each with its 5-fold held-out residual).
//!
//!     cargo bench --bench scale

mod common;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use ltcal::calibrate::{Network, Norm, Objective, Settings, calibrate};
use ltcal::campaign::Campaign;
use ltcal::diagnose::{self, diagnose, models};
use ltcal::error_model::{ErrorModel, ErrorParams};
use ltcal::layout::Kind;
use ltcal::trackers::TrackerModel;
use std::hint::black_box;
use std::time::Duration;

/// `(wall reflectors per level, stations, faces)`: 33, 110, 330, 605 and
/// 1 100 reflectors.
const SERIES: [(usize, usize, usize); 6] = [
    (6, 8, 1),
    (20, 8, 1),
    (60, 8, 1),
    (110, 8, 1),
    (200, 16, 2),
    (200, 20, 2),
];

/// A simulated campaign of the `network` layout with the paper's Table 2
/// errors and typical indoor noise.
fn campaign(per_level: usize, stations: usize, faces: usize) -> Campaign {
    campaign_of(Kind::Network, per_level, stations, faces)
}

fn campaign_of(kind: Kind, per_level: usize, stations: usize, faces: usize) -> Campaign {
    campaign_with(kind, per_level, stations, faces, &ErrorParams::table2())
}

fn campaign_with(
    kind: Kind,
    per_level: usize,
    stations: usize,
    faces: usize,
    errors: &ErrorParams,
) -> Campaign {
    common::simulated("network", kind, per_level, stations, faces, errors)
}

fn id(c: &Campaign, stations: usize, faces: usize) -> BenchmarkId {
    BenchmarkId::new(
        format!("{}x{stations}x{faces}f", c.targets.len()),
        c.readings.len(),
    )
}

/// The bundle adjustment as `calibrate` runs it by default.
fn bundle() -> Settings {
    Settings {
        objective: Objective::Bundle,
        norm: Norm::L2,
        rank_tol: 1e-9,
        max_iters: 100,
        std: ltcal::calibrate::BundleStd::Auto,
    }
}

fn calibrate_scale(c: &mut Criterion) {
    let mut g = c.benchmark_group("calibrate_scale");
    g.sample_size(10).measurement_time(Duration::from_secs(4));
    let start = ErrorParams::zero(&ErrorModel::constant());
    let settings = bundle();
    for (per_level, stations, faces) in SERIES {
        let camp = campaign(per_level, stations, faces);
        let net = Network::from_campaign(&camp).unwrap();
        g.bench_function(id(&camp, stations, faces), |b| {
            b.iter(|| calibrate(black_box(&net), &start, &[true; 18], &settings).unwrap())
        });
    }
    g.finish();
}

fn calibrate_hall(c: &mut Criterion) {
    let mut g = c.benchmark_group("calibrate_hall");
    g.sample_size(20).measurement_time(Duration::from_secs(4));
    let camp = campaign_of(Kind::Hall, 200, 8, 1);
    let net = Network::from_campaign(&camp).unwrap();
    let start = ErrorParams::zero(&ErrorModel::constant());
    let settings = bundle();
    g.bench_function(id(&camp, 8, 1), |b| {
        b.iter(|| calibrate(black_box(&net), &start, &[true; 18], &settings).unwrap())
    });
    g.finish();
}

fn mirror_hall(c: &mut Criterion) {
    let mut g = c.benchmark_group("mirror_hall");
    g.sample_size(10).measurement_time(Duration::from_secs(4));
    let model = ErrorModel::of(TrackerModel::parse("mirror-tracker").unwrap());
    let mut truth = ErrorParams::zero(&model);
    truth.values_mut().iter_mut().for_each(|v| *v = 10.0);
    let camp = campaign_with(Kind::Hall, 200, 8, 1, &truth);
    let net = Network::from_campaign(&camp).unwrap();
    let start = ErrorParams::zero(&model);
    let free = vec![true; start.coefs().len()];
    let settings = bundle();
    g.bench_function(BenchmarkId::new("calibrate", camp.readings.len()), |b| {
        b.iter(|| calibrate(black_box(&net), &start, &free, &settings).unwrap())
    });
    g.bench_function(
        BenchmarkId::new("compare_models", camp.readings.len()),
        |b| b.iter(|| models::compare_campaign(black_box(&camp), 5, 0).unwrap()),
    );
    g.finish();
}

/// The whole diagnosis as `ltcal diagnose` runs it: the bundle adjustment,
/// every candidate, 5-fold cross-validation, 100 Monte Carlo draws and the
/// other tracker model fitted.
fn diagnose_scale(c: &mut Criterion) {
    let mut g = c.benchmark_group("diagnose_scale");
    g.sample_size(10).measurement_time(Duration::from_secs(10));
    for (per_level, stations, faces) in SERIES {
        let camp = campaign(per_level, stations, faces);
        g.bench_function(id(&camp, stations, faces), |b| {
            b.iter(|| diagnose(black_box(&camp), &diagnose::Settings::default()).unwrap())
        });
    }
    g.finish();
}

criterion_group!(
    benches,
    calibrate_scale,
    calibrate_hall,
    mirror_hall,
    diagnose_scale
);
criterion_main!(benches);
