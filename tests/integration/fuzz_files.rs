//! Fuzzing what ltcal reads back from its own results folder (issue 28):
//! packs, loose manifests and tables, published tables, `jobs.json`, the
//! Slurm job script a pipeline's `[executor.slurm]` makes, and hostile file
//! types — a FIFO, a link to `/dev/zero`, a link to a folder or a file
//! outside, a folder where a file is expected, `chmod 000` — at every path
//! `ltcal` reads or writes below `results/<pipeline>/`. The hand-written
//! cases of `file_safety.rs` are the model; here they are generated from a
//! case number, so a finding is reproduced by its number.
//!
//! The properties, every case: no panic, no abort, no hang (each case under
//! a deadline: a worker thread in process, a killed child for the binary);
//! every error names a file; the binary exits 0, 1 or 2; nothing appears
//! outside the case's results folder; after a run the cache verifies — it
//! healed what it found damaged. Each kind runs at CI size under
//! `cargo test`; `fuzz_100k_mutants` (fuzz.rs) runs them at length.

use crate::cli::BIN;
use crate::fuzz::{Rng, VALUES, mutate};
use ltcal::pipeline::cluster::slurm::Slurm;
use ltcal::pipeline::cluster::{self, ArrayJob, JobRecord, Scheduler, TaskState, Unit};
use ltcal::pipeline::{self, cache::Store, plan, published, run};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, mpsc};
use std::time::{Duration, Instant};

/// The kinds of mutant, each with its own generator and checks.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Kind {
    /// A pack of a cached sweep: bytes flipped, cut, extended, zeroed; the
    /// trailer or the index damaged, or the index rewritten with a valid
    /// hash (entries swapped, offsets and counts at edge values). Read in
    /// process: verify, plan, show, run, verify.
    Pack,
    /// A loose entry's `manifest.json` or table, or a published table.
    Loose,
    /// `.ltcal/slurm/jobs.json`, read by `status` and the coordinator (a
    /// scheduler stand-in: no Slurm needed).
    Jobs,
    /// `[executor.slurm]` settings and `--set executor.slurm.…`; the job
    /// script built from what loads.
    Slurm,
    /// A hostile file type at a path below `results/<pipeline>/`, or a
    /// damaged cache file, met by the `ltcal` binary (`verify`, `plan`,
    /// `status`, `show`, `explain`, `verify --repair`, then `run`, then
    /// `verify`).
    Files,
}

/// What one case came to.
#[derive(Debug)]
enum Verdict {
    /// Accepted: nothing was found wrong, and nothing went wrong.
    Fine,
    /// The damage was seen — refused or reported with its file named —
    /// and nothing went wrong.
    Caught,
    Unlocated(String),
    Panicked(String),
    /// Killed by a signal (an abort) or an exit code other than 0, 1, 2.
    BadExit(String),
    /// `verify` still red after a run.
    Unhealed(String),
    /// Something appeared or changed outside the results folder.
    Outside(String),
    /// An `ltcal` process killed at the deadline.
    Hung(String),
}

/// The counts of one kind.
#[derive(Default, Debug)]
pub struct Tally {
    pub cases: usize,
    /// Cases whose damage was seen (refused, reported, healed).
    pub caught: usize,
    pub unlocated: usize,
    pub panics: usize,
    pub hangs: usize,
    pub bad_exits: usize,
    pub unhealed: usize,
    pub outside: usize,
    /// The first findings, with their case numbers.
    pub found: Vec<String>,
}

impl Tally {
    pub fn clean(&self) -> bool {
        self.unlocated + self.panics + self.hangs + self.bad_exits + self.unhealed + self.outside
            == 0
    }

    fn add(&mut self, kind: Kind, n: u64, v: Option<Verdict>) {
        self.cases += 1;
        let what = match v {
            Some(Verdict::Fine) => return,
            Some(Verdict::Caught) => {
                self.caught += 1;
                return;
            }
            None => {
                self.hangs += 1;
                "over the deadline".to_string()
            }
            Some(Verdict::Unlocated(m)) => {
                self.unlocated += 1;
                format!("no file named: {m}")
            }
            Some(Verdict::Panicked(m)) => {
                self.panics += 1;
                format!("panic: {m}")
            }
            Some(Verdict::BadExit(m)) => {
                self.bad_exits += 1;
                format!("exit: {m}")
            }
            Some(Verdict::Unhealed(m)) => {
                self.unhealed += 1;
                format!("not healed: {m}")
            }
            Some(Verdict::Outside(m)) => {
                self.outside += 1;
                format!("outside: {m}")
            }
            Some(Verdict::Hung(m)) => {
                self.hangs += 1;
                format!("hang: {m}")
            }
        };
        if self.found.len() < 20 {
            self.found.push(format!("{kind:?} case {n}: {what}"));
        }
    }
}

const SWEEP_TEXT: &str = r#"
[pipeline]
name = "fz-sweep"

[stages.truth]
kind = "inject"
preset = "table2"

[stages.target]
kind = "mesh"
shape = "plane"
x_mm = 3000.0
y = { from = 0, to = 0, step = 1 }
z = { from = 0, to = 0, step = 1 }

[stages.reading]
kind = "measure"
inputs = { points = "target", errors = "truth" }
noise = { sigma_angle_urad = 1.0, sigma_range_um = 2.0 }
seed = 0

[[sweep.axis]]
path = "stages.reading.seed"
range = { from = 0, to = 3, step = 1 }

[sweep]
gather = ["reading.readings"]
"#;

/// The cheap chain without a sweep: loose entries, published tables.
fn loose_text() -> String {
    SWEEP_TEXT
        .split("[[sweep.axis]]")
        .next()
        .unwrap()
        .replace("fz-sweep", "fz-loose")
}

/// Two cheap pipelines (a 4-point sweep, packed; the same chain loose) run
/// once by the binary: the pristine results every case starts from.
struct Fixture {
    _tmp: tempfile::TempDir,
    root: PathBuf,
    shared: Arc<Shared>,
}

/// What a case needs of the fixture (shared with worker threads).
struct Shared {
    sweep: PathBuf,
    loose: PathBuf,
    results: PathBuf,
    /// Every path below each pipeline's folder, relative to `results`,
    /// folders included.
    paths: Vec<PathBuf>,
    /// `jobs.json` as a coordinator writes it for the sweep.
    jobs: Vec<u8>,
}

