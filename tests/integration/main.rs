//! ltcal's integration tests: one binary, one module per area.

mod cache_safety;
mod campaign_io;
mod cli;
mod calibration;
mod effects;
mod errors;
mod report;
mod runner;
mod snapshots;
mod synthetic;
mod util;
