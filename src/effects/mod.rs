//! The unmodelled effects of `effects.md` (version 2), each a plug-in: one
//! file holds everything ltcal knows about it, and the catalogue is the one
//! list of [`catalogue!`] below.
//!
//! Why plug-ins: an effect is used in three places — the simulator injects
//! it, the diagnosis tests it as a candidate explanation, the blind check
//! draws it at random and scores the diagnosis against it. When each of
//! those matched the effect's id, adding an effect meant editing every one
//! of them; now an effect's file implements [`Effect`] (settings, checks,
//! truth rows, candidate columns, draw) and [`Forward`] (its forward model,
//! in the order of effects.md's steps), and the simulator, the diagnosis and
//! the blind check iterate the registry. ARCHITECTURE.md has the recipe.
//!
//! An effect's id (`incidence`, `range-scale`, …) is its key in TOML, its
//! name in tables and in reports. In a `simulate_campaign` stage:
//!
//! ```toml
//! [stages.sim.effects.incidence]
//! e_axial_um = 5.0
//! [stages.sim.effects.range-scale]
//! ppm = { S1 = 2.0, S3 = -1.5 }
//! ```
//!
//! Angles are radians inside formulas, lengths mm; parameters carry their
//! unit. Blunders (`blunder`, any number of them, each on one reading) are
//! gross errors rather than a model to fit: they have their own file and
//! are found by the w-test, not as candidates.

mod blunder;

pub use blunder::{Blunder, Coordinate};
pub use encoder_harmonic::Axis;
pub use incidence_table9::{TABLE9_UM, table9_angles_deg, table9_delta_d_um};

use crate::diagnose::candidates::{Context, Found};
use crate::kinematics::Reading;
use nalgebra::Vector3;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize, de::DeserializeOwned};
use std::collections::BTreeMap;
use std::sync::LazyLock;

/// The SMR's acceptance: beyond it the beam does not return.
pub const DEFAULT_MAX_ANGLE_DEG: f64 = 30.0;

/// What an effect needs the readings to record.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Needs {
    /// `time_s` (effects.md: station-drift "needs time_s").
    pub time: bool,
    /// `temperature_c` (air-refraction's readings "carry the true temperature_c").
    pub temperature: bool,
}

impl Needs {
    pub const NOTHING: Needs = Needs {
        time: false,
        temperature: false,
    };

    /// Whether a file without `time_s` and `temperature_c` can carry it.
    pub fn any(self) -> bool {
        self.time || self.temperature
    }
}

/// The campaign an effect is injected into, before its first reading.
pub struct Setup<'a> {
    /// Station ids in the measuring order.
    pub stations: &'a [String],
    /// Reflector ids.
    pub targets: &'a [String],
    pub seed: u64,
}

/// Which reading the simulator is taking.
pub struct Place<'a> {
    pub station: &'a str,
    /// The station's place in the measuring order (0: the first).
    pub rank: usize,
    pub target: &'a str,
    /// Station ids in the measuring order.
    pub stations: &'a [String],
}