impl Shared {
    fn with(&self, pred: impl Fn(&Path) -> bool) -> Vec<PathBuf> {
        self.paths.iter().filter(|p| pred(p)).cloned().collect()
    }
}

fn walk(dir: &Path, base: &Path, out: &mut Vec<PathBuf>) {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return;
    };
    let mut v: Vec<_> = rd.flatten().map(|e| e.path()).collect();
    v.sort();
    for p in v {
        out.push(p.strip_prefix(base).unwrap().to_path_buf());
        if p.symlink_metadata().is_ok_and(|m| m.is_dir()) {
            walk(&p, base, out);
        }
    }
}

fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let t = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_tree(&e.path(), &t);
        } else {
            std::fs::copy(e.path(), &t).unwrap();
        }
    }
}

/// Removes `dir` whatever was planted in it (permissions given back first,
/// links removed, never followed).
fn wipe(dir: &Path) {
    use std::os::unix::fs::PermissionsExt as _;
    let mut all = Vec::new();
    walk(dir, dir, &mut all);
    for p in all {
        let p = dir.join(p);
        if p.symlink_metadata().is_ok_and(|m| !m.is_symlink()) {
            let _ = std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o755));
        }
    }
    let _ = std::fs::remove_dir_all(dir);
}

impl Fixture {
    fn new() -> Fixture {
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path().to_path_buf();
        let sweep = root.join("fz-sweep.toml");
        let loose = root.join("fz-loose.toml");
        std::fs::write(&sweep, SWEEP_TEXT).unwrap();
        std::fs::write(&loose, loose_text()).unwrap();
        let results = root.join("results");
        for f in [&sweep, &loose] {
            let out = Command::new(BIN)
                .current_dir(&root)
                .args(["run", f.to_str().unwrap(), "-q", "--results"])
                .arg(&results)
                .output()
                .unwrap();
            assert!(out.status.success(), "{out:?}");
        }
        let mut paths = Vec::new();
        walk(&results, &results, &mut paths);
        let p = pipeline::load(&sweep, &[]).unwrap();
        let record = |job: &str, points: &[usize]| JobRecord {
            job: job.into(),
            wave: results.join("fz-sweep/slurm/wave-20260101T000000Z-1"),
            units: points
                .chunks(2)
                .map(|c| Unit {
                    first: c[0],
                    last: c[c.len() - 1],
                    points: cluster::ranges(c),
                })
                .collect(),
            code: ltcal::CODE_FINGERPRINT.into(),
            pipeline_hash: ltcal::pipeline::cache::hash_bytes(SWEEP_TEXT.as_bytes()),
            set_args: vec![],
            submitted: "2026-01-01T00:00:00Z".into(),
        };
        let n = p.sweep.as_ref().unwrap().len();
        let all: Vec<usize> = (0..n).collect();
        let jobs =
            serde_json::to_vec_pretty(&[record("41", &all), record("42", &all[1..])]).unwrap();
        Fixture {
            _tmp: tmp,
            root: root.clone(),
            shared: Arc::new(Shared {
                sweep,
                loose,
                results,
                paths,
                jobs,
            }),
        }
    }
}

/// A case run by a worker in its own folder.
type Job = Box<dyn FnOnce(&Path) -> Verdict + Send>;

/// A worker thread; a case that outlives the deadline is a hang, and the
/// worker is abandoned (blocked where it hung) for a new one in a new
/// folder.
struct Runner {
    root: PathBuf,
    n: usize,
    send: mpsc::Sender<Job>,
    recv: mpsc::Receiver<Verdict>,
}

impl Runner {
    fn new(root: &Path) -> Runner {
        let (send, recv) = Runner::spawn(root, 0);
        Runner {
            root: root.to_path_buf(),
            n: 0,
            send,
            recv,
        }
    }

    fn spawn(root: &Path, n: usize) -> (mpsc::Sender<Job>, mpsc::Receiver<Verdict>) {
        let (send, jobs) = mpsc::channel::<Job>();
        let (results, recv) = mpsc::channel();
        let dir = root.join(format!("w{n}"));
        std::thread::spawn(move || {
            for job in jobs {
                let v = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| job(&dir)))
                    .unwrap_or_else(|p| {
                        Verdict::Panicked(
                            p.downcast_ref::<String>()
                                .cloned()
                                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                                .unwrap_or_default(),
                        )
                    });
                if results.send(v).is_err() {
                    return;
                }
            }
        });
        (send, recv)
    }

    fn run(&mut self, job: Job, deadline: Duration) -> Option<Verdict> {
        self.send.send(job).unwrap();
        match self.recv.recv_timeout(deadline) {
            Ok(v) => Some(v),
            Err(_) => {
                self.n += 1;
                (self.send, self.recv) = Runner::spawn(&self.root, self.n);
                None
            }
        }
    }
}

/// The deadline of an in-process case (a cheap chain runs in well under a
/// second).
const DEADLINE: Duration = Duration::from_secs(20);
/// The deadline of one `ltcal` process.
const CHILD_DEADLINE: Duration = Duration::from_secs(30);

/// Runs `count` cases of `kind`, numbered from `first`.
pub fn fuzz(kind: Kind, first: u64, count: u64) -> Tally {
    let fx = Fixture::new();
    let mut tally = Tally::default();
    let mut runner = Runner::new(&fx.root.join("workers"));
    let files_dir = fx.root.join("files");
    for n in first..first + count {
        let mut r = Rng::new(n ^ 0x5EED_F11E);
        let sh = fx.shared.clone();
        let v = match kind {
            Kind::Pack => runner.run(Box::new(move |d| cache_case(&sh, d, n, true)), DEADLINE),
            Kind::Loose => runner.run(Box::new(move |d| cache_case(&sh, d, n, false)), DEADLINE),
            Kind::Jobs => runner.run(Box::new(move |d| jobs_case(&sh, d, n)), DEADLINE),
            Kind::Slurm => runner.run(Box::new(move |d| slurm_case(&sh, d, n)), DEADLINE),
            Kind::Files => Some(files_case(&sh, &files_dir, &mut r)),
        };
        tally.add(kind, n, v);
    }
    tally
}

