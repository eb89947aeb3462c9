//! The upper tail of the F distribution, safe on any statistic.
//!
//! statrs' `FisherSnedecor::sf` unwraps the regularised incomplete beta
//! function, which panics when its argument is NaN — what a campaign with
//! finite but extreme values (a `temperature_c` or a gauge `distance_mm` of
//! 1e308) makes of the F statistic, either directly (∞ − ∞, ∞ / ∞) or via
//! `d1·F` overflowing inside statrs. Every F test of the diagnosis goes
//! through [`p_value`] instead.
//!
//! Decision: a statistic that is not a finite number carries no evidence,
//! so its p-value is 1 (not significant) — the diagnosis still completes and
//! the overflowed alternative simply never wins. A finite statistic gets the
//! exact tail, computed in the form that cannot overflow.

use statrs::function::beta::checked_beta_reg;

/// P(F(d1, d2) > f): 1 for a non-finite or negative statistic or for
/// degrees of freedom that are not positive.
pub fn p_value(d1: f64, d2: f64, f: f64) -> f64 {
    if !(f.is_finite() && f >= 0.0 && d1 > 0.0 && d2 > 0.0 && d1.is_finite() && d2.is_finite()) {
        return 1.0;
    }
    // 1 − d1·f / (d1·f + d2) written as d2 / (d1·f + d2): in [0, 1] even
    // when d1·f overflows (then it is 0 and so is the tail).
    let x = d2 / (d1 * f + d2);
    checked_beta_reg(d2 / 2.0, d1 / 2.0, x).unwrap_or(1.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use statrs::distribution::{ContinuousCDF, FisherSnedecor};

    /// Regression (issue 12): a campaign value of ±1e308 made the F
    /// statistic NaN and `FisherSnedecor::sf` panicked.
    #[test]
    fn f_test_panic_on_a_non_finite_statistic_is_p_one() {
        for f in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, -1.0] {
            assert_eq!(p_value(3.0, 100.0, f), 1.0, "{f}");
        }
        // d1·f overflows inside statrs' form: no panic, the tail is 0.
        assert_eq!(p_value(4.0, 100.0, 1e308), 0.0);
        assert_eq!(p_value(0.0, 100.0, 2.0), 1.0);
    }

    #[test]
    fn finite_statistics_match_statrs() {
        let d = FisherSnedecor::new(3.0, 40.0).unwrap();
        for f in [0.0, 0.5, 1.0, 2.5, 10.0] {
            assert!((p_value(3.0, 40.0, f) - d.sf(f)).abs() < 1e-12, "{f}");
        }
    }
}
