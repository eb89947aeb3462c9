//! `evaluate_campaign`: the paper's criteria before and after applying error
//! parameters to a campaign — Eq. (16) and (17) per station and overall
//! (Tables 5, 6, 7), and against reference coordinates where the campaign
//! has them (Table 4, and Table 8 when the parameters come from another
//! campaign: the verification of Section 9).
//!
//! ```toml
//! [stages.evaluation]
//! kind = "evaluate_campaign"
//! inputs = { campaign = "corner", params = "calibration" }   # params: optional
//! ```
//!
//! Outputs (µm throughout; see [`crate::criteria`] for the definitions):
//! * `criteria` — `criterion` (`distances` = Eq. 16, `coordinates` =
//!   Eq. 17, `reference_distances`, `reference_coordinates`), `station`
//!   (an id or `all`), `statistic` (`average`, `maximum`), `before_um`,
//!   `after_um`, `improvement_pct`, `registration_converged` (Eq. 17:
//!   whether both registrations, before and after, reached 1e-10 mm —
//!   `false` marks numbers not to trust; empty for the other criteria);
//! * `table5`, `table6` — Eq. (16), Eq. (17) after calibration laid out as
//!   the paper's Tables 5 and 6: `statistic`, one column per station
//!   (`<id>_um`), `all_um`, `improvement_pct`;
//! * `table7` — Table 7 (and Table 4/8 for the reference criteria):
//!   `error` (`initial`, `residual`, `improvement`), `statistic`,
//!   `coordinates_um`, `distances_um`, `reference_coordinates_um`,
//!   `reference_distances_um` (empty without references);
//! * `terms` — every compared quantity: `criterion`, `station_a`,
//!   `station_b`, `target_a`, `target_b`, `before_um`, `after_um`.

use super::{Context, Slot, StageInputs, StageKind, StageOutput};
use crate::calibrate::Network;
use crate::campaign::{self, Campaign};
use crate::criteria::{self, Criterion, improvement_pct};
use crate::error_model::{ErrorModel, ErrorParams};
use crate::schema;
use crate::table::TableBuilder;
use anyhow::Result;
use polars::prelude::DataFrame;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Default, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct EvaluateCampaignStage {}

/// The four criteria names, in output order.
pub const CRITERIA: [&str; 4] = [
    "coordinates",
    "distances",
    "reference_coordinates",
    "reference_distances",
];

/// Each criterion before and after.
pub struct Evaluation {
    pub stations: Vec<String>,
    pub targets: Vec<String>,
    /// `(name, before, after)`; coordinates is `None` if unregistrable.
    pub criteria: Vec<(&'static str, Criterion, Criterion)>,
}

pub fn evaluate(net: &Network, params: &ErrorParams) -> Evaluation {
    let zero = ErrorParams::zero(&ErrorModel::constant());
    let mut criteria = Vec::new();
    if let (Some(b), Some(a)) = (
        criteria::coordinates(net, &zero),
        criteria::coordinates(net, params),
    ) {
        criteria.push((CRITERIA[0], b, a));
    }
    criteria.push((
        CRITERIA[1],
        criteria::distances(net, &zero),
        criteria::distances(net, params),
    ));
    let rb = criteria::reference_coordinates(net, &zero);
    if rb.overall.count > 0 {
        criteria.push((
            CRITERIA[2],
            rb,
            criteria::reference_coordinates(net, params),
        ));
        criteria.push((
            CRITERIA[3],
            criteria::reference_distances(net, &zero),
            criteria::reference_distances(net, params),
        ));
    }
    Evaluation {
        stations: net.stations.clone(),
        targets: net.targets.clone(),
        criteria,
    }
}

impl StageKind for EvaluateCampaignStage {
    const KIND: &'static str = "evaluate_campaign";
    const SUMMARY: &'static str = "Eq. 16 and 17 per station before and after, and against reference coordinates (Tables 4-8)";
    const INPUTS: &'static [Slot] = &[
        Slot::group(
            "campaign",
            true,
            "the campaign to evaluate",
            campaign::TABLES,
        ),
        Slot::table(
            "params",
            false,
            "error parameters to apply (none: the uncorrected readings only)",
        ),
    ];
    const OUTPUTS: &'static [&'static str] = &["criteria", "table5", "table6", "table7", "terms"];

    /// `table5` and `table6` have a column per station: not fixed.
    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "criteria" => Some(&[
                "criterion",
                "station",
                "statistic",
                "before_um",
                "after_um",
                "improvement_pct",
                "registration_converged",
            ]),
            "table7" => Some(&[
                "error",
                "statistic",
                "coordinates_um",
                "distances_um",
                "reference_coordinates_um",
                "reference_distances_um",
            ]),
            // table5 and table6 have one column per station: the data's.
            "terms" => Some(&[
                "criterion",
                "station_a",
                "station_b",
                "target_a",
                "target_b",
                "before_um",
                "after_um",
            ]),
            _ => None,
        }
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let c = Campaign::from_inputs(inputs, "campaign")?;
        let net = Network::from_campaign(&c)?;
        let params = match inputs.optional("params") {
            Some(t) => schema::params_from(&t)?,
            None => ErrorParams::zero(&ErrorModel::constant()),
        };
        let e = evaluate(&net, &params);
        Ok(StageOutput::default()
            .table("criteria", criteria_table(&e)?)
            .table("table5", wide(&e, "distances")?)
            .table("table6", wide(&e, "coordinates")?)
            .table("table7", summary(&e)?)
            .table("terms", terms_table(&e)?))
    }
}

