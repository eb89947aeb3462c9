//! The mirror-based tracker of the paper's Section 12: the laser source in
//! the fixed base, the beam sent up the standing axis and turned towards the
//! reflector by a mirror that rotates with the head and about the transit
//! (elevation) axis. Its kinematics follow the beam path; its errors are the
//! misalignments of that path, in the spirit of the NIST mirror-tracker
//! model (Muralikrishnan et al., 2009).
//!
//! # Nominal kinematics
//!
//! The head turns by the azimuth `az` about the standing axis (z); the
//! mirror turns about the transit axis (the head's `ŷ_h`, horizontal,
//! across the line of sight) by half the beam's elevation: its normal, in
//! the head frame `(x̂_h forward, ŷ_h, ẑ)`, is
//!
//! ```text
//! n_h = (cos β, 0, sin β),   β = el/2 − 45°
//! ```
//!
//! so that the beam coming up, `u = ẑ`, leaves along `r = u − 2(u·n)n`, the
//! direction of `(az, el)`. The interferometer counts the path from the
//! plane `z = 0` through the gimbal point: nominally zero up to the mirror
//! (at the origin), then `d` out to the reflector. With no misalignment a
//! reading is the spherical point of `kinematics` — the same reading
//! convention as every tracker in ltcal, front and back face alike (the
//! back face turns the head by 180° and the mirror through: the same plane
//! with its normal reversed).
//!
//! # Misalignments ([`MirrorErrors`], display units µm and µrad)
//!
//! | id | where | what |
//! | --- | --- | --- |
//! | `beam_offset_x`, `beam_offset_y` | base | the incoming beam's offset from the standing axis at `z = 0` |
//! | `beam_tilt_x`, `beam_tilt_y` | base | its tilt: `u ∝ (t_x, t_y, 1)` |
//! | `transit_offset` | head | the transit axis's offset from the standing axis, towards the beam (`x̂_h`) |
//! | `transit_tilt` | head | the transit axis turned about `x̂_h` |
//! | `mirror_offset` | mirror | the reflecting surface's offset from the transit axis, along its normal |
//! | `mirror_tilt` | mirror | its normal turned out of the plane square to the transit axis (`n_h` gains a `ŷ_h` part) |
//! | `vertical_index` | encoder | the beam's elevation above the reading's (the mirror turned by half of it) |
//! | `range_offset` | interferometer | R0: the path out exceeds the reading by it |
//!
//! The point a reading reaches is then exact geometry: the mirror plane
//! through the transit axis point `o = transit_offset·x̂_h`, offset along
//! its normal `n = R_z(az)·R_x(transit_tilt)·n_h(β, mirror_tilt)`; the beam
//! line `s₀ + t·u` meets it at `t*`; the path out is `d + R0 − t*` along
//! the reflected `r = u − 2(u·n)n` ([`MirrorTracker::point`]). The base
//! errors are fixed in the station frame while the mirror turns: they act
//! through the reflection, `δr = (I − 2nnᵀ)·δu`, an error no joint of the
//! head-laser DH chain carries — which is why a mirror tracker needs its own
//! model. The test of the model is an independent ray trace
//! (`tests::an_independent_ray_trace_agrees_to_a_nanometre`).

use crate::kinematics::Reading;
use nalgebra::{Rotation3, Vector3};

/// The misalignments of a mirror tracker, display units (µm, µrad).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MirrorErrors {
    pub beam_offset_x: f64,
    pub beam_offset_y: f64,
    pub beam_tilt_x: f64,
    pub beam_tilt_y: f64,
    pub transit_offset: f64,
    pub transit_tilt: f64,
    pub mirror_offset: f64,
    pub mirror_tilt: f64,
    pub vertical_index: f64,
    pub range_offset: f64,
}

