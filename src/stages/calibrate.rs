//! `calibrate`: the error parameters from a campaign with unknown station
//! poses (Sections 5.2, 7, 8).
//!
//! ```toml
//! [stages.calibration]
//! kind = "calibrate"
//! inputs = { campaign = "corner" }    # a whole campaign (import or simulate); start = "…" optional
//! objective = "eq15"                  # "eq13", "eq14", "eq15" or "bundle"
//! norm = "l1"                         # "l1" (the paper's |…|) or "l2"; the bundle is "l2"
//! model = "api-tracker3"              # the tracker model to fit; the campaign's by default
//! fixed = ["ez3"]                     # held at their start value (parameters of `model`)
//! shapes = { dz3 = "poly:1" }         # the model to fit; constants by default
//! reject_blunders = false             # bundle only: iterated data snooping (Baarda's w-test)
//! blunder_alpha = 0.01                # its family-wise level
//! std = "auto"                        # bundle only: "auto", "stated-noise",
//!                                     # "variance-components", "scaled-stated-noise"
//! ```
//!
//! The bundle's `std` (see [`calibrate::bundle`]): `auto` keeps the
//! stated noise, unscaled, while the χ² test accepts it (p ≥ 0.01) and
//! otherwise re-weights the angle and range groups by their Helmert
//! variance components; the other values force one or the other, or the
//! former global `max(χ²/dof, 1)` scaling.
//!
//! Outputs: `params`, `singular_values`, `combinations` (as `identify`:
//! what the campaign determines once poses are free), `fit` (one row:
//! `objective`, `norm`, `n_readings`, `n_residuals`, `n_unknowns`, `rank`,
//! `iterations`, `stop`, `std_from` (`stated-noise`, `variance-components`,
//! `scaled-stated-noise`, `sandwich`, `sandwich-l1`: see
//! [`calibrate::FitSummary::std_from`]), `sigma_angle_factor`,
//! `sigma_angle_factor_u`, `sigma_range_factor`, `sigma_range_factor_u`
//! (bundle: the Helmert variance components as estimated σ / stated σ,
//! dimensionless, with their standard uncertainty, when they were
//! estimated — `std_from = "variance-components"`; null otherwise),
//! `rms_before`, `rms_after`, `mean_abs_before`, `mean_abs_after` — µm for
//! Eq. 13–15, units of the stated σ for the bundle, as `chi2`, `dof` and
//! `chi2_p` (the test of the stated noise) —
//! `gauge_scale_ppm`, `noise_stated`), `stations`
//! (`station`, `x_mm`, `y_mm`, `z_mm`, `roll_urad`, `pitch_urad`, `yaw_deg`,
//! `std_position_mm`, `std_rotation_urad`), `targets` (`target`, `x_mm`,
//! `y_mm`, `z_mm`, `std_mm`) and `residuals` (per reading: `station`,
//! `target`, `face`, `az_urad`, `el_urad`, `d_um`, and the same over σ:
//! `az_sigma`, `el_sigma`, `d_sigma`), and `rejected` (the readings data
//! snooping removed, in order: `station`, `target`, `face`, `line`,
//! `coordinate`, `w`, `critical_w`, `redundancy`, `size`, `unit`; empty
//! unless `reject_blunders`).

use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput, fitting};
use crate::calibrate::snooping::{self, Rejected};
use crate::calibrate::{self, BundleStd, Calibration, Network, Norm, Objective, Settings};
use crate::campaign::Campaign;
use crate::error_model::{ParamId, Shape};
use crate::table::TableBuilder;
use crate::trackers::TrackerModel;
use anyhow::Result;
use polars::prelude::DataFrame;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct CalibrateStage {
    /// `eq13`, `eq14`, `eq15` (the paper's criteria) or `bundle` (stations and
    /// reflectors adjusted with the parameters).
    pub objective: Objective,
    /// `l1` (the paper's |…|) or `l2`; the bundle is `l2`.
    #[serde(default)]
    pub norm: Norm,
    /// The tracker model to fit; the campaign's by default.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<TrackerModel>,
    /// Parameters of `model` held at their start value.
    #[serde(default)]
    pub fixed: Vec<ParamId>,
    /// Per parameter, the shape to fit: `fourier:k` or `poly:k`; constants by
    /// default.
    #[serde(default)]
    pub shapes: BTreeMap<ParamId, Shape>,
    /// Relative singular-value threshold below which a direction counts as not
    /// determined.
    #[serde(default = "fitting::default_rank_tol")]
    pub rank_tol: f64,
    /// Iteration limit of the adjustment.
    #[serde(default = "fitting::default_max_iters")]
    pub max_iters: u64,
    /// Bundle only: iterated data snooping (Baarda's w-test) removes blunders
    /// before the final fit.
    #[serde(default)]
    pub reject_blunders: bool,
    /// The data snooping's family-wise significance level.
    #[serde(default = "default_blunder_alpha")]
    pub blunder_alpha: f64,
    /// Bundle only: where `std` comes from: `auto` (the stated noise while the
    /// χ² test accepts it, else variance components), `stated-noise`,
    /// `variance-components` or `scaled-stated-noise`.
    #[serde(default)]
    pub std: BundleStd,
}

