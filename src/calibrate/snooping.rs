//! Gross errors: Baarda's data snooping on a bundle adjustment.
//!
//! A reading whose beam caught the wrong reflector, or that was taken before
//! the SMR settled, is off by far more than its noise in one coordinate. The
//! test of geodesy (W. Baarda, *A testing procedure for use in geodetic
//! networks*, 1968) asks of every observation alone whether it is such a
//! blunder: with the residuals `v` in units of the a-priori σ and the
//! redundancy `R = I − J·N⁻¹·Jᵀ` (the share of an observation's own error
//! that shows in its residual, `Q_vv` in units of σ²),
//!
//! ```text
//! w_i = v_i / √R_ii          ~ N(0, 1) when observation i is sound
//! ∇_i = v_i / R_ii           the blunder's estimated size (units of σ)
//! ```
//!
//! `w_i²` is the χ² a blunder on observation i explains. The tests are
//! Bonferroni-corrected over every observation tested: the critical value
//! is the normal quantile of `1 − α/(2·n)`. Iterated data snooping rejects
//! the worst observation above it, adjusts again and tests again — one at a
//! time, because one blunder raises its neighbours' residuals too.
//!
//! `R` comes from the factored normal matrix one reading at a time
//! ([`sparse::leverages`]): a few columns of the whitened Schur factor per
//! reading, never the `m × m` matrix. When effects are modelled beside the
//! base parameters (the diagnosis' explanation set), their columns `C` are
//! absorbed too:
//! `R = I − H − (P⊥C)·(CᵀP⊥C)⁻¹·(P⊥C)ᵀ` on the reading's rows.

use super::sparse::{self, BlockJacobian, Factor, Normal};
use super::{Calibration, Network, Settings};
use crate::error_model::ErrorParams;
use anyhow::{Result, anyhow};
use nalgebra::DMatrix;
use rayon::prelude::*;

/// The coordinates of a reading, in the order of its residual rows.
pub const COORDINATES: [&str; 3] = ["az", "el", "d"];

/// Below this redundancy an observation is not tested: its residual shows
/// (almost) nothing of its own error (a reflector seen only once).
pub const MIN_REDUNDANCY: f64 = 1e-6;

/// One coordinate's test.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WTest {
    /// The reading (index in the network's readings).
    pub obs: usize,
    /// 0 az, 1 el, 2 d ([`COORDINATES`]).
    pub coordinate: usize,
    /// Baarda's normalised residual.
    pub w: f64,
    /// `R_ii`: 0 (the fit absorbs the observation's error) to 1.
    pub redundancy: f64,
    /// The blunder's estimated size, units of σ.
    pub size_sigma: f64,
}

impl WTest {
    /// Whether the test can say anything.
    pub fn testable(&self) -> bool {
        self.redundancy >= MIN_REDUNDANCY
    }
}

/// Columns modelled beside the base parameters: `P⊥C` on every row
/// (row-major, `k` values per row) and `(CᵀP⊥C)⁻¹`.
pub struct Absorbed<'a> {
    pub projected: &'a [f64],
    pub k: usize,
    pub gram_inverse: &'a DMatrix<f64>,
}

/// The w-test of each coordinate of the first `readings` residual blocks
/// (three rows each). `v`: the residuals (units of σ) at the solution,
/// orthogonal to `j` and to the absorbed columns.
pub fn w_tests(
    j: &BlockJacobian,
    f: &Factor,
    v: &[f64],
    readings: usize,
    absorbed: Option<&Absorbed>,
) -> Vec<[WTest; 3]> {
    let hat = sparse::leverages(j, f, readings);
    (0..readings)
        .into_par_iter()
        .map(|i| {
            let mut r =
                DMatrix::identity(3, 3) - DMatrix::from_column_slice(3, 3, hat[i].as_slice());
            if let Some(a) = absorbed {
                let pc =
                    DMatrix::from_row_slice(3, a.k, &a.projected[3 * i * a.k..3 * (i + 1) * a.k]);
                r -= &pc * a.gram_inverse * pc.transpose();
            }
            std::array::from_fn(|c| {
                let redundancy = r[(c, c)].clamp(0.0, 1.0);
                let (w, size_sigma) = if redundancy >= MIN_REDUNDANCY {
                    (v[3 * i + c] / redundancy.sqrt(), v[3 * i + c] / redundancy)
                } else {
                    (0.0, 0.0)
                };
                WTest {
                    obs: i,
                    coordinate: c,
                    w,
                    redundancy,
                    size_sigma,
                }
            })
        })
        .collect()
}

/// The critical `|w|` for `tests` tests at family-wise level `alpha`
/// (Bonferroni, two-sided).
pub fn critical_w(alpha: f64, tests: usize) -> f64 {
    use statrs::distribution::{ContinuousCDF, Normal};
    let tail = (alpha / (2.0 * tests.max(1) as f64)).clamp(1e-300, 0.5);
    Normal::standard().inverse_cdf(1.0 - tail).max(0.0)
}

