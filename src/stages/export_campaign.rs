//! `export_campaign`: writes a campaign (the four campaign tables, from
//! `import_campaign` or any stage that makes them) as a campaign folder
//! (`campaign-format.md`, version 1), so that other tools can read what ltcal
//! simulates or changes.
//!
//! ```toml
//! [stages.export]
//! kind = "export_campaign"
//! inputs = { campaign = "campaign" }
//! path = "exports/corner-lab"      # the folder to write, relative to the current directory
//! overwrite = false                # true: replace a campaign folder already there
//! ```
//!
//! The campaign is held to the format's rules first; an invalid one fails
//! the stage and nothing is written. The folder appears whole or not at all
//! (written beside it, then renamed in); without `overwrite`, a folder
//! already at `path` fails the stage unless it holds exactly this campaign;
//! with it, the folder there is replaced only if it is a campaign folder
//! (`campaign.toml` and nothing but campaign files, as `ltcal diagnose
//! --out` asks of an earlier diagnosis) — a folder of other files, a file
//! or a link fails the stage, and nothing of it is touched.
//! Output `export`: one row, `path`, `readings`, `targets`, `gauge_rows`
//! (the numbers of rows written).
//!
//! Cache: like every stage, a rerun with the same campaign and settings is
//! answered from the cache and writes nothing — delete the folder and it
//! stays deleted until the campaign or the settings change (or the cache is
//! cleared).

use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput};
use crate::campaign::{self, Campaign};
use crate::table::TableBuilder;
use anyhow::Result;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct ExportCampaignStage {
    /// The folder to write.
    pub path: PathBuf,
    /// Replace a campaign folder already at `path` (never a folder of other
    /// files).
    #[serde(default)]
    pub overwrite: bool,
}

impl StageKind for ExportCampaignStage {
    const KIND: &'static str = "export_campaign";
    const SUMMARY: &'static str =
        "writes a campaign's tables as a campaign folder (campaign-format.md), atomically";
    const INPUTS: &'static [Slot] = &[Slot::group(
        "campaign",
        true,
        "the campaign to write (an `import_campaign` stage, or any with its tables)",
        campaign::TABLES,
    )];
    const OUTPUTS: &'static [&'static str] = &["export"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "export" => Some(&["path", "readings", "targets", "gauge_rows"]),
            _ => None,
        }
    }

    fn validate(&self) -> Vec<Invalid> {
        if self.path.as_os_str().is_empty() || self.path.file_name().is_none() {
            return vec![Invalid::new(
                "path",
                format!(
                    "`path` must name the folder to write, got \"{}\"",
                    self.path.display()
                ),
            )];
        }
        Vec::new()
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let c = Campaign::from_inputs(inputs, "campaign")?;
        if self.overwrite {
            campaign::overwrite(&c, &self.path)?;
        } else {
            campaign::write(&c, &self.path)?;
        }
        let path = self.path.display().to_string();
        let count = |n: usize| vec![n as i64];
        let table = TableBuilder::new()
            .str("path", &[path])
            .i64("readings", count(c.readings.len()))
            .i64("targets", count(c.targets.len()))
            .i64("gauge_rows", count(c.gauge.len()))
            .build()?;
        Ok(StageOutput::default().table("export", table))
    }
}
