//! The nominal kinematic model of the tracker: the Denavit–Hartenberg chain of
//! Table 1 (API Tracker 3) and the conversions between readings, joint values
//! and points.
//!
//! # One angle convention
//!
//! Everything outside this module speaks in **readings**: azimuth `az`,
//! elevation `el` (both in radians inside the library, degrees in tables and
//! files) and distance `d` in millimetres, with the point in the station frame
//!
//! ```text
//! x = d·cos(el)·cos(az),  y = d·cos(el)·sin(az),  z = d·sin(el)
//! ```
//!
//! exactly as `campaign-format.md` defines it (z up the standing axis). The DH
//! chain of Table 1 uses its own joint variables, `θ = az − 90°` and `φ = el`
//! (NOTES item 3); the conversion happens here and nowhere else. The paper's
//! Eq. (1)–(3) measure φ from the zenith and are not used.

use nalgebra::{Matrix3, Matrix4, Vector3};
use std::f64::consts::{FRAC_PI_2, PI};

/// Which face of the tracker took a reading. The back face turns the head 180°
/// in azimuth and flips the elevation axis: it reads `(az + 180°, 180° − el, d)`
/// for the same point.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Face {
    Front,
    Back,
}

impl Face {
    /// The number the campaign format uses (1 = front, 2 = back).
    pub fn number(self) -> i64 {
        match self {
            Face::Front => 1,
            Face::Back => 2,
        }
    }

    pub fn from_number(n: i64) -> Option<Face> {
        match n {
            1 => Some(Face::Front),
            2 => Some(Face::Back),
            _ => None,
        }
    }
}

/// A tracker reading: azimuth and elevation in radians, distance in mm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Reading {
    pub az: f64,
    pub el: f64,
    pub d: f64,
}

/// The joint variables of the DH chain of Table 1: θ and φ in radians, d in mm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Joints {
    pub theta: f64,
    pub phi: f64,
    pub d: f64,
}

impl Reading {
    /// Table 1 / NOTES item 3: `θ = az − 90°`, `φ = el`.
    pub fn joints(self) -> Joints {
        Joints {
            theta: self.az - FRAC_PI_2,
            phi: self.el,
            d: self.d,
        }
    }

    /// The face a reading was taken in, from its elevation: the back face reads
    /// elevations beyond the zenith, `el ∈ (90°, 270°]`.
    pub fn face(self) -> Face {
        if self.el > FRAC_PI_2 {
            Face::Back
        } else {
            Face::Front
        }
    }

    /// The same reading with the azimuth wrapped into (−180°, 180°].
    pub fn wrapped(self) -> Reading {
        Reading {
            az: wrap_angle(self.az),
            ..self
        }
    }
}

impl Joints {
    pub fn reading(self) -> Reading {
        Reading {
            az: self.theta + FRAC_PI_2,
            el: self.phi,
            d: self.d,
        }
    }
}

/// Wraps an angle into (−π, π].
pub fn wrap_angle(a: f64) -> f64 {
    let mut w = a.rem_euclid(2.0 * PI);
    if w > PI {
        w -= 2.0 * PI;
    }
    w
}

/// One row of a Denavit–Hartenberg table: `α` and the offset added to the
/// joint angle in radians, `a` and the fixed part of `d` in mm.
#[derive(Clone, Copy, Debug)]
pub struct DhRow {
    pub alpha: f64,
    pub a: f64,
    pub d: f64,
    pub theta_offset: f64,
}

/// Table 1: the API Tracker 3. Joint 1 turns by θ, joint 2 by φ, joint 3 is
/// the beam of length d.
pub const API_TRACKER3: [DhRow; 3] = [
    DhRow {
        alpha: -FRAC_PI_2,
        a: 0.0,
        d: 0.0,
        theta_offset: -FRAC_PI_2,
    },
    DhRow {
        alpha: FRAC_PI_2,
        a: 0.0,
        d: 0.0,
        theta_offset: -FRAC_PI_2,
    },
    DhRow {
        alpha: 0.0,
        a: 0.0,
        d: 0.0,
        theta_offset: -FRAC_PI_2,
    },
];