/// The ids of [`MirrorErrors`]' fields, in order, with their units and
/// meanings.
pub const IDS: [(&str, &str, &str); 10] = [
    (
        "beam_offset_x",
        "µm",
        "incoming beam's offset from the standing axis, x",
    ),
    (
        "beam_offset_y",
        "µm",
        "incoming beam's offset from the standing axis, y",
    ),
    (
        "beam_tilt_x",
        "µrad",
        "incoming beam's tilt from the standing axis, x",
    ),
    (
        "beam_tilt_y",
        "µrad",
        "incoming beam's tilt from the standing axis, y",
    ),
    (
        "transit_offset",
        "µm",
        "transit axis offset from the standing axis, towards the beam",
    ),
    (
        "transit_tilt",
        "µrad",
        "transit axis out of square with the standing axis",
    ),
    (
        "mirror_offset",
        "µm",
        "reflecting surface's offset from the transit axis",
    ),
    (
        "mirror_tilt",
        "µrad",
        "mirror normal out of the plane square to the transit axis",
    ),
    ("vertical_index", "µrad", "elevation encoder zero offset"),
    ("range_offset", "µm", "distance zero (R0)"),
];

impl MirrorErrors {
    /// The misalignments in the order of [`IDS`].
    pub(crate) fn from_array(a: [f64; 10]) -> MirrorErrors {
        MirrorErrors {
            beam_offset_x: a[0],
            beam_offset_y: a[1],
            beam_tilt_x: a[2],
            beam_tilt_y: a[3],
            transit_offset: a[4],
            transit_tilt: a[5],
            mirror_offset: a[6],
            mirror_tilt: a[7],
            vertical_index: a[8],
            range_offset: a[9],
        }
    }
}

/// A mirror tracker with its misalignments, in internal units (mm, rad).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MirrorTracker {
    /// Where the incoming beam crosses `z = 0`.
    s0: Vector3<f64>,
    /// The incoming beam's direction (unit).
    u: Vector3<f64>,
    transit_offset: f64,
    /// The transit axis's tilt, as the rotation about `x̂_h` it is.
    transit_tilt: Rotation3<f64>,
    mirror_offset: f64,
    /// `(sin, cos)` of the mirror tilt.
    mirror_tilt: (f64, f64),
    vertical_index: f64,
    range_offset: f64,
}

impl MirrorTracker {
    pub fn new(e: &MirrorErrors) -> MirrorTracker {
        let (um, urad) = (1e-3, 1e-6);
        MirrorTracker {
            s0: Vector3::new(e.beam_offset_x * um, e.beam_offset_y * um, 0.0),
            u: Vector3::new(e.beam_tilt_x * urad, e.beam_tilt_y * urad, 1.0).normalize(),
            transit_offset: e.transit_offset * um,
            transit_tilt: Rotation3::from_axis_angle(&Vector3::x_axis(), e.transit_tilt * urad),
            mirror_offset: e.mirror_offset * um,
            mirror_tilt: (e.mirror_tilt * urad).sin_cos(),
            vertical_index: e.vertical_index * urad,
            range_offset: e.range_offset * um,
        }
    }

    /// The mirror's unit normal and a point of its transit axis, station
    /// frame, at reading `r`.
    fn mirror(&self, r: Reading) -> (Vector3<f64>, Vector3<f64>) {
        let beta = 0.5 * (r.el + self.vertical_index) - std::f64::consts::FRAC_PI_4;
        let (st, ct) = self.mirror_tilt;
        let n_h = Vector3::new(ct * beta.cos(), st, ct * beta.sin());
        let head = Rotation3::from_axis_angle(&Vector3::z_axis(), r.az);
        let n = head * (self.transit_tilt * n_h);
        let o = head * Vector3::new(self.transit_offset, 0.0, 0.0);
        (n, o)
    }

