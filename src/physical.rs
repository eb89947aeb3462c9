//! The physical misalignment model of a tracker with the laser source in the
//! rotating head, after Loser and Kyle as NIST uses it with the ASME
//! B89.4.19 tests (Muralikrishnan et al., 2009): beam offset and tilt,
//! transit offset and tilt, vertical index offset, encoder eccentricity and
//! second harmonics, range offset — and where each sits among the paper's
//! 18 DH error parameters.
//!
//! # Why a second parametrisation
//!
//! Metrologists read and specify trackers in these terms (a beam offset in
//! µm, a transit tilt in µrad), and the standard's tests are discussed in
//! them. The DH chain of Section 4 with a 6-DOF error transform per joint is
//! a rigid-body chain: each misalignment here is one rigid displacement of an
//! axis or of the beam, so each is **exactly one coefficient** of the DH
//! model (the encoder terms through the Fourier shapes of Eq. 9), up to sign
//! and to the angle its harmonic is written in. The model is therefore the
//! DH model restricted to [`CORRESPONDENCE`]'s coefficients, with
//! physical names; [`to_dh`] maps values across. The tests hold the
//! mapping against the classical first-order observation model (the `Δ`
//! column below), derived on its own.
//!
//! # Correspondence (frames of `error_model`'s module doc)
//!
//! With the reading's local directions `e_R` (along the beam), `e_az`
//! (horizontal, towards increasing azimuth) and `e_el` (towards increasing
//! elevation), a misalignment moves the point the beam reaches by `Δ` (true
//! point minus the nominal point of the reading):
//!
//! | parameter | meaning | Δ (first order) | DH coefficient |
//! | --- | --- | --- | --- |
//! | `beam_offset_el` (µm) | beam offset from the transit axis, in the beam's vertical plane | `o·e_el` | `+δx3` |
//! | `beam_offset_az` (µm) | beam offset along the transit axis | `o·e_az` | `−δy3` |
//! | `transit_offset` (µm) | transit axis offset from the standing axis, towards the beam | `o·e_h` | `−δx2` |
//! | `beam_tilt_el` (µrad) | beam tilt in its vertical plane | `c·d·e_el` | `+εy3` |
//! | `beam_tilt_az` (µrad) | beam tilt towards the transit axis | `c·d·e_az` | `+εx3` |
//! | `vertical_index` (µrad) | elevation encoder zero | `ε·d·e_el` | `+εz2` |
//! | `transit_tilt` (µrad) | transit axis out of square with the standing axis | `i·d·sin(el)·e_az` | `+εx2` |
//! | `range_offset` (µm) | R0, the distance zero (bird-bath) | `R0·e_R` | `+δz3` |
//! | `az_ecc_sin`, `az_ecc_cos` (µrad) | horizontal encoder eccentricity: azimuth error `a·sin(az) + b·cos(az)` | `ε(az)·d·cos(el)·e_az` | `+εz1.cos1`, `−εz1.sin1` |
//! | `az_h2_sin`, `az_h2_cos` (µrad) | its second harmonic, `a·sin(2az) + b·cos(2az)` | same | `−εz1.sin2`, `−εz1.cos2` |
//! | `el_ecc_sin`, `el_ecc_cos` (µrad) | vertical encoder eccentricity: elevation error `a·sin(el) + b·cos(el)` | `ε(el)·d·e_el` | `+εz2.sin1`, `+εz2.cos1` |
//! | `el_h2_sin`, `el_h2_cos` (µrad) | its second harmonic | same | `+εz2.sin2`, `+εz2.cos2` |
//!
//! `e_h = cos(el)·e_R − sin(el)·e_el` is the head's horizontal forward
//! direction. Angles are the encoders' own (the reading's `az`, `el`, also in
//! the back face); the DH harmonics are written in `θ = az − 90°` and
//! `φ = el`, hence the signs and the swap of sine and cosine in azimuth.
//!
//! The DH coefficients with no physical counterpart are the tracker's
//! placement, which a free station pose absorbs (δx1, δy1, δz1, εx1, εy1, the
//! constant εz1 — the azimuth zero — and δy2, the transit axis's height),
//! exact duplicates of a coefficient above (δz2 moves the point as δy3 does,
//! εy2 as −εz1), and εz3, a rotation about the beam, which moves nothing.
//! `tests::dh_coefficients_without_a_counterpart_are_placement_or_duplicates`
//! holds each of these statements.

