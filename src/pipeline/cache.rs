//! The content-addressed stage cache under `results/<pipeline>/.ltcal/`.
//!
//! A stage's outputs are stored under the hash of its [`KeyFields`] — its
//! kind, its fully resolved settings, the content hashes of its input tables,
//! the ltcal version and the fingerprint of the code ([`crate::code`]). An entry is a directory holding the tables
//! (Parquet), the files (figures) and `manifest.json`, which records each
//! file's content hash and is written last. Entries are built in a temporary
//! directory and published with one `rename`, so a reader — this process,
//! another `ltcal run` on the same folder, or the next run after a SIGKILL —
//! sees a complete entry or none. On reuse every file is hashed again: a
//! truncated, flipped or edited file is reported and the entry recomputed.
//! A cached sweep point is taken on its manifests, and a table read from
//! it ([`Store::table`]) is hashed alone, against its manifest: what is
//! not read is not served.
//!
//! A sweep point's entries are not loose folders but go into **packs**
//! ([`super::pack`]): kept in memory ([`Store::put_packed`]) until the
//! runner writes them as one file ([`Store::flush`]), then found through the
//! packs' indexes, which every process reads (and a coordinator re-reads,
//! [`Store::refresh_packs`], to see what a cluster's tasks wrote). A packed
//! entry is verified as a loose one when read; a bad copy is passed over
//! (a pack is never edited) and the entry recomputed into a new pack. The
//! packs also record which stages ran at each point (what `explain`
//! compares with) and, for a cluster task, which failed and why.
//!
//! # Concurrency and killed runs
//!
//! There is no lock, by design. Two `ltcal run`s on one folder may compute
//! the same stage at once: each builds its entry in a private temporary
//! directory and renames it into place; the first rename wins, the second
//! finds the key taken, verifies the winner and drops its own copy. The key
//! hashes everything an output depends on and stages are deterministic, so
//! both copies are identical and losing the race costs only time. A run
//! looks each stage up just before it would compute it, so it reuses every
//! loose entry another run has finished by then; of packs, those written
//! before it first looked (a process reads the packs' indexes once, and a
//! coordinator again after its tasks ran). Two runs computing the same
//! sweep point write two packs holding identical copies; either serves.
//!
//! A lock would serialise runs for no gain in correctness, and a lock held
//! by a SIGKILLed process has to be recognised and broken — a guess about
//! another process on the path that decides what is served. Here a dead
//! process can neither block nor mislead a live one: its temporary
//! directories and files are never read, and the next run on the same
//! machine removes them once their process id is gone (a guess that can
//! only delay a clean-up; a temporary made on another machine is left to
//! the runs there). A key
//! directory without `manifest.json` cannot come from [`Store::put`]; if one
//! appears it is treated as incomplete, ignored and removed.
//!
//! # Hostile files and healing
//!
//! Every file of the cache is read through [`crate::fs::read_regular_file`]
//! (a pack through [`crate::fs::open_regular_file`]) with a bound of its
//! kind ([`MAX_MANIFEST_BYTES`], [`MAX_TABLE_BYTES`], [`MAX_FIGURE_BYTES`],
//! [`pack::MAX_PACK_BYTES`]): a FIFO, a device, a folder or a symbolic link
//! where a file of the cache should be is damage, reported like a flipped
//! byte — never waited on, read without end or followed out of the results
//! folder ([`crate::fs::confine`]).
//!
//! What [`Store::verify`] finds damaged, [`Store::heal`] takes out — what
//! `ltcal run` does at the end of every run and `ltcal verify --repair` on
//! demand: a damaged loose entry is removed, a pack that cannot be read is
//! removed (its points are recomputed by the next run), and a pack with
//! some damaged entries is written again without them (its good entries,
//! records and failures kept, under its old time, so records keep their
//! order) before the old one is removed. A bad entry is never served
//! meanwhile: it fails its hashes on every read. So one run after any
//! damage leaves a cache that `verify` passes. To cost a cached rerun
//! nothing, `run` re-reads only what changed since it was last found
//! good: `.ltcal/verified.json` records each entry's and pack's identity
//! (inode, size, modification and change times — a byte written, a
//! `chmod`, a file put in its place all change it); `verify` and
//! `verify --repair` read everything.

use super::pack::{self, Key, Span};
use crate::fs::{ReadError, StagedFolder, read_regular_file, temp_name, write_atomic};
use anyhow::{Context as _, Result, anyhow, bail};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap, HashSet};
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, RwLock};

/// The largest manifest (or last-run record) read: a stage's key fields and
/// the list of its tables and files, far below this.
pub const MAX_MANIFEST_BYTES: u64 = 64 << 20;
/// The largest table read (a cache entry's or a published one).
pub const MAX_TABLE_BYTES: u64 = 16 << 30;
/// The largest figure or other file of an entry read.
pub const MAX_FIGURE_BYTES: u64 = 4 << 30;

/// Everything a stage's output depends on. Its hash is the cache key.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct KeyFields {
    pub ltcal_version: String,
    /// [`crate::CODE_FINGERPRINT`] of the build that computed it. Records
    /// written before it existed read as empty: a change, and said so.
    #[serde(default)]
    pub code: String,
    pub kind: String,
    /// The fully resolved settings, as JSON (object keys sorted).
    pub params: serde_json::Value,
    /// Slot → content hash of the table wired to it.
    pub inputs: BTreeMap<String, String>,
    /// Content hash of the file or folder the stage reads
    /// ([`crate::stages::StageFile`]), when it reads one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file: Option<String>,
}

impl KeyFields {
    /// The key: blake3 of the canonical JSON (serde_json sorts object keys).
    pub fn hash(&self) -> String {
        let bytes = serde_json::to_vec(self).expect("key fields serialize");
        blake3::hash(&bytes).to_hex().to_string()
    }

    /// What differs from an earlier key, field by field, in words; a change
    /// of the code first.
    pub fn diff(&self, old: &KeyFields) -> Vec<String> {
        let mut out: Vec<String> = self.code_change(old).into_iter().collect();
        if self.ltcal_version != old.ltcal_version {
            out.push(format!(
                "ltcal version: {} → {}",
                old.ltcal_version, self.ltcal_version
            ));
        }
        if self.kind != old.kind {
            out.push(format!("kind: {} → {}", old.kind, self.kind));
        }
        json_diff("", &old.params, &self.params, &mut out);
        if self.file != old.file {
            out.push(format!(
                "its file changed ({} → {})",
                old.file.as_deref().map_or("none", short),
                self.file.as_deref().map_or("none", short)
            ));
        }
        for (slot, h) in &self.inputs {
            match old.inputs.get(slot) {
                None => out.push(format!("input `{slot}`: newly connected")),
                Some(o) if o != h => out.push(format!(
                    "input `{slot}`: content changed ({} → {})",
                    short(o),
                    short(h)
                )),
                _ => {}
            }
        }
        for slot in old.inputs.keys() {
            if !self.inputs.contains_key(slot) {
                out.push(format!("input `{slot}`: disconnected"));
            }
        }
        out
    }
}

impl KeyFields {
    /// `the code changed (<old> → <new>)`, shortened, when it did.
    pub fn code_change(&self, old: &KeyFields) -> Option<String> {
        (self.code != old.code).then(|| {
            format!(
                "the code changed ({} → {})",
                short_or_unrecorded(&old.code),
                short_or_unrecorded(&self.code)
            )
        })
    }

