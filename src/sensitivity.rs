//! Sensitivity of the measured point to each error parameter (Section 6):
//! the error field over a mesh with one parameter at 1 µm or 1 µrad, which
//! of θ, φ and d that error varies with, where it is largest and smallest
//! (the check of Figure 12), and — where ours differs from the paper's
//! statement — why.
//!
//! It exists because Section 6 is the test that decides where the error
//! transforms of Eq. (8) sit (NOTES items 5 and 11): a faithful tool shows
//! the classification parameter by parameter and explains any difference
//! instead of hiding it.

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
/// parameter `p` at `value` (µm or µrad): reported minus true position. The
/// tracker is the model `p` belongs to (either construction).
pub fn error_field(
    p: ParamId,
    value: f64,
    points: &[Vector3<f64>],
) -> Result<Vec<FieldPoint>, InverseError> {
    let mut e = ErrorParams::zero(&ErrorModel::of(p.tracker()));
    let k = e
        .coefs()
        .iter()
        .position(|c| c.param == p)
        .expect("every parameter of a model has its constant");
    e.values_mut()[k] = value;
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

/// Section 6's statement for each parameter (NOTES item 11); none for a
/// parameter of another tracker than the paper's.
pub fn paper_statement(p: ParamId) -> Option<&'static str> {
    p.tracker().plugin().section6(p.local())
}

/// Section 6's statement as a [`Classification`], for comparing field by field.
pub fn paper_classification(p: ParamId) -> Option<Classification> {
    let statement = paper_statement(p)?;
    let varies = statement.strip_prefix("varies with ").unwrap_or_default();
    let with = |q: &str| varies.split(", ").any(|x| x == q);
    Some(Classification {
        produces_error: statement != "no error",
        theta: with("θ"),
        phi: with("φ"),
        d: with("d"),
    })
}

/// How many distinct values of θ, φ and d a mesh has: a coordinate with one
/// value cannot show a variation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MeshSpan {
    pub theta: usize,
    pub phi: usize,
    pub d: usize,
}

impl MeshSpan {
    pub fn of(field: &[FieldPoint]) -> MeshSpan {
        let count = |f: &dyn Fn(&FieldPoint) -> f64| {
            let mut v: Vec<f64> = field.iter().map(f).collect();
            v.sort_by(f64::total_cmp);
            v.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
            v.len()
        };
        MeshSpan {
            theta: count(&|f| f.at.az),
            phi: count(&|f| f.at.el),
            d: count(&|f| f.at.d),
        }
    }
}

/// Why `ours` differs from the paper's statement for `p`, in words; empty
/// when they agree or the paper says nothing of `p`. `rel_tol` is the
/// threshold [`classify`] used.
pub fn explain_difference(
    p: ParamId,
    ours: &Classification,
    span: MeshSpan,
    rel_tol: f64,
) -> String {
    let Some(paper) = paper_classification(p) else {
        return String::new();
    };
    if ours == &paper {
        return String::new();
    }
    if ours.produces_error != paper.produces_error {
        return if ours.produces_error {
            format!(
                "{} moves the measured point on this mesh; the paper says it produces no error",
                p.symbol()
            )
        } else {
            format!(
                "{} moves no point by more than 1e-5 µm on this mesh; the paper says it produces an error",
                p.symbol()
            )
        };
    }
    let coords = [
        (ours.theta, paper.theta, "θ", span.theta),
        (ours.phi, paper.phi, "φ", span.phi),
        (ours.d, paper.d, "d", span.d),
    ];
    let mut out = Vec::new();
    for (o, q, name, n) in coords {
        if o == q {
            continue;
        }
        out.push(if o {
            format!("its error varies with {name} on this mesh, which the paper does not say")
        } else if n < 2 {
            format!("the mesh has a single {name}, so a variation with {name} cannot show")
        } else if p.id() == "ez1" && name == "θ" {
            // The one difference on the paper's sphere (NOTES item 11).
            "εz1 is a rotation about the vertical (standing) axis: it turns every point about \
             that axis by the same angle, so its error, εz1·d·cos φ, depends on the elevation \
             φ and the distance d but cannot vary with the azimuth θ"
                .to_string()
        } else {
            format!("its error does not vary with {name} by more than {rel_tol:e} of its largest value on this mesh")
        });
    }
    out.join("; ")
}

/// Where on a grid of directions at one distance the error of a parameter
/// is largest and where smallest — the check of the paper's reading of
/// Figure 12 ("the maximum and minimum error values correspond to maximum,
/// minimum and zero values of φ and also on θ every π/4").
#[derive(Clone, Debug, PartialEq)]
pub struct Extremes {
    pub max_um: f64,
    pub min_um: f64,
    /// The (θ, φ) in degrees (the paper's θ = az − 90°) of every grid point
    /// whose error ties with the maximum (within [`TIE_REL`] of the largest
    /// error); likewise for the minimum.
    pub max_at: Vec<(f64, f64)>,
    pub min_at: Vec<(f64, f64)>,
}

