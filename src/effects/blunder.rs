//! `blunder` (effects.md version 2) — a gross error on one reading. Not a
//! model to fit but an outlier to find: the diagnosis tests each reading
//! (Baarda's w-test) rather than a candidate's columns, so a blunder is not
//! an [`super::Effect`] of the catalogue; any number of them is applied
//! last, after the noise.

use crate::kinematics::Reading;
use serde::{Deserialize, Serialize};

/// The coordinate of a reading a blunder moves.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Coordinate {
    Az,
    El,
    D,
}

fn face_one() -> u8 {
    1
}

/// One reading off by a gross amount in one coordinate:
/// `Δaz = size_urad·1e-6`, `Δel = size_urad·1e-6` or `Δd = size_um·1e-3`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Blunder {
    pub station: String,
    pub target: String,
    /// 1 (front) or 2 (back).
    #[serde(default = "face_one")]
    pub face: u8,
    pub coordinate: Coordinate,
    /// For `coordinate = "az"` or `"el"`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub size_urad: Option<f64>,
    /// For `coordinate = "d"`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub size_um: Option<f64>,
}

impl Blunder {
    /// effects.md's name for the reading: `station/target/face`.
    pub fn place(&self) -> String {
        format!("{}/{}/{}", self.station, self.target, self.face)
    }

    /// The reading moved by the blunder.
    pub fn apply(&self, mut r: Reading) -> Reading {
        let (angle, range) = (self.size_urad.unwrap_or(0.0), self.size_um.unwrap_or(0.0));
        match self.coordinate {
            Coordinate::Az => r.az += angle * 1e-6,
            Coordinate::El => r.el += angle * 1e-6,
            Coordinate::D => r.d += range * 1e-3,
        }
        r
    }

    /// What is wrong with it, as `(field, message)` below `blunder[i]`.
    pub(super) fn check(&self, i: usize, out: &mut Vec<(String, String)>) {
        let at = |f: &str| format!("blunder[{i}].{f}");
        if !(self.face == 1 || self.face == 2) {
            out.push((
                at("face"),
                format!("`face` must be 1 or 2, got {}", self.face),
            ));
        }
        let (wanted, other) = match self.coordinate {
            Coordinate::Az | Coordinate::El => {
                (("size_urad", self.size_urad), ("size_um", self.size_um))
            }
            Coordinate::D => (("size_um", self.size_um), ("size_urad", self.size_urad)),
        };
        match wanted.1 {
            None => out.push((
                at(wanted.0),
                format!("a blunder in this coordinate needs `{}`", wanted.0),
            )),
            Some(v) if !v.is_finite() => out.push((
                at(wanted.0),
                format!("`{}` must be finite, got {v}", wanted.0),
            )),
            Some(_) => {}
        }
        if other.1.is_some() {
            out.push((
                at(other.0),
                format!(
                    "`{}` does not apply to this coordinate (use `{}`)",
                    other.0, wanted.0
                ),
            ));
        }
    }
}
