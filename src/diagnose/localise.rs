//! Where the residual the explanation set leaves lies, as a number a
//! researcher acts on.
//!
//! Why not binned means of the residuals ([`super::factors`]): after the
//! adjustment, the station poses and reflector positions have absorbed
//! whatever part of a structure resembles them, and a periodic pattern
//! averages out within bins — binned residual means point at the right
//! factor in a minority of campaigns. Here each factor's *basis* (smooth
//! or periodic functions of the factor, on the reading coordinate or on
//! the station pose) enters the adjustment as extra columns beside the
//! explanation set's members, and its Δχ² is the score test against that
//! augmented model ([`super::linear::LinearModel::fit`]: the columns
//! projected off everything the adjustment can absorb). The test is an F
//! test of the basis's Δχ² per column against the residual variance that
//! is left (so a stated noise too small does not make every basis
//! significant), Bonferroni-corrected over every factor and alternative
//! tried; a residual at rounding level (χ² per degree of freedom below
//! 1e-6) is never structure.
//!
//! What each factor tries:
//!
//! | factor | basis |
//! |---|---|
//! | `range` | a cubic B-spline in d on each coordinate; sine and cosine of `2π·d/P` on d for periods P from 0.2 m to 5 m (the best period counted as alternatives) |
//! | `az`, `el` | a Fourier series in az (orders 2–4) / a cubic B-spline in el, on each coordinate |
//! | `time` | a cubic B-spline in `time_s` on each coordinate, and a growth of the reflector field about its centroid |
//! | `station × time` | a step of one station's pose (translation, rotation) and of its range after a time, at times on a grid (station and time counted as alternatives) |
//! | `station`, `reflector`, `face` | a range offset per station / per reflector, a face-2 offset on each coordinate |
//! | `incidence`, `temperature` | a cubic B-spline on d |
//!
//! Each factor is reported with its best basis: its share of what is left
//! (Δχ² over the set's χ²), its p-value, the held-out gap a smooth function
//! of that factor would remove, and its fitted shape as a table.

/// The structure left along one factor.
#[derive(Clone, Debug)]
pub struct Localised {
    /// `range`, `az`, `el`, `time`, `station × time`, `station`,
    /// `reflector`, `face`, `incidence`, `temperature`.
    pub factor: &'static str,
    /// The best basis of the factor, in words (`periodic in d, period
    /// 812 mm`, `step of S3's pose after 1 840 s`, …).
    pub basis: String,
    /// Columns of that basis.
    pub columns: usize,
    /// Alternatives the basis was chosen from (counted in the correction).
    pub alternatives: usize,
    /// Its Δχ² against the augmented model.
    pub delta_chi2: f64,
    /// Δχ² as a share of the χ² the set leaves.
    pub share: f64,
    /// F statistic and p-value (before and after the correction).
    pub f: f64,
    pub p: f64,
    pub p_adjusted: f64,
    pub significant: bool,
    /// Held-out gap over the noise floor the basis removes, %.
    pub gap_removed_pct: f64,
    /// The fitted shape: `(x, value, u)` in the units of [`Localised::shape_x`]
    /// and [`Localised::shape_unit`].
    pub shape: Vec<(f64, f64, f64)>,
    pub shape_x: String,
    pub shape_unit: String,
}
