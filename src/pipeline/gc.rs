//! `ltcal gc`: the cache entries and packs nothing can reach any more,
//! found and removed.
//!
//! The cache only grows: a code change (a new [`crate::CODE_FINGERPRINT`])
//! or a changed setting gives every affected stage a new key, and the old
//! entries — a sweep's packs above all — stay. What is still *reachable* is
//! kept:
//!
//! - every key a current pipeline's plan finds cached ([`super::plan`]: the
//!   pipeline as the files now say, and each of its experiments with its
//!   recorded overrides), at every sweep point — so a rerun after `gc` is
//!   as cached as before it;
//! - every key a recorded run names: the "last run" records of the main
//!   results and of every experiment, the packs' latest record of each
//!   sweep point's stages, and the stages of every `run.json` — so
//!   `explain` and `show` of a recorded run keep what they compare with.
//!
//! A pack is removed when none of its entries is reachable; a pack with
//! some reachable entries is kept whole (a pack is never edited) and
//! counted. A pack whose index cannot be read is left to `ltcal verify
//! --repair`. Removal is one step per thing ([`Store::remove_entry`]: a
//! rename out of the key, then deletion; [`Store::remove_pack`]: one
//! unlink), so a killed `gc` never leaves a half-removed entry under its
//! key: what a reader finds is whole or absent, and an absent entry is
//! computed again.

use super::cache::{self, Store};
use super::plan;
use super::resolve::Pipeline;
use super::status::Status;
use anyhow::Result;
use std::collections::HashSet;
use std::path::{Path, PathBuf};

/// One thing `gc` removes (or would remove).
#[derive(Clone, Debug)]
pub struct Item {
    pub path: PathBuf,
    /// `entry <key> of `<stage>`` or `pack (<n> entries)`.
    pub what: String,
    pub bytes: u64,
}

/// What `gc` found in one pipeline's cache.
#[derive(Clone, Debug, Default)]
pub struct Collected {
    /// Unreachable loose entries and wholly unreachable packs.
    pub removed: Vec<Item>,
    /// Kept: loose entries, packs, and their bytes.
    pub kept_entries: usize,
    pub kept_packs: usize,
    pub kept_bytes: u64,
    /// Kept packs some of whose entries are unreachable: (pack, unreachable
    /// entries, entries).
    pub partly: Vec<(PathBuf, usize, usize)>,
    /// Packs whose index cannot be read, left alone, and why.
    pub unreadable: Vec<(PathBuf, String)>,
}

impl Collected {
    pub fn freed(&self) -> u64 {
        self.removed.iter().map(|i| i.bytes).sum()
    }
}

/// The keys reachable in the cache of the folder `pipeline_dir`: from
/// `pipelines` (the pipeline and its experiments, resolved) through their
/// plans, and from every recorded run.
pub fn reachable(pipelines: &[Pipeline], store: &Store, pipeline_dir: &Path) -> HashSet<String> {
    let mut keys = store.recorded_keys();
    let mut cached = |a: &plan::Assessment| {
        if a.item.status == Status::Cached {
            keys.extend(a.item.key.clone());
        }
    };
    for p in pipelines {
        // A sweep's per-point stages are assessed (and keyed) per point;
        // `assess` gives the stages after the sweep their keys.
        plan::assess(p, store).iter().for_each(&mut cached);
        if let Some(sw) = &p.sweep {
            plan::assess_points(sw, store, |_, assessed| {
                assessed.iter().for_each(&mut cached)
            });
        }
    }
    let mut runs = vec![pipeline_dir.join("run.json")];
    runs.extend(
        super::experiment::names(pipeline_dir)
            .iter()
            .map(|n| super::experiment::folder(pipeline_dir, n).join("run.json")),
    );
    for path in runs {
        keys.extend(run_keys(&path));
    }
    keys
}

/// The stage keys a `run.json` records (none when it cannot be read).
fn run_keys(path: &Path) -> Vec<String> {
    let Ok(bytes) = crate::fs::read_regular_file(path, cache::MAX_MANIFEST_BYTES) else {
        return Vec::new();
    };
    let Ok(v) = serde_json::from_slice::<serde_json::Value>(&bytes) else {
        return Vec::new();
    };
    v["stages"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|s| s["key"].as_str().map(str::to_string))
        .collect()
}

/// Finds what `reachable` does not hold and, unless `dry_run`, removes it.
pub fn collect(store: &Store, reachable: &HashSet<String>, dry_run: bool) -> Result<Collected> {
    let mut c = Collected::default();
    for (key, dir) in store.loose_entries() {
        let bytes = folder_bytes(&dir);
        if reachable.contains(&key) {
            c.kept_entries += 1;
            c.kept_bytes += bytes;
            continue;
        }
        let stage = store.manifest(&key).and_then(Result::ok).map_or_else(
            || "an unreadable entry".to_string(),
            |m| format!("`{}`", m.stage),
        );
        if !dry_run {
            store.remove_entry(&dir)?;
        }
        c.removed.push(Item {
            path: dir,
            what: format!("entry {} of {stage}", cache::short(&key)),
            bytes,
        });
    }
    for (path, keys) in store.pack_files() {
        let bytes = std::fs::symlink_metadata(&path).map_or(0, |m| m.len());
        let keys = match keys {
            Ok(k) => k,
            Err(why) => {
                c.unreadable.push((path, format!("{why:#}")));
                continue;
            }
        };
        let unreachable = keys.iter().filter(|k| !reachable.contains(*k)).count();
        if unreachable < keys.len() {
            c.kept_packs += 1;
            c.kept_bytes += bytes;
            if unreachable > 0 {
                c.partly.push((path, unreachable, keys.len()));
            }
            continue;
        }
        if !dry_run {
            store.remove_pack(&path)?;
        }
        c.removed.push(Item {
            path,
            what: format!(
                "pack ({} entr{})",
                keys.len(),
                if keys.len() == 1 { "y" } else { "ies" }
            ),
            bytes,
        });
    }
    Ok(c)
}

/// The bytes of the files of an entry folder (and of its `files/`).
fn folder_bytes(dir: &Path) -> u64 {
    let size = |d: &Path| -> u64 {
        std::fs::read_dir(d)
            .into_iter()
            .flatten()
            .flatten()
            .filter_map(|e| e.metadata().ok())
            .filter(|m| m.is_file())
            .map(|m| m.len())
            .sum()
    };
    size(dir) + size(&dir.join("files"))
}

/// Bytes for people: `812 B`, `4.2 KiB`, `1.3 MiB`, `2.0 GiB`.
pub fn human_bytes(b: u64) -> String {
    const UNITS: [&str; 4] = ["KiB", "MiB", "GiB", "TiB"];
    if b < 1024 {
        return format!("{b} B");
    }
    let mut v = b as f64 / 1024.0;
    let mut unit = 0;
    while v >= 1024.0 && unit + 1 < UNITS.len() {
        v /= 1024.0;
        unit += 1;
    }
    format!("{v:.1} {}", UNITS[unit])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bytes_are_written_for_people_in_binary_units() {
        assert_eq!(human_bytes(812), "812 B");
        assert_eq!(human_bytes(4300), "4.2 KiB");
        assert_eq!(human_bytes(3 << 30), "3.0 GiB");
    }
}
