//! `ltcal diagnose` of big networks (issue 34): the whole diagnosis — base
//! adjustment, noise floor, every candidate scored and cross-validated,
//! the tracker models compared, the localisation — and its outputs (tables,
//! figures, report pages; everything but the folder's write) on the race's
//! hall campaigns of 4 800 and 24 000 readings (`benches/data/race-halls.toml`,
//! the same simulator settings and seed: `common::simulated`).
//!
//!     cargo bench --bench diagnose -- --warm-up-time 1 --measurement-time 5

mod common;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use ltcal::campaign::Campaign;
use ltcal::error_model::ErrorParams;
use ltcal::layout::Kind;
use ltcal::stages::diagnose::{DiagnoseStage, outputs};
use std::hint::black_box;
use std::time::Duration;

/// `(reflectors per level, stations, faces)`: the race's 4 800 and 24 000
/// reading halls.
const SIZES: [(usize, usize, usize); 2] = [(200, 8, 1), (200, 20, 2)];

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

fn diagnose(c: &mut Criterion) {
    let mut g = c.benchmark_group("diagnose");
    g.sample_size(10).measurement_time(Duration::from_secs(5));
    // `ltcal diagnose`'s defaults: every effect, 5 folds, 100 draws.
    let stage: DiagnoseStage = toml::from_str("").unwrap();
    for (per_level, stations, faces) in SIZES {
        let camp = hall(per_level, stations, faces);
        g.bench_function(BenchmarkId::from_parameter(camp.readings.len()), |b| {
            b.iter(|| outputs(&stage.diagnose(black_box(&camp)).unwrap()).unwrap())
        });
    }
    g.finish();
}

criterion_group!(benches, diagnose);
criterion_main!(benches);
