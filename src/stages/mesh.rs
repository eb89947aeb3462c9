//! `mesh`: a mesh of synthetic reflectors (Section 5.1).
//!
//! ```toml
//! [stages.sphere]
//! kind = "mesh"
//! shape = "sphere"                       # "plane", "cube" or "sphere"
//! h_deg = { from = 0, to = 363, step = 33 }   # optional: the paper's by default
//! ```
//!
//! Defaults are the paper's meshes (NOTES item 7): plane `x_mm`, `y`, `z`;
//! cube `x`, `y`, `z`; sphere `h_deg` (azimuth), `v_deg` (elevation), `r_mm`.
//! Output `points`: `target`, `x_mm`, `y_mm`, `z_mm`.

use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput};
use crate::mesh::{self, Range};
use crate::schema;
use anyhow::Result;
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Shape {
    Plane,
    Cube,
    Sphere,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MeshStage {
    pub shape: Shape,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x: Option<Range>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y: Option<Range>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z: Option<Range>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub h_deg: Option<Range>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub v_deg: Option<Range>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub r_mm: Option<Range>,
}

impl MeshStage {
    /// The fields each shape reads.
    fn fields(&self) -> &'static [&'static str] {
        match self.shape {
            Shape::Plane => &["x_mm", "y", "z"],
            Shape::Cube => &["x", "y", "z"],
            Shape::Sphere => &["h_deg", "v_deg", "r_mm"],
        }
    }

    fn ranges(&self) -> [(&'static str, Option<&Range>); 6] {
        [
            ("x", self.x.as_ref()),
            ("y", self.y.as_ref()),
            ("z", self.z.as_ref()),
            ("h_deg", self.h_deg.as_ref()),
            ("v_deg", self.v_deg.as_ref()),
            ("r_mm", self.r_mm.as_ref()),
        ]
    }
}

impl StageKind for MeshStage {
    const KIND: &'static str = "mesh";
    const SUMMARY: &'static str =
        "a mesh of reflectors: the paper's plane, cube or sphere (Section 5.1) or your own ranges";
    const INPUTS: &'static [Slot] = &[];
    const OUTPUTS: &'static [&'static str] = &["points"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "points" => Some(&["target", "x_mm", "y_mm", "z_mm"]),
            _ => None,
        }
    }

    fn resolve(&mut self) {
        match self.shape {
            Shape::Plane => {
                self.x_mm.get_or_insert(mesh::PLANE_X_MM);
                self.y.get_or_insert(mesh::PLANE_Y);
                self.z.get_or_insert(mesh::PLANE_Z);
            }
            Shape::Cube => {
                self.x.get_or_insert(mesh::CUBE_AXIS);
                self.y.get_or_insert(mesh::CUBE_AXIS);
                self.z.get_or_insert(mesh::CUBE_AXIS);
            }
            Shape::Sphere => {
                self.h_deg.get_or_insert(mesh::SPHERE_H_DEG);
                self.v_deg.get_or_insert(mesh::SPHERE_V_DEG);
                self.r_mm.get_or_insert(mesh::SPHERE_R_MM);
            }
        }
    }

    fn validate(&self) -> Vec<Invalid> {
        let mut out = Vec::new();
        let used = self.fields();
        let shape = serde_json::to_value(self.shape).unwrap_or_default();
        let mut present: Vec<&str> = self
            .ranges()
            .iter()
            .filter(|(_, r)| r.is_some())
            .map(|(n, _)| *n)
            .collect();
        if self.x_mm.is_some() {
            present.push("x_mm");
        }
        for name in present {
            if !used.contains(&name) {
                out.push(Invalid::new(
                    name,
                    format!(
                        "`{name}` does not apply to shape = {shape}, which reads {}",
                        used.join(", ")
                    ),
                ));
            }
        }
        for (name, r) in self.ranges() {
            if let Some(Err((part, msg))) = r.map(Range::check) {
                out.push(Invalid::new(
                    format!("{name}.{part}"),
                    format!("`{name}.{part}` {msg}"),
                ));
            }
        }
        if let Some(x) = self.x_mm.filter(|x| !x.is_finite()) {
            out.push(Invalid::new(
                "x_mm",
                format!("`x_mm` must be finite, got {x}"),
            ));
        }
        if let Some(r) = self.r_mm.as_ref().filter(|r| r.from.min(r.to) <= 0.0) {
            out.push(Invalid::new(
                "r_mm.from",
                format!("`r_mm` must stay above zero, got {} … {}", r.from, r.to),
            ));
        }
        out
    }

    fn run(&self, _: &Context, _: &StageInputs) -> Result<StageOutput> {
        let (x, y, z) = (self.x.as_ref(), self.y.as_ref(), self.z.as_ref());
        let points = match self.shape {
            Shape::Plane => mesh::plane(self.x_mm.unwrap(), y.unwrap(), z.unwrap()),
            Shape::Cube => mesh::cube(x.unwrap(), y.unwrap(), z.unwrap()),
            Shape::Sphere => mesh::sphere(
                self.h_deg.as_ref().unwrap(),
                self.v_deg.as_ref().unwrap(),
                self.r_mm.as_ref().unwrap(),
            ),
        };
        Ok(StageOutput::default().table("points", schema::points_table(&points)?))
    }
}
