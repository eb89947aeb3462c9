//! `layout_design`: how well a campaign layout — stations, reflectors,
//! faces — determines the error parameters once station poses and
//! reflector positions are unknown, before anyone measures it. This answers
//! the paper's future-work question (Section 12) on the number and
//! distribution of reflectors with numbers instead of a rule of thumb.
//!
//! ```toml
//! [stages.design]
//! kind = "layout_design"
//! inputs = { campaign = "corner" }   # optional: also a real or simulated campaign, as it is
//! layouts = [
//!   { name = "paper", layout = { kind = "corner" }, faces = "front" },
//!   { name = "2 stations", layout = { kind = "corner", stations = 2 } },
//!   { name = "no gauge", layout = { kind = "corner" }, gauge = false },
//! ]
//! noise = { sigma_angle_urad = 1.0, sigma_range_um = 2.0 }   # the weights (default)
//! model = "api-tracker3"             # the tracker model analysed: the input campaign's,
//!                                    # else api-tracker3, by default
//! fixed = []                         # parameters held fixed (none by default)
//! seed = 0                           # station yaw and levelling of the simulated layouts
//! ```
//!
//! Each layout is the `simulate_campaign` layout spec (`crate::layout::Spec`
//! with `faces`, `aim` and `max_angle_deg`, and `gauge = false` to leave the
//! gauge out), simulated noise-free with a perfect tracker. The analysis is [`crate::calibrate::bundle::analyse`]:
//! the Jacobian of the bundle adjustment's weighted residuals (readings in
//! units of σ, gauge lengths) with respect to the model's error parameters
//! (the 18 DH parameters, or the mirror tracker's 10 misalignments; in µm
//! and µrad), with everything the free station poses and reflector
//! positions can absorb projected out. Its singular values σ₁ ≥ … say how
//! many σ of residual a unit (1 µm or 1 µrad) change along each direction
//! produces; 1/σ_min is the standard uncertainty of the worst-determined
//! combination for the stated noise. Every row, the input campaign's too,
//! is weighted by the same `noise`, so that the rows compare.
//!
//! **Scale.** Singular values grow with the square root of the number of
//! readings: the same layout measured twice has √2 larger σ's (exactly so
//! for the readings' rows; the gauge's few, heavily weighted rows do not
//! repeat). σ_min therefore rewards more readings as such; the
//! observability index O1 = (σ₁⋯σ_L)^(1/L)/√m (m = 3 × readings, the
//! reading equations) divides that out and rewards geometry. The table
//! reports both, and O2 … O5 ([`crate::identifiability::Observability`]).
//!
//! Outputs: `layouts` (one row per layout: `name`, `n_stations`,
//! `n_reflectors`, `n_readings`, `rank`, `sigma_min`, `condition_number`,
//! `o1` … `o5`, `undetermined`: the combinations the layout cannot
//! determine, "; "-joined sentences), `singular_values` (`layout`,
//! `index`, `sigma`) and the file `layout-design.svg` (σ_min and O1 per
//! layout).

use super::measure::Faces;
use super::simulate_campaign::SimulateCampaignStage;
use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput};
use crate::calibrate::{Network, bundle};
use crate::campaign::{self, Aim, Campaign};
use crate::effects::DEFAULT_MAX_ANGLE_DEG;
use crate::error_model::{ErrorModel, ErrorParams, ParamId};
use crate::identifiability::{self, Analysis, Combination};
use crate::layout::Spec;
use crate::noise::Noise;
use crate::plots;
use crate::table::TableBuilder;
use crate::trackers::TrackerModel;
use anyhow::{Context as _, Result, bail};
use polars::prelude::DataFrame;
use serde::{Deserialize, Serialize};

/// One layout to evaluate, as a `simulate_campaign` stage would take it.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LayoutCase {
    pub name: String,
    pub layout: Spec,
    #[serde(default)]
    pub faces: Faces,
    #[serde(default = "Aim::simulated_default")]
    pub aim: Aim,
    #[serde(default = "default_max_angle")]
    pub max_angle_deg: f64,
    /// Whether the campaign has the layout's gauge of calibrated lengths
    /// (Eq. 15); `false`: no scale reference at all.
    #[serde(default = "yes")]
    pub gauge: bool,
}

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct LayoutDesignStage {
    /// The layouts compared: `{ name, layout = { … }, faces, aim,
    /// max_angle_deg, gauge }` each.
    #[serde(default)]
    pub layouts: Vec<LayoutCase>,
    /// The tracker model analysed: the input campaign's, else `api-tracker3`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<TrackerModel>,
    /// The noise that weights every row, 1 σ.
    #[serde(default = "default_noise")]
    pub noise: Noise,
    /// Parameters held fixed.
    #[serde(default)]
    pub fixed: Vec<ParamId>,
    /// Relative singular-value threshold below which a direction counts as not
    /// determined.
    #[serde(default = "default_rank_tol")]
    pub rank_tol: f64,
    /// Seed of the simulated layouts' station yaw and levelling.
    #[serde(default)]
    pub seed: u64,
}

