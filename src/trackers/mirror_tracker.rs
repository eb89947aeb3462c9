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
//! the reflected `r = u − 2(u·n)n` ([`BeamPath::point`]). The base
//! errors are fixed in the station frame while the mirror turns: they act
//! through the reflection, `δr = (I − 2nnᵀ)·δu`, an error no joint of the
//! head-laser DH chain carries — which is why a mirror tracker needs its own
//! model. The test of the model is an independent ray trace
//! (`tests::an_independent_ray_trace_agrees_to_a_nanometre`).
//!
//! # The plug-in
//!
//! [`MirrorTracker`] is the registry's entry: the ten misalignments as
//! constant parameters, the beam path as the forward model. Its
//! derivatives are analytic ([`BeamPath::point_with_jacobian`]): each
//! misalignment moves the beam's start `s₀`, its direction `u`, the
//! mirror's normal `n` or axis point `o`, the mirror offset or the range
//! offset, and the reflection's chain rule carries that tangent through
//! `t*`, the reflected `r` and the path out — one beam path per reading
//! instead of the 21 of central differences, which made a mirror
//! adjustment cost twice a head-laser one (issue 34). They agree with
//! central differences of the exact beam path to 1e-7 of the derivative
//! (`evaluator_tests::mirror_derivatives_are_analytic_and_match_central_differences`).
//! The B89 stage reports and accepts the misalignments themselves.

use super::{Evaluate, Model, Param};
use crate::error_model::{ErrorParams, Links};
use crate::kinematics::{Joints, Reading};
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

/// The parameters of [`MirrorErrors`]' fields, in order: constants (a
/// mirror's misalignment takes no shape), with their units and meanings.
pub const PARAMS: [Param; 10] = [
    misalignment("beam_offset_x", false, "incoming beam's offset from the standing axis, x"),
    misalignment("beam_offset_y", false, "incoming beam's offset from the standing axis, y"),
    misalignment("beam_tilt_x", true, "incoming beam's tilt from the standing axis, x"),
    misalignment("beam_tilt_y", true, "incoming beam's tilt from the standing axis, y"),
    misalignment("transit_offset", false, "transit axis offset from the standing axis, towards the beam"),
    misalignment("transit_tilt", true, "transit axis out of square with the standing axis"),
    misalignment("mirror_offset", false, "reflecting surface's offset from the transit axis"),
    misalignment("mirror_tilt", true, "mirror normal out of the plane square to the transit axis"),
    misalignment("vertical_index", true, "elevation encoder zero offset"),
    misalignment("range_offset", false, "distance zero (R0)"),
];

/// A misalignment: its id is its symbol, its unit µrad if `angular` else µm.
const fn misalignment(id: &'static str, angular: bool, meaning: &'static str) -> Param {
    Param {
        id,
        symbol: id,
        angular,
        meaning,
        joint: None,
    }
}

