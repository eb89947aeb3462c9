//! `ltcal explain`: why a stage would run, or why it is cached — its current
//! key fields against those of the last successful run of a stage of that
//! name in the results asked about (`.ltcal/last/<stage>.json` for the
//! pipeline's own, `.ltcal/last/runs/<name>/<stage>.json` for an
//! experiment's — or, for an experiment that has not published the stage,
//! the pipeline's), field by field: what these results hold, whichever run
//! computed it.
//!
//! A stage that runs at every point of a sweep is explained at one point
//! (`--point`, else the first point that would run it, else point 0),
//! against the last run at that point (recorded in the sweep's packs).
//!
//! An input whose producer would run first has no content hash yet; its
//! row says which stage it waits for, and every other field is still
//! compared, so that a change of the stage's own settings shows even when an
//! upstream change makes it rerun anyway.

use super::cache::{KeyFields, Store, short};
use super::error::InputError;
use super::plan::{self, Assessment};
use super::resolve::Pipeline;
use super::status::Status;
use anyhow::Result;
use serde::Serialize;
use std::collections::BTreeMap;
use std::fmt;

/// One key field, last run against now.
#[derive(Clone, Debug, Serialize)]
pub struct Row {
    pub field: String,
    /// `None`: the last run had no such field (or there was no last run).
    pub last: Option<String>,
    /// `None`: no such field now, or not known yet (see `waits_for`).
    pub now: Option<String>,
    /// The stage that must run before this input's content is known.
    pub waits_for: Option<String>,
    pub changed: bool,
}

/// Why a stage is cached or would run.
#[derive(Clone, Debug, Serialize)]
pub struct Explanation {
    pub stage: String,
    pub kind: String,
    /// [`Status::Cached`] or [`Status::Run`], as `ltcal plan` says.
    pub status: Status,
    pub reason: String,
    /// The current key, when every input's content is known.
    pub key: Option<String>,
    /// The key of the last successful run of this stage, if any.
    pub last_key: Option<String>,
    /// The experiment explained (`--name`, `--set`); `None`: the
    /// pipeline's own results.
    pub experiment: Option<String>,
    /// Whose last run `last_key` is: `experiment` or `main` (an experiment
    /// that has not published the stage is compared with the pipeline's
    /// results), or `point` (a sweep point's last run, by any run).
    pub compared_with: Option<String>,
    /// For a stage that runs per sweep point: the point explained.
    pub point: Option<PointInfo>,
    pub rows: Vec<Row>,
}

/// The sweep point a per-point stage is explained at.
#[derive(Clone, Debug, Serialize)]
pub struct PointInfo {
    pub index: usize,
    pub points: usize,
    /// Axis name → its value at the point.
    pub values: BTreeMap<String, serde_json::Value>,
    /// How many points would run the stage.
    pub would_run: usize,
}

/// Explains one stage of the pipeline against its store; a stage that runs
/// per sweep point at `point` (see the module doc when `None`).
pub fn explain(
    p: &Pipeline,
    store: &Store,
    stage: &str,
    point: Option<usize>,
) -> Result<Explanation> {
    p.stage(stage)?;
    let per_point = p
        .sweep
        .as_ref()
        .filter(|sw| sw.point_stages().any(|s| s == stage));
    let find = |assessed: Vec<Assessment>| {
        assessed
            .into_iter()
            .find(|a| a.item.stage == stage)
            .expect("every stage is assessed")
    };
    let (a, at) = match (per_point, point) {
        (None, None) => (find(plan::assess(p, store)), None),
        (None, Some(_)) => {
            return Err(InputError::arg(format!(
                "`{stage}` does not run per sweep point: explain it without --point"
            )));
        }
        (Some(sw), point) => {
            if let Some(i) = point.filter(|&i| i >= sw.len()) {
                return Err(InputError::arg(format!(
                    "--point {i}: the sweep has {} points, 0 to {}",
                    sw.len(),
                    sw.len() - 1
                )));
            }
            // The point asked for, else the first that would run it, else
            // the first; and how many would.
            let mut would_run = 0;
            let mut chosen: Option<(usize, Assessment)> = None;
            plan::assess_points(sw, store, |i, assessed| {
                let a = find(assessed);
                let stale = a.item.status != Status::Cached;
                would_run += usize::from(stale);
                let take = match point {
                    Some(p) => p == i,
                    None => {
                        chosen.is_none()
                            || (stale
                                && chosen
                                    .as_ref()
                                    .is_some_and(|(_, c)| c.item.status == Status::Cached))
                    }
                };
                if take {
                    chosen = Some((i, a));
                }
            });
            let (index, a) = chosen.expect("a sweep has at least one point");
            let pt = sw.point(index);
            let info = PointInfo {
                index: pt.index,
                points: sw.len(),
                values: sw
                    .axes
                    .iter()
                    .zip(&pt.values)
                    .map(|(axis, v)| (axis.name.clone(), v.clone()))
                    .collect(),
                would_run,
            };
            (a, Some(info))
        }
    };
    let last = store.last(stage, at.as_ref().map(|i| i.index));
    let compared_with = last.as_ref().map(|_| {
        match (&at, store.experiment()) {
            (Some(_), _) => "point",
            (None, Some(_)) if store.last_here(stage).is_some() => "experiment",
            (None, _) => "main",
        }
        .to_string()
    });
    Ok(Explanation {
        experiment: store.experiment().map(String::from),
        compared_with,
        rows: rows(&a, last.as_ref()),
        last_key: last.as_ref().map(KeyFields::hash),
        point: at,
        stage: a.item.stage,
        kind: a.item.kind,
        status: a.item.status,
        reason: a.item.reason,
        key: a.item.key,
    })
}

