//! `diagnose`: where a campaign's residual lies, which unmodelled effect
//! causes it and how far the gap shrinks once it is modelled (see
//! [`crate::diagnose`]). The same as `ltcal diagnose <campaign-dir>`.
//!
//! ```toml
//! [stages.diagnosis]
//! kind = "diagnose"
//! inputs = { campaign = "corner" }   # a whole campaign (import or simulate)
//! model = "api-tracker3"             # the tracker model to fit (the campaign's by default)
//! shapes = {}                        # the base model's shapes (its constants by default)
//! fixed = []
//! folds = 5                          # cross-validation
//! mc_draws = 100                     # Monte Carlo draws of the noise floor (at most)
//! alpha = 0.01                       # family-wise significance
//! effects = []                       # effect ids to try (empty: all of effects.md)
//! seed = 0
//! max_steps = 8                      # members of the explanation set at most
//! hypotheses = "hypotheses/adm.toml" # your own effects, tried beside the catalogue's
//! ```
//!
//! Outputs: `diagnosis` (the contract of `diagnosis.csv`, see
//! [`crate::diagnose::output`]), `where` (`factor`, `component`, `groups`,
//! `eta2`, `f`, `p`, `significant`, `worst_group`, `worst_mean_sigma`),
//! `residuals` (per reading, with the factor values and each coordinate's
//! w-test and redundancy), `summary` (one row: `campaign`, `chi2`, `dof`,
//! `chi2_p`, `noise_stated`, `noise_floor_um`, `noise_floor_u_um` (its Monte Carlo
//! standard error), `tried`, `blunder_tests`,
//! `explanation`, `set_rms_before_um`, `set_rms_after_um`,
//! `set_gap_shrink_pct`, `verdict`), `skipped` (`effect`, `reason`); files
//! `diagnosis.csv`, `report.md`, `report.html` (the same words and the
//! figures inlined: [`crate::diagnose::page`]), `residuals-<factor>.svg`
//! and, when a factor localises what is left, `unexplained.svg` (its
//! fitted shape).

use super::{Context, Invalid, Slot, StageFile, StageInputs, StageKind, StageOutput, fitting};
use crate::campaign::{self, Campaign};
use crate::diagnose::{self, Diagnosis, Settings, output};
use crate::effects;
use crate::error_model::{ParamId, Shape};
use crate::hypothesis::Hypothesis;
use crate::trackers::TrackerModel;
use anyhow::{Result, anyhow};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::SystemTime;

/// A hypothesis file, every mistake in it at its place (one message).
pub fn load_hypotheses(path: &Path) -> Result<Vec<Hypothesis>, String> {
    crate::hypothesis::load(path).map_err(|problems| {
        problems
            .iter()
            .map(|p| match p {
                crate::diagnostics::Problem::At(e) => e.to_string(),
                other => format!("{}: {}", other.location(), other.message()),
            })
            .collect::<Vec<_>>()
            .join("\n")
    })
}

/// [`super::StageFile::check`] of a hypothesis file: its content hash once
/// it parses.
pub fn check_hypotheses(path: &Path) -> Result<String, String> {
    load_hypotheses(path)?;
    let bytes = crate::fs::read_regular_file(path, crate::hypothesis::MAX_FILE_BYTES)
        .map_err(|e| e.to_string())?;
    Ok(blake3::hash(&bytes).to_hex().to_string())
}

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct DiagnoseStage {
    /// The tracker model to fit; the campaign's by default.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<TrackerModel>,
    /// The base model's shapes (its constants by default).
    #[serde(default)]
    pub shapes: BTreeMap<ParamId, Shape>,
    /// Parameters of the base model held at zero.
    #[serde(default)]
    pub fixed: Vec<ParamId>,
    /// Cross-validation folds for the held-out residual of each candidate.
    #[serde(default = "default_folds")]
    pub folds: usize,
    /// Monte Carlo draws of the noise floor at most: only the first 32 when
    /// their mean is already known to 0.1 % (a big network).
    #[serde(default = "default_draws")]
    pub mc_draws: usize,
    /// Family-wise significance level of the effect and blunder tests.
    #[serde(default = "default_alpha")]
    pub alpha: f64,
    /// Effect ids to try; empty: every effect of effects.md.
    #[serde(default)]
    pub effects: Vec<String>,
    /// Seed of the folds and Monte Carlo draws.
    #[serde(default)]
    pub seed: u64,
    /// Members of the explanation set at most.
    #[serde(default = "default_max_steps")]
    pub max_steps: usize,
    /// A hypothesis file ([`crate::hypothesis`]): a researcher's effects,
    /// tried beside the catalogue's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hypotheses: Option<PathBuf>,
}

fn default_max_steps() -> usize {
    diagnose::DEFAULT_MAX_STEPS
}

