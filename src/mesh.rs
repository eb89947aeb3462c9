//! Meshes of synthetic reflectors (Section 5.1): the paper's plane, cube and
//! sphere, with the dimensions restored in NOTES item 7 as defaults.
//!
//! Points are in the station frame of the reading convention (mm); the sphere's
//! `H` is the azimuth and `V` the elevation of that convention.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// `from`, `from + step`, … up to and including `to` (within 1e-9 of a step).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Range {
    pub from: f64,
    pub to: f64,
    pub step: f64,
}

/// Most values a range may hold: a typo in a step should not allocate gigabytes.
pub const MAX_RANGE_VALUES: usize = 1_000_000;

/// Most points a grid of ranges (a mesh, a sensitivity sphere) may hold:
/// three ranges within [`MAX_RANGE_VALUES`] each would still make 10^18.
pub const MAX_GRID_POINTS: usize = 1_000_000;

/// The points of the grid of `ranges` (checked ranges), saturating.
pub fn grid_points(ranges: &[&Range]) -> usize {
    ranges
        .iter()
        .fold(1usize, |n, r| n.saturating_mul(r.count()))
}

impl Range {
    pub const fn new(from: f64, to: f64, step: f64) -> Range {
        Range { from, to, step }
    }

    /// Why this range cannot be used, naming the offending part.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        for (name, v) in [("from", self.from), ("to", self.to), ("step", self.step)] {
            if !v.is_finite() {
                return Err((name, format!("must be a finite number, got {v}")));
            }
        }
        if self.step == 0.0 {
            return Err(("step", "must not be zero".into()));
        }
        if (self.to - self.from) * self.step < 0.0 {
            return Err((
                "step",
                format!(
                    "goes the wrong way: from {} to {} needs a step of the other sign",
                    self.from, self.to
                ),
            ));
        }
        let n = ((self.to - self.from) / self.step).floor() + 1.0;
        if n > MAX_RANGE_VALUES as f64 {
            return Err((
                "step",
                format!("gives {n:.0} values, more than the limit of {MAX_RANGE_VALUES}"),
            ));
        }
        Ok(())
    }

    /// How many values a checked range holds.
    pub fn count(&self) -> usize {
        ((self.to - self.from) / self.step + 1e-9).floor() as usize + 1
    }

    /// The values of a checked range.
    pub fn values(&self) -> Vec<f64> {
        (0..self.count())
            .map(|i| self.from + i as f64 * self.step)
            .collect()
    }
}

/// A mesh point with its id.
#[derive(Clone, Debug, PartialEq)]
pub struct MeshPoint {
    pub id: String,
    pub p: Vector3<f64>,
}

/// Plane YZ mesh: `x` fixed, a grid in y and z (Figure 6: 15 × 14 = 210).
pub fn plane(x_mm: f64, y: &Range, z: &Range) -> Vec<MeshPoint> {
    let mut out = Vec::new();
    for &yv in &y.values() {
        for &zv in &z.values() {
            out.push(Vector3::new(x_mm, yv, zv));
        }
    }
    with_ids("P", out)
}

/// Cubic XYZ mesh (Figure 7: 6 × 6 × 6 = 216).
pub fn cube(x: &Range, y: &Range, z: &Range) -> Vec<MeshPoint> {
    let mut out = Vec::new();
    for &xv in &x.values() {
        for &yv in &y.values() {
            for &zv in &z.values() {
                out.push(Vector3::new(xv, yv, zv));
            }
        }
    }
    with_ids("C", out)
}

/// Spherical HVR mesh (Figure 8: 12 × 8 × 5 = 480); angles in degrees.
pub fn sphere(h_deg: &Range, v_deg: &Range, r_mm: &Range) -> Vec<MeshPoint> {
    let mut out = Vec::new();
    for &h in &h_deg.values() {
        for &v in &v_deg.values() {
            for &r in &r_mm.values() {
                let (h, v) = (h.to_radians(), v.to_radians());
                out.push(Vector3::new(
                    r * v.cos() * h.cos(),
                    r * v.cos() * h.sin(),
                    r * v.sin(),
                ));
            }
        }
    }
    with_ids("S", out)
}

fn with_ids(prefix: &str, pts: Vec<Vector3<f64>>) -> Vec<MeshPoint> {
    let width = pts.len().to_string().len().max(3);
    pts.into_iter()
        .enumerate()
        .map(|(i, p)| MeshPoint {
            id: format!("{prefix}{:0width$}", i + 1),
            p,
        })
        .collect()
}

/// NOTES item 7: the plane at X = 5000 mm.
pub const PLANE_X_MM: f64 = 5000.0;
pub const PLANE_Y: Range = Range::new(-10000.0, 9880.0, 1420.0);
pub const PLANE_Z: Range = Range::new(-1500.0, 5000.0, 500.0);
pub const CUBE_AXIS: Range = Range::new(-10000.0, 10000.0, 4000.0);
pub const SPHERE_H_DEG: Range = Range::new(0.0, 363.0, 33.0);
pub const SPHERE_V_DEG: Range = Range::new(77.0, -63.0, -20.0);
pub const SPHERE_R_MM: Range = Range::new(1000.0, 15000.0, 3500.0);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_meshes_have_the_paper_counts() {
        assert_eq!(plane(PLANE_X_MM, &PLANE_Y, &PLANE_Z).len(), 210);
        assert_eq!(cube(&CUBE_AXIS, &CUBE_AXIS, &CUBE_AXIS).len(), 216);
        assert_eq!(
            sphere(&SPHERE_H_DEG, &SPHERE_V_DEG, &SPHERE_R_MM).len(),
            480
        );
        assert_eq!(PLANE_Y.values().last(), Some(&9880.0));
        assert_eq!(SPHERE_V_DEG.values().last(), Some(&-63.0));
    }

    #[test]
    fn bad_ranges_name_the_field() {
        assert_eq!(Range::new(0.0, 1.0, 0.0).check().unwrap_err().0, "step");
        assert_eq!(Range::new(0.0, 1.0, -1.0).check().unwrap_err().0, "step");
        assert_eq!(
            Range::new(f64::NAN, 1.0, 1.0).check().unwrap_err().0,
            "from"
        );
        assert!(Range::new(0.0, 1e9, 1e-3).check().is_err());
        assert!(Range::new(5.0, 5.0, 1.0).check().is_ok());
    }
}
