//! The blind check: many simulated campaigns, each with an effect drawn at
//! random (or none) at a random magnitude and place, diagnosed without
//! seeing the truth, then scored against it.
//!
//! # What counts as detectable
//!
//! An effect can only be found if the readings carry it in a form the base
//! model cannot absorb: station poses, reflector positions and the error
//! parameters soak up whatever part of an effect resembles them. A case is
//! *detectable* when the effect's signature on the readings — the same
//! campaign simulated with and without the effect, noise-free, differenced
//! — left after projecting out everything the base adjustment can absorb,
//! amounts to Δχ² ≥ `detect_chi2` (default 25, five standard deviations)
//! in units of the stated noise. Below that, no method can tell the effect
//! from noise reliably; accuracy is reported on detectable cases and on all.

use super::{Diagnosis, Settings as DiagnoseSettings, diagnose};
use crate::campaign::{Aim, CampaignReading};
use crate::effects::{
    AirRefraction, Axis, Effects, EncoderHarmonic, Incidence, IncidenceTable9, RangeScale,
    StationDrift, TargetShift,
};
use crate::error_model::{ErrorModel, ErrorParams};
use crate::kinematics::Face;
use crate::layout::{self, Kind, Spec};
use crate::noise::Noise;
use crate::random;
use crate::simulate::{CampaignSpec, SimulatedCampaign, simulate_campaign};
use anyhow::{Result, anyhow};
use nalgebra::{DVector, Vector3};
use rand::rngs::ChaCha8Rng;
use rayon::prelude::*;
use std::collections::BTreeMap;

/// How the cases are drawn.
#[derive(Clone, Debug)]
pub struct Plan {
    pub cases: usize,
    pub seed: u64,
    pub layouts: Vec<Kind>,
    /// Station counts, drawn uniformly from this inclusive range.
    pub stations: (usize, usize),
    pub noise_angle_urad: (f64, f64),
    pub noise_range_um: (f64, f64),
    /// Share of effect-free campaigns.
    pub none_fraction: f64,
    /// Effect ids to draw from.
    pub effects: Vec<String>,
    /// Kinematic error parameters of each tracker: Gaussian, this σ in µm
    /// and µrad (a factory-compensated tracker has a few).
    pub tracker_sigma: f64,
    pub detect_chi2: f64,
    /// Monte Carlo draws per diagnosis.
    pub mc_draws: usize,
}

/// The truth of one case.
#[derive(Clone, Debug)]
pub struct Truth {
    pub effect: String,
    /// A station or reflector id, an axis, or `all`.
    pub place: String,
    /// Comparable with the diagnosis's magnitude (same unit).
    pub magnitude: f64,
    /// Whether `place` is a single station or reflector to be named.
    pub has_place: bool,
    pub effects: Effects,
}

/// One case, scored.
#[derive(Clone, Debug)]
pub struct Case {
    pub case: usize,
    pub layout: String,
    pub stations: usize,
    pub readings: usize,
    pub sigma_angle_urad: f64,
    pub sigma_range_um: f64,
    pub truth: Truth,
    /// Δχ² of the unabsorbed signature.
    pub signal_chi2: f64,
    pub detectable: bool,
    pub named_effect: String,
    pub named_place: String,
    pub named_magnitude: f64,
    pub effect_correct: bool,
    /// `None` when the truth has no single place to name.
    pub place_correct: Option<bool>,
    pub magnitude_ratio: Option<f64>,
}

fn between(rng: &mut ChaCha8Rng, (lo, hi): (f64, f64)) -> f64 {
    lo + (hi - lo) * random::uniform(rng)
}

/// Log-uniform in [lo, hi], with a random sign when `signed`.
fn magnitude(rng: &mut ChaCha8Rng, lo: f64, hi: f64, signed: bool) -> f64 {
    let m = (lo.ln() + (hi.ln() - lo.ln()) * random::uniform(rng)).exp();
    if signed && random::uniform(rng) < 0.5 {
        -m
    } else {
        m
    }
}

fn direction(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    Vector3::new(
        random::normal(rng),
        random::normal(rng),
        random::normal(rng),
    )
    .normalize()
}

fn pick<'a, T>(rng: &mut ChaCha8Rng, v: &'a [T]) -> &'a T {
    &v[((random::uniform(rng) * v.len() as f64) as usize).min(v.len() - 1)]
}

