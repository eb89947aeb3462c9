//! `monte_carlo`: the uncertainty of a bundle calibration by GUM
//! Supplement 1 — the campaign's stated reading noise, gauge and reference
//! uncertainties propagated through the full nonlinear adjustment (see
//! [`crate::calibrate::monte_carlo`]), side by side with the linear
//! propagation the `calibrate` stage reports.
//!
//! ```toml
//! [stages.uncertainty]
//! kind = "monte_carlo"
//! inputs = { campaign = "corner" }   # a whole campaign (import or simulate); start = "…" optional
//! model = "api-tracker3"             # the tracker model (the campaign's by default)
//! shapes = {}                        # its shapes (constants by default)
//! fixed = []
//! block_trials = 10000               # M, trials per block (≥ 100/(1 − coverage))
//! digits = 1                         # significant digits the uncertainties must be stable to
//! max_trials = 100000                # whole blocks only; the outcome says whether they were
//! coverage = 0.95
//! seed = 0
//! ```
//!
//! Outputs: `params` (`coef`, `unit`, `value` — the nominal fit's —,
//! `mean`, `u_mc`, `low`, `high` — the coverage interval —, `u_linear`,
//! `u_ratio` = `u_mc / u_linear`, `determined`), `stations` and `targets`
//! (`station`/`target`, `x_mm`, `y_mm`, `z_mm`, `u_x_mm`, `u_y_mm`,
//! `u_z_mm`, `u_mm` — the root mean square of the three, what the linear
//! `std_mm` reports —, `u_linear_mm`, `u_ratio`; the stations also
//! `u_rotation_urad` — the root mean square of the three components of
//! the rotation away from the nominal pose —, `u_rotation_linear_urad`,
//! `u_rotation_ratio`; the station that defines the frame has none),
//! `trials` (per block: `block`, `trials`, `worst_ratio` — the largest
//! `2s/δ`, ≤ 1 when stable —, `stable`), and two figures: `coverage.svg`,
//! the determined coefficients' Monte Carlo coverage intervals beside the
//! linear `±z·u` (z = 1.96 at 95 %), in units of `u`, and `ellipses.svg`,
//! the reflectors in plan with their 95 % uncertainty ellipses from the
//! network (the bundle's linear covariance of x, y, magnified) and the
//! stations.
//!
//! The linear uncertainties are `calibrate`'s default (`std = "auto"`):
//! the stated noise while the χ² test accepts it, else the noise the
//! variance components estimate; the trials draw the stated noise alone,
//! so a campaign whose residuals refute the stated noise shows `u_ratio`
//! away from 1 for that reason alone.

use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput, fitting};
use crate::calibrate::bundle::Repeated;
use crate::calibrate::monte_carlo::{self, Estimate, Outcome, Output};
use crate::calibrate::{self, Calibration, Network};
use crate::campaign::Campaign;
use crate::error_model::{ParamId, Shape};
use crate::plots::{self, CoverageRow, PlanPoint};
use crate::table::TableBuilder;
use crate::trackers::TrackerModel;
use anyhow::{Result, anyhow};
use polars::prelude::DataFrame;
use serde::{Deserialize, Serialize};
use statrs::distribution::{ContinuousCDF, Normal};
use std::collections::BTreeMap;

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct MonteCarloStage {
    /// The tracker model to fit; the campaign's by default.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<TrackerModel>,
    /// Its shapes (constants by default).
    #[serde(default)]
    pub shapes: BTreeMap<ParamId, Shape>,
    /// Parameters held at their start value.
    #[serde(default)]
    pub fixed: Vec<ParamId>,
    /// Relative singular-value threshold below which a direction counts as not
    /// determined.
    #[serde(default = "fitting::default_rank_tol")]
    pub rank_tol: f64,
    /// Iteration limit of each trial's adjustment.
    #[serde(default = "fitting::default_max_iters")]
    pub max_iters: u64,
    /// Trials per block, M (at least 100/(1 − coverage)).
    #[serde(default = "default_block")]
    pub block_trials: usize,
    /// Significant digits the uncertainties must be stable to (GUM-S1 §7.9).
    #[serde(default = "default_digits")]
    pub digits: u32,
    /// Trials at most, in whole blocks; the `trials` table says whether they
    /// were stable.
    #[serde(default = "default_max_trials")]
    pub max_trials: usize,
    /// Probability of the coverage intervals.
    #[serde(default = "default_coverage")]
    pub coverage: f64,
    /// Seed of the trials: trial i is seeded by i, whatever the thread count.
    #[serde(default)]
    pub seed: u64,
}

