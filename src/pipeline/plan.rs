//! Layer 3: the executable plan. Orders the stages (dependencies first, file
//! order among equals), groups them into levels that can run in parallel,
//! computes each stage's cache key where its inputs are known, and says for
//! every stage whether it is cached or why it would run.

use super::cache::{self, KeyFields, Store};
use super::resolve::{Pipeline, Stage, Sweep};
use super::status::Status;
use super::sweep::{Gatherer, PSEUDO_STAGE};
use crate::table;
use rayon::prelude::*;
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet};

/// Stage indices in an order that runs every producer before its consumers,
/// grouped into levels whose stages depend only on earlier levels.
#[derive(Clone, Debug)]
pub struct Graph {
    pub levels: Vec<Vec<usize>>,
}

impl Graph {
    pub fn new(p: &Pipeline) -> Graph {
        Graph::of(&p.stages)
    }

    /// The graph of a list of stages (inputs from outside it are given).
    pub fn of(stages: &[Stage]) -> Graph {
        let index = |name: &str| stages.iter().position(|s| s.name == name);
        let n = stages.len();
        let mut level = vec![usize::MAX; n];
        // The resolver rejected cycles, so repeated relaxation terminates.
        let mut changed = true;
        while changed {
            changed = false;
            for (i, s) in stages.iter().enumerate() {
                // Inputs from outside the stage list (a sweep's gathered
                // tables) are there before any stage runs.
                let deps: Option<usize> = s
                    .inputs
                    .values()
                    .filter_map(|r| index(&r.stage).map(|j| level[j]))
                    .try_fold(0usize, |acc, l| (l != usize::MAX).then(|| acc.max(l + 1)));
                if let Some(l) = deps {
                    if level[i] != l {
                        level[i] = l;
                        changed = true;
                    }
                }
            }
        }
        let depth = level.iter().copied().max().map_or(0, |m| m + 1);
        let mut levels = vec![Vec::new(); depth];
        for (i, &l) in level.iter().enumerate() {
            levels[l].push(i);
        }
        Graph { levels }
    }

    pub fn order(&self) -> impl Iterator<Item = usize> + '_ {
        self.levels.iter().flatten().copied()
    }
}

/// The key fields of a stage given the content hashes of its inputs.
pub fn key_fields(stage: &Stage, input_hashes: BTreeMap<String, String>) -> KeyFields {
    KeyFields {
        ltcal_version: crate::VERSION.to_string(),
        code: crate::CODE_FINGERPRINT.to_string(),
        kind: stage.config.kind().to_string(),
        params: stage.config.to_json(),
        inputs: input_hashes,
        file: stage.file_hash.clone(),
    }
}

/// Why a stage (at a sweep point) would run, given its key and the store.
pub fn reason(store: &Store, stage: &str, point: Option<usize>, key: &KeyFields) -> String {
    match store.last(stage, point) {
        None => "never run".to_string(),
        Some(old) if old == *key => "its cached result is missing".to_string(),
        Some(old) => {
            let d = key.diff(&old);
            // A change of the code is no setting the user changed: said
            // first, in its own words (`diff` puts it first).
            match (key.code_change(&old), d.split_first()) {
                (_, None) => "its cached result is missing".to_string(),
                (Some(code), Some((_, []))) => code,
                (Some(code), Some((_, rest))) => {
                    format!("{code}; changed: {}", rest.join("; "))
                }
                (None, Some(_)) => format!("changed: {}", d.join("; ")),
            }
        }
    }
}

/// What `ltcal plan` reports for one stage.
#[derive(Clone, Debug, Serialize)]
pub struct PlanItem {
    pub stage: String,
    pub kind: String,
    /// [`Status::Cached`] or [`Status::Run`].
    pub status: Status,
    pub reason: String,
    /// The cache key, when every input's content is known.
    pub key: Option<String>,
}

