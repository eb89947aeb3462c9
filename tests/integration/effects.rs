//! Each effect of effects.md against a hand computation on a single reading
//! of a simulated campaign.

use ltcal::campaign::{Aim, CampaignReading};
use ltcal::effects::{
    AirRefraction, Axis, Blunder, Coordinate, Effects, EncoderHarmonic, Incidence, IncidenceTable9,
    RangeScale, StationDrift, TargetShift,
};
use ltcal::kinematics::{Face, nominal_reading};
use ltcal::layout::Layout;
use ltcal::noise::Noise;
use ltcal::simulate::{CampaignSpec, SimulatedCampaign, simulate_campaign};
use nalgebra::Vector3;

fn layout() -> Layout {
    Layout {
        targets: vec![
            ("T01".into(), Vector3::new(5000.0, 1200.0, 2500.0)),
            ("T02".into(), Vector3::new(4500.0, -1500.0, 800.0)),
            ("T03".into(), Vector3::new(6000.0, 300.0, 0.0)),
        ],
        stations: vec![
            ("S1".into(), Vector3::new(0.0, 0.0, 1500.0)),
            ("S2".into(), Vector3::new(800.0, 900.0, 1400.0)),
        ],
        gauge: vec![],
        references: false,
    }
}

fn simulate(effects: &Effects, noise: Noise) -> SimulatedCampaign {
    simulate_accepting(effects, noise, 90.0)
}

/// With the stage's SMR acceptance `max_angle_deg`.
fn simulate_accepting(effects: &Effects, noise: Noise, max_angle_deg: f64) -> SimulatedCampaign {
    try_simulate(effects, noise, max_angle_deg).unwrap()
}

fn try_simulate(
    effects: &Effects,
    noise: Noise,
    max_angle_deg: f64,
) -> Result<SimulatedCampaign, String> {
    let l = layout();
    simulate_campaign(&CampaignSpec {
        name: "effects".into(),
        layout: &l,
        errors: None,
        faces: &[Face::Front],
        aim: Aim::StationsCentroid,
        max_angle_deg,
        noise,
        effects,
        gauge_u_mm: 0.0,
        reference_u_mm: 0.0,
        level_urad: 1000.0,
        interval_s: 20.0,
        record_time: true,
        record_temperature: true,
        seed: 11,
    })
}

fn reading<'a>(s: &'a SimulatedCampaign, station: &str, target: &str) -> &'a CampaignReading {
    s.campaign
        .readings
        .iter()
        .find(|r| r.station == station && r.target == target)
        .unwrap()
}

/// The exact reading of `target` from `station` without any effect,
/// with the station's origin moved by `shift` and the target by `moved`.
fn exact(
    s: &SimulatedCampaign,
    station: &str,
    target: &str,
    origin_shift: Vector3<f64>,
    moved: Vector3<f64>,
) -> (f64, f64, f64) {
    let pose = s.poses.iter().find(|p| p.id == station).unwrap();
    let x = s.targets.iter().find(|t| t.0 == target).unwrap().1 + moved;
    let local = pose.rotation.inverse() * (x - pose.position - origin_shift);
    let r = nominal_reading(&local, Face::Front);
    (r.az, r.el, r.d)
}

/// The incidence geometry by hand: n towards the stations' centroid, r
/// towards the tracker, h = ẑ×n normalised, v = n×h.
fn angles(s: &SimulatedCampaign, station: &str, target: &str) -> (f64, f64, f64) {
    let l = layout();
    let centroid = l.stations.iter().map(|s| s.1).sum::<Vector3<f64>>() / 2.0;
    let x = l.targets.iter().find(|t| t.0 == target).unwrap().1;
    let pos = s.poses.iter().find(|p| p.id == station).unwrap().position;
    let n = (centroid - x).normalize();
    let r = (pos - x).normalize();
    let h = Vector3::z().cross(&n).normalize();
    let v = n.cross(&h);
    let rn = r.dot(&n);
    (rn.acos(), r.dot(&h).atan2(rn), r.dot(&v).atan2(rn))
}