fn default_block() -> usize {
    monte_carlo::DEFAULT_BLOCK_TRIALS
}
fn default_digits() -> u32 {
    1
}
fn default_max_trials() -> usize {
    100_000
}
fn default_coverage() -> f64 {
    0.95
}

/// The tables' coordinate columns.
const XYZ: [&str; 3] = ["x_mm", "y_mm", "z_mm"];
const U_XYZ: [&str; 3] = ["u_x_mm", "u_y_mm", "u_z_mm"];

impl MonteCarloStage {
    /// The nominal calibration (its linear uncertainties) and the
    /// propagation.
    pub fn propagate(
        &self,
        c: &Campaign,
        inputs: Option<&StageInputs>,
    ) -> Result<(Network, Calibration, Outcome)> {
        let net = Network::from_campaign(c)?;
        let tracker = fitting::tracker(self.model, c);
        let model = fitting::run_model(tracker, &self.shapes, &self.fixed)?;
        let start = fitting::start(&model, inputs)?;
        let free = fitting::free(&start, &self.fixed);
        let settings = calibrate::Settings {
            rank_tol: self.rank_tol,
            max_iters: self.max_iters,
            ..calibrate::Settings::bundle()
        };
        let cal = calibrate::calibrate(&net, &start, &free, &settings)?;
        let repeated = Repeated::new(&net, &start, &free, &settings)?;
        let outcome = monte_carlo::run(
            &net,
            &repeated,
            &free,
            &monte_carlo::Settings {
                block_trials: self.block_trials,
                digits: self.digits,
                max_trials: self.max_trials,
                coverage: self.coverage,
                seed: self.seed,
            },
        )?;
        Ok((net, cal, outcome))
    }
}

impl StageKind for MonteCarloStage {
    const KIND: &'static str = "monte_carlo";
    const SUMMARY: &'static str = "uncertainty of a bundle calibration by Monte Carlo (GUM Supplement 1, adaptive), beside the linear propagation";
    const INPUTS: &'static [Slot] = &[fitting::CAMPAIGN, fitting::START];
    const OUTPUTS: &'static [&'static str] = &["params", "stations", "targets", "trials"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "params" => Some(&[
                "coef",
                "unit",
                "value",
                "mean",
                "u_mc",
                "low",
                "high",
                "u_linear",
                "u_ratio",
                "determined",
            ]),
            "stations" => Some(&[
                "station",
                "x_mm",
                "y_mm",
                "z_mm",
                "u_x_mm",
                "u_y_mm",
                "u_z_mm",
                "u_mm",
                "u_linear_mm",
                "u_ratio",
                "u_rotation_urad",
                "u_rotation_linear_urad",
                "u_rotation_ratio",
            ]),
            "targets" => Some(&[
                "target",
                "x_mm",
                "y_mm",
                "z_mm",
                "u_x_mm",
                "u_y_mm",
                "u_z_mm",
                "u_mm",
                "u_linear_mm",
                "u_ratio",
            ]),
            "trials" => Some(&["block", "trials", "worst_ratio", "stable"]),
            _ => None,
        }
    }

    fn validate(&self) -> Vec<Invalid> {
        let mut out = fitting::check(
            self.model,
            &self.shapes,
            &self.fixed,
            self.rank_tol,
            self.max_iters,
        );
        if !(self.coverage > 0.5 && self.coverage < 1.0) {
            out.push(Invalid::new(
                "coverage",
                format!("`coverage` must lie in (0.5, 1), got {}", self.coverage),
            ));
        } else {
            let min = monte_carlo::min_block_trials(self.coverage);
            if self.block_trials < min {
                out.push(Invalid::new(
                    "block_trials",
                    format!(
                        "`block_trials` must be at least {min} (GUM-S1 7.9.4: 100/(1 − coverage)), got {}",
                        self.block_trials
                    ),
                ));
            }
        }
        if !(1..=4).contains(&self.digits) {
            out.push(Invalid::new("digits", "`digits` must be 1 … 4"));
        }
        if self.max_trials < self.block_trials {
            out.push(Invalid::new(
                "max_trials",
                "`max_trials` must be at least `block_trials`",
            ));
        } else if self.max_trials / self.block_trials.max(1) > monte_carlo::MAX_BLOCKS {
            out.push(Invalid::new(
                "max_trials",
                format!(
                    "`max_trials` allows at most {} blocks of `block_trials`: raise `block_trials` or lower `max_trials`",
                    monte_carlo::MAX_BLOCKS
                ),
            ));
        }
        out
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let c = Campaign::from_inputs(inputs, "campaign")?;
        let (net, cal, outcome) = self.propagate(&c, Some(inputs))?;
        let coverage = plots::coverage_intervals(
            &format!(
                "{}: {} % coverage intervals of the determined coefficients ({} trials)",
                c.meta.name,
                100.0 * self.coverage,
                outcome.trials
            ),
            &coverage_rows(&cal, &outcome, self.coverage)?,
        )?;
        let (stations, targets) = plan_points(&net, &cal);
        let ellipses = plots::uncertainty_ellipses(
            &format!("{}: reflectors in plan", c.meta.name),
            &stations,
            &targets,
        )?;
        Ok(StageOutput::default()
            .table("params", params_table(&cal, &outcome)?)
            .table("stations", stations_table(&net, &cal, &outcome)?)
            .table("targets", targets_table(&net, &cal, &outcome)?)
            .table("trials", trials_table(&outcome)?)
            .file("coverage.svg".into(), coverage.into_bytes())
            .file("ellipses.svg".into(), ellipses.into_bytes()))
    }
}