/// One stage assessed against the store: its plan item, and what is known
/// of its key.
#[derive(Clone, Debug)]
pub struct Assessment {
    pub item: PlanItem,
    /// The key fields, with the inputs whose content is known (all of them
    /// when `pending` is empty).
    pub fields: KeyFields,
    /// Slot → the stage that must run before the slot's content is known.
    pub pending: BTreeMap<String, String>,
}

/// The plan of a pipeline against its store, in execution order.
pub fn plan(p: &Pipeline, store: &Store) -> Vec<PlanItem> {
    assess(p, store).into_iter().map(|a| a.item).collect()
}

/// Every stage assessed against the store, in execution order. A sweep's
/// per-point stages are assessed at every point and reported once each
/// (cached when every point has it), then the stages after the sweep.
pub fn assess(p: &Pipeline, store: &Store) -> Vec<Assessment> {
    match &p.sweep {
        None => assess_stages(&p.stages, store, BTreeMap::new(), None),
        Some(sw) => assess_sweep(p, sw, store),
    }
}

/// Stage → table → content hash, for stages known to be cached.
type Known = BTreeMap<String, BTreeMap<String, String>>;

fn assess_sweep(p: &Pipeline, sw: &Sweep, store: &Store) -> Vec<Assessment> {
    // Per per-point stage, by name (an axis over a stage's inputs can order
    // the stages of one point differently from another's): its assessment
    // at the first point, and how many points would run it, with the first.
    let mut out: Vec<(Assessment, usize, Option<String>)> = Vec::new();
    let mut gathering = Some(sw.gatherers());
    assess_points(sw, store, |index, assessed| {
        for a in &assessed {
            let stale = a.item.status != Status::Cached;
            match out
                .iter_mut()
                .find(|(x, _, _)| x.item.stage == a.item.stage)
            {
                Some((_, n, first)) => {
                    *n += usize::from(stale);
                    if stale && first.is_none() {
                        *first = Some(a.item.reason.clone());
                    }
                }
                None => out.push((
                    a.clone(),
                    usize::from(stale),
                    stale.then(|| a.item.reason.clone()),
                )),
            }
        }
        if let Some(gs) = gathering.as_mut() {
            if gather_point(sw, store, index, &assessed, gs).is_none() {
                gathering = None;
            }
        }
    });
    let out: Vec<Assessment> = out
        .into_iter()
        .map(|(mut a, n, first)| {
            a.item.key = None;
            if let Some(first) = first {
                a.item.status = Status::Run;
                a.item.reason = format!(
                    "{n} of {} sweep points would run it (first: {first})",
                    sw.len()
                );
            }
            a
        })
        .collect();
    let mut known = Known::new();
    if let Some(gs) = gathering {
        if let Some(h) = gathered_hashes(sw, gs) {
            known.insert(PSEUDO_STAGE.to_string(), h);
        }
    }
    let after: Vec<Stage> = p
        .stages
        .iter()
        .filter(|s| sw.after.contains(&s.name))
        .cloned()
        .collect();
    let mut all = out;
    all.extend(assess_stages(&after, store, known, None));
    all
}

/// The content hashes the gathered tables would have now: `None` unless
/// every point is cached.
pub fn gathered_now(sw: &Sweep, store: &Store) -> Option<BTreeMap<String, String>> {
    let mut gathering = Some(sw.gatherers());
    assess_points(sw, store, |index, assessed| {
        if let Some(gs) = gathering.as_mut() {
            if gather_point(sw, store, index, &assessed, gs).is_none() {
                gathering = None;
            }
        }
    });
    gathered_hashes(sw, gathering?)
}

