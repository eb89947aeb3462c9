//! The diagnosis as files: `diagnosis.csv` (the output contract: `rank,
//! effect, where, magnitude, unit, score, significant, rms_before_um,
//! rms_after_um, gap_before_um, gap_after_um, gap_shrink_pct`, then `step`
//! — the explanation set's order of selection, empty for the rest —,
//! `magnitude_u` — the magnitude's standard uncertainty, same unit — and
//! the supporting `k, delta_chi2, p_corrected, delta_bic, detail`), the same
//! as Parquet, `where.csv`, `report.md` in words, and a residual plot per
//! factor.
//!
//! A member's held-out RMS before and after are those of the model before
//! and after it joined (after the nonlinear refit): along the set they
//! chain, so the first member's `rms_before_um` and the last one's
//! `rms_after_um` are the set's. The other rows are tested against the
//! whole set.

use super::Diagnosis;
use crate::plots;
use crate::table::TableBuilder;
use anyhow::{Result, anyhow};
use polars::prelude::DataFrame;
use rayon::prelude::*;
use std::fmt::Write as _;

/// The columns of `diagnosis`, in order: the contract's twelve, then the
/// test's numbers and the detail.
pub const DIAGNOSIS_COLUMNS: &[&str] = &[
    "rank",
    "effect",
    "where",
    "magnitude",
    "unit",
    "score",
    "significant",
    "rms_before_um",
    "rms_after_um",
    "gap_before_um",
    "gap_after_um",
    "gap_shrink_pct",
    "step",
    "magnitude_u",
    "k",
    "delta_chi2",
    "p_corrected",
    "delta_bic",
    "detail",
];

pub fn diagnosis_table(d: &Diagnosis) -> Result<DataFrame> {
    let r = &d.rows;
    let col = |f: fn(&super::Row) -> f64| r.iter().map(f).collect::<Vec<f64>>();
    TableBuilder::new()
        .i64("rank", r.iter().map(|x| x.rank as i64).collect())
        .str(
            "effect",
            &r.iter().map(|x| x.effect.as_str()).collect::<Vec<_>>(),
        )
        .str(
            "where",
            &r.iter().map(|x| x.place.as_str()).collect::<Vec<_>>(),
        )
        .f64("magnitude", col(|x| x.magnitude))
        .str(
            "unit",
            &r.iter().map(|x| x.unit.as_str()).collect::<Vec<_>>(),
        )
        .f64("score", col(|x| x.score))
        .bool("significant", r.iter().map(|x| x.significant).collect())
        .f64("rms_before_um", col(|x| x.rms_before_um))
        .f64("rms_after_um", col(|x| x.rms_after_um))
        .f64("gap_before_um", col(|x| x.gap_before_um))
        .f64("gap_after_um", col(|x| x.gap_after_um))
        .f64("gap_shrink_pct", col(|x| x.gap_shrink_pct))
        .opt_i64("step", r.iter().map(|x| x.step.map(|s| s as i64)).collect())
        .opt_f64(
            "magnitude_u",
            r.iter()
                .map(|x| x.magnitude_u.is_finite().then_some(x.magnitude_u))
                .collect(),
        )
        .i64("k", r.iter().map(|x| x.k as i64).collect())
        .f64("delta_chi2", col(|x| x.delta_chi2))
        .f64("p_corrected", col(|x| x.p_corrected))
        .f64("delta_bic", col(|x| x.delta_bic))
        .str(
            "detail",
            &r.iter().map(|x| x.detail.as_str()).collect::<Vec<_>>(),
        )
        .build()
}

pub fn where_table(d: &Diagnosis) -> Result<DataFrame> {
    let f = &d.factors;
    TableBuilder::new()
        .str("factor", &f.iter().map(|t| t.factor).collect::<Vec<_>>())
        .str(
            "component",
            &f.iter().map(|t| t.component).collect::<Vec<_>>(),
        )
        .i64("groups", f.iter().map(|t| t.groups as i64).collect())
        .f64("eta2", f.iter().map(|t| t.eta2).collect())
        .f64("f", f.iter().map(|t| t.f).collect())
        .f64("p", f.iter().map(|t| t.p).collect())
        .bool("significant", f.iter().map(|t| t.significant).collect())
        .str(
            "worst_group",
            &f.iter().map(|t| t.worst_group.as_str()).collect::<Vec<_>>(),
        )
        .f64(
            "worst_mean_sigma",
            f.iter().map(|t| t.worst_mean_sigma).collect(),
        )
        .build()
}

