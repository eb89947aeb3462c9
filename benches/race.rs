//! The calibrate stage on the hall campaigns of the race against the Ceres
//! peer (issue 34, `benches/ceres_race.sh`), and where its time goes.
//!
//! `race_stage/<readings>`: the whole `calibrate` stage as `ltcal run`
//! runs it on the race's pipeline (`benches/data/race-calibrate.toml`: the
//! peer's 7 parameters free) — network, identifiability, adjustment,
//! covariances and the output tables — on campaigns of 2 400, 4 800 and
//! 24 000 readings (the race's) and 50 040 and 100 080 (the growth; the
//! README's exponent is the log–log slope of these medians).
//!
//! `race_phases/<phase>/<readings>`: its parts, each alone: `read` (the
//! campaign folder's CSV files read and checked), `network`
//! (`Network::from_campaign`), `identifiability` (`bundle::analyse`),
//! `adjustment` (`bundle::calibrate`: the fit with its covariances), and on
//! the final linearisation `schur` (`Normal::assemble`: `JᵀJ`, `Jᵀr` in
//! arrow form), `factor` (the reflectors eliminated, the Schur complement
//! factorised), `solve` (one back-substitution), `covariances` (the dense
//! part's and every reflector's), `tables` (the stage's output tables).
//!
//!     cargo bench --bench race -- --warm-up-time 1 --measurement-time 3

mod common;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use ltcal::calibrate::sparse::Normal;
use ltcal::calibrate::{Network, Settings, bundle};
use ltcal::campaign::{self, Campaign};
use ltcal::error_model::{ErrorModel, ErrorParams, ParamId};
use ltcal::layout::Kind;
use ltcal::stages::calibrate::{CalibrateStage, tables};
use std::hint::black_box;
use std::time::Duration;

/// `(reflectors per level, stations, faces)` of the hall: 2 400, 4 800,
/// 24 000, 50 040 and 100 080 readings (every reflector read from every
/// station).
const SIZES: [(usize, usize, usize); 5] = [
    (100, 8, 1),
    (200, 8, 1),
    (200, 20, 2),
    (417, 20, 2),
    (834, 20, 2),
];

/// The 11 parameters the Ceres peer holds at zero.
const HELD: [&str; 11] = [
    "dx1", "dy1", "dz1", "ex1", "ey1", "ez1", "dy2", "ey2", "dy3", "ey3", "ez3",
];

/// The hall campaign of `benches/data/race-halls.toml` (Table 2 errors,
/// the pipeline's noise and seed).
fn hall(per_level: usize, stations: usize, faces: usize) -> Campaign {
    common::simulated(
        "hall",
        Kind::Hall,
        per_level,
        stations,
        faces,
        &ErrorParams::table2(),
    )
}

/// The stage of `benches/data/race-calibrate.toml`.
fn stage() -> CalibrateStage {
    let fixed = HELD.map(|p| format!("\"{p}\"")).join(", ");
    toml::from_str(&format!("objective = \"bundle\"\nfixed = [{fixed}]")).unwrap()
}

fn race_stage(c: &mut Criterion) {
    let mut g = c.benchmark_group("race_stage");
    g.sample_size(10).measurement_time(Duration::from_secs(3));
    let st = stage();
    for (per_level, stations, faces) in SIZES {
        let camp = hall(per_level, stations, faces);
        g.bench_function(BenchmarkId::from_parameter(camp.readings.len()), |b| {
            b.iter(|| {
                let (net, cal, _) = st.calibrate(black_box(&camp), None).unwrap();
                tables(&net, &cal).unwrap()
            })
        });
    }
    g.finish();
}

fn race_phases(c: &mut Criterion) {
    let mut g = c.benchmark_group("race_phases");
    g.sample_size(10).measurement_time(Duration::from_secs(2));
    let start = ErrorParams::zero(&ErrorModel::constant());
    let held: Vec<usize> = HELD.map(|p| ParamId::parse(p).unwrap().index()).into();
    let free: Vec<bool> = (0..18).map(|i| !held.contains(&i)).collect();
    let settings = Settings::bundle();
    let dir = tempfile::tempdir().unwrap();
    for (per_level, stations, faces) in &SIZES[..3] {
        let camp = hall(*per_level, *stations, *faces);
        let n = camp.readings.len();
        let folder = dir.path().join(n.to_string());
        campaign::write(&camp, &folder).unwrap();
        let net = Network::from_campaign(&camp).unwrap();
        let cal = bundle::calibrate(&net, &start, &free, &settings).unwrap();
        let lin = cal.linearisation.as_ref().unwrap();
        let normal = Normal::assemble(&lin.jacobian, Some(&lin.residuals), |_| true);
        let factor = normal.factor(0.0).unwrap();
        let id = |phase: &str| BenchmarkId::new(phase, n);
        g.bench_function(id("read"), |b| {
            b.iter(|| campaign::read(black_box(&folder)).unwrap())
        });
        g.bench_function(id("network"), |b| {
            b.iter(|| Network::from_campaign(black_box(&camp)).unwrap())
        });
        g.bench_function(id("identifiability"), |b| {
            b.iter(|| bundle::analyse(black_box(&net), &start, &free, settings.rank_tol).unwrap())
        });
        g.bench_function(id("adjustment"), |b| {
            b.iter(|| bundle::calibrate(black_box(&net), &start, &free, &settings).unwrap())
        });
        g.bench_function(id("schur"), |b| {
            b.iter(|| Normal::assemble(black_box(&lin.jacobian), Some(&lin.residuals), |_| true))
        });
        g.bench_function(id("factor"), |b| {
            b.iter(|| black_box(&normal).factor(1e-3).unwrap())
        });
        g.bench_function(id("solve"), |b| {
            b.iter(|| black_box(&factor).solve(normal.gradient()))
        });
        g.bench_function(id("covariances"), |b| {
            b.iter(|| {
                let cov = black_box(&factor).dense_covariance();
                let points = factor.point_covariances(&cov, 1.0);
                points.iter().map(|c| c.trace()).sum::<f64>()
            })
        });
        g.bench_function(id("tables"), |b| {
            b.iter(|| tables(black_box(&net), &cal).unwrap())
        });
    }
    g.finish();
}

criterion_group!(benches, race_stage, race_phases);
criterion_main!(benches);
