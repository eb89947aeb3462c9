//! ltcal: laser-tracker kinematic calibration research.

pub mod error_model;
pub mod kinematics;