/// `unexplained.csv`: what the explanation set leaves, per factor (its best
/// basis), most significant first.
pub fn unexplained_table(d: &Diagnosis) -> Result<DataFrame> {
    let u = &d.unexplained;
    TableBuilder::new()
        .str("factor", &u.iter().map(|l| l.factor).collect::<Vec<_>>())
        .str(
            "basis",
            &u.iter().map(|l| l.basis.as_str()).collect::<Vec<_>>(),
        )
        .i64("columns", u.iter().map(|l| l.columns as i64).collect())
        .i64(
            "alternatives",
            u.iter().map(|l| l.alternatives as i64).collect(),
        )
        .f64("delta_chi2", u.iter().map(|l| l.delta_chi2).collect())
        .f64("share", u.iter().map(|l| l.share).collect())
        .f64("f", u.iter().map(|l| l.f).collect())
        .f64("p", u.iter().map(|l| l.p).collect())
        .f64("p_corrected", u.iter().map(|l| l.p_adjusted).collect())
        .bool("significant", u.iter().map(|l| l.significant).collect())
        .f64(
            "gap_removed_pct",
            u.iter().map(|l| l.gap_removed_pct).collect(),
        )
        .build()
}

/// `unexplained-shapes.csv`: each factor's fitted function, point by point.
pub fn unexplained_shapes_table(d: &Diagnosis) -> Result<DataFrame> {
    let rows: Vec<(&str, &str, &super::localise::ShapePoint, &str)> = d
        .unexplained
        .iter()
        .flat_map(|l| {
            l.shape
                .iter()
                .map(move |p| (l.factor, l.shape_x.as_str(), p, l.shape_unit.as_str()))
        })
        .collect();
    TableBuilder::new()
        .str("factor", &rows.iter().map(|r| r.0).collect::<Vec<_>>())
        .str("along", &rows.iter().map(|r| r.1).collect::<Vec<_>>())
        .str(
            "at",
            &rows.iter().map(|r| r.2.at.as_str()).collect::<Vec<_>>(),
        )
        .f64("x", rows.iter().map(|r| r.2.x).collect())
        .f64("value", rows.iter().map(|r| r.2.value).collect())
        .f64("value_u", rows.iter().map(|r| r.2.u).collect())
        .str("unit", &rows.iter().map(|r| r.3).collect::<Vec<_>>())
        .build()
}

pub fn residuals_table(d: &Diagnosis) -> Result<DataFrame> {
    let r = &d.residuals;
    let opt =
        |f: fn(&super::factors::ResidualRow) -> Option<f64>| r.iter().map(f).collect::<Vec<_>>();
    let w = |c: usize, redundancy: bool| -> Vec<Option<f64>> {
        r.iter()
            .map(|x| x.w.map(|t| if redundancy { t[c].1 } else { t[c].0 }))
            .collect()
    };
    TableBuilder::new()
        .str(
            "station",
            &r.iter().map(|x| x.station.as_str()).collect::<Vec<_>>(),
        )
        .str(
            "target",
            &r.iter().map(|x| x.target.as_str()).collect::<Vec<_>>(),
        )
        .i64("face", r.iter().map(|x| x.face).collect())
        .f64("az_urad", r.iter().map(|x| x.physical[0]).collect())
        .f64("el_urad", r.iter().map(|x| x.physical[1]).collect())
        .f64("d_um", r.iter().map(|x| x.physical[2]).collect())
        .f64("az_sigma", r.iter().map(|x| x.sigma_units[0]).collect())
        .f64("el_sigma", r.iter().map(|x| x.sigma_units[1]).collect())
        .f64("d_sigma", r.iter().map(|x| x.sigma_units[2]).collect())
        .opt_f64("incidence_deg", opt(|x| x.incidence_deg))
        .f64("range_mm", r.iter().map(|x| x.range_mm).collect())
        .f64("azimuth_deg", r.iter().map(|x| x.azimuth_deg).collect())
        .f64("elevation_deg", r.iter().map(|x| x.elevation_deg).collect())
        .opt_f64("time_s", opt(|x| x.time_s))
        .opt_f64("temperature_c", opt(|x| x.temperature_c))
        .opt_f64("w_az", w(0, false))
        .opt_f64("w_el", w(1, false))
        .opt_f64("w_d", w(2, false))
        .opt_f64("redundancy_az", w(0, true))
        .opt_f64("redundancy_el", w(1, true))
        .opt_f64("redundancy_d", w(2, true))
        .build()
}