use crate::error_model::{Coef, ErrorModel, ErrorParams, ParamId, Shape};

/// One physical misalignment and its DH coefficient.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Misalignment {
    /// The id in TOML and tables.
    pub id: &'static str,
    /// Display unit of its value: µm or µrad.
    pub unit: &'static str,
    /// What it is, in words.
    pub meaning: &'static str,
    /// The DH coefficient it is, by its table name (`dx3`, `ez1.cos1`) …
    pub dh: &'static str,
    /// … times this sign.
    pub sign: f64,
}

/// The model's parameters in table order, with their DH coefficients (the
/// module doc's table).
pub const CORRESPONDENCE: [Misalignment; 16] = [
    m(
        "beam_offset_el",
        "µm",
        "beam offset from the transit axis, in the beam's vertical plane",
        "dx3",
        1.0,
    ),
    m(
        "beam_offset_az",
        "µm",
        "beam offset along the transit axis (towards increasing azimuth)",
        "dy3",
        -1.0,
    ),
    m(
        "transit_offset",
        "µm",
        "transit axis offset from the standing axis, towards the beam",
        "dx2",
        -1.0,
    ),
    m(
        "beam_tilt_el",
        "µrad",
        "beam tilt in its vertical plane",
        "ey3",
        1.0,
    ),
    m(
        "beam_tilt_az",
        "µrad",
        "beam tilt towards increasing azimuth",
        "ex3",
        1.0,
    ),
    m(
        "vertical_index",
        "µrad",
        "elevation encoder zero offset",
        "ez2",
        1.0,
    ),
    m(
        "transit_tilt",
        "µrad",
        "transit axis out of square with the standing axis",
        "ex2",
        1.0,
    ),
    m(
        "range_offset",
        "µm",
        "distance zero (R0, bird-bath offset)",
        "dz3",
        1.0,
    ),
    m(
        "az_ecc_sin",
        "µrad",
        "horizontal encoder eccentricity, a·sin(az)",
        "ez1.cos1",
        1.0,
    ),
    m(
        "az_ecc_cos",
        "µrad",
        "horizontal encoder eccentricity, b·cos(az)",
        "ez1.sin1",
        -1.0,
    ),
    m(
        "az_h2_sin",
        "µrad",
        "horizontal encoder second harmonic, a·sin(2az)",
        "ez1.sin2",
        -1.0,
    ),
    m(
        "az_h2_cos",
        "µrad",
        "horizontal encoder second harmonic, b·cos(2az)",
        "ez1.cos2",
        -1.0,
    ),
    m(
        "el_ecc_sin",
        "µrad",
        "vertical encoder eccentricity, a·sin(el)",
        "ez2.sin1",
        1.0,
    ),
    m(
        "el_ecc_cos",
        "µrad",
        "vertical encoder eccentricity, b·cos(el)",
        "ez2.cos1",
        1.0,
    ),
    m(
        "el_h2_sin",
        "µrad",
        "vertical encoder second harmonic, a·sin(2el)",
        "ez2.sin2",
        1.0,
    ),
    m(
        "el_h2_cos",
        "µrad",
        "vertical encoder second harmonic, b·cos(2el)",
        "ez2.cos2",
        1.0,
    ),
];

const fn m(
    id: &'static str,
    unit: &'static str,
    meaning: &'static str,
    dh: &'static str,
    sign: f64,
) -> Misalignment {
    Misalignment {
        id,
        unit,
        meaning,
        dh,
        sign,
    }
}

impl Misalignment {
    /// The misalignment with this id.
    pub fn parse(id: &str) -> Option<&'static Misalignment> {
        CORRESPONDENCE.iter().find(|m| m.id == id)
    }

    /// Its DH coefficient.
    pub fn coef(&self) -> Coef {
        Coef::parse(self.dh).expect("the correspondence names valid coefficients")
    }
}

/// The DH error model that holds every misalignment: the paper's 18
/// constants with second-order Fourier shapes on εz1 and εz2.
pub fn dh_model() -> ErrorModel {
    let harmonics = |p: &str| ParamId::parse(p).expect("a DH parameter");
    ErrorModel::constant()
        .with_shape(harmonics("ez1"), Shape::Fourier(2))
        .and_then(|m| m.with_shape(harmonics("ez2"), Shape::Fourier(2)))
        .expect("rotary joints take Fourier shapes")
}