    /// Every field as `(name, value)`, named as [`KeyFields::diff`] names
    /// them: `ltcal version`, `code` (short), `kind`, each setting by its
    /// dotted path (arrays whole), `input `<slot>`` with the input's short
    /// content hash.
    pub fn fields(&self) -> Vec<(String, String)> {
        let mut out = vec![
            ("ltcal version".to_string(), self.ltcal_version.clone()),
            (
                "code".to_string(),
                short_or_unrecorded(&self.code).to_string(),
            ),
            ("kind".to_string(), self.kind.clone()),
        ];
        json_leaves("", &self.params, &mut out);
        for (slot, h) in &self.inputs {
            out.push((format!("input `{slot}`"), short(h).to_string()));
        }
        out
    }
}

fn json_leaves(path: &str, v: &serde_json::Value, out: &mut Vec<(String, String)>) {
    match v {
        serde_json::Value::Object(m) => {
            for (k, v) in m {
                let p = if path.is_empty() {
                    k.clone()
                } else {
                    format!("{path}.{k}")
                };
                json_leaves(&p, v, out);
            }
        }
        _ => out.push((path.to_string(), v.to_string())),
    }
}

/// The first 12 characters of a hash, for people.
pub fn short(h: &str) -> &str {
    &h[..h.len().min(12)]
}

/// [`short`], or `unrecorded` for a code fingerprint a record lacks.
fn short_or_unrecorded(h: &str) -> &str {
    if h.is_empty() { "unrecorded" } else { short(h) }
}

fn json_diff(path: &str, old: &serde_json::Value, new: &serde_json::Value, out: &mut Vec<String>) {
    use serde_json::Value::Object;
    match (old, new) {
        (Object(a), Object(b)) => {
            let keys: std::collections::BTreeSet<&String> = a.keys().chain(b.keys()).collect();
            for k in keys {
                let p = if path.is_empty() {
                    k.clone()
                } else {
                    format!("{path}.{k}")
                };
                let null = serde_json::Value::Null;
                json_diff(
                    &p,
                    a.get(k).unwrap_or(&null),
                    b.get(k).unwrap_or(&null),
                    out,
                );
            }
        }
        _ if old != new => out.push(format!("{path}: {old} → {new}")),
        _ => {}
    }
}

/// One table of an entry.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TableRecord {
    pub name: String,
    pub rows: usize,
    /// blake3 of the Parquet file.
    pub hash: String,
}

/// One file (figure) of an entry.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FileRecord {
    pub name: String,
    pub bytes: usize,
    pub hash: String,
}

/// Provenance of an entry; written last, so its presence means the entry is
/// complete. Everything a reader needs to know where a result came from:
/// the stage that made it, its key fields (kind, resolved settings, the
/// content hash of every input table, the ltcal version, the code
/// fingerprint), when it ran, and
/// each table's rows and content hash (blake3 of its Parquet bytes, which
/// depend on the table alone: see [`crate::table::to_parquet_bytes`]).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Manifest {
    pub stage: String,
    pub key: String,
    pub key_fields: KeyFields,
    /// RFC 3339 wall-clock times of the stage's run.
    pub started: String,
    pub finished: String,
    pub seconds: f64,
    pub tables: Vec<TableRecord>,
    pub files: Vec<FileRecord>,
}

/// A complete entry read back and verified.
#[derive(Clone, Debug)]
pub struct Entry {
    pub manifest: Manifest,
    /// Table name → Parquet bytes.
    pub tables: BTreeMap<String, Vec<u8>>,
    /// File name → bytes.
    pub files: BTreeMap<String, Vec<u8>>,
}

impl Entry {
    /// The entry of a stage's fresh output: its tables as Parquet bytes,
    /// each table and file recorded with its hash in the manifest.
    /// `times` is when the stage started and finished (RFC 3339).
    pub fn new(
        stage: &str,
        key_fields: &KeyFields,
        times: (String, String),
        seconds: f64,
        tables: &[(String, polars::prelude::DataFrame)],
        files: BTreeMap<String, Vec<u8>>,
    ) -> anyhow::Result<Entry> {
        // Each table encoded and hashed on its own, in parallel (issue 34:
        // the encoding was the largest cost of a 24 000-reading run outside
        // its stages); recorded in the stage's order. Collected whole first,
        // so that of two tables that fail, the first in that order is the
        // one reported, whichever thread failed first.
        let encoded = tables
            .par_iter()
            .map(|(name, df)| {
                let b = crate::table::to_parquet_bytes(df)?;
                let record = TableRecord {
                    name: name.clone(),
                    rows: df.height(),
                    hash: hash_bytes(&b),
                };
                Ok((record, b))
            })
            .collect::<Vec<anyhow::Result<_>>>()
            .into_iter()
            .collect::<anyhow::Result<Vec<_>>>()?;
        let mut bytes = BTreeMap::new();
        let mut records = Vec::with_capacity(encoded.len());
        for (record, b) in encoded {
            bytes.insert(record.name.clone(), b);
            records.push(record);
        }
        let manifest = Manifest {
            stage: stage.to_string(),
            key: key_fields.hash(),
            key_fields: key_fields.clone(),
            started: times.0,
            finished: times.1,
            seconds,
            tables: records,
            files: files
                .iter()
                .map(|(n, b)| FileRecord {
                    name: n.clone(),
                    bytes: b.len(),
                    hash: hash_bytes(b),
                })
                .collect(),
        };
        Ok(Entry {
            manifest,
            tables: bytes,
            files,
        })
    }
}

/// What a lookup found: the entry with every table and file verified
/// against its manifest, or why the stage must run.
#[derive(Debug)]
pub enum Lookup {
    Hit(Box<Entry>),
    Miss(Miss),
}

/// Why a stage's cached result is not served. The runner's report says it
/// in these words ([`Miss`]'s `Display`), except for [`Miss::Absent`],
/// whose reason is what changed since the stage last ran (`plan::reason`).
#[derive(Clone, Debug, PartialEq)]
pub enum Miss {
    /// No entry under the key.
    Absent,
    /// The entry existed but failed verification (what was wrong); a loose
    /// one has been removed, a packed copy is passed over from now on by
    /// every lookup.
    Corrupt(String),
    /// The entry verified, but a table of it could not be decoded.
    Unreadable(String),
    /// `--force`: not looked up, neither read nor verified.
    Forced,
}

impl Miss {
    /// The damage found in the cache, for the report's `cache_problem`: a
    /// damaged cache is made visible, not silently repaired.
    pub fn damage(&self) -> Option<&str> {
        match self {
            Miss::Corrupt(why) => Some(why),
            _ => None,
        }
    }
}

impl std::fmt::Display for Miss {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Miss::Absent => write!(f, "its cached result is missing"),
            Miss::Corrupt(why) => {
                write!(f, "its cached result was corrupt and is recomputed: {why}")
            }
            Miss::Unreadable(why) => write!(f, "its cached result could not be read: {why}"),
            Miss::Forced => write!(f, "forced (--force)"),
        }
    }
}

pub fn hash_bytes(b: &[u8]) -> String {
    blake3::hash(b).to_hex().to_string()
}

/// The cache of one pipeline.
pub struct Store {
    root: PathBuf,
    /// Every pack's index, read on first use and refreshed on demand.
    packs: RwLock<Option<Packs>>,
    /// Entries of sweep points computed by this process and not yet
    /// written as a pack ([`Store::flush`]).
    pending: Mutex<Pending>,
    /// What this process wrote (entries, packs), by [`Store::heal`]'s name
    /// for it, with its identity ([`identity`]) just after: good without
    /// being read again.
    fresh: Mutex<BTreeMap<String, String>>,
    /// The experiment (`results/<pipeline>/runs/<name>/`) whose last run
    /// [`Store::last`] and [`Store::last_record`] are about; `None`: the
    /// pipeline's main results. The entries are shared by every run.
    experiment: Option<String>,
}