impl MirrorErrors {
    /// The misalignments in the order of [`PARAMS`].
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
pub struct BeamPath {
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

impl BeamPath {
    pub fn new(e: &MirrorErrors) -> BeamPath {
        let (um, urad) = (1e-3, 1e-6);
        BeamPath {
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

    /// The point of [`BeamPath::point`] (the same arithmetic, the same
    /// value) and its derivative with respect to each misalignment of
    /// [`PARAMS`], mm per display unit (µm or µrad), by the chain rule of
    /// the beam path: each misalignment's tangent of `s₀`, `u`, `n`, `o`,
    /// the mirror offset and the range offset, carried through
    /// `t* = (n·o + m − n·s₀)/(n·u)` and `r = u − 2(u·n)n`.
    pub fn point_with_jacobian(&self, r: Reading, jac: &mut [Vector3<f64>; 10]) -> Vector3<f64> {
        let (um, urad) = (1e-3, 1e-6);
        let beta = 0.5 * (r.el + self.vertical_index) - std::f64::consts::FRAC_PI_4;
        let (st, ct) = self.mirror_tilt;
        let (sb, cb) = beta.sin_cos();
        let n_h = Vector3::new(ct * cb, st, ct * sb);
        let head = Rotation3::from_axis_angle(&Vector3::z_axis(), r.az);
        let tn = self.transit_tilt * n_h;
        let n = head * tn;
        let x_h = head * Vector3::x();
        let o = self.transit_offset * x_h;
        let (u, s0) = (self.u, self.s0);
        let den = n.dot(&u);
        let t = (n.dot(&o) + self.mirror_offset - n.dot(&s0)) / den;
        let at = s0 + t * u;
        let un = u.dot(&n);
        let out = u - 2.0 * un * n;
        let reach = r.d + self.range_offset - t;
        let point = at + reach * out;
        // `u = v/|v|` with `v = (t_x, t_y, 1)`: `∂u/∂v = (I − uuᵀ)/|v|`,
        // and `1/|v| = u_z`.
        let du = |axis: Vector3<f64>| (axis - u * u.dot(&axis)) * (u.z * urad);
        let zero = Vector3::zeros();
        // (ds₀, du, dn, do, d mirror offset, d range offset) per misalignment.
        let tangents = [
            (Vector3::x() * um, zero, zero, zero, 0.0, 0.0),
            (Vector3::y() * um, zero, zero, zero, 0.0, 0.0),
            (zero, du(Vector3::x()), zero, zero, 0.0, 0.0),
            (zero, du(Vector3::y()), zero, zero, 0.0, 0.0),
            (zero, zero, zero, x_h * um, 0.0, 0.0),
            // A turn about the head's x̂: `∂(R_x·n_h)/∂τ = x̂ × R_x·n_h`.
            (zero, zero, head * Vector3::x().cross(&tn) * urad, zero, 0.0, 0.0),
            (zero, zero, zero, zero, um, 0.0),
            (
                zero,
                zero,
                head * (self.transit_tilt * Vector3::new(-st * cb, ct, -st * sb)) * urad,
                zero,
                0.0,
                0.0,
            ),
            (
                zero,
                zero,
                head * (self.transit_tilt * Vector3::new(-ct * sb, 0.0, ct * cb)) * (0.5 * urad),
                zero,
                0.0,
                0.0,
            ),
            (zero, zero, zero, zero, 0.0, um),
        ];
        for (out_k, (ds0, du, dn, d_o, dm, dr0)) in jac.iter_mut().zip(tangents) {
            let dnum = dn.dot(&o) + n.dot(&d_o) + dm - dn.dot(&s0) - n.dot(&ds0);
            let dden = dn.dot(&u) + n.dot(&du);
            let dt = (dnum - t * dden) / den;
            let dout = du - 2.0 * ((du.dot(&n) + u.dot(&dn)) * n + un * dn);
            *out_k = ds0 + dt * u + t * du + (dr0 - dt) * out + reach * dout;
        }
        point
    }
}

/// The plug-in.
pub struct MirrorTracker;

impl Model for MirrorTracker {
    fn id(&self) -> &'static str {
        "mirror-tracker"
    }

    fn describe(&self) -> &'static str {
        "laser in the base, steered by a mirror on the transit axis"
    }

    fn params(&self) -> &'static [Param] {
        &PARAMS
    }

    fn evaluate<'a>(&self, params: &'a ErrorParams) -> Box<dyn Evaluate + 'a> {
        Box::new(Analytic {
            at: BeamPath::new(&mirror_errors(params, params.values())),
            of: params.coefs().iter().map(|c| c.param.local()).collect(),
        })
    }
}

/// The misalignments of a mirror parameter set with coefficient values
/// `values`.
fn mirror_errors(params: &ErrorParams, values: &[f64]) -> MirrorErrors {
    let mut a = [0.0; PARAMS.len()];
    for (c, v) in params.coefs().iter().zip(values) {
        a[c.param.local()] += v;
    }
    MirrorErrors::from_array(a)
}

/// The beam path at the values, and each coefficient's misalignment (a
/// coefficient is a constant: its derivative is its misalignment's).
struct Analytic {
    at: BeamPath,
    of: Vec<usize>,
}

impl Evaluate for Analytic {
    fn point(&self, q: Joints, _: &Links) -> Vector3<f64> {
        self.at.point(q.reading())
    }