/// Whether an error message names a file below `dir`.
fn names_a_file(msg: &str, dir: &Path) -> bool {
    msg.contains(dir.to_str().unwrap())
}

/// A fresh copy of the pristine results in `dir/results`; nothing else in
/// `dir`.
fn fresh(sh: &Shared, dir: &Path) -> PathBuf {
    wipe(dir);
    let results = dir.join("results");
    copy_tree(&sh.results, &results);
    results
}

/// What `dir` holds besides `results`: must stay nothing.
fn outside_results(dir: &Path) -> Option<Verdict> {
    let extra: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n != "results")
        .collect();
    (!extra.is_empty()).then(|| Verdict::Outside(format!("{} gained {extra:?}", dir.display())))
}

/// Byte damage: 1 to 3 of a bit flipped, the file cut, bytes appended
/// (zeros or junk), a run zeroed, a byte set, junk inserted.
fn damage(b: &[u8], r: &mut Rng) -> Vec<u8> {
    let mut b = b.to_vec();
    for _ in 0..=r.below(3) {
        let at = r.below(b.len() + 1);
        let byte = at.min(b.len().saturating_sub(1));
        match r.below(6) {
            0 if !b.is_empty() => b[byte] ^= 1 << r.below(8),
            1 => b.truncate(at),
            2 => {
                let n = 1 + r.below(64);
                let zeros = r.below(2) == 0;
                b.extend((0..n).map(|_| if zeros { 0 } else { r.next() as u8 }));
            }
            3 => {
                let end = (at + 1 + r.below(64)).min(b.len());
                b[at.min(end)..end].fill(0);
            }
            4 if !b.is_empty() => b[byte] = r.next() as u8,
            _ => {
                let junk: Vec<u8> = (0..=r.below(16)).map(|_| r.next() as u8).collect();
                b.splice(at..at, junk);
            }
        }
    }
    b
}

/// Values a field of a pack's index could be damaged to.
const EDGES: &[u64] = &[
    0,
    1,
    2,
    3,
    4,
    7,
    8,
    48,
    255,
    4096,
    u32::MAX as u64,
    u64::MAX,
    1 << 40,
];

/// Damage aimed at a pack's structure: the trailer, the index (with its
/// hash then made valid again, so the damage gets past the hash), two
/// entries' spans swapped, or plain byte damage.
fn damage_pack(b: &[u8], r: &mut Rng) -> Vec<u8> {
    let n = b.len();
    if n < 64 {
        return damage(b, r);
    }
    let trailer = n - 56;
    let ix_at = u64::from_le_bytes(b[trailer..trailer + 8].try_into().unwrap()) as usize;
    let mut b = b.to_vec();
    let rehash = |b: &mut Vec<u8>| {
        let h = *blake3::hash(&b[ix_at..trailer]).as_bytes();
        b[trailer + 16..trailer + 48].copy_from_slice(&h);
    };
    match r.below(6) {
        0 | 1 => return damage(&b, r),
        2 => {
            let at = trailer + r.below(56);
            b[at] = r.next() as u8;
        }
        3 => {
            // A u32 or u64 field of the index at an edge value.
            let at = ix_at + r.below(trailer - ix_at);
            let v = EDGES[r.below(EDGES.len())];
            let w = if r.below(2) == 0 { 4 } else { 8 };
            let end = (at + w).min(trailer);
            b[at..end].copy_from_slice(&v.to_le_bytes()[..end - at]);
            rehash(&mut b);
        }
        4 => {
            // Two entries' spans swapped (each entry: key 32, offset 8, len 8).
            let count = u64::from_le_bytes(b[ix_at..ix_at + 8].try_into().unwrap()) as usize;
            if count >= 2 {
                let (i, j) = (r.below(count), r.below(count));
                let span = |k: usize| ix_at + 8 + 48 * k + 32;
                let (si, sj) = (span(i), span(j));
                let a: Vec<u8> = b[si..si + 16].to_vec();
                let c: Vec<u8> = b[sj..sj + 16].to_vec();
                b[si..si + 16].copy_from_slice(&c);
                b[sj..sj + 16].copy_from_slice(&a);
            }
            rehash(&mut b);
        }
        _ => {
            let at = ix_at + r.below(trailer - ix_at);
            b[at] ^= 1 << r.below(8);
            rehash(&mut b);
        }
    }
    b
}

/// JSON values a field could be damaged to.
const JSON_VALUES: &[&str] = &[
    "null",
    "0",
    "-1",
    "18446744073709551615",
    "1e400",
    "\"\"",
    "\"../../outside\"",
    "\"/dev/zero\"",
    "\"0-99999999999\"",
    "\"0-3,0-3,0-3\"",
    "\"3-0\"",
    "[]",
    "{}",
    "[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]",
    "true",
    "\"\\u0000\"",
    "\"\u{1F642}\"",
];

/// A JSON text damaged: a value replaced (keeping the line's comma), or
/// [`mutate`]'s line and byte damage.
fn damage_json(text: &[u8], r: &mut Rng) -> Vec<u8> {
    let text = String::from_utf8_lossy(text);
    if r.below(3) == 0 {
        return mutate(&text, r);
    }
    let mut lines: Vec<String> = text.lines().map(String::from).collect();
    for _ in 0..=r.below(2) {
        let i = r.below(lines.len());
        let l = &lines[i];
        let v = JSON_VALUES[r.below(JSON_VALUES.len())];
        if let Some((k, rest)) = l.split_once("\": ") {
            let comma = if rest.ends_with(',') { "," } else { "" };
            lines[i] = format!("{k}\": {v}{comma}");
        } else if l.trim_start().starts_with('"') || l.trim_start().starts_with(char::is_numeric) {
            let comma = if l.ends_with(',') { "," } else { "" };
            lines[i] = format!("{v}{comma}");
        }
    }
    (lines.join("\n") + "\n").into_bytes()
}

fn opts(results: &Path) -> run::RunOptions {
    run::RunOptions {
        results_root: results.to_path_buf(),
        keep_going: false,
        progress: false,
        not_computed: None,
        experiment: None,
        control: Default::default(),
    }
}

