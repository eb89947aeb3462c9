//! `ideal-sphere` — a made-up tracker that exists to prove the plug-in
//! recipe of ARCHITECTURE.md: this file and one line of the registry
//! (compiled for tests only) are all it takes to have a tracker model
//! simulated, calibrated and compared. Its construction is the ideal
//! spherical instrument of `kinematics` with two errors of its own: a
//! distance zero (`distance_zero`, µm, added to every distance) and an
//! elevation index (`elevation_index`, µrad, added to every elevation
//! reading, so that the back face sees it reversed). An azimuth index is
//! left out on purpose: it turns every station about its vertical, which
//! the station's pose absorbs, so no campaign determines it.

use super::{Evaluate, Model, Param};
use crate::error_model::{ErrorParams, Links};
use crate::kinematics::{Joints, Reading, nominal_point};
use nalgebra::Vector3;

/// The plug-in.
pub struct IdealSphere;

const PARAMS: [Param; 2] = [
    Param {
        id: "distance_zero",
        symbol: "distance_zero",
        angular: false,
        meaning: "distance zero offset",
        joint: None,
    },
    Param {
        id: "elevation_index",
        symbol: "elevation_index",
        angular: true,
        meaning: "elevation encoder zero offset",
        joint: None,
    },
];

impl Model for IdealSphere {
    fn id(&self) -> &'static str {
        "ideal-sphere"
    }

    fn describe(&self) -> &'static str {
        "an ideal spherical instrument with a distance zero and an elevation index"
    }

    fn params(&self) -> &'static [Param] {
        &PARAMS
    }

    fn evaluate<'a>(&self, params: &'a ErrorParams) -> Box<dyn Evaluate + 'a> {
        let mut v = [0.0; PARAMS.len()];
        for (c, x) in params.coefs().iter().zip(params.values()) {
            v[c.param.local()] += x;
        }
        Box::new(Sphere {
            params,
            d0_mm: v[0] * 1e-3,
            el0_rad: v[1] * 1e-6,
        })
    }
}

/// One parameter set: its errors in mm and rad.
struct Sphere<'a> {
    params: &'a ErrorParams,
    d0_mm: f64,
    el0_rad: f64,
}

impl Sphere<'_> {
    /// The reading an ideal instrument would have taken.
    fn corrected(&self, q: Joints) -> Reading {
        let r = q.reading();
        Reading {
            az: r.az,
            el: r.el + self.el0_rad,
            d: r.d + self.d0_mm,
        }
    }
}