fn yes() -> bool {
    true
}
fn default_max_angle() -> f64 {
    DEFAULT_MAX_ANGLE_DEG
}
/// FIELD.md's typical indoor reading noise, as `calibrate` assumes it.
fn default_noise() -> Noise {
    crate::calibrate::DEFAULT_NOISE
}
fn default_rank_tol() -> f64 {
    identifiability::DEFAULT_REL_TOL
}

/// One evaluated layout.
struct Row {
    name: String,
    n_stations: usize,
    n_reflectors: usize,
    n_readings: usize,
    analysis: Analysis,
    combinations: Vec<Combination>,
}

impl LayoutCase {
    fn campaign(&self, seed: u64) -> Result<Campaign> {
        let sim = SimulateCampaignStage::noise_free(
            &self.name,
            &self.layout,
            self.faces,
            self.aim,
            self.max_angle_deg,
            seed,
        )
        .simulate(None)?;
        let mut c = sim.campaign;
        if !self.gauge {
            c.gauge.clear();
        }
        Ok(c)
    }
}

impl LayoutDesignStage {
    /// The identifiability of one campaign's error parameters, its readings
    /// weighted by `noise`.
    fn evaluate(&self, tracker: TrackerModel, name: &str, mut c: Campaign) -> Result<Row> {
        c.meta.tracker.sigma_angle_urad = Some(self.noise.sigma_angle_urad);
        c.meta.tracker.sigma_range_um = Some(self.noise.sigma_range_um);
        c.meta.tracker.sigma_range_ppm = Some(self.noise.sigma_range_ppm);
        let net = Network::from_campaign(&c)?;
        let start = ErrorParams::zero(&ErrorModel::of(tracker));
        let free: Vec<bool> = start
            .coefs()
            .iter()
            .map(|k| !self.fixed.contains(&k.param))
            .collect();
        let (analysis, combinations) = bundle::analyse(&net, &start, &free, self.rank_tol)?;
        let mut seen: Vec<usize> = net.obs.iter().map(|o| o.target).collect();
        seen.sort_unstable();
        seen.dedup();
        Ok(Row {
            name: name.to_string(),
            n_stations: net.stations.len(),
            n_reflectors: seen.len(),
            n_readings: net.obs.len(),
            analysis,
            combinations,
        })
    }
}

