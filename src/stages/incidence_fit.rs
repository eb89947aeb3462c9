//! `incidence_fit`: Section 10 — the paper's only published raw measurement,
//! Table 9 (an SMR's interferometer reading against its incidence angles),
//! fitted with the vertex-offset model of effects.md's `incidence` effect and
//! with a low-order polynomial, so that the measured effect can be put into a
//! simulated campaign.
//!
//! ```toml
//! [stages.incidence]
//! kind = "incidence_fit"
//! path = "pipelines/data/table9.csv"   # the default; relative to where ltcal runs
//! poly_order = 3                       # total degree of the polynomial, 1 … 4
//! snippet_stage = "simulated"          # the stage name written into the effect snippet
//! ```
//!
//! The file is a grid: `#` comment lines, a header `alpha_v_deg,<α_h>…`,
//! then one row per α_v (degrees; µm in the cells). ltcal reads it when
//! the pipeline loads and its blake3 hash enters the cache key
//! ([`super::StageFile`]), so an edited file is not answered from the cache.
//!
//! The models — effects.md's vertex offset and a polynomial of total degree
//! `poly_order` — and their least squares are in [`crate::incidence_grid`].
//! The polynomial's default order is 3, the lowest that describes the
//! table's shape: along α_v the reading falls steeply from −30° and flattens
//! past 0° (10.0, 6.2, 3.0, 0.9, 0, −0.5, … at α_h = 0), which no quadratic
//! follows; `ltcal run pipelines/incidence.toml --set
//! stages.incidence.poly_order=2` shows what a quadratic leaves.
//!
//! Outputs: `fits` (`model`, `parameter`, `value`, `unit`, `std`),
//! `residuals` (`model`, `rms_um`, `max_um` (largest |residual|), `n`),
//! `grid` (`alpha_v_deg`, `alpha_h_deg`, `data_um`, `vertex_um`,
//! `poly_um`), `effect` (`model`, `toml`: the fitted vertex model as a
//! `simulate_campaign` effect), and the files `incidence-effect.toml` (the
//! same snippet) and `table9-fits.svg` (data, fits and residuals as heat
//! maps).

use super::{Context, Invalid, Slot, StageFile, StageInputs, StageKind, StageOutput};
use crate::effects::DEFAULT_MAX_ANGLE_DEG;
use crate::incidence_grid::{Fit, Grid, fit_poly, fit_vertex, read_grid};
use crate::plots::{self, FitMaps};
use crate::table::TableBuilder;
use anyhow::{Result, anyhow, bail};
use polars::prelude::DataFrame;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct IncidenceFitStage {
    /// The Table 9 grid file, relative to where ltcal runs.
    #[serde(default = "default_path")]
    pub path: PathBuf,
    /// Total degree of the polynomial fit, 1 … 4.
    #[serde(default = "default_order")]
    pub poly_order: usize,
    /// The stage name written into the effect snippet.
    #[serde(default = "default_snippet_stage")]
    pub snippet_stage: String,
}

/// The file's check when the pipeline loads: a readable grid, and its hash.
fn check(path: &Path) -> Result<String, String> {
    let bytes = read_data(path).map_err(|e| format!("`path`: {e}"))?;
    let text = std::str::from_utf8(&bytes).map_err(|_| {
        format!(
            "`path`: cannot read {}: stream did not contain valid UTF-8",
            path.display()
        )
    })?;
    read_grid(path, text).map_err(|e| e.to_string())?;
    Ok(hash(&bytes))
}

fn default_path() -> PathBuf {
    PathBuf::from("pipelines/data/table9.csv")
}
fn default_order() -> usize {
    3
}
fn default_snippet_stage() -> String {
    "simulated".into()
}

/// The blake3 hash of a file's bytes.
fn hash(bytes: &[u8]) -> String {
    blake3::hash(bytes).to_hex().to_string()
}

/// The fitted vertex model as a `simulate_campaign` effect (effects.md
/// `incidence`), ready to paste.
pub fn effect_snippet(stage: &str, vertex: &Fit, rms_um: f64, source: &Path) -> String {
    let v = |n: &str| vertex.value(n).unwrap_or(f64::NAN);
    format!(
        "# The `incidence` effect (effects.md): the vertex-offset model fitted to\n\
         # {} by ltcal's `incidence_fit` stage (residual RMS {rms_um:.3} µm).\n\
         # Paste it after your `simulate_campaign` stage and rename `{stage}` to\n\
         # that stage's name.\n\
         [stages.{stage}.effects.incidence]\n\
         e_axial_um = {:.4}\n\
         e_h_um = {:.4}\n\
         e_v_um = {:.4}\n\
         max_angle_deg = {:.1}\n",
        source.display(),
        v("e_axial_um"),
        v("e_h_um"),
        v("e_v_um"),
        DEFAULT_MAX_ANGLE_DEG,
    )
}

/// The largest data file this stage reads: Table 9 is a few kilobytes, and
/// a measured map of the same kind would be far below this.
const MAX_DATA_BYTES: u64 = 64 << 20;

fn read_data(path: &Path) -> Result<Vec<u8>, crate::fs::ReadError> {
    crate::fs::read_regular_file(path, MAX_DATA_BYTES)
}