/// Eq. (4) (as restored in NOTES item 2): `A = T_z(d)·R_z(θ)·T_x(a)·R_x(α)`.
pub fn dh_transform(theta: f64, d: f64, a: f64, alpha: f64) -> Matrix4<f64> {
    let (st, ct) = theta.sin_cos();
    let (sa, ca) = alpha.sin_cos();
    Matrix4::new(
        ct,
        -st * ca,
        st * sa,
        a * ct,
        st,
        ct * ca,
        -ct * sa,
        a * st,
        0.0,
        sa,
        ca,
        d,
        0.0,
        0.0,
        0.0,
        1.0,
    )
}

/// The three link transforms `0A1, 1A2, 2A3` of Table 1 at the given joints.
pub fn link_transforms(q: Joints) -> [Matrix4<f64>; 3] {
    let t = API_TRACKER3;
    [
        dh_transform(q.theta + t[0].theta_offset, t[0].d, t[0].a, t[0].alpha),
        dh_transform(q.phi + t[1].theta_offset, t[1].d, t[1].a, t[1].alpha),
        dh_transform(t[2].theta_offset, t[2].d + q.d, t[2].a, t[2].alpha),
    ]
}

/// The rotation part of `0A1`, `R_z(θ − 90°)·R_x(−90°)`, in closed form.
pub fn link1_rotation(theta: f64) -> Matrix3<f64> {
    let (s, c) = theta.sin_cos();
    // Columns: R_z(θ−90°) applied to x̂, R_x(−90°)ŷ = −ẑ, R_x(−90°)ẑ = ŷ.
    Matrix3::new(s, 0.0, c, -c, 0.0, s, 0.0, -1.0, 0.0)
}

/// The rotation part of `1A2`, `R_z(φ − 90°)·R_x(90°)`, in closed form.
pub fn link2_rotation(phi: f64) -> Matrix3<f64> {
    let (s, c) = phi.sin_cos();
    Matrix3::new(s, 0.0, -c, -c, 0.0, -s, 0.0, 1.0, 0.0)
}

/// Eq. (5) without errors: the reflector centre in the station frame.
pub fn nominal_point(r: Reading) -> Vector3<f64> {
    let (se, ce) = r.el.sin_cos();
    let (sa, ca) = r.az.sin_cos();
    Vector3::new(r.d * ce * ca, r.d * ce * sa, r.d * se)
}

/// The reading a perfect tracker takes of `p` in the given face.
pub fn nominal_reading(p: &Vector3<f64>, face: Face) -> Reading {
    let d = p.norm();
    let az = p.y.atan2(p.x);
    let el = (p.z / d).clamp(-1.0, 1.0).asin();
    match face {
        Face::Front => Reading { az, el, d },
        Face::Back => Reading {
            az: wrap_angle(az + PI),
            el: PI - el,
            d,
        },
    }
}

/// Newton steps of a tracker's inverse.
const MAX_INVERSE_ITERS: usize = 50;
/// The round trip holds to 1e-9 mm; ask for more where rounding allows.
const INVERSE_TOL_MM: f64 = 1e-11;
const INVERSE_MAX_MISS_MM: f64 = 1e-9;

/// Section 5.1, measuring, for any tracker model: the reading whose point
/// (`point`, the model's forward kinematics with its errors) is `target`,
/// by Newton iteration from the nominal reading. The nominal Jacobian
/// differs from the true one by the errors (≈1e-5), so each step gains about
/// five digits.
pub fn invert(
    target: &Vector3<f64>,
    face: Face,
    point: impl Fn(Reading) -> Vector3<f64>,
) -> Result<Reading, InverseError> {
    let mut r = nominal_reading(target, face);
    let mut last = f64::INFINITY;
    for _ in 0..MAX_INVERSE_ITERS {
        let miss = point(r) - target;
        let m = miss.norm();
        // Converged, or down to the rounding noise of coordinates of this
        // size (which can sit just above the target tolerance).
        if m <= INVERSE_TOL_MM || (m >= last && m <= INVERSE_MAX_MISS_MM) {
            return Ok(r);
        }
        last = m;
        let step = nominal_jacobian(r)
            .lu()
            .solve(&miss)
            .ok_or(InverseError::Singular)?;
        r.az -= step.x;
        r.el -= step.y;
        r.d -= step.z;
    }
    Err(InverseError::NoConvergence)
}