/// An effect's forward model: the simulator calls these, for the effects
/// present, in effects.md's order of steps (true centre, true station pose,
/// acceptance, the reading, reading-level changes; noise and blunders
/// after). Every hook defaults to "no change", and a change is applied only
/// when an effect makes one — adding a zero would turn a −0 into a +0.
pub trait Forward: Send + Sync + std::fmt::Debug {
    /// Checks the names it uses against the layout and draws its own random
    /// values (from its own stream), once before the first reading.
    fn prepare(&mut self, _setup: &Setup) -> Result<(), String> {
        Ok(())
    }
    /// The SMR acceptance it imposes (degrees of incidence α).
    fn max_angle_deg(&self) -> Option<f64> {
        None
    }
    /// Step 1: the reflector's true centre moves by this (mm, campaign frame).
    fn reflector_shift_mm(&self, _at: &Place) -> Option<Vector3<f64>> {
        None
    }
    /// Step 2: the station's origin moves by this (mm, campaign frame),
    /// `since_station_s` after the station's first reading.
    fn station_shift_mm(&self, _at: &Place, _since_station_s: f64) -> Option<Vector3<f64>> {
        None
    }
    /// Whether a reading at these incidence angles is taken at all.
    fn takes(&self, _angles: &IncidenceAngles) -> bool {
        true
    }
    /// The air temperature it sets at `time_s` (°C).
    fn temperature_c(&self, _time_s: f64) -> Option<f64> {
        None
    }
    /// Step 4: a change of the distance (mm), summed over the effects.
    fn delta_d_mm(
        &self,
        _at: &Place,
        _reading: &Reading,
        _angles: &IncidenceAngles,
        _temperature_c: f64,
    ) -> Option<f64> {
        None
    }
    /// Step 4, after the distance changes are summed: changes of the angles.
    fn move_angles(&self, _reading: &mut Reading) {}
}

/// What the blind check draws for one effect: the effect, and the truth
/// the diagnosis is scored against.
pub struct Drawn<T> {
    pub effect: T,
    /// As the diagnosis names it: a station or reflector id, an axis, `all`.
    pub place: String,
    /// Comparable with the diagnosis's magnitude (same unit).
    pub magnitude: f64,
    /// Whether `place` is a single station, reflector or axis to be named.
    pub has_place: bool,
}

/// The layout an effect is drawn for.
pub struct DrawContext<'a> {
    /// Station ids in the measuring order.
    pub stations: &'a [String],
    pub targets: &'a [String],
    /// The effect's size as a multiple of the blind check's draw (1: as the
    /// blind check draws it; the open-world check's wrong-model cases draw
    /// larger effects). An effect without a free size (a fixed table)
    /// ignores it.
    pub size: f64,
}

/// One effect of the catalogue: everything ltcal knows about it.
pub trait Effect:
    Forward + Clone + PartialEq + Serialize + DeserializeOwned + Sized + 'static
{
    /// Its id in effects.md, TOML and tables.
    const ID: &'static str;
    /// One line for `ltcal kinds` and the docs.
    const SUMMARY: &'static str;
    const NEEDS: Needs = Needs::NOTHING;
    /// Drawn by the blind check only as the one effect of a case (a second
    /// model of an error another effect models, with nothing of its own to
    /// draw: `incidence-table9`).
    const ALONE: bool = false;

    /// Settings that cannot work, as `(field, message)` below its table.
    fn check(&self) -> Vec<(String, String)> {
        Vec::new()
    }
    /// Its parameters as `(where, parameter, value)` rows of a simulated
    /// campaign's `truth_effects` (after [`Forward::prepare`]): by default
    /// every number of its settings, `where` its `station` or `target`.
    fn truth(&self) -> Vec<(String, String, f64)> {
        flat_truth(&serde_json::to_value(self).unwrap_or_default())
    }
    /// Its candidate explanations for the diagnosis: signature columns on
    /// the readings (see [`crate::diagnose::candidates`]).
    fn candidates(cx: &Context, out: &mut Found);
    /// One effect at a random, realistic magnitude and place.
    fn draw(rng: &mut ChaCha8Rng, cx: &DrawContext) -> Drawn<Self>;
}

/// The default truth rows: numbers, and arrays as `.x`, `.y`, `.z`.
fn flat_truth(settings: &serde_json::Value) -> Vec<(String, String, f64)> {
    let place = settings
        .get("station")
        .or_else(|| settings.get("target"))
        .and_then(|v| v.as_str())
        .unwrap_or("all")
        .to_string();
    let mut rows = Vec::new();
    for (k, v) in settings.as_object().into_iter().flatten() {
        match v {
            serde_json::Value::Number(n) => {
                rows.push((place.clone(), k.clone(), n.as_f64().unwrap_or(f64::NAN)))
            }
            serde_json::Value::Array(a) => {
                for (i, x) in a.iter().enumerate() {
                    let axis = ["x", "y", "z"].get(i).copied().unwrap_or("?");
                    rows.push((
                        place.clone(),
                        format!("{k}.{axis}"),
                        x.as_f64().unwrap_or(f64::NAN),
                    ));
                }
            }
            _ => {}
        }
    }
    rows
}