/// The DH parameter set of misalignment values `(id, value)` in display
/// units (every other coefficient zero). Unknown ids are the caller's to
/// reject ([`Misalignment::parse`]).
pub fn to_dh(values: &[(&Misalignment, f64)]) -> ErrorParams {
    let mut p = ErrorParams::zero(&dh_model());
    let coefs = p.coefs().to_vec();
    for (m, v) in values {
        let at = coefs
            .iter()
            .position(|c| *c == m.coef())
            .expect("the DH model holds every misalignment's coefficient");
        p.values_mut()[at] += m.sign * v;
    }
    p
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error_model::rotation_xyz;
    use crate::kinematics::{Face, Reading, nominal_point, nominal_reading};
    use nalgebra::Vector3;

    /// The reading's local directions `(e_R, e_az, e_el)` in the station frame.
    fn local_frame(r: Reading) -> [Vector3<f64>; 3] {
        let (sa, ca) = r.az.sin_cos();
        let (se, ce) = r.el.sin_cos();
        [
            Vector3::new(ce * ca, ce * sa, se),
            Vector3::new(-sa, ca, 0.0),
            Vector3::new(-se * ca, -se * sa, ce),
        ]
    }

    /// The classical first-order observation model: how far misalignment `m`
    /// at `value` (display units) moves the point a reading reaches, in mm —
    /// the module doc's `Δ` column, derived from the geometry of each
    /// misalignment alone, not from the DH chain.
    fn first_order_displacement(m: &Misalignment, value: f64, r: Reading) -> Vector3<f64> {
        let [e_r, e_az, e_el] = local_frame(r);
        let v = value * if m.unit == "µm" { 1e-3 } else { 1e-6 };
        let (az, el, d) = (r.az, r.el, r.d);
        match m.id {
            "beam_offset_el" => v * e_el,
            "beam_offset_az" => v * e_az,
            "transit_offset" => v * (el.cos() * e_r - el.sin() * e_el),
            "beam_tilt_el" | "vertical_index" => v * d * e_el,
            "beam_tilt_az" => v * d * e_az,
            "transit_tilt" => v * d * el.sin() * e_az,
            "range_offset" => v * e_r,
            "az_ecc_sin" => v * az.sin() * d * el.cos() * e_az,
            "az_ecc_cos" => v * az.cos() * d * el.cos() * e_az,
            "az_h2_sin" => v * (2.0 * az).sin() * d * el.cos() * e_az,
            "az_h2_cos" => v * (2.0 * az).cos() * d * el.cos() * e_az,
            "el_ecc_sin" => v * el.sin() * d * e_el,
            "el_ecc_cos" => v * el.cos() * d * e_el,
            "el_h2_sin" => v * (2.0 * el).sin() * d * e_el,
            "el_h2_cos" => v * (2.0 * el).cos() * d * e_el,
            other => unreachable!("`{other}` is in CORRESPONDENCE without a displacement"),
        }
    }

    /// Readings over the volume, both faces.
    fn readings() -> Vec<Reading> {
        let mut out = Vec::new();
        for az in (-170..=180).step_by(35) {
            for el in [-40.0_f64, -10.0, 0.0, 25.0, 60.0] {
                for d in [1000.0, 4000.0, 12000.0] {
                    let az = (az as f64).to_radians();
                    let el = el.to_radians();
                    let p = nominal_point(Reading { az, el, d });
                    out.push(nominal_reading(&p, Face::Front));
                    out.push(nominal_reading(&p, Face::Back));
                }
            }
        }
        out
    }

    /// The DH chain's exact displacement of a reading's point.
    fn dh_displacement(p: &ErrorParams, r: Reading) -> Vector3<f64> {
        p.correct(r) - nominal_point(r)
    }

    #[test]
    fn each_misalignment_is_its_dh_coefficient_to_first_order() {
        for m in &CORRESPONDENCE {
            let value = 10.0;
            let p = to_dh(&[(m, value)]);
            for r in readings() {
                let exact = dh_displacement(&p, r);
                let first = first_order_displacement(m, value, r);
                // Second order: (10 µrad)·Δ, or 1e-8 mm·d-free terms.
                let tol = 1e-4 * first.norm() + 1e-9;
                assert!(
                    (exact - first).norm() <= tol,
                    "{} at az {:.1}° el {:.1}° d {}: DH {exact:?} first order {first:?}",
                    m.id,
                    r.az.to_degrees(),
                    r.el.to_degrees(),
                    r.d
                );
            }
        }
    }

    #[test]
    fn two_face_separations_are_the_field_facts() {
        // FIELD.md: offsets give 2·offset, beam tilt 2·c·R, vertical index
        // 2·ε·R, transit tilt 2·i·R·sin(el); R0 and even harmonics none,
        // odd harmonics a separation (they cancel in the face average).
        let v = 10.0;
        for r in readings().into_iter().filter(|r| r.el.cos() > 0.0) {
            let p = nominal_point(r);
            for m in &CORRESPONDENCE {
                let dh = to_dh(&[(m, v)]);
                // A tracker with these errors reading the same point in both
                // faces reports points that differ by this much.
                let front_rep = nominal_point(dh.reading_of(&p, Face::Front).unwrap());
                let back_rep = nominal_point(dh.reading_of(&p, Face::Back).unwrap());
                let sep_um = (front_rep - back_rep).norm() * 1e3;
                let (d_m, el) = (r.d * 1e-3, r.el);
                let expected_um = match m.id {
                    "beam_offset_el" | "beam_offset_az" | "transit_offset" => 2.0 * v,
                    "beam_tilt_el" | "beam_tilt_az" | "vertical_index" => 2.0 * v * d_m,
                    "transit_tilt" => 2.0 * v * d_m * el.sin().abs(),
                    "range_offset" | "az_h2_sin" | "az_h2_cos" => 0.0,
                    "az_ecc_sin" => 2.0 * v * d_m * el.cos() * r.az.sin().abs(),
                    "az_ecc_cos" => 2.0 * v * d_m * el.cos() * r.az.cos().abs(),
                    _ => continue,
                };
                assert!(
                    (sep_um - expected_um).abs() <= 1e-3 * expected_um + 1e-4,
                    "{} at el {:.0}° d {} m: {sep_um} µm, expected {expected_um}",
                    m.id,
                    el.to_degrees(),
                    d_m
                );
            }
        }
    }

    #[test]
    fn dh_coefficients_without_a_counterpart_are_placement_or_duplicates() {
        let one = |id: &str, v: f64| {
            let mut p = ErrorParams::zero(&dh_model());
            let c = Coef::parse(id).unwrap();
            let at = p.coefs().iter().position(|x| *x == c).unwrap();
            p.values_mut()[at] = v;
            p
        };
        let rs = readings();
        // A rigid motion of the station frame: the same for every reading.
        for id in ["dx1", "dy1", "dz1", "dy2"] {
            let p = one(id, 10.0);
            let d0 = dh_displacement(&p, rs[0]);
            for r in &rs {
                assert!((dh_displacement(&p, *r) - d0).norm() < 1e-9, "{id}");
            }
        }
        // Rotations of the station frame: Δ = (R(ε1) − I)·P exactly.
        for (id, w) in [
            ("ex1", [1.0, 0.0, 0.0]),
            ("ey1", [0.0, 1.0, 0.0]),
            ("ez1", [0.0, 0.0, 1.0]),
        ] {
            let p = one(id, 10.0);
            let r_e = rotation_xyz(10e-6 * w[0], 10e-6 * w[1], 10e-6 * w[2]);
            for r in &rs {
                let pt = nominal_point(*r);
                let expected = r_e * pt - pt;
                assert!((dh_displacement(&p, *r) - expected).norm() < 1e-9, "{id}");
            }
        }
        // Duplicates.
        for (a, b, sign) in [("dz2", "dy3", 1.0), ("ey2", "ez1", -1.0)] {
            let (pa, pb) = (one(a, 10.0), one(b, sign * 10.0));
            for r in &rs {
                let (da, db) = (dh_displacement(&pa, *r), dh_displacement(&pb, *r));
                assert!(
                    (da - db).norm() <= 1e-4 * da.norm() + 1e-12,
                    "{a} ≡ {sign}·{b}"
                );
            }
        }
        // A rotation about the beam moves nothing.
        let p = one("ez3", 10.0);
        for r in &rs {
            assert!(dh_displacement(&p, *r).norm() < 1e-9);
        }
    }

    #[test]
    fn every_misalignment_is_a_distinct_coefficient_of_the_dh_model() {
        let coefs = dh_model().coefs();
        let mut seen = Vec::new();
        for m in &CORRESPONDENCE {
            assert!(coefs.contains(&m.coef()), "{}", m.id);
            assert!(
                !seen.contains(&m.coef()),
                "{} maps onto a taken coefficient",
                m.id
            );
            seen.push(m.coef());
            assert_eq!(Misalignment::parse(m.id), Some(m));
        }
    }
}
