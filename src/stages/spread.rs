//! `spread`: the scatter of an estimate over repeated draws against the
//! standard uncertainty each draw reported.
//!
//! A standard uncertainty claims to be the standard deviation of the
//! estimator (GUM 2.3.1). Over the noise seeds of a sweep that claim can be
//! checked: the sample standard deviation of the estimates (`spread`)
//! against the root mean square of the reported ones (`std_reported`).
//! With `n` draws the ratio itself is uncertain by about `1/√(2(n−1))`
//! (4.1 % at 300 draws), which the table states beside it.
//!
//! ```toml
//! [stages.identify_spread]
//! kind = "spread"
//! inputs = { table = "sweep.identify.params" }   # one row per draw and key
//! by = ["coef"]        # one output row per distinct key (any columns)
//! value = "value"      # the estimate
//! std = "std"          # its reported standard uncertainty
//! band_pct = 10        # `within_band`: |ratio − 1| ≤ band_pct / 100
//! min_std = 1e-9       # keys reporting less are left out
//! ```
//!
//! Rows whose value or reported uncertainty is missing (fixed
//! coefficients) are left out; so are keys whose reported uncertainty is
//! below `min_std` (a coefficient the data cannot move: its value and its
//! uncertainty are both round-off, and so is their ratio). Output `spread`: the
//! `by` columns, `n`, `mean`, `spread`, `std_reported`, `ratio` =
//! `spread / std_reported`, `ratio_u` = `ratio / √(2(n−1))`,
//! `within_band`.

use super::{ColumnUse, Context, Invalid, Slot, StageInputs, StageKind, StageOutput};
use crate::table::TableBuilder;
use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct SpreadStage {
    /// Columns that key an output row (e.g. `coef`).
    #[serde(default = "default_by")]
    pub by: Vec<String>,
    /// The column of the estimate.
    #[serde(default = "default_value")]
    pub value: String,
    /// The column of its reported standard uncertainty.
    #[serde(default = "default_std")]
    pub std: String,
    /// `within_band` when |ratio − 1| ≤ band_pct / 100.
    #[serde(default = "default_band")]
    pub band_pct: f64,
    /// Keys reporting a smaller uncertainty are left out (round-off).
    #[serde(default = "default_min_std")]
    pub min_std: f64,
}

fn default_by() -> Vec<String> {
    vec!["coef".into()]
}
fn default_value() -> String {
    "value".into()
}
fn default_std() -> String {
    "std".into()
}
fn default_band() -> f64 {
    10.0
}
fn default_min_std() -> f64 {
    1e-9
}

/// One key's draws: the statistics of [`SpreadStage`]'s table.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Spread {
    pub n: usize,
    pub mean: f64,
    /// Sample standard deviation of the estimates.
    pub spread: f64,
    /// Root mean square of the reported standard uncertainties.
    pub std_reported: f64,
}

impl Spread {
    /// `None` with fewer than two draws.
    pub fn of(values: &[f64], stds: &[f64]) -> Option<Spread> {
        let n = values.len();
        if n < 2 || stds.len() != n {
            return None;
        }
        let mean = values.iter().sum::<f64>() / n as f64;
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        let ms = stds.iter().map(|s| s * s).sum::<f64>() / n as f64;
        Some(Spread {
            n,
            mean,
            spread: var.sqrt(),
            std_reported: ms.sqrt(),
        })
    }

    pub fn ratio(&self) -> f64 {
        self.spread / self.std_reported
    }

    /// The standard uncertainty of [`Spread::ratio`] from the number of
    /// draws (a normal sample's standard deviation).
    pub fn ratio_u(&self) -> f64 {
        self.ratio() / (2.0 * (self.n - 1) as f64).sqrt()
    }
}