fn assert_close(what: &str, got: f64, want: f64, tol: f64) {
    assert!(
        (got - want).abs() <= tol,
        "{what}: got {got}, want {want} (Δ {:e})",
        got - want
    );
}

#[test]
fn no_effect_reads_the_exact_point() {
    let s = simulate(&Effects::default(), Noise::default());
    let r = reading(&s, "S1", "T01");
    let (az, el, d) = exact(&s, "S1", "T01", Vector3::zeros(), Vector3::zeros());
    assert_close("az", r.az_deg.to_radians(), az, 1e-14);
    assert_close("el", r.el_deg.to_radians(), el, 1e-14);
    assert_close("d", r.d_mm, d, 1e-9);
}

#[test]
fn incidence() {
    let fx = Effects {
        incidence: Some(Incidence {
            e_axial_um: 200.0,
            e_h_um: -20.0,
            e_v_um: 12.0,
            max_angle_deg: 90.0,
        }),
        ..Effects::default()
    };
    let s = simulate(&fx, Noise::default());
    let (a, ah, av) = angles(&s, "S2", "T02");
    let dd_um = 200.0 * (1.0 - a.cos()) - 20.0 * ah.sin() + 12.0 * av.sin();
    let (_, _, d) = exact(&s, "S2", "T02", Vector3::zeros(), Vector3::zeros());
    assert_close("d", reading(&s, "S2", "T02").d_mm, d + dd_um * 1e-3, 1e-9);
    assert!(
        dd_um.abs() > 1.0,
        "the geometry should give a visible effect: {dd_um} µm"
    );
}

#[test]
fn incidence_table9() {
    let fx = Effects {
        incidence_table9: Some(IncidenceTable9 {}),
        ..Effects::default()
    };
    let s = simulate(&fx, Noise::default());
    let (_, ah, av) = angles(&s, "S1", "T03");
    // Bilinear interpolation by hand between the four surrounding cells.
    let t = ltcal::effects::TABLE9_UM;
    let (v, h) = (av.to_degrees(), ah.to_degrees());
    let (fi, fj) = ((v + 30.0) / 7.5, (h + 30.0) / 7.5);
    let (i, j) = (fi.floor() as usize, fj.floor() as usize);
    let (u, w) = (fi - i as f64, fj - j as f64);
    let dd_um = (1.0 - u) * ((1.0 - w) * t[i][j] + w * t[i][j + 1])
        + u * ((1.0 - w) * t[i + 1][j] + w * t[i + 1][j + 1]);
    let (_, _, d) = exact(&s, "S1", "T03", Vector3::zeros(), Vector3::zeros());
    assert_close("d", reading(&s, "S1", "T03").d_mm, d + dd_um * 1e-3, 1e-9);
}

#[test]
fn range_scale() {
    let fx = Effects {
        range_scale: Some(RangeScale {
            ppm: [("S2".to_string(), 7.5)].into(),
            sigma_ppm: None,
        }),
        ..Effects::default()
    };
    let s = simulate(&fx, Noise::default());
    let (_, _, d) = exact(&s, "S2", "T01", Vector3::zeros(), Vector3::zeros());
    assert_close("S2 d", reading(&s, "S2", "T01").d_mm, d + 7.5e-6 * d, 1e-9);
    let (_, _, d1) = exact(&s, "S1", "T01", Vector3::zeros(), Vector3::zeros());
    assert_close("S1 d", reading(&s, "S1", "T01").d_mm, d1, 1e-9);
}

