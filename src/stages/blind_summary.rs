//! `blind_summary`: the scores of a blind check from its `cases` table —
//! for a blind check split into blocks of cases run as sweep points (on a
//! cluster, each block a task), scored once on the gathered cases.
//!
//! ```toml
//! [stages.blind]
//! kind = "blind_check"
//! cases = 25                           # a block
//! seed = 1
//! [[sweep.axis]]
//! path = "stages.blind.first_case"
//! range = { from = 0, to = 175, step = 25 }   # 8 blocks: cases 0 … 199
//! [sweep]
//! gather = ["blind.cases"]
//!
//! [stages.scores]
//! kind = "blind_summary"
//! inputs = { cases = "sweep.blind.cases" }
//! effects = ["incidence", "range-scale"]   # the matrix's effects (blind_check's default)
//! ```
//!
//! Outputs as `blind_check`'s — `summary`, `cases`, `confusion`, `kinds`,
//! `confusion.svg` — and equal to those of one check of the same cases
//! (a case is drawn from the seed and its number alone).

use super::blind_check::{self, default_effects, invalid_effects};
use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput};
use crate::diagnose::blind::{Case, CaseKind, SetScore, Truth};
use crate::effects::Effects;
use crate::table::TableRef;
use anyhow::{Result, anyhow, bail};
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct BlindSummaryStage {
    /// The confusion matrix's effects (`blind_check`'s default).
    #[serde(default = "default_effects")]
    pub effects: Vec<String>,
}

impl StageKind for BlindSummaryStage {
    const KIND: &'static str = "blind_summary";
    const SUMMARY: &'static str =
        "the scores of a blind check from its cases (a check split into sweep points, gathered)";
    const INPUTS: &'static [Slot] = &[Slot::table(
        "cases",
        true,
        "a blind check's `cases` table (e.g. `sweep.blind.cases`)",
    )];
    const OUTPUTS: &'static [&'static str] = &["summary", "cases", "confusion", "kinds"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        blind_check::BlindCheckStage::columns(table)
    }

    fn validate(&self) -> Vec<Invalid> {
        invalid_effects(&self.effects)
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let t = inputs.get("cases")?;
        let mut cases = read_cases(&t)?;
        // One check's order, whatever order the blocks were gathered in.
        cases.sort_by_key(|c| c.case);
        if let Some(w) = cases.windows(2).find(|w| w[0].case == w[1].case) {
            bail!(
                "case {} appears twice: the blocks of the check overlap",
                w[0].case
            );
        }
        blind_check::scored(&cases, &self.effects)
    }
}

/// The cases of a `cases` table, as scored (the effects a case put in are
/// not in the table, and no score reads them).
fn read_cases(t: &TableRef) -> Result<Vec<Case>> {
    let n = t.height();
    let int = |c: &str| -> Result<Vec<usize>> {
        t.i64(c)?
            .into_iter()
            .map(|v| usize::try_from(v).map_err(|_| anyhow!("column `{c}`: {v} is negative")))
            .collect()
    };
    let (case, stations, readings) = (int("case")?, int("stations")?, int("readings")?);
    let (members, detectable_n, found) = (
        int("members")?,
        int("members_detectable")?,
        int("members_found")?,
    );
    let (spurious, blunders, blunders_found) =
        (int("spurious")?, int("blunders")?, int("blunders_found")?);
    let (false_blunders, detectable_blunders, clean_readings) = (
        int("false_blunders")?,
        int("detectable_blunders")?,
        int("clean_readings")?,
    );
    let kinds = t.str("kind")?;
    let (layout, true_effect, true_where) = (
        t.str("layout")?,
        t.str("true_effect")?,
        t.str("true_where")?,
    );
    let (named_effect, named_where) = (t.str("named_effect")?, t.str("named_where")?);
    let (true_set, named_set) = (t.str("true_set")?, t.str("named_set")?);
    let (angle, range) = (t.f64("sigma_angle_urad")?, t.f64("sigma_range_um")?);
    let (true_magnitude, signal_chi2) = (t.f64("true_magnitude")?, t.f64("signal_chi2")?);
    let named_magnitude = t.f64("named_magnitude")?;
    let (detectable, effect_correct) = (t.bool("detectable")?, t.bool("effect_correct")?);
    let where_correct = t.opt_bool("where_correct")?;
    let magnitude_ratio = t.opt_f64("magnitude_ratio")?;
    let time = t.bool("time_effect_without_time")?;
    let not_explained = t.bool("not_explained")?;
    (0..n)
        .map(|i| {
            let kind = CaseKind::parse(&kinds[i])
                .ok_or_else(|| anyhow!("row {i}: `{}` is not a kind of case", kinds[i]))?;
            Ok(Case {
                case: case[i],
                kind,
                layout: layout[i].clone(),
                stations: stations[i],
                readings: readings[i],
                sigma_angle_urad: angle[i],
                sigma_range_um: range[i],
                truth: Truth {
                    effect: true_effect[i].clone(),
                    place: true_where[i].clone(),
                    magnitude: true_magnitude[i],
                    has_place: where_correct[i].is_some(),
                    effects: Effects::default(),
                },
                signal_chi2: signal_chi2[i],
                detectable: detectable[i],
                named_effect: named_effect[i].clone(),
                named_place: named_where[i].clone(),
                named_magnitude: named_magnitude[i],
                effect_correct: effect_correct[i],
                place_correct: where_correct[i],
                magnitude_ratio: magnitude_ratio[i],
                set: SetScore {
                    members: members[i],
                    detectable: detectable_n[i],
                    found: found[i],
                    spurious: spurious[i],
                    true_blunders: blunders[i],
                    detectable_blunders: detectable_blunders[i],
                    blunders_found: blunders_found[i],
                    false_blunders: false_blunders[i],
                    clean_readings: clean_readings[i],
                    time_effect_without_time: time[i],
                    not_explained: not_explained[i],
                    true_set: true_set[i].clone(),
                    named_set: named_set[i].clone(),
                },
            })
        })
        .collect()
}