/// Adds a wholly cached point's gathered tables; `None` when the point is
/// not wholly cached or a table cannot be read.
fn gather_point(
    sw: &Sweep,
    store: &Store,
    index: usize,
    assessed: &[Assessment],
    gs: &mut [Gatherer],
) -> Option<()> {
    if assessed.iter().any(|a| a.item.status != Status::Cached) {
        return None;
    }
    for (g, gatherer) in sw.gather.iter().zip(gs) {
        let a = assessed.iter().find(|a| a.item.stage == g.stage)?;
        // One read of the entry, every table verified.
        let entry = store.read(a.item.key.as_ref()?)?.ok()?;
        let df = table::from_parquet_bytes(entry.tables.get(&g.table)?).ok()?;
        gatherer.push(index, &df).ok()?;
    }
    Some(())
}

fn gathered_hashes(sw: &Sweep, gs: Vec<Gatherer>) -> Option<BTreeMap<String, String>> {
    let mut out = BTreeMap::new();
    for (g, gatherer) in sw.gather.iter().zip(gs) {
        let (_, bytes) = gatherer.finish().ok()?;
        out.insert(g.to_string(), cache::hash_bytes(&bytes));
    }
    Some(out)
}

/// Points assessed at once.
const CHUNK: usize = 256;

/// Assesses every point of the sweep, a chunk of points in parallel,
/// handing each point's assessments to `f` in point order (nothing is held
/// for all points at once).
pub fn assess_points(sw: &Sweep, store: &Store, mut f: impl FnMut(usize, Vec<Assessment>)) {
    let all: Vec<usize> = (0..sw.len()).collect();
    for part in all.chunks(CHUNK) {
        let assessed: Vec<Vec<Assessment>> = part
            .par_iter()
            .map(|&i| assess_stages(&sw.point(i).stages, store, BTreeMap::new(), Some(i)))
            .collect();
        for (&i, a) in part.iter().zip(assessed) {
            f(i, a);
        }
    }
}

fn assess_stages(
    stages: &[Stage],
    store: &Store,
    mut known: Known,
    point: Option<usize>,
) -> Vec<Assessment> {
    let graph = Graph::of(stages);
    let mut out = Vec::new();
    for i in graph.order() {
        let s = &stages[i];
        let mut hashes = BTreeMap::new();
        let mut pending = BTreeMap::new();
        for (slot, r) in s.wired_tables() {
            match known.get(r.stage.as_str()).and_then(|t| t.get(&r.table)) {
                Some(h) => {
                    hashes.insert(slot, h.clone());
                }
                None => {
                    pending.insert(slot, r.stage.clone());
                }
            }
        }
        let fields = key_fields(s, hashes);
        let (status, reason, key) = if !pending.is_empty() {
            // New code reruns the stage whatever its inputs turn out to be:
            // the root cause, rather than the stage it waits for.
            let code = store
                .last(&s.name, point)
                .and_then(|old| fields.code_change(&old));
            let reason = code.unwrap_or_else(|| {
                let stages: BTreeSet<String> = pending.values().map(|s| format!("`{s}`")).collect();
                let stages: Vec<String> = stages.into_iter().collect();
                format!("its input stage {} will run", stages.join(", "))
            });
            (Status::Run, reason, None)
        } else {
            let key = fields.hash();
            // A sweep point's entries on their manifests (as the run takes
            // them); another stage's read whole.
            let found = match point {
                Some(_) => store.manifest(&key),
                None => store.check(&key),
            };
            let (status, reason) = match found {
                Some(Ok(m)) => {
                    known.insert(
                        s.name.clone(),
                        m.tables
                            .iter()
                            .map(|t| (t.name.clone(), t.hash.clone()))
                            .collect(),
                    );
                    (Status::Cached, String::new())
                }
                Some(Err(why)) => (Status::Run, format!("its cached result is corrupt: {why}")),
                None => (Status::Run, reason(store, &s.name, point, &fields)),
            };
            (status, reason, Some(key))
        };
        out.push(Assessment {
            item: PlanItem {
                stage: s.name.clone(),
                kind: s.config.kind().to_string(),
                status,
                reason,
                key,
            },
            fields,
            pending,
        });
    }
    out
}
