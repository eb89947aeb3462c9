//! ltcal's integration tests: one binary, one module per area.

mod errors;
mod runner;
mod synthetic;
mod util;
