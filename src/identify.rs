//! Identification against known reflector positions (Section 5.1, Eq. 11):
//! find the error parameters that bring the corrected readings onto the
//! reference coordinates,
//!
//! ```text
//! Φ = Σᵢ ‖P(qᵢ; p) − Xᵢ‖²                                      Eq. (11)
//! ```
//!
//! solved by Levenberg–Marquardt with the analytic Jacobian of
//! [`crate::error_model`]. Only what the data determine is estimated: the
//! free coefficients are restricted to the span of the Jacobian's non-null
//! right singular vectors at the start point, so the undetermined directions
//! keep their start values (zero by default) — the minimum-norm solution —
//! and the result says so, naming them.

use crate::determined::Determined;
use crate::error_model::{ErrorParams, Links};
use crate::identifiability::{Analysis, Combination};
use crate::kinematics::{Joints, Reading};
use crate::solver::{DenseNormal, LevenbergMarquardt};
use anyhow::{Result, bail};
use argmin::core::{Error as ArgminError, Jacobian, Operator};
use nalgebra::{DMatrix, DVector, Vector3};

/// A reading of a reflector whose true position is known.
#[derive(Clone, Copy, Debug)]
pub struct KnownPoint {
    pub reading: Reading,
    /// Reference coordinates, mm.
    pub reference: Vector3<f64>,
}

/// Settings of the identification.
#[derive(Clone, Debug)]
pub struct Settings {
    /// Relative singular-value threshold for the rank.
    pub rank_tol: f64,
    pub max_iters: u64,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            rank_tol: crate::identifiability::DEFAULT_REL_TOL,
            max_iters: 100,
        }
    }
}

/// What the identification found.
#[derive(Clone, Debug)]
pub struct Identification {
    /// The estimate: free coefficients fitted, fixed ones at their start value.
    pub params: ErrorParams,
    pub free: Vec<bool>,
    /// Standard uncertainty of each free coefficient's minimum-norm estimate
    /// (from the residual variance and the covariance); `None` when fixed.
    pub std: Vec<Option<f64>>,
    /// Singular values of the Jacobian of the free coefficients (µm per unit).
    pub analysis: Analysis,
    /// The free-coefficient indices the analysis columns refer to.
    pub free_index: Vec<usize>,
    /// Undetermined directions, in free-coefficient indices.
    pub combinations: Vec<Combination>,
    pub rms_before_um: f64,
    pub rms_after_um: f64,
    pub iterations: u64,
    pub stop_reason: &'static str,
    pub n_observations: usize,
}

/// A known point prepared for repeated evaluation: its joints and nominal
/// link rotations do not change while the parameters do.
struct Prepared {
    q: Joints,
    links: Links,
    reference: Vector3<f64>,
}

fn prepare(obs: &[KnownPoint]) -> Vec<Prepared> {
    obs.iter()
        .map(|o| {
            let q = o.reading.joints();
            Prepared {
                q,
                links: Links::new(q),
                reference: o.reference,
            }
        })
        .collect()
}

/// Residuals `P(qᵢ; p) − Xᵢ` in µm, three per point.
fn residuals(params: &ErrorParams, obs: &[Prepared]) -> DVector<f64> {
    let mut r = DVector::zeros(3 * obs.len());
    let eval = params.evaluator();
    for (i, o) in obs.iter().enumerate() {
        let p = eval.point(o.q, &o.links);
        r.fixed_rows_mut::<3>(3 * i)
            .copy_from(&((p - o.reference) * 1e3));
    }
    r
}

/// The Jacobian of [`residuals`] with respect to the listed coefficients,
/// µm per display unit (3 rows per point).
fn jacobian(params: &ErrorParams, obs: &[Prepared], columns: &[usize]) -> DMatrix<f64> {
    let mut j = DMatrix::zeros(3 * obs.len(), columns.len());
    let mut cols = Vec::new();
    let eval = params.evaluator();
    for (i, o) in obs.iter().enumerate() {
        eval.point_with_jacobian(o.q, &o.links, &mut cols);
        for (k, &c) in columns.iter().enumerate() {
            for a in 0..3 {
                j[(3 * i + a, k)] = cols[c][a] * 1e3;
            }
        }
    }
    j
}