fn default_blunder_alpha() -> f64 {
    0.01
}

impl CalibrateStage {
    /// Calibrates a campaign; also what `diagnose` builds on.
    pub fn calibrate(
        &self,
        c: &Campaign,
        inputs: Option<&StageInputs>,
    ) -> Result<(Network, Calibration, Vec<Rejected>)> {
        let net = Network::from_campaign(c)?;
        let tracker = fitting::tracker(self.model, c);
        let model = fitting::run_model(tracker, &self.shapes, &self.fixed)?;
        let start = fitting::start(&model, inputs)?;
        let free = fitting::free(&start, &self.fixed);
        let settings = Settings {
            objective: self.objective,
            norm: self.norm,
            rank_tol: self.rank_tol,
            max_iters: self.max_iters,
            std: self.std,
        };
        if self.reject_blunders {
            snooping::calibrate_rejecting(&net, &start, &free, &settings, self.blunder_alpha)
        } else {
            let cal = calibrate::calibrate(&net, &start, &free, &settings)?;
            Ok((net, cal, Vec::new()))
        }
    }
}

impl StageKind for CalibrateStage {
    const KIND: &'static str = "calibrate";
    const SUMMARY: &'static str = "error parameters from a campaign with unknown poses: Eq. 13-15 (L1 or L2) or a bundle adjustment";
    const INPUTS: &'static [Slot] = &[fitting::CAMPAIGN, fitting::START];
    const OUTPUTS: &'static [&'static str] = &[
        "params",
        "singular_values",
        "combinations",
        "fit",
        "stations",
        "targets",
        "residuals",
        "rejected",
    ];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "fit" => Some(&[
                "objective",
                "norm",
                "n_readings",
                "n_residuals",
                "n_unknowns",
                "rank",
                "iterations",
                "stop",
                "std_from",
                "sigma_angle_factor",
                "sigma_angle_factor_u",
                "sigma_range_factor",
                "sigma_range_factor_u",
                "rms_before",
                "rms_after",
                "mean_abs_before",
                "mean_abs_after",
                "chi2",
                "dof",
                "chi2_p",
                "gauge_scale_ppm",
                "noise_stated",
            ]),
            "residuals" => Some(&[
                "station", "target", "face", "az_urad", "el_urad", "d_um", "az_sigma", "el_sigma",
                "d_sigma",
            ]),
            "stations" => Some(&[
                "station",
                "x_mm",
                "y_mm",
                "z_mm",
                "roll_urad",
                "pitch_urad",
                "yaw_deg",
                "std_position_mm",
                "std_rotation_urad",
            ]),
            "targets" => Some(&["target", "x_mm", "y_mm", "z_mm", "std_mm"]),
            "rejected" => Some(&[
                "station",
                "target",
                "face",
                "line",
                "coordinate",
                "w",
                "critical_w",
                "redundancy",
                "size",
                "unit",
            ]),
            _ => fitting::columns(table),
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
        if self.objective == Objective::Bundle && self.norm == Norm::L1 {
            out.push(Invalid::new(
                "norm",
                "the bundle adjustment is a least-squares fit of the readings: use norm = \"l2\"",
            ));
        }
        if self.std != BundleStd::Auto && self.objective != Objective::Bundle {
            out.push(Invalid::new(
                "std",
                "`std` chooses the bundle adjustment's covariance; Eq. 13-15 take the sandwich of the stated noise: use objective = \"bundle\" or drop `std`",
            ));
        }
        if self.reject_blunders && self.objective != Objective::Bundle {
            out.push(Invalid::new(
                "reject_blunders",
                "blunders are found by the w-test of each reading, which needs the readings' own residuals: use objective = \"bundle\"",
            ));
        }
        if !(self.blunder_alpha > 0.0 && self.blunder_alpha < 0.5) {
            out.push(Invalid::new(
                "blunder_alpha",
                format!(
                    "`blunder_alpha` must lie in (0, 0.5), got {}",
                    self.blunder_alpha
                ),
            ));
        }
        out
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let c = Campaign::from_inputs(inputs, "campaign")?;
        let (net, cal, rejected) = self.calibrate(&c, Some(inputs))?;
        Ok(tables(&net, &cal)?.table("rejected", rejected_table(&c, &rejected)?))
    }
}