pub fn summary_table(d: &Diagnosis) -> Result<DataFrame> {
    let set = set_numbers(d);
    TableBuilder::new()
        .str("campaign", &[&d.campaign])
        .f64("chi2", vec![d.chi2])
        .i64("dof", vec![d.dof as i64])
        .f64("chi2_p", vec![d.chi2_p])
        .bool("noise_stated", vec![d.noise_stated])
        .f64("noise_floor_um", vec![d.floor.um])
        .f64("noise_floor_u_um", vec![d.floor.u_um])
        .i64("tried", vec![d.tried as i64])
        .i64("blunder_tests", vec![d.blunder_tests as i64])
        .str("explanation", &[explanation(d)])
        .f64("set_rms_before_um", vec![set.0])
        .f64("set_rms_after_um", vec![set.1])
        .f64("set_gap_shrink_pct", vec![set.2])
        .str("verdict", &[verdict(d)])
        .build()
}

/// The explanation set's members as `effect at place` joined by ` + `;
/// `none` when empty.
pub fn explanation(d: &Diagnosis) -> String {
    let names: Vec<String> = d
        .explanation()
        .map(|r| format!("{} at {}", r.effect, r.place))
        .collect();
    if names.is_empty() {
        "none".into()
    } else {
        names.join(" + ")
    }
}

/// The set's held-out RMS before and after (µm) and the share of the gap
/// it removes (%).
pub fn set_numbers(d: &Diagnosis) -> (f64, f64, f64) {
    let set: Vec<&super::Row> = d.explanation().collect();
    // A gross blunder screened out before the folds has no held-out
    // residual before it: the set's gap is measured from the first member
    // that has one.
    let first = set.iter().find(|r| r.rms_before_um.is_finite()).copied();
    match (first, set.last()) {
        (Some(a), Some(b)) => {
            let gb = a.rms_before_um - d.floor.um;
            let ga = b.rms_after_um - d.floor.um;
            let shrink = d.floor.shrink_pct(gb, ga);
            (a.rms_before_um, b.rms_after_um, shrink)
        }
        _ => {
            let rms = d.best().rms_before_um;
            (rms, rms, 0.0)
        }
    }
}

pub fn skipped_table(d: &Diagnosis) -> Result<DataFrame> {
    TableBuilder::new()
        .str(
            "effect",
            &d.skipped
                .iter()
                .map(|s| s.effect.as_str())
                .collect::<Vec<_>>(),
        )
        .str(
            "reason",
            &d.skipped
                .iter()
                .map(|s| s.reason.as_str())
                .collect::<Vec<_>>(),
        )
        .build()
}

