//! ltcal's integration tests: one binary, one module per area.

mod cache_safety;
mod calibration;
mod campaign_io;
mod cli;
mod effects;
mod errors;
mod report;
mod runner;
mod snapshots;
mod synthetic;
mod util;
