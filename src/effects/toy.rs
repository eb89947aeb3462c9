//! `toy-range` — a toy effect that exists to prove the plug-in recipe of
//! ARCHITECTURE.md: this file and one line of the catalogue (compiled for
//! tests only) are all it takes to have an effect simulated, diagnosed and
//! drawn by the blind check. Its physics is made up: a range error that
//! repeats twice per turn of the azimuth, `Δd = amplitude_um·cos(2·az)`.

use super::{DrawContext, Drawn, Effect, Forward, IncidenceAngles, Place, finite};
use crate::diagnose::candidates::{Context, Found, first, put_d};
use crate::diagnose::linear::Signature;
use crate::kinematics::Reading;
use crate::random;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToyRange {
    pub amplitude_um: f64,
}

impl Forward for ToyRange {
    fn delta_d_mm(&self, _: &Place, r: &Reading, _: &IncidenceAngles, _: f64) -> Option<f64> {
        Some(self.amplitude_um * 1e-3 * (2.0 * r.az).cos())
    }
}

impl Effect for ToyRange {
    const ID: &'static str = "toy-range";
    const SUMMARY: &'static str = "a made-up range error: Δd = amplitude_um·cos(2·az)";

    fn check(&self) -> Vec<(String, String)> {
        let mut out = Vec::new();
        finite(&mut out, "amplitude_um", self.amplitude_um);
        out
    }

    fn candidates(cx: &Context, out: &mut Found) {
        let mut c = Signature::new(1);
        for (i, r) in cx.readings.iter().enumerate() {
            put_d(&mut c, i, r, 0, 1e-3 * (2.0 * r.az).cos());
        }
        out.push(Self::ID, "all", c, Arc::new(first), "µm");
    }

    fn draw(rng: &mut ChaCha8Rng, cx: &DrawContext) -> Drawn<Self> {
        let a = cx.size * random::log_uniform(rng, 20.0, 60.0, true);
        Drawn {
            effect: ToyRange { amplitude_um: a },
            place: "all".into(),
            magnitude: a,
            has_place: false,
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::campaign::Aim;
    use crate::diagnose::blind::{self, Campaigns, CaseKind, Plan};
    use crate::diagnose::{self, Settings};
    use crate::effects::Effects;
    use crate::kinematics::Face;
    use crate::layout::{self, Kind, Spec};
    use crate::noise::Noise;
    use crate::simulate::{CampaignSpec, SimulatedCampaign, simulate_campaign};
    use crate::trackers::TrackerModel;

    const NOISE: Noise = Noise {
        sigma_angle_urad: 1.0,
        sigma_range_um: 2.0,
        sigma_range_ppm: 0.3,
    };

    fn simulate(effects: &Effects, noise: Noise) -> SimulatedCampaign {
        let layout = layout::build(&Spec::new(Kind::Corner));
        simulate_campaign(&CampaignSpec {
            name: "toy".into(),
            layout: &layout,
            errors: None,
            faces: &[Face::Front],
            aim: Aim::StationsCentroid,
            max_angle_deg: 30.0,
            noise,
            effects,
            gauge_u_mm: 0.0005,
            reference_u_mm: 0.002,
            level_urad: 1000.0,
            interval_s: 20.0,
            record_time: true,
            record_temperature: true,
            seed: 3,
        })
        .unwrap()
    }

    fn toy(amplitude_um: f64) -> Effects {
        toml::from_str(&format!("[toy-range]\namplitude_um = {amplitude_um}\n")).unwrap()
    }

    #[test]
    fn the_toy_effect_is_simulated_from_its_toml_entry() {
        let with = simulate(&toy(40.0), Noise::default());
        let without = simulate(&Effects::default(), Noise::default());
        assert_eq!(with.campaign.readings.len(), without.campaign.readings.len());
        for (a, b) in with.campaign.readings.iter().zip(&without.campaign.readings) {
            let expect = 40e-3 * (2.0 * b.az_deg.to_radians()).cos();
            assert!((a.d_mm - b.d_mm - expect).abs() < 1e-9, "{a:?} {b:?}");
            assert_eq!((a.az_deg, a.el_deg), (b.az_deg, b.el_deg));
        }
    }

    #[test]
    fn the_toy_effect_is_diagnosed_with_its_magnitude() {
        let sim = simulate(&toy(40.0), NOISE);
        let d = diagnose::diagnose(&sim.campaign, &Settings::default()).unwrap();
        let best = d.best();
        assert_eq!(best.effect, "toy-range", "{:?}", d.rows.first());
        assert!(
            (best.magnitude - 40.0).abs() <= 3.0 * best.magnitude_u,
            "{} ± {}",
            best.magnitude,
            best.magnitude_u
        );
    }

    #[test]
    fn the_toy_effect_is_drawn_and_named_by_the_blind_check() {
        let plan = Plan {
            cases: 6,
            first: 0,
            seed: 11,
            campaigns: Campaigns {
                layouts: vec![Kind::Corner],
                stations: (4, 5),
                noise_angle_urad: (0.5, 1.0),
                noise_range_um: (1.0, 2.0),
                tracker: TrackerModel::default(),
                tracker_sigma: 5.0,
            },
            none_fraction: 0.0,
            effects: vec!["toy-range".into()],
            kinds: vec![CaseKind::Single],
            detect_chi2: 25.0,
            mc_draws: 0,
        };
        let cases = blind::run(&plan).unwrap();
        assert_eq!(cases.len(), 6);
        for c in &cases {
            assert_eq!(c.truth.effect, "toy-range");
            assert!(c.truth.effects.toy_range.is_some());
            assert!(c.detectable && c.effect_correct, "{c:?}");
        }
    }

    /// ARCHITECTURE.md's recipe: an effect is its file and one line of the
    /// catalogue. Every other source file is blind to it.
    #[test]
    fn the_toy_effect_takes_its_file_and_one_registry_line() {
        let mentions = crate::source_scan::mentions_outside("effects/toy.rs", |line| {
            line.to_lowercase().contains("toy")
        });
        assert_eq!(mentions.len(), 1, "{mentions:#?}");
        assert!(mentions[0].contains("effects/mod.rs"), "{mentions:?}");
        assert!(mentions[0].contains("\"toy-range\" => toy_range: toy::ToyRange"));
    }
}
