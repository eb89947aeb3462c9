//! ltcal: laser-tracker kinematic calibration research.

pub mod error_model;
pub mod identifiability;
pub mod identify;
pub mod kinematics;
pub mod mesh;
pub mod solver;
pub mod table;
