//! `sweep_points`: a 40-point sweep of the corner campaign (simulate,
//! bundle adjustment, evaluate; every point computed, nothing cached) on a
//! pool of 1 thread and of 2 threads. Points are the parallel unit: the
//! ratio of the two medians is the sweep's scaling.
//!
//! `cached_sweep/<n>`: the coordinator's cost per point — loading a
//! sweep of a cheap stage chain (inject, mesh, measure over `n` seeds),
//! checking every point in the cache, gathering its table — with every
//! point cached (the rerun of a finished or resumed sweep), at 1 000,
//! 4 000 and 16 000 points: the median over `n` is the cost of a cached
//! point, their growth how it scales.
//!
//!     cargo bench --bench sweep

use criterion::{BatchSize, Criterion, criterion_group, criterion_main};
use ltcal::pipeline::{self, run};
use std::path::{Path, PathBuf};

const PIPELINE: &str = r#"
[pipeline]
name = "bench-sweep"

[stages.truth]
kind = "inject"

[stages.corner]
kind = "simulate_campaign"
inputs = { errors = "truth" }
layout = { kind = "corner" }
noise = { sigma_angle_urad = 1.0, sigma_range_um = 2.0 }

[stages.calibration]
kind = "calibrate"
inputs = { campaign = "corner" }
objective = "bundle"

[stages.evaluation]
kind = "evaluate_campaign"
inputs = { campaign = "corner", params = "calibration" }

[[sweep.axis]]
path = "stages.corner.noise.sigma_angle_urad"
values = [0.5, 1.0, 2.0, 4.0]

[[sweep.axis]]
path = "stages.corner.seed"
random = { count = 10, seed = 1, low = 0, high = 1000000, integer = true }

[sweep]
gather = ["evaluation.criteria"]
"#;

fn run_once(file: &Path, results: PathBuf) {
    let p = pipeline::load(file, &[]).unwrap();
    let r = ltcal::pipeline::publish::run(
        &p,
        &run::RunOptions {
            results_root: results,
            keep_going: false,
            progress: false,
            not_computed: None,
            experiment: None,
            control: Default::default(),
        },
    )
    .unwrap();
    assert_eq!(r.sweep.unwrap().ran, 40);
}

fn sweep_points(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("bench-sweep.toml");
    std::fs::write(&file, PIPELINE).unwrap();
    let mut g = c.benchmark_group("sweep_points");
    g.sample_size(10);
    for threads in [1, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        g.bench_function(format!("{threads}_threads"), |b| {
            // By reference, so that removing the results folder is not timed.
            b.iter_batched_ref(
                || tempfile::tempdir().unwrap(),
                |results| pool.install(|| run_once(&file, results.path().to_path_buf())),
                BatchSize::PerIteration,
            )
        });
    }
    g.finish();
}

fn cheap_sweep(points: usize) -> String {
    format!(
        r#"
[pipeline]
name = "bench-cached-{points}"

[stages.truth]
kind = "inject"

[stages.target]
kind = "mesh"
shape = "plane"
x_mm = 3000.0
y = {{ from = 0, to = 0, step = 1 }}
z = {{ from = 0, to = 0, step = 1 }}

[stages.reading]
kind = "measure"
inputs = {{ points = "target", errors = "truth" }}
noise = {{ sigma_angle_urad = 1.0, sigma_range_um = 2.0 }}

[[sweep.axis]]
path = "stages.reading.seed"
range = {{ from = 0, to = {}, step = 1 }}

[sweep]
gather = ["reading.readings"]
"#,
        points - 1
    )
}

fn cached_sweep(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    let mut g = c.benchmark_group("cached_sweep");
    g.sample_size(10);
    for points in [1000, 4000, 16000] {
        let file = dir.path().join(format!("cached-{points}.toml"));
        std::fs::write(&file, cheap_sweep(points)).unwrap();
        let results = dir.path().join("results");
        let rerun = |expect_ran: usize| {
            let p = pipeline::load(&file, &[]).unwrap();
            let r = ltcal::pipeline::publish::run(
                &p,
                &run::RunOptions {
                    results_root: results.clone(),
                    keep_going: false,
                    progress: false,
                    not_computed: None,
                    experiment: None,
                    control: Default::default(),
                },
            )
            .unwrap();
            let sweep = r.sweep.unwrap();
            assert_eq!((sweep.ran, sweep.cached), (expect_ran, points - expect_ran));
        };
        rerun(points);
        g.bench_function(format!("{points}_points"), |b| b.iter(|| rerun(0)));
    }
    g.finish();
}

criterion_group!(benches, sweep_points, cached_sweep);
criterion_main!(benches);