impl Evaluate for Sphere<'_> {
    fn point(&self, q: Joints, _: &Links) -> Vector3<f64> {
        nominal_point(self.corrected(q))
    }

    fn point_with_jacobian(
        &self,
        q: Joints,
        _: &Links,
        jac: &mut Vec<Vector3<f64>>,
    ) -> Vector3<f64> {
        let r = self.corrected(q);
        let (se, ce) = r.el.sin_cos();
        let (sa, ca) = r.az.sin_cos();
        // ∂P/∂d along the beam, ∂P/∂el across it, per display unit.
        let along = Vector3::new(ce * ca, ce * sa, se) * 1e-3;
        let up = Vector3::new(-se * ca, -se * sa, ce) * (r.d * 1e-6);
        jac.extend(
            self.params
                .coefs()
                .iter()
                .map(|c| if c.param.local() == 0 { along } else { up }),
        );
        nominal_point(r)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calibrate::{self, Network, Norm, Objective, Settings};
    use crate::campaign::Aim;
    use crate::effects::Effects;
    use crate::error_model::ErrorModel;
    use crate::kinematics::Face;
    use crate::layout::{self, Kind, Spec};
    use crate::noise::Noise;
    use crate::simulate::{CampaignSpec, SimulatedCampaign, simulate_campaign};
    use crate::trackers::TrackerModel;

    fn handle() -> TrackerModel {
        TrackerModel::parse(IdealSphere.id()).unwrap()
    }

    /// 40 µm of distance zero, 15 µrad of elevation index.
    fn truth() -> ErrorParams {
        let mut p = ErrorParams::zero(&ErrorModel::of(handle()));
        p.values_mut().copy_from_slice(&[40.0, 15.0]);
        p
    }

    fn simulate(errors: &ErrorParams, noise: Noise) -> SimulatedCampaign {
        let layout = layout::build(&Spec::new(Kind::Corner));
        simulate_campaign(&CampaignSpec {
            name: "sphere".into(),
            layout: &layout,
            errors: Some(errors),
            faces: &[Face::Front, Face::Back],
            aim: Aim::StationsCentroid,
            max_angle_deg: 30.0,
            noise,
            effects: &Effects::default(),
            gauge_u_mm: 0.0005,
            reference_u_mm: 0.002,
            level_urad: 1000.0,
            interval_s: 20.0,
            record_time: false,
            record_temperature: false,
            seed: 5,
        })
        .unwrap()
    }

    #[test]
    fn a_campaign_is_simulated_through_its_inverse() {
        let errors = truth();
        let sim = simulate(&errors, Noise::default());
        assert_eq!(sim.campaign.meta.tracker.model, "ideal-sphere");
        assert!(sim.campaign.readings.len() > 50);
        for r in &sim.campaign.readings {
            let pose = sim.poses.iter().find(|p| p.id == r.station).unwrap();
            let (_, x) = sim.targets.iter().find(|(t, _)| *t == r.target).unwrap();
            let reading = Reading {
                az: r.az_deg.to_radians(),
                el: r.el_deg.to_radians(),
                d: r.d_mm,
            };
            let miss = (errors.correct(reading) - pose.to_local(x)).norm();
            assert!(miss < 1e-9, "{r:?}: {miss} mm");
        }
    }

    #[test]
    fn the_bundle_adjustment_recovers_its_parameters() {
        let noise = Noise {
            sigma_angle_urad: 1.0,
            sigma_range_um: 2.0,
            sigma_range_ppm: 0.3,
        };
        let sim = simulate(&truth(), noise);
        let net = Network::from_campaign(&sim.campaign).unwrap();
        let start = ErrorParams::zero(&ErrorModel::of(handle()));
        let cal = calibrate::calibrate(
            &net,
            &start,
            &[true, true],
            &Settings {
                objective: Objective::Bundle,
                norm: Norm::L2,
                rank_tol: crate::identifiability::DEFAULT_REL_TOL,
                max_iters: 100,
                std: calibrate::BundleStd::Auto,
            },
        )
        .unwrap();
        let est = &cal.estimate;
        for (k, want) in truth().values().iter().enumerate() {
            let (got, u) = (est.params.values()[k], est.std[k].unwrap());
            // Determined well below the truth's size, and found within 3σ.
            assert!(
                u < 0.1 * want && (got - want).abs() <= 3.0 * u,
                "{}: {got} ± {u}, truth {want}",
                est.params.coefs()[k].name()
            );
        }
    }

    #[test]
    fn the_jacobian_matches_central_differences() {
        let p = truth();
        let eval = p.evaluator();
        let mut jac = Vec::new();
        for (az, el, d) in [(-2.5, -0.6, 1500.0), (0.3, 0.2, 8000.0), (1.9, 2.4, 25000.0)] {
            let q = Reading { az, el, d }.joints();
            let links = Links::new(q);
            eval.point_with_jacobian(q, &links, &mut jac);
            for (k, col) in jac.iter().enumerate() {
                let h = 1.0;
                let at = |s: f64| {
                    let mut stepped = p.clone();
                    stepped.values_mut()[k] += s;
                    stepped.point(q)
                };
                let fd = (at(h) - at(-h)) / (2.0 * h);
                assert!(
                    (col - fd).norm() <= 1e-6 * fd.norm(),
                    "{}: {col} vs {fd}",
                    p.coefs()[k].name()
                );
            }
        }
    }

    /// ARCHITECTURE.md's recipe: a tracker model is its file and one line
    /// of the registry. Every other source file is blind to it.
    #[test]
    fn the_ideal_sphere_takes_its_file_and_one_registry_line() {
        let mentions = crate::source_scan::mentions_outside("trackers/ideal_sphere.rs", |line| {
            let l = line.to_lowercase().replace(['-', '_'], "");
            ["idealsphere", "distancezero", "elevationindex"]
                .iter()
                .any(|w| l.contains(w))
        });
        assert_eq!(mentions.len(), 1, "{mentions:#?}");
        assert!(mentions[0].contains("trackers/mod.rs"), "{mentions:?}");
        assert!(mentions[0].contains("#[cfg(test)] ideal_sphere::IdealSphere,"));
    }
}