/// Rank 1 in one sentence.
pub fn verdict(d: &Diagnosis) -> String {
    let b = d.best();
    // What the set leaves when it is more than the stated noise: no member
    // is then presented as the whole cause.
    let left = d.rest().filter(|r| !r.significant && b.effect != "none");
    if let Some(rest) = left {
        let (before, _, shrink) = set_numbers(d);
        let what = match (
            b.effect == super::MODEL && b.step.is_some(),
            d.explanation().count(),
        ) {
            (true, _) => format!("the {} model", b.place),
            (false, 1) => format!(
                "{} at {}: {:.3}{} {}",
                b.effect,
                b.place,
                b.magnitude,
                plus_minus(b.magnitude_u),
                b.unit
            ),
            (false, _) => explanation(d),
        };
        let rest = rest.place.trim_start_matches("unexplained structure: ");
        return format!(
            "partly explained: {what} {}; \
             the residual left is not consistent with the stated noise ({rest}) — an effect \
             outside the catalogue, or a hypothesis of your own (--hypotheses), may explain the rest",
            match gap_removed(d, before - d.floor.um, shrink) {
                Some(pct) => format!("removes {pct}"),
                None => format!("is fitted, {NO_GAP}"),
            }
        );
    }
    if b.effect == super::MODEL && b.step.is_some() {
        let rest: Vec<String> = d
            .explanation()
            .skip(1)
            .map(|r| format!("{} at {}", r.effect, r.place))
            .collect();
        format!(
            "model mismatch: the readings fit the {} model, not the base model (ΔBIC = {:.1}; {}){}",
            b.place,
            b.delta_bic,
            b.detail,
            if rest.is_empty() {
                "; no effect on top of it".to_string()
            } else {
                format!("; on top of it: {}", rest.join(" + "))
            }
        )
    } else if b.effect == "none" {
        if b.significant {
            "none: no candidate effect is significant and the residual is consistent with the stated noise".into()
        } else {
            format!(
                "none: no candidate effect is significant, but the residual is not consistent with the stated noise ({})",
                b.place
            )
        }
    } else if d.explanation().count() > 1 {
        let (before, _, shrink) = set_numbers(d);
        format!(
            "{} together: {}",
            explanation(d),
            removed(d, before - d.floor.um, shrink)
        )
    } else {
        format!(
            "{} at {}{}: {:.3}{} {}, {}",
            b.effect,
            b.place,
            if b.detail.is_empty() {
                String::new()
            } else {
                format!(" ({})", b.detail)
            },
            b.magnitude,
            plus_minus(b.magnitude_u),
            b.unit,
            // The one measure of "how far" the report uses everywhere: the
            // held-out gap over the noise floor.
            match (b.step.is_some(), b.rms_before_um.is_finite()) {
                (_, false) => "the held-out residual before it not measurable".to_string(),
                (true, true) => {
                    let (before, _, shrink) = set_numbers(d);
                    removed(d, before - d.floor.um, shrink)
                }
                (false, true) => removed(d, b.gap_before_um, b.gap_shrink_pct),
            }
        )
    }
}

/// What a verdict says when the held-out gap over the noise floor is within
/// the floor's own Monte Carlo error: no share of it is read as removed.
const NO_GAP: &str = "no held-out gap over the noise floor beyond its Monte Carlo error";

/// `shrink` % "of the gap over the noise floor" when the gap (`gap_um`)
/// stands beyond the floor's Monte Carlo error, else none.
fn gap_removed(d: &Diagnosis, gap_um: f64, shrink: f64) -> Option<String> {
    d.floor
        .has_gap(gap_um)
        .then(|| format!("{shrink:.1} % of the gap over the noise floor"))
}

/// "… % of the gap over the noise floor removed", or [`NO_GAP`].
fn removed(d: &Diagnosis, gap_um: f64, shrink: f64) -> String {
    match gap_removed(d, gap_um, shrink) {
        Some(pct) => format!("{pct} removed"),
        None => NO_GAP.to_string(),
    }
}

/// ` ± u` (a standard uncertainty, to three decimals), or nothing when
/// there is none.
fn plus_minus(u: f64) -> String {
    if u.is_finite() {
        format!(" ± {u:.3}")
    } else {
        String::new()
    }
}

/// A float as CSV text that round-trips: positional, except far from 1,
/// where Rust's positional form would spell out hundreds of zeros (a
/// `p_corrected` of 1e-300).
fn float_text(x: f64) -> String {
    if x != 0.0 && x.is_finite() && !(1e-5..1e16).contains(&x.abs()) {
        format!("{x:e}")
    } else {
        format!("{x}")
    }
}

/// A table as CSV text (floats written to round-trip).
pub fn csv(df: &DataFrame) -> Result<Vec<u8>> {
    let mut w = csv::Writer::from_writer(Vec::new());
    let names: Vec<String> = df
        .get_column_names()
        .iter()
        .map(|s| s.to_string())
        .collect();
    w.write_record(&names)?;
    for i in 0..df.height() {
        let row: Vec<String> = df
            .columns()
            .iter()
            .map(|c| match c.get(i) {
                Ok(polars::prelude::AnyValue::Float64(x)) => float_text(x),
                Ok(v) => crate::table::cell_text(&v, 12),
                Err(_) => String::new(),
            })
            .collect();
        w.write_record(&row)?;
    }
    w.into_inner().map_err(|e| anyhow!("writing CSV: {e}"))
}