#[test]
fn air_refraction() {
    let a = AirRefraction {
        t0_c: 20.0,
        offset_c: 0.3,
        amplitude_c: 1.5,
        period_s: 600.0,
        phase_deg: 40.0,
        drift_c_per_h: -0.8,
    };
    let fx = Effects {
        air_refraction: Some(a.clone()),
        ..Effects::default()
    };
    let s = simulate(&fx, Noise::default());
    let r = reading(&s, "S2", "T03");
    let t = r.time_s.unwrap();
    let temp =
        20.0 + 0.3 + 1.5 * (2.0 * std::f64::consts::PI * t / 600.0 + 40f64.to_radians()).sin()
            - 0.8 * t / 3600.0;
    assert_close("temperature", r.temperature_c.unwrap(), temp, 1e-12);
    let (_, _, d) = exact(&s, "S2", "T03", Vector3::zeros(), Vector3::zeros());
    assert_close("d", r.d_mm, d - 0.93e-6 * (temp - 20.0) * d, 1e-9);
}

#[test]
fn encoder_harmonic() {
    for axis in [Axis::Az, Axis::El] {
        let fx = Effects {
            encoder_harmonic: Some(EncoderHarmonic {
                axis,
                order: 3,
                amplitude_urad: 12.0,
                phase_deg: 30.0,
            }),
            ..Effects::default()
        };
        let s = simulate(&fx, Noise::default());
        let r = reading(&s, "S1", "T02");
        let (az, el, _) = exact(&s, "S1", "T02", Vector3::zeros(), Vector3::zeros());
        let (want_az, want_el) = match axis {
            Axis::Az => (az + 12e-6 * (3.0 * az + 30f64.to_radians()).sin(), el),
            Axis::El => (az, el + 12e-6 * (3.0 * el + 30f64.to_radians()).sin()),
        };
        assert_close("az", r.az_deg.to_radians(), want_az, 1e-14);
        assert_close("el", r.el_deg.to_radians(), want_el, 1e-14);
    }
}

#[test]
fn station_drift() {
    let fx = Effects {
        station_drift: Some(StationDrift {
            station: Some("S2".into()),
            velocity_um_per_min: [30.0, -12.0, 6.0],
        }),
        ..Effects::default()
    };
    let s = simulate(&fx, Noise::default());
    let first = reading(&s, "S2", "T01").time_s.unwrap();
    let r = reading(&s, "S2", "T03");
    let dt_min = (r.time_s.unwrap() - first) / 60.0;
    let shift = Vector3::new(30.0, -12.0, 6.0) * dt_min * 1e-3;
    let (az, el, d) = exact(&s, "S2", "T03", shift, Vector3::zeros());
    assert_close("az", r.az_deg.to_radians(), az, 1e-14);
    assert_close("el", r.el_deg.to_radians(), el, 1e-14);
    assert_close("d", r.d_mm, d, 1e-9);
    assert!(shift.norm() > 1e-3, "the drift should be visible: {shift}");
}

/// `incidence` with only an acceptance: the incidence angles of this layout
/// are 4.3°–7.5°; 5.2° keeps S1–T01, S1–T03 and S2–T03 (4.5°, 4.3°, 4.9°).
fn acceptance_only(max_angle_deg: f64) -> Incidence {
    Incidence {
        e_axial_um: 0.0,
        e_h_um: 0.0,
        e_v_um: 0.0,
        max_angle_deg,
    }
}

fn taken(s: &SimulatedCampaign) -> Vec<(String, String)> {
    let r = &s.campaign.readings;
    r.iter()
        .map(|r| (r.station.clone(), r.target.clone()))
        .collect()
}

