//! Effects *outside* the catalogue of `effects.md`: an independent generator
//! that perturbs an already simulated campaign with physics the diagnosis has
//! no name for (issue 30, item 3).
//!
//! # Why it is kept apart from the diagnosis
//!
//! The diagnosis is judged on campaigns it has never been told about. If
//! this generator shared the catalogue's code ([`crate::effects`]), its
//! hypotheses or its factors, a bug or a modelling choice there would be
//! repeated here, and an "unknown" effect would secretly be a known one.
//! So this module imports only the simulator's geometry (`simulate`,
//! `kinematics`, `error_model`, `campaign`), `random`, `nalgebra` and
//! `serde` — never `crate::diagnose`, `crate::effects` or
//! `crate::hypothesis` (a unit test below reads its own sources to hold
//! that) — and it says of each effect only which *factor* its structure
//! lies along, the thing a localisation is scored against.
//!
//! # The effects
//!
//! Magnitudes for a laser tracker in a hall of 5–20 m
//! (`/work/shared/paper/FIELD.md`); each file holds the physics and the
//! formula.
//!
//! | id | what | formula | drawn magnitude | factor |
//! |----|------|---------|-----------------|--------|
//! | `tripod-knock` | a station's tripod is knocked at `t0` | pose shifted by `s`, turned by yaw `ψ` from `t0` on | \|s\| 20–150 µm, \|ψ\| 5–30 µrad | `station × time` |
//! | `adm-cyclic` | the ADM's periodic nonlinearity | `Δd = A·sin(2π·d/P + φ)` | A 3–20 µm, P 0.5–1.5 m | `range` |
//! | `part-expansion` | the reflectors' structure warms | `x = x0 + (x0 − c)·α·ΔT(t)` | α 11.5e-6/K, 0.3–2 K/h | `time` |
//! | `axis-wobble` | the standing axis tilts with az, k = 2, 3 | `Δel = w·cos((k−1)·az + φ)`, `Δaz = −w·tan el·sin((k−1)·az + φ)` | w 3–20 µrad | `az` |
//! | `beam-bending` | a vertical temperature gradient G | `Δel = 0.93e-6·G·cos el·d/2`, `Δd = −0.93e-6·G·(d·sin el/2)·d` | G 0.2–1 K/m | `range` |
//! | `two-smr-kinds` | 30–50 % of the reflectors are another SMR kind | `Δd = c` on their readings | \|c\| 5–40 µm | `reflector` |
//! | `adm-reset` | a station's ADM re-initialises at `t0` | `Δd = c` from `t0` on | \|c\| 5–25 µm | `station × time` |
//!
//! Effects that move geometry (`tripod-knock`, `part-expansion`) change each
//! reading by the exact noise-free difference of what the tracker, with its
//! kinematic errors, reads with and without the move; the others add their
//! change to the reading. Either way the reading's noise is untouched.
//! Angles are radians inside formulas, lengths mm; parameters carry their
//! unit in their name.

mod adm_cyclic;
mod adm_reset;
mod axis_wobble;
mod beam_bending;
mod part_expansion;
mod tripod_knock;
mod two_smr_kinds;

pub use adm_cyclic::AdmCyclic;
pub use adm_reset::AdmReset;
pub use axis_wobble::AxisWobble;
pub use beam_bending::BeamBending;
pub use part_expansion::PartExpansion;
pub use tripod_knock::TripodKnock;
pub use two_smr_kinds::TwoSmrKinds;

use crate::campaign::CampaignReading;
use crate::error_model::ErrorParams;
use crate::simulate::{SimulatedCampaign, StationPose, read};
use nalgebra::Vector3;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// Every effect id, in [`Kind::ALL`]'s order.
pub const KINDS: &[&str] = &[
    "tripod-knock",
    "adm-cyclic",
    "part-expansion",
    "axis-wobble",
    "beam-bending",
    "two-smr-kinds",
    "adm-reset",
];

/// The factors an effect's structure can lie along: what a localisation
/// is scored against.
pub const FACTORS: &[&str] = &["station × time", "range", "time", "az", "el", "reflector"];

