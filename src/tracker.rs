//! Which construction a tracker has, and so which kinematic model its readings
//! follow: the `[tracker] model` of a campaign (`campaign-format.md`) and the
//! `model` setting of every stage that simulates, fits or analyses a tracker.
//!
//! Two constructions exist. The paper's API Tracker 3 carries the laser in the
//! rotating head: its model is the Denavit–Hartenberg chain of Table 1 with an
//! error transform per joint ([`crate::error_model`], 18 parameters). A mirror
//! tracker keeps the laser in the fixed base and steers the beam with a mirror
//! on the transit axis: its model follows the beam path ([`crate::mirror`], 10
//! misalignments). Every parameter of ltcal belongs to exactly one model
//! ([`crate::error_model::ParamId::tracker`]), so a parameter set says by
//! itself which tracker it describes; this enum is the name users write.

use serde::{Deserialize, Deserializer, Serialize, Serializer};
use std::fmt;

/// A tracker construction, by the ids of `campaign-format.md`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum TrackerModel {
    /// The paper's tracker, the laser in the head (Table 1's chain).
    #[default]
    ApiTracker3,
    /// The laser in the base, a mirror on the transit axis.
    MirrorTracker,
}

impl TrackerModel {
    /// Every model ltcal knows, in the order tables list them.
    pub const ALL: [TrackerModel; 2] = [TrackerModel::ApiTracker3, TrackerModel::MirrorTracker];

    /// The id campaigns and pipelines write.
    pub fn id(self) -> &'static str {
        match self {
            TrackerModel::ApiTracker3 => "api-tracker3",
            TrackerModel::MirrorTracker => "mirror-tracker",
        }
    }

    /// The construction in words.
    pub fn describe(self) -> &'static str {
        match self {
            TrackerModel::ApiTracker3 => "laser in the head: the DH chain of Table 1",
            TrackerModel::MirrorTracker => {
                "laser in the base, steered by a mirror on the transit axis"
            }
        }
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
