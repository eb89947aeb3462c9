//! Levenberg–Marquardt as an argmin [`Solver`].
//!
//! argmin 0.11 has Gauss–Newton but no Levenberg–Marquardt, and its
//! Gauss–Newton forms and inverts `JᵀJ` densely. Calibration problems need a
//! damped step (the error parameters are tiny beside the station poses) and,
//! for multi-station bundle adjustment, a step that exploits the block
//! structure of `JᵀJ`. So the solver here asks the problem's Jacobian for its
//! *normal equations* through [`LmJacobian`]: a dense matrix gives dense ones,
//! a block-sparse Jacobian can give a Schur-complement solver. The problem
//! (residuals, Jacobian) stays separate from the solver, as argmin intends.
//!
//! The damping update is Nielsen's (H. B. Nielsen, *Damping parameter in
//! Marquardt's method*, IMM-REP-1999-05), with Marquardt's scaling of the
//! damping by `diag(JᵀJ)`.

use argmin::core::{
    Error, Executor, IterState, Jacobian, KV, Operator, Problem, Solver, State, TerminationReason,
    TerminationStatus,
};
use nalgebra::{DMatrix, DVector};

/// The linearised system a Jacobian offers the solver.
pub trait NormalEquations {
    /// `g = Jᵀr`.
    fn gradient(&self) -> &DVector<f64>;
    /// The step `δ` solving `(JᵀJ + λ·D)·δ = −g`, `D` Marquardt's scaling;
    /// `None` when the system is singular.
    fn damped_step(&self, lambda: f64) -> Option<DVector<f64>>;
    /// `‖J·δ‖²`, for the predicted decrease of the cost.
    fn jacobian_norm2(&self, step: &DVector<f64>) -> f64;
}

/// A Jacobian that can form the normal equations at given residuals.
pub trait LmJacobian {
    type Normal: NormalEquations;
    fn normal_equations(self, residuals: &DVector<f64>) -> Self::Normal;
}

/// Dense normal equations, for problems with a few dozen unknowns.
pub struct DenseNormal {
    jtj: DMatrix<f64>,
    g: DVector<f64>,
}

impl DenseNormal {
    pub fn new(jtj: DMatrix<f64>, g: DVector<f64>) -> DenseNormal {
        DenseNormal { jtj, g }
    }
}

impl NormalEquations for DenseNormal {
    fn gradient(&self) -> &DVector<f64> {
        &self.g
    }
    fn damped_step(&self, lambda: f64) -> Option<DVector<f64>> {
        let mut a = self.jtj.clone();
        for i in 0..a.nrows() {
            a[(i, i)] += lambda * self.jtj[(i, i)].max(1e-300);
        }
        a.cholesky().map(|c| -c.solve(&self.g))
    }
    fn jacobian_norm2(&self, step: &DVector<f64>) -> f64 {
        step.dot(&(&self.jtj * step))
    }
}

impl LmJacobian for DMatrix<f64> {
    type Normal = DenseNormal;
    fn normal_equations(self, r: &DVector<f64>) -> DenseNormal {
        DenseNormal {
            jtj: self.tr_mul(&self),
            g: self.tr_mul(r),
        }
    }
}

/// A problem with many residuals and few unknowns may accumulate `JᵀJ` and
/// `Jᵀr` reading by reading instead of forming `J`; its "Jacobian" is then
/// the normal equations themselves, already taken at the current residuals.
impl LmJacobian for DenseNormal {
    type Normal = DenseNormal;
    fn normal_equations(self, _: &DVector<f64>) -> DenseNormal {
        self
    }
}