/// Eq. (11) in the coordinates `z` of the determined directions:
/// `p = p₀ + S·B·z` with `S` the free coefficients and `B` the row basis.
struct Eq11<'a> {
    start: &'a ErrorParams,
    obs: &'a [Prepared],
    free_index: &'a [usize],
    basis: &'a DMatrix<f64>,
}

impl Eq11<'_> {
    fn params(&self, z: &DVector<f64>) -> ErrorParams {
        self.start.plus(self.free_index, &(self.basis * z))
    }
}

impl Operator for Eq11<'_> {
    type Param = DVector<f64>;
    type Output = DVector<f64>;
    fn apply(&self, z: &DVector<f64>) -> Result<DVector<f64>, ArgminError> {
        Ok(residuals(&self.params(z), self.obs))
    }
}

impl Jacobian for Eq11<'_> {
    type Param = DVector<f64>;
    type Jacobian = DenseNormal;
    /// `JᵀJ` and `Jᵀr` accumulated point by point over the free coefficients,
    /// then projected on the determined directions: the 3n × k Jacobian is
    /// never formed.
    fn jacobian(&self, z: &DVector<f64>) -> Result<DenseNormal, ArgminError> {
        let params = self.params(z);
        let f = self.free_index.len();
        let mut jtj = DMatrix::<f64>::zeros(f, f);
        let mut g = DVector::<f64>::zeros(f);
        let mut cols = Vec::new();
        let mut block = vec![Vector3::zeros(); f];
        let eval = params.evaluator();
        for o in self.obs {
            let p = eval.point_with_jacobian(o.q, &o.links, &mut cols);
            let r = (p - o.reference) * 1e3;
            for (k, &c) in self.free_index.iter().enumerate() {
                block[k] = cols[c] * 1e3;
            }
            for a in 0..f {
                g[a] += block[a].dot(&r);
                for b in a..f {
                    jtj[(a, b)] += block[a].dot(&block[b]);
                }
            }
        }
        for a in 0..f {
            for b in 0..a {
                jtj[(a, b)] = jtj[(b, a)];
            }
        }
        let bt = self.basis.transpose();
        Ok(DenseNormal::new(&bt * jtj * self.basis, bt * g))
    }
}

/// Identifies the free coefficients of `start` from known points.
pub fn identify(
    obs: &[KnownPoint],
    start: &ErrorParams,
    free: &[bool],
    settings: &Settings,
) -> Result<Identification> {
    if obs.is_empty() {
        bail!("no readings to identify from");
    }
    let obs = &prepare(obs)[..];
    let r0 = residuals(start, obs);
    let free_index: Vec<usize> = (0..free.len()).filter(|&i| free[i]).collect();
    let det = Determined::analyse(
        &jacobian(start, obs, &free_index),
        start,
        free,
        settings.rank_tol,
    )?;
    let basis = det.basis();
    let rank = det.rank();

    let problem = Eq11 {
        start,
        obs,
        free_index: &free_index,
        basis,
    };
    let (z, r, iterations, stop_reason) = if rank == 0 {
        (DVector::zeros(0), r0.clone(), 0, "nothing-to-estimate")
    } else {
        // The problem is nearly linear: start with little damping.
        let fit = LevenbergMarquardt::new()
            .with_initial_lambda(1e-6)
            .and_then(|lm| lm.minimize(problem, DVector::zeros(rank), settings.max_iters))
            .map_err(|e| anyhow::anyhow!("identification failed: {e}"))?;
        (fit.x, fit.residuals, fit.iterations, fit.reason)
    };
    let params = det.params(start, &z);
    let std = match rank {
        0 => vec![None; free.len()],
        _ => {
            let jz = jacobian(&params, obs, &free_index) * basis;
            det.scatter_covariance(&jz, &r)
                .map_or_else(|| vec![None; free.len()], |c| det.std(&c, free.len()))
        }
    };
    let rms = |r: &DVector<f64>| (r.norm_squared() / obs.len() as f64).sqrt();
    Ok(Identification {
        params,
        free: free.to_vec(),
        std,
        analysis: det.analysis,
        free_index: det.free_index,
        combinations: det.combinations,
        rms_before_um: rms(&r0),
        rms_after_um: rms(&r),
        iterations,
        stop_reason,
        n_observations: obs.len(),
    })
}