/// Which effect.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Kind {
    TripodKnock,
    AdmCyclic,
    PartExpansion,
    AxisWobble,
    BeamBending,
    TwoSmrKinds,
    AdmReset,
}

impl Kind {
    pub const ALL: [Kind; 7] = [
        Kind::TripodKnock,
        Kind::AdmCyclic,
        Kind::PartExpansion,
        Kind::AxisWobble,
        Kind::BeamBending,
        Kind::TwoSmrKinds,
        Kind::AdmReset,
    ];

    /// The id tables and reports use.
    pub fn id(self) -> &'static str {
        match self {
            Kind::TripodKnock => "tripod-knock",
            Kind::AdmCyclic => "adm-cyclic",
            Kind::PartExpansion => "part-expansion",
            Kind::AxisWobble => "axis-wobble",
            Kind::BeamBending => "beam-bending",
            Kind::TwoSmrKinds => "two-smr-kinds",
            Kind::AdmReset => "adm-reset",
        }
    }

    /// The factor, one of [`FACTORS`], that the effect's structure lies
    /// along (each effect's file says why).
    pub fn factor(self) -> &'static str {
        match self {
            Kind::TripodKnock | Kind::AdmReset => "station × time",
            Kind::AdmCyclic | Kind::BeamBending => "range",
            Kind::PartExpansion => "time",
            Kind::AxisWobble => "az",
            Kind::TwoSmrKinds => "reflector",
        }
    }

    /// Whether the effect needs the readings' `time_s`.
    pub fn needs_time(self) -> bool {
        matches!(
            self,
            Kind::TripodKnock | Kind::PartExpansion | Kind::AdmReset
        )
    }
}

/// The kind an id (as [`Kind::id`] writes it) stands for.
pub fn parse(id: &str) -> Option<Kind> {
    Kind::ALL.into_iter().find(|k| k.id() == id)
}

/// One drawn effect with its parameters; in TOML its `effect` key is its
/// id.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "effect", rename_all = "kebab-case")]
pub enum OpenEffect {
    TripodKnock(TripodKnock),
    AdmCyclic(AdmCyclic),
    PartExpansion(PartExpansion),
    AxisWobble(AxisWobble),
    BeamBending(BeamBending),
    TwoSmrKinds(TwoSmrKinds),
    AdmReset(AdmReset),
}

impl OpenEffect {
    pub fn kind(&self) -> Kind {
        match self {
            OpenEffect::TripodKnock(_) => Kind::TripodKnock,
            OpenEffect::AdmCyclic(_) => Kind::AdmCyclic,
            OpenEffect::PartExpansion(_) => Kind::PartExpansion,
            OpenEffect::AxisWobble(_) => Kind::AxisWobble,
            OpenEffect::BeamBending(_) => Kind::BeamBending,
            OpenEffect::TwoSmrKinds(_) => Kind::TwoSmrKinds,
            OpenEffect::AdmReset(_) => Kind::AdmReset,
        }
    }