/// Reads a damaged cache back every way the runner does, runs, and
/// checks the cache verifies after the run.
fn read_back(results: &Path, file: &Path) -> Verdict {
    let p = pipeline::load(file, &[]).unwrap();
    let dir = run::pipeline_dir(results, &p);
    let store = Store::new(&dir);
    let v = store.verify();
    let mut seen = !(v.problems.is_empty() && v.superseded.is_empty());
    for why in v.problems.iter().chain(&v.superseded) {
        if !names_a_file(why, &dir) {
            return Verdict::Unlocated(format!("verify: {why}"));
        }
    }
    let _ = plan::plan(&p, &store);
    let mut shown: Vec<(String, Option<String>)> =
        p.stages.iter().map(|s| (s.name.clone(), None)).collect();
    if p.sweep.is_some() {
        shown.push(("sweep".into(), Some("reading.readings".into())));
    }
    for (stage, table) in shown {
        if let Err(e) = published::read(&p, &store, &dir, &stage, table.as_deref(), "ltcal run") {
            let m = format!("{e:#}");
            // "not run yet" and the like name the stage; a read that
            // failed names the file.
            if !names_a_file(&m, &dir) && !m.contains(&format!("`{stage}`")) {
                return Verdict::Unlocated(format!("show {stage}: {m}"));
            }
            seen |= names_a_file(&m, &dir);
        }
    }
    match ltcal::pipeline::publish::run(&p, &opts(results)) {
        Err(e) => {
            let m = format!("{e:#}");
            if !names_a_file(&m, &dir) {
                return Verdict::Unlocated(format!("run: {m}"));
            }
        }
        Ok(rep) => {
            if let Some(f) = rep.failed().first() {
                return Verdict::Unhealed(format!("a stage failed on a damaged cache: {f:?}"));
            }
        }
    }
    let after = Store::new(&dir).verify();
    if !after.problems.is_empty() {
        return Verdict::Unhealed(format!("verify after the run: {:?}", after.problems));
    }
    if seen { Verdict::Caught } else { Verdict::Fine }
}

/// A pack (`packs`) or a loose entry's file or a published table damaged.
fn cache_case(sh: &Shared, dir: &Path, n: u64, packs: bool) -> Verdict {
    let mut r = Rng::new(n);
    let results = fresh(sh, dir);
    let (targets, file) = if packs {
        (
            sh.with(|p| p.extension().is_some_and(|x| x == "pack")),
            &sh.sweep,
        )
    } else {
        (
            sh.with(|p| {
                p.starts_with("fz-loose")
                    && (p.ends_with("manifest.json")
                        || p.extension().is_some_and(|x| x == "parquet"))
            }),
            &sh.loose,
        )
    };
    let target = results.join(&targets[r.below(targets.len())]);
    let bytes = std::fs::read(&target).unwrap();
    let damaged = if packs {
        damage_pack(&bytes, &mut r)
    } else if target.ends_with("manifest.json") && r.below(2) == 0 {
        damage_json(&bytes, &mut r)
    } else {
        damage(&bytes, &mut r)
    };
    std::fs::write(&target, damaged).unwrap();
    match read_back(&results, file) {
        v @ (Verdict::Fine | Verdict::Caught) => outside_results(dir).unwrap_or(v),
        v => v,
    }
}

/// A scheduler stand-in: every job is listed with tasks in one state (or
/// not known), submissions get a number.
struct Fake {
    state: Option<&'static str>,
}

impl Scheduler for Fake {
    fn name(&self) -> &'static str {
        "Slurm"
    }
    fn script(&self, job: &ArrayJob) -> String {
        Slurm.script(job)
    }
    fn submit(&self, _: &Path) -> anyhow::Result<String> {
        Ok("4242".into())
    }
    fn tasks(&self, _: &str) -> anyhow::Result<Option<Vec<TaskState>>> {
        Ok(self.state.map(|s| {
            (0..3)
                .map(|index| TaskState {
                    index,
                    state: s.into(),
                    node: "n1".into(),
                })
                .collect()
        }))
    }
    fn cancel(&self, _: &[String]) -> anyhow::Result<()> {
        Ok(())
    }
    fn task_prefix(&self, job: &str, task: usize) -> String {
        format!("slurm-{job}_{task}")
    }
}

/// `jobs.json` damaged, read by `status` and by the coordinator (detached,
/// or waiting on a wave that ends at once); sometimes with a pack taken
/// out so that points are submitted too.
fn jobs_case(sh: &Shared, dir: &Path, n: u64) -> Verdict {
    let mut r = Rng::new(n);
    let results = fresh(sh, dir);
    let p = pipeline::load(&sh.sweep, &[]).unwrap();
    let pdir = run::pipeline_dir(&results, &p);
    let path = pdir.join(".ltcal/slurm/jobs.json");
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let damaged = match r.below(4) {
        0 => damage(&sh.jobs, &mut r),
        _ => damage_json(&sh.jobs, &mut r),
    };
    std::fs::write(&path, damaged).unwrap();
    // Or not a file at all (a link outside would point at nothing here:
    // this folder holds only `results`).
    if r.below(5) == 0 {
        let what = [
            "a FIFO",
            "a link to /dev/zero",
            "a folder",
            "a dangling link",
        ][r.below(4)];
        plant(&path, what, dir, &mut r);
    }
    if r.below(3) == 0 {
        for pack in sh.with(|p| p.extension().is_some_and(|x| x == "pack")) {
            std::fs::remove_file(results.join(pack)).unwrap();
        }
    }
    let detach = r.below(2) == 0;
    let state = [None, Some("COMPLETED"), Some("NODE_FAIL"), Some("RUNNING")]
        [r.below(if detach { 4 } else { 3 })];
    let fake = Fake { state };
    let o = opts(&results);
    let check = |e: anyhow::Error, what: &str| {
        let m = format!("{e:#}");
        (!names_a_file(&m, &pdir)).then(|| Verdict::Unlocated(format!("{what}: {m}")))
    };
    let mut seen = false;
    if let Err(e) = cluster::status(&p, &o, &fake) {
        if let Some(v) = check(e, "status") {
            return v;
        }
        seen = true;
    }
    let c = cluster::ClusterOptions {
        pipeline_file: sh.sweep.clone(),
        set_args: vec![],
        detach,
        interrupted: Arc::new(AtomicBool::new(false)),
    };
    if let Err(e) = cluster::run(&p, &o, &c, &fake) {
        if let Some(v) = check(e, "coordinator") {
            return v;
        }
        seen = true;
    }
    outside_results(dir).unwrap_or(if seen { Verdict::Caught } else { Verdict::Fine })
}