impl Identification {
    /// A combination's determined value for the estimate, with its free
    /// coefficients mapped back to the full vector.
    pub fn determined_value(&self, c: &Combination, params: &ErrorParams) -> Option<f64> {
        let x: Vec<f64> = self
            .free_index
            .iter()
            .map(|&i| params.values()[i])
            .collect();
        c.determined_value(&x)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error_model::{ErrorModel, ParamId};
    use crate::kinematics::Face;
    use crate::mesh;

    fn observe(truth: &ErrorParams, pts: &[mesh::MeshPoint]) -> Vec<KnownPoint> {
        pts.iter()
            .map(|m| KnownPoint {
                reading: truth.reading_of(&m.p, Face::Front).unwrap(),
                reference: m.p,
            })
            .collect()
    }

    fn sphere() -> Vec<mesh::MeshPoint> {
        mesh::sphere(&mesh::SPHERE_H_DEG, &mesh::SPHERE_V_DEG, &mesh::SPHERE_R_MM)
    }

    #[test]
    fn sphere_null_space_is_the_five_redundancies() {
        let truth = ErrorParams::table2();
        let obs = observe(&truth, &sphere());
        let start = ErrorParams::zero(&ErrorModel::constant());
        let id = identify(&obs, &start, &[true; 18], &Settings::default()).unwrap();
        assert_eq!(id.analysis.rank, 13, "{:?}", id.analysis.singular_values);
        let mut texts: Vec<String> = id.combinations.iter().map(|c| c.sentence()).collect();
        texts.sort();
        assert!(
            texts.iter().any(|t| t == "εz3 has no effect on the data"),
            "{texts:?}"
        );
        for pair in [
            ("δz1", "δy2"),
            ("εz1", "εy2"),
            ("δz2", "δy3"),
            ("εz2", "εy3"),
        ] {
            assert!(
                texts
                    .iter()
                    .any(|t| t.starts_with(pair.0) && t.contains(pair.1)),
                "{pair:?} missing from {texts:?}"
            );
        }
        assert!(
            id.rms_after_um < 1e-3 * id.rms_before_um,
            "{} → {}",
            id.rms_before_um,
            id.rms_after_um
        );
    }

    #[test]
    fn truth_in_the_determined_subspace_is_recovered_exactly() {
        let obs0 = observe(&ErrorParams::table2(), &sphere());
        let start = ErrorParams::zero(&ErrorModel::constant());
        let id = identify(&obs0, &start, &[true; 18], &Settings::default()).unwrap();
        // Project Table 2 onto the determined directions and measure again.
        let b = &id.analysis.row_basis;
        let t = DVector::from_vec(vec![10.0; 18]);
        let proj = b * (b.transpose() * t);
        let truth = ErrorParams::from_parts(start.coefs().to_vec(), proj.iter().copied().collect());
        let obs = observe(&truth, &sphere());
        let id = identify(&obs, &start, &[true; 18], &Settings::default()).unwrap();
        for (k, (a, b)) in id.params.values().iter().zip(truth.values()).enumerate() {
            assert!(
                (a - b).abs() < 1e-6,
                "{}: {a} vs {b}",
                ParamId::from_index(k)
            );
        }
    }
}