impl StageKind for SpreadStage {
    const KIND: &'static str = "spread";
    const SUMMARY: &'static str = "the scatter of an estimate over draws (sweep seeds) against its reported standard uncertainty";
    const INPUTS: &'static [Slot] = &[Slot::table(
        "table",
        true,
        "one row per draw and key (a gathered sweep table)",
    )];
    const OUTPUTS: &'static [&'static str] = &["spread"];

    fn validate(&self) -> Vec<Invalid> {
        let mut out = Vec::new();
        if !(self.band_pct.is_finite() && self.band_pct > 0.0) {
            out.push(Invalid::new(
                "band_pct",
                format!("`band_pct` must be above 0, got {}", self.band_pct),
            ));
        }
        if !(self.min_std.is_finite() && self.min_std >= 0.0) {
            out.push(Invalid::new(
                "min_std",
                format!("`min_std` must be 0 or above, got {}", self.min_std),
            ));
        }
        if self.by.contains(&self.value) || self.by.contains(&self.std) {
            out.push(Invalid::new(
                "by",
                "`by` must not hold the `value` or `std` column",
            ));
        }
        out
    }

    fn columns_named(&self) -> Vec<ColumnUse> {
        let mut out: Vec<ColumnUse> = self
            .by
            .iter()
            .enumerate()
            .map(|(i, c)| ColumnUse {
                slot: "table",
                field: format!("by.{i}"),
                column: c.clone(),
            })
            .collect();
        for (field, c) in [("value", &self.value), ("std", &self.std)] {
            out.push(ColumnUse {
                slot: "table",
                field: field.into(),
                column: c.clone(),
            });
        }
        out
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let t = inputs.get("table")?;
        let keys: Vec<Vec<String>> = self.by.iter().map(|c| t.text(c)).collect::<Result<_>>()?;
        let (values, stds) = (t.opt_f64(&self.value)?, t.opt_f64(&self.std)?);
        // Keys in order of first appearance, so the table reads like its input.
        let mut order: Vec<Vec<String>> = Vec::new();
        let mut draws: BTreeMap<Vec<String>, (Vec<f64>, Vec<f64>)> = BTreeMap::new();
        for i in 0..t.height() {
            let (Some(v), Some(s)) = (values[i], stds[i]) else {
                continue;
            };
            let key: Vec<String> = keys.iter().map(|k| k[i].clone()).collect();
            let e = draws.entry(key.clone()).or_insert_with(|| {
                order.push(key);
                (Vec::new(), Vec::new())
            });
            e.0.push(v);
            e.1.push(s);
        }
        let rows: Vec<(&Vec<String>, Spread)> = order
            .iter()
            .filter_map(|k| {
                let (v, s) = &draws[k];
                Spread::of(v, s)
                    .filter(|x| x.std_reported > self.min_std)
                    .map(|x| (k, x))
            })
            .collect();
        if rows.is_empty() {
            bail!(
                "table `{}` has no key with two or more draws that report a standard uncertainty above {}",
                t.name,
                self.min_std
            );
        }
        let band = self.band_pct / 100.0;
        let mut b = TableBuilder::new();
        for (j, col) in self.by.iter().enumerate() {
            b = b.str(
                col,
                &rows.iter().map(|r| r.0[j].as_str()).collect::<Vec<_>>(),
            );
        }
        let table = b
            .i64("n", rows.iter().map(|r| r.1.n as i64).collect())
            .f64("mean", rows.iter().map(|r| r.1.mean).collect())
            .f64("spread", rows.iter().map(|r| r.1.spread).collect())
            .f64(
                "std_reported",
                rows.iter().map(|r| r.1.std_reported).collect(),
            )
            .f64("ratio", rows.iter().map(|r| r.1.ratio()).collect())
            .f64("ratio_u", rows.iter().map(|r| r.1.ratio_u()).collect())
            .bool(
                "within_band",
                rows.iter()
                    .map(|r| (r.1.ratio() - 1.0).abs() <= band)
                    .collect(),
            )
            .build()?;
        Ok(StageOutput::default().table("spread", table))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spread_is_the_sample_deviation_against_the_rms_of_the_reported() {
        let s = Spread::of(&[1.0, 2.0, 3.0], &[1.0, 1.0, 1.0]).unwrap();
        assert_eq!((s.n, s.mean, s.spread, s.std_reported), (3, 2.0, 1.0, 1.0));
        assert_eq!(s.ratio(), 1.0);
        assert_eq!(s.ratio_u(), 0.5);
        let s = Spread::of(&[0.0, 2.0], &[1.0, 7.0_f64.sqrt()]).unwrap();
        assert_eq!(s.std_reported, 2.0);
        assert!((s.ratio() - 2.0_f64.sqrt() / 2.0).abs() < 1e-15);
        assert!(Spread::of(&[1.0], &[1.0]).is_none());
    }
}