fn criteria_table(e: &Evaluation) -> Result<DataFrame> {
    let mut rows: Vec<(&str, String, &str, f64, f64)> = Vec::new();
    let mut converged: Vec<Option<bool>> = Vec::new();
    for (name, b, a) in &e.criteria {
        let both = b
            .registration_converged
            .zip(a.registration_converged)
            .map(|(b, a)| b && a);
        let mut add = |station: String, sb: &criteria::Stat, sa: &criteria::Stat| {
            rows.push((name, station.clone(), "average", sb.mean_um, sa.mean_um));
            rows.push((name, station, "maximum", sb.max_um, sa.max_um));
            converged.extend([both, both]);
        };
        for (i, s) in e.stations.iter().enumerate() {
            add(s.clone(), &b.per_station[i], &a.per_station[i]);
        }
        add("all".into(), &b.overall, &a.overall);
    }
    TableBuilder::new()
        .str("criterion", &rows.iter().map(|r| r.0).collect::<Vec<_>>())
        .str(
            "station",
            &rows.iter().map(|r| r.1.clone()).collect::<Vec<_>>(),
        )
        .str("statistic", &rows.iter().map(|r| r.2).collect::<Vec<_>>())
        .f64("before_um", rows.iter().map(|r| r.3).collect())
        .f64("after_um", rows.iter().map(|r| r.4).collect())
        .f64(
            "improvement_pct",
            rows.iter().map(|r| improvement_pct(r.3, r.4)).collect(),
        )
        .opt_bool("registration_converged", converged)
        .build()
}

/// Tables 5 and 6: after calibration, per station and overall.
fn wide(e: &Evaluation, name: &str) -> Result<DataFrame> {
    let mut b = TableBuilder::new().str("statistic", &["average", "maximum"]);
    let Some((_, before, after)) = e.criteria.iter().find(|c| c.0 == name) else {
        return b.build();
    };
    for (i, s) in e.stations.iter().enumerate() {
        let st = &after.per_station[i];
        b = b.f64(&format!("{s}_um"), vec![st.mean_um, st.max_um]);
    }
    b.f64("all_um", vec![after.overall.mean_um, after.overall.max_um])
        .opt_f64(
            "improvement_pct",
            vec![
                Some(improvement_pct(
                    before.overall.mean_um,
                    after.overall.mean_um,
                )),
                None,
            ],
        )
        .build()
}

/// Table 7 (and 4, 8): initial and residual maximum and average, and the
/// improvement of the average, per criterion.
fn summary(e: &Evaluation) -> Result<DataFrame> {
    let col = |name: &str| -> Vec<Option<f64>> {
        match e.criteria.iter().find(|c| c.0 == name) {
            Some((_, b, a)) => vec![
                Some(b.overall.max_um),
                Some(b.overall.mean_um),
                Some(a.overall.max_um),
                Some(a.overall.mean_um),
                Some(improvement_pct(b.overall.mean_um, a.overall.mean_um)),
            ],
            None => vec![None; 5],
        }
    };
    TableBuilder::new()
        .str(
            "error",
            &["initial", "initial", "residual", "residual", "improvement"],
        )
        .str(
            "statistic",
            &["maximum", "average", "maximum", "average", "pct"],
        )
        .opt_f64("coordinates_um", col("coordinates"))
        .opt_f64("distances_um", col("distances"))
        .opt_f64("reference_coordinates_um", col("reference_coordinates"))
        .opt_f64("reference_distances_um", col("reference_distances"))
        .build()
}

fn terms_table(e: &Evaluation) -> Result<DataFrame> {
    let mut rows: Vec<(&str, &str, &str, &str, String, f64, f64)> = Vec::new();
    for (name, b, a) in &e.criteria {
        for (tb, ta) in b.terms.iter().zip(&a.terms) {
            rows.push((
                name,
                &e.stations[tb.stations.0],
                &e.stations[tb.stations.1],
                &e.targets[tb.targets.0],
                tb.targets
                    .1
                    .map(|t| e.targets[t].clone())
                    .unwrap_or_default(),
                tb.error_um,
                ta.error_um,
            ));
        }
    }
    TableBuilder::new()
        .str("criterion", &rows.iter().map(|r| r.0).collect::<Vec<_>>())
        .str("station_a", &rows.iter().map(|r| r.1).collect::<Vec<_>>())
        .str("station_b", &rows.iter().map(|r| r.2).collect::<Vec<_>>())
        .str("target_a", &rows.iter().map(|r| r.3).collect::<Vec<_>>())
        .str(
            "target_b",
            &rows.iter().map(|r| r.4.clone()).collect::<Vec<_>>(),
        )
        .f64("before_um", rows.iter().map(|r| r.5).collect())
        .f64("after_um", rows.iter().map(|r| r.6).collect())
        .build()
}
