//! `ltcal run <pipeline> <stage>… --force <stage>`: which stages a run may
//! compute, and which it computes even when cached.
//!
//! A target needs its ancestors (their tables are its inputs); nothing
//! else is computed. The other stages are still looked up: a cached one is
//! served and published as in any run (so a partial run leaves the page
//! and the other stages' tables as they were, and reports them `cached`,
//! which they are), one that would have to run is reported `skipped`,
//! saying so — never `ran`. A forced stage is computed without looking at
//! the cache, and so is every stage after it among those the run computes:
//! "recompute this" means its consequences too.
//!
//! A sweep's per-point stages go together: an axis may rewire a point's
//! inputs, so a target that needs one of them needs all of them.

use super::error::InputError;
use super::resolve::Pipeline;
use super::sweep::PSEUDO_STAGE;
use std::collections::BTreeSet;

/// What a run computes.
#[derive(Clone, Debug, Default)]
pub struct Selection {
    /// The stages it may compute (targets and their ancestors); `None`:
    /// every stage.
    pub only: Option<BTreeSet<String>>,
    /// The stages it computes even when cached.
    pub force: BTreeSet<String>,
}

impl Selection {
    /// The selection of `targets` (none: every stage) with `force`d stages,
    /// each a stage of `p` (an unknown name is the user's mistake, with the
    /// nearest stage suggested); a forced stage must be among those run.
    pub fn new(p: &Pipeline, targets: &[String], force: &[String]) -> anyhow::Result<Selection> {
        let names: Vec<&str> = p.stages.iter().map(|s| s.name.as_str()).collect();
        let mut problems = Vec::new();
        for (what, name) in targets
            .iter()
            .map(|t| ("stage", t))
            .chain(force.iter().map(|f| ("--force", f)))
        {
            if !names.contains(&name.as_str()) {
                problems.push(format!(
                    "{what} `{name}`: no such stage in pipeline `{}`{}",
                    p.name,
                    crate::suggest::hint(name, names.iter().copied())
                ));
            }
        }
        if !problems.is_empty() {
            return Err(InputError::arg(problems.join("\n")));
        }
        let only = (!targets.is_empty()).then(|| closure(p, targets, Direction::Up));
        if let Some(only) = &only {
            if let Some(f) = force.iter().find(|f| !only.contains(*f)) {
                return Err(InputError::arg(format!(
                    "--force `{f}`: not among the stages this run computes (the targets and \
                     what they need); add it as a target"
                )));
            }
        }
        let mut forced = closure(p, force, Direction::Down);
        if let Some(only) = &only {
            forced.retain(|s| only.contains(s));
        }
        Ok(Selection {
            only,
            force: forced,
        })
    }

    /// Whether the run may compute `stage`.
    pub fn computes(&self, stage: &str) -> bool {
        self.only.as_ref().is_none_or(|o| o.contains(stage))
    }
}

#[derive(Clone, Copy, PartialEq)]
enum Direction {
    /// Toward the inputs: what the stages need.
    Up,
    /// Toward the readers: what depends on the stages.
    Down,
}

/// `from` and every stage reached from it in `dir`.
fn closure(p: &Pipeline, from: &[String], dir: Direction) -> BTreeSet<String> {
    let per_point: BTreeSet<&str> = p
        .sweep
        .iter()
        .flat_map(|sw| {
            p.stages
                .iter()
                .filter(|s| !sw.after.contains(&s.name))
                .map(|s| s.name.as_str())
        })
        .collect();
    // Edges producer → reader; a gathered table's producer is every
    // per-point stage.
    let edges: Vec<(&str, &str)> = p
        .stages
        .iter()
        .flat_map(|s| {
            s.wired_tables()
                .into_iter()
                .flat_map(|(_, r)| {
                    if r.stage == PSEUDO_STAGE {
                        per_point.iter().copied().collect::<Vec<_>>()
                    } else {
                        p.stages
                            .iter()
                            .find(|x| x.name == r.stage)
                            .map(|x| x.name.as_str())
                            .into_iter()
                            .collect()
                    }
                })
                .map(move |producer| (producer, s.name.as_str()))
        })
        .collect();
    let mut set: BTreeSet<String> = from.iter().cloned().collect();
    loop {
        let before = set.len();
        if dir == Direction::Up && set.iter().any(|s| per_point.contains(s.as_str())) {
            set.extend(per_point.iter().map(|s| s.to_string()));
        }
        for &(producer, reader) in &edges {
            let (have, add) = match dir {
                Direction::Up => (reader, producer),
                Direction::Down => (producer, reader),
            };
            if set.contains(have) {
                set.insert(add.to_string());
            }
        }
        if set.len() == before {
            return set;
        }
    }
}