/// The determined coefficients' Monte Carlo intervals in units of their
/// linear standard uncertainty, beside the linear interval `±z·u`.
fn coverage_rows(cal: &Calibration, o: &Outcome, coverage: f64) -> Result<Vec<CoverageRow>> {
    let z = Normal::new(0.0, 1.0)
        .map_err(|e| anyhow!("{e}"))?
        .inverse_cdf(0.5 + coverage / 2.0);
    let est = &cal.estimate;
    let determined = est.determined();
    Ok(o.outputs
        .iter()
        .zip(&o.estimates)
        .filter_map(|(out, e)| match out {
            Output::Param(i) if determined[*i] => {
                let u = est.std[*i].filter(|u| *u > 0.0)?;
                Some(CoverageRow {
                    label: est.params.coefs()[*i].name(),
                    low_u: (e.low - e.nominal) / u,
                    high_u: (e.high - e.nominal) / u,
                    linear_u: z,
                })
            }
            _ => None,
        })
        .collect())
}

/// Stations and reflectors in plan, in metres, the reflectors with the
/// linear covariance of their x, y.
fn plan_points(net: &Network, cal: &Calibration) -> (Vec<PlanPoint>, Vec<PlanPoint>) {
    let stations = cal
        .poses
        .iter()
        .zip(&net.stations)
        .map(|(p, id)| PlanPoint {
            label: id.clone(),
            x_m: p.translation.x / 1000.0,
            y_m: p.translation.y / 1000.0,
            cov_xy_mm2: None,
        })
        .collect();
    let targets = cal
        .points
        .iter()
        .map(|(t, x)| PlanPoint {
            label: net.targets[*t].clone(),
            x_m: x.x / 1000.0,
            y_m: x.y / 1000.0,
            cov_xy_mm2: cal
                .point_cov
                .get(t)
                .map(|c| [c[(0, 0)], c[(0, 1)], c[(1, 1)]]),
        })
        .collect();
    (stations, targets)
}

fn ratio(a: f64, b: Option<f64>) -> Option<f64> {
    b.filter(|b| *b > 0.0).map(|b| a / b)
}

fn params_table(cal: &Calibration, o: &Outcome) -> Result<DataFrame> {
    let est = &cal.estimate;
    let coefs = est.params.coefs();
    let determined = est.determined();
    let rows: Vec<(usize, &Estimate)> = o
        .outputs
        .iter()
        .zip(&o.estimates)
        .filter_map(|(out, e)| match out {
            Output::Param(i) => Some((*i, e)),
            _ => None,
        })
        .collect();
    let linear: Vec<Option<f64>> = rows.iter().map(|(i, _)| est.std[*i]).collect();
    TableBuilder::new()
        .str(
            "coef",
            &rows
                .iter()
                .map(|(i, _)| coefs[*i].name())
                .collect::<Vec<_>>(),
        )
        .str(
            "unit",
            &rows
                .iter()
                .map(|(i, _)| coefs[*i].unit())
                .collect::<Vec<_>>(),
        )
        .f64("value", rows.iter().map(|r| r.1.nominal).collect())
        .f64("mean", rows.iter().map(|r| r.1.mean).collect())
        .f64("u_mc", rows.iter().map(|r| r.1.u).collect())
        .f64("low", rows.iter().map(|r| r.1.low).collect())
        .f64("high", rows.iter().map(|r| r.1.high).collect())
        .opt_f64("u_linear", linear.clone())
        .opt_f64(
            "u_ratio",
            rows.iter()
                .zip(&linear)
                .map(|(r, l)| ratio(r.1.u, *l).filter(|_| determined[r.0]))
                .collect(),
        )
        .bool(
            "determined",
            rows.iter().map(|(i, _)| determined[*i]).collect(),
        )
        .build()
}