    /// The point a reading reaches (station frame, mm): the module doc's
    /// beam path.
    pub fn point(&self, r: Reading) -> Vector3<f64> {
        let (n, o) = self.mirror(r);
        // The plane n·x = n·o + mirror_offset meets s₀ + t·u at t*.
        let t = (n.dot(&o) + self.mirror_offset - n.dot(&self.s0)) / n.dot(&self.u);
        let at = self.s0 + t * self.u;
        let out = self.u - 2.0 * self.u.dot(&n) * n;
        at + (r.d + self.range_offset - t) * out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::{Face, nominal_point, nominal_reading};
    use nalgebra::Matrix3;

    fn readings() -> Vec<Reading> {
        let mut out = Vec::new();
        for az in (-170..=180).step_by(40) {
            for el in [-50.0_f64, -15.0, 0.0, 20.0, 55.0, 75.0] {
                for d in [800.0, 5000.0, 30000.0] {
                    let p = nominal_point(Reading {
                        az: (az as f64).to_radians(),
                        el: el.to_radians(),
                        d,
                    });
                    out.push(nominal_reading(&p, Face::Front));
                    out.push(nominal_reading(&p, Face::Back));
                }
            }
        }
        out
    }

    fn misaligned() -> MirrorErrors {
        MirrorErrors {
            beam_offset_x: 40.0,
            beam_offset_y: -25.0,
            beam_tilt_x: 30.0,
            beam_tilt_y: 15.0,
            transit_offset: 20.0,
            transit_tilt: -12.0,
            mirror_offset: 35.0,
            mirror_tilt: 18.0,
            vertical_index: 9.0,
            range_offset: 7.0,
        }
    }

    #[test]
    fn without_misalignment_a_reading_reaches_its_spherical_point() {
        let t = MirrorTracker::new(&MirrorErrors::default());
        for r in readings() {
            assert!((t.point(r) - nominal_point(r)).norm() < 1e-9);
        }
    }

    /// The same tracker built from physical parts by other means: the
    /// mirror as three points on its surface (placed by rotating about the
    /// tilted transit axis itself), the ray met by solving for the ray
    /// parameter and two in-plane coordinates, the reflection a Householder
    /// matrix, the path out walked from the optical path length.
    fn ray_trace(e: &MirrorErrors, r: Reading) -> Vector3<f64> {
        let (um, urad) = (1e-3, 1e-6);
        let head = Rotation3::from_axis_angle(&Vector3::z_axis(), r.az);
        let axis_dir = head
            * Rotation3::from_axis_angle(&Vector3::x_axis(), e.transit_tilt * urad)
            * Vector3::y();
        let axis_point = head * Vector3::new(e.transit_offset * um, 0.0, 0.0);
        // At el = −90° the mirror faces straight down the incoming beam:
        // normal −ẑ, tilted by mirror_tilt about the head's forward
        // direction; from there it turns about the transit axis itself by
        // (el + vi)/2 + 45° towards the target.
        let n_start = Rotation3::from_axis_angle(
            &nalgebra::Unit::new_normalize(
                head * Rotation3::from_axis_angle(&Vector3::x_axis(), e.transit_tilt * urad)
                    * Vector3::x(),
            ),
            e.mirror_tilt * urad,
        ) * (head
            * Rotation3::from_axis_angle(&Vector3::x_axis(), e.transit_tilt * urad)
            * -Vector3::z());
        let turn = 0.5 * (r.el + e.vertical_index * urad) + std::f64::consts::FRAC_PI_4;
        let n =
            Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis_dir), -turn) * n_start;
        // Three points of the surface: the foot on the axis pushed along the
        // normal, and two more across the surface.
        let foot = axis_point + e.mirror_offset * um * n;
        let across1 = n.cross(&axis_dir).normalize();
        let across2 = n.cross(&across1).normalize();
        let (p1, p2, p3) = (foot, foot + 10.0 * across1, foot + 7.0 * across2);
        // The ray from its crossing of z = 0: s₀ + t·u = p1 + a·(p2 − p1) + b·(p3 − p1).
        let s0 = Vector3::new(e.beam_offset_x * um, e.beam_offset_y * um, 0.0);
        let u = Vector3::new(e.beam_tilt_x * urad, e.beam_tilt_y * urad, 1.0).normalize();
        let m = Matrix3::from_columns(&[u, -(p2 - p1), -(p3 - p1)]);
        let sol = m.lu().solve(&(p1 - s0)).expect("the ray meets the mirror");
        let hit = s0 + sol.x * u;
        let householder = Matrix3::identity() - 2.0 * n * n.transpose();
        let out = householder * u;
        // Optical path: d + R0 in all, sol.x of it spent before the mirror.
        hit + (r.d + e.range_offset * um - sol.x) * out
    }

    #[test]
    fn an_independent_ray_trace_agrees_to_a_nanometre() {
        let e = misaligned();
        let t = MirrorTracker::new(&e);
        for r in readings() {
            let (model, traced) = (t.point(r), ray_trace(&e, r));
            assert!(
                (model - traced).norm() < 1e-9,
                "az {:.0}° el {:.0}° d {}: {:?} vs {:?}",
                r.az.to_degrees(),
                r.el.to_degrees(),
                r.d,
                model,
                traced
            );
        }
    }

    #[test]
    fn mirror_errors_show_as_the_geometry_says() {
        // A mirror offset mo meets the beam t* = mo/(u·n) further along,
        // and the path out is t* shorter: the point moves by
        // t*·(u − r) = 2·mo·n, exactly — along the mirror's normal, which
        // the back face reverses (a two-face separation of 4·mo).
        let mo = 50.0;
        let e = MirrorErrors {
            mirror_offset: mo,
            ..MirrorErrors::default()
        };
        let t = MirrorTracker::new(&e);
        for r in readings() {
            let dp = t.point(r) - nominal_point(r);
            let (n, _) = t.mirror(r);
            assert!((dp - 2.0 * mo * 1e-3 * n).norm() < 1e-12 * (1.0 + r.d));
        }
        // A tilted incoming beam is fixed in the station while the mirror
        // turns: its error on the point changes with the azimuth at a
        // fixed elevation, unlike any rotation carried by the head.
        let e = MirrorErrors {
            beam_tilt_x: 20.0,
            ..MirrorErrors::default()
        };
        let t = MirrorTracker::new(&e);
        let at = |az_deg: f64| {
            let r = Reading {
                az: az_deg.to_radians(),
                el: 0.3,
                d: 10_000.0,
            };
            let (sa, ca) = r.az.sin_cos();
            let (se, ce) = r.el.sin_cos();
            let e_az = Vector3::new(-sa, ca, 0.0);
            let e_el = Vector3::new(-se * ca, -se * sa, ce);
            let dp = t.point(r) - nominal_point(r);
            (dp.dot(&e_az), dp.dot(&e_el))
        };
        let (a0, e0) = at(0.0);
        let (a90, e90) = at(90.0);
        assert!((a0 - a90).abs() > 0.05 || (e0 - e90).abs() > 0.05);
    }

    #[test]
    fn from_array_follows_the_ids() {
        let fields = |e: &MirrorErrors| {
            [
                ("beam_offset_x", e.beam_offset_x),
                ("beam_offset_y", e.beam_offset_y),
                ("beam_tilt_x", e.beam_tilt_x),
                ("beam_tilt_y", e.beam_tilt_y),
                ("transit_offset", e.transit_offset),
                ("transit_tilt", e.transit_tilt),
                ("mirror_offset", e.mirror_offset),
                ("mirror_tilt", e.mirror_tilt),
                ("vertical_index", e.vertical_index),
                ("range_offset", e.range_offset),
            ]
        };
        for (k, (id, _, _)) in IDS.iter().enumerate() {
            let e = MirrorErrors::from_array(std::array::from_fn(|j| f64::from(j == k)));
            for (name, v) in fields(&e) {
                assert_eq!(v, f64::from(name == *id), "{id}: {name}");
            }
        }
    }
}