/// Grid points count as tied with the extreme within this fraction of the
/// largest error: exact ties (εx1 is d·1 µrad on a whole meridian) differ by
/// rounding only.
const TIE_REL: f64 = 1e-6;

/// The error of `p` at `value` on the grid `theta_deg × phi_deg` (the
/// paper's θ and φ) at distance `d_mm`, row-major in φ: `[iφ][iθ]` in µm.
pub fn direction_grid(
    p: ParamId,
    value: f64,
    theta_deg: &[f64],
    phi_deg: &[f64],
    d_mm: f64,
) -> Result<Vec<Vec<f64>>, InverseError> {
    let pts: Vec<Vector3<f64>> = phi_deg
        .iter()
        .flat_map(|&phi| {
            theta_deg.iter().map(move |&theta| {
                let (az, el) = ((theta + 90.0).to_radians(), phi.to_radians());
                d_mm * Vector3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin())
            })
        })
        .collect();
    let field = error_field(p, value, &pts)?;
    Ok(field
        .chunks(theta_deg.len().max(1))
        .map(|row| row.iter().map(FieldPoint::magnitude_um).collect())
        .collect())
}

/// The extremes of a [`direction_grid`].
pub fn extremes(grid: &[Vec<f64>], theta_deg: &[f64], phi_deg: &[f64]) -> Extremes {
    let all = || grid.iter().flatten().copied();
    let max = all().fold(f64::NEG_INFINITY, f64::max);
    let min = all().fold(f64::INFINITY, f64::min);
    let tol = TIE_REL * max.abs();
    let at = |target: f64| {
        let mut v = Vec::new();
        for (i, row) in grid.iter().enumerate() {
            for (j, &e) in row.iter().enumerate() {
                if (e - target).abs() <= tol {
                    v.push((theta_deg[j], phi_deg[i]));
                }
            }
        }
        v
    };
    Extremes {
        max_um: max,
        min_um: min,
        max_at: at(max),
        min_at: at(min),
    }
}

impl Extremes {
    /// E.g. "max 15.0000 µm at θ = −180°, 0° (any φ); min 0.0000 µm at θ = −90°, 90°, φ = 0°".
    pub fn describe(&self, theta_deg: &[f64], phi_deg: &[f64]) -> String {
        let part = |name: &str, um: f64, at: &[(f64, f64)]| {
            format!("{name} {um:.4} µm at {}", place(at, theta_deg, phi_deg))
        };
        format!(
            "{}; {}",
            part("max", self.max_um, &self.max_at),
            part("min", self.min_um, &self.min_at)
        )
    }

    /// Whether the extremes sit where the paper says: every θ of an
    /// extreme a multiple of 45° (π/4), every φ zero or the grid's lowest
    /// or highest — or the extreme does not depend on that coordinate.
    pub fn as_paper(&self, theta_deg: &[f64], phi_deg: &[f64]) -> bool {
        let (lo, hi) = (
            phi_deg.iter().copied().fold(f64::INFINITY, f64::min),
            phi_deg.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        );
        [&self.max_at, &self.min_at].iter().all(|at| {
            let (thetas, phis) = coordinates(at);
            let theta_ok = thetas.len() == distinct(theta_deg).len()
                || thetas
                    .iter()
                    .all(|t| (t / 45.0 - (t / 45.0).round()).abs() < 1e-9);
            let phi_ok = phis.len() == distinct(phi_deg).len()
                || phis
                    .iter()
                    .all(|&f| f.abs() < 1e-9 || (f - lo).abs() < 1e-9 || (f - hi).abs() < 1e-9);
            theta_ok && phi_ok
        })
    }
}

fn distinct(v: &[f64]) -> Vec<f64> {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    v
}

fn coordinates(at: &[(f64, f64)]) -> (Vec<f64>, Vec<f64>) {
    (
        distinct(&at.iter().map(|a| a.0).collect::<Vec<_>>()),
        distinct(&at.iter().map(|a| a.1).collect::<Vec<_>>()),
    )
}

