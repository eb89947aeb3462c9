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

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct MeshStage {
    /// The mesh: `plane`, `cube` or `sphere` (Section 5.1).
    pub shape: Shape,
    /// Plane only: the plane's distance from the tracker, mm (the paper's by
    /// default).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x_mm: Option<f64>,
    /// Plane, cube: the x grid `{ from, to, step }`, mm (plane: along its
    /// width).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x: Option<Range>,
    /// Plane, cube: the y grid `{ from, to, step }`, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y: Option<Range>,
    /// Plane, cube: the z grid `{ from, to, step }`, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z: Option<Range>,
    /// Sphere: the azimuths `{ from, to, step }`, degrees.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub h_deg: Option<Range>,
    /// Sphere: the elevations `{ from, to, step }`, degrees.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub v_deg: Option<Range>,
    /// Sphere: the radii `{ from, to, step }`, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub r_mm: Option<Range>,
}

/// What a shape is built from, every default filled.
enum Geometry {
    Plane {
        x_mm: f64,
        y: Range,
        z: Range,
    },
    Cube {
        x: Range,
        y: Range,
        z: Range,
    },
    Sphere {
        h_deg: Range,
        v_deg: Range,
        r_mm: Range,
    },
}

impl MeshStage {
    /// The shape's ranges as written, the paper's mesh where not.
    fn geometry(&self) -> Geometry {
        let or = |r: &Option<Range>, d: Range| r.unwrap_or(d);
        match self.shape {
            Shape::Plane => Geometry::Plane {
                x_mm: self.x_mm.unwrap_or(mesh::PLANE_X_MM),
                y: or(&self.y, mesh::PLANE_Y),
                z: or(&self.z, mesh::PLANE_Z),
            },
            Shape::Cube => Geometry::Cube {
                x: or(&self.x, mesh::CUBE_AXIS),
                y: or(&self.y, mesh::CUBE_AXIS),
                z: or(&self.z, mesh::CUBE_AXIS),
            },
            Shape::Sphere => Geometry::Sphere {
                h_deg: or(&self.h_deg, mesh::SPHERE_H_DEG),
                v_deg: or(&self.v_deg, mesh::SPHERE_V_DEG),
                r_mm: or(&self.r_mm, mesh::SPHERE_R_MM),
            },
        }
    }

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

    /// Writes the shape's defaults into the settings, so that the cache
    /// key sees them: the same values [`MeshStage::geometry`] runs with.
    fn resolved(mut self) -> Self {
        match self.geometry() {
            Geometry::Plane { x_mm, y, z } => {
                self.x_mm = Some(x_mm);
                (self.y, self.z) = (Some(y), Some(z));
            }
            Geometry::Cube { x, y, z } => {
                (self.x, self.y, self.z) = (Some(x), Some(y), Some(z));
            }
            Geometry::Sphere { h_deg, v_deg, r_mm } => {
                (self.h_deg, self.v_deg, self.r_mm) = (Some(h_deg), Some(v_deg), Some(r_mm));
            }
        }
        self
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
        if out.is_empty() {
            let n = match self.geometry() {
                Geometry::Plane { y, z, .. } => mesh::grid_points(&[&y, &z]),
                Geometry::Cube { x, y, z } => mesh::grid_points(&[&x, &y, &z]),
                Geometry::Sphere { h_deg, v_deg, r_mm } => {
                    mesh::grid_points(&[&h_deg, &v_deg, &r_mm])
                }
            };
            if n > mesh::MAX_GRID_POINTS {
                out.push(Invalid::new(
                    used[used.len() - 1],
                    format!(
                        "the mesh has {n} points, more than the limit of {}: use fewer or coarser ranges",
                        mesh::MAX_GRID_POINTS
                    ),
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
        let points = match self.geometry() {
            Geometry::Plane { x_mm, y, z } => mesh::plane(x_mm, &y, &z),
            Geometry::Cube { x, y, z } => mesh::cube(&x, &y, &z),
            Geometry::Sphere { h_deg, v_deg, r_mm } => mesh::sphere(&h_deg, &v_deg, &r_mm),
        };
        Ok(StageOutput::default().table("points", schema::points_table(&points)?))
    }
}