/// Long option names sbatch knows, ltcal's own first.
const OWN_LONG: &[&str] = &[
    "array",
    "output",
    "error",
    "export",
    "export-file",
    "chdir",
    "workdir",
];
const OTHER_LONG: &[&str] = &[
    "qos",
    "partition",
    "time",
    "mem",
    "hold",
    "nice",
    "comment",
    "job-name",
    "exclusive",
    "wrap",
    "open-mode",
    "begin",
    "dependency",
    "signal",
    "get-user-env",
    "requeue",
    "no-requeue",
    "input",
    "ntasks",
    "x11",
    "gres",
];
/// Values and fragments: quotes, shell syntax, comments, newlines, another
/// option hidden in a value.
const PIECES: &[&str] = &[
    "1",
    "x",
    "long",
    "'q'",
    "\"q\"",
    "a b",
    "$(touch pwned)",
    "`touch pwned`",
    "; touch pwned",
    "#c",
    "\\",
    "\n",
    "\t",
    "\r",
    "ALL,PATH=/tmp",
    "/dev/null",
    "%j.out",
    "0-99",
    "--array=1",
    "-o x",
    "'--output=x'",
    "\"--arr=1\"",
    "--ar\"ra\"y=1",
    "--out\\put=x",
    "-Ho",
    "x\\ --outp=/tmp/l",
    "\\ --ar=1",
    "-Jao",
    "-ba",
    "--",
    "packjob",
    "\u{1F642}",
];
/// sbatch's short options that take a value (the rest of their word, or
/// the next word): every letter after one of these is its value.
const SHORT_VALUED: &str = "AabBcCDdeFGiJLMmNnopqStwx";
/// ltcal's own short options (`-a` array, `-o` output, `-e` error, `-D` chdir).
const OWN_SHORT: &str = "aoeD";

/// One generated `sbatch_options` entry.
fn sbatch_entry(r: &mut Rng) -> String {
    let mut words = Vec::new();
    for _ in 0..=r.below(2) {
        let w = match r.below(5) {
            0 | 1 => {
                let names = if r.below(2) == 0 {
                    OWN_LONG
                } else {
                    OTHER_LONG
                };
                let name = names[r.below(names.len())];
                let cut = 1 + r.below(name.len());
                let name = &name[..cut];
                let value = PIECES[r.below(PIECES.len())];
                match r.below(3) {
                    0 => format!("--{name}"),
                    1 => format!("--{name}={value}"),
                    _ => format!("--{name} {value}"),
                }
            }
            2 => {
                let letters: String = (0..=r.below(3))
                    .map(|_| {
                        let set = b"aoeDJqpHtNcnxAQWVvkhsOIbBGiLMmSdwF";
                        set[r.below(set.len())] as char
                    })
                    .collect();
                format!("-{letters}")
            }
            3 => PIECES[r.below(PIECES.len())].to_string(),
            _ => {
                // A valid option wrapped in quotes sbatch removes.
                let name = OWN_LONG[r.below(OWN_LONG.len())];
                let q = ["'", "\"", ""][r.below(3)];
                format!(
                    "{q}--{}{q}={}",
                    &name[..1 + r.below(name.len())],
                    r.below(9)
                )
            }
        };
        words.push(w);
    }
    words.join(" ")
}

/// TOML string of `s`.
fn toml_str(s: &str) -> String {
    toml::Value::String(s.to_string()).to_string()
}

/// The words sbatch makes of an `#SBATCH` line, as Slurm's
/// `_get_argument` (src/sbatch/opt.c) makes them: unquoted whitespace ends
/// a word — even right after a backslash, which is dropped; a backslash
/// otherwise copies the next character; `'` and `"` quote; an unquoted `#`
/// ends the line, and so does an empty word.
fn sbatch_argv(line: &str) -> Vec<String> {
    let mut line = line.to_string();
    for word in ["packjob", "hetjob"] {
        while let Some(at) = line.to_lowercase().find(word) {
            line.replace_range(at..at + word.len(), &" ".repeat(word.len()));
        }
    }
    let c: Vec<char> = line.chars().collect();
    let mut i = 0;
    let mut out = Vec::new();
    loop {
        while i < c.len() && c[i].is_whitespace() {
            i += 1;
        }
        let mut w = String::new();
        let mut quote: Option<char> = None;
        let mut escaped = false;
        while i < c.len() && (quote.is_some() || !c[i].is_whitespace()) && c[i] != '\n' {
            if escaped {
                escaped = false;
            } else if c[i] == '\\' {
                escaped = true;
                i += 1;
                continue;
            } else if let Some(q) = quote {
                if c[i] == q {
                    quote = None;
                    i += 1;
                    continue;
                }
            } else if c[i] == '"' || c[i] == '\'' {
                quote = Some(c[i]);
                i += 1;
                continue;
            } else if c[i] == '#' {
                break;
            }
            w.push(c[i]);
            i += 1;
        }
        if w.is_empty() {
            return out;
        }
        out.push(w);
    }
}

/// The option of ltcal's own an `#SBATCH` line would set, read as sbatch's
/// getopt reads its words (a unique or ambiguous prefix of a long name, a
/// short letter alone or in a cluster). Every word is checked, even one
/// that may be the previous option's value: never too lenient.
fn sets_own(line: &str) -> Option<String> {
    for w in sbatch_argv(line) {
        if let Some(long) = w.strip_prefix("--") {
            let name = long.split('=').next().unwrap();
            if !name.is_empty() && OWN_LONG.iter().any(|o| o.starts_with(name)) {
                return Some(w);
            }
        } else if let Some(short) = w.strip_prefix('-') {
            for c in short.chars() {
                if OWN_SHORT.contains(c) {
                    return Some(w);
                }
                if SHORT_VALUED.contains(c) {
                    break;
                }
            }
        }
    }
    None
}