/// "θ = 0°, 180° (any φ)": a coordinate that takes every grid value is "any".
fn place(at: &[(f64, f64)], theta_deg: &[f64], phi_deg: &[f64]) -> String {
    let (thetas, phis) = coordinates(at);
    let list = |name: &str, v: &[f64], all: &[f64]| {
        if v.len() == distinct(all).len() {
            None
        } else {
            let s: Vec<String> = v
                .iter()
                .map(|x| {
                    format!(
                        "{}°",
                        crate::table::format_float(*x, 1)
                            .trim_end_matches(".0")
                            .replace('-', "−")
                    )
                })
                .collect();
            Some(format!("{name} = {}", s.join(", ")))
        }
    };
    match (list("θ", &thetas, theta_deg), list("φ", &phis, phi_deg)) {
        (Some(t), Some(f)) => format!("{t}, {f}"),
        (Some(t), None) => format!("{t} (any φ)"),
        (None, Some(f)) => format!("{f} (any θ)"),
        (None, None) => "every direction".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh;
    use crate::trackers::TrackerModel;

    #[test]
    fn section6_classification() {
        let pts: Vec<Vector3<f64>> =
            mesh::sphere(&mesh::SPHERE_H_DEG, &mesh::SPHERE_V_DEG, &mesh::SPHERE_R_MM)
                .into_iter()
                .map(|m| m.p)
                .collect();
        for p in ParamId::of(TrackerModel::default()) {
            let field = error_field(p, 1.0, &pts).unwrap();
            let ours = classify(&field, 1e-6).describe();
            // The one difference from the paper: a rotation about the
            // vertical axis cannot vary with the azimuth.
            let expect = if p.id() == "ez1" {
                "varies with φ, d"
            } else {
                paper_statement(p).unwrap()
            };
            assert_eq!(ours, expect, "parameter {}", p.id());
        }
    }

    #[test]
    fn paper_classification_says_what_the_paper_says() {
        for p in ParamId::of(TrackerModel::default()) {
            assert_eq!(
                paper_classification(p).map(|c| c.describe()).as_deref(),
                paper_statement(p)
            );
        }
        // The paper says nothing of the mirror tracker.
        for p in ParamId::of(TrackerModel::parse("mirror-tracker").unwrap()) {
            assert_eq!(paper_statement(p), None);
            assert_eq!(
                explain_difference(
                    p,
                    &Classification {
                        produces_error: true,
                        theta: true,
                        phi: true,
                        d: true
                    },
                    MeshSpan {
                        theta: 2,
                        phi: 2,
                        d: 2
                    },
                    1e-6
                ),
                ""
            );
        }
    }

    #[test]
    fn mirror_offsets_are_constant_errors_and_its_tilts_vary() {
        // A mirror offset moves every point by 2·mo along the mirror normal
        // (`mirror` tests), whose direction follows the elevation; the
        // incoming beam's offset is a constant shift of every point.
        let pts: Vec<Vector3<f64>> =
            mesh::sphere(&mesh::SPHERE_H_DEG, &mesh::SPHERE_V_DEG, &mesh::SPHERE_R_MM)
                .into_iter()
                .map(|m| m.p)
                .collect();
        let class = |id: &str| {
            classify(
                &error_field(ParamId::parse(id).unwrap(), 1.0, &pts).unwrap(),
                1e-6,
            )
            .describe()
        };
        assert_eq!(class("beam_offset_x"), "constant");
        assert_eq!(class("range_offset"), "constant");
        assert_eq!(class("transit_tilt"), "varies with φ, d");
    }

    #[test]
    fn differences_are_explained_and_agreement_is_silent() {
        let span = MeshSpan {
            theta: 12,
            phi: 8,
            d: 5,
        };
        let ez1 = ParamId::parse("ez1").unwrap();
        let ours = Classification {
            produces_error: true,
            theta: false,
            phi: true,
            d: true,
        };
        let note = explain_difference(ez1, &ours, span, 1e-6);
        assert!(
            note.contains("vertical") && note.contains("cannot vary with the azimuth θ"),
            "{note}"
        );
        let ex1 = ParamId::parse("ex1").unwrap();
        let paper = paper_classification(ex1).unwrap();
        assert_eq!(explain_difference(ex1, &paper, span, 1e-6), "");
        // A mesh with one distance cannot show a variation with d.
        let flat = Classification { d: false, ..paper };
        let note = explain_difference(ex1, &flat, MeshSpan { d: 1, ..span }, 1e-6);
        assert_eq!(
            note,
            "the mesh has a single d, so a variation with d cannot show"
        );
    }

    #[test]
    fn extremes_of_a_standing_axis_tilt() {
        // εx1 tilts the standing axis about x: |Δ| = εx1·d·sqrt(1 − cos²φ·cos²az),
        // largest (εx1·d) where the point is perpendicular to x — az = ±90°,
        // θ = 0°, 180° — and zero along x: θ = ±90°, φ = 0.
        let theta: Vec<f64> = (0..8).map(|k| -180.0 + 45.0 * k as f64).collect();
        let phi = [-30.0, 0.0, 30.0];
        let ex1 = ParamId::parse("ex1").unwrap();
        let g = direction_grid(ex1, 1.0, &theta, &phi, 10_000.0).unwrap();
        let e = extremes(&g, &theta, &phi);
        assert!(
            (e.max_um - 10.0).abs() < 1e-6 && e.min_um.abs() < 1e-6,
            "{e:?}"
        );
        assert_eq!(
            e.describe(&theta, &phi),
            "max 10.0000 µm at θ = −180°, 0° (any φ); min 0.0000 µm at θ = −90°, 90°, φ = 0°"
        );
        assert!(e.as_paper(&theta, &phi));
        // At φ = ±30° and az = 45° the error is d·sqrt(1 − 0.75·0.5).
        let at = g[0][5];
        assert!((at - 10.0 * (1.0f64 - 0.375).sqrt()).abs() < 1e-6, "{at}");
    }
}
