//! The simulated campaign the benches time (`scale`, `race`): a layout of
//! `kind` with `per_level` reflectors per level read from `stations`
//! stations on `faces` faces, with `errors`, the typical indoor noise
//! (1 µrad, 2 µm + 0.3 ppm) and seed 11 — the settings of
//! `benches/data/race-halls.toml`, so that a bench times the campaign the
//! race's pipeline makes.

use ltcal::campaign::{Aim, Campaign};
use ltcal::effects::Effects;
use ltcal::error_model::ErrorParams;
use ltcal::kinematics::Face;
use ltcal::layout::{self, Kind, Spec};
use ltcal::noise::Noise;
use ltcal::simulate::{CampaignSpec, simulate_campaign};

pub fn simulated(
    name: &str,
    kind: Kind,
    per_level: usize,
    stations: usize,
    faces: usize,
    errors: &ErrorParams,
) -> Campaign {
    let mut spec = Spec::new(kind);
    spec.per_level = per_level;
    spec.stations = stations;
    let layout = layout::build(&spec);
    simulate_campaign(&CampaignSpec {
        name: name.into(),
        layout: &layout,
        errors: Some(errors),
        faces: &[Face::Front, Face::Back][..faces],
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
        seed: 11,
    })
    .unwrap_or_else(|e| panic!("the {name} layout simulates: {e}"))
    .campaign
}