/// With the `incidence` effect on, a reading is taken within both the
/// stage's acceptance and the effect's (effects.md).
#[test]
fn the_incidence_effects_acceptance_and_the_stages_both_hold() {
    let narrow = Effects {
        incidence: Some(acceptance_only(5.2)),
        ..Effects::default()
    };
    let want = [("S1", "T01"), ("S1", "T03"), ("S2", "T03")];
    let got = taken(&simulate_accepting(&narrow, Noise::default(), 90.0));
    assert_eq!(got, want.map(|(a, b)| (a.to_string(), b.to_string())));
    let wide = Effects {
        incidence: Some(acceptance_only(90.0)),
        ..Effects::default()
    };
    let got = taken(&simulate_accepting(&wide, Noise::default(), 5.2));
    assert_eq!(got, want.map(|(a, b)| (a.to_string(), b.to_string())));
    assert_eq!(
        taken(&simulate_accepting(&wide, Noise::default(), 90.0)).len(),
        6
    );
    // Without the effect, the stage's acceptance holds.
    let plain = simulate_accepting(&Effects::default(), Noise::default(), 5.2);
    assert_eq!(plain.campaign.readings.len(), 3);
}

/// Regression: station-drift's clock started at the station's first
/// *attempted* reading; effects.md starts it at the first reading, and a
/// reading beyond the SMR's acceptance is not one.
#[test]
fn station_drift_runs_from_the_first_reading_taken() {
    let fx = Effects {
        incidence: Some(acceptance_only(5.2)),
        station_drift: Some(StationDrift {
            station: Some("S2".into()),
            velocity_um_per_min: [3000.0, -1200.0, 600.0],
        }),
        ..Effects::default()
    };
    let s = simulate(&fx, Noise::default());
    // S2 tried T01 and T02 first; T03 is its first reading, so not moved.
    let r = reading(&s, "S2", "T03");
    let (az, el, d) = exact(&s, "S2", "T03", Vector3::zeros(), Vector3::zeros());
    assert_close("az", r.az_deg.to_radians(), az, 1e-14);
    assert_close("el", r.el_deg.to_radians(), el, 1e-14);
    assert_close("d", r.d_mm, d, 1e-9);
}

#[test]
fn target_shift() {
    let fx = Effects {
        target_shift: Some(TargetShift {
            target: "T01".into(),
            from_station: "S2".into(),
            shift_um: [80.0, -40.0, 25.0],
        }),
        ..Effects::default()
    };
    let s = simulate(&fx, Noise::default());
    let moved = Vector3::new(0.080, -0.040, 0.025);
    let (_, _, d2) = exact(&s, "S2", "T01", Vector3::zeros(), moved);
    assert_close(
        "S2 (after the knock)",
        reading(&s, "S2", "T01").d_mm,
        d2,
        1e-9,
    );
    let (_, _, d1) = exact(&s, "S1", "T01", Vector3::zeros(), Vector3::zeros());
    assert_close(
        "S1 (before the knock)",
        reading(&s, "S1", "T01").d_mm,
        d1,
        1e-9,
    );
}

/// `blunder` (effects.md version 2): after the noise, the named reading —
/// and only it — moves by exactly the stated size in its coordinate; two
/// blunders act independently.
#[test]
fn blunder() {
    let noise = Noise {
        sigma_angle_urad: 1.0,
        sigma_range_um: 2.0,
        sigma_range_ppm: 0.0,
    };
    let clean = simulate(&Effects::default(), noise);
    let blunders = vec![
        Blunder {
            station: "S2".into(),
            target: "T03".into(),
            face: 1,
            coordinate: Coordinate::El,
            size_urad: Some(-38.0),
            size_um: None,
        },
        Blunder {
            station: "S1".into(),
            target: "T02".into(),
            face: 1,
            coordinate: Coordinate::D,
            size_urad: None,
            size_um: Some(250.0),
        },
    ];
    let fx = Effects {
        blunder: blunders.clone(),
        ..Effects::default()
    };
    assert_eq!(fx.ids(), ["blunder", "blunder"]);
    let s = simulate(&fx, noise);
    let mut moved = 0;
    for (a, b) in clean.campaign.readings.iter().zip(&s.campaign.readings) {
        let place = (a.station.as_str(), a.target.as_str());
        let (daz, del, dd) = (
            (b.az_deg - a.az_deg).to_radians() * 1e6,
            (b.el_deg - a.el_deg).to_radians() * 1e6,
            (b.d_mm - a.d_mm) * 1e3,
        );
        match place {
            ("S2", "T03") => {
                assert_close("Δel (µrad)", del, -38.0, 1e-6);
                assert_eq!((daz, dd), (0.0, 0.0));
                moved += 1;
            }
            ("S1", "T02") => {
                assert_close("Δd (µm)", dd, 250.0, 1e-6);
                assert_eq!((daz, del), (0.0, 0.0));
                moved += 1;
            }
            _ => assert_eq!((daz, del, dd), (0.0, 0.0, 0.0), "{place:?}"),
        }
    }
    assert_eq!(moved, 2);
    assert_eq!(blunders[0].place(), "S2/T03/1");
    // A blunder on a reading the campaign does not take is refused.
    let nowhere = Effects {
        blunder: vec![Blunder {
            station: "S9".into(),
            ..blunders[0].clone()
        }],
        ..Effects::default()
    };
    let err = try_simulate(&nowhere, noise, 90.0).unwrap_err();
    assert!(err.contains("blunder S9/T03/1"), "{err}");
}

