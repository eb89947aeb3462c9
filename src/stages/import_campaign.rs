//! `import_campaign`: a campaign folder (`campaign-format.md`, version 1) as
//! the four campaign tables, for the stages that take a campaign.
//!
//! ```toml
//! [stages.campaign]
//! kind = "import_campaign"
//! path = "../shared/data/campaigns/example-00-none"   # relative to the current directory
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
//! file is not answered from the cache, `resolve` adds the setting
//! `content_hash` — the blake3 hash of the files the reader reads
//! ([`crate::campaign::content_hash`]) — which the key then covers. ltcal
//! fills it in; it cannot be written in the pipeline file. `run` hashes the
//! folder again before and after reading it and fails if it changed since
//! the pipeline was loaded, rather than cache one content under another's
//! key.

use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput};
use crate::campaign::{self, Campaign};
use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImportCampaignStage {
    /// The campaign folder.
    pub path: PathBuf,
    /// Filled in by `resolve`: the hash of the folder's campaign files, or
    /// `None` when the folder cannot be read (then `validate` says why).
    #[serde(default, skip_deserializing, skip_serializing_if = "Option::is_none")]
    pub content_hash: Option<String>,
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

    fn resolve(&mut self) {
        self.content_hash = campaign::content_hash(&self.path).ok();
    }

    fn validate(&self) -> Vec<Invalid> {
        match campaign::read(&self.path) {
            Ok(_) => Vec::new(),
            Err(e) => vec![Invalid::new("path", e.to_string())],
        }
    }

    fn run(&self, _: &Context, _: &StageInputs) -> Result<StageOutput> {
        let unchanged = || campaign::content_hash(&self.path).ok() == self.content_hash;
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
