//! The tables `ltcal run` publishes under `results/<pipeline>/<stage>/`
//! (and `results/<pipeline>/sweep/`; an experiment's under its folder,
//! `results/<pipeline>/runs/<name>/`), read back with the one check that says
//! whether a published table is the current result: its bytes must hash to
//! the table of the cache entry the plan would use now. An edited or damaged
//! file is refused; a result from an earlier run is returned with the reason
//! it is stale, for the caller to say so. The file is read as every file ltcal
//! did not just write is ([`crate::fs::read_regular_file`]): a FIFO, a device
//! or a link in its place is refused, not waited on or read without end.

use super::cache::{self, Store};
use super::error::InputError;
use super::resolve::Pipeline;
use super::status::Status;
use super::{plan, sweep};
use anyhow::{Result, bail};
use std::path::{Path, PathBuf};

/// A published table, checked.
pub struct Published {
    pub path: PathBuf,
    /// The Parquet file as published.
    pub bytes: Vec<u8>,
    /// Why this is not the current result (a stage or sweep point would run
    /// again); `None` when it is.
    pub stale: Option<String>,
}

/// Reads the table `name` (the stage's first when `None`) that `stage`
/// published in `dir`; `rerun` is the command that brings it up to date, for
/// messages.
pub fn read(
    pipeline: &Pipeline,
    store: &Store,
    dir: &Path,
    stage: &str,
    name: Option<&str>,
    rerun: &str,
) -> Result<Published> {
    // What the published file must hash to if it is the current result,
    // or why there is no current result.
    let (path, expected): (PathBuf, Result<String, String>) = match (&pipeline.sweep, stage) {
        (Some(sw), sweep::PSEUDO_STAGE) => {
            let names = sw.table_names();
            let Some(name) = name.filter(|n| names.iter().any(|g| g == n)) else {
                return Err(InputError::arg(format!(
                    "the sweep gathers {}: show one as `sweep.<stage>.<table>`{}",
                    names.join(", "),
                    name.map(|n| crate::suggest::hint(n, names.iter().map(String::as_str)))
                        .unwrap_or_default()
                )));
            };
            let expected = plan::gathered_now(sw, store)
                .and_then(|mut h| h.remove(name))
                .ok_or_else(|| "some sweep points would run again".to_string());
            (dir.join(stage).join(format!("{name}.parquet")), expected)
        }
        (sw, _) => {
            let s = pipeline.stage(stage)?;
            if let Some(sw) = sw.as_ref().filter(|sw| !sw.after.contains(&s.name)) {
                return Err(InputError::arg(format!(
                    "`{stage}` runs at every sweep point, and a point's tables are not published \
                     one by one; the sweep gathers {} (show one as `sweep.<stage>.<table>`; \
                     [sweep] gather chooses which)",
                    sw.table_names().join(", ")
                )));
            }
            let outputs = s.config.outputs();
            let name = name.unwrap_or(outputs[0]);
            if !outputs.contains(&name) {
                return Err(InputError::arg(format!(
                    "stage `{stage}` has no table `{name}`; its tables are: {}{}",
                    outputs.join(", "),
                    crate::suggest::hint(name, outputs.iter().copied())
                )));
            }
            let item = plan::plan(pipeline, store)
                .into_iter()
                .find(|i| i.stage == stage)
                .expect("every stage is planned");
            let manifest = item.key.as_deref().and_then(|k| store.check(k));
            let expected = match (item.status, manifest) {
                (Status::Cached, Some(Ok(m))) => m
                    .tables
                    .into_iter()
                    .find(|t| t.name == name)
                    .map(|t| t.hash)
                    .ok_or_else(|| format!("`{stage}` would run again")),
                _ => Err(format!("`{stage}` would run again ({})", item.reason)),
            };
            (dir.join(stage).join(format!("{name}.parquet")), expected)
        }
    };
    let bytes = match crate::fs::read_regular_file(&path, cache::MAX_TABLE_BYTES) {
        Ok(b) => b,
        Err(e) if e.is_missing() => {
            bail!(
                "no result yet ({} does not exist): run {rerun} first",
                path.display()
            )
        }
        Err(e) => bail!("{e}: {rerun} restores it"),
    };
    let stale = match expected {
        Ok(hash) if hash != cache::hash_bytes(&bytes) => bail!(
            "{} differs from the result it was published from (edited or damaged): \
             {rerun} restores it",
            path.display()
        ),
        Ok(_) => None,
        Err(why) => Some(why),
    };
    Ok(Published { path, bytes, stale })
}
