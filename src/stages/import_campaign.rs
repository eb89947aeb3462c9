//! `import_campaign`: a campaign folder (`campaign-format.md`, version 1) as
//! the four campaign tables, for the stages that take a campaign.
//!
//! ```toml
//! [stages.campaign]
//! kind = "import_campaign"
//! path = "examples/campaigns/example-00-none"   # relative to the current directory
//! ```
//!
//! Outputs `readings`, `targets`, `gauge`, `meta` ([`crate::campaign::TABLES`];
//! columns as the files', see [`Campaign::to_tables`]). Wire them to a
//! group slot with `inputs = { campaign = "campaign" }`.
//!
//! The folder is read while the pipeline is loaded, so a bad campaign stops
//! `ltcal run` (and `plan`) before anything runs, with every problem's file,
//! line and column.
//!
//! Cache: a stage's key covers its settings and input tables, and this
//! stage's real input is the folder, which is neither. So that an edited
//! file is not answered from the cache, the stage declares the folder
//! ([`super::StageFile`]): the runner reads and checks it once when the
//! pipeline loads, however many sweep points name it, and puts the blake3
//! hash of the files the reader reads ([`crate::campaign::content_hash`])
//! in the key. `run` hashes the folder again before and after reading it
//! and fails if it changed since the pipeline was loaded, rather than cache
//! one content under another's key.
//!
//! The load-time check keeps what it read ([`LOADED`], by folder and content
//! hash), and `run` takes it from there when the folder still hashes the
//! same: the CSV files are parsed once per process, not twice (issue 34: 60 ms
//! each at 24 000 readings).

use super::{Context, Slot, StageFile, StageInputs, StageKind, StageOutput};
use crate::campaign::{self, Campaign};
use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct ImportCampaignStage {
    /// The campaign folder.
    pub path: PathBuf,
}

/// How many checked campaigns [`LOADED`] keeps: a pipeline names a few
/// folders; past this the oldest is dropped (and read again by its run), so
/// that a long sweep over many folders does not hold them all.
const LOADED_MAX: usize = 4;

/// The campaigns the load-time check read, newest last, each with its folder
/// and the content hash of the files as they were read — the hash before and
/// after reading agreed, so the campaign is that content's.
static LOADED: Mutex<Vec<(PathBuf, String, Arc<Campaign>)>> = Mutex::new(Vec::new());

/// The folder's check when the pipeline loads: it reads as a campaign, and
/// the hash of its files. The campaign is kept for the run ([`LOADED`]) when
/// the folder did not change while it was read.
fn check(path: &Path) -> Result<String, String> {
    // (The reader's problems, with their file and line, come first.)
    let before = campaign::content_hash(path).ok();
    let c = campaign::read(path).map_err(|e| e.to_string())?;
    let after =
        campaign::content_hash(path).map_err(|e| format!("`path`: {}: {e}", path.display()))?;
    if before.as_ref() == Some(&after) {
        let mut loaded = LOADED.lock().unwrap_or_else(|e| e.into_inner());
        loaded.retain(|(p, _, _)| p != path);
        if loaded.len() == LOADED_MAX {
            loaded.remove(0);
        }
        loaded.push((path.to_path_buf(), after.clone(), Arc::new(c)));
    }
    Ok(after)
}

/// The campaign the check read from `path` when its files hashed `hash`.
fn loaded(path: &Path, hash: Option<&str>) -> Option<Arc<Campaign>> {
    let loaded = LOADED.lock().unwrap_or_else(|e| e.into_inner());
    loaded
        .iter()
        .find(|(p, h, _)| p == path && Some(h.as_str()) == hash)
        .map(|(_, _, c)| Arc::clone(c))
}

impl StageKind for ImportCampaignStage {
    const KIND: &'static str = "import_campaign";
    const SUMMARY: &'static str =
        "a campaign folder (campaign-format.md) as the tables readings, targets, gauge, meta";
    const INPUTS: &'static [Slot] = &[];
    const OUTPUTS: &'static [&'static str] = campaign::TABLES;

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        super::campaign_tables::columns(table)
    }

    fn file(&self) -> Option<StageFile<'_>> {
        Some(StageFile {
            field: "path",
            path: &self.path,
            check,
        })
    }

    fn run(&self, ctx: &Context, _: &StageInputs) -> Result<StageOutput> {
        let unchanged = || campaign::content_hash(&self.path).ok().as_deref() == ctx.file_hash;
        let before = unchanged();
        // Read while the pipeline loaded, from the same content: taken as
        // read; otherwise (a stage run without the load-time check, or a
        // folder dropped from [`LOADED`]) read now.
        let c = match loaded(&self.path, ctx.file_hash).filter(|_| before) {
            Some(c) => c,
            None => Arc::new(campaign::read(&self.path)?),
        };
        if !(before && unchanged()) {
            bail!(
                "the campaign in {} changed while the pipeline ran: run it again",
                self.path.display()
            );
        }
        Ok(StageOutput {
            tables: Campaign::checked_tables(&c)?,
            files: Vec::new(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A copy of the smallest example campaign in a temporary folder.
    fn example_copy() -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        let from = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/campaigns/example-00-none");
        for f in ["campaign.toml", "readings.csv", "targets.csv", "gauge.csv"] {
            std::fs::copy(from.join(f), dir.path().join(f)).unwrap();
        }
        dir
    }

    fn run(stage: &ImportCampaignStage, hash: &str) -> Result<StageOutput> {
        let ctx = Context {
            pipeline: "p",
            stage: "campaign",
            file_hash: Some(hash),
        };
        stage.run(&ctx, &StageInputs::default())
    }

    /// Issue 34: the run took the campaign the load-time check had parsed
    /// (not parsing it a second time) — and an edit between the load and the
    /// run is still refused, not answered with the campaign read before it.
    #[test]
    fn the_run_imports_the_campaign_the_load_check_read_and_refuses_an_edit_since() {
        let dir = example_copy();
        let stage = ImportCampaignStage {
            path: dir.path().to_path_buf(),
        };
        let hash = check(&stage.path).unwrap();
        let kept = loaded(&stage.path, Some(&hash)).expect("kept by the check");
        let readings = run(&stage, &hash).unwrap().tables;
        let n = |t: &[(String, polars::prelude::DataFrame)]| {
            t.iter()
                .find(|(name, _)| name == "readings")
                .unwrap()
                .1
                .height()
        };
        assert_eq!(n(&readings), kept.readings.len());
        assert!(n(&readings) > 10);
        // Another hash finds nothing kept.
        assert!(loaded(&stage.path, Some("0")).is_none());

        let file = stage.path.join("readings.csv");
        let text = std::fs::read_to_string(&file).unwrap();
        let last = text.trim_end().lines().last().unwrap().to_string();
        std::fs::write(
            &file,
            text.replacen(&last, "", 1).trim_end().to_string() + "\n",
        )
        .unwrap();
        let Err(e) = run(&stage, &hash) else {
            panic!("the edited folder was imported under the old hash")
        };
        let e = e.to_string();
        assert!(e.contains("changed while the pipeline ran"), "{e}");
        // Checked again, the edited folder is what the run imports.
        let hash = check(&stage.path).unwrap();
        assert_eq!(
            n(&run(&stage, &hash).unwrap().tables),
            kept.readings.len() - 1
        );
    }
}