/// Levenberg–Marquardt settings; the builder rejects settings that cannot work
/// and names the field.
#[derive(Clone, Debug)]
pub struct LevenbergMarquardt {
    lambda: f64,
    nu: f64,
    /// Stop when the largest gradient component `|Jᵀr|∞` falls below this.
    gtol: f64,
    /// Stop when the step is below `xtol·(‖x‖ + xtol)`.
    xtol: f64,
    /// Stop when the relative decrease of the cost falls below this.
    ftol: f64,
    max_rejections: usize,
    /// Why the last iteration asked to stop.
    stop: Option<&'static str>,
}

impl Default for LevenbergMarquardt {
    fn default() -> Self {
        LevenbergMarquardt {
            lambda: 1e-3,
            nu: 2.0,
            gtol: 1e-12,
            xtol: 1e-12,
            ftol: 1e-14,
            max_rejections: 30,
            stop: None,
        }
    }
}

fn positive(field: &str, v: f64) -> Result<f64, Error> {
    if v.is_finite() && v > 0.0 {
        Ok(v)
    } else {
        Err(argmin::core::ArgminError::InvalidParameter {
            text: format!(
                "Levenberg–Marquardt: `{field}` must be a positive finite number, got {v}"
            ),
        }
        .into())
    }
}

impl LevenbergMarquardt {
    pub fn new() -> Self {
        Self::default()
    }
    pub fn with_initial_lambda(mut self, lambda: f64) -> Result<Self, Error> {
        self.lambda = positive("initial_lambda", lambda)?;
        Ok(self)
    }
    pub fn with_gtol(mut self, gtol: f64) -> Result<Self, Error> {
        self.gtol = positive("gtol", gtol)?;
        Ok(self)
    }

    /// Runs the solver on `problem` from `x0` for at most `max_iters` steps.
    pub fn minimize<O, J>(self, problem: O, x0: DVector<f64>, max_iters: u64) -> Result<Fit, Error>
    where
        O: Operator<Param = DVector<f64>, Output = DVector<f64>>
            + Jacobian<Param = DVector<f64>, Jacobian = J>,
        J: LmJacobian,
    {
        let res = Executor::new(problem, self)
            .configure(|s| s.param(x0).max_iters(max_iters))
            .timer(false)
            .run()?;
        let reason = res
            .solver
            .stop
            .unwrap_or(match res.state.get_termination_reason() {
                Some(TerminationReason::MaxItersReached) => "max-iterations",
                _ => "converged",
            });
        let mut state = res.state;
        let iterations = state.get_iter();
        let cost = state.get_cost();
        Ok(Fit {
            x: state.take_param().expect("solver keeps its parameter"),
            residuals: state.take_residuals().expect("solver keeps its residuals"),
            cost,
            iterations,
            reason,
        })
    }
}

/// The outcome of [`LevenbergMarquardt::minimize`].
#[derive(Clone, Debug)]
pub struct Fit {
    pub x: DVector<f64>,
    pub residuals: DVector<f64>,
    /// `½‖r‖²` at `x`.
    pub cost: f64,
    pub iterations: u64,
    /// `gradient`, `step`, `cost`, `no-descent` or `max-iterations`.
    pub reason: &'static str,
}

type LmState<J> = IterState<DVector<f64>, (), J, (), DVector<f64>, f64>;

fn half_norm2(r: &DVector<f64>) -> f64 {
    0.5 * r.norm_squared()
}

