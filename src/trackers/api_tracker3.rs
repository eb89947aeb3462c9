//! The paper's tracker, API Tracker 3, as a plug-in: the laser in the
//! rotating head, its model the Denavit–Hartenberg chain of Table 1 with an
//! error transform per joint. The chain's mathematics (Eq. 6–10, the
//! analytic Jacobian) lives in [`crate::error_model`], which the paper's
//! sections define; this file is what the registry needs of it — the 18
//! parameters, the evaluator that builds the error frames once when every
//! coefficient is a constant, and the answers only the paper's tracker
//! gives: its physical misalignments for the B89 stage
//! ([`crate::physical`]) and Section 6's classification.

use super::{Evaluate, Misalignment, Model, Param};
use crate::error_model::{Coef, ErrorFrames, ErrorModel, ErrorParams, Joint, Links, Term};
use crate::kinematics::Joints;
use crate::physical::{self, CORRESPONDENCE};
use nalgebra::Vector3;

/// The plug-in.
pub struct ApiTracker3;

/// A DH parameter: translations δ in µm, rotations ε in µrad.
const fn dh(
    id: &'static str,
    symbol: &'static str,
    joint: Joint,
    angular: bool,
    meaning: &'static str,
) -> Param {
    Param {
        id,
        symbol,
        angular,
        meaning,
        joint: Some(joint),
    }
}

/// `δx, δy, δz, εx, εy, εz` of joints 1, 2, 3, in the order of the chain's
/// arrays ([`ErrorFrames::new`]).
const PARAMS: [Param; 18] = {
    use Joint::{D, Phi, Theta};
    [
        dh("dx1", "δx1", Theta, false, "joint 1 (standing axis): translation error along x"),
        dh("dy1", "δy1", Theta, false, "joint 1 (standing axis): translation error along y"),
        dh("dz1", "δz1", Theta, false, "joint 1 (standing axis): translation error along z"),
        dh("ex1", "εx1", Theta, true, "joint 1 (standing axis): rotation error about x"),
        dh("ey1", "εy1", Theta, true, "joint 1 (standing axis): rotation error about y"),
        dh("ez1", "εz1", Theta, true, "joint 1 (standing axis): rotation error about z"),
        dh("dx2", "δx2", Phi, false, "joint 2 (elevation axis): translation error along x"),
        dh("dy2", "δy2", Phi, false, "joint 2 (elevation axis): translation error along y"),
        dh("dz2", "δz2", Phi, false, "joint 2 (elevation axis): translation error along z"),
        dh("ex2", "εx2", Phi, true, "joint 2 (elevation axis): rotation error about x"),
        dh("ey2", "εy2", Phi, true, "joint 2 (elevation axis): rotation error about y"),
        dh("ez2", "εz2", Phi, true, "joint 2 (elevation axis): rotation error about z"),
        dh("dx3", "δx3", D, false, "joint 3 (beam): translation error along x"),
        dh("dy3", "δy3", D, false, "joint 3 (beam): translation error along y"),
        dh("dz3", "δz3", D, false, "joint 3 (beam): translation error along z"),
        dh("ex3", "εx3", D, true, "joint 3 (beam): rotation error about x"),
        dh("ey3", "εy3", D, true, "joint 3 (beam): rotation error about y"),
        dh("ez3", "εz3", D, true, "joint 3 (beam): rotation error about z"),
    ]
};

impl Model for ApiTracker3 {
    fn id(&self) -> &'static str {
        "api-tracker3"
    }

    fn describe(&self) -> &'static str {
        "laser in the head: the DH chain of Table 1"
    }

    fn params(&self) -> &'static [Param] {
        &PARAMS
    }

    fn evaluate<'a>(&self, params: &'a ErrorParams) -> Box<dyn Evaluate + 'a> {
        let constant = params.coefs().iter().all(|c| c.term == Term::Const);
        let q0 = Joints {
            theta: 0.0,
            phi: 0.0,
            d: 0.0,
        };
        Box::new(Chain {
            params,
            columns: params
                .coefs()
                .iter()
                .map(|c| (c.param.local(), c.param.scale()))
                .collect(),
            constant: constant.then(|| ErrorFrames::new(&params.base_at(q0))),
        })
    }

    fn misalignments(&self) -> Vec<Misalignment> {
        CORRESPONDENCE
            .iter()
            .map(|m| Misalignment {
                id: m.id,
                unit: m.unit,
                meaning: m.meaning,
                coef: m.coef(),
                sign: m.sign,
            })
            .collect()
    }

    fn misaligned(&self, given: &[(&str, f64)]) -> Result<Vec<(Coef, f64)>, String> {
        let given = given
            .iter()
            .map(|&(id, v)| {
                physical::Misalignment::parse(id)
                    .map(|m| (m, v))
                    .ok_or_else(|| id.to_string())
            })
            .collect::<Result<Vec<_>, String>>()?;
        let mapped = physical::to_dh(&given);
        Ok(mapped
            .coefs()
            .iter()
            .zip(mapped.values())
            .filter(|(_, v)| **v != 0.0)
            .map(|(c, v)| (*c, *v))
            .collect())
    }

    fn b89_model(&self) -> Option<ErrorModel> {
        Some(physical::dh_model())
    }

    fn coefficient_rows(&self) -> bool {
        true
    }

    fn section6(&self, param: usize) -> Option<&'static str> {
        Some(match PARAMS[param].id {
            "ex1" | "ey1" | "ez1" => "varies with θ, φ, d",
            "ex2" | "ey2" => "varies with φ, d",
            "ez2" | "ex3" | "ey3" => "varies with d",
            "ez3" => "no error",
            _ => "constant",
        })
    }
}

/// The chain for one parameter set; its error frames when constant.
struct Chain<'a> {
    params: &'a ErrorParams,
    /// Per coefficient, its parameter's place in the chain's arrays and its
    /// display-to-internal scale: looked up once, not per reading.
    columns: Vec<(usize, f64)>,
    constant: Option<ErrorFrames>,
}

impl Chain<'_> {
    /// The error frames at `q`.
    fn with_frames<T>(&self, q: Joints, f: impl FnOnce(&ErrorFrames) -> T) -> T {
        match &self.constant {
            Some(fr) => f(fr),
            None => f(&ErrorFrames::new(&self.params.base_at(q))),
        }
    }
}

impl Evaluate for Chain<'_> {
    fn point(&self, q: Joints, links: &Links) -> Vector3<f64> {
        self.with_frames(q, |fr| fr.forward(links))
    }

    fn point_with_jacobian(
        &self,
        q: Joints,
        links: &Links,
        jac: &mut Vec<Vector3<f64>>,
    ) -> Vector3<f64> {
        let (p, dbase) = self.with_frames(q, |fr| fr.forward_with_jacobian(links));
        // Every basis function of a constant model is 1, and `1 · scale`
        // is `scale` exactly: not looked up per coefficient and reading.
        match self.constant {
            Some(_) => jac.extend(self.columns.iter().map(|&(k, scale)| dbase[k] * scale)),
            None => jac.extend(
                self.params
                    .coefs()
                    .iter()
                    .zip(&self.columns)
                    .map(|(c, &(k, scale))| dbase[k] * (c.basis(q) * scale)),
            ),
        }
        p
    }
}
