//! The reading-noise model: what a tracker's readings scatter by, 1 σ —
//! the `noise` effect of `effects.md`: independent Gaussian noise of
//! `sigma_angle_urad` on az and on el, and on d a standard deviation of
//! `sqrt(sigma_range_um² + (sigma_range_ppm·d/1000)²)` µm.
//!
//! The simulation draws from it and the calibration weights every reading
//! by it, so it lives apart from both.

use crate::kinematics::Reading;
use crate::random;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// Reading noise, 1 σ.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Noise {
    #[serde(default)]
    pub sigma_angle_urad: f64,
    #[serde(default)]
    pub sigma_range_um: f64,
    #[serde(default)]
    pub sigma_range_ppm: f64,
}

impl Noise {
    pub fn is_zero(&self) -> bool {
        self.sigma_angle_urad == 0.0 && self.sigma_range_um == 0.0 && self.sigma_range_ppm == 0.0
    }

    /// The range noise at distance `d_mm`, in µm.
    pub fn sigma_range_at_um(&self, d_mm: f64) -> f64 {
        self.sigma_range_um
            .hypot(self.sigma_range_ppm * d_mm / 1000.0)
    }

    /// The reading with one draw of noise added.
    pub fn apply(&self, r: Reading, rng: &mut ChaCha8Rng) -> Reading {
        let mut draw = || random::normal(rng);
        let (na, ne, nd) = (draw(), draw(), draw());
        Reading {
            az: r.az + na * self.sigma_angle_urad * 1e-6,
            el: r.el + ne * self.sigma_angle_urad * 1e-6,
            d: r.d + nd * self.sigma_range_at_um(r.d) * 1e-3,
        }
    }

    /// Names the first field that is negative or not finite.
    pub fn check(&self) -> Result<(), (&'static str, f64)> {
        for (f, v) in [
            ("sigma_angle_urad", self.sigma_angle_urad),
            ("sigma_range_um", self.sigma_range_um),
            ("sigma_range_ppm", self.sigma_range_ppm),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err((f, v));
            }
        }
        Ok(())
    }
}
