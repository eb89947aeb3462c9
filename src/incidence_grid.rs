//! Table 9's kind of measurement — an SMR's interferometer reading over a
//! grid of incidence angles (Section 10) — and the two models fitted to it:
//! the vertex offset of effects.md's `incidence` effect and a polynomial.
//! The `incidence_fit` stage reads the file and publishes these fits; the
//! mathematics lives here so that a stage is configuration and tables only.
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
//! **Polynomial**: every monomial `α_v^i·α_h^j` with `i + j ≤ order`
//! (degrees), constant included.
//!
//! Both are linear least squares; `std` is the coefficient's standard error
//! from the residual scatter (`s² = RSS/(n − p)`).

use anyhow::{Result, anyhow, bail};
use nalgebra::{DMatrix, DVector};
use std::path::Path;

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
