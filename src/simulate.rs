//! Simulated measurement: what a tracker with error parameters reads when it
//! points at true reflector positions, plus reading noise — for a single
//! mesh (Section 5.1) and for whole campaigns with the effects of
//! `effects.md`.
//!
//! A tracker with errors pointed at a true point reports the *nominal*
//! coordinates of the joint values that actually reach the point
//! ([`ErrorParams::reading_of`] solves Eq. (8) exactly for them). Noise is
//! drawn from the reading-noise model of [`crate::noise`].

use crate::campaign::{Aim, Campaign, CampaignReading, GaugeLength, Meta, Target, Tracker};
use crate::effects::{Effects, Place, Setup, incidence_angles};
use crate::error_model::{ErrorParams, InverseError};
use crate::hypothesis::ActsOn;
use crate::hypothesis::covariates::Covariates;
use crate::kinematics::{Face, Reading};
use crate::layout::Layout;
use crate::noise::Noise;
use crate::random;
use crate::trackers::TrackerModel;
use nalgebra::{Rotation3, Vector3};
use std::f64::consts::PI;

/// The reading of `target` by a tracker with `errors` (none: a perfect one).
pub fn read(
    errors: Option<&ErrorParams>,
    target: &Vector3<f64>,
    face: Face,
) -> Result<Reading, InverseError> {
    match errors {
        Some(e) => e.reading_of(target, face),
        None => Ok(crate::kinematics::nominal_reading(target, face)),
    }
}

/// A tracker station's true pose: `x_campaign = R·x_station + position`.
#[derive(Clone, Debug, PartialEq)]
pub struct StationPose {
    pub id: String,
    pub position: Vector3<f64>,
    pub rotation: Rotation3<f64>,
}

impl StationPose {
    pub fn to_local(&self, x: &Vector3<f64>) -> Vector3<f64> {
        self.rotation.inverse() * (x - self.position)
    }
}

/// What a simulated campaign is made from.
#[derive(Clone, Debug)]
pub struct CampaignSpec<'a> {
    pub name: String,
    pub layout: &'a Layout,
    pub errors: Option<&'a ErrorParams>,
    pub faces: &'a [Face],
    pub aim: Aim,
    /// SMR acceptance: readings beyond it are not taken (nor, with the
    /// `incidence` effect, readings beyond that effect's `max_angle_deg`).
    pub max_angle_deg: f64,
    pub noise: Noise,
    pub effects: &'a Effects,
    /// Standard uncertainty of the gauge's calibrated lengths (mm).
    pub gauge_u_mm: f64,
    /// Standard uncertainty of reference coordinates, when the layout has them.
    pub reference_u_mm: f64,
    /// Station levelling: tilt about x and y, 1 σ (µrad).
    pub level_urad: f64,
    /// Seconds between readings.
    pub interval_s: f64,
    pub record_time: bool,
    pub record_temperature: bool,
    pub seed: u64,
}

/// A simulated campaign and the truth behind it.
#[derive(Clone, Debug)]
pub struct SimulatedCampaign {
    pub campaign: Campaign,
    pub poses: Vec<StationPose>,
    /// True reflector centres before any `target-shift`.
    pub targets: Vec<(String, Vector3<f64>)>,
    /// The effects as injected: prepared ([`crate::effects::Forward::prepare`]),
    /// so drawn values (`range-scale`'s `sigma_ppm`) are filled in.
    pub effects: Effects,
    /// Readings beyond the acceptance angle, not taken.
    pub not_taken: usize,
}

/// Seconds spent moving the tracker between stations.
const STATION_CHANGE_S: f64 = 300.0;

