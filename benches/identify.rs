//! `identify_sphere`: Eq. (11) on the paper's spherical mesh (480 points)
//! with the free parameters of Table 3 (δz1, δy2, εz3 held at zero).
//!
//!     cargo bench --bench identify

use criterion::{Criterion, criterion_group, criterion_main};
use ltcal::error_model::{ErrorModel, ErrorParams, ParamId};
use ltcal::identify::{KnownPoint, Settings, identify};
use ltcal::kinematics::Face;
use ltcal::mesh;
use std::hint::black_box;

fn identify_sphere(c: &mut Criterion) {
    let truth = ErrorParams::table2();
    let obs: Vec<KnownPoint> =
        mesh::sphere(&mesh::SPHERE_H_DEG, &mesh::SPHERE_V_DEG, &mesh::SPHERE_R_MM)
            .iter()
            .map(|m| KnownPoint {
                reading: truth.reading_of(&m.p, Face::Front).unwrap(),
                reference: m.p,
            })
            .collect();
    let start = ErrorParams::zero(&ErrorModel::constant());
    let fixed = ["dz1", "dy2", "ez3"].map(|p| ParamId::parse(p).unwrap());
    let free: Vec<bool> = start
        .coefs()
        .iter()
        .map(|c| !fixed.contains(&c.param))
        .collect();
    let settings = Settings::default();
    c.bench_function("identify_sphere", |b| {
        b.iter(|| identify(black_box(&obs), &start, &free, &settings).unwrap())
    });
}

criterion_group!(benches, identify_sphere);
criterion_main!(benches);