/// `field` must be finite.
pub(crate) fn finite(out: &mut Vec<(String, String)>, field: &str, v: f64) {
    if !v.is_finite() {
        out.push((
            field.to_string(),
            format!("`{field}` must be finite, got {v}"),
        ));
    }
}

/// One entry of the registry: an effect's id, docs and static parts, so
/// that code iterating the catalogue needs no effect's type.
pub struct Kind {
    pub id: &'static str,
    pub summary: &'static str,
    pub needs: Needs,
    pub alone: bool,
    /// Its candidates, added to `out`.
    pub candidates: fn(&Context, &mut Found),
    /// Draws it into `fx`: the place, the magnitude, whether it has a place.
    pub draw: fn(&mut ChaCha8Rng, &DrawContext, &mut Effects) -> (String, f64, bool),
}

/// The catalogue: one line per effect (`"id" => field: file::Type`).
/// Declares the effect's module, and generates [`Effects`] (one optional
/// entry per effect, the id its TOML key, spans kept by serde), the
/// registry [`kinds`], and the iteration over the effects present.
macro_rules! catalogue {
    ($($(#[$attr:meta])* $id:literal => $field:ident: $module:ident::$ty:ident,)*) => {
        $(
            $(#[$attr])*
            mod $module;
            $(#[$attr])*
            pub use $module::$ty;
        )*

        /// The effects a simulated campaign carries (at most one of each,
        /// and any number of blunders).
        #[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
        #[serde(deny_unknown_fields)]
        pub struct Effects {
            /// effects.md's `noise` is given by the stage's own `noise`
            /// table (the same field names), not here: kept only to say so
            /// where it was written, rather than to call a known id an
            /// unknown field.
            #[serde(default, skip_serializing_if = "Option::is_none")]
            pub noise: Option<serde_json::Value>,
            $(
                $(#[$attr])*
                #[serde(default, rename = $id, skip_serializing_if = "Option::is_none")]
                pub $field: Option<$ty>,
            )*
            /// Any number of gross errors, each on one reading.
            #[serde(default, skip_serializing_if = "Vec::is_empty")]
            pub blunder: Vec<Blunder>,
            /// A researcher's hypotheses ([`crate::hypothesis`]), injected
            /// at their parameters' `value`s. Never written under
            /// `effects`: a stage sets them from its `hypotheses` file,
            /// whose content hash its cache key holds.
            #[serde(skip)]
            pub hypotheses: Injected,
        }

        /// Every effect of the catalogue, in its order.
        pub fn kinds() -> &'static [Kind] {
            static KINDS: LazyLock<Vec<Kind>> = LazyLock::new(|| {
                let mut v = Vec::new();
                $(
                    $(#[$attr])*
                    v.push(Kind {
                        id: <$ty as Effect>::ID,
                        summary: <$ty as Effect>::SUMMARY,
                        needs: <$ty as Effect>::NEEDS,
                        alone: <$ty as Effect>::ALONE,
                        candidates: <$ty as Effect>::candidates,
                        draw: |rng, cx, fx| {
                            let d = <$ty as Effect>::draw(rng, cx);
                            fx.$field = Some(d.effect);
                            (d.place, d.magnitude, d.has_place)
                        },
                    });
                )*
                v
            });
            &KINDS
        }

        impl Effects {
            /// The forward models of the effects present, in the
            /// catalogue's order, with their ids.
            pub fn present(&self) -> Vec<(&'static str, &dyn Forward)> {
                let mut v: Vec<(&'static str, &dyn Forward)> = Vec::new();
                $(
                    $(#[$attr])*
                    if let Some(e) = &self.$field {
                        v.push((<$ty as Effect>::ID, e));
                    }
                )*
                v
            }

            /// The same effects, each after [`Forward::prepare`]: names
            /// checked against the layout, random values drawn.
            pub fn prepared(&self, setup: &Setup) -> Result<Effects, String> {
                let mut out = self.clone();
                $(
                    $(#[$attr])*
                    if let Some(e) = &mut out.$field {
                        e.prepare(setup)?;
                    }
                )*
                Ok(out)
            }

            /// `self` with only the effect `id` (no blunder, no hypothesis).
            pub fn only(&self, id: &str) -> Effects {
                let mut one = Effects::default();
                $(
                    $(#[$attr])*
                    if id == <$ty as Effect>::ID {
                        one.$field = self.$field.clone();
                    }
                )*
                one
            }

            /// Every effect's settings problems, as `(field, message)`
            /// relative to `effects`.
            fn check_each(&self, out: &mut Vec<(String, String)>) {
                $(
                    $(#[$attr])*
                    if let Some(e) = &self.$field {
                        out.extend(
                            e.check()
                                .into_iter()
                                .map(|(f, m)| (format!("{}.{f}", <$ty as Effect>::ID), m)),
                        );
                    }
                )*
            }

            /// The `truth_effects` rows of the effects present, as
            /// `(effect, where, parameter, value)`, by effect id.
            pub fn truth(&self) -> Vec<(String, String, String, f64)> {
                let mut by_id: BTreeMap<&'static str, Vec<(String, String, f64)>> =
                    BTreeMap::new();
                $(
                    $(#[$attr])*
                    if let Some(e) = &self.$field {
                        by_id.insert(<$ty as Effect>::ID, e.truth());
                    }
                )*
                by_id
                    .into_iter()
                    .flat_map(|(id, rows)| {
                        rows.into_iter()
                            .map(move |(at, p, v)| (id.to_string(), at, p, v))
                    })
                    .collect()
            }
        }
    };
}

catalogue! {
    "incidence" => incidence: incidence::Incidence,
    "incidence-table9" => incidence_table9: incidence_table9::IncidenceTable9,
    "range-scale" => range_scale: range_scale::RangeScale,
    "air-refraction" => air_refraction: air_refraction::AirRefraction,
    "encoder-harmonic" => encoder_harmonic: encoder_harmonic::EncoderHarmonic,
    "station-drift" => station_drift: station_drift::StationDrift,
    "target-shift" => target_shift: target_shift::TargetShift,
    #[cfg(test)] "toy-range" => toy_range: toy::ToyRange,
}

/// The entry of `id`, if the catalogue has it.
pub fn kind(id: &str) -> Option<&'static Kind> {
    kinds().iter().find(|k| k.id == id)
}

/// The catalogue's ids joined for messages: `incidence, range-scale, …`.
pub fn ids_joined() -> String {
    kinds().iter().map(|k| k.id).collect::<Vec<_>>().join(", ")
}

/// Whether `name` is taken by effects.md: an effect of the catalogue,
/// `noise`, `blunder` or `none`.
pub fn is_reserved(name: &str) -> bool {
    kind(name).is_some() || matches!(name, "noise" | "blunder" | "none")
}

/// Hypotheses to inject; equal when they are the same list (a file's
/// content is compared through its hash, not here).
#[derive(Clone, Debug, Default)]
pub struct Injected(pub std::sync::Arc<Vec<crate::hypothesis::Hypothesis>>);

impl PartialEq for Injected {
    fn eq(&self, other: &Self) -> bool {
        std::sync::Arc::ptr_eq(&self.0, &other.0) || (self.0.is_empty() && other.0.is_empty())
    }
}

impl Effects {
    /// The ids of the effects present (a blunder once per blunder).
    pub fn ids(&self) -> Vec<&'static str> {
        let mut v: Vec<&'static str> = self.present().into_iter().map(|(id, _)| id).collect();
        v.extend(self.blunder.iter().map(|_| "blunder"));
        v
    }

    /// What the effects present need the readings to record.
    pub fn needs(&self) -> Needs {
        self.present()
            .into_iter()
            .filter_map(|(id, _)| kind(id))
            .fold(Needs::NOTHING, |n, k| Needs {
                time: n.time || k.needs.time,
                temperature: n.temperature || k.needs.temperature,
            })
    }

    /// Settings that cannot work, as `(field, message)` relative to `effects`.
    pub fn check(&self) -> Vec<(String, String)> {
        let mut out = Vec::new();
        if self.noise.is_some() {
            out.push((
                "noise".to_string(),
                "reading noise is the stage's `noise` table, not an entry of `effects`: \
                 write `noise = { sigma_angle_urad = …, sigma_range_um = …, sigma_range_ppm = … }` \
                 in the stage"
                    .to_string(),
            ));
        }
        self.check_each(&mut out);
        for (i, b) in self.blunder.iter().enumerate() {
            b.check(i, &mut out);
        }
        out
    }
}

/// The incidence geometry of one reading (effects.md, `incidence`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IncidenceAngles {
    /// `acos(r·n)`.
    pub alpha: f64,
    pub alpha_h: f64,
    pub alpha_v: f64,
}

/// `n`: unit SMR axis (centre → aim point); `r`: unit vector from the
/// reflector's centre to the tracker. `h = normalize(ẑ × n)` (`x̂` if `n` is
/// vertical), `v = n × h`.
pub fn incidence_angles(n: &Vector3<f64>, r: &Vector3<f64>) -> IncidenceAngles {
    let z = Vector3::z();
    let c = z.cross(n);
    let h = if c.norm() < 1e-12 {
        Vector3::x()
    } else {
        c.normalize()
    };
    let v = n.cross(&h);
    let rn = r.dot(n);
    IncidenceAngles {
        alpha: rn.clamp(-1.0, 1.0).acos(),
        alpha_h: r.dot(&h).atan2(rn),
        alpha_v: r.dot(&v).atan2(rn),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn incidence_angles_by_hand() {
        // SMR facing +x; tracker up and to the side.
        let n = Vector3::x();
        let r = Vector3::new(1.0, 1.0, 1.0).normalize();
        let a = incidence_angles(&n, &r);
        // h = ẑ × x̂ = ŷ, v = x̂ × ŷ = ẑ.
        assert!((a.alpha - (1.0f64 / 3f64.sqrt()).acos()).abs() < 1e-15);
        assert!((a.alpha_h - std::f64::consts::FRAC_PI_4).abs() < 1e-15);
        assert!((a.alpha_v - std::f64::consts::FRAC_PI_4).abs() < 1e-15);
        // Vertical axis: h = x̂, v = ẑ × x̂ = ŷ.
        let a = incidence_angles(&Vector3::z(), &Vector3::new(0.0, 0.1, 1.0).normalize());
        assert!(a.alpha_h.abs() < 1e-15);
        assert!((a.alpha_v - 0.1f64.atan()).abs() < 1e-12, "{a:?}");
    }

    #[test]
    fn the_registry_holds_effects_md_in_its_order() {
        let ids: Vec<&str> = kinds().iter().map(|k| k.id).collect();
        assert_eq!(
            &ids[..7],
            [
                "incidence",
                "incidence-table9",
                "range-scale",
                "air-refraction",
                "encoder-harmonic",
                "station-drift",
                "target-shift"
            ]
        );
        assert!(is_reserved("noise") && is_reserved("blunder") && is_reserved("range-scale"));
        assert!(!is_reserved("adm-cyclic"));
        let needs = |id| kind(id).unwrap().needs;
        assert!(needs("station-drift").time && needs("air-refraction").temperature);
        assert!(!needs("range-scale").any());
        assert!(kind("incidence-table9").unwrap().alone && !kind("incidence").unwrap().alone);
    }
}
