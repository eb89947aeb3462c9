//! Experiments: runs with `--set`. A run that overrides a stage's setting
//! computes something the pipeline file does not say, so it must not
//! replace the pipeline's results (committed, cited, compared with): it
//! publishes to a folder of its own, `results/<pipeline>/runs/<name>/`,
//! named by `--name` or by a hash of its overrides (the same overrides, the
//! same folder), with the overrides recorded beside the tables
//! (`overrides.toml`), so that `--name` alone brings the experiment back.
//! The cache is shared: switching between the main results and an
//! experiment computes nothing twice.
//!
//! Overrides of `executor.*` (where the points run) change nothing
//! computed: they make no experiment, and are not part of one.

use super::cache;
use super::error::InputError;
use super::overrides::Override;
use anyhow::{Context as _, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

pub use super::names::EXPERIMENTS_DIR as DIR;

/// The file of an experiment's folder that records its overrides.
pub const OVERRIDES_FILE: &str = "overrides.toml";

/// The largest `overrides.toml` read: a few lines in practice.
const MAX_OVERRIDES_BYTES: u64 = 1 << 20;

/// The largest `run.json` read to list an experiment: a sweep's lists its
/// failed points, one short record each.
const MAX_RUN_JSON_BYTES: u64 = 256 << 20;

/// An experiment: its name and its stage overrides as typed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Experiment {
    pub name: String,
    /// The `--set` arguments that override stage settings, as typed.
    pub overrides: Vec<String>,
}

/// What `overrides.toml` holds.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Recorded {
    set: Vec<String>,
}

/// Whether an override changes what a stage computes (`stages.…`), rather
/// than where it runs (`executor.…`).
fn is_stage_override(o: &Override) -> bool {
    o.path.first().is_some_and(|s| s == "stages")
}

/// Checks an experiment's name given with `--name`: it names a folder.
pub fn check_name(name: &str) -> Result<()> {
    let ok = super::raw::valid_name(name) && name.starts_with(|c: char| c.is_ascii_alphanumeric());
    if ok {
        Ok(())
    } else {
        Err(InputError::arg(format!(
            "--name {name:?}: an experiment's name starts with a letter or digit and has at most \
             64 letters, digits, `_` and `-` (it names the folder results/<pipeline>/{DIR}/<name>/)"
        )))
    }
}

/// The name of the experiment of `overrides` when none is given:
/// `set-<hash>`, the same for the same overrides in any order (unless the
/// order matters: one path inside another's value).
pub fn hash_name(overrides: &[Override]) -> String {
    let mut parts: Vec<(Vec<String>, String)> = overrides
        .iter()
        .filter(|o| is_stage_override(o))
        .map(|o| (o.path.clone(), o.value.to_string()))
        .collect();
    let nested = parts.iter().enumerate().any(|(i, (a, _))| {
        parts
            .iter()
            .enumerate()
            .any(|(j, (b, _))| i != j && b.starts_with(a))
    });
    if !nested {
        parts.sort();
    }
    let canonical = serde_json::to_vec(&parts).expect("strings serialize");
    format!("set-{}", cache::short(&cache::hash_bytes(&canonical)))
}

/// The folder of the experiment `name` of the pipeline results `dir`.
pub fn folder(pipeline_dir: &Path, name: &str) -> PathBuf {
    pipeline_dir.join(DIR).join(name)
}

/// Which results a command is about, from `--name` and `--set`: the
/// pipeline's main results (`None`: no stage override, no name), or an
/// experiment — named, or named by its overrides' hash. `--name` without
/// stage overrides is the recorded experiment of that name. Returns the
/// experiment and every override to resolve the pipeline with.
pub fn target(
    pipeline_dir: &Path,
    name: Option<&str>,
    overrides: &[Override],
) -> Result<(Option<Experiment>, Vec<Override>)> {
    if let Some(n) = name {
        check_name(n)?;
    }
    let stage: Vec<&Override> = overrides.iter().filter(|o| is_stage_override(o)).collect();
    let texts = |os: &[&Override]| os.iter().map(|o| o.text.clone()).collect::<Vec<_>>();
    match (name, stage.is_empty()) {
        (None, true) => Ok((None, overrides.to_vec())),
        (None, false) => Ok((
            Some(Experiment {
                name: hash_name(overrides),
                overrides: texts(&stage),
            }),
            overrides.to_vec(),
        )),
        (Some(n), false) => Ok((
            Some(Experiment {
                name: n.to_string(),
                overrides: texts(&stage),
            }),
            overrides.to_vec(),
        )),
        (Some(n), true) => {
            let dir = folder(pipeline_dir, n);
            let Some(recorded) = recorded(&dir)? else {
                return Err(InputError::arg(format!(
                    "--name {n}: no experiment of that name ({} does not exist); start one with \
                     --set, or list them with `ltcal runs`",
                    dir.join(OVERRIDES_FILE).display()
                )));
            };
            let mut all = Vec::new();
            for text in &recorded {
                all.push(Override::parse(text).map_err(|e| {
                    InputError::arg(format!("{}: {e}", dir.join(OVERRIDES_FILE).display()))
                })?);
            }
            // Where it runs is the command line's to say.
            all.extend(overrides.iter().cloned());
            Ok((
                Some(Experiment {
                    name: n.to_string(),
                    overrides: recorded,
                }),
                all,
            ))
        }
    }
}