/// The readings data snooping rejected, with their tests.
fn rejected_table(c: &Campaign, rejected: &[Rejected]) -> Result<DataFrame> {
    let readings: Vec<_> = rejected.iter().map(|r| &c.readings[r.test.obs]).collect();
    // The stated σ come from the campaign's network, built again only when
    // something was rejected (7 ms at 24 000 readings, issue 34).
    let (size, unit): (Vec<f64>, Vec<&str>) = if rejected.is_empty() {
        (Vec::new(), Vec::new())
    } else {
        let net = Network::from_campaign(c)?;
        rejected
            .iter()
            .map(|r| {
                let sigma = net.obs[r.test.obs].sigma[r.test.coordinate];
                match r.test.coordinate {
                    2 => (r.test.size_sigma * sigma * 1e3, "µm"),
                    _ => (r.test.size_sigma * sigma * 1e6, "µrad"),
                }
            })
            .unzip()
    };
    TableBuilder::new()
        .str(
            "station",
            &readings
                .iter()
                .map(|r| r.station.as_str())
                .collect::<Vec<_>>(),
        )
        .str(
            "target",
            &readings
                .iter()
                .map(|r| r.target.as_str())
                .collect::<Vec<_>>(),
        )
        .i64("face", readings.iter().map(|r| r.face.number()).collect())
        .opt_i64(
            "line",
            readings.iter().map(|r| r.line.map(|l| l as i64)).collect(),
        )
        .str(
            "coordinate",
            &rejected
                .iter()
                .map(|r| snooping::COORDINATES[r.test.coordinate])
                .collect::<Vec<_>>(),
        )
        .f64("w", rejected.iter().map(|r| r.test.w).collect())
        .f64(
            "critical_w",
            rejected.iter().map(|r| r.critical_w).collect(),
        )
        .f64(
            "redundancy",
            rejected.iter().map(|r| r.test.redundancy).collect(),
        )
        .f64("size", size)
        .str("unit", &unit)
        .build()
}

/// The output tables of a calibration.
pub fn tables(net: &Network, cal: &Calibration) -> Result<StageOutput> {
    // The residuals' table (a row per reading) built beside the others.
    let (residuals, rest) = rayon::join(
        || residuals_table(net, cal),
        || -> Result<_> {
            Ok((
                fitting::tables(&cal.estimate)?,
                fit_table(net, cal)?,
                stations_table(net, cal)?,
                targets_table(net, cal)?,
            ))
        },
    );
    let ([params, singular_values, combinations], fit, stations, targets) = rest?;
    Ok(StageOutput::default()
        .table("params", params)
        .table("singular_values", singular_values)
        .table("combinations", combinations)
        .table("fit", fit)
        .table("stations", stations)
        .table("targets", targets)
        .table("residuals", residuals?))
}