/// The diagnosis in words, as Markdown: `report.md` joins the parts in
/// the order of the analysis ([`Sections::markdown`]), the page
/// (`super::page`) in the order a reader asks. One source of the words.
pub struct Sections {
    /// `# Diagnosis of …`.
    pub title: String,
    /// `**Verdict:** …` ([`verdict`]).
    pub verdict: String,
    /// `## Base calibration`: χ², the held-out residual, the noise floor.
    pub base: String,
    /// `## Where`: the significant factors.
    pub place: String,
    /// `## What is left`: what the set leaves, per factor.
    pub left: String,
    /// `## Which tracker model`; empty when no model was compared.
    pub models: String,
    /// The `## Which` heading.
    pub which: String,
    /// How many candidates were tried, and how the set is built.
    pub tried: String,
    /// The ranking's table (magnitude ± u), and what the set leaves in words.
    pub ranking: String,
    /// The candidates skipped, with why; empty when none.
    pub skipped: String,
    /// The readings rejected as blunders; empty when none.
    pub blunders: String,
    /// `## How far`: the held-out residual before and after the set.
    pub how_far: String,
}

impl Sections {
    /// `report.md`.
    pub fn markdown(&self) -> String {
        [
            &self.title,
            &self.verdict,
            &self.base,
            &self.place,
            &self.left,
            &self.models,
            &self.which,
            &self.tried,
            &self.ranking,
            &self.skipped,
            &self.blunders,
            &self.how_far,
        ]
        .into_iter()
        .map(String::as_str)
        .collect()
    }
}

/// The diagnosis in words (`report.md`).
pub fn report(d: &Diagnosis) -> String {
    sections(d).markdown()
}

/// The figures left out, with why (appended to `report.md`); empty when
/// every figure was drawn.
pub fn figures_left_out(notes: &[String]) -> String {
    let mut s = String::new();
    if !notes.is_empty() {
        s.push_str("\n## Figures left out\n\n");
        for note in notes {
            let _ = writeln!(s, "- {note}");
        }
    }
    s
}