/// The job script of `settings`: `#!/bin/sh`, ltcal's own `#SBATCH` lines
/// first and unchanged, one line per setting (a value one word, no quote),
/// one per `sbatch_options` entry, none setting ltcal's own options; then
/// the body, exactly the one of default settings.
fn check_script(p: &pipeline::resolve::Pipeline, job: &ArrayJob, tasks: usize) -> Option<String> {
    let script = Slurm.script(job);
    let default = cluster::SlurmSettings::default();
    let plain = Slurm.script(&ArrayJob {
        settings: &default,
        command: job.command.clone(),
        ..*job
    });
    let body = |s: &str| -> Vec<String> {
        s.lines()
            .skip(1)
            .filter(|l| !l.starts_with("#SBATCH "))
            .map(String::from)
            .collect()
    };
    if !script.starts_with("#!/bin/sh\n") || body(&script) != body(&plain) {
        return Some(format!("the body changed:\n{script}"));
    }
    let heads: Vec<&str> = script
        .lines()
        .skip(1)
        .take_while(|l| l.starts_with("#SBATCH "))
        .map(|l| &l["#SBATCH ".len()..])
        .collect();
    let s = &p.slurm;
    let expected = 7
        + [
            s.partition.is_some(),
            s.account.is_some(),
            s.time_limit.is_some(),
            s.memory_mb.is_some(),
        ]
        .iter()
        .filter(|x| **x)
        .count()
        + s.sbatch_options.len();
    if heads.len() != expected
        || script.lines().filter(|l| l.starts_with("#SBATCH")).count() != expected
    {
        return Some(format!(
            "{} #SBATCH lines, not {expected}:\n{script}",
            heads.len()
        ));
    }
    let own = [
        format!("--job-name=ltcal-{}", p.name),
        format!(
            "--array=0-{}%{}",
            tasks - 1,
            s.max_running.min(tasks).max(1)
        ),
        "--output=/dev/null".into(),
        "--error=/dev/null".into(),
        "--export=ALL".into(),
    ];
    if heads[..5] != own {
        return Some(format!("ltcal's own lines changed:\n{script}"));
    }
    for (i, h) in heads.iter().enumerate().skip(5) {
        if h.chars().any(char::is_control) {
            return Some(format!("a control character in `{h:?}`"));
        }
        if let Some(w) = sets_own(h) {
            return Some(format!("`#SBATCH {h}` sets ltcal's own option ({w})"));
        }
        let setting = i < expected - s.sbatch_options.len() && i >= 7;
        if setting && (sbatch_argv(h) != [h.to_string()]) {
            return Some(format!("a setting's value is not one plain word: `{h}`"));
        }
    }
    None
}

/// Folder names a job script's paths could hold.
const HOSTILE_NAMES: &[&str] = &[
    "a b",
    "q'uote",
    "d\"q",
    "$(touch pwned)",
    "`touch pwned`",
    "x;touch pwned",
    "nl\ntouch pwned",
    "$HOME",
    "*",
    "-n",
    "back\\slash",
    "\u{1F642}",
];

/// `[executor.slurm]` settings generated, loaded; what loads makes a job
/// script that is checked; every 16th case runs the script with `/bin/sh`
/// below a folder with a hostile name, with a `PATH` that finds nothing.
fn slurm_case(sh: &Shared, dir: &Path, n: u64) -> Verdict {
    let mut r = Rng::new(n);
    let mut text = format!("{SWEEP_TEXT}\n[executor.slurm]\n");
    let mut sets = Vec::new();
    let entries: Vec<String> = (0..r.below(4)).map(|_| sbatch_entry(&mut r)).collect();
    let list = format!(
        "[{}]",
        entries
            .iter()
            .map(|e| toml_str(e))
            .collect::<Vec<_>>()
            .join(", ")
    );
    if r.below(4) == 0 {
        sets.push(format!("executor.slurm.sbatch_options={list}"));
    } else {
        text += &format!("sbatch_options = {list}\n");
    }
    for field in ["partition", "account", "time_limit"] {
        if r.below(3) == 0 {
            let v = if r.below(2) == 0 {
                PIECES[r.below(PIECES.len())].to_string()
            } else {
                sbatch_entry(&mut r)
            };
            text += &format!("{field} = {}\n", toml_str(&v));
        }
    }
    if r.below(4) == 0 {
        text += &format!("memory_mb = {}\n", VALUES[r.below(VALUES.len())]);
    }
    if r.below(4) == 0 {
        text += &format!("max_running = {}\n", VALUES[r.below(VALUES.len())]);
    }
    let overrides: Vec<_> = match sets
        .iter()
        .map(|s| ltcal::pipeline::resolve::Override::parse(s))
        .collect::<anyhow::Result<Vec<_>>>()
    {
        Ok(o) => o,
        Err(e) => {
            let m = e.to_string();
            return if m.contains("--set") {
                Verdict::Caught
            } else {
                Verdict::Unlocated(m)
            };
        }
    };
    let p = match ltcal::pipeline::load_source(
        &ltcal::diagnostics::Source::new(&sh.sweep, text.as_str()),
        &overrides,
    ) {
        Ok(p) => p,
        Err(e) => {
            // Located in the file, or naming the `--set`.
            let m = format!("{e:#}");
            let located = e
                .downcast_ref::<ltcal::pipeline::InputError>()
                .is_some_and(|i| crate::fuzz::located(&i.0));
            return if located || (!sets.is_empty() && m.contains("--set")) {
                Verdict::Caught
            } else {
                Verdict::Unlocated(m)
            };
        }
    };
    let tasks = 1 + r.below(5);
    let name = if n % 16 == 0 {
        HOSTILE_NAMES[r.below(HOSTILE_NAMES.len())]
    } else {
        "plain"
    };
    wipe(dir);
    let place = dir.join(name);
    std::fs::create_dir_all(&place).unwrap();
    let units = place.join("points.txt");
    std::fs::write(&units, "0-1 0-1\n2-3 2,3\n4-5 4-5\n5-5 5\n6-6 6\n").unwrap();
    let command = vec![
        "/bin/echo".to_string(),
        "task".into(),
        place.display().to_string(),
    ];
    let job = ArrayJob {
        name: &p.name,
        tasks,
        settings: &p.slurm,
        workdir: &place,
        wave: &place,
        units: &units,
        command,
    };
    if let Some(why) = check_script(&p, &job, tasks) {
        return Verdict::Unlocated(format!("job script: {why}"));
    }
    if n % 16 == 0 {
        let script = dir.join("job.sh");
        std::fs::write(&script, Slurm.script(&job)).unwrap();
        let st = Command::new("/bin/sh")
            .arg(&script)
            .current_dir(dir)
            .env_clear()
            .env("PATH", dir.join("nothing"))
            .env("SLURM_ARRAY_TASK_ID", "1")
            .env("SLURM_ARRAY_JOB_ID", "7")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .unwrap();
        let log = place.join("points-2-3.log");
        let want = format!("task {} --points 2,3 --prefix slurm-7_1\n", place.display());
        let got = std::fs::read_to_string(&log).unwrap_or_default();
        if !st.success() || got != want {
            return Verdict::Outside(format!(
                "the job script below {name:?} ran {st}, logged {got:?}, not {want:?}"
            ));
        }
        let mut all = Vec::new();
        walk(dir, dir, &mut all);
        all.sort();
        let expected = vec![
            PathBuf::from("job.sh"),
            PathBuf::from(name),
            Path::new(name).join("points-2-3.log"),
            Path::new(name).join("points.txt"),
        ];
        let mut expected = expected;
        expected.sort();
        if all != expected {
            return Verdict::Outside(format!("the job script made {all:?}"));
        }
    }
    Verdict::Fine
}

