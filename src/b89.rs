//! The ASME B89.4.19 performance tests of a laser tracker, simulated: the
//! two-face tests and the length tests, what a tracker with given errors
//! shows in each, and each test's sensitivity to each error parameter.
//!
//! # Why
//!
//! The standard's tests are how a tracker is accepted and re-verified; the
//! paper (Section 1) sets its calibration against them. Which test sees which
//! misalignment decides what a verification can vouch for: a range offset is
//! invisible to every two-face test, and so is an even encoder harmonic
//! (an odd one cancels in the face average instead); a beam tilt grows
//! with distance. Simulating the tests through the
//! same forward model as everything else answers that for any parameter set,
//! the physical misalignments of [`crate::physical`] or the paper's DH
//! coefficients alike.
//!
//! # The tests (positions after B89.4.19-2006 and Muralikrishnan et al., 2009)
//!
//! * **Two-face**: one reflector read in the front and the back face; the
//!   test's error is the distance between the two reported points. At each
//!   horizontal distance, height (relative to the tracker) and azimuth of the
//!   settings — the standard's 1, 3 and 6 m at three heights and four
//!   azimuths by default (36 tests).
//! * **Length**: a reference length (2.3 m, the standard's scale bar) read at
//!   both ends in the front face; the error is the measured minus the true
//!   length. The bar is centred at each distance, height and azimuth,
//!   across the line of sight — horizontal, vertical, right and left
//!   diagonal — or along it (`ranging`: from the distance outwards). At the
//!   tracker's own height (the default) a bar lies symmetric about the line
//!   of sight, and an error that moves its two ends symmetrically cancels
//!   (a beam tilt, for one): other heights show it.
//!
//! A test's error under given parameters is simulated exactly: the tracker
//! with errors reads each point ([`ErrorParams::reading_of`]) and reports its
//! nominal coordinates. A sensitivity is linear, at zero error: the
//! reported point moves by `−Δ`, `Δ` the forward model's derivative.

use crate::error_model::{ErrorParams, Links};
use crate::kinematics::{Face, nominal_point, nominal_reading};
use nalgebra::Vector3;

/// Where the tests are made (metres and degrees).
#[derive(Clone, Debug, PartialEq)]
pub struct Positions {
    /// The reference length, m.
    pub length_m: f64,
    /// Horizontal distances of the bar's centre (of its near end, ranging), m.
    pub length_distances_m: Vec<f64>,
    /// Heights of the bar's centre above the tracker, m.
    pub length_heights_m: Vec<f64>,
    /// Horizontal distances of the two-face reflector, m.
    pub two_face_distances_m: Vec<f64>,
    /// Heights of the two-face reflector above the tracker, m.
    pub two_face_heights_m: Vec<f64>,
    /// Azimuths of every test, degrees.
    pub azimuths_deg: Vec<f64>,
}

impl Default for Positions {
    fn default() -> Positions {
        Positions {
            length_m: 2.3,
            length_distances_m: vec![1.0, 6.0],
            length_heights_m: vec![0.0],
            two_face_distances_m: vec![1.0, 3.0, 6.0],
            two_face_heights_m: vec![-1.5, 0.0, 1.5],
            azimuths_deg: vec![0.0, 90.0, 180.0, 270.0],
        }
    }
}

/// A length test's bar orientation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Orientation {
    Horizontal,
    Vertical,
    RightDiagonal,
    LeftDiagonal,
    /// Along the line of sight.
    Ranging,
}

impl Orientation {
    pub const ALL: [Orientation; 5] = [
        Orientation::Horizontal,
        Orientation::Vertical,
        Orientation::RightDiagonal,
        Orientation::LeftDiagonal,
        Orientation::Ranging,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Orientation::Horizontal => "horizontal",
            Orientation::Vertical => "vertical",
            Orientation::RightDiagonal => "right-diagonal",
            Orientation::LeftDiagonal => "left-diagonal",
            Orientation::Ranging => "ranging",
        }
    }
}