/// `noise`: the reading minus the exact one, over σ, is standard normal.
#[test]
fn noise() {
    let noise = Noise {
        sigma_angle_urad: 2.0,
        sigma_range_um: 3.0,
        sigma_range_ppm: 0.5,
    };
    let mut z = Vec::new();
    for seed in 0..60 {
        let l = layout();
        let s = simulate_campaign(&CampaignSpec {
            name: "n".into(),
            layout: &l,
            errors: None,
            faces: &[Face::Front],
            aim: Aim::StationsCentroid,
            max_angle_deg: 90.0,
            noise,
            effects: &Effects::default(),
            gauge_u_mm: 0.0,
            reference_u_mm: 0.0,
            level_urad: 1000.0,
            interval_s: 20.0,
            record_time: true,
            record_temperature: true,
            seed,
        })
        .unwrap();
        for r in &s.campaign.readings {
            let (az, el, d) = exact(
                &s,
                &r.station,
                &r.target,
                Vector3::zeros(),
                Vector3::zeros(),
            );
            let sd = 3.0f64.hypot(0.5 * d / 1000.0) * 1e-3;
            z.push([
                (r.az_deg.to_radians() - az) / 2e-6,
                (r.el_deg.to_radians() - el) / 2e-6,
                (r.d_mm - d) / sd,
            ]);
        }
    }
    for k in 0..3 {
        let v: Vec<f64> = z.iter().map(|x| x[k]).collect();
        let n = v.len() as f64;
        let mean = v.iter().sum::<f64>() / n;
        let sd = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        assert!(mean.abs() < 4.0 / n.sqrt(), "component {k}: mean {mean}");
        assert!((sd - 1.0).abs() < 0.15, "component {k}: sd {sd}");
    }
}

/// A blunder as a pipeline writes it: an array of tables under the stage's
/// `effects`; one without the size its coordinate needs is refused at load.
#[test]
fn a_blunder_without_its_size_is_refused_at_load() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("b.toml");
    let text = "[stages.corner]\nkind = \"simulate_campaign\"\nlayout = { kind = \"corner\" }\n\n\
                [[stages.corner.effects.blunder]]\nstation = \"S1\"\ntarget = \"T01\"\ncoordinate = \"d\"\nsize_urad = 30.0\n";
    std::fs::write(&file, text).unwrap();
    let err = ltcal::pipeline::load(&file, &[]).unwrap_err().to_string();
    assert!(err.contains("needs `size_um`"), "{err}");
    assert!(err.contains("`size_urad` does not apply"), "{err}");
    std::fs::write(&file, text.replace("size_urad", "size_um")).unwrap();
    ltcal::pipeline::load(&file, &[]).unwrap();
}