/// The Bonferroni-corrected two-sided p-value of `w` over `tests` tests.
pub fn p_corrected(w: f64, tests: usize) -> f64 {
    use statrs::distribution::{ContinuousCDF, Normal};
    (2.0 * Normal::standard().sf(w.abs()) * tests.max(1) as f64).min(1.0)
}

/// The worst testable coordinate of `tests`, by `|w|`; ties to the first.
pub fn worst(tests: &[[WTest; 3]]) -> Option<WTest> {
    tests.iter().flatten().filter(|t| t.testable()).fold(
        None,
        |best: Option<WTest>, t| match best {
            Some(b) if b.w.abs() >= t.w.abs() => Some(b),
            _ => Some(*t),
        },
    )
}

/// Number of testable coordinates.
pub fn testable(tests: &[[WTest; 3]]) -> usize {
    tests.iter().flatten().filter(|t| t.testable()).count()
}

/// A reading rejected by iterated data snooping.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rejected {
    /// The coordinate whose test rejected it (`obs`: the reading's index in
    /// the network the snooping started from).
    pub test: WTest,
    /// The test's critical value at that iteration.
    pub critical_w: f64,
}

/// At most this share of the readings is rejected: a campaign with more
/// gross errors than that needs looking at, not an automatic answer.
pub const MAX_REJECTED_SHARE: f64 = 0.1;

/// A bundle adjustment with iterated data snooping: adjust, test every
/// reading coordinate, remove the reading with the worst `|w|` above the
/// critical value (Bonferroni over the coordinates tested, level
/// `alpha`), adjust again — until no test rejects or
/// [`MAX_REJECTED_SHARE`] of the readings are gone. Returns the network
/// kept, its calibration and the rejected readings in order.
pub fn calibrate_rejecting(
    net: &Network,
    start: &ErrorParams,
    free: &[bool],
    settings: &Settings,
    alpha: f64,
) -> Result<(Network, Calibration, Vec<Rejected>)> {
    let max = (MAX_REJECTED_SHARE * net.obs.len() as f64).floor() as usize;
    let mut kept: Vec<usize> = (0..net.obs.len()).collect();
    let mut current = net.clone();
    let mut rejected = Vec::new();
    loop {
        let cal = super::calibrate(&current, start, free, settings)?;
        if rejected.len() >= max {
            return Ok((current, cal, rejected));
        }
        let lin = cal
            .linearisation
            .as_ref()
            .ok_or_else(|| anyhow!("blunders are tested on the bundle adjustment"))?;
        let f = Normal::assemble(&lin.jacobian, None, |_| true)
            .factor(0.0)
            .ok_or_else(|| anyhow!("singular normal matrix at the solution"))?;
        let tests = w_tests(
            &lin.jacobian,
            &f,
            lin.residuals.as_slice(),
            current.obs.len(),
            None,
        );
        let critical = critical_w(alpha, testable(&tests));
        match worst(&tests) {
            Some(t) if t.w.abs() > critical => {
                rejected.push(Rejected {
                    test: WTest {
                        obs: kept[t.obs],
                        ..t
                    },
                    critical_w: critical,
                });
                kept.remove(t.obs);
                current = current.without_readings(&[t.obs]);
            }
            _ => return Ok((current, cal, rejected)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calibrate::sparse::{Normal, project_out, random_arrow};
    use nalgebra::DVector;

    /// A blunder planted on one row of a consistent network is the worst
    /// w, with its size recovered; the redundancies are the diagonal of
    /// `I − H` computed densely.
    #[test]
    fn a_planted_blunder_is_the_worst_w_and_its_size_is_recovered() {
        let (j, jd) = random_arrow(8, 0.29, 2.0, true);
        let f = Normal::assemble(&j, None, |_| true).factor(0.0).unwrap();
        let mut e = DVector::from_fn(j.nrows(), |i, _| 1e-3 * ((i * 7 % 11) as f64 - 5.0));
        e[3 * 5 + 1] += 40.0;
        let v = project_out(&j, &f, &e);
        let tests = w_tests(&j, &f, v.as_slice(), j.nrows() / 3, None);
        let hat = &jd * (jd.transpose() * &jd).try_inverse().unwrap() * jd.transpose();
        for t in tests.iter().flatten() {
            let row = 3 * t.obs + t.coordinate;
            assert!((t.redundancy - (1.0 - hat[(row, row)])).abs() < 1e-10);
        }
        let w = worst(&tests).unwrap();
        assert_eq!((w.obs, w.coordinate), (5, 1));
        assert!((w.size_sigma - 40.0).abs() < 0.1, "{w:?}");
        assert!(w.w.abs() > critical_w(0.01, testable(&tests)));
    }

    #[test]
    fn critical_values_are_the_bonferroni_normal_quantiles() {
        // z(1 − 0.05/2) = 1.95996; 345 tests at 5 %: 3.7996 (the
        // independent generator's value for example 11).
        assert!((critical_w(0.05, 1) - 1.959964).abs() < 1e-5);
        assert!((critical_w(0.05, 345) - 3.799604).abs() < 1e-5);
        assert!((p_corrected(critical_w(0.01, 100), 100) - 0.01).abs() < 1e-9);
    }
}
