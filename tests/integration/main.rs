//! ltcal's integration tests: one binary, one module per area.

mod b89;
mod cache_safety;
mod calibration;
mod campaign_io;
mod cli;
mod columns;
mod diagnose;
mod effects;
mod errors;
mod file_safety;
mod fuzz;
mod fuzz_files;
mod hostile;
mod hypotheses;
mod incidence;
mod layering;
mod layout_design;
mod report;
mod runner;
mod sensitivity;
mod slurm;
mod snapshots;
mod sweep;
mod synthetic;
mod trackers;
mod util;