fn rows(a: &Assessment, last: Option<&KeyFields>) -> Vec<Row> {
    // Without a recorded run there is nothing to call a change.
    let recorded = last.is_some();
    let last: BTreeMap<String, String> = last
        .map(|k| k.fields())
        .unwrap_or_default()
        .into_iter()
        .collect();
    let mut now = a.fields.fields();
    now.extend(
        a.pending
            .keys()
            .map(|slot| (format!("input `{slot}`"), String::new())),
    );
    let waits: BTreeMap<String, &String> = a
        .pending
        .iter()
        .map(|(slot, stage)| (format!("input `{slot}`"), stage))
        .collect();
    let mut rows: Vec<Row> = Vec::new();
    for (field, value) in now {
        let waits_for = waits.get(&field).map(|s| s.to_string());
        let value = waits_for.is_none().then_some(value);
        let last = last.get(&field).cloned();
        rows.push(Row {
            changed: recorded && waits_for.is_none() && value != last,
            field,
            last,
            now: value,
            waits_for,
        });
    }
    // Fields only the last run had (a setting or input since removed).
    for (field, value) in &last {
        if !rows.iter().any(|r| &r.field == field) {
            rows.push(Row {
                field: field.clone(),
                last: Some(value.clone()),
                now: None,
                waits_for: None,
                changed: true,
            });
        }
    }
    rows
}

impl fmt::Display for Explanation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let verdict = match (self.status, self.reason.is_empty()) {
            (Status::Cached, _) => "cached".to_string(),
            (_, true) => "would run".to_string(),
            (_, false) => format!("would run: {}", self.reason),
        };
        writeln!(f, "stage `{}` ({}): {verdict}", self.stage, self.kind)?;
        if let Some(pt) = &self.point {
            let values: Vec<String> = pt
                .values
                .iter()
                .map(|(k, v)| format!("{k} = {v}"))
                .collect();
            writeln!(
                f,
                "at sweep point {} of {} ({}); {} of {} points would run it",
                pt.index,
                pt.points,
                values.join(", "),
                pt.would_run,
                pt.points
            )?;
        }
        let key = |k: &Option<String>| k.as_deref().map_or("—".to_string(), |k| short(k).into());
        writeln!(
            f,
            "key now {}, at the last run {}",
            key(&self.key),
            key(&self.last_key)
        )?;
        if let Some(name) = &self.experiment {
            let whose = match self.compared_with.as_deref() {
                Some("experiment") => format!("compared with the last run of experiment `{name}`"),
                Some("main") => format!(
                    "experiment `{name}` has not published it: compared with the pipeline's own results"
                ),
                Some(_) => "compared with the last run at that point, by any run".to_string(),
                None => format!("experiment `{name}`"),
            };
            writeln!(f, "({whose})")?;
        }
        if self.last_key.is_none() {
            writeln!(
                f,
                "(no earlier run of it is recorded here: nothing to compare with)"
            )?;
        } else if self.status == Status::Cached && self.rows.iter().any(|r| r.changed) {
            writeln!(
                f,
                "(an earlier run with the current settings is in the cache; the last run differed)"
            )?;
        }
        let cell = |r: &Row, v: &Option<String>, now: bool| match (v, &r.waits_for) {
            (_, Some(s)) if now => format!("(known once `{s}` has run)"),
            (Some(v), _) => v.clone(),
            (None, _) => "—".to_string(),
        };
        let table: Vec<[String; 4]> = std::iter::once([
            String::new(),
            "field".to_string(),
            "last run".to_string(),
            "now".to_string(),
        ])
        .chain(self.rows.iter().map(|r| {
            [
                if r.changed { "*".into() } else { String::new() },
                r.field.clone(),
                cell(r, &r.last, false),
                cell(r, &r.now, true),
            ]
        }))
        .collect();
        let width = |j: usize| {
            table
                .iter()
                .map(|r| r[j].chars().count())
                .max()
                .unwrap_or(0)
        };
        let (w1, w2) = (width(1), width(2));
        for r in &table {
            let line = format!("{:>3} {:w1$}  {:w2$}  {}", r[0], r[1], r[2], r[3]);
            writeln!(f, "{}", line.trim_end())?;
        }
        if self.rows.iter().any(|r| r.changed) {
            writeln!(f, "(* changed since the last run)")?;
        }
        Ok(())
    }
}