/// How many packs a store keeps open (far below the usual limit of 1 024
/// open files a process); a pack beyond them is opened per read.
const MAX_OPEN_PACKS: usize = 256;

/// What the packs of the folder hold, by key: 40-odd bytes an entry, so
/// that a coordinator of 100 000 points holds their keys, not their data.
#[derive(Default)]
struct Packs {
    files: Vec<PathBuf>,
    /// The first [`MAX_OPEN_PACKS`] packs, kept open since their index was
    /// read: a cached sweep's entries are read by position, without an
    /// open (and a check of every folder on the way) per entry.
    open: Vec<Option<fs::File>>,
    seen: HashSet<PathBuf>,
    by_key: HashMap<Key, Vec<(u32, Span)>>,
    /// Stage names, each once.
    stages: Vec<String>,
    /// (point, stage) → the key of the stage's last run there.
    last: HashMap<(u32, u32), Key>,
    /// (pack, failure) of every pack.
    failures: Vec<(u32, pack::Failure)>,
    /// Packs that could not be read, and why.
    unreadable: Vec<(PathBuf, String)>,
}

impl Packs {
    fn stage_id(&mut self, stage: &str) -> u32 {
        match self.stages.iter().position(|s| s == stage) {
            Some(i) => i as u32,
            None => {
                self.stages.push(stage.to_string());
                (self.stages.len() - 1) as u32
            }
        }
    }

    fn add(&mut self, path: PathBuf, ix: pack::Index, file: Option<fs::File>) {
        let id = self.files.len() as u32;
        self.seen.insert(path.clone());
        self.files.push(path);
        let kept = self.open.iter().filter(|f| f.is_some()).count();
        self.open.push(file.filter(|_| kept < MAX_OPEN_PACKS));
        for (k, span) in ix.entries {
            self.by_key.entry(k).or_default().push((id, span));
        }
        for r in ix.records {
            let stage = self.stage_id(&r.stage);
            self.last.insert((r.point, stage), r.key);
        }
        for f in ix.failures {
            self.failures.push((id, f));
        }
    }
}

#[derive(Default)]
struct Pending {
    entries: Vec<Entry>,
    by_key: HashMap<String, usize>,
    records: Vec<pack::PointRecord>,
    failures: Vec<pack::Failure>,
}

/// What [`Store::verify`] found.
#[derive(Clone, Debug, Default)]
pub struct Verified {
    pub loose: usize,
    pub packs: usize,
    pub packed: usize,
    /// Damaged entries (and unreadable packs) with no good copy.
    pub problems: Vec<String>,
    /// Damaged packed copies of entries another copy of which is good.
    pub superseded: Vec<String>,
}

/// One damaged thing [`Store::heal`] found in the cache and what it did.
#[derive(Clone, Debug, Serialize)]
pub struct Healed {
    /// The entry or pack, as a path.
    pub path: PathBuf,
    /// What was wrong.
    pub damage: String,
    /// What was done: `removed`, or the pack it was rewritten as.
    pub action: String,
}

impl std::fmt::Display for Healed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}: {}; {}",
            self.path.display(),
            self.damage,
            self.action
        )
    }
}

/// A failure a pack records: the sweep point, the stage, why, and the
/// prefix of the pack's name (the task that wrote it).
#[derive(Clone, Debug)]
pub struct PointFailure {
    pub point: usize,
    pub stage: String,
    pub reason: String,
    pub prefix: String,
}

/// `<prefix>` of a pack named `<time>-<prefix>-<hash>.pack`.
fn pack_prefix(path: &Path) -> String {
    let name = path
        .file_stem()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let rest = name.split_once('-').map_or("", |(_, r)| r);
    rest.rsplit_once('-').map_or("", |(p, _)| p).to_string()
}

impl Store {
    /// `results/<pipeline>/.ltcal`; nothing is created until something is written.
    /// Declares the folder ltcal's own ([`crate::fs::confine`]): nothing
    /// below it is read or written through a symbolic link.
    pub fn new(pipeline_results: &Path) -> Store {
        crate::fs::confine(pipeline_results);
        Store {
            root: pipeline_results.join(".ltcal"),
            packs: RwLock::new(None),
            pending: Mutex::new(Pending::default()),
            fresh: Mutex::new(BTreeMap::new()),
            experiment: None,
        }
    }

    /// The same cache, its "last run" records those of the experiment
    /// `name` (`.ltcal/last/runs/<name>/`) rather than of the main results.
    pub fn for_experiment(mut self, name: &str) -> Store {
        self.experiment = Some(name.to_string());
        self
    }

    /// The experiment this store's "last run" records are about.
    pub fn experiment(&self) -> Option<&str> {
        self.experiment.as_deref()
    }

    fn packs_dir(&self) -> PathBuf {
        self.root.join("packs")
    }

    fn entries(&self) -> PathBuf {
        self.root.join("cache")
    }

    pub fn entry_dir(&self, key: &str) -> PathBuf {
        self.entries().join(key)
    }

    /// Finds and verifies the entry for `key`: a loose entry, one this
    /// process has not yet packed, or a packed one. A bad loose entry is
    /// removed; a bad packed one is passed over (a pack is never edited)
    /// for another copy, and reported when there is none.
    pub fn lookup(&self, key: &str) -> Lookup {
        let dir = self.entry_dir(key);
        if dir.symlink_metadata().is_ok() {
            let id = identity(&dir);
            return match self.read_entry(&dir, key) {
                Ok(e) => {
                    // Good as it was before it was read.
                    if let (Some(name), Some(id)) = (self.heal_name(&dir), id) {
                        self.fresh
                            .lock()
                            .unwrap_or_else(|e| e.into_inner())
                            .insert(name, id);
                    }
                    Lookup::Hit(Box::new(e))
                }
                Err(why) => {
                    self.discard(&dir);
                    Lookup::Miss(Miss::Corrupt(why.to_string()))
                }
            };
        }
        if let Some(e) = self.pending_entry(key) {
            return Lookup::Hit(Box::new(e));
        }
        match self.packed(key, |f, span| read_packed(f, span, key)) {
            None => Lookup::Miss(Miss::Absent),
            Some(Ok(e)) => Lookup::Hit(Box::new(e)),
            Some(Err(why)) => Lookup::Miss(Miss::Corrupt(why.to_string())),
        }
    }

    /// Reads and verifies the entry for `key` without removing a bad one:
    /// `None` when there is none, `Some(Err(why))` when it is bad.
    pub fn read(&self, key: &str) -> Option<Result<Entry>> {
        let dir = self.entry_dir(key);
        if dir.symlink_metadata().is_ok() {
            return Some(self.read_entry(&dir, key));
        }
        if let Some(e) = self.pending_entry(key) {
            return Some(Ok(e));
        }
        self.packed(key, |f, span| read_packed(f, span, key))
    }

    /// [`Store::read`], keeping only the manifest.
    pub fn check(&self, key: &str) -> Option<Result<Manifest>> {
        self.read(key).map(|e| e.map(|e| e.manifest))
    }

    /// The manifest of the entry for `key`, checked to belong to it, its
    /// tables not read: what a cached sweep point needs of the stages whose
    /// tables nothing reads — their tables' hashes, for the keys of the
    /// stages after them. A table is verified when it is read
    /// ([`Store::table`]).
    ///
    /// Packs are asked first: a cached sweep point's entries are there,
    /// and asking for a loose folder first cost a failed `statx` per stage
    /// per point. Either copy is verified alike.
    pub fn manifest(&self, key: &str) -> Option<Result<Manifest>> {
        if let Some(m) = self.packed(key, |f, span| {
            parse_manifest(&pack::read_manifest_at(f, span)?, key)
        }) {
            return Some(m);
        }
        let dir = self.entry_dir(key);
        if dir.symlink_metadata().is_ok() {
            return Some(read_manifest_file(&dir).and_then(|b| parse_manifest(&b, key)));
        }
        self.pending_entry(key).map(|e| Ok(e.manifest))
    }