/// The overrides recorded in the experiment folder `dir`; `None` when it
/// has none (no such experiment).
pub fn recorded(dir: &Path) -> Result<Option<Vec<String>>> {
    let path = dir.join(OVERRIDES_FILE);
    let bytes = match crate::fs::read_regular_file(&path, MAX_OVERRIDES_BYTES) {
        Ok(b) => b,
        Err(e) if e.is_missing() => return Ok(None),
        Err(e) => return Err(InputError::arg(e.to_string())),
    };
    let text = String::from_utf8(bytes)
        .map_err(|_| InputError::arg(format!("{}: not UTF-8 text", path.display())))?;
    let r: Recorded =
        toml::from_str(&text).map_err(|e| InputError::arg(format!("{}: {e}", path.display())))?;
    Ok(Some(r.set))
}

/// Whether two lists of overrides (as typed) are the same experiment:
/// the same overrides, in any order that cannot matter.
fn equivalent(a: &[String], b: &[String]) -> bool {
    let parse = |v: &[String]| -> Option<Vec<Override>> {
        v.iter().map(|t| Override::parse(t).ok()).collect()
    };
    match (parse(a), parse(b)) {
        (Some(x), Some(y)) => hash_name(&x) == hash_name(&y),
        _ => a == b,
    }
}

/// For a command that looks at the experiment `e` rather than running it:
/// refuses overrides other than those its folder records (its tables were
/// computed with those), exit 2.
pub fn check_recorded(pipeline_dir: &Path, e: &Experiment) -> Result<()> {
    match recorded(&folder(pipeline_dir, &e.name))? {
        Some(r) if !equivalent(&r, &e.overrides) => Err(InputError::arg(format!(
            "--name {}: the experiment was run with {}, not these overrides; leave out --set to \
             look at it (a run with --name and --set replaces it)",
            e.name,
            set_args(&r)
        ))),
        _ => Ok(()),
    }
}

/// Writes the experiment's `overrides.toml` in its folder `dir` (before
/// it runs, so that a killed run's folder still says what it is), unless
/// it records the same overrides already. Returns the experiment as
/// recorded (the recorded order of the same overrides kept), and the
/// overrides recorded before when they differ (the name was given to other
/// overrides).
pub fn record(dir: &Path, e: &Experiment) -> Result<(Experiment, Option<Vec<String>>)> {
    let before = recorded(dir).ok().flatten();
    if let Some(b) = before.as_ref().filter(|b| equivalent(b, &e.overrides)) {
        let kept = Experiment {
            name: e.name.clone(),
            overrides: b.clone(),
        };
        return Ok((kept, None));
    }
    let body = toml::to_string(&Recorded {
        set: e.overrides.clone(),
    })
    .context("writing the overrides as TOML")?;
    let text = format!(
        "# The overrides of the experiment `{}`: `ltcal run <pipeline> --name {}` runs it again.\n{body}",
        e.name, e.name
    );
    crate::fs::write_atomic(&dir.join(OVERRIDES_FILE), text.as_bytes())?;
    Ok((e.clone(), before))
}

/// One experiment as `ltcal runs` lists it.
#[derive(Clone, Debug, Serialize)]
pub struct Listed {
    pub name: String,
    pub overrides: Vec<String>,
    /// When its last run finished (`run.json`); `None` if it never did.
    pub finished: Option<String>,
    /// `ok`, `failed` (a stage failed or was skipped), `not finished`
    /// (killed or running: no `run.json` of these overrides), or `damaged`
    /// (its `overrides.toml` cannot be read: `problem` says why).
    pub status: String,
    pub problem: Option<String>,
}

/// The part of a `run.json` a listing reads.
#[derive(Deserialize)]
struct RunSummary {
    finished: String,
    stages: Vec<StageSummary>,
    experiment: Option<Experiment>,
}

#[derive(Deserialize)]
struct StageSummary {
    status: String,
}

/// The names of the experiment folders of the pipeline results
/// `pipeline_dir`, sorted.
pub fn names(pipeline_dir: &Path) -> Vec<String> {
    let Ok(rd) = std::fs::read_dir(pipeline_dir.join(DIR)) else {
        return Vec::new();
    };
    let mut names: Vec<String> = rd
        .flatten()
        .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
        .map(|e| e.file_name().to_string_lossy().into_owned())
        // Temporary folders and the like: no experiment's name.
        .filter(|n| !n.starts_with('.'))
        .collect();
    names.sort();
    names
}

