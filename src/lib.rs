//! ltcal: laser-tracker kinematic calibration research.
//!
//! The library holds the paper's models (one module per concept) and the
//! pipeline runner; the `ltcal` binary is a thin shell over [`run`].

pub mod b89;
pub mod calibrate;
pub mod campaign;
pub mod cli;
pub mod code;
pub mod criteria;
pub mod determined;
pub mod diagnose;
pub mod diagnostics;
pub mod effects;
pub mod error_model;
pub mod fs;
pub mod hypothesis;
pub mod identifiability;
pub mod identify;
pub mod incidence_grid;
pub mod kinematics;
pub mod layout;
pub mod mesh;
pub mod noise;
pub mod open_world;
pub mod physical;
pub mod pipeline;
pub mod plots;
pub mod random;
/// The stages' table columns, where they were first declared.
pub use stages::schema;
pub mod sensitivity;
pub mod simulate;
pub mod solver;
#[cfg(test)]
mod source_scan;
pub mod stages;
pub mod suggest;
pub mod table;
pub mod trackers;

/// The version that enters every cache key.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// The fingerprint of the code this binary was built from (see [`code`]),
/// which enters every cache key next to [`VERSION`].
pub const CODE_FINGERPRINT: &str = env!("LTCAL_CODE_FINGERPRINT");

/// Runs the command line; see [`cli`].
pub fn run() -> std::process::ExitCode {
    cli::main()
}