    pub fn id(&self) -> &'static str {
        self.kind().id()
    }

    pub fn factor(&self) -> &'static str {
        self.kind().factor()
    }

    /// One line with the drawn values, for reports.
    pub fn describe(&self) -> String {
        let what = match self {
            OpenEffect::TripodKnock(e) => e.describe(),
            OpenEffect::AdmCyclic(e) => e.describe(),
            OpenEffect::PartExpansion(e) => e.describe(),
            OpenEffect::AxisWobble(e) => e.describe(),
            OpenEffect::BeamBending(e) => e.describe(),
            OpenEffect::TwoSmrKinds(e) => e.describe(),
            OpenEffect::AdmReset(e) => e.describe(),
        };
        format!("{}: {what}", self.id())
    }

    /// An effect of `kind` at a random realistic magnitude and place in the
    /// campaign `ctx` describes. Fails for a time-dependent kind when the
    /// campaign has no `time_s`.
    pub fn draw(kind: Kind, rng: &mut ChaCha8Rng, ctx: &Context) -> Result<OpenEffect, String> {
        Ok(match kind {
            Kind::TripodKnock => OpenEffect::TripodKnock(TripodKnock::draw(rng, ctx)?),
            Kind::AdmCyclic => OpenEffect::AdmCyclic(AdmCyclic::draw(rng)),
            Kind::PartExpansion => OpenEffect::PartExpansion(PartExpansion::draw(rng, ctx)?),
            Kind::AxisWobble => OpenEffect::AxisWobble(AxisWobble::draw(rng)),
            Kind::BeamBending => OpenEffect::BeamBending(BeamBending::draw(rng)),
            Kind::TwoSmrKinds => OpenEffect::TwoSmrKinds(TwoSmrKinds::draw(rng, ctx)?),
            Kind::AdmReset => OpenEffect::AdmReset(AdmReset::draw(rng, ctx)?),
        })
    }

    /// The campaign with every reading moved by the effect. `errors` are
    /// the tracker's kinematic error parameters the campaign was simulated
    /// with (`None`: a perfect tracker); geometric effects read through
    /// them. `poses` and `targets` stay the truth before this effect: the
    /// effect's own parameters say what moved.
    pub fn apply(
        &self,
        sim: &SimulatedCampaign,
        errors: Option<&ErrorParams>,
    ) -> Result<SimulatedCampaign, String> {
        let mut out = sim.clone();
        match self {
            OpenEffect::TripodKnock(e) => e.apply(&mut out, errors)?,
            OpenEffect::AdmCyclic(e) => e.apply(&mut out),
            OpenEffect::PartExpansion(e) => e.apply(&mut out, errors)?,
            OpenEffect::AxisWobble(e) => e.apply(&mut out),
            OpenEffect::BeamBending(e) => e.apply(&mut out),
            OpenEffect::TwoSmrKinds(e) => e.apply(&mut out)?,
            OpenEffect::AdmReset(e) => e.apply(&mut out)?,
        }
        Ok(out)
    }
}

/// What a draw may place an effect on: the stations with the times of
/// their readings, and the reflectors.
#[derive(Clone, Debug)]
pub struct Context {
    pub sessions: Vec<Session>,
    /// `(id, true centre)`, mm.
    pub targets: Vec<(String, Vector3<f64>)>,
}

/// One station's readings in time.
#[derive(Clone, Debug, PartialEq)]
pub struct Session {
    pub station: String,
    /// Times of its first and last reading (s); `None` when a reading of
    /// the station has no `time_s`.
    pub times_s: Option<(f64, f64)>,
}

impl Context {
    pub fn of(sim: &SimulatedCampaign) -> Context {
        let sessions = sim
            .poses
            .iter()
            .map(|p| {
                let times: Option<Vec<f64>> = sim
                    .campaign
                    .readings
                    .iter()
                    .filter(|r| r.station == p.id)
                    .map(|r| r.time_s)
                    .collect();
                Session {
                    station: p.id.clone(),
                    times_s: times.filter(|t| !t.is_empty()).map(|t| {
                        t.iter()
                            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &x| {
                                (lo.min(x), hi.max(x))
                            })
                    }),
                }
            })
            .collect();
        Context {
            sessions,
            targets: sim.targets.clone(),
        }
    }

    /// The time of the campaign's first reading, when every station has
    /// times.
    pub fn start_s(&self) -> Option<f64> {
        self.sessions
            .iter()
            .map(|s| s.times_s.map(|t| t.0))
            .collect::<Option<Vec<f64>>>()?
            .into_iter()
            .reduce(f64::min)
    }
}

/// Uniform in [lo, hi).
fn between(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * crate::random::uniform(rng)
}