    /// One table of the entry for `key`: its manifest checked to belong to
    /// the key and to record the table with `hash` (the hash the reader
    /// took from it), and the table's bytes hashed against it. Only this
    /// table is read and hashed: a damaged other table of the entry is not
    /// served by this, and is found when it is read, by `verify`, or by the
    /// run's closing [`Store::heal`] (the pack or entry changed since it
    /// was last found good).
    pub fn table(&self, key: &str, name: &str, hash: &str) -> Result<Vec<u8>> {
        let recorded = |m: &Manifest| -> Result<usize> {
            m.tables
                .iter()
                .position(|t| t.name == name && t.hash == hash)
                .ok_or_else(|| {
                    anyhow!(
                        "table {name} of entry {} does not match its manifest",
                        short(key)
                    )
                })
        };
        let file = format!("{name}.parquet");
        let checked = |b: Vec<u8>| -> Result<Vec<u8>> {
            if hash_bytes(&b) != hash {
                bail!("table {file} does not match its manifest (truncated, corrupted or edited)");
            }
            Ok(b)
        };
        // Packs first, as [`Store::manifest`].
        let packed = self.packed(key, |f, span| {
            let bytes = pack::read_span_at(f, span)?;
            let mut at = None;
            let blob = pack::split(&bytes, |m| {
                let m = parse_manifest(m, key)?;
                at = Some(recorded(&m)?);
                Ok(m.tables.len() + m.files.len())
            })?;
            let at = at.expect("split parsed the manifest");
            checked(blob.parts[at].to_vec())
        });
        if let Some(Ok(b)) = packed {
            return Ok(b);
        }
        let dir = self.entry_dir(key);
        if dir.symlink_metadata().is_ok() {
            recorded(&parse_manifest(&read_manifest_file(&dir)?, key)?)?;
            let b = read_part(&dir.join(&file), MAX_TABLE_BYTES, &format!("table {file}"))?;
            return checked(b);
        }
        if let Some(b) = self.pending_table(key, name) {
            return Ok(b);
        }
        packed.unwrap_or_else(|| Err(anyhow!("its cache entry {} is gone", short(key))))
    }

    /// A table of an entry this process has not yet packed.
    fn pending_table(&self, key: &str, name: &str) -> Option<Vec<u8>> {
        let p = self.pending.lock().unwrap_or_else(|e| e.into_inner());
        p.by_key
            .get(key)
            .and_then(|&i| p.entries[i].tables.get(name).cloned())
    }

    fn pending_entry(&self, key: &str) -> Option<Entry> {
        let p = self.pending.lock().unwrap_or_else(|e| e.into_inner());
        p.by_key.get(key).map(|&i| p.entries[i].clone())
    }

    /// Reads `key` from the first of its packed copies that `read` accepts;
    /// the first copy's problem when none does.
    fn packed<T>(
        &self,
        key: &str,
        read: impl Fn(&fs::File, Span) -> Result<T>,
    ) -> Option<Result<T>> {
        let k = pack::key_bytes(key)?;
        self.load_packs();
        let guard = self.packs.read().unwrap_or_else(|e| e.into_inner());
        let packs = guard.as_ref()?;
        let copies = packs.by_key.get(&k)?;
        let mut first_problem = None;
        for &(file, span) in copies {
            let path = &packs.files[file as usize];
            let got = match packs.open.get(file as usize).and_then(Option::as_ref) {
                Some(f) => read(f, span),
                None => pack::open_pack(path).and_then(|f| read(&f, span)),
            };
            match got {
                Ok(v) => return Some(Ok(v)),
                Err(e) => {
                    first_problem
                        .get_or_insert_with(|| anyhow!("in pack {}: {e:#}", path.display()));
                }
            }
        }
        first_problem.map(Err)
    }

    fn load_packs(&self) {
        if self
            .packs
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .is_none()
        {
            self.refresh_packs();
        }
    }

    /// Reads the indexes of packs written since the last look (by other
    /// processes: the tasks of a cluster). Packs sort by name, which starts
    /// with the time they were written, so a later record of a point
    /// replaces an earlier one.
    pub fn refresh_packs(&self) {
        let mut guard = self.packs.write().unwrap_or_else(|e| e.into_inner());
        let packs = guard.get_or_insert_with(Packs::default);
        let Ok(rd) = fs::read_dir(self.packs_dir()) else {
            return;
        };
        let mut new: Vec<PathBuf> = rd
            .flatten()
            .map(|e| e.path())
            .filter(|p| p.extension().is_some_and(|x| x == "pack") && !packs.seen.contains(p))
            .collect();
        new.sort();
        for path in new {
            match pack::open_index(&path) {
                Ok((ix, file)) => packs.add(path, ix, Some(file)),
                Err(e) => {
                    packs.seen.insert(path.clone());
                    packs.unreadable.push((path, e.to_string()));
                }
            }
        }
    }

    /// Reads and verifies every entry of the cache, loose and packed — what
    /// `ltcal verify` runs: a served entry is one of these, so a cache that
    /// passes serves nothing bad. Removes nothing.
    pub fn verify(&self) -> Verified {
        let mut v = Verified::default();
        if let Ok(rd) = fs::read_dir(self.entries()) {
            for e in rd.flatten() {
                let name = e.file_name().to_string_lossy().into_owned();
                if name.starts_with('.') {
                    continue;
                }
                v.loose += 1;
                if let Err(why) = self.read_entry(&e.path(), &name) {
                    v.problems
                        .push(format!("entry {}: {why:#}", e.path().display()));
                }
            }
        }
        self.refresh_packs();
        let guard = self.packs.read().unwrap_or_else(|e| e.into_inner());
        if let Some(p) = guard.as_ref() {
            v.packs = p.files.len();
            for (path, why) in &p.unreadable {
                v.problems.push(format!("pack {}: {why}", path.display()));
            }
            for (key, copies) in &p.by_key {
                let hex = pack::key_hex(key);
                let mut bad = Vec::new();
                for &(file, span) in copies {
                    v.packed += 1;
                    let path = &p.files[file as usize];
                    let got = match p.open.get(file as usize).and_then(Option::as_ref) {
                        Some(f) => read_packed(f, span, &hex),
                        None => pack::open_pack(path).and_then(|f| read_packed(&f, span, &hex)),
                    };
                    if let Err(why) = got {
                        bad.push(format!(
                            "entry {} in pack {}: {why:#}",
                            short(&hex),
                            path.display()
                        ));
                    }
                }
                // A pack is never edited: a damaged copy stays, but where
                // another copy is good the damaged one is never served.
                if bad.len() < copies.len() {
                    v.superseded.append(&mut bad);
                } else {
                    v.problems.append(&mut bad);
                }
            }
        }
        v
    }

    /// Takes out of the cache what [`Store::verify`] would find damaged
    /// (see the module's doc), and says what it did, one [`Healed`] a thing.
    /// With `all`, reads everything (`verify --repair`); without, only
    /// what changed since it was last found good (`run`). Never acts
    /// through a link ([`crate::fs::confine`]): a link where the cache's
    /// folders should be is reported, and nothing behind it touched.
    pub fn heal(&self, all: bool) -> Vec<Healed> {
        let (done, record) = self.heal_recorded(all);
        if let Some((path, bytes)) = record {
            let _ = write_atomic(&path, &bytes);
        }
        done
    }

