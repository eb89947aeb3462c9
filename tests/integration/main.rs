//! ltcal's integration tests: one binary, one module per area.

mod campaign_io;
mod errors;
mod runner;
mod synthetic;
mod util;