/// Draws an effect of the given id for a layout.
fn draw_effect(rng: &mut ChaCha8Rng, id: &str, stations: &[String], targets: &[String]) -> Truth {
    let mut fx = Effects::default();
    let (place, mag, has_place) = match id {
        "incidence" => {
            let e = magnitude(rng, 30.0, 300.0, false);
            let i = Incidence {
                e_axial_um: e,
                e_h_um: 0.2 * e * (2.0 * random::uniform(rng) - 1.0),
                e_v_um: 0.2 * e * (2.0 * random::uniform(rng) - 1.0),
                max_angle_deg: crate::effects::DEFAULT_MAX_ANGLE_DEG,
            };
            fx.incidence = Some(i);
            ("all".to_string(), e, false)
        }
        "incidence-table9" => {
            fx.incidence_table9 = Some(IncidenceTable9 {});
            ("all".to_string(), 1.0, false)
        }
        "range-scale" => {
            let s = pick(rng, stations).clone();
            let ppm = magnitude(rng, 2.0, 12.0, true);
            fx.range_scale = Some(RangeScale {
                ppm: BTreeMap::from([(s.clone(), ppm)]),
                sigma_ppm: None,
            });
            (s, ppm, true)
        }
        "air-refraction" => {
            fx.air_refraction = Some(AirRefraction {
                t0_c: 20.0,
                offset_c: 0.0,
                amplitude_c: magnitude(rng, 0.5, 2.5, false),
                period_s: between(rng, (600.0, 2400.0)),
                phase_deg: 360.0 * random::uniform(rng),
                drift_c_per_h: between(rng, (-1.5, 1.5)),
            });
            // The physics fixes the coefficient: −0.93 ppm/K.
            ("all".to_string(), -0.93, false)
        }
        "encoder-harmonic" => {
            let axis = if random::uniform(rng) < 0.5 {
                Axis::Az
            } else {
                Axis::El
            };
            let amp = magnitude(rng, 3.0, 25.0, false);
            fx.encoder_harmonic = Some(EncoderHarmonic {
                axis,
                order: 2 + (random::uniform(rng) * 3.0) as u32 % 3,
                amplitude_urad: amp,
                phase_deg: 360.0 * random::uniform(rng),
            });
            (
                if axis == Axis::Az { "az" } else { "el" }.to_string(),
                amp,
                true,
            )
        }
        "station-drift" => {
            let s = pick(rng, stations).clone();
            let v = direction(rng) * magnitude(rng, 2.0, 15.0, false);
            fx.station_drift = Some(StationDrift {
                station: Some(s.clone()),
                velocity_um_per_min: [v.x, v.y, v.z],
            });
            (s, v.norm(), true)
        }
        "target-shift" => {
            let t = pick(rng, targets).clone();
            let from = pick(rng, &stations[1..]).clone();
            let s = direction(rng) * magnitude(rng, 30.0, 200.0, false);
            fx.target_shift = Some(TargetShift {
                target: t.clone(),
                from_station: from,
                shift_um: [s.x, s.y, s.z],
            });
            (t, s.norm(), true)
        }
        _ => ("all".to_string(), 0.0, false),
    };
    Truth {
        effect: if fx.ids().is_empty() {
            "none".into()
        } else {
            id.into()
        },
        place,
        magnitude: mag,
        has_place,
        effects: fx,
    }
}

fn simulate(
    spec: &Spec,
    errors: &ErrorParams,
    noise: Noise,
    fx: &Effects,
    seed: u64,
) -> Result<SimulatedCampaign> {
    let layout = layout::build(spec);
    simulate_campaign(&CampaignSpec {
        name: "blind".into(),
        layout: &layout,
        errors: Some(errors),
        faces: &[Face::Front],
        aim: Aim::StationsCentroid,
        max_angle_deg: crate::effects::DEFAULT_MAX_ANGLE_DEG,
        noise,
        effects: fx,
        gauge_u_mm: 0.0005,
        reference_u_mm: 0.002,
        level_urad: 1000.0,
        interval_s: 20.0,
        record_time: true,
        record_temperature: true,
        seed,
    })
    .map_err(|e| anyhow!(e))
}

type Key = (String, String, i64);

fn key(r: &CampaignReading) -> Key {
    (r.station.clone(), r.target.clone(), r.face.number())
}

/// The effect's Δχ² on the readings once the base adjustment has absorbed
/// what it can: `‖P⊥·W·Δ‖²` with Δ the noise-free difference of the
/// readings with and without the effect.
fn signal_chi2(
    d: &Diagnosis,
    with: &SimulatedCampaign,
    without: &SimulatedCampaign,
    readings: &[CampaignReading],
) -> f64 {
    let Some(lin) = &d.calibration.linearisation else {
        return 0.0;
    };
    let base: BTreeMap<Key, &CampaignReading> = without
        .campaign
        .readings
        .iter()
        .map(|r| (key(r), r))
        .collect();
    let eff: BTreeMap<Key, &CampaignReading> =
        with.campaign.readings.iter().map(|r| (key(r), r)).collect();
    let mut delta = DVector::zeros(lin.jacobian.nrows());
    for (i, r) in readings.iter().enumerate() {
        let k = key(r);
        if let (Some(a), Some(b)) = (eff.get(&k), base.get(&k)) {
            let daz = crate::kinematics::wrap_angle((a.az_deg - b.az_deg).to_radians());
            let del = (a.el_deg - b.el_deg).to_radians();
            let dd = a.d_mm - b.d_mm;
            let s = d.sigma[i];
            delta[3 * i] = daz / s.x;
            delta[3 * i + 1] = del / s.y;
            delta[3 * i + 2] = dd / s.z;
        }
    }
    super::linear::unabsorbed_norm2(&lin.jacobian, &delta)
}