fn fit_table(net: &Network, cal: &Calibration) -> Result<DataFrame> {
    let f = &cal.fit;
    TableBuilder::new()
        .str("objective", &[f.objective.name()])
        .str("norm", &[f.norm.name()])
        .i64("n_readings", vec![f.n_readings as i64])
        .i64("n_residuals", vec![f.n_residuals as i64])
        .i64("n_unknowns", vec![f.n_unknowns as i64])
        .i64("rank", vec![f.rank as i64])
        .i64("iterations", vec![f.iterations as i64])
        .str("stop", &[f.stop])
        .str("std_from", &[f.std_from])
        .opt_f64(
            "sigma_angle_factor",
            vec![f.sigma_angle_factor.map(|c| c.factor)],
        )
        .opt_f64(
            "sigma_angle_factor_u",
            vec![f.sigma_angle_factor.map(|c| c.u)],
        )
        .opt_f64(
            "sigma_range_factor",
            vec![f.sigma_range_factor.map(|c| c.factor)],
        )
        .opt_f64(
            "sigma_range_factor_u",
            vec![f.sigma_range_factor.map(|c| c.u)],
        )
        .f64("rms_before", vec![f.rms_before])
        .f64("rms_after", vec![f.rms_after])
        .f64("mean_abs_before", vec![f.mean_abs_before])
        .f64("mean_abs_after", vec![f.mean_abs_after])
        .opt_f64("chi2", vec![f.chi2])
        .opt_f64("dof", vec![f.dof.map(|d| d as f64)])
        .opt_f64("chi2_p", vec![f.chi2_p])
        .opt_f64("gauge_scale_ppm", vec![f.gauge_scale_ppm])
        .bool("noise_stated", vec![net.noise_stated])
        .build()
}

fn stations_table(net: &Network, cal: &Calibration) -> Result<DataFrame> {
    let e: Vec<(f64, f64, f64)> = cal
        .poses
        .iter()
        .map(|p| p.rotation.euler_angles())
        .collect();
    TableBuilder::new()
        .str("station", &net.stations)
        .f64("x_mm", cal.poses.iter().map(|p| p.translation.x).collect())
        .f64("y_mm", cal.poses.iter().map(|p| p.translation.y).collect())
        .f64("z_mm", cal.poses.iter().map(|p| p.translation.z).collect())
        .f64("roll_urad", e.iter().map(|a| a.0 * 1e6).collect())
        .f64("pitch_urad", e.iter().map(|a| a.1 * 1e6).collect())
        .f64("yaw_deg", e.iter().map(|a| a.2.to_degrees()).collect())
        .opt_f64(
            "std_position_mm",
            cal.pose_std.iter().map(|s| s.map(|s| s.0)).collect(),
        )
        .opt_f64(
            "std_rotation_urad",
            cal.pose_std.iter().map(|s| s.map(|s| s.1 * 1e6)).collect(),
        )
        .build()
}

fn targets_table(net: &Network, cal: &Calibration) -> Result<DataFrame> {
    let ids: Vec<&str> = cal
        .points
        .keys()
        .map(|&t| net.targets[t].as_str())
        .collect();
    let pts: Vec<_> = cal.points.values().collect();
    TableBuilder::new()
        .str("target", &ids)
        .f64("x_mm", pts.iter().map(|p| p.x).collect())
        .f64("y_mm", pts.iter().map(|p| p.y).collect())
        .f64("z_mm", pts.iter().map(|p| p.z).collect())
        .opt_f64(
            "std_mm",
            cal.points
                .keys()
                .map(|t| cal.point_std.get(t).copied())
                .collect(),
        )
        .build()
}

fn residuals_table(net: &Network, cal: &Calibration) -> Result<DataFrame> {
    let r = &cal.residuals;
    // The names borrowed, not copied: two strings a reading otherwise.
    let stations: Vec<&str> = r
        .iter()
        .map(|x| net.stations[net.obs[x.obs].station].as_str())
        .collect();
    let targets: Vec<&str> = r
        .iter()
        .map(|x| net.targets[net.obs[x.obs].target].as_str())
        .collect();
    TableBuilder::new()
        .str("station", &stations)
        .str("target", &targets)
        .i64(
            "face",
            r.iter().map(|x| net.obs[x.obs].face.number()).collect(),
        )
        .f64("az_urad", r.iter().map(|x| x.az_urad).collect())
        .f64("el_urad", r.iter().map(|x| x.el_urad).collect())
        .f64("d_um", r.iter().map(|x| x.d_um).collect())
        .f64("az_sigma", r.iter().map(|x| x.normalized.x).collect())
        .f64("el_sigma", r.iter().map(|x| x.normalized.y).collect())
        .f64("d_sigma", r.iter().map(|x| x.normalized.z).collect())
        .build()
}
