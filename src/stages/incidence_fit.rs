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
//! **Vertex-offset model** (effects.md, `incidence`):
//! `Δd = e_axial·(1 − cos α) + e_h·sin α_h + e_v·sin α_v`. A cell gives
//! `(α_v, α_h)`; with effects.md's `α_h = atan2(r·h, r·n)` and
//! `α_v = atan2(r·v, r·n)` the beam direction is `r ∝ n + tan α_h·h +
//! tan α_v·v`, so `cos α = r·n = 1/√(1 + tan²α_h + tan²α_v)`. No constant:
//! the interferometer was reset at normal incidence (Section 10) and the
//! table's centre cell is exactly 0.0, which is the model's own
//! `Δd(0, 0) = 0`; a constant would be a range offset (R0), which the
//! kinematic model already has, not an incidence effect.
//!
//! **Polynomial**: every monomial `α_v^i·α_h^j` with `i + j ≤ poly_order`
//! (degrees), constant included. The default is 3, the lowest order that
//! describes the table's shape: along α_v the reading falls steeply from
//! −30° and flattens past 0° (10.0, 6.2, 3.0, 0.9, 0, −0.5, … at α_h = 0),
//! which no quadratic follows; `ltcal run pipelines/incidence.toml --set
//! stages.incidence.poly_order=2` shows what a quadratic leaves.
//!
//! Both are linear least squares; `std` is the coefficient's standard error
//! from the residual scatter (`s² = RSS/(n − p)`).
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
use crate::plots::{self, FitMaps};
use crate::table::TableBuilder;
use anyhow::{Result, anyhow, bail};
use nalgebra::{DMatrix, DVector};
use polars::prelude::DataFrame;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IncidenceFitStage {
    #[serde(default = "default_path")]
    pub path: PathBuf,
    #[serde(default = "default_order")]
    pub poly_order: usize,
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

/// A measured grid: `um[i][j]` at `(alpha_v_deg[i], alpha_h_deg[j])`.
#[derive(Clone, Debug, PartialEq)]
pub struct Grid {
    pub alpha_v_deg: Vec<f64>,
    pub alpha_h_deg: Vec<f64>,
    pub um: Vec<Vec<f64>>,
}

/// Reads a grid file (see the module doc); errors name `file:line`.
pub fn read_grid(path: &Path, text: &str) -> Result<Grid> {
    let at = |line: usize| format!("{}:{line}", path.display());
    let mut rows = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'));
    let (hline, header) = rows
        .next()
        .ok_or_else(|| anyhow!("{}: no header line `alpha_v_deg,<α_h>…`", path.display()))?;
    let mut cells = header.split(',').map(str::trim);
    if cells.next() != Some("alpha_v_deg") {
        bail!("{}: the header must start with `alpha_v_deg`", at(hline));
    }
    let number = |s: &str, line: usize, what: &str| -> Result<f64> {
        s.parse::<f64>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| anyhow!("{}: {what} `{s}` is not a number", at(line)))
    };
    let alpha_h_deg = cells
        .map(|c| number(c, hline, "the α_h header cell"))
        .collect::<Result<Vec<f64>>>()?;
    if alpha_h_deg.len() < 2 {
        bail!("{}: the header needs at least two α_h columns", at(hline));
    }
    let (mut alpha_v_deg, mut um) = (Vec::new(), Vec::new());
    for (line, l) in rows {
        let c: Vec<&str> = l.split(',').map(str::trim).collect();
        if c.len() != alpha_h_deg.len() + 1 {
            bail!(
                "{}: {} cells, the header has {}",
                at(line),
                c.len(),
                alpha_h_deg.len() + 1
            );
        }
        alpha_v_deg.push(number(c[0], line, "α_v")?);
        um.push(
            c[1..]
                .iter()
                .map(|s| number(s, line, "reading"))
                .collect::<Result<Vec<f64>>>()?,
        );
    }
    if alpha_v_deg.len() < 2 {
        bail!("{}: needs at least two α_v rows", path.display());
    }
    for (name, v) in [("α_v", &alpha_v_deg), ("α_h", &alpha_h_deg)] {
        if v.windows(2).any(|w| w[1] <= w[0]) {
            bail!("{}: the {name} values must increase", path.display());
        }
        if v.iter().any(|a| a.abs() >= 90.0) {
            bail!(
                "{}: the {name} values must lie inside (−90°, 90°)",
                path.display()
            );
        }
    }
    Ok(Grid {
        alpha_v_deg,
        alpha_h_deg,
        um,
    })
}

