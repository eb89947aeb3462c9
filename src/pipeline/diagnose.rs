//! `ltcal diagnose` as a function: the `diagnose` stage run on a campaign
//! folder outside any pipeline, its outputs published as one folder. Here,
//! not in the command line, because it decides what may be replaced and
//! how the folder is written — the command line only shows progress and
//! prints the verdict.

use super::error::InputError;
use crate::diagnose::Diagnosis;
use crate::stages::StageKind as _;
use crate::stages::diagnose::{self, DiagnoseStage};
use crate::table;
use anyhow::Result;
use std::path::Path;

/// Diagnoses the campaign folder `campaign` with `stage`'s settings and
/// publishes its tables and files as the folder `out` by one rename.
/// `step` hears each step under way (reading, adjusting, writing).
pub fn run(
    campaign: &Path,
    out: &Path,
    stage: &DiagnoseStage,
    step: &dyn Fn(String),
) -> Result<Diagnosis> {
    if let Some(bad) = stage.validate().first() {
        return Err(InputError::arg(bad.message.clone()));
    }
    if let Some(path) = &stage.hypotheses {
        crate::hypothesis::load(path).map_err(|p| anyhow::Error::from(InputError(p)))?;
    }
    // What a killed earlier run left beside --out (its owner gone).
    for stale in diagnose::remove_stale_temporaries(out, std::time::SystemTime::now()) {
        eprintln!(
            "removed {}, left by a diagnosis that was stopped",
            stale.display()
        );
    }
    step(format!("reading {}", campaign.display()));
    let c = crate::campaign::read_for_diagnosis(campaign)
        .map_err(|e| InputError::arg(e.to_string()))?;
    step(format!(
        "adjusting and diagnosing {} readings",
        c.readings.len()
    ));
    crate::fs::check_replaceable(
        out,
        "a diagnosis",
        "diagnosis.csv",
        crate::stages::diagnose::replaceable_folder_file,
    )
    .map_err(|why| InputError::arg(format!("--out: {why}")))?;
    let d = stage.diagnose(&c)?;
    let output = diagnose::outputs(&d)?;
    // Every file in memory first, then one folder published by one rename:
    // a full disk or a kill leaves the previous folder (or none), never a
    // partial one that looks finished.
    let mut files: Vec<(String, Vec<u8>)> = Vec::new();
    for (name, df) in &output.tables {
        files.push((format!("{name}.parquet"), table::to_parquet_bytes(df)?));
        if name == "where" {
            files.push(("where.csv".into(), crate::diagnose::output::csv(df)?));
        }
    }
    files.extend(output.files.iter().cloned());
    step(format!("writing {}", out.display()));
    crate::fs::publish_folder(out, &files)?;
    Ok(d)
}
