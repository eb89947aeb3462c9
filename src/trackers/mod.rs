//! The tracker models, each a plug-in: one file holds everything ltcal
//! knows about a construction, and the registry is the one list of
//! [`registry!`] below.
//!
//! Why plug-ins: a model is used wherever a tracker is simulated, fitted or
//! analysed — its parameters name coefficients in tables and TOML, its
//! forward model and derivatives drive identification, the bundle
//! adjustment and the diagnosis, its inverse simulates readings, and the
//! B89 stage, the sensitivity analysis and the model comparison ask it
//! model-specific questions. When each of those matched the model, adding a
//! construction meant editing all of them; now a model's file implements
//! [`Model`] and code outside this folder iterates [`TrackerModel::ALL`] or
//! asks a [`TrackerModel`] handle. ARCHITECTURE.md has the recipe.
//!
//! Two constructions ship. The paper's API Tracker 3 carries the laser in
//! the rotating head: its model is the Denavit–Hartenberg chain of Table 1
//! with an error transform per joint ([`crate::error_model`], 18
//! parameters). A mirror tracker keeps the laser in the fixed base and
//! steers the beam with a mirror on the transit axis: its model follows the
//! beam path (`mirror_tracker.rs`, 10 misalignments). Every parameter of
//! ltcal belongs to exactly one model
//! ([`crate::error_model::ParamId::tracker`]), so a parameter set says by
//! itself which tracker it describes; a model's id is the name users write
//! (`[tracker] model` of `campaign-format.md`, the `model` of every stage).

use crate::error_model::{Coef, ErrorModel, ErrorParams, Joint, Links};
use crate::kinematics::Joints;
use nalgebra::Vector3;
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use std::fmt;
use std::sync::LazyLock;

/// One parameter of a model, in display units.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Param {
    /// The ASCII id in TOML and tables (`dx1`, `transit_tilt`).
    pub id: &'static str,
    /// The paper's symbol (`δx1`); the id where the paper has none.
    pub symbol: &'static str,
    /// An angle (µrad) rather than a length (µm).
    pub angular: bool,
    /// What it is, in words.
    pub meaning: &'static str,
    /// The joint whose variable its shape may follow (Eq. 9 and 10). Shapes
    /// are the DH chain's: every other model's parameters are constants
    /// (`None`).
    pub joint: Option<Joint>,
}

/// A misalignment the B89 stage reports on, as a direction in the model's
/// coefficients: `sign` times one coefficient.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Misalignment {
    pub id: &'static str,
    pub unit: &'static str,
    pub meaning: &'static str,
    pub coef: Coef,
    pub sign: f64,
}

/// A model's forward model for one parameter set, with what does not depend
/// on the joints built once ([`Model::evaluate`]).
pub trait Evaluate: Send + Sync {
    /// The point the tracker reaches at joints `q` whose DH link rotations
    /// are `links` (models other than the DH chain ignore them).
    fn point(&self, q: Joints, links: &Links) -> Vector3<f64>;
    /// The point, and in `jac` (empty on entry) `∂P/∂value` for every
    /// coefficient of the set, mm per display unit, in the set's order.
    fn point_with_jacobian(
        &self,
        q: Joints,
        links: &Links,
        jac: &mut Vec<Vector3<f64>>,
    ) -> Vector3<f64>;
}

/// One tracker construction: everything ltcal knows about it. The inverse
/// (the reading a tracker takes of a point) needs nothing of the model but
/// its forward model ([`crate::error_model::Evaluator::reading_of`]).
///
/// Some questions are the DH chain's alone, and every other model answers
/// "not applicable" through the default: shapes (a parameter's
/// [`Param::joint`]), [`Model::b89_model`], [`Model::coefficient_rows`] and
/// [`Model::section6`].
pub trait Model: Sync {
    /// The id campaigns and pipelines write.
    fn id(&self) -> &'static str;
    /// The construction in words.
    fn describe(&self) -> &'static str;
    /// Its parameters, in table order.
    fn params(&self) -> &'static [Param];
    /// Its forward model and derivatives for `params` (a set of this model).
    fn evaluate<'a>(&self, params: &'a ErrorParams) -> Box<dyn Evaluate + 'a>;
    /// The misalignments the B89 stage reports and accepts, each a
    /// direction in the coefficients of [`Model::b89_model`]. By default a
    /// model's parameters are its misalignments, each a constant.
    fn misalignments(&self) -> Vec<Misalignment> {
        self.params()
            .iter()
            .map(|p| Misalignment {
                id: p.id,
                unit: if p.angular { "µrad" } else { "µm" },
                meaning: p.meaning,
                coef: Coef::parse(p.id).expect("a parameter is a coefficient"),
                sign: 1.0,
            })
            .collect()
    }
    /// The coefficients and values of misalignment settings `(id, value)`,
    /// every other coefficient zero; `Err(id)` names the first unknown one.
    /// By default each id is one of the model's parameters.
    fn misaligned(&self, given: &[(&str, f64)]) -> Result<Vec<(Coef, f64)>, String> {
        given
            .iter()
            .map(|&(id, v)| {
                Coef::parse(id)
                    .filter(|c| c.param.tracker().id() == self.id())
                    .map(|c| (c, v))
                    .ok_or_else(|| id.to_string())
            })
            .collect()
    }
    /// The B89 stage's coefficients when they are not every parameter as a
    /// constant (`None`): the DH chain's harmonics, which its physical
    /// misalignments need.
    fn b89_model(&self) -> Option<ErrorModel> {
        None
    }
    /// Whether the B89 stage may report its coefficients themselves
    /// (`parameters = "dh"`): the DH chain's alone.
    fn coefficient_rows(&self) -> bool {
        false
    }
    /// Section 6's statement of how parameter `param` (`params()[param]`)
    /// varies (NOTES item 11): the paper's tracker alone.
    fn section6(&self, _param: usize) -> Option<&'static str> {
        None
    }
}