impl<O, J> Solver<O, LmState<J>> for LevenbergMarquardt
where
    O: Operator<Param = DVector<f64>, Output = DVector<f64>>
        + Jacobian<Param = DVector<f64>, Jacobian = J>,
    J: LmJacobian,
{
    fn name(&self) -> &str {
        "Levenberg–Marquardt"
    }

    fn init(
        &mut self,
        problem: &mut Problem<O>,
        mut state: LmState<J>,
    ) -> Result<(LmState<J>, Option<KV>), Error> {
        let x = state.take_param().ok_or_else(|| {
            Error::from(argmin::core::ArgminError::NotInitialized {
                text: "Levenberg–Marquardt needs an initial parameter vector".into(),
            })
        })?;
        let r = problem.apply(&x)?;
        let cost = half_norm2(&r);
        self.stop = None;
        Ok((state.param(x).residuals(r).cost(cost), None))
    }

    fn next_iter(
        &mut self,
        problem: &mut Problem<O>,
        mut state: LmState<J>,
    ) -> Result<(LmState<J>, Option<KV>), Error> {
        let x = state.take_param().expect("parameter set in init");
        let r = state.take_residuals().expect("residuals set in init");
        let cost = state.get_cost();
        let normal = problem.jacobian(&x)?.normal_equations(&r);
        if normal.gradient().amax() <= self.gtol {
            self.stop = Some("gradient");
            return Ok((state.param(x).residuals(r).cost(cost), None));
        }
        for _ in 0..self.max_rejections {
            let Some(step) = normal.damped_step(self.lambda) else {
                self.lambda *= self.nu;
                self.nu *= 2.0;
                continue;
            };
            if step.norm() <= self.xtol * (x.norm() + self.xtol) {
                self.stop = Some("step");
                return Ok((state.param(x).residuals(r).cost(cost), None));
            }
            let trial = &x + &step;
            let r_trial = problem.apply(&trial)?;
            let cost_trial = half_norm2(&r_trial);
            // Predicted decrease of ½‖r + Jδ‖².
            let predicted = -(step.dot(normal.gradient()) + 0.5 * normal.jacobian_norm2(&step));
            let rho = if predicted > 0.0 {
                (cost - cost_trial) / predicted
            } else {
                -1.0
            };
            if rho > 0.0 && cost_trial.is_finite() {
                self.lambda *= (1.0 - (2.0 * rho - 1.0).powi(3)).max(1.0 / 3.0);
                self.nu = 2.0;
                if cost - cost_trial <= self.ftol * cost {
                    self.stop = Some("cost");
                }
                return Ok((state.param(trial).residuals(r_trial).cost(cost_trial), None));
            }
            self.lambda *= self.nu;
            self.nu *= 2.0;
        }
        self.stop = Some("no-descent");
        Ok((state.param(x).residuals(r).cost(cost), None))
    }

    fn terminate(&mut self, _state: &LmState<J>) -> TerminationStatus {
        if self.stop.is_some() {
            TerminationStatus::Terminated(TerminationReason::SolverConverged)
        } else {
            TerminationStatus::NotTerminated
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rosenbrock as residuals: r = (10(y − x²), 1 − x).
    struct Rosenbrock;
    impl Operator for Rosenbrock {
        type Param = DVector<f64>;
        type Output = DVector<f64>;
        fn apply(&self, p: &DVector<f64>) -> Result<DVector<f64>, Error> {
            Ok(DVector::from_vec(vec![
                10.0 * (p[1] - p[0] * p[0]),
                1.0 - p[0],
            ]))
        }
    }
    impl Jacobian for Rosenbrock {
        type Param = DVector<f64>;
        type Jacobian = DMatrix<f64>;
        fn jacobian(&self, p: &DVector<f64>) -> Result<DMatrix<f64>, Error> {
            Ok(DMatrix::from_row_slice(
                2,
                2,
                &[-20.0 * p[0], 10.0, -1.0, 0.0],
            ))
        }
    }

    #[test]
    fn solves_rosenbrock() {
        let fit = LevenbergMarquardt::new()
            .minimize(Rosenbrock, DVector::from_vec(vec![-1.2, 1.0]), 200)
            .unwrap();
        assert!(
            (fit.x[0] - 1.0).abs() < 1e-9 && (fit.x[1] - 1.0).abs() < 1e-9,
            "{:?}",
            fit
        );
    }

    #[test]
    fn builder_names_the_bad_field() {
        let err = LevenbergMarquardt::new().with_gtol(-1.0).unwrap_err();
        assert!(err.to_string().contains("`gtol`"), "{err}");
    }
}