/// The experiments of the pipeline results `pipeline_dir`, by name.
pub fn list(pipeline_dir: &Path) -> Vec<Listed> {
    names(pipeline_dir)
        .into_iter()
        .map(|name| {
            let dir = folder(pipeline_dir, &name);
            let overrides = match recorded(&dir) {
                Ok(Some(o)) => o,
                Ok(None) => {
                    return damaged(name, format!("no {OVERRIDES_FILE}"));
                }
                Err(e) => return damaged(name, format!("{e:#}")),
            };
            let run: Option<RunSummary> =
                crate::fs::read_regular_file(&dir.join("run.json"), MAX_RUN_JSON_BYTES)
                    .ok()
                    .and_then(|b| serde_json::from_slice(&b).ok());
            // A run.json of other overrides is an earlier definition's.
            let run =
                run.filter(|r| r.experiment.as_ref().map(|e| &e.overrides) == Some(&overrides));
            let (finished, status) = match run {
                None => (None, "not finished".to_string()),
                Some(r) => {
                    let ok = r
                        .stages
                        .iter()
                        .all(|s| s.status == "ran" || s.status == "cached");
                    (
                        Some(r.finished),
                        if ok { "ok" } else { "failed" }.to_string(),
                    )
                }
            };
            Listed {
                name,
                overrides,
                finished,
                status,
                problem: None,
            }
        })
        .collect()
}

fn damaged(name: String, why: String) -> Listed {
    Listed {
        name,
        overrides: Vec::new(),
        finished: None,
        status: "damaged".to_string(),
        problem: Some(why),
    }
}

/// `--set <text>` for each override, quoted for a POSIX shell where
/// needed: the part of the command line that runs the experiment again.
pub fn set_args(overrides: &[String]) -> String {
    overrides
        .iter()
        .map(|o| format!("--set {}", shell_quote(o)))
        .collect::<Vec<_>>()
        .join(" ")
}

fn shell_quote(s: &str) -> String {
    let plain = !s.is_empty()
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || "_-.=/:,+@%".contains(c));
    if plain {
        s.to_string()
    } else {
        format!("'{}'", s.replace('\'', r"'\''"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sets(args: &[&str]) -> Vec<Override> {
        args.iter().map(|a| Override::parse(a).unwrap()).collect()
    }

    #[test]
    fn the_same_overrides_in_any_order_name_the_same_experiment() {
        let a = hash_name(&sets(&["stages.m.seed=2", "stages.i.max_iters=50"]));
        let b = hash_name(&sets(&["stages.i.max_iters = 50", "stages.m.seed=2"]));
        assert_eq!(a, b);
        assert!(a.starts_with("set-") && a.len() == 16, "{a}");
        assert_ne!(
            a,
            hash_name(&sets(&["stages.m.seed=3", "stages.i.max_iters=50"]))
        );
        // Where it runs is not part of it.
        assert_eq!(
            hash_name(&sets(&["stages.m.seed=2", "executor.slurm.partition=x"])),
            hash_name(&sets(&["stages.m.seed=2"]))
        );
        // One path inside another's value: the order matters, and counts.
        let x = hash_name(&sets(&["stages.m.x={step=1}", "stages.m.x.step=2"]));
        let y = hash_name(&sets(&["stages.m.x.step=2", "stages.m.x={step=1}"]));
        assert_ne!(x, y);
    }

    #[test]
    fn an_experiment_name_must_be_a_plain_folder_name() {
        for bad in ["", "..", "a/b", "-x", "_x", "a b", "é", &"x".repeat(65)] {
            assert!(check_name(bad).is_err(), "{bad:?}");
        }
        for good in ["seed2", "A-1_b", &"x".repeat(64)] {
            assert!(check_name(good).is_ok(), "{good:?}");
        }
    }

    #[test]
    fn executor_overrides_alone_are_no_experiment() {
        let dir = tempfile::tempdir().unwrap();
        let (e, all) = target(dir.path(), None, &sets(&["executor.slurm.partition=x"])).unwrap();
        assert!(e.is_none());
        assert_eq!(all.len(), 1);
    }

    #[test]
    fn recorded_overrides_round_trip_and_shell_quote() {
        let dir = tempfile::tempdir().unwrap();
        let e = Experiment {
            name: "x".into(),
            overrides: vec!["stages.a.path='it''s here'".into(), "stages.a.n=3".into()],
        };
        assert_eq!(record(dir.path(), &e).unwrap(), (e.clone(), None));
        assert_eq!(recorded(dir.path()).unwrap(), Some(e.overrides.clone()));
        // The same overrides in another order: the record is kept.
        let swapped = Experiment {
            name: "x".into(),
            overrides: e.overrides.iter().rev().cloned().collect(),
        };
        assert_eq!(record(dir.path(), &swapped).unwrap(), (e.clone(), None));
        // Others: recorded, and the earlier ones returned.
        let other = Experiment {
            name: "x".into(),
            overrides: vec!["stages.a.n=4".into()],
        };
        assert_eq!(
            record(dir.path(), &other).unwrap(),
            (other.clone(), Some(e.overrides.clone()))
        );
        assert_eq!(
            set_args(&e.overrides),
            r"--set 'stages.a.path='\''it'\'''\''s here'\''' --set stages.a.n=3"
        );
    }
}