/// The registry: one line per model (`file::Type`), in the order tables
/// list them; the first is the default, the paper's. Declares the model's
/// module and lists it; a `#[cfg(test)]` line adds a model to unit tests
/// only, and must come last so the shipped models keep their places.
macro_rules! registry {
    ($($(#[$attr:meta])* $module:ident::$ty:ident,)*) => {
        $(
            $(#[$attr])*
            mod $module;
        )*

        /// The models, in registry order.
        static MODELS: &[&dyn Model] = &[$($(#[$attr])* &$module::$ty,)*];
        const COUNT: usize = [$($(#[$attr])* stringify!($ty),)*].len();
    };
}

registry! {
    api_tracker3::ApiTracker3,
    mirror_tracker::MirrorTracker,
    #[cfg(test)] ideal_sphere::IdealSphere,
}

/// A tracker model: a handle on its place in the registry, so that it is
/// `Copy`, compares and orders by that place, and serialises as its id.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct TrackerModel(u8);

/// Where each model's parameters sit in the shared coefficient space of
/// [`crate::error_model::ParamId`]: in registry order, one after another.
struct Space {
    /// The first parameter of each model.
    first: Vec<usize>,
    /// Each parameter's model and place in its model's table.
    owner: Vec<(TrackerModel, usize)>,
}

static SPACE: LazyLock<Space> = LazyLock::new(|| {
    let mut first = Vec::new();
    let mut owner = Vec::new();
    for m in TrackerModel::ALL {
        first.push(owner.len());
        owner.extend((0..m.params().len()).map(|k| (m, k)));
    }
    Space { first, owner }
});

/// Parameters of every model together.
pub(crate) fn n_params() -> usize {
    SPACE.owner.len()
}

/// The model and the place in its table of parameter `i` of the shared space.
pub(crate) fn owner(i: usize) -> (TrackerModel, usize) {
    SPACE.owner[i]
}

impl TrackerModel {
    /// Every model ltcal knows, in the order tables list them.
    pub const ALL: [TrackerModel; COUNT] = {
        let mut all = [TrackerModel(0); COUNT];
        let mut i = 0;
        while i < COUNT {
            all[i] = TrackerModel(i as u8);
            i += 1;
        }
        all
    };

    /// Its plug-in.
    pub fn plugin(self) -> &'static dyn Model {
        MODELS[self.0 as usize]
    }

    /// The id campaigns and pipelines write.
    pub fn id(self) -> &'static str {
        self.plugin().id()
    }

    /// The construction in words.
    pub fn describe(self) -> &'static str {
        self.plugin().describe()
    }

    /// Its parameters, in table order.
    pub fn params(self) -> &'static [Param] {
        self.plugin().params()
    }

    /// Where its parameters start in the shared coefficient space.
    pub(crate) fn first_param(self) -> usize {
        SPACE.first[self.0 as usize]
    }

    /// The coefficients the B89 stage works in: [`Model::b89_model`], or
    /// every parameter a constant.
    pub fn b89_model(self) -> ErrorModel {
        self.plugin()
            .b89_model()
            .unwrap_or_else(|| ErrorModel::of(self))
    }

    pub fn parse(s: &str) -> Option<TrackerModel> {
        TrackerModel::ALL.into_iter().find(|m| m.id() == s.trim())
    }

    /// The known ids, for error messages: `"api-tracker3" or "mirror-tracker"`.
    pub fn expected() -> String {
        let ids: Vec<String> = TrackerModel::ALL
            .iter()
            .map(|m| format!("\"{}\"", m.id()))
            .collect();
        ids.join(" or ")
    }
}

impl fmt::Display for TrackerModel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.id())
    }
}

impl Serialize for TrackerModel {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.id())
    }
}

impl<'de> Deserialize<'de> for TrackerModel {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        TrackerModel::parse(&s).ok_or_else(|| {
            serde::de::Error::custom(format!(
                "unknown tracker model `{s}`; expected {}",
                TrackerModel::expected()
            ))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_round_trip_and_unknown_ids_are_refused() {
        for m in TrackerModel::ALL {
            assert_eq!(TrackerModel::parse(m.id()), Some(m));
        }
        assert_eq!(TrackerModel::parse("leica-at960"), None);
        let e = toml::from_str::<std::collections::BTreeMap<String, TrackerModel>>(
            "model = \"leica-at960\"",
        )
        .unwrap_err();
        assert!(
            e.to_string()
                .contains("expected \"api-tracker3\" or \"mirror-tracker\"")
        );
    }
}
