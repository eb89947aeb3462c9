//! Sensitivity of the measured point to each error parameter (Section 6):
//! the error field over a mesh with one parameter at 1 µm or 1 µrad, and
//! which of θ, φ and d that error varies with.

use crate::error_model::{ErrorModel, ErrorParams, InverseError, ParamId};
use crate::kinematics::{Face, Reading, nominal_point, nominal_reading};
use nalgebra::Vector3;

/// The error a single parameter produces at one point.
#[derive(Clone, Copy, Debug)]
pub struct FieldPoint {
    /// The true point's nominal reading: where on the mesh it lies.
    pub at: Reading,
    pub error: Vector3<f64>,
}

impl FieldPoint {
    pub fn magnitude_um(&self) -> f64 {
        self.error.norm() * 1e3
    }
}

/// The measurement error over `points` of a tracker whose only error is
/// parameter `p` at `value` (µm or µrad): reported minus true position.
pub fn error_field(
    p: ParamId,
    value: f64,
    points: &[Vector3<f64>],
) -> Result<Vec<FieldPoint>, InverseError> {
    let mut e = ErrorParams::zero(&ErrorModel::constant());
    e.values_mut()[p.index()] = value;
    points
        .iter()
        .map(|x| {
            let r = e.reading_of(x, Face::Front)?;
            Ok(FieldPoint {
                at: nominal_reading(x, Face::Front),
                error: nominal_point(r) - x,
            })
        })
        .collect()
}

/// Which joint coordinates an error field varies with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Classification {
    pub produces_error: bool,
    pub theta: bool,
    pub phi: bool,
    pub d: bool,
}

impl Classification {
    /// In the paper's words: "constant", "θ, φ, d", "none".
    pub fn describe(&self) -> String {
        if !self.produces_error {
            return "no error".into();
        }
        let v: Vec<&str> = [(self.theta, "θ"), (self.phi, "φ"), (self.d, "d")]
            .iter()
            .filter(|x| x.0)
            .map(|x| x.1)
            .collect();
        if v.is_empty() {
            "constant".into()
        } else {
            format!("varies with {}", v.join(", "))
        }
    }
}

/// Classifies an error field on a grid mesh: it varies with a coordinate
/// when two points equal in the other two coordinates differ in error
/// magnitude by more than `rel_tol` of the largest error.
pub fn classify(field: &[FieldPoint], rel_tol: f64) -> Classification {
    let rows: Vec<([f64; 3], f64)> = field
        .iter()
        .map(|f| ([f.at.az, f.at.el, f.at.d], f.magnitude_um()))
        .collect();
    let max = rows.iter().map(|r| r.1).fold(0.0, f64::max);
    // Varies with coordinate k: two points equal in the other two
    // coordinates whose errors differ.
    let varies = |k: usize| {
        rows.iter().any(|(a, ea)| {
            rows.iter().any(|(b, eb)| {
                (0..3).all(|j| j == k || (a[j] - b[j]).abs() < 1e-9)
                    && (ea - eb).abs() > rel_tol * max
            })
        })
    };
    // Below 1e-5 µm is the rounding floor of the exact inverse (1e-9 mm at
    // most); a 1 µm or 1 µrad parameter moves points by ~1 µm.
    let produces_error = max > 1e-5;
    Classification {
        produces_error,
        theta: produces_error && varies(0),
        phi: produces_error && varies(1),
        d: produces_error && varies(2),
    }
}

/// Section 6's statement for each parameter (NOTES item 11).
pub fn paper_statement(p: ParamId) -> &'static str {
    match p.id() {
        "ex1" | "ey1" | "ez1" => "varies with θ, φ, d",
        "ex2" | "ey2" => "varies with φ, d",
        "ez2" | "ex3" | "ey3" => "varies with d",
        "ez3" => "no error",
        _ => "constant",
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh;

    #[test]
    fn section6_classification() {
        let pts: Vec<Vector3<f64>> =
            mesh::sphere(&mesh::SPHERE_H_DEG, &mesh::SPHERE_V_DEG, &mesh::SPHERE_R_MM)
                .into_iter()
                .map(|m| m.p)
                .collect();
        for p in ParamId::all() {
            let field = error_field(p, 1.0, &pts).unwrap();
            let ours = classify(&field, 1e-6).describe();
            // The one difference from the paper: a rotation about the
            // vertical axis cannot vary with the azimuth.
            let expect = if p.id() == "ez1" {
                "varies with φ, d"
            } else {
                paper_statement(p)
            };
            assert_eq!(ours, expect, "parameter {}", p.id());
        }
    }
}