/// What is planted at a path.
const PLANTS: &[&str] = &[
    "a FIFO",
    "a link to /dev/zero",
    "a link to a folder outside",
    "a link to a file outside",
    "a dangling link",
    "a folder",
    "chmod 000",
    "damaged bytes",
];

fn plant(path: &Path, what: &str, case: &Path, r: &mut Rng) {
    use std::os::unix::fs::PermissionsExt as _;
    let meta = path.symlink_metadata().ok();
    let remove = || match &meta {
        Some(m) if m.is_dir() => wipe(path),
        Some(_) => std::fs::remove_file(path).unwrap(),
        None => {}
    };
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let link = |to: &Path| {
        remove();
        std::os::unix::fs::symlink(to, path).unwrap();
    };
    match what {
        "a FIFO" => {
            remove();
            let c = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
            assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0);
        }
        "a link to /dev/zero" => link(Path::new("/dev/zero")),
        "a link to a folder outside" => link(&case.join("outside")),
        "a link to a file outside" => link(&case.join("outside/sentinel.txt")),
        "a dangling link" => link(&case.join("nowhere")),
        "a folder" => {
            if meta.as_ref().is_some_and(|m| m.is_dir()) {
                // A file where a folder is expected.
                remove();
                std::fs::write(path, b"not a folder").unwrap();
            } else {
                remove();
                std::fs::create_dir_all(path.join("inner")).unwrap();
                std::fs::write(path.join("inner/x"), b"x").unwrap();
            }
        }
        "chmod 000" => {
            if meta.is_some() {
                std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o000)).unwrap();
            }
        }
        _ => {
            if meta.as_ref().is_some_and(|m| m.is_file()) {
                let b = std::fs::read(path).unwrap();
                let d = if path.extension().is_some_and(|x| x == "pack") {
                    damage_pack(&b, r)
                } else if path.extension().is_some_and(|x| x == "json") {
                    damage_json(&b, r)
                } else {
                    damage(&b, r)
                };
                std::fs::write(path, d).unwrap();
            }
        }
    }
}

/// Everything in the case folder but `results/`: (path, kind, length).
fn around(case: &Path) -> Vec<(PathBuf, String, u64)> {
    let mut all = Vec::new();
    walk(case, case, &mut all);
    all.into_iter()
        .filter(|p| !p.starts_with("results"))
        .map(|p| {
            let m = case.join(&p).symlink_metadata().unwrap();
            (p, format!("{:?}", m.file_type()), m.len())
        })
        .collect()
}