/// Log-uniform in [lo, hi): every decade of a magnitude range as likely.
fn log_uniform(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> f64 {
    between(rng, lo.ln(), hi.ln()).exp()
}

/// +1 or −1, each with probability ½.
fn sign(rng: &mut ChaCha8Rng) -> f64 {
    if crate::random::uniform(rng) < 0.5 {
        -1.0
    } else {
        1.0
    }
}

/// An index in 0..n (n > 0), uniform.
fn index(rng: &mut ChaCha8Rng, n: usize) -> usize {
    ((crate::random::uniform(rng) * n as f64) as usize).min(n - 1)
}

/// A time `t0` inside a station's session, drawn in the middle half of it
/// so that readings come both before and after: the draw of the "mid-session"
/// events (`tripod-knock`, `adm-reset`).
fn mid_session(rng: &mut ChaCha8Rng, ctx: &Context, kind: Kind) -> Result<(String, f64), String> {
    let timed: Vec<(&str, (f64, f64))> = ctx
        .sessions
        .iter()
        .filter_map(|s| s.times_s.map(|t| (s.station.as_str(), t)))
        .filter(|(_, (a, b))| b > a)
        .collect();
    if timed.is_empty() {
        return Err(format!(
            "{} needs a station with readings at two times (time_s)",
            kind.id()
        ));
    }
    let (station, (first, last)) = timed[index(rng, timed.len())];
    let t0 = first + between(rng, 0.25, 0.75) * (last - first);
    Ok((station.to_string(), t0))
}

/// The reading's time, or why a time-dependent effect cannot act on it.
fn time_of(r: &CampaignReading, kind: Kind) -> Result<f64, String> {
    r.time_s.ok_or_else(|| {
        format!(
            "{} needs time_s, and reading {}/{}/{} has none",
            kind.id(),
            r.station,
            r.target,
            r.face.number()
        )
    })
}

fn pose<'a>(poses: &'a [StationPose], station: &str) -> Result<&'a StationPose, String> {
    poses
        .iter()
        .find(|p| p.id == station)
        .ok_or_else(|| format!("station `{station}` is not in the campaign"))
}

fn target(targets: &[(String, Vector3<f64>)], id: &str) -> Result<Vector3<f64>, String> {
    targets
        .iter()
        .find(|t| t.0 == id)
        .map(|t| t.1)
        .ok_or_else(|| format!("reflector `{id}` is not in the campaign"))
}

/// The noise-free change `(Δaz rad, Δel rad, Δd mm)` of the reading of
/// `r`'s station, reflector and face when the station's pose `from.0` and
/// the reflector's centre `from.1` become `to`: the tracker, with its
/// errors, reads both exactly, so the change carries the errors' (tiny)
/// cross terms too.
fn geometric_change(
    errors: Option<&ErrorParams>,
    r: &CampaignReading,
    from: (&StationPose, &Vector3<f64>),
    to: (&StationPose, &Vector3<f64>),
) -> Result<(f64, f64, f64), String> {
    let reading = |(p, x): (&StationPose, &Vector3<f64>)| {
        read(errors, &p.to_local(x), r.face)
            .map_err(|e| format!("station {}, reflector {}: {e}", r.station, r.target))
    };
    let (a, b) = (reading(from)?, reading(to)?);
    Ok((
        crate::kinematics::wrap_angle(b.az - a.az),
        b.el - a.el,
        b.d - a.d,
    ))
}

/// Moves a reading by `Δaz`, `Δel` (rad) and `Δd` (mm), keeping `az` in
/// (−180°, 180°] as the simulator writes it. A zero change leaves the
/// coordinate bit-identical (adding 0 would turn a −0 into +0).
fn move_reading(r: &mut CampaignReading, daz_rad: f64, del_rad: f64, dd_mm: f64) {
    if daz_rad != 0.0 {
        let az = r.az_deg + daz_rad.to_degrees();
        r.az_deg = if az > 180.0 {
            az - 360.0
        } else if az <= -180.0 {
            az + 360.0
        } else {
            az
        };
    }
    if del_rad != 0.0 {
        r.el_deg += del_rad.to_degrees();
    }
    if dd_mm != 0.0 {
        r.d_mm += dd_mm;
    }
}

#[cfg(test)]
pub(crate) mod fixture {
    //! A small simulated campaign for the effects' tests.

    use crate::campaign::Aim;
    use crate::error_model::ErrorParams;
    use crate::kinematics::Face;
    use crate::layout::{Kind, Spec, build};
    use crate::noise::Noise;
    use crate::simulate::{CampaignSpec, SimulatedCampaign, simulate_campaign};

    /// The `time_s` of `station`'s readings, in reading order.
    pub fn times_of(sim: &SimulatedCampaign, station: &str) -> Vec<f64> {
        let readings = sim.campaign.readings.iter();
        readings
            .filter(|r| r.station == station)
            .map(|r| r.time_s.unwrap())
            .collect()
    }