/// Why a tracker cannot take a reading of a target.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum InverseError {
    #[error("the target is on the standing axis or at the station: no unique reading")]
    Singular,
    #[error("the inverse of the error model did not converge (errors too large?)")]
    NoConvergence,
}

/// `∂p/∂(az, el, d)` of [`nominal_point`], columns in that order.
pub fn nominal_jacobian(r: Reading) -> Matrix3<f64> {
    let (se, ce) = r.el.sin_cos();
    let (sa, ca) = r.az.sin_cos();
    Matrix3::new(
        -r.d * ce * sa,
        -r.d * se * ca,
        ce * ca,
        r.d * ce * ca,
        -r.d * se * sa,
        ce * sa,
        0.0,
        r.d * ce,
        se,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    fn chain_point(q: Joints) -> Vector3<f64> {
        let [a1, a2, a3] = link_transforms(q);
        let t = a1 * a2 * a3;
        Vector3::new(t[(0, 3)], t[(1, 3)], t[(2, 3)])
    }

    #[test]
    fn table1_chain_matches_notes_item_3() {
        for &(th, ph, d) in &[(0.3, 0.2, 1000.0), (-2.0, -0.9, 12000.0), (3.0, 1.2, 50.0)] {
            let p = chain_point(Joints {
                theta: th,
                phi: ph,
                d,
            });
            let expect = Vector3::new(
                -d * th.sin() * ph.cos(),
                d * th.cos() * ph.cos(),
                d * ph.sin(),
            );
            assert!((p - expect).norm() < 1e-9, "{p} vs {expect}");
        }
    }

    #[test]
    fn chain_agrees_with_reading_convention() {
        let r = Reading {
            az: 0.7,
            el: -0.4,
            d: 5432.1,
        };
        assert!((chain_point(r.joints()) - nominal_point(r)).norm() < 1e-9);
    }

    #[test]
    fn closed_form_link_rotations_match_dh() {
        for a in [-2.5, -0.3, 0.0, 1.1, 3.0] {
            let [a1, a2, _] = link_transforms(Joints {
                theta: a,
                phi: a,
                d: 1.0,
            });
            assert!((a1.fixed_view::<3, 3>(0, 0) - link1_rotation(a)).norm() < 1e-14);
            assert!((a2.fixed_view::<3, 3>(0, 0) - link2_rotation(a)).norm() < 1e-14);
        }
    }

    #[test]
    fn back_face_reads_the_same_point() {
        let p = Vector3::new(1200.0, -3400.0, 800.0);
        for face in [Face::Front, Face::Back] {
            let r = nominal_reading(&p, face);
            assert_eq!(r.face(), face);
            assert!((nominal_point(r) - p).norm() < 1e-9);
        }
        let f = nominal_reading(&p, Face::Front);
        let b = nominal_reading(&p, Face::Back);
        assert!(
            close(wrap_angle(b.az - f.az), PI, 1e-12) || close(wrap_angle(b.az - f.az), -PI, 1e-12)
        );
        assert!(close(b.el, PI - f.el, 1e-12));
    }

    #[test]
    fn nominal_jacobian_matches_finite_differences() {
        let r = Reading {
            az: 0.4,
            el: 0.3,
            d: 3000.0,
        };
        let j = nominal_jacobian(r);
        let h = 1e-7;
        let bump = |k: usize| {
            let mut a = r;
            match k {
                0 => a.az += h,
                1 => a.el += h,
                _ => a.d += h,
            }
            (nominal_point(a) - nominal_point(r)) / h
        };
        for k in 0..3 {
            let col = bump(k);
            assert!((col - j.column(k)).norm() < 1e-3 * (1.0 + col.norm()));
        }
    }
}