/// The report's parts (see [`Sections`]).
///
/// Long on purpose (issue 31): the sections in the order the report reads,
/// each a few lines of words over the diagnosis; no step is reused.
pub fn sections(d: &Diagnosis) -> Sections {
    let mut s = String::new();
    let _ = writeln!(s, "# Diagnosis of `{}`\n", d.campaign);
    let title = std::mem::take(&mut s);
    let _ = writeln!(s, "**Verdict:** {}.\n", verdict(d));
    let verdict = std::mem::take(&mut s);
    let _ = writeln!(s, "## Base calibration\n");
    // After a model mismatch the diagnosis stands on the model that fits.
    let b = d.best();
    let mismatch = b.effect == super::MODEL && b.step.is_some();
    let held_out = if mismatch {
        b.rms_after_um
    } else {
        b.rms_before_um
    };
    let fitted = d.calibration.estimate.params.tracker();
    let _ = writeln!(
        s,
        "Bundle adjustment with the {fitted} model{}: χ² = {:.1} on {} degrees of freedom (χ²/dof = {:.2}, p = {:.3}). The residual is {} with the {} noise.",
        if mismatch {
            " (the model that fits: see \"Which tracker model\")"
        } else {
            ""
        },
        d.chi2,
        d.dof,
        d.chi2 / d.dof as f64,
        d.chi2_p,
        if d.chi2_p >= 0.01 {
            "consistent"
        } else {
            "not consistent"
        },
        if d.noise_stated {
            "stated"
        } else {
            "assumed (the campaign states none)"
        }
    );
    let _ = writeln!(
        s,
        "Held-out residual (5-fold cross-validation): {:.2} µm RMS; noise alone would leave {:.2} ± {:.3} µm in this geometry (Monte Carlo, ± its standard error), so the gap is {:.2} µm{}.\n",
        held_out,
        d.floor.um,
        d.floor.u_um,
        held_out - d.floor.um,
        if d.floor.has_gap(held_out - d.floor.um) {
            ""
        } else {
            ": none beyond the floor's own Monte Carlo error, so no share of it is counted as removed"
        }
    );
    let base = std::mem::take(&mut s);
    let _ = writeln!(s, "## Where\n");
    let sig: Vec<_> = d.factors.iter().filter(|t| t.significant).collect();
    let named: Vec<String> = d
        .explanation()
        .map(|r| match r.place.as_str() {
            "" | "all" => r.effect.clone(),
            place => format!("{} at {place}", r.effect),
        })
        .collect();
    if sig.is_empty() && named.is_empty() {
        let _ = writeln!(
            s,
            "No factor explains a significant share of the residual variance.\n"
        );
    } else if sig.is_empty() {
        // "Where" and "Which" must not seem to disagree: the set is found
        // by fitting its signatures, which this one-factor test cannot.
        let _ = writeln!(
            s,
            "No single factor's groups differ significantly, yet *Which* names {}: each member's signature is fitted as columns of the adjustment over every reading at once, while this test compares one factor's group means at a time, so an effect of this size shows there and not here.\n",
            named.join(", ")
        );
    } else {
        let _ = writeln!(
            s,
            "| factor | component | share of variance (η²) | p | worst group | its mean (σ) |\n|---|---|---|---|---|---|"
        );
        let mut sig = sig;
        sig.sort_by(|a, b| b.eta2.total_cmp(&a.eta2));
        for t in sig.iter().take(10) {
            let _ = writeln!(
                s,
                "| {} | {} | {:.3} | {:.2e} | {} | {:+.2} |",
                t.factor, t.component, t.eta2, t.p, t.worst_group, t.worst_mean_sigma
            );
        }
        s.push('\n');
    }
    let place = std::mem::take(&mut s);
    let _ = writeln!(s, "## What is left\n");
    let left: Vec<_> = d.unexplained.iter().filter(|l| l.significant).collect();
    if left.is_empty() {
        let _ = writeln!(
            s,
            "No factor's smooth or periodic function explains a significant part of what the explanation set leaves (each tried as extra columns of the adjustment; `unexplained.csv`).\n"
        );
    } else {
        let _ = writeln!(
            s,
            "Each factor's best basis, fitted as extra columns of the adjustment beside the explanation set (`unexplained.csv`; the fitted shapes in `unexplained-shapes.csv`):\n\n| factor | best basis | share of the χ² left | held-out gap it removes | p (corrected) |\n|---|---|---|---|---|"
        );
        for l in &left {
            let _ = writeln!(
                s,
                "| {} | {} | {:.0} % | {:.0} % | {:.1e} |",
                l.factor,
                l.basis,
                100.0 * l.share,
                l.gap_removed_pct,
                l.p_adjusted
            );
        }
        let _ = writeln!(
            s,
            "\nThe first factor's fitted shape, with ±2u bars: `unexplained.svg`."
        );
        if left[0].hypothesis.is_some() {
            let _ = writeln!(
                s,
                "\nThe first is written as a hypothesis in `discovered.toml`: rename it, edit it, and test it on the next campaign with `ltcal diagnose --hypotheses discovered.toml`."
            );
        }
        s.push('\n');
    }
    let left = std::mem::take(&mut s);
    if !d.models.is_empty() {
        let _ = writeln!(s, "## Which tracker model\n");
        let _ = writeln!(
            s,
            "Every tracker model fitted to the readings (bundle adjustment; after the explanation set's effects are taken off them when the comparison is made at its end); BIC = χ² + k·ln m with k the determined combinations, held-out RMS by the same folds. A model mismatch is called when another model explains ≥ {} more χ², its BIC is lower by ≥ {}, and by more than any effect's.\n",
            super::models::DETECTABLE_CHI2,
            super::models::MISMATCH_BIC
        );
        let _ = writeln!(
            s,
            "| model | χ² | dof | p | determined | BIC | held-out RMS (µm) |\n|---|---|---|---|---|---|---|"
        );
        for m in &d.models {
            let _ = writeln!(
                s,
                "| {} | {:.1} | {} | {:.3} | {} of {} | {:.1} | {:.2} |",
                m.model, m.chi2, m.dof, m.chi2_p, m.rank, m.n_params, m.bic, m.cv_rms_um
            );
        }
        s.push('\n');
    }
    let models = std::mem::take(&mut s);
    let _ = writeln!(s, "## Which\n");
    let which = std::mem::take(&mut s);
    let _ = writeln!(
        s,
        "{} candidate explanations were tried (alternatives included; the significance threshold is Bonferroni-corrected for them).\n",
        d.tried
    );
    let _ = writeln!(
        s,
        "The explanation set is built step by step: the most significant candidate (an effect, or the worst reading by Baarda's w-test over {} reading coordinates) joins the model, the campaign is adjusted again with it, and every other candidate is tested against the augmented model; α is spent as α·2⁻ˢ over the steps.\n",
        d.blunder_tests
    );
    let tried = std::mem::take(&mut s);
    let _ = writeln!(
        s,
        "| rank | step | effect | where | magnitude ± u | score (%) | significant | held-out RMS before → after (µm) | gap shrink (%) |\n|---|---|---|---|---|---|---|---|---|"
    );
    // `none` is not a candidate but what the set leaves: said in words
    // below the table, never a row that reads as a significant member.
    for r in d.rows.iter().filter(|r| r.effect != "none").take(10) {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {:.3}{} {} | {:.1} | {} | {:.2} → {:.2} | {:.1} |",
            r.rank,
            r.step.map(|s| s.to_string()).unwrap_or_default(),
            r.effect,
            r.place,
            r.magnitude,
            plus_minus(r.magnitude_u),
            r.unit,
            r.score,
            if r.significant { "yes" } else { "no" },
            r.rms_before_um,
            r.rms_after_um,
            r.gap_shrink_pct
        );
    }
    if let Some(r) = d.rest() {
        let _ = writeln!(
            s,
            "\nWhat the explanation set leaves (rank {}, `none`: not a candidate) has χ²/dof = {:.3} ({}), held-out RMS {:.2} µm. Rest consistent with the stated noise: {}.",
            r.rank,
            r.magnitude,
            r.detail,
            r.rms_before_um,
            if r.significant {
                "yes".to_string()
            } else {
                format!(
                    "no ({})",
                    r.place.trim_start_matches("unexplained structure: ")
                )
            }
        );
    }
    let ranking = std::mem::take(&mut s);
    if !d.skipped.is_empty() {
        let _ = writeln!(s, "\nSkipped, not guessed:\n");
        for k in &d.skipped {
            let _ = writeln!(s, "- `{}`: {}", k.effect, k.reason);
        }
    }
    let skipped = std::mem::take(&mut s);
    let blunders: Vec<&super::Row> = d.explanation().filter(|r| r.effect == "blunder").collect();
    if !blunders.is_empty() {
        let _ = writeln!(s, "\nReadings rejected as blunders:\n");
        for r in blunders {
            let _ = writeln!(
                s,
                "- {} ({}): {:+.1} ± {:.1} {}",
                r.place, r.detail, r.magnitude, r.magnitude_u, r.unit
            );
        }
    }
    let blunders_text = std::mem::take(&mut s);
    let _ = writeln!(s, "\n## How far\n");
    let b = d.best();
    let set: Vec<&super::Row> = d.explanation().collect();
    if set.len() > 1 {
        let (before, after, shrink) = set_numbers(d);
        let names: Vec<String> = set
            .iter()
            .map(|r| format!("`{}` ({})", r.effect, r.place))
            .collect();
        let _ = writeln!(
            s,
            "{} together bring the held-out residual from {before:.2} µm to {after:.2} µm: they shrink the gap over the noise floor from {:.2} µm to {:.2} µm ({shrink:.1} %).",
            names.join(" and "),
            before - d.floor.um,
            after - d.floor.um,
        );
    } else if b.effect == "none" {
        let _ = writeln!(
            s,
            "No effect is added; the gap stays at {:.2} µm.",
            b.gap_before_um
        );
    } else {
        let _ = writeln!(
            s,
            "Adding `{}` at {} brings the held-out residual from {:.2} µm to {:.2} µm: the gap over the noise floor shrinks from {:.2} µm to {:.2} µm ({:.1} %).",
            b.effect,
            b.place,
            b.rms_before_um,
            b.rms_after_um,
            b.gap_before_um,
            b.gap_after_um,
            b.gap_shrink_pct
        );
    }
    Sections {
        title,
        verdict,
        base,
        place,
        left,
        models,
        which,
        tried,
        ranking,
        skipped,
        blunders: blunders_text,
        how_far: s,
    }
}