/// The blake3 hash of a file's bytes.
fn hash(bytes: &[u8]) -> String {
    blake3::hash(bytes).to_hex().to_string()
}

/// One fitted model: its parameters with units and standard errors, and its
/// value at every cell.
#[derive(Clone, Debug)]
pub struct Fit {
    pub names: Vec<String>,
    pub units: Vec<String>,
    pub values: Vec<f64>,
    pub std: Vec<f64>,
    /// `[i][j]` as the grid.
    pub fitted: Vec<Vec<f64>>,
}

impl Fit {
    pub fn residuals<'a>(&'a self, g: &'a Grid) -> impl Iterator<Item = f64> + 'a {
        g.um.iter()
            .flatten()
            .zip(self.fitted.iter().flatten())
            .map(|(d, f)| d - f)
    }
    pub fn rms_um(&self, g: &Grid) -> f64 {
        let n = g.um.iter().flatten().count().max(1);
        (self.residuals(g).map(|r| r * r).sum::<f64>() / n as f64).sqrt()
    }
    pub fn max_um(&self, g: &Grid) -> f64 {
        self.residuals(g).map(f64::abs).fold(0.0, f64::max)
    }
    pub fn value(&self, name: &str) -> Option<f64> {
        self.names
            .iter()
            .position(|n| n == name)
            .map(|i| self.values[i])
    }
}

/// Least squares of `y ≈ A·x` over the grid's cells (row-major), with the
/// standard errors from the residual scatter; the caller names the
/// parameters.
fn least_squares(g: &Grid, terms: &dyn Fn(f64, f64) -> Vec<f64>) -> Result<Fit> {
    let rows: Vec<Vec<f64>> = g
        .alpha_v_deg
        .iter()
        .flat_map(|&v| g.alpha_h_deg.iter().map(move |&h| terms(v, h)))
        .collect();
    let (n, p) = (rows.len(), rows[0].len());
    if n <= p {
        bail!("{n} cells cannot fit {p} parameters with a residual to spare");
    }
    let a = DMatrix::from_fn(n, p, |i, j| rows[i][j]);
    let y = DVector::from_iterator(n, g.um.iter().flatten().copied());
    let ata = a.transpose() * &a;
    let cov = ata
        .clone()
        .try_inverse()
        .ok_or_else(|| anyhow!("the model's terms are linearly dependent on this grid"))?;
    let x = &cov * (a.transpose() * &y);
    let fitted = &a * &x;
    let rss = (&y - &fitted).norm_squared();
    let s2 = rss / (n - p) as f64;
    let std = (0..p).map(|k| (s2 * cov[(k, k)]).sqrt()).collect();
    let cols = g.alpha_h_deg.len();
    let grid = fitted
        .as_slice()
        .chunks(cols)
        .map(<[f64]>::to_vec)
        .collect();
    Ok(Fit {
        names: Vec::new(),
        units: Vec::new(),
        values: x.as_slice().to_vec(),
        std,
        fitted: grid,
    })
}

/// `(1 − cos α, sin α_h, sin α_v)` of a cell, from `r ∝ n + tan α_h·h + tan α_v·v`.
pub fn vertex_terms(alpha_v_deg: f64, alpha_h_deg: f64) -> [f64; 3] {
    let (v, h) = (alpha_v_deg.to_radians(), alpha_h_deg.to_radians());
    let cos_alpha = 1.0 / (1.0 + h.tan().powi(2) + v.tan().powi(2)).sqrt();
    [1.0 - cos_alpha, h.sin(), v.sin()]
}

/// The vertex-offset model of effects.md (`e_axial_um`, `e_h_um`, `e_v_um`).
pub fn fit_vertex(g: &Grid) -> Result<Fit> {
    Ok(Fit {
        names: vec!["e_axial_um".into(), "e_h_um".into(), "e_v_um".into()],
        units: vec!["µm".into(); 3],
        ..least_squares(g, &|v, h| vertex_terms(v, h).to_vec())?
    })
}