/// Simulates a campaign in the order of `effects.md`: true centre (after
/// `target-shift`), true station pose (after `station-drift`), the readings
/// of the tracker with its error parameters, reading-level effects, noise.
///
/// Long on purpose (issue 31): one pass in `effects.md`'s order of steps,
/// each step a hook call on every effect; cut into functions, the order
/// the document fixes would be spread over their call sites.
pub fn simulate_campaign(spec: &CampaignSpec) -> Result<SimulatedCampaign, String> {
    let layout = spec.layout;
    let fx = spec.effects;
    let mut pose_rng = random::stream(spec.seed, "stations");
    let poses: Vec<StationPose> = layout
        .stations
        .iter()
        .map(|(id, p)| {
            let yaw = (random::uniform(&mut pose_rng) * 2.0 - 1.0) * PI;
            let tx = random::normal(&mut pose_rng) * spec.level_urad * 1e-6;
            let ty = random::normal(&mut pose_rng) * spec.level_urad * 1e-6;
            StationPose {
                id: id.clone(),
                position: *p,
                rotation: Rotation3::from_euler_angles(tx, ty, yaw),
            }
        })
        .collect();
    let station_ids: Vec<String> = poses.iter().map(|p| p.id.clone()).collect();
    let target_ids: Vec<String> = layout.targets.iter().map(|t| t.0.clone()).collect();
    let fx = fx.prepared(&Setup {
        stations: &station_ids,
        targets: &target_ids,
        seed: spec.seed,
    })?;
    let present = fx.present();
    let centroid: Vector3<f64> =
        poses.iter().map(|p| p.position).sum::<Vector3<f64>>() / poses.len().max(1) as f64;
    // The SMR's acceptance: the campaign's, and an effect's own (effects.md:
    // "a reading with α over max_angle_deg is not taken") — every limit holds.
    let max_angle = present
        .iter()
        .filter_map(|(_, e)| e.max_angle_deg())
        .fold(spec.max_angle_deg, f64::min)
        .to_radians();
    // The air temperature an effect sets, if one does.
    let air_c = |time: f64| present.iter().find_map(|(_, e)| e.temperature_c(time));
    let mut noise_rng = random::stream(spec.seed, "noise");
    let mut time_rng = random::stream(spec.seed, "time");
    let mut temp_rng = random::stream(spec.seed, "temperature");
    let mut readings = Vec::new();
    let mut not_taken = 0;
    let mut time = 0.0;
    for (si, pose) in poses.iter().enumerate() {
        if si > 0 {
            time += STATION_CHANGE_S;
        }
        // station-drift runs "from the time of that station's first
        // reading": the first one taken, not an attempt beyond acceptance.
        let mut first_time: Option<f64> = None;
        let mut first = true;
        for (tid, x0) in &layout.targets {
            let at = Place {
                station: &pose.id,
                rank: si,
                target: tid,
                stations: &station_ids,
            };
            let mut x = *x0;
            for s in present
                .iter()
                .filter_map(|(_, e)| e.reflector_shift_mm(&at))
            {
                x += s;
            }
            let aim_dir = (centroid - x).normalize();
            for &face in spec.faces {
                if !first {
                    time += spec.interval_s * (0.9 + 0.2 * random::uniform(&mut time_rng));
                }
                first = false;
                let mut origin = pose.position;
                let since_station_s = time - first_time.unwrap_or(time);
                for s in present
                    .iter()
                    .filter_map(|(_, e)| e.station_shift_mm(&at, since_station_s))
                {
                    origin += s;
                }
                let place = || format!("{}/{tid}/{}", pose.id, face.number());
                // Hypotheses on positions: their covariates are those of
                // the reading the unmoved geometry gives.
                let (mut x, mut origin) = (x, origin);
                for h in fx
                    .hypotheses
                    .0
                    .iter()
                    .filter(|h| matches!(h.acts_on, ActsOn::Reflector | ActsOn::Station))
                {
                    let local = StationPose {
                        position: origin,
                        ..pose.clone()
                    }
                    .to_local(&x);
                    let r0 = crate::kinematics::nominal_reading(&local, face);
                    let cov = Covariates {
                        az: r0.az,
                        el: r0.el,
                        d: r0.d,
                        face: face.number() as f64,
                        time_s: Some(time),
                        since_station_s: Some(since_station_s),
                        temperature_c: air_c(time),
                        incidence: Some(incidence_angles(&aim_dir, &(origin - x).normalize())),
                        point: x,
                        station_pos: origin,
                        station: &pose.id,
                        reflector: tid,
                    };
                    let theta = h.theta(&cov, &|k, inst| h.params[k].value.at(inst));
                    let s = h.apply(&cov, &theta, &place()).map_err(|e| e.to_string())?;
                    match h.acts_on {
                        ActsOn::Station => origin += s,
                        _ => x += s,
                    }
                }
                let moved = StationPose {
                    position: origin,
                    ..pose.clone()
                };
                let angles = incidence_angles(&aim_dir, &(origin - x).normalize());
                if angles.alpha > max_angle || !present.iter().all(|(_, e)| e.takes(&angles)) {
                    not_taken += 1;
                    continue;
                }
                first_time.get_or_insert(time);
                let mut r = read(spec.errors, &moved.to_local(&x), face)
                    .map_err(|e| format!("station {}, reflector {tid}: {e}", pose.id))?;
                let temperature =
                    air_c(time).unwrap_or_else(|| 20.0 + 0.01 * random::normal(&mut temp_rng));
                let mut dd_mm = 0.0;
                for dd in present
                    .iter()
                    .filter_map(|(_, e)| e.delta_d_mm(&at, &r, &angles, temperature))
                {
                    dd_mm += dd;
                }
                let cov = Covariates {
                    az: r.az,
                    el: r.el,
                    d: r.d,
                    face: face.number() as f64,
                    time_s: Some(time),
                    since_station_s: Some(time - first_time.unwrap_or(time)),
                    temperature_c: Some(temperature),
                    incidence: Some(angles),
                    point: x,
                    station_pos: origin,
                    station: &pose.id,
                    reflector: tid,
                };
                // Only when there are any: adding 0 would turn a −0 into +0.
                for h in fx
                    .hypotheses
                    .0
                    .iter()
                    .filter(|h| matches!(h.acts_on, ActsOn::Reading(_)))
                {
                    let theta = h.theta(&cov, &|k, inst| h.params[k].value.at(inst));
                    let v = h.apply(&cov, &theta, &place()).map_err(|e| e.to_string())?;
                    r.az += v.x;
                    r.el += v.y;
                    dd_mm += v.z;
                }
                for (_, e) in &present {
                    e.move_angles(&mut r);
                }
                r.d += dd_mm;
                let mut r = spec.noise.apply(r, &mut noise_rng);
                // Gross errors last (effects.md, step 6).
                for b in fx.blunder.iter().filter(|b| {
                    b.station == pose.id && &b.target == tid && i64::from(b.face) == face.number()
                }) {
                    r = b.apply(r);
                }
                let r = r.wrapped();
                readings.push(CampaignReading {
                    station: pose.id.clone(),
                    target: tid.clone(),
                    az_deg: r.az.to_degrees(),
                    el_deg: r.el.to_degrees(),
                    d_mm: r.d,
                    face,
                    time_s: spec.record_time.then_some(time),
                    temperature_c: spec.record_temperature.then_some(temperature),
                    pressure_hpa: None,
                    humidity_pct: None,
                    line: None,
                });
            }
        }
    }
    for b in &fx.blunder {
        let taken = readings.iter().any(|r| {
            r.station == b.station && r.target == b.target && r.face.number() == i64::from(b.face)
        });
        if !taken {
            return Err(format!(
                "blunder {}: the campaign takes no such reading (station, reflector and face)",
                b.place()
            ));
        }
    }
    let mut ref_rng = random::stream(spec.seed, "references");
    let targets = layout
        .targets
        .iter()
        .map(|(id, x)| {
            let reference = layout.references.then(|| {
                x + Vector3::from_fn(|_, _| random::normal(&mut ref_rng) * spec.reference_u_mm)
            });
            Target {
                id: id.clone(),
                reference,
                u_mm: layout.references.then_some(spec.reference_u_mm),
                aim: (spec.aim == Aim::AimColumns).then_some(centroid),
            }
        })
        .collect();
    let mut gauge_rng = random::stream(spec.seed, "gauge");
    let mut gauge = Vec::new();
    for (a, ia) in layout.gauge.iter().zip(0..) {
        for b in layout.gauge.iter().skip(ia + 1) {
            let pa = layout.targets.iter().find(|t| &t.0 == a).map(|t| t.1);
            let pb = layout.targets.iter().find(|t| &t.0 == b).map(|t| t.1);
            if let (Some(pa), Some(pb)) = (pa, pb) {
                gauge.push(GaugeLength {
                    target_a: a.clone(),
                    target_b: b.clone(),
                    distance_mm: (pa - pb).norm()
                        + spec.gauge_u_mm * random::normal(&mut gauge_rng),
                    u_mm: Some(spec.gauge_u_mm),
                });
            }
        }
    }
    let campaign = Campaign {
        meta: Meta {
            format: 1,
            name: spec.name.clone(),
            description: format!("simulated by ltcal {}", crate::VERSION),
            tracker: Tracker {
                model: spec
                    .errors
                    .map_or(TrackerModel::default(), ErrorParams::tracker)
                    .id()
                    .into(),
                sigma_angle_urad: Some(spec.noise.sigma_angle_urad),
                sigma_range_um: Some(spec.noise.sigma_range_um),
                sigma_range_ppm: Some(spec.noise.sigma_range_ppm),
            },
            aim: spec.aim,
            smr_radius_mm: Some(19.05),
        },
        readings,
        targets,
        gauge,
    };
    Ok(SimulatedCampaign {
        campaign,
        poses,
        targets: layout.targets.clone(),
        effects: fx,
        not_taken,
    })
}