/// One test: its name, where it is, and the points it reads (both the same
/// reflector for a two-face test).
#[derive(Clone, Debug, PartialEq)]
pub struct Test {
    /// `two-face d3m h+1.5m az90`, `length horizontal d6m az180`.
    pub id: String,
    /// `None` for a two-face test.
    pub orientation: Option<Orientation>,
    pub distance_m: f64,
    pub height_m: f64,
    pub az_deg: f64,
    /// The points read, station frame, mm.
    pub a: Vector3<f64>,
    pub b: Vector3<f64>,
}

/// Every test at `pos`: the two-face tests, then the length tests, each
/// distance by azimuth in the settings' order.
pub fn tests(pos: &Positions) -> Vec<Test> {
    let mut out = Vec::new();
    for &d in &pos.two_face_distances_m {
        for &h in &pos.two_face_heights_m {
            for &az in &pos.azimuths_deg {
                let p = horizontal(az, d * 1e3) + Vector3::new(0.0, 0.0, h * 1e3);
                out.push(Test {
                    id: format!("two-face d{d}m h{h:+}m az{az}"),
                    orientation: None,
                    distance_m: d,
                    height_m: h,
                    az_deg: az,
                    a: p,
                    b: p,
                });
            }
        }
    }
    let half = 0.5 * pos.length_m * 1e3;
    for o in Orientation::ALL {
        for &d in &pos.length_distances_m {
            for (&h, &az) in pos
                .length_heights_m
                .iter()
                .flat_map(|h| pos.azimuths_deg.iter().map(move |az| (h, az)))
            {
                let lift = Vector3::new(0.0, 0.0, h * 1e3);
                let centre = horizontal(az, d * 1e3) + lift;
                let across = horizontal(az + 90.0, 1.0);
                let up = Vector3::z();
                let (a, b) = match o {
                    Orientation::Horizontal => (centre - half * across, centre + half * across),
                    Orientation::Vertical => (centre - half * up, centre + half * up),
                    Orientation::RightDiagonal => {
                        let u = (across + up) / 2f64.sqrt();
                        (centre - half * u, centre + half * u)
                    }
                    Orientation::LeftDiagonal => {
                        let u = (up - across) / 2f64.sqrt();
                        (centre - half * u, centre + half * u)
                    }
                    Orientation::Ranging => (centre, horizontal(az, d * 1e3 + 2.0 * half) + lift),
                };
                out.push(Test {
                    id: format!("length {} d{d}m h{h:+}m az{az}", o.name()),
                    orientation: Some(o),
                    distance_m: d,
                    height_m: h,
                    az_deg: az,
                    a,
                    b,
                });
            }
        }
    }
    out
}

/// The point at horizontal distance `r_mm` in azimuth `az_deg`.
fn horizontal(az_deg: f64, r_mm: f64) -> Vector3<f64> {
    let (s, c) = az_deg.to_radians().sin_cos();
    Vector3::new(r_mm * c, r_mm * s, 0.0)
}

impl Test {
    pub fn kind(&self) -> &'static str {
        if self.orientation.is_some() {
            "length"
        } else {
            "two-face"
        }
    }

    /// The faces of the two readings.
    fn faces(&self) -> [Face; 2] {
        match self.orientation {
            None => [Face::Front, Face::Back],
            Some(_) => [Face::Front, Face::Front],
        }
    }

    /// The test's error, µm, from the two reported points: the two-face
    /// separation, or the measured minus the true length.
    fn error_um(&self, ra: &Vector3<f64>, rb: &Vector3<f64>) -> f64 {
        match self.orientation {
            None => (ra - rb).norm() * 1e3,
            Some(_) => ((ra - rb).norm() - (self.a - self.b).norm()) * 1e3,
        }
    }
}

/// Each test's error, µm, shown by a tracker with `errors` (of either
/// model); `Err` names the first test whose point it cannot read.
pub fn simulate(tests: &[Test], errors: &ErrorParams) -> Result<Vec<f64>, String> {
    let eval = errors.evaluator();
    tests
        .iter()
        .map(|t| {
            let [fa, fb] = t.faces();
            let read = |p, f| {
                eval.reading_of(p, f)
                    .ok()
                    .map(nominal_point)
                    .ok_or_else(|| format!("the tracker cannot read the points of `{}`", t.id))
            };
            Ok(t.error_um(&read(&t.a, fa)?, &read(&t.b, fb)?))
        })
        .collect()
}