fn default_folds() -> usize {
    5
}
fn default_draws() -> usize {
    100
}
fn default_alpha() -> f64 {
    0.01
}

impl Default for DiagnoseStage {
    fn default() -> Self {
        DiagnoseStage {
            model: None,
            shapes: BTreeMap::new(),
            fixed: Vec::new(),
            folds: default_folds(),
            mc_draws: default_draws(),
            alpha: default_alpha(),
            effects: Vec::new(),
            seed: 0,
            max_steps: default_max_steps(),
            hypotheses: None,
        }
    }
}

impl DiagnoseStage {
    /// The diagnosis settings for campaign `c` (whose tracker model is the
    /// default).
    pub fn settings(&self, c: &Campaign) -> Result<Settings> {
        let tracker = fitting::tracker(self.model, c);
        Ok(Settings {
            model: fitting::run_model(tracker, &self.shapes, &self.fixed)?,
            fixed: self.fixed.clone(),
            folds: self.folds,
            mc_draws: self.mc_draws,
            alpha: self.alpha,
            effects: self.effects.clone(),
            seed: self.seed,
            max_steps: self.max_steps,
            hypotheses: Arc::new(match &self.hypotheses {
                Some(path) => load_hypotheses(path).map_err(|e| anyhow!(e))?,
                None => Vec::new(),
            }),
        })
    }

    /// The diagnosis of `c`; a campaign it cannot test against (a stated
    /// noise of 0: [`Campaign::diagnosis_issues`]) is refused by its key.
    /// (`ltcal diagnose` reads through [`campaign::read_for_diagnosis`],
    /// which locates it in campaign.toml first.)
    pub fn diagnose(&self, c: &Campaign) -> Result<Diagnosis> {
        if let Some(first) = c.diagnosis_issues().first() {
            anyhow::bail!("the campaign cannot be diagnosed: {first}");
        }
        diagnose::diagnose(c, &self.settings(c)?)
    }
}

/// Whether a file named `name` is one a diagnosis writes into its folder:
/// the folder is replaced whole, so it must hold only such files (or be
/// empty) — `--out .` must not delete the user's files. The one rule of
/// `ltcal diagnose` and of the Python package's `ltcal.diagnose`.
pub fn replaceable_folder_file(name: &str) -> bool {
    name == "report.md"
        || name == "report.html"
        || name == "discovered.toml"
        || [".csv", ".parquet", ".svg"]
            .iter()
            .any(|ext| name.ends_with(ext))
}

/// Removes what a killed `ltcal diagnose --out <out>` left beside `out`:
/// the folders `fs::publish_folder` builds (`.<name>.<temp_name>.tmp`) or
/// sets aside (`.<name>.<temp_name>.old`), when the process that made them
/// has ended on this machine ([`crate::fs::temp_owner_gone`]) and they are
/// older than `started`. A SIGTERM during a million-reading diagnosis left
/// 1.8 GB that no later run removed. Anything else — another name, a live
/// owner, another machine's, a file or a symlink — is left alone. Returns
/// what was removed.
pub fn remove_stale_temporaries(out: &Path, started: SystemTime) -> Vec<PathBuf> {
    let Some(name) = out.file_name().map(|n| n.to_string_lossy().into_owned()) else {
        return Vec::new();
    };
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let Ok(entries) = std::fs::read_dir(parent) else {
        return Vec::new();
    };
    let prefix = format!(".{name}.");
    let mut removed = Vec::new();
    for entry in entries.flatten() {
        let file = entry.file_name().to_string_lossy().into_owned();
        let Some(temp) = file
            .strip_prefix(&prefix)
            .and_then(|t| t.strip_suffix(".tmp").or_else(|| t.strip_suffix(".old")))
        else {
            continue;
        };
        let path = entry.path();
        // `symlink_metadata`: a symlink is not ours to follow or remove.
        let ours = std::fs::symlink_metadata(&path)
            .is_ok_and(|m| m.is_dir() && m.modified().is_ok_and(|t| t < started));
        if ours && crate::fs::temp_owner_gone(temp) && std::fs::remove_dir_all(&path).is_ok() {
            removed.push(path);
        }
    }
    removed
}