    /// [`Store::heal`], returning `.ltcal/verified.json` (path and bytes)
    /// for the caller to write instead of writing it: a run writes it
    /// beside its own record, the two syncs overlapping (issue 34). Its
    /// write may fail: the next run only reads more.
    pub fn heal_recorded(&self, all: bool) -> (Vec<Healed>, Option<(PathBuf, Vec<u8>)>) {
        let mut done = Vec::new();
        if let Some(link) = crate::fs::link_on_the_way(&self.packs_dir())
            .or_else(|| crate::fs::link_on_the_way(&self.entries()))
        {
            done.push(Healed {
                path: link.clone(),
                damage: crate::fs::refuse_links(&link)
                    .err()
                    .map_or_else(String::new, |e| format!("{e:#}")),
                action: "left alone: nothing is read or removed through it".into(),
            });
            return (done, None);
        }
        let known = if all {
            BTreeMap::new()
        } else {
            self.verified()
        };
        let fresh = std::mem::take(&mut *self.fresh.lock().unwrap_or_else(|e| e.into_inner()));
        let mut good = BTreeMap::new();
        // Good as recorded, or written by this process: not read again.
        let still_good = |path: &Path, good: &mut BTreeMap<String, String>| {
            let (Some(name), Some(id)) = (self.heal_name(path), identity(path)) else {
                return false;
            };
            let ok = fresh.get(&name) == Some(&id) || known.get(&name) == Some(&id);
            if ok {
                good.insert(name, id);
            }
            ok
        };
        for path in list(&self.entries(), |name| !name.starts_with('.')) {
            if still_good(&path, &mut good) {
                continue;
            }
            let id = identity(&path);
            let key = path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            match self.read_entry(&path, &key) {
                Ok(_) => {
                    if let (Some(name), Some(id)) = (self.heal_name(&path), id) {
                        good.insert(name, id);
                    }
                }
                Err(why) => {
                    self.discard(&path);
                    done.push(Healed {
                        path,
                        damage: format!("{why:#}"),
                        action: "removed (the stage runs again when it is needed)".into(),
                    });
                }
            }
        }
        for path in list(&self.packs_dir(), |name| name.ends_with(".pack")) {
            if still_good(&path, &mut good) {
                continue;
            }
            let id = identity(&path);
            match self.heal_pack(&path) {
                Ok(None) => {
                    if let (Some(name), Some(id)) = (self.heal_name(&path), id) {
                        good.insert(name, id);
                    }
                }
                Ok(Some((healed, new))) => {
                    if let Some(new) = &new {
                        if let (Some(name), Some(id)) = (self.heal_name(new), identity(new)) {
                            good.insert(name, id);
                        }
                    }
                    done.push(healed);
                }
                Err(e) => done.push(Healed {
                    path,
                    damage: format!("{e:#}"),
                    action: "could not be removed".into(),
                }),
            }
        }
        // What another process recorded meanwhile is lost: it is only
        // read again.
        let record = serde_json::to_vec_pretty(&good)
            .ok()
            .map(|bytes| (self.root.join("verified.json"), bytes));
        // Packs were removed and written: read their indexes afresh.
        *self.packs.write().unwrap_or_else(|e| e.into_inner()) = None;
        (done, record)
    }