/// A parameter as a direction in the DH model's coefficients: one physical
/// misalignment (its coefficient and sign, [`crate::physical`]) or one DH
/// coefficient (sign 1) — `(coefficient index, sign)`, per display unit.
pub type Direction = (usize, f64);

/// Sensitivities below this (µm per µm or µrad) are the round-off of
/// points millimetres to metres away, not a test seeing a parameter.
pub const ROUND_OFF_UM: f64 = 1e-6;

/// A sensitivity, exactly zero below [`ROUND_OFF_UM`].
fn snap(s: f64) -> f64 {
    if s.abs() < ROUND_OFF_UM { 0.0 } else { s }
}

/// `[test][direction]`: each test's error per display unit of each
/// direction (µm per µm or per µrad), linear at zero error. Two-face
/// sensitivities are the separation's length (≥ 0); length sensitivities
/// are signed; either is exactly zero below [`ROUND_OFF_UM`].
pub fn sensitivity(tests: &[Test], zero: &ErrorParams, directions: &[Direction]) -> Vec<Vec<f64>> {
    let eval = zero.evaluator();
    let mut cols = Vec::new();
    // The reported point's shift per unit of each direction: −Δ.
    let mut shifts = |p: &Vector3<f64>, face: Face| -> Vec<Vector3<f64>> {
        let q = nominal_reading(p, face).joints();
        eval.point_with_jacobian(q, &Links::new(q), &mut cols);
        directions
            .iter()
            .map(|&(c, sign)| -sign * cols[c])
            .collect()
    };
    tests
        .iter()
        .map(|t| {
            let [fa, fb] = t.faces();
            let (sa, sb) = (shifts(&t.a, fa), shifts(&t.b, fb));
            // A two-face test reads one point: its separation has a length,
            // a length test's change lies along the bar.
            let along = t.orientation.map(|_| (t.a - t.b).normalize());
            sa.iter()
                .zip(&sb)
                .map(|(da, db)| {
                    let moved = da - db;
                    snap(1e3 * along.map_or_else(|| moved.norm(), |u| u.dot(&moved)))
                })
                .collect()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error_model::ErrorModel;
    use crate::physical::{self, CORRESPONDENCE};
    use crate::trackers::TrackerModel;

    fn physical_directions(zero: &ErrorParams) -> Vec<Direction> {
        CORRESPONDENCE
            .iter()
            .map(|m| {
                let at = zero.coefs().iter().position(|c| *c == m.coef()).unwrap();
                (at, m.sign)
            })
            .collect()
    }

    #[test]
    fn the_default_positions_are_the_standards_counts() {
        let t = tests(&Positions::default());
        assert_eq!(t.iter().filter(|t| t.kind() == "two-face").count(), 36);
        assert_eq!(t.iter().filter(|t| t.kind() == "length").count(), 40);
        for x in &t {
            if x.kind() == "length" {
                assert!(((x.a - x.b).norm() - 2300.0).abs() < 1e-9, "{}", x.id);
            }
        }
    }

    #[test]
    fn simulated_errors_are_the_linear_sensitivities_for_small_errors() {
        let t = tests(&Positions::default());
        let zero = ErrorParams::zero(&physical::dh_model());
        let dirs = physical_directions(&zero);
        let s = sensitivity(&t, &zero, &dirs);
        for (k, m) in CORRESPONDENCE.iter().enumerate() {
            let v = 5.0;
            let sim = simulate(&t, &physical::to_dh(&[(m, v)])).unwrap();
            for (i, test) in t.iter().enumerate() {
                let lin = v * s[i][k];
                // What is left is second order: v²·d ≈ (5 µrad)²·6 m ≈ 0.2 nm.
                assert!(
                    (sim[i] - lin).abs() <= 1e-3 * lin.abs() + 1e-3,
                    "{} on {}: simulated {} µm, linear {lin} µm",
                    m.id,
                    test.id,
                    sim[i]
                );
            }
        }
    }

    #[test]
    fn the_mirror_offset_separates_the_faces_by_four_times_itself() {
        // It moves a point by 2·mo along the mirror's normal, which the
        // back face reverses (`trackers::mirror_tracker::tests`).
        let t = tests(&Positions::default());
        let zero = ErrorParams::zero(&ErrorModel::of(
            TrackerModel::parse("mirror-tracker").unwrap(),
        ));
        let every: Vec<Direction> = (0..zero.coefs().len()).map(|k| (k, 1.0)).collect();
        let s = sensitivity(&t, &zero, &every);
        let at = |id: &str| {
            zero.coefs()
                .iter()
                .position(|c| c.param.id() == id)
                .unwrap()
        };
        let k = at("mirror_offset");
        for (x, row) in t.iter().zip(&s) {
            if x.kind() == "two-face" {
                assert!((row[k] - 4.0).abs() < 1e-6, "{}: {}", x.id, row[k]);
            }
        }
        // And the slopes are the simulated errors'.
        let k = at("mirror_tilt");
        let mut e = zero.clone();
        e.values_mut()[k] = 3.0;
        let sim = simulate(&t, &e).unwrap();
        for (i, x) in t.iter().enumerate() {
            let lin = 3.0 * s[i][k];
            assert!((sim[i] - lin).abs() <= 1e-3 * lin.abs() + 1e-3, "{}", x.id);
        }
    }

    #[test]
    fn which_tests_see_which_misalignment() {
        let t = tests(&Positions::default());
        let zero = ErrorParams::zero(&physical::dh_model());
        let s = sensitivity(&t, &zero, &physical_directions(&zero));
        let col = |id: &str| {
            CORRESPONDENCE
                .iter()
                .position(|m| m.id == id)
                .unwrap_or_else(|| panic!("{id}"))
        };
        let max_over = |id: &str, kind: &str| {
            t.iter()
                .zip(&s)
                .filter(|(x, _)| x.kind() == kind)
                .map(|(_, row)| row[col(id)].abs())
                .fold(0.0, f64::max)
        };
        // The range offset: no two-face test sees it, nor a bar along the
        // beam (both ends move alike); a bar across the line of sight does.
        assert_eq!(max_over("range_offset", "two-face"), 0.0);
        for (x, row) in t.iter().zip(&s) {
            if x.orientation == Some(Orientation::Ranging) {
                assert_eq!(row[col("range_offset")], 0.0, "{}", x.id);
            }
        }
        // Beam offset: 2 µm per µm in every two-face test.
        for (x, row) in t.iter().zip(&s) {
            if x.kind() == "two-face" {
                assert!((row[col("beam_offset_el")] - 2.0).abs() < 1e-9, "{}", x.id);
            }
        }
        // Beam tilt: 2·d per µrad, the farthest two-face test the largest.
        let far = (6f64.powi(2) + 1.5f64.powi(2)).sqrt();
        assert!((max_over("beam_tilt_el", "two-face") - 2.0 * far).abs() < 1e-6);
        // Even harmonics: no two-face test sees them, length tests do.
        assert_eq!(max_over("az_h2_sin", "two-face"), 0.0);
        assert!(max_over("az_h2_sin", "length") > 1.0);
        // A bar at the tracker's height is symmetric about the line of
        // sight: a beam tilt moves both ends alike and no length test sees
        // it; raised by a metre, the horizontal and diagonal bars do.
        assert_eq!(max_over("beam_tilt_el", "length"), 0.0);
        let raised = tests(&Positions {
            length_heights_m: vec![1.0],
            ..Positions::default()
        });
        let s = sensitivity(&raised, &zero, &physical_directions(&zero));
        let seen = raised
            .iter()
            .zip(&s)
            .filter(|(x, _)| x.kind() == "length")
            .map(|(_, row)| row[col("beam_tilt_el")].abs())
            .fold(0.0, f64::max);
        assert!(seen > 0.1, "{seen}");
    }
}