/// Every output of a diagnosis, as a stage (or `ltcal diagnose`) writes it.
pub fn outputs(d: &Diagnosis) -> Result<StageOutput> {
    let table = output::diagnosis_table(d)?;
    let figures = output::figures(d)?;
    let mut report = output::report(d);
    report.push_str(&output::figures_left_out(&figures.notes));
    let page = diagnose::page::html(d, &figures);
    let unexplained = output::unexplained_table(d)?;
    let shapes = output::unexplained_shapes_table(d)?;
    let mut out = StageOutput::default()
        .file("diagnosis.csv".into(), output::csv(&table)?)
        .file("unexplained.csv".into(), output::csv(&unexplained)?)
        .file("unexplained-shapes.csv".into(), output::csv(&shapes)?)
        .file("report.md".into(), report.into_bytes())
        .file("report.html".into(), page.into_bytes())
        .table("diagnosis", table)
        .table("where", output::where_table(d)?)
        .table("residuals", output::residuals_table(d)?)
        .table("summary", output::summary_table(d)?)
        .table("skipped", output::skipped_table(d)?)
        .table("unexplained", unexplained)
        .table("unexplained_shapes", shapes);
    for (name, svg) in figures.files {
        out = out.file(name, svg);
    }
    if let Some(text) = crate::diagnose::localise::discovered(&d.campaign, &d.unexplained) {
        out = out.file("discovered.toml".into(), text.into_bytes());
    }
    Ok(out)
}

impl StageKind for DiagnoseStage {
    const KIND: &'static str = "diagnose";
    const SUMMARY: &'static str = "where a campaign's residual lies, which unmodelled effect causes it, how far the gap shrinks";
    const INPUTS: &'static [Slot] = &[Slot::group(
        "campaign",
        true,
        "the campaign to diagnose (`import_campaign` or `simulate_campaign`)",
        campaign::TABLES,
    )];
    const OUTPUTS: &'static [&'static str] = &[
        "diagnosis",
        "where",
        "residuals",
        "summary",
        "skipped",
        "unexplained",
        "unexplained_shapes",
    ];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "diagnosis" => Some(crate::diagnose::output::DIAGNOSIS_COLUMNS),
            "unexplained" => Some(&[
                "factor",
                "basis",
                "columns",
                "alternatives",
                "delta_chi2",
                "share",
                "f",
                "p",
                "p_corrected",
                "significant",
                "gap_removed_pct",
            ]),
            "unexplained_shapes" => {
                Some(&["factor", "along", "at", "x", "value", "value_u", "unit"])
            }
            "where" => Some(&[
                "factor",
                "component",
                "groups",
                "eta2",
                "f",
                "p",
                "significant",
                "worst_group",
                "worst_mean_sigma",
            ]),
            "residuals" => Some(&[
                "station",
                "target",
                "face",
                "az_urad",
                "el_urad",
                "d_um",
                "az_sigma",
                "el_sigma",
                "d_sigma",
                "incidence_deg",
                "range_mm",
                "azimuth_deg",
                "elevation_deg",
                "time_s",
                "temperature_c",
                "w_az",
                "w_el",
                "w_d",
                "redundancy_az",
                "redundancy_el",
                "redundancy_d",
            ]),
            "summary" => Some(&[
                "campaign",
                "chi2",
                "dof",
                "chi2_p",
                "noise_stated",
                "noise_floor_um",
                "noise_floor_u_um",
                "tried",
                "blunder_tests",
                "explanation",
                "set_rms_before_um",
                "set_rms_after_um",
                "set_gap_shrink_pct",
                "verdict",
            ]),
            "skipped" => Some(&["effect", "reason"]),
            _ => None,
        }
    }

    fn file(&self) -> Option<StageFile<'_>> {
        self.hypotheses.as_deref().map(|path| StageFile {
            field: "hypotheses",
            path,
            check: check_hypotheses,
        })
    }

    fn validate(&self) -> Vec<Invalid> {
        let mut out: Vec<Invalid> = fitting::check(self.model, &self.shapes, &self.fixed, 0.5, 1);
        if !(2..=20).contains(&self.folds) {
            out.push(Invalid::new(
                "folds",
                format!("`folds` must be 2 … 20, got {}", self.folds),
            ));
        }
        if self.mc_draws > 100_000 {
            out.push(Invalid::new(
                "mc_draws",
                "`mc_draws` must be at most 100000",
            ));
        }
        if !(self.alpha > 0.0 && self.alpha < 0.5) {
            out.push(Invalid::new(
                "alpha",
                format!("`alpha` must lie in (0, 0.5), got {}", self.alpha),
            ));
        }
        for (i, e) in self.effects.iter().enumerate() {
            if !(effects::kind(e).is_some() || e == "blunder") {
                out.push(Invalid::new(
                    format!("effects.{i}"),
                    format!(
                        "`{e}` is not a candidate effect; one of {}, blunder",
                        effects::ids_joined()
                    ),
                ));
            }
        }
        if !(1..=100).contains(&self.max_steps) {
            out.push(Invalid::new(
                "max_steps",
                format!("`max_steps` must be 1 … 100, got {}", self.max_steps),
            ));
        }
        out
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let c = Campaign::from_inputs(inputs, "campaign")?;
        outputs(&self.diagnose(&c)?)
    }
}