    /// What `.ltcal/verified.json` records as good: name → identity.
    fn verified(&self) -> BTreeMap<String, String> {
        read_regular_file(&self.root.join("verified.json"), MAX_MANIFEST_BYTES)
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok())
            .unwrap_or_default()
    }

    /// `cache/<key>` or `packs/<name>`: how `verified.json` names a thing.
    fn heal_name(&self, path: &Path) -> Option<String> {
        let rel = path.strip_prefix(&self.root).ok()?;
        Some(rel.to_string_lossy().into_owned())
    }

    /// Checks one pack: `None` when every entry is good; else takes it out,
    /// rewriting its good entries, records and failures as a new pack
    /// (returned) first when its index can be read.
    fn heal_pack(&self, path: &Path) -> Result<Option<(Healed, Option<PathBuf>)>> {
        let (ix, file) = match pack::open_index(path) {
            Ok(open) => open,
            Err(why) => {
                remove_any(path)?;
                return Ok(Some((
                    Healed {
                        path: path.to_path_buf(),
                        damage: format!("{why:#}"),
                        action: "removed (its points are computed again by the next run)".into(),
                    },
                    None,
                )));
            }
        };
        let mut b = pack::Builder::default();
        let mut bad = Vec::new();
        for (key, span) in &ix.entries {
            let hex = pack::key_hex(key);
            match pack::read_span_at(&file, *span).and_then(|bytes| {
                verify_packed(&bytes, &hex)?;
                Ok(bytes)
            }) {
                Ok(bytes) => b.add_entry(*key, &bytes),
                Err(why) => bad.push(format!("entry {}: {why:#}", short(&hex))),
            }
        }
        if bad.is_empty() {
            return Ok(None);
        }
        let kept = ix.entries.len() - bad.len();
        for r in ix.records {
            b.record(r);
        }
        for f in ix.failures {
            b.fail(f);
        }
        // Under the old pack's time and prefix: records keep their order,
        // failures their task.
        let stem = path
            .file_stem()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let head = stem.rsplit_once('-').map_or(stem.as_str(), |(h, _)| h);
        let new = if b.is_empty() {
            None
        } else {
            let (bytes, _) = b.finish();
            let new = path.with_file_name(format!("{head}-{}.pack", short(&hash_bytes(&bytes))));
            write_atomic(&new, &bytes).context("rewriting a damaged pack's good entries")?;
            Some(new)
        };
        if new.as_deref() != Some(path) {
            remove_any(path)?;
        }
        let action = match &new {
            Some(new) => format!(
                "removed; its {kept} good entr{} and its records rewritten as {} (the damaged \
                 ones are computed again by the next run)",
                if kept == 1 { "y" } else { "ies" },
                new.display()
            ),
            None => "removed (its points are computed again by the next run)".into(),
        };
        Ok(Some((
            Healed {
                path: path.to_path_buf(),
                damage: format!(
                    "{} damaged entr{}: {}",
                    bad.len(),
                    if bad.len() == 1 { "y" } else { "ies" },
                    bad.join("; ")
                ),
                action,
            },
            new,
        )))
    }

    /// Packs that could not be read, and why (reported by the runner, and
    /// by the cache verifier).
    pub fn unreadable_packs(&self) -> Vec<(PathBuf, String)> {
        self.load_packs();
        let guard = self.packs.read().unwrap_or_else(|e| e.into_inner());
        guard
            .as_ref()
            .map(|p| p.unreadable.clone())
            .unwrap_or_default()
    }

    /// Every failure the packs record, with the prefix of the pack's name
    /// (`<time>-<prefix>-<hash>.pack`: which task wrote it).
    pub fn failures(&self) -> Vec<PointFailure> {
        self.load_packs();
        let guard = self.packs.read().unwrap_or_else(|e| e.into_inner());
        let Some(p) = guard.as_ref() else {
            return Vec::new();
        };
        p.failures
            .iter()
            .map(|(file, f)| PointFailure {
                point: f.point as usize,
                stage: f.stage.clone(),
                reason: f.reason.clone(),
                prefix: pack_prefix(&p.files[*file as usize]),
            })
            .collect()
    }

    /// Keeps an entry of a sweep point to be written with the next pack,
    /// and records that its stage ran at `point`.
    pub fn put_packed(&self, entry: Entry, point: usize) {
        let mut p = self.pending.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(key) = pack::key_bytes(&entry.manifest.key) {
            p.records.push(pack::PointRecord {
                point: point as u32,
                stage: entry.manifest.stage.clone(),
                key,
            });
        }
        if !p.by_key.contains_key(&entry.manifest.key) {
            let i = p.entries.len();
            p.by_key.insert(entry.manifest.key.clone(), i);
            p.entries.push(entry);
        }
    }

    /// Records that a stage failed at a sweep point, and why.
    pub fn fail_packed(&self, point: usize, stage: &str, reason: &str) {
        let mut p = self.pending.lock().unwrap_or_else(|e| e.into_inner());
        p.failures.push(pack::Failure {
            point: point as u32,
            stage: stage.to_string(),
            reason: reason.to_string(),
        });
    }

    /// Writes what [`Store::put_packed`] and [`Store::fail_packed`] kept as
    /// one pack, `packs/<time>-<prefix>-<hash>.pack` (so that packs sort by
    /// the time they were written), by one rename; returns
    /// its path (none when nothing was kept). The entries stay readable
    /// throughout: from memory until the pack is in place, from it after.
    pub fn flush(&self, prefix: &str) -> Result<Option<PathBuf>> {
        let mut pending = self.pending.lock().unwrap_or_else(|e| e.into_inner());
        let mut b = pack::Builder::default();
        for e in &pending.entries {
            let Some(key) = pack::key_bytes(&e.manifest.key) else {
                continue;
            };
            let manifest = serde_json::to_vec(&e.manifest)?;
            let parts: Vec<&[u8]> = e
                .manifest
                .tables
                .iter()
                .map(|t| e.tables[&t.name].as_slice())
                .chain(e.manifest.files.iter().map(|f| e.files[&f.name].as_slice()))
                .collect();
            b.add(
                key,
                &pack::Blob {
                    manifest: &manifest,
                    parts,
                },
            );
        }
        for r in &pending.records {
            b.record(r.clone());
        }
        for f in &pending.failures {
            b.fail(f.clone());
        }
        if b.is_empty() {
            return Ok(None);
        }
        let (bytes, index) = b.finish();
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0);
        let path = self.packs_dir().join(format!(
            "{nanos:020}-{prefix}-{}.pack",
            short(&hash_bytes(&bytes))
        ));
        write_atomic(&path, &bytes).context("writing a pack of sweep points' entries")?;
        self.mark_fresh(&path);
        {
            let mut guard = self.packs.write().unwrap_or_else(|e| e.into_inner());
            guard
                .get_or_insert_with(Packs::default)
                .add(path.clone(), index, None);
        }
        *pending = Pending::default();
        Ok(Some(path))
    }

    fn read_entry(&self, dir: &Path, key: &str) -> Result<Entry> {
        let bytes = read_manifest_file(dir)?;
        let manifest = parse_manifest(&bytes, key)?;
        let mut tables = BTreeMap::new();
        for t in &manifest.tables {
            let name = format!("{}.parquet", t.name);
            let b = read_part(&dir.join(&name), MAX_TABLE_BYTES, &format!("table {name}"))?;
            if hash_bytes(&b) != t.hash {
                bail!("table {name} does not match its manifest (truncated, corrupted or edited)");
            }
            tables.insert(t.name.clone(), b);
        }
        let mut files = BTreeMap::new();
        for f in &manifest.files {
            let path = dir.join("files").join(&f.name);
            let b = read_part(&path, MAX_FIGURE_BYTES, &format!("file {}", f.name))?;
            if hash_bytes(&b) != f.hash {
                bail!("file {} does not match its manifest", f.name);
            }
            files.insert(f.name.clone(), b);
        }
        Ok(Entry {
            manifest,
            tables,
            files,
        })
    }

    /// Moves a bad entry out of the way, then deletes it: readers never see
    /// a half-deleted entry under its key.
    /// Never through a link: the entry itself may be one (the link is
    /// what goes), the folders above it not.
    fn discard(&self, dir: &Path) {
        if dir
            .parent()
            .is_none_or(|p| crate::fs::link_on_the_way(p).is_some())
        {
            return;
        }
        let trash = self.entries().join(format!(".trash-{}", temp_name()));
        if fs::rename(dir, &trash).is_ok() {
            let _ = fs::remove_dir_all(&trash);
        }
    }

    /// Publishes an entry. If another process published the same key first,
    /// its entry (identical by construction) is kept.
    pub fn put(&self, entry: &Entry) -> Result<()> {
        let key = &entry.manifest.key;
        let entries = self.entries();
        crate::fs::create_dirs(&entries)?;
        let tmp = entries.join(format!(".tmp-{}-{}", short(key), temp_name()));
        let staged = (|| -> std::io::Result<StagedFolder> {
            let staged = StagedFolder::create(tmp, false)?;
            if !entry.files.is_empty() {
                staged.folder("files")?;
            }
            for (name, b) in &entry.tables {
                staged.write(format!("{name}.parquet"), b)?;
            }
            for (name, b) in &entry.files {
                staged.write(Path::new("files").join(name), b)?;
            }
            let manifest =
                serde_json::to_vec_pretty(&entry.manifest).map_err(std::io::Error::other)?;
            staged.write("manifest.json", &manifest)?;
            Ok(staged)
        })();
        let mut staged = staged.map_err(|e| {
            anyhow!(e).context(format!(
                "writing the cache entry for {}",
                entry.manifest.stage
            ))
        })?;
        let dest = self.entry_dir(key);
        // The rename fails onto an existing non-empty directory: another
        // writer won the race (its entry is identical by construction and is
        // kept), or a bad entry sits there, which `lookup` discards so that
        // ours can take its place. The staged folder removes itself if unused.
        let published = staged.place(&dest).is_ok()
            || matches!(self.lookup(key), Lookup::Hit(_))
            || staged.place(&dest).is_ok();
        drop(staged);
        if !published && !matches!(self.lookup(key), Lookup::Hit(_)) {
            bail!("could not publish the cache entry {}", dest.display());
        }
        self.mark_fresh(&dest);
        Ok(())
    }

    /// Records that what is at `path` is good as it is now.
    fn mark_fresh(&self, path: &Path) {
        if let (Some(name), Some(id)) = (self.heal_name(path), identity(path)) {
            self.fresh
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .insert(name, id);
        }
    }

    /// Removes what killed runs left behind: temporary entry directories and
    /// files of processes that no longer exist. Returns how many were removed.
    pub fn clean_incomplete(&self) -> usize {
        // Nothing is removed through a link: it would reach outside.
        if crate::fs::link_on_the_way(&self.root).is_some() {
            return 0;
        }
        // `verified.json`'s temporaries sit in the root.
        let mut n = clean_temp_files_in(&self.root)
            + clean_temp_files_in(&self.root.join("last"))
            // Every experiment's records (a killed one may never run again).
            + fs::read_dir(self.root.join("last").join("runs"))
                .into_iter()
                .flatten()
                .flatten()
                // A link is not followed: it would reach outside.
                .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
                .map(|e| clean_temp_files_in(&e.path()))
                .sum::<usize>()
            + clean_temp_files_in(&self.packs_dir());
        let Ok(rd) = fs::read_dir(self.entries()) else {
            return n;
        };
        for e in rd.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let stale = if let Some(rest) = name.strip_prefix(".tmp-") {
                rest.split_once('-')
                    .is_some_and(|(_, t)| crate::fs::temp_owner_gone(t))
            } else if let Some(rest) = name.strip_prefix(".trash-") {
                crate::fs::temp_owner_gone(rest)
            } else {
                // A key directory without a manifest cannot be published by
                // `put`; if one appears (copied by hand, half-deleted), drop it.
                !e.path().join("manifest.json").exists()
            };
            if stale && fs::remove_dir_all(e.path()).is_ok() {
                n += 1;
            }
        }
        n
    }

    /// The keys the cache's records name: every "last run" record (the
    /// main results' and every experiment's, `.ltcal/last/`) and, per sweep
    /// point and stage, the packs' latest record of a run there — what
    /// `explain` compares with, so what [`super::gc`] keeps.
    pub fn recorded_keys(&self) -> HashSet<String> {
        let main = self.root.join("last");
        let mut dirs = vec![main.clone()];
        dirs.extend(
            fs::read_dir(main.join("runs"))
                .into_iter()
                .flatten()
                .flatten()
                .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
                .map(|e| e.path()),
        );
        let mut keys: HashSet<String> = dirs
            .iter()
            .flat_map(|d| list(d, |n| n.ends_with(".json")))
            .filter_map(|p| read_last(&p))
            .map(|k| k.hash())
            .collect();
        self.refresh_packs();
        let guard = self.packs.read().unwrap_or_else(|e| e.into_inner());
        if let Some(p) = guard.as_ref() {
            keys.extend(p.last.values().map(pack::key_hex));
        }
        keys
    }

    /// Every loose entry: its key and folder, by key.
    pub fn loose_entries(&self) -> Vec<(String, PathBuf)> {
        list(&self.entries(), |n| !n.starts_with('.'))
            .into_iter()
            .filter_map(|p| Some((p.file_name()?.to_string_lossy().into_owned(), p)))
            .collect()
    }

    /// Every pack, by name (the time it was written), with its entries'
    /// keys, or why its index cannot be read.
    pub fn pack_files(&self) -> Vec<(PathBuf, Result<Vec<String>>)> {
        list(&self.packs_dir(), |n| n.ends_with(".pack"))
            .into_iter()
            .map(|p| {
                let keys = pack::read_index(&p)
                    .map(|ix| ix.entries.iter().map(|(k, _)| pack::key_hex(k)).collect());
                (p, keys)
            })
            .collect()
    }

    /// Takes a loose entry out for good, as [`Store::discard`] does a bad
    /// one: renamed out of its key first (one step, so a reader finds the
    /// whole entry or none — a killed process leaves a `.trash-` folder
    /// that the next run removes), then deleted.
    pub fn remove_entry(&self, dir: &Path) -> Result<()> {
        crate::fs::refuse_links(&self.entries())?;
        let trash = self.entries().join(format!(".trash-{}", temp_name()));
        fs::rename(dir, &trash).with_context(|| format!("moving {} out", dir.display()))?;
        fs::remove_dir_all(&trash).with_context(|| format!("removing {}", trash.display()))
    }

    /// Takes a pack out for good: one unlink, so a reader opens the whole
    /// pack or none.
    pub fn remove_pack(&self, path: &Path) -> Result<()> {
        crate::fs::refuse_links(&self.packs_dir())?;
        remove_any(path)?;
        *self.packs.write().unwrap_or_else(|e| e.into_inner()) = None;
        Ok(())
    }

    /// Where the "last run" records of this store's results are: the main
    /// results' in `.ltcal/last/`, an experiment's below it (a stage's
    /// record is a file, `<stage>.json`, so the folder `runs` is no stage's).
    fn last_dir(&self) -> PathBuf {
        let main = self.root.join("last");
        match &self.experiment {
            Some(name) => main.join("runs").join(name),
            None => main,
        }
    }

    fn last_path(&self, stage: &str) -> PathBuf {
        self.last_dir().join(format!("{stage}.json"))
    }

    /// The key fields of the last successful run of a stage of this name
    /// (at this sweep point: what the packs record, whichever run computed
    /// it). Of the results this store is about: an experiment that has not
    /// published the stage yet falls back on the main results' record — its
    /// change is its overrides ([`Store::last_here`] does not fall back).
    pub fn last(&self, stage: &str, point: Option<usize>) -> Option<KeyFields> {
        match point {
            Some(i) => {
                let key = {
                    let pending = self.pending.lock().unwrap_or_else(|e| e.into_inner());
                    pending
                        .records
                        .iter()
                        .rev()
                        .find(|r| r.point as usize == i && r.stage == stage)
                        .map(|r| r.key)
                };
                let key = key.or_else(|| {
                    self.load_packs();
                    let guard = self.packs.read().unwrap_or_else(|e| e.into_inner());
                    let p = guard.as_ref()?;
                    let s = p.stages.iter().position(|s| s == stage)? as u32;
                    p.last.get(&(u32::try_from(i).ok()?, s)).copied()
                })?;
                Some(self.manifest(&pack::key_hex(&key))?.ok()?.key_fields)
            }
            None => self.last_here(stage).or_else(|| {
                self.experiment.as_ref()?;
                read_last(&self.root.join("last").join(format!("{stage}.json")))
            }),
        }
    }

    /// The key fields of what the last run of these results (the main
    /// results, or this store's experiment) published for `stage`.
    pub fn last_here(&self, stage: &str) -> Option<KeyFields> {
        read_last(&self.last_path(stage))
    }

    /// The file (path and bytes) that records `k` as what the last run of
    /// these results published for `stage`, for the caller to write
    /// atomically once the stage's files are published; `None` when that is
    /// already the record.
    pub fn last_record(&self, stage: &str, k: &KeyFields) -> Result<Option<(PathBuf, Vec<u8>)>> {
        if self.last_here(stage).as_ref() == Some(k) {
            return Ok(None);
        }
        Ok(Some((self.last_path(stage), serde_json::to_vec_pretty(k)?)))
    }
}