/// Runs one case.
fn run_case(plan: &Plan, case: usize) -> Result<Case> {
    let mut rng = random::stream(plan.seed, &format!("blind-check-{case}"));
    let kind = *pick(&mut rng, &plan.layouts);
    let n_st = plan.stations.0
        + ((random::uniform(&mut rng) * (plan.stations.1 - plan.stations.0 + 1) as f64) as usize)
            .min(plan.stations.1 - plan.stations.0);
    let mut spec = Spec::new(kind);
    spec.stations = n_st;
    let noise = Noise {
        sigma_angle_urad: between(&mut rng, plan.noise_angle_urad),
        sigma_range_um: between(&mut rng, plan.noise_range_um),
        sigma_range_ppm: 0.3,
    };
    let mut errors = ErrorParams::zero(&ErrorModel::constant());
    for v in errors.values_mut() {
        *v = plan.tracker_sigma * random::normal(&mut rng);
    }
    let lay = layout::build(&spec);
    let stations: Vec<String> = lay.stations.iter().map(|s| s.0.clone()).collect();
    let targets: Vec<String> = lay.targets.iter().map(|t| t.0.clone()).collect();
    let id = if random::uniform(&mut rng) < plan.none_fraction || plan.effects.is_empty() {
        "none".to_string()
    } else {
        pick(&mut rng, &plan.effects).clone()
    };
    let truth = draw_effect(&mut rng, &id, &stations, &targets);
    let seed = plan.seed.wrapping_mul(1_000_003).wrapping_add(case as u64);
    let noisy = simulate(&spec, &errors, noise, &truth.effects, seed)?;
    let clean_with = simulate(&spec, &errors, Noise::default(), &truth.effects, seed)?;
    let clean_without = simulate(&spec, &errors, Noise::default(), &Effects::default(), seed)?;
    let d = diagnose(
        &noisy.campaign,
        &DiagnoseSettings {
            mc_draws: plan.mc_draws,
            seed,
            ..DiagnoseSettings::default()
        },
    )?;
    let signal = if truth.effect == "none" {
        0.0
    } else {
        signal_chi2(&d, &clean_with, &clean_without, &noisy.campaign.readings)
    };
    let best = d.best();
    let effect_correct = best.effect == truth.effect;
    let place_correct = truth
        .has_place
        .then(|| effect_correct && best.place == truth.place);
    let magnitude_ratio = (effect_correct && truth.effect != "none" && truth.magnitude != 0.0)
        .then(|| best.magnitude / truth.magnitude);
    Ok(Case {
        case,
        layout: format!("{kind:?}").to_lowercase(),
        stations: n_st,
        readings: noisy.campaign.readings.len(),
        sigma_angle_urad: noise.sigma_angle_urad,
        sigma_range_um: noise.sigma_range_um,
        signal_chi2: signal,
        detectable: truth.effect == "none" || signal >= plan.detect_chi2,
        named_effect: best.effect.clone(),
        named_place: best.place.clone(),
        named_magnitude: best.magnitude,
        effect_correct,
        place_correct,
        magnitude_ratio,
        truth,
    })
}

/// Runs every case (in parallel; the result does not depend on the
/// number of threads: each case has its own random stream).
pub fn run(plan: &Plan) -> Result<Vec<Case>> {
    (0..plan.cases)
        .into_par_iter()
        .map(|k| run_case(plan, k))
        .collect()
}

/// Accuracy figures.
#[derive(Clone, Debug, Default)]
pub struct Score {
    pub cases: usize,
    pub with_effect: usize,
    pub effect_correct: usize,
    pub with_place: usize,
    pub place_correct: usize,
    pub effect_free: usize,
    pub none_correct: usize,
    /// Median of |named/true − 1| over correctly named effects.
    pub median_magnitude_error: f64,
}

impl Score {
    pub fn of<'a>(cases: impl Iterator<Item = &'a Case>) -> Score {
        let mut s = Score::default();
        let mut errs = Vec::new();
        for c in cases {
            s.cases += 1;
            if c.truth.effect == "none" {
                s.effect_free += 1;
                s.none_correct += c.effect_correct as usize;
            } else {
                s.with_effect += 1;
                s.effect_correct += c.effect_correct as usize;
            }
            if let Some(p) = c.place_correct {
                s.with_place += 1;
                s.place_correct += p as usize;
            }
            if let Some(r) = c.magnitude_ratio {
                errs.push((r - 1.0).abs());
            }
        }
        errs.sort_by(f64::total_cmp);
        s.median_magnitude_error = errs.get(errs.len() / 2).copied().unwrap_or(f64::NAN);
        s
    }

    pub fn effect_rate(&self) -> f64 {
        self.effect_correct as f64 / self.with_effect.max(1) as f64
    }
    pub fn place_rate(&self) -> f64 {
        self.place_correct as f64 / self.with_place.max(1) as f64
    }
    pub fn none_rate(&self) -> f64 {
        self.none_correct as f64 / self.effect_free.max(1) as f64
    }
}
