//! What a calibration leaves in a measurement made afterwards: the
//! corrected coordinates of a new reading (Eq. 8 with the estimated error
//! parameters) and their 3×3 covariance, the calibration's uncertainty and
//! the new reading's noise combined — SpatialAnalyzer's "uncertainty
//! field", by linear propagation:
//!
//! ```text
//! C_P = J_p·C_p·J_pᵀ + J_r·diag(σ_az², σ_el², σ_d²)·J_rᵀ
//! ```
//!
//! `J_p = ∂P/∂p` on the calibration's free coefficients, `C_p` their
//! covariance ([`Estimate::cov`]: correlations matter, the determined
//! combinations are far better known than single coefficients), and
//! `J_r = ∂P/∂(az, el, d)`, for which the nominal Jacobian of Eq. (5)
//! serves: the error parameters change it by parts in 10⁵, far below what
//! an uncertainty is quoted to. The two terms are independent (the new
//! reading is not among the calibration's).
//!
//! The point is in the measuring station's own frame: a station pose is a
//! property of one set-up, not of the tracker, so its uncertainty belongs
//! to the network, not to a later measurement. The undetermined
//! combinations are held at their start values with no uncertainty: they
//! act as a change of the station frame and leave the coordinates a
//! network relates unchanged.

use crate::determined::Estimate;
use crate::error_model::Links;
use crate::kinematics::{self, Reading};
use crate::noise::Noise;
use nalgebra::{DMatrix, Matrix3, Vector3};

/// A measurement after calibration: its corrected coordinates (mm) and the
/// two parts of their covariance (mm²).
#[derive(Clone, Copy, Debug)]
pub struct Measured {
    pub point: Vector3<f64>,
    /// From the calibration's parameter uncertainty.
    pub cov_cal: Matrix3<f64>,
    /// From the new reading's noise.
    pub cov_reading: Matrix3<f64>,
}

impl Measured {
    pub fn cov(&self) -> Matrix3<f64> {
        self.cov_cal + self.cov_reading
    }

    /// The root mean square of the three coordinates' standard
    /// uncertainties (mm) of a covariance — the figure every position in
    /// ltcal reports as `u_mm` (`sqrt(trace/3)`).
    pub fn rms(cov: &Matrix3<f64>) -> f64 {
        (cov.trace().max(0.0) / 3.0).sqrt()
    }
}

/// Measures with one calibration: the estimate and the reading noise of
/// the measurements to come.
pub struct Measurer<'a> {
    estimate: &'a Estimate,
    noise: Noise,
}

impl<'a> Measurer<'a> {
    pub fn new(estimate: &'a Estimate, noise: Noise) -> Self {
        Self { estimate, noise }
    }

    /// The corrected point of reading `r` and its covariance; the
    /// calibration part is zero when the estimate has no covariance.
    pub fn measure(&self, r: Reading) -> Measured {
        let est = self.estimate;
        let q = r.joints();
        let mut jac = Vec::new();
        let point = est
            .params
            .evaluator()
            .point_with_jacobian(q, &Links::new(q), &mut jac);
        let cov_cal = match &est.cov {
            Some(c) => {
                let jp = DMatrix::from_fn(3, est.free_index.len(), |row, k| {
                    jac[est.free_index[k]][row]
                });
                let m = &jp * c * jp.transpose();
                Matrix3::from_fn(|i, j| m[(i, j)])
            }
            None => Matrix3::zeros(),
        };
        let jr = kinematics::nominal_jacobian(r);
        let sa = self.noise.sigma_angle_urad * 1e-6;
        let sd = self.noise.sigma_range_at_um(r.d) * 1e-3;
        let s = Matrix3::from_diagonal(&Vector3::new(sa * sa, sa * sa, sd * sd));
        Measured {
            point,
            cov_cal,
            cov_reading: jr * s * jr.transpose(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::determined::Determined;
    use crate::error_model::ErrorParams;
    use crate::kinematics::Face;
    use crate::random;

    /// An estimate of Table 2's errors in which every free coefficient is
    /// known to `u` (display units), uncorrelated.
    fn estimate(u: f64) -> Estimate {
        let params = ErrorParams::table2();
        let n = params.values().len();
        let free = vec![true; n];
        let jac = DMatrix::<f64>::identity(n, n);
        let det = Determined::analyse(&jac, &params, &free, 1e-9).unwrap();
        let cov_z = DMatrix::<f64>::identity(n, n) * (u * u);
        det.estimate(params, &free, Some(&cov_z))
    }

    /// The reading noise alone: at 10 m straight ahead a 1 µrad angle noise
    /// moves the point 10 µm across the beam, the range noise along it.
    #[test]
    fn reading_noise_maps_through_the_beam_geometry() {
        let noise = Noise {
            sigma_angle_urad: 1.0,
            sigma_range_um: 2.0,
            sigma_range_ppm: 0.0,
        };
        let est = estimate(0.0);
        let m = Measurer::new(&est, noise).measure(kinematics::nominal_reading(
            &Vector3::new(10_000.0, 0.0, 0.0),
            Face::Front,
        ));
        let u: Vec<f64> = (0..3).map(|i| m.cov_reading[(i, i)].sqrt() * 1e3).collect();
        assert!((u[0] - 2.0).abs() < 1e-9, "along the beam {}", u[0]);
        assert!((u[1] - 10.0).abs() < 1e-9, "across {}", u[1]);
        assert!((u[2] - 10.0).abs() < 1e-9, "up {}", u[2]);
        assert!(m.cov_cal.norm() < 1e-30);
    }

    /// The calibration part against Monte Carlo: parameters drawn from
    /// their covariance, each draw's corrected point through Eq. (8); the
    /// spread matches the propagated covariance within the draws' own
    /// uncertainty.
    #[test]
    fn calibration_part_matches_monte_carlo_over_parameter_draws() {
        let est = estimate(3.0);
        let measurer = Measurer::new(&est, Noise::default());
        let r = kinematics::nominal_reading(&Vector3::new(4_000.0, -2_500.0, 1_500.0), Face::Front);
        let m = measurer.measure(r);
        let mut rng = random::stream(5, "measurement-test");
        let draws = 20_000;
        let mut sum = Vector3::zeros();
        let mut sum2 = Matrix3::zeros();
        let mut params = est.params.clone();
        for _ in 0..draws {
            for (v, v0) in params.values_mut().iter_mut().zip(est.params.values()) {
                *v = v0 + 3.0 * random::normal(&mut rng);
            }
            let p = params.correct(r);
            sum += p;
            sum2 += p * p.transpose();
        }
        let mean = sum / draws as f64;
        let cov = sum2 / draws as f64 - mean * mean.transpose();
        for i in 0..3 {
            let ratio = (cov[(i, i)] / m.cov_cal[(i, i)]).sqrt();
            // 20 000 draws: a standard deviation known to 0.5 %.
            assert!((0.98..1.02).contains(&ratio), "coordinate {i}: {ratio}");
        }
    }
}