fn read_last(path: &Path) -> Option<KeyFields> {
    let b = read_regular_file(path, MAX_MANIFEST_BYTES).ok()?;
    serde_json::from_slice(&b).ok()
}

/// A manifest, checked to be the one of `key`.
fn parse_manifest(bytes: &[u8], key: &str) -> Result<Manifest> {
    let manifest: Manifest =
        serde_json::from_slice(bytes).map_err(|e| anyhow!("manifest.json is unreadable: {e}"))?;
    if manifest.key != key || manifest.key_fields.hash() != key {
        bail!("manifest.json does not belong to key {}", short(key));
    }
    Ok(manifest)
}

/// The `manifest.json` of the loose entry `dir`.
fn read_manifest_file(dir: &Path) -> Result<Vec<u8>> {
    read_regular_file(&dir.join("manifest.json"), MAX_MANIFEST_BYTES).map_err(|e| {
        if e.is_missing() {
            anyhow!("manifest.json is missing (an incomplete entry)")
        } else {
            anyhow!("manifest.json {}", e.reason)
        }
    })
}

/// A table or file of a loose entry, `what` naming it.
fn read_part(path: &Path, max: u64, what: &str) -> Result<Vec<u8>> {
    read_regular_file(path, max).map_err(|e: ReadError| {
        if e.is_missing() {
            anyhow!("{what} is missing")
        } else {
            anyhow!("{what} {}", e.reason)
        }
    })
}

/// An entry read from a pack and verified as a loose one is.
fn read_packed(f: &fs::File, span: Span, key: &str) -> Result<Entry> {
    verify_packed(&pack::read_span_at(f, span)?, key)
}