impl StageKind for LayoutDesignStage {
    const KIND: &'static str = "layout_design";
    const SUMMARY: &'static str = "identifiability of the error parameters for campaign layouts with free station poses: singular values, O1-O5, what each layout cannot determine";
    const INPUTS: &'static [Slot] = &[Slot::group(
        "campaign",
        false,
        "a campaign to evaluate as it is, beside the layouts (`import_campaign` or `simulate_campaign`)",
        campaign::TABLES,
    )];
    const OUTPUTS: &'static [&'static str] = &["layouts", "singular_values"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "layouts" => Some(&[
                "name",
                "n_stations",
                "n_reflectors",
                "n_readings",
                "rank",
                "sigma_min",
                "condition_number",
                "o1",
                "o2",
                "o3",
                "o4",
                "o5",
                "undetermined",
            ]),
            "singular_values" => Some(&["layout", "index", "sigma"]),
            _ => None,
        }
    }

    fn validate(&self) -> Vec<Invalid> {
        let mut out = Vec::new();
        let named = self.fixed.first().map(|p| p.tracker());
        let tracker = self.model.or(named).unwrap_or_default();
        if let Err(e) = super::fitting::model(tracker, &Default::default(), &self.fixed) {
            out.push(e);
        }
        for (i, l) in self.layouts.iter().enumerate() {
            // Fields by their dotted path (how the pipeline file locates
            // them), messages as a reader writes it.
            let (field, at) = (format!("layouts.{i}"), format!("layouts[{i}]"));
            if l.name.trim().is_empty() {
                out.push(Invalid::new(
                    format!("{field}.name"),
                    format!("`{at}.name` must not be empty"),
                ));
            }
            if self.layouts[..i].iter().any(|o| o.name == l.name) {
                out.push(Invalid::new(
                    format!("{field}.name"),
                    format!(
                        "`{at}.name`: another layout is already called \"{}\"",
                        l.name
                    ),
                ));
            }
            for (f, m) in l.layout.check() {
                out.push(Invalid::new(
                    format!("{field}.layout.{f}"),
                    format!("`{at}.layout`: {m}"),
                ));
            }
            if !(l.max_angle_deg > 0.0 && l.max_angle_deg <= 90.0) {
                out.push(Invalid::new(
                    format!("{field}.max_angle_deg"),
                    format!(
                        "`{at}.max_angle_deg` must lie in (0, 90], got {}",
                        l.max_angle_deg
                    ),
                ));
            }
        }
        out.extend(Invalid::noise(&self.noise));
        if self.noise.sigma_angle_urad <= 0.0 || self.noise.sigma_range_um <= 0.0 {
            out.push(Invalid::new(
                "noise",
                "`noise` weights the readings: `sigma_angle_urad` and `sigma_range_um` must be > 0",
            ));
        }
        if !(self.rank_tol > 0.0 && self.rank_tol < 1.0) {
            out.push(Invalid::new(
                "rank_tol",
                format!("`rank_tol` must lie in (0, 1), got {}", self.rank_tol),
            ));
        }
        out
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let mut rows = Vec::new();
        let campaign = match inputs.optional("campaign.readings") {
            Some(_) => Some(Campaign::from_inputs(inputs, "campaign")?),
            None => None,
        };
        let tracker = match (&campaign, self.model) {
            (_, Some(t)) => t,
            (Some(c), None) => c.tracker_model(),
            (None, None) => TrackerModel::default(),
        };
        super::fitting::run_model(tracker, &Default::default(), &self.fixed)?;
        if let Some(c) = campaign {
            let name = c.meta.name.clone();
            rows.push(
                self.evaluate(tracker, &name, std::sync::Arc::unwrap_or_clone(c))
                    .context("the input campaign")?,
            );
        }
        for l in &self.layouts {
            let c = l
                .campaign(self.seed)
                .with_context(|| format!("layout \"{}\"", l.name))?;
            rows.push(
                self.evaluate(tracker, &l.name, c)
                    .with_context(|| format!("layout \"{}\"", l.name))?,
            );
        }
        if rows.is_empty() {
            bail!("nothing to evaluate: give `layouts` or connect a `campaign` input");
        }
        let names: Vec<&str> = rows.iter().map(|r| r.name.as_str()).collect();
        let o: Vec<identifiability::Observability> = rows
            .iter()
            .map(|r| r.analysis.observability(3 * r.n_readings))
            .collect();
        let sigma_min: Vec<f64> = o.iter().map(|o| o.o3).collect();
        let o1: Vec<f64> = o.iter().map(|o| o.o1).collect();
        let svg = plots::layout_bars(
            &format!(
                "Layout design ({tracker}): identifiability of the error parameters with free station poses"
            ),
            &names,
            &[
                ("σ_min (σ of residual per µm or µrad)", &sigma_min),
                ("O1 = (σ₁⋯σ_L)^(1/L)/√m", &o1),
            ],
        )?;
        Ok(StageOutput::default()
            .table("layouts", layouts_table(&rows, &o)?)
            .table("singular_values", singular_values_table(&rows)?)
            .file("layout-design.svg".into(), svg.into_bytes()))
    }
}

fn layouts_table(rows: &[Row], o: &[identifiability::Observability]) -> Result<DataFrame> {
    let int = |f: &dyn Fn(&Row) -> usize| rows.iter().map(|r| f(r) as i64).collect::<Vec<_>>();
    TableBuilder::new()
        .str(
            "name",
            &rows.iter().map(|r| r.name.as_str()).collect::<Vec<_>>(),
        )
        .i64("n_stations", int(&|r| r.n_stations))
        .i64("n_reflectors", int(&|r| r.n_reflectors))
        .i64("n_readings", int(&|r| r.n_readings))
        .i64("rank", int(&|r| r.analysis.rank))
        .f64("sigma_min", o.iter().map(|o| o.o3).collect())
        .f64(
            "condition_number",
            rows.iter().map(|r| r.analysis.condition_number()).collect(),
        )
        .f64("o1", o.iter().map(|o| o.o1).collect())
        .f64("o2", o.iter().map(|o| o.o2).collect())
        .f64("o3", o.iter().map(|o| o.o3).collect())
        .f64("o4", o.iter().map(|o| o.o4).collect())
        .f64("o5", o.iter().map(|o| o.o5).collect())
        .str(
            "undetermined",
            &rows
                .iter()
                .map(|r| {
                    r.combinations
                        .iter()
                        .map(Combination::sentence)
                        .collect::<Vec<_>>()
                        .join("; ")
                })
                .collect::<Vec<_>>(),
        )
        .build()
}

fn singular_values_table(rows: &[Row]) -> Result<DataFrame> {
    let cells: Vec<(&str, usize, f64)> = rows
        .iter()
        .flat_map(|r| {
            r.analysis
                .singular_values
                .iter()
                .enumerate()
                .map(move |(i, &s)| (r.name.as_str(), i + 1, s))
        })
        .collect();
    TableBuilder::new()
        .str("layout", &cells.iter().map(|c| c.0).collect::<Vec<_>>())
        .i64("index", cells.iter().map(|c| c.1 as i64).collect())
        .f64("sigma", cells.iter().map(|c| c.2).collect())
        .build()
}