    /// The tracker: Table 2's errors, every parameter 10 µm or 10 µrad.
    pub fn errors() -> ErrorParams {
        ErrorParams::table2()
    }

    /// Three stations, 12 reflectors of the corner layout, both faces,
    /// noisy, with (`timed`) or without `time_s`.
    pub fn campaign(timed: bool) -> SimulatedCampaign {
        let mut spec = Spec::new(Kind::Corner);
        spec.stations = 3;
        spec.per_level = 4;
        let layout = build(&spec);
        let errors = errors();
        simulate_campaign(&CampaignSpec {
            name: "open-world".into(),
            layout: &layout,
            errors: Some(&errors),
            faces: &[Face::Front, Face::Back],
            aim: Aim::StationsCentroid,
            max_angle_deg: 30.0,
            noise: Noise {
                sigma_angle_urad: 1.0,
                sigma_range_um: 3.0,
                sigma_range_ppm: 0.3,
            },
            // No catalogue effect: this module does not name them.
            effects: &Default::default(),
            gauge_u_mm: 0.0005,
            reference_u_mm: 0.002,
            level_urad: 1000.0,
            interval_s: 20.0,
            record_time: timed,
            record_temperature: timed,
            seed: 11,
        })
        .expect("the fixture simulates")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::random::stream;

    #[test]
    fn kinds_ids_and_factors_agree() {
        assert_eq!(KINDS.len(), Kind::ALL.len());
        for (k, id) in Kind::ALL.iter().zip(KINDS) {
            assert_eq!(k.id(), *id);
            assert_eq!(parse(id), Some(*k));
            assert!(FACTORS.contains(&k.factor()), "{id}");
        }
        assert_eq!(parse("blunder"), None);
        assert_eq!(Kind::TripodKnock.factor(), "station × time");
        assert_eq!(Kind::AdmCyclic.factor(), "range");
        assert_eq!(Kind::PartExpansion.factor(), "time");
        assert_eq!(Kind::AxisWobble.factor(), "az");
        assert_eq!(Kind::BeamBending.factor(), "range");
        assert_eq!(Kind::TwoSmrKinds.factor(), "reflector");
        assert_eq!(Kind::AdmReset.factor(), "station × time");
    }

    #[test]
    fn context_has_every_station_session_and_reflector() {
        let sim = fixture::campaign(true);
        let ctx = Context::of(&sim);
        assert_eq!(ctx.sessions.len(), 3);
        assert_eq!(ctx.targets.len(), sim.targets.len());
        let (a, b) = ctx.sessions[1].times_s.unwrap();
        let times = fixture::times_of(&sim, &ctx.sessions[1].station);
        assert_eq!(a, times[0]);
        assert_eq!(b, *times.last().unwrap());
        // The first reading taken (the first attempts may lie beyond the
        // SMR's acceptance).
        let first = sim.campaign.readings[0].time_s;
        assert_eq!(ctx.start_s(), first);
        assert!(first.unwrap() >= 0.0);
        let untimed = Context::of(&fixture::campaign(false));
        assert!(untimed.sessions.iter().all(|s| s.times_s.is_none()));
        assert_eq!(untimed.start_s(), None);
    }

    #[test]
    fn draws_are_deterministic_serialisable_and_described() {
        let ctx = Context::of(&fixture::campaign(true));
        for k in Kind::ALL {
            let a = OpenEffect::draw(k, &mut stream(5, "open"), &ctx).unwrap();
            let b = OpenEffect::draw(k, &mut stream(5, "open"), &ctx).unwrap();
            let c = OpenEffect::draw(k, &mut stream(6, "open"), &ctx).unwrap();
            assert_eq!(a, b);
            assert_ne!(a, c);
            assert_eq!(a.kind(), k);
            // TOML, as a pipeline would write it: its floats round-trip.
            let text = toml::to_string(&a).unwrap();
            assert!(text.contains(&format!("effect = \"{}\"", k.id())), "{text}");
            assert_eq!(toml::from_str::<OpenEffect>(&text).unwrap(), a);
            assert!(a.describe().starts_with(&format!("{}: ", k.id())));
        }
    }

    #[test]
    fn time_dependent_kinds_refuse_a_campaign_without_time() {
        let sim = fixture::campaign(false);
        let ctx = Context::of(&sim);
        let timed_ctx = Context::of(&fixture::campaign(true));
        for k in Kind::ALL {
            let drawn = OpenEffect::draw(k, &mut stream(1, "t"), &ctx);
            assert_eq!(drawn.is_err(), k.needs_time(), "{}", k.id());
            let e = OpenEffect::draw(k, &mut stream(1, "t"), &timed_ctx).unwrap();
            let applied = e.apply(&sim, Some(&fixture::errors()));
            assert_eq!(applied.is_err(), k.needs_time(), "{}", k.id());
            if let Err(msg) = applied {
                assert!(msg.contains("needs time_s"), "{msg}");
            }
        }
    }

    #[test]
    fn every_effect_moves_the_campaign_and_keeps_its_readings_in_order() {
        let sim = fixture::campaign(true);
        let ctx = Context::of(&sim);
        for k in Kind::ALL {
            let e = OpenEffect::draw(k, &mut stream(2, "m"), &ctx).unwrap();
            let out = e.apply(&sim, Some(&fixture::errors())).unwrap();
            assert_eq!(out.campaign.readings.len(), sim.campaign.readings.len());
            let moved = out
                .campaign
                .readings
                .iter()
                .zip(&sim.campaign.readings)
                .filter(|(a, b)| a != b)
                .count();
            assert!(moved > 0, "{}", k.id());
            for (a, b) in out.campaign.readings.iter().zip(&sim.campaign.readings) {
                assert_eq!(
                    (&a.station, &a.target, a.face),
                    (&b.station, &b.target, b.face)
                );
                assert!(a.az_deg > -180.0 && a.az_deg <= 180.0);
                // Realistic: no effect moves a reading by more than 1 mm or
                // 100 µrad.
                assert!((a.d_mm - b.d_mm).abs() < 1.0, "{}", k.id());
                let daz = crate::kinematics::wrap_angle((a.az_deg - b.az_deg).to_radians());
                assert!(daz.abs() < 1e-4, "{}", k.id());
                assert!(
                    (a.el_deg - b.el_deg).to_radians().abs() < 1e-4,
                    "{}",
                    k.id()
                );
            }
        }
    }

    #[test]
    fn move_reading_wraps_az_and_leaves_zero_changes_alone() {
        let sim = fixture::campaign(true);
        let mut r = sim.campaign.readings[0].clone();
        r.az_deg = 179.9999;
        r.el_deg = -0.0;
        move_reading(&mut r, 1e-3, 0.0, 0.0);
        assert!((r.az_deg - (179.9999 + 1e-3f64.to_degrees() - 360.0)).abs() < 1e-12);
        assert!(r.el_deg.is_sign_negative());
        r.az_deg = -179.9999;
        move_reading(&mut r, -1e-3, 0.0, 0.002);
        assert!((r.az_deg - (-179.9999 - 1e-3f64.to_degrees() + 360.0)).abs() < 1e-12);
    }

    #[test]
    fn the_generator_knows_nothing_of_the_diagnosis() {
        let sources = [
            include_str!("mod.rs"),
            include_str!("adm_cyclic.rs"),
            include_str!("adm_reset.rs"),
            include_str!("axis_wobble.rs"),
            include_str!("beam_bending.rs"),
            include_str!("part_expansion.rs"),
            include_str!("tripod_knock.rs"),
            include_str!("two_smr_kinds.rs"),
        ];
        for src in sources {
            for line in src.lines() {
                let code = line.split_once("//").map_or(line, |(c, _)| c);
                let code: String = code.chars().filter(|c| !c.is_whitespace()).collect();
                // Any path from the crate root, `use crate::{…}` groups too.
                if !(code.contains("crate::") || code.contains("super::super")) {
                    continue;
                }
                for forbidden in ["diagnose", "effects", "hypothesis"] {
                    assert!(
                        !code.contains(forbidden),
                        "open_world names {forbidden}: {line}"
                    );
                }
            }
        }
    }
}