/// The entry of `key` from its bytes in a pack, verified as a loose one is.
fn verify_packed(bytes: &[u8], key: &str) -> Result<Entry> {
    let mut manifest = None;
    let blob = pack::split(bytes, |m| {
        let parsed = parse_manifest(m, key)?;
        let n = parsed.tables.len() + parsed.files.len();
        manifest = Some(parsed);
        Ok(n)
    })?;
    let manifest = manifest.expect("split parsed the manifest");
    let mut parts = blob.parts.into_iter();
    let mut tables = BTreeMap::new();
    for t in &manifest.tables {
        let b = parts.next().expect("one part per table");
        if hash_bytes(b) != t.hash {
            bail!(
                "table {}.parquet does not match its manifest (truncated, corrupted or edited)",
                t.name
            );
        }
        tables.insert(t.name.clone(), b.to_vec());
    }
    let mut files = BTreeMap::new();
    for f in &manifest.files {
        let b = parts.next().expect("one part per file");
        if hash_bytes(b) != f.hash {
            bail!("file {} does not match its manifest", f.name);
        }
        files.insert(f.name.clone(), b.to_vec());
    }
    Ok(Entry {
        manifest,
        tables,
        files,
    })
}

/// The entries of `dir` whose names `keep` accepts, sorted.
fn list(dir: &Path, keep: impl Fn(&str) -> bool) -> Vec<PathBuf> {
    let Ok(rd) = fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut out: Vec<PathBuf> = rd
        .flatten()
        .filter(|e| keep(&e.file_name().to_string_lossy()))
        .map(|e| e.path())
        .collect();
    out.sort();
    out
}

/// Removes what is at `path` in the cache's own folders, whatever it is (a
/// link goes, not what it points to).
fn remove_any(path: &Path) -> Result<()> {
    let meta = fs::symlink_metadata(path)?;
    if meta.is_dir() {
        fs::remove_dir_all(path)
    } else {
        fs::remove_file(path)
    }
    .with_context(|| format!("removing {}", path.display()))
}

/// A file's or entry folder's identity: inode, size, modification and
/// change times of it (and, for a folder, of everything in it and in its
/// `files/`). Writing a byte, `chmod`, or another file put in its place
/// all change it; `None` when it cannot be read.
fn identity(path: &Path) -> Option<String> {
    use std::os::unix::fs::MetadataExt as _;
    let one = |m: &fs::Metadata| {
        format!(
            "{}:{}:{}.{}:{}.{}:{:o}",
            m.ino(),
            m.len(),
            m.mtime(),
            m.mtime_nsec(),
            m.ctime(),
            m.ctime_nsec(),
            m.mode()
        )
    };
    let meta = fs::symlink_metadata(path).ok()?;
    if !meta.is_dir() {
        return Some(one(&meta));
    }
    let mut parts = vec![one(&meta)];
    for dir in [path.to_path_buf(), path.join("files")] {
        for p in list(&dir, |_| true) {
            parts.push(format!(
                "{}={}",
                p.file_name()?.to_string_lossy(),
                one(&fs::symlink_metadata(&p).ok()?)
            ));
        }
    }
    Some(short(&hash_bytes(parts.join("\n").as_bytes())).to_string())
}

/// Removes the temporary files [`write_atomic`] leaves when its process is
/// killed between creating and renaming them, in `dir` and its immediate
/// subfolders (the published stage folders). Returns how many were removed.
pub fn clean_temp_files(dir: &Path) -> usize {
    let Ok(rd) = fs::read_dir(dir) else {
        return 0;
    };
    let mut n = 0;
    for e in rd.flatten() {
        let path = e.path();
        let name = e.file_name().to_string_lossy().into_owned();
        if e.file_type().is_ok_and(|t| t.is_dir()) {
            if !name.starts_with('.') {
                n += clean_temp_files_in(&path);
            }
        } else if is_dead_temp_file(&name) && fs::remove_file(&path).is_ok() {
            n += 1;
        }
    }
    n
}

fn clean_temp_files_in(dir: &Path) -> usize {
    let Ok(rd) = fs::read_dir(dir) else {
        return 0;
    };
    rd.flatten()
        .filter(|e| {
            is_dead_temp_file(&e.file_name().to_string_lossy()) && fs::remove_file(e.path()).is_ok()
        })
        .count()
}

/// `.<name>.<temp_name>.tmp` of a process that has ended.
fn is_dead_temp_file(name: &str) -> bool {
    let Some(stem) = name.strip_prefix('.').and_then(|n| n.strip_suffix(".tmp")) else {
        return false;
    };
    // Only names `write_atomic` makes: a user's own dot-files stay.
    stem.rsplit_once('.')
        .is_some_and(|(_, suffix)| crate::fs::temp_owner_gone(suffix))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key_fields(seed: u64) -> KeyFields {
        KeyFields {
            ltcal_version: "0.1.0".into(),
            code: "c0de".into(),
            kind: "measure".into(),
            params: serde_json::json!({"seed": seed, "noise": {"sigma_angle_urad": 1.0}}),
            inputs: BTreeMap::from([("points".to_string(), "abc".to_string())]),
            file: None,
        }
    }

    fn entry(k: &KeyFields) -> Entry {
        let bytes = b"table bytes".to_vec();
        Entry {
            manifest: Manifest {
                stage: "m".into(),
                key: k.hash(),
                key_fields: k.clone(),
                started: String::new(),
                finished: String::new(),
                seconds: 0.0,
                tables: vec![TableRecord {
                    name: "readings".into(),
                    rows: 1,
                    hash: hash_bytes(&bytes),
                }],
                files: vec![],
            },
            tables: BTreeMap::from([("readings".to_string(), bytes)]),
            files: BTreeMap::new(),
        }
    }

    #[test]
    fn a_packs_prefix_is_the_task_that_wrote_it() {
        let p = Path::new("/r/.ltcal/packs/01795640197434165756-slurm-47_0-9208f04d7a72.pack");
        assert_eq!(pack_prefix(p), "slurm-47_0");
        assert_eq!(pack_prefix(Path::new("x.pack")), "");
    }

    #[test]
    fn diff_names_each_changed_field() {
        let a = key_fields(1);
        let mut b = key_fields(2);
        b.inputs.insert("points".into(), "def".into());
        let d = b.diff(&a);
        assert_eq!(d[0], "seed: 1 → 2");
        assert!(d[1].starts_with("input `points`: content changed"));
        assert_ne!(a.hash(), b.hash());
    }

    #[test]
    fn the_code_fingerprint_is_in_the_key_and_a_record_without_one_reads_as_a_code_change() {
        let a = key_fields(1);
        let mut b = a.clone();
        b.code = "0123456789abcdef".into();
        assert_ne!(a.hash(), b.hash());
        assert_eq!(b.diff(&a), ["the code changed (c0de → 0123456789ab)"]);
        // A record from before the fingerprint existed.
        let mut old = serde_json::to_value(&a).unwrap();
        old.as_object_mut().unwrap().remove("code");
        let old: KeyFields = serde_json::from_value(old).unwrap();
        assert_eq!(a.diff(&old), ["the code changed (unrecorded → c0de)"]);
    }

    #[test]
    fn put_lookup_and_detect_a_flipped_byte() {
        let dir = std::env::temp_dir().join(format!("ltcal-store-{}", temp_name()));
        let store = Store::new(&dir);
        let k = key_fields(1);
        store.put(&entry(&k)).unwrap();
        assert!(matches!(store.lookup(&k.hash()), Lookup::Hit(_)));
        // A second put of the same key keeps the first.
        store.put(&entry(&k)).unwrap();
        let f = store.entry_dir(&k.hash()).join("readings.parquet");
        let mut b = fs::read(&f).unwrap();
        b[0] ^= 1;
        fs::write(&f, b).unwrap();
        assert!(matches!(
            store.lookup(&k.hash()),
            Lookup::Miss(Miss::Corrupt(why)) if why.contains("readings.parquet does not match its manifest")
        ));
        assert!(matches!(
            store.lookup(&k.hash()),
            Lookup::Miss(Miss::Absent)
        ));
        fs::remove_dir_all(&dir).unwrap();
    }
}