/// Exponents `(i, j)` of `α_v^i·α_h^j`, `i + j ≤ order`, by total degree.
fn monomials(order: usize) -> Vec<(i32, i32)> {
    (0..=order as i32)
        .flat_map(|deg| (0..=deg).rev().map(move |i| (i, deg - i)))
        .collect()
}

/// The full polynomial of total degree `order` in `α_v`, `α_h` (degrees).
pub fn fit_poly(g: &Grid, order: usize) -> Result<Fit> {
    let m = monomials(order);
    let fit = least_squares(g, &|v, h| {
        m.iter().map(|&(i, j)| v.powi(i) * h.powi(j)).collect()
    })?;
    let power = |name: &str, k: i32| match k {
        0 => String::new(),
        1 => name.to_string(),
        k => format!("{name}^{k}"),
    };
    let names = m
        .iter()
        .map(|&(i, j)| {
            let t: Vec<String> = [power("alpha_v", i), power("alpha_h", j)]
                .into_iter()
                .filter(|s| !s.is_empty())
                .collect();
            if t.is_empty() {
                "1".into()
            } else {
                t.join("*")
            }
        })
        .collect();
    let units = m
        .iter()
        .map(|&(i, j)| match i + j {
            0 => "µm".to_string(),
            1 => "µm/deg".to_string(),
            k => format!("µm/deg^{k}"),
        })
        .collect();
    Ok(Fit {
        names,
        units,
        ..fit
    })
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vertex_terms_follow_effects_md() {
        // Along one axis α is that angle: 1 − cos α, sin α.
        let t = vertex_terms(0.0, 30.0);
        assert!((t[0] - (1.0 - 30f64.to_radians().cos())).abs() < 1e-15);
        assert!((t[1] - 0.5).abs() < 1e-15 && t[2] == 0.0);
        // Off the axes, the angles effects.md computes from r are the cell's.
        let (v, h) = (-22.5f64, 15.0f64);
        let (n, hh, vv) = (
            nalgebra::Vector3::new(1.0, 0.0, 0.0),
            nalgebra::Vector3::new(0.0, 1.0, 0.0),
            nalgebra::Vector3::new(0.0, 0.0, 1.0),
        );
        let r = (n + h.to_radians().tan() * hh + v.to_radians().tan() * vv).normalize();
        assert!((r.dot(&hh).atan2(r.dot(&n)).to_degrees() - h).abs() < 1e-12);
        assert!((r.dot(&vv).atan2(r.dot(&n)).to_degrees() - v).abs() < 1e-12);
        assert!((vertex_terms(v, h)[0] - (1.0 - r.dot(&n))).abs() < 1e-15);
    }

    #[test]
    fn an_exact_model_is_recovered_exactly() {
        let a: Vec<f64> = (0..5).map(|i| -30.0 + 15.0 * i as f64).collect();
        let um = a
            .iter()
            .map(|&v| {
                a.iter()
                    .map(|&h| {
                        let t = vertex_terms(v, h);
                        20.0 * t[0] - 3.0 * t[1] + 7.0 * t[2]
                    })
                    .collect()
            })
            .collect();
        let g = Grid {
            alpha_v_deg: a.clone(),
            alpha_h_deg: a,
            um,
        };
        let f = fit_vertex(&g).unwrap();
        for (got, want) in f.values.iter().zip([20.0, -3.0, 7.0]) {
            assert!((got - want).abs() < 1e-9, "{:?}", f.values);
        }
        assert!(f.rms_um(&g) < 1e-9);
        assert_eq!(
            monomials(2),
            vec![(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2)]
        );
    }

    #[test]
    fn a_bad_grid_file_names_the_line() {
        let p = Path::new("t.csv");
        let e = read_grid(p, "# c\nalpha_v_deg,-1,1\n-1,0,1\n1,0\n").unwrap_err();
        assert_eq!(e.to_string(), "t.csv:4: 2 cells, the header has 3");
        let e = read_grid(p, "alpha_v_deg,-1,1\n-1,0,x\n1,0,1\n").unwrap_err();
        assert_eq!(e.to_string(), "t.csv:2: reading `x` is not a number");
    }
}