/// Per station or target with Monte Carlo coordinates: its three
/// estimates in x, y, z order.
fn by_place(o: &Outcome, station: bool) -> BTreeMap<usize, [Estimate; 3]> {
    let mut m: BTreeMap<usize, [Estimate; 3]> = BTreeMap::new();
    for (out, e) in o.outputs.iter().zip(&o.estimates) {
        let (i, k) = match (out, station) {
            (Output::Station(s, k), true) => (*s, *k),
            (Output::Target(t, k), false) => (*t, *k),
            _ => continue,
        };
        m.entry(i).or_insert([*e; 3])[k] = *e;
    }
    m
}

/// The rows of `stations` or `targets`: id, position, the three Monte
/// Carlo uncertainties and their root mean square beside the linear one.
fn place_table(
    id_column: &str,
    ids: &[String],
    places: &BTreeMap<usize, [Estimate; 3]>,
    linear: impl Fn(usize) -> Option<f64>,
    extra: Vec<(&str, Vec<Option<f64>>)>,
) -> Result<DataFrame> {
    let rows: Vec<(&usize, &[Estimate; 3])> = places.iter().collect();
    let u_rms: Vec<f64> = rows
        .iter()
        .map(|(_, e)| (e.iter().map(|x| x.u * x.u).sum::<f64>() / 3.0).sqrt())
        .collect();
    let lin: Vec<Option<f64>> = rows.iter().map(|(i, _)| linear(**i)).collect();
    let mut b = TableBuilder::new().str(
        id_column,
        &rows
            .iter()
            .map(|(i, _)| ids[**i].as_str())
            .collect::<Vec<_>>(),
    );
    for (k, col) in XYZ.iter().enumerate() {
        b = b.f64(col, rows.iter().map(|(_, e)| e[k].nominal).collect());
    }
    for (k, col) in U_XYZ.iter().enumerate() {
        b = b.f64(col, rows.iter().map(|(_, e)| e[k].u).collect());
    }
    b = b
        .f64("u_mm", u_rms.clone())
        .opt_f64("u_linear_mm", lin.clone())
        .opt_f64(
            "u_ratio",
            u_rms.iter().zip(&lin).map(|(u, l)| ratio(*u, *l)).collect(),
        );
    for (col, values) in extra {
        b = b.opt_f64(col, values);
    }
    b.build()
}

/// Besides the positions, each station's rotation: the root mean square
/// of its three components' Monte Carlo uncertainty beside the linear one.
fn stations_table(net: &Network, cal: &Calibration, o: &Outcome) -> Result<DataFrame> {
    let places = by_place(o, true);
    let mut rotation: BTreeMap<usize, f64> = BTreeMap::new();
    for (out, e) in o.outputs.iter().zip(&o.estimates) {
        if let Output::StationRotation(s, _) = out {
            *rotation.entry(*s).or_default() += e.u * e.u / 3.0;
        }
    }
    let mc: Vec<Option<f64>> = places
        .keys()
        .map(|s| rotation.get(s).map(|v| v.sqrt() * 1e6))
        .collect();
    let lin: Vec<Option<f64>> = places
        .keys()
        .map(|&s| cal.pose_std[s].map(|p| p.1 * 1e6))
        .collect();
    let ratios = mc
        .iter()
        .zip(&lin)
        .map(|(u, l)| u.and_then(|u| ratio(u, *l)))
        .collect();
    place_table(
        "station",
        &net.stations,
        &places,
        |s| cal.pose_std[s].map(|p| p.0),
        vec![
            ("u_rotation_urad", mc),
            ("u_rotation_linear_urad", lin),
            ("u_rotation_ratio", ratios),
        ],
    )
}

fn targets_table(net: &Network, cal: &Calibration, o: &Outcome) -> Result<DataFrame> {
    place_table(
        "target",
        &net.targets,
        &by_place(o, false),
        |t| cal.point_std.get(&t).copied(),
        Vec::new(),
    )
}

fn trials_table(o: &Outcome) -> Result<DataFrame> {
    TableBuilder::new()
        .i64("block", (1..=o.blocks.len() as i64).collect())
        .i64("trials", o.blocks.iter().map(|b| b.trials as i64).collect())
        .opt_f64(
            "worst_ratio",
            o.blocks
                .iter()
                .map(|b| b.worst_ratio.is_finite().then_some(b.worst_ratio))
                .collect(),
        )
        .bool(
            "stable",
            o.blocks
                .iter()
                .enumerate()
                .map(|(i, _)| o.stable && i + 1 == o.blocks.len())
                .collect(),
        )
        .build()
}