/// One SVG per factor: the residuals against it. A factor whose values
/// (or residuals) span more than a figure can draw — a `time_s` of 1.8e308
/// — gets no figure but a note for the report instead, so an extreme but
/// valid value costs a figure, not the diagnosis.
pub fn figures(d: &Diagnosis) -> Result<Figures> {
    let mut out = Figures::default();
    let comp: Vec<Vec<f64>> = (0..3)
        .map(|c| d.residuals.iter().map(|r| r.physical[c]).collect())
        .collect();
    // Each factor's figure is its own (a thinning and an SVG of every
    // reading): drawn side by side, taken in the factors' order — the
    // same files, the same notes, the same first error.
    let drawn: Vec<Result<String>> = d
        .factor_defs
        .par_iter()
        .map(|f| {
            let categorical = matches!(f.name, "station" | "reflector" | "face");
            plots::residuals_by_factor(
                &format!("{}: residuals by {}", d.campaign, plots::axis_title(f.name)),
                &plots::axis_title(f.name),
                categorical.then_some(&f.labels[..]),
                &f.x,
                [
                    ("az residual (µrad)", &comp[0]),
                    ("el residual (µrad)", &comp[1]),
                    ("d residual (µm)", &comp[2]),
                ],
            )
        })
        .collect();
    for (f, drawn) in d.factor_defs.iter().zip(drawn) {
        match drawn {
            Ok(svg) => out
                .files
                .push((format!("residuals-{}.svg", f.name), svg.into_bytes())),
            Err(e) => match e.downcast_ref::<plots::Undrawable>() {
                Some(u) => out
                    .notes
                    .push(format!("No figure of the residuals by {}: {u}.", f.name)),
                None => return Err(e),
            },
        }
    }
    // What is left: the first significant factor's fitted shape.
    if let Some(l) = d.unexplained.iter().find(|l| l.significant) {
        let labels: Vec<String> = l.shape.iter().map(|p| p.at.clone()).collect();
        let categorical = l.shape_x == "column";
        let drawn = plots::fitted_shape(
            &format!(
                "{}: what is left along {} — {}",
                d.campaign, l.factor, l.basis
            ),
            if categorical { "" } else { &l.shape_x },
            &l.shape_unit,
            categorical.then_some(&labels[..]),
            &l.shape
                .iter()
                .map(|p| (p.x, p.value, p.u))
                .collect::<Vec<_>>(),
        );
        match drawn {
            Ok(svg) => out.files.push(("unexplained.svg".into(), svg.into_bytes())),
            Err(e) => match e.downcast_ref::<plots::Undrawable>() {
                Some(u) => out.notes.push(format!(
                    "No figure of what is left along {}: {u}.",
                    l.factor
                )),
                None => return Err(e),
            },
        }
    }
    Ok(out)
}

/// The figures of a diagnosis, and a note for each one left out.
#[derive(Default)]
pub struct Figures {
    pub files: Vec<(String, Vec<u8>)>,
    pub notes: Vec<String>,
}

#[cfg(test)]
mod tests {
    use super::float_text;

    /// Regression: a `p_corrected` of 2.6e-300 was written to
    /// `diagnosis.csv` as 300 characters of zeros.
    #[test]
    fn tiny_p_values_are_written_short_and_round_trip() {
        for x in [
            2.569340674987612e-300,
            1e-6,
            0.5,
            8.176087746984,
            -35.76,
            0.0,
            3e20,
        ] {
            let t = float_text(x);
            assert!(t.len() <= 24, "{t}");
            assert_eq!(t.parse::<f64>().unwrap(), x);
        }
        assert_eq!(float_text(0.5), "0.5");
        assert_eq!(float_text(1e-300), "1e-300");
    }
}