/// `ltcal <args>` in `case`, killed after [`CHILD_DEADLINE`]: its exit
/// code and stderr, or `None` on a hang.
fn ltcal(case: &Path, args: &[&str]) -> Option<(Option<i32>, String)> {
    let mut child = Command::new(BIN)
        .current_dir(case)
        .args(args)
        .env("TMPDIR", case.join("tmp"))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let err = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = std::io::Read::read_to_string(&mut std::io::Read::take(err, 1 << 20), &mut s);
        s
    });
    let t0 = Instant::now();
    loop {
        if let Some(st) = child.try_wait().unwrap() {
            let err = reader.join().unwrap();
            use std::os::unix::process::ExitStatusExt as _;
            return Some((st.code().or(st.signal().map(|s| -s)), err));
        }
        if t0.elapsed() > CHILD_DEADLINE {
            let _ = child.kill();
            let _ = child.wait();
            return None;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// A hostile file type or damaged bytes at a path below
/// `results/<pipeline>/`, met by a read command, then `run`, then `verify`.
fn files_case(sh: &Shared, case: &Path, r: &mut Rng) -> Verdict {
    wipe(case);
    let results = case.join("results");
    copy_tree(&sh.results, &results);
    std::fs::create_dir_all(case.join("outside")).unwrap();
    std::fs::write(case.join("outside/sentinel.txt"), b"mine").unwrap();
    std::fs::create_dir_all(case.join("tmp")).unwrap();
    // Paths the runner reads or writes: every pristine one, and those a
    // run makes when missing.
    let mut targets: Vec<PathBuf> = sh.paths.clone();
    for p in ["fz-sweep", "fz-loose"] {
        targets.push(PathBuf::from(p));
        targets.push(Path::new(p).join(".ltcal/slurm/jobs.json"));
        targets.push(Path::new(p).join(".ltcal/slurm"));
    }
    let rel = targets[r.below(targets.len())].clone();
    let sweep = rel.starts_with("fz-sweep");
    let file = if sweep { &sh.sweep } else { &sh.loose };
    let what = PLANTS[r.below(PLANTS.len())];
    let planted = results.join(&rel);
    plant(&planted, what, case, r);
    let before = around(case);
    let f = file.to_str().unwrap();
    let res = results.to_str().unwrap();
    let stage = ["truth", "target", "reading"][r.below(3)];
    // A sweep's per-point stages are not published one by one: its
    // gathered table is what `show` shows.
    let show = if sweep {
        "sweep.reading.readings"
    } else {
        stage
    };
    let reads: Vec<Vec<&str>> = vec![
        vec!["verify", f],
        vec!["plan", f],
        vec!["status", f],
        vec!["show", f, show],
        vec!["explain", f, stage],
        vec!["verify", f, "--repair"],
        vec!["graph", f, "--format", "dot"],
    ];
    let mut read = reads[r.below(reads.len())].clone();
    if read[0] == "status" && !sweep {
        read = vec!["plan", f];
    }
    let label = format!("{what} at {}", rel.display());
    let mut ran = None;
    let mut seen = false;
    for args in [read, vec!["run", f, "-q"], vec!["verify", f]] {
        let mut full = args.clone();
        full.extend(["--results", res]);
        let Some((code, err)) = ltcal(case, &full) else {
            return Verdict::Hung(format!("{label}: `ltcal {}`", args.join(" ")));
        };
        let cmd = format!("{label}: `ltcal {}`", args.join(" "));
        // Seen: refused, or reported (healed, restored) by its path.
        seen |= err.contains(planted.to_str().unwrap());
        match code {
            Some(0) => {}
            Some(1 | 2) => {
                if !names_a_file(&err, case) {
                    return Verdict::Unlocated(format!("{cmd}: {err}"));
                }
                seen = true;
            }
            _ => return Verdict::BadExit(format!("{cmd}: {code:?} {err}")),
        }
        if args[0] == "run" {
            ran = code;
        } else if args[0] == "verify" && args.len() == 2 && ran == Some(0) && code != Some(0) {
            return Verdict::Unhealed(format!("{cmd} after a run that exited 0: {err}"));
        }
    }
    let after = around(case);
    if after != before {
        return Verdict::Outside(format!("{label}: {before:?} → {after:?}"));
    }
    if seen { Verdict::Caught } else { Verdict::Fine }
}

/// Regression (found by `fuzz_slurm_settings_and_job_script`): sbatch
/// ends an unquoted word at whitespace even right after a backslash (its
/// `_get_argument` checks for whitespace before it looks at escapes), but
/// ltcal's check read `\ ` as an escaped space inside one word — so
/// `--hold\ --ar=1` passed as one harmless option and sbatch read a second
/// one, `--array=1`, overriding ltcal's array (`--qos=x\ --outp=…` the
/// logs). Now refused at load, with its line.
#[test]
fn an_escaped_space_cannot_hide_an_own_sbatch_option() {
    for (bad, own) in [
        (r"--hold\ --ar=1", "`--ar` is read by sbatch as `--array`"),
        (
            r"--qos=x\ --outp=/tmp/log",
            "`--outp` is read by sbatch as `--output`",
        ),
        (r"--comment=a\ -e/tmp/x", "`-e` is `--error`"),
    ] {
        let e = ltcal::pipeline::cluster::settings::check_sbatch_option(bad).unwrap_err();
        assert!(e.contains(own), "{bad}: {e}");
        let text = format!(
            "{SWEEP_TEXT}\n[executor.slurm]\nsbatch_options = [{}]\n",
            toml_str(bad)
        );
        let path = Path::new("fz.toml");
        let e = ltcal::pipeline::load_source(
            &ltcal::diagnostics::Source::new(path, text.as_str()),
            &[],
        )
        .unwrap_err();
        let line = text.lines().position(|l| l == "[executor.slurm]").unwrap() + 1;
        let m = format!("{e:#}");
        assert!(m.contains(&format!("fz.toml:{line}:")), "{m}");
        assert!(m.contains(own), "{m}");
        assert!(sets_own(bad).is_some(), "{bad}");
    }
    // Quoted, the space is part of the word, as in sbatch.
    assert_eq!(
        ltcal::pipeline::cluster::settings::check_sbatch_option(r"--comment='a\ --ar=1'"),
        Ok(())
    );
}

/// Regression (found by `fuzz_slurm_settings_and_job_script`): a
/// `partition`, `account` or `time_limit` holding `#`, `\` or `packjob`
/// was written into its `#SBATCH` line as is, and sbatch read another
/// value (cut at the `#`, the escape dropped, `packjob` blanked out). Now
/// refused at load.
#[test]
fn a_slurm_setting_sbatch_would_read_otherwise_is_refused() {
    for (field, v) in [
        ("partition", "gpu#2"),
        ("account", r"me\x"),
        ("time_limit", "packjob"),
        ("partition", "HetJob"),
    ] {
        let s: cluster::SlurmSettings =
            serde_json::from_value(serde_json::json!({ field: v })).unwrap();
        let p = s.problems();
        assert_eq!(p.len(), 1, "{field} = {v:?}: {p:?}");
        assert!(p[0].contains(&format!("`{field}` = {v:?}")), "{p:?}");
    }
    let s: cluster::SlurmSettings =
        serde_json::from_value(serde_json::json!({ "partition": "gpu-2_a.b" })).unwrap();
    assert!(s.problems().is_empty());
}

/// Cases of one kind at CI size, failing with the findings; at least a
/// quarter of them must have been seen damaged (a harness whose damage
/// nothing notices tests nothing).
fn ci(kind: Kind, count: u64) {
    let t = fuzz(kind, 1, count);
    println!("{kind:?}: {} cases, {} seen damaged", t.cases, t.caught);
    assert_eq!(t.cases as u64, count);
    assert!(t.clean(), "{kind:?}: {t:#?}");
    assert!(4 * t.caught >= t.cases, "{kind:?}: {t:#?}");
}

#[test]
fn fuzz_packs() {
    ci(Kind::Pack, 80);
}

#[test]
fn fuzz_loose_entries_and_published_tables() {
    ci(Kind::Loose, 60);
}

#[test]
fn fuzz_jobs_json() {
    ci(Kind::Jobs, 120);
}

#[test]
fn fuzz_slurm_settings_and_job_script() {
    ci(Kind::Slurm, 1500);
}

#[test]
fn fuzz_results_folder_file_types() {
    ci(Kind::Files, 50);
}
