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

use super::{Context, Slot, StageFile, StageInputs, StageKind, StageOutput};
use crate::campaign::{self, Campaign};
use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImportCampaignStage {
    /// The campaign folder.
    pub path: PathBuf,
}

/// The folder's check when the pipeline loads: it reads as a campaign, and
/// the hash of its files.
fn check(path: &Path) -> Result<String, String> {
    campaign::read(path).map_err(|e| e.to_string())?;
    campaign::content_hash(path).map_err(|e| format!("`path`: {}: {e}", path.display()))
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
        let c: Campaign = campaign::read(&self.path)?;
        if !(before && unchanged()) {
            bail!(
                "the campaign in {} changed while the pipeline ran: run it again",
                self.path.display()
            );
        }
        Ok(StageOutput {
            tables: c.to_tables()?,
            files: Vec::new(),
        })
    }
}