    fn point_with_jacobian(
        &self,
        q: Joints,
        _: &Links,
        jac: &mut Vec<Vector3<f64>>,
    ) -> Vector3<f64> {
        let mut all = [Vector3::zeros(); PARAMS.len()];
        let point = self.at.point_with_jacobian(q.reading(), &mut all);
        jac.extend(self.of.iter().map(|&k| all[k]));
        point
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
        let t = BeamPath::new(&MirrorErrors::default());
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
        let t = BeamPath::new(&e);
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
        let t = BeamPath::new(&e);
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
        let t = BeamPath::new(&e);
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
        for (k, id) in PARAMS.iter().map(|p| p.id).enumerate() {
            let e = MirrorErrors::from_array(std::array::from_fn(|j| f64::from(j == k)));
            for (name, v) in fields(&e) {
                assert_eq!(v, f64::from(name == id), "{id}: {name}");
            }
        }
    }
}

#[cfg(test)]
mod evaluator_tests {
    use super::*;
    use crate::error_model::{Coef, ErrorModel, Shape};
    use crate::trackers::TrackerModel;

    fn handle() -> TrackerModel {
        TrackerModel::parse(MirrorTracker.id()).unwrap()
    }

    /// Every misalignment at a few µm / µrad, some of each sign.
    fn mirror_params() -> ErrorParams {
        let mut p = ErrorParams::zero(&ErrorModel::of(handle()));
        for (k, v) in p.values_mut().iter_mut().enumerate() {
            *v = [7.0, -4.0, 12.0, -9.0, 5.0][k % 5] + k as f64;
        }
        p
    }

    fn readings() -> Vec<Joints> {
        let mut out = Vec::new();
        for az in [-170.0, -60.0, 10.0, 95.0] {
            for el in [-40.0, 0.0, 35.0, 70.0, 120.0] {
                for d in [900.0, 6000.0, 25000.0] {
                    let r = Reading {
                        az: f64::to_radians(az),
                        el: f64::to_radians(el),
                        d,
                    };
                    out.push(r.joints());
                }
            }
        }
        out
    }

    /// Issue 34: the reflection's Jacobian, analytic, against central
    /// differences of the exact beam path (a step of 0.1 display unit:
    /// truncation ~1e-10 of the derivative, rounding ~1e-11), every
    /// misalignment at a few µm / µrad, over both faces and the range.
    #[test]
    fn mirror_derivatives_are_analytic_and_match_central_differences() {
        let p = mirror_params();
        let eval = p.evaluator();
        let mut jac = Vec::new();
        for q in readings() {
            jac.clear();
            let at = eval.point_with_jacobian(q, &Links::new(q), &mut jac);
            assert_eq!(at, eval.point(q, &Links::new(q)));
            assert_eq!(jac.len(), PARAMS.len());
            for (k, col) in jac.iter().enumerate() {
                let h = 0.1;
                let e = |s: f64| {
                    let mut v = p.values().to_vec();
                    v[k] += s;
                    BeamPath::new(&mirror_errors(&p, &v)).point(q.reading())
                };
                let fine = (e(h) - e(-h)) / (2.0 * h);
                assert!(
                    (col - fine).norm() <= 1e-7 * col.norm().max(1e-3),
                    "{}: {col} vs {fine}",
                    p.coefs()[k].name()
                );
            }
        }
    }

    #[test]
    fn the_mirror_inverse_round_trips_through_the_evaluator() {
        let p = mirror_params();
        let eval = p.evaluator();
        for q in readings() {
            let r = q.reading();
            let face = r.face();
            let x = eval.point(q, &Links::new(q));
            let back = eval.reading_of(&x, face).unwrap();
            let y = p.point(back.joints());
            assert!((x - y).norm() < 1e-9, "{r:?}: {}", (x - y).norm());
            assert_eq!(back.face(), face);
        }
    }

    #[test]
    fn a_parameter_set_is_of_one_model() {
        let dx1 = Coef::parse("dx1").unwrap();
        let tilt = Coef::parse("transit_tilt").unwrap();
        assert_eq!(tilt.param.tracker(), handle());
        assert_eq!(Coef::parse("transit_tilt.sin1"), None);
        assert!(ErrorParams::tracker_of(&[dx1, tilt]).is_err());
        assert_eq!(
            ErrorParams::tracker_of(&[tilt]),
            Ok(handle())
        );
        let m = ErrorModel::of(handle());
        assert_eq!(m.coefs().len(), PARAMS.len());
        assert!(m.clone().with_shape(dx1.param, Shape::Poly(1)).is_err());
        assert!(m.with_shape(tilt.param, Shape::Fourier(1)).is_err());
    }
}