impl StageKind for IncidenceFitStage {
    const KIND: &'static str = "incidence_fit";
    const SUMMARY: &'static str = "Section 10: Table 9 fitted with the SMR vertex-offset model and a polynomial; the fit as a simulate_campaign effect";
    const INPUTS: &'static [Slot] = &[];
    const OUTPUTS: &'static [&'static str] = &["fits", "residuals", "grid", "effect"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "effect" => Some(&["model", "toml"]),
            "fits" => Some(&["model", "parameter", "value", "unit", "std"]),
            "grid" => Some(&[
                "alpha_v_deg",
                "alpha_h_deg",
                "data_um",
                "vertex_um",
                "poly_um",
            ]),
            "residuals" => Some(&["model", "rms_um", "max_um", "n"]),
            _ => None,
        }
    }

    fn file(&self) -> Option<StageFile<'_>> {
        Some(StageFile {
            field: "path",
            path: &self.path,
            check,
        })
    }

    fn validate(&self) -> Vec<Invalid> {
        let mut out = Vec::new();
        if !(1..=4).contains(&self.poly_order) {
            out.push(Invalid::new(
                "poly_order",
                format!("`poly_order` must be 1 … 4, got {}", self.poly_order),
            ));
        }
        let ident = |s: &str| {
            !s.is_empty()
                && s.chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        };
        if !ident(&self.snippet_stage) {
            out.push(Invalid::new(
                "snippet_stage",
                format!(
                    "`snippet_stage` must be a bare TOML key (letters, digits, _ and -), got \"{}\"",
                    self.snippet_stage
                ),
            ));
        }
        out
    }

    fn run(&self, ctx: &Context, _: &StageInputs) -> Result<StageOutput> {
        let bytes = read_data(&self.path)
            .map_err(|e| anyhow!("reading {}: {}", e.path.display(), e.reason))?;
        if Some(hash(&bytes).as_str()) != ctx.file_hash {
            bail!(
                "{} changed since the pipeline was loaded: run it again",
                self.path.display()
            );
        }
        let text = String::from_utf8(bytes)
            .map_err(|_| anyhow!("{} is not UTF-8 text", self.path.display()))?;
        let g = read_grid(&self.path, &text)?;
        let vertex = fit_vertex(&g)?;
        let poly = fit_poly(&g, self.poly_order)?;
        let models = [("vertex", &vertex), ("poly", &poly)];
        let snippet = effect_snippet(&self.snippet_stage, &vertex, vertex.rms_um(&g), &self.path);
        let svg = plots::incidence_maps(
            "Table 9: SMR incidence error, data, fits and residuals",
            &g.alpha_h_deg,
            &g.alpha_v_deg,
            &g.um,
            &[
                FitMaps {
                    label: format!("vertex offset (RMS {:.2} µm)", vertex.rms_um(&g)),
                    fitted: &vertex.fitted,
                },
                FitMaps {
                    label: format!(
                        "polynomial of order {} (RMS {:.2} µm)",
                        self.poly_order,
                        poly.rms_um(&g)
                    ),
                    fitted: &poly.fitted,
                },
            ],
        )?;
        Ok(StageOutput::default()
            .table("fits", fits_table(&models)?)
            .table("residuals", residuals_table(&models, &g)?)
            .table("grid", grid_table(&g, &vertex, &poly)?)
            .table(
                "effect",
                TableBuilder::new()
                    .str("model", &["vertex"])
                    .str("toml", &[&snippet])
                    .build()?,
            )
            .file("incidence-effect.toml".into(), snippet.into_bytes())
            .file("table9-fits.svg".into(), svg.into_bytes()))
    }
}

fn fits_table(models: &[(&str, &Fit)]) -> Result<DataFrame> {
    let rows: Vec<(&str, &Fit, usize)> = models
        .iter()
        .flat_map(|&(m, f)| (0..f.values.len()).map(move |k| (m, f, k)))
        .collect();
    TableBuilder::new()
        .str("model", &rows.iter().map(|r| r.0).collect::<Vec<_>>())
        .str(
            "parameter",
            &rows
                .iter()
                .map(|r| r.1.names[r.2].as_str())
                .collect::<Vec<_>>(),
        )
        .f64("value", rows.iter().map(|r| r.1.values[r.2]).collect())
        .str(
            "unit",
            &rows
                .iter()
                .map(|r| r.1.units[r.2].as_str())
                .collect::<Vec<_>>(),
        )
        .f64("std", rows.iter().map(|r| r.1.std[r.2]).collect())
        .build()
}

fn residuals_table(models: &[(&str, &Fit)], g: &Grid) -> Result<DataFrame> {
    let n = g.um.iter().flatten().count() as i64;
    TableBuilder::new()
        .str("model", &models.iter().map(|m| m.0).collect::<Vec<_>>())
        .f64("rms_um", models.iter().map(|m| m.1.rms_um(g)).collect())
        .f64("max_um", models.iter().map(|m| m.1.max_um(g)).collect())
        .i64("n", vec![n; models.len()])
        .build()
}

fn grid_table(g: &Grid, vertex: &Fit, poly: &Fit) -> Result<DataFrame> {
    let cells: Vec<(usize, usize)> = (0..g.alpha_v_deg.len())
        .flat_map(|i| (0..g.alpha_h_deg.len()).map(move |j| (i, j)))
        .collect();
    TableBuilder::new()
        .f64(
            "alpha_v_deg",
            cells.iter().map(|&(i, _)| g.alpha_v_deg[i]).collect(),
        )
        .f64(
            "alpha_h_deg",
            cells.iter().map(|&(_, j)| g.alpha_h_deg[j]).collect(),
        )
        .f64("data_um", cells.iter().map(|&(i, j)| g.um[i][j]).collect())
        .f64(
            "vertex_um",
            cells.iter().map(|&(i, j)| vertex.fitted[i][j]).collect(),
        )
        .f64(
            "poly_um",
            cells.iter().map(|&(i, j)| poly.fitted[i][j]).collect(),
        )
        .build()
}
