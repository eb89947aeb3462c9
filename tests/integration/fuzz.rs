//! Fuzzing in the repository (issue 12): arbitrary bytes and structured
//! mutations of the example campaigns and pipelines, fed to the campaign
//! reader, the pipeline loader and the diagnosis; `fuzz_files.rs` does the
//! same for what ltcal reads back from the results folder (issue 28). Under
//! `cargo test` the property tests run a bounded number of cases;
//! `fuzz_100k_mutants` (ignored: `cargo test --release --test integration
//! -- --ignored fuzz_100k_mutants --nocapture`) runs 100 000 of all kinds
//! and prints what it found.
//!
//! The property asserted everywhere: no panic, no hang, and every rejection
//! is an error that names a file (with line and column where there is one).

use ltcal::campaign::Problem;
use ltcal::diagnostics::Source;
use proptest::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Duration;

const CAMPAIGN_FILES: [&str; 4] = ["campaign.toml", "readings.csv", "targets.csv", "gauge.csv"];

/// Values that broke, or might break, a reader or the numerics.
pub(crate) const VALUES: &[&str] = &[
    "1e308",
    "-1e308",
    "1.7976931348623157e308",
    "-1.7976931348623157e308",
    "5e-324",
    "1e-300",
    "0",
    "-0",
    "90",
    "-90",
    "270",
    "-90.0000001",
    "1e15",
    "NaN",
    "inf",
    "-inf",
    "",
    "abc",
    "\"q\"",
    "\"",
    "1,2",
    "S1",
    "T01",
    "2",
    "3",
    "\u{1F642}",
    "1e",
    "0x10",
    "99999999999999999999999",
    "[1, 2]",
    "{ a = 1 }",
    "true",
    "\"/dev/zero\"",
    "100000000",
];

fn examples() -> Vec<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("examples/campaigns");
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join("campaign.toml").is_file())
        .collect();
    v.sort();
    v
}

fn pipelines() -> Vec<(PathBuf, String)> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("pipelines");
    let mut v: Vec<(PathBuf, String)> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "toml"))
        .map(|p| {
            let text = std::fs::read_to_string(&p).unwrap();
            (p, text)
        })
        .collect();
    v.sort();
    v
}

/// A small deterministic generator (xorshift), so mutants are reproducible
/// from their number.
pub(crate) struct Rng(u64);

impl Rng {
    pub(crate) fn new(seed: u64) -> Rng {
        Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }
    pub(crate) fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    pub(crate) fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// One to three mutations of `text`: a cell (CSV) or value (TOML) replaced
/// by one of [`VALUES`], a line deleted or duplicated, the text cut, or
/// random bytes inserted.
pub(crate) fn mutate(text: &str, r: &mut Rng) -> Vec<u8> {
    let mut lines: Vec<String> = text.lines().map(String::from).collect();
    let mut bytes = None;
    for _ in 0..=r.below(3) {
        if lines.is_empty() {
            break;
        }
        let i = r.below(lines.len());
        match r.below(8) {
            0..=3 => {
                let v = VALUES[r.below(VALUES.len())];
                lines[i] = match lines[i].split_once(" = ") {
                    Some((k, _)) => format!("{k} = {v}"),
                    None => {
                        let mut cells: Vec<&str> = lines[i].split(',').collect();
                        let k = r.below(cells.len());
                        cells[k] = v;
                        cells.join(",")
                    }
                };
            }
            4 => {
                lines.remove(i);
            }
            5 => {
                let l = lines[i].clone();
                lines.insert(i, l);
            }
            6 => {
                let mut b = lines.join("\n").into_bytes();
                b.truncate(r.below(b.len() + 1));
                bytes = Some(b);
                break;
            }
            _ => {
                let mut b = lines.join("\n").into_bytes();
                let at = r.below(b.len() + 1);
                let junk: Vec<u8> = (0..=r.below(8)).map(|_| r.next() as u8).collect();
                b.splice(at..at, junk);
                bytes = Some(b);
                break;
            }
        }
    }
    bytes.unwrap_or_else(|| (lines.join("\n") + "\n").into_bytes())
}

/// What one case came to.
#[derive(Clone, Debug, PartialEq)]
enum Outcome {
    Accepted,
    Located,
    /// Rejected without a file named: the message.
    Unlocated(String),
    Panicked(String),
}

pub(crate) fn located(problems: &[Problem]) -> bool {
    !problems.is_empty()
        && problems.iter().all(|p| match p {
            Problem::At(_) => true,
            Problem::File { path, .. } => path.is_some(),
        })
}

/// The example campaign `example` with `file` replaced by `bytes`, written
/// into `dir` (emptied first); `None` for `bytes` removes the file.
fn write_campaign(dir: &Path, example: &Path, file: &str, bytes: Option<&[u8]>) {
    let _ = std::fs::remove_dir_all(dir);
    std::fs::create_dir_all(dir).unwrap();
    for f in CAMPAIGN_FILES {
        let src = example.join(f);
        if f == file {
            if let Some(b) = bytes {
                std::fs::write(dir.join(f), b).unwrap();
            }
        } else if src.is_file() {
            std::fs::copy(&src, dir.join(f)).unwrap();
        }
    }
}

/// Reads the campaign in `dir` (for calibration when `diagnose`), and
/// diagnoses it when it loads and `diagnose` is set.
fn read_campaign(dir: &Path, diagnose: bool) -> Outcome {
    let read = if diagnose {
        ltcal::campaign::read_for_calibration(dir)
    } else {
        ltcal::campaign::read(dir)
    };
    match read {
        Err(e) if located(&e.problems) => Outcome::Located,
        Err(e) => Outcome::Unlocated(e.to_string()),
        Ok(c) if diagnose => {
            // The default folds (2 folds leave the example campaigns'
            // adjustment singular on a fold); few noise draws, for time.
            let s = ltcal::diagnose::Settings {
                mc_draws: 4,
                ..Default::default()
            };
            match ltcal::diagnose::diagnose(&c, &s) {
                Ok(_) => Outcome::Accepted,
                Err(e) => Outcome::Unlocated(format!("diagnosis: {e}")),
            }
        }
        Ok(_) => Outcome::Accepted,
    }
}

fn load_pipeline(path: &Path, text: &[u8]) -> Outcome {
    let Ok(text) = std::str::from_utf8(text) else {
        // Not UTF-8: `pipeline::load` refuses it at the first bad byte
        // (pinned by the CLI tests); `load_source` takes text.
        return Outcome::Located;
    };
    match ltcal::pipeline::load_source(&Source::new(path, text), &[]) {
        Ok(_) => Outcome::Accepted,
        Err(e) => match e.downcast_ref::<ltcal::pipeline::InputError>() {
            Some(i) if located(&i.0) => Outcome::Located,
            _ => Outcome::Unlocated(e.to_string()),
        },
    }
}

/// Runs `case`, turning a panic into [`Outcome::Panicked`].
fn guarded(case: impl FnOnce() -> Outcome) -> Outcome {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(case)).unwrap_or_else(|p| {
        Outcome::Panicked(
            p.downcast_ref::<String>()
                .cloned()
                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_default(),
        )
    })
}

fn assert_no_panic_and_located(o: Outcome) {
    assert!(matches!(o, Outcome::Accepted | Outcome::Located), "{o:?}");
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, failure_persistence: None, ..ProptestConfig::default() })]

    /// Arbitrary bytes as one campaign file: refused at a place, never a
    /// panic.
    #[test]
    fn fuzz_campaign_reader_arbitrary_bytes(
        file in 0..CAMPAIGN_FILES.len(),
        bytes in proptest::collection::vec(any::<u8>(), 0..400),
    ) {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("c");
        write_campaign(&dir, &examples()[0], CAMPAIGN_FILES[file], Some(&bytes));
        assert_no_panic_and_located(guarded(|| read_campaign(&dir, false)));
    }

    /// Structured mutations of every example campaign's files.
    #[test]
    fn fuzz_campaign_reader_mutants(example in 0usize..64, file in 0..CAMPAIGN_FILES.len(), seed in any::<u64>()) {
        let ex = examples();
        let ex = &ex[example % ex.len()];
        let text = std::fs::read_to_string(ex.join(CAMPAIGN_FILES[file])).unwrap_or_default();
        let bytes = mutate(&text, &mut Rng::new(seed));
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("c");
        write_campaign(&dir, ex, CAMPAIGN_FILES[file], Some(&bytes));
        assert_no_panic_and_located(guarded(|| read_campaign(&dir, false)));
    }

    /// Arbitrary text and structured mutations of every pipeline file.
    #[test]
    fn fuzz_pipeline_loader(which in 0usize..64, seed in any::<u64>(), raw in proptest::collection::vec(any::<u8>(), 0..200)) {
        let ps = pipelines();
        let (path, text) = &ps[which % ps.len()];
        assert_no_panic_and_located(guarded(|| load_pipeline(path, &raw)));
        let bytes = mutate(text, &mut Rng::new(seed));
        assert_no_panic_and_located(guarded(|| load_pipeline(path, &bytes)));
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, failure_persistence: None, ..ProptestConfig::default() })]

    /// Small mutations of a valid campaign, diagnosed: a campaign that loads
    /// for calibration is diagnosed or refused with an error, never a panic
    /// or a hang. (A diagnosis error has no file position: it is about the
    /// campaign as a whole.)
    #[test]
    fn fuzz_diagnosis_of_mutated_campaigns(seed in any::<u64>()) {
        let ex = &examples()[0];
        let text = std::fs::read_to_string(ex.join("readings.csv")).unwrap();
        let mut r = Rng::new(seed);
        // Cell replacements only: the campaign should mostly still load.
        let mut lines: Vec<String> = text.lines().map(String::from).collect();
        let i = 1 + r.below(lines.len() - 1);
        let mut cells: Vec<String> = lines[i].split(',').map(String::from).collect();
        let k = 2 + r.below(cells.len() - 2);
        cells[k] = VALUES[r.below(16)].to_string();
        lines[i] = cells.join(",");
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("c");
        write_campaign(&dir, ex, "readings.csv", Some((lines.join("\n") + "\n").as_bytes()));
        let o = guarded(|| read_campaign(&dir, true));
        prop_assert!(!matches!(o, Outcome::Panicked(_)), "{:?}", o);
    }
}

/// The counts of a fuzz run.
#[derive(Default, Debug)]
struct Counts {
    cases: usize,
    accepted: usize,
    located: usize,
    unlocated: usize,
    panics: usize,
    hangs: usize,
    diagnosed: usize,
}

/// One case for the worker: what to run.
enum Case {
    Campaign {
        example: PathBuf,
        file: &'static str,
        bytes: Vec<u8>,
        diagnose: bool,
    },
    Pipeline {
        path: PathBuf,
        bytes: Vec<u8>,
    },
}

/// A worker thread that runs cases in its own folder; a case that outlives
/// the deadline is counted as a hang and the worker abandoned for a new one.
struct Worker {
    send: mpsc::Sender<Case>,
    recv: mpsc::Receiver<Outcome>,
}

fn worker(root: &Path, n: usize) -> Worker {
    let (send, cases) = mpsc::channel::<Case>();
    let (results, recv) = mpsc::channel();
    let dir = root.join(format!("w{n}"));
    std::thread::spawn(move || {
        for case in cases {
            let o = guarded(|| match &case {
                Case::Campaign {
                    example,
                    file,
                    bytes,
                    diagnose,
                } => {
                    write_campaign(&dir, example, file, Some(bytes));
                    read_campaign(&dir, *diagnose)
                }
                Case::Pipeline { path, bytes } => load_pipeline(path, bytes),
            });
            if results.send(o).is_err() {
                return;
            }
        }
    });
    Worker { send, recv }
}

/// The long fuzz run: 100 000 mutants in all — 50 000 of the example
/// campaigns and pipelines (every 200th loaded campaign also diagnosed),
/// each with a 20-second deadline, and the kinds of [`crate::fuzz_files`]
/// (packs, loose entries, `jobs.json`, Slurm settings, results-folder file
/// types) at the counts of [`LONG_KINDS`]. Prints the counts per kind and
/// fails on any panic, abort, hang, rejection without a location, cache
/// left damaged after a run, or file written outside the results folder.
#[test]
#[ignore = "long: run with --release -- --ignored fuzz_100k_mutants --nocapture"]
fn fuzz_100k_mutants() {
    const MUTANTS: usize = 50_000;
    let repo = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let listing = |d: &Path| {
        let mut v: Vec<_> = std::fs::read_dir(d)
            .unwrap()
            .flatten()
            .map(|e| e.file_name())
            .collect();
        v.sort();
        v
    };
    let repo_before = (listing(&repo), listing(&repo.join("pipelines")));
    let t0 = std::time::Instant::now();
    const DEADLINE: Duration = Duration::from_secs(20);
    std::panic::set_hook(Box::new(|_| {}));
    let tmp = tempfile::tempdir().unwrap();
    let ex = examples();
    let ps = pipelines();
    let texts: Vec<Vec<String>> = ex
        .iter()
        .map(|e| {
            CAMPAIGN_FILES
                .iter()
                .map(|f| std::fs::read_to_string(e.join(f)).unwrap_or_default())
                .collect()
        })
        .collect();
    let mut counts = Counts::default();
    let mut workers = 0;
    let mut w = worker(tmp.path(), workers);
    let mut found: Vec<String> = Vec::new();
    let mut loaded = 0usize;
    for n in 0..MUTANTS {
        let mut r = Rng::new(n as u64 + 1);
        let case = if n % 4 == 3 {
            let (path, text) = &ps[r.below(ps.len())];
            Case::Pipeline {
                path: path.clone(),
                bytes: mutate(text, &mut r),
            }
        } else {
            let e = r.below(ex.len());
            let f = r.below(CAMPAIGN_FILES.len());
            Case::Campaign {
                example: ex[e].clone(),
                file: CAMPAIGN_FILES[f],
                bytes: mutate(&texts[e][f], &mut r),
                diagnose: false,
            }
        };
        let mut run = |case: Case, counts: &mut Counts, w: &mut Worker| {
            counts.cases += 1;
            w.send.send(case).unwrap();
            match w.recv.recv_timeout(DEADLINE) {
                Ok(Outcome::Accepted) => counts.accepted += 1,
                Ok(Outcome::Located) => counts.located += 1,
                Ok(Outcome::Unlocated(m)) => {
                    counts.unlocated += 1;
                    found.push(format!("mutant {n}: no location: {m}"));
                }
                Ok(Outcome::Panicked(m)) => {
                    counts.panics += 1;
                    found.push(format!("mutant {n}: panic: {m}"));
                }
                Err(_) => {
                    counts.hangs += 1;
                    found.push(format!("mutant {n}: over {DEADLINE:?}"));
                    workers += 1;
                    *w = worker(tmp.path(), workers);
                }
            }
        };
        let diagnose_next = matches!(&case, Case::Campaign { .. });
        let campaign = match &case {
            Case::Campaign {
                example,
                file,
                bytes,
                ..
            } => Some((example.clone(), *file, bytes.clone())),
            Case::Pipeline { .. } => None,
        };
        let before = counts.accepted;
        run(case, &mut counts, &mut w);
        if diagnose_next && counts.accepted > before {
            loaded += 1;
            if loaded % 200 == 0 {
                let (example, file, bytes) = campaign.unwrap();
                counts.diagnosed += 1;
                run(
                    Case::Campaign {
                        example,
                        file,
                        bytes,
                        diagnose: true,
                    },
                    &mut counts,
                    &mut w,
                );
            }
        }
    }
    println!(
        "fuzz: campaigns and pipelines {counts:?} in {:.0} s",
        t0.elapsed().as_secs_f64()
    );
    for f in found.iter().take(30) {
        println!("  {f}");
    }
    let mut total = counts.cases;
    let mut clean = true;
    for &(kind, n) in LONG_KINDS {
        let t = std::time::Instant::now();
        let tally = crate::fuzz_files::fuzz(kind, 1_000_000, n);
        println!(
            "fuzz: {kind:?}: {} cases ({} seen damaged), {} panics, {} hangs, \
             {} aborts or other exits, {} unlocated errors, {} not healed, \
             {} writes outside, in {:.0} s",
            tally.cases,
            tally.caught,
            tally.panics,
            tally.hangs,
            tally.bad_exits,
            tally.unlocated,
            tally.unhealed,
            tally.outside,
            t.elapsed().as_secs_f64()
        );
        for f in &tally.found {
            println!("  {f}");
        }
        total += tally.cases;
        clean &= tally.clean();
    }
    let _ = std::panic::take_hook();
    let repo_after = (listing(&repo), listing(&repo.join("pipelines")));
    println!(
        "fuzz: {total} mutants in {:.0} s",
        t0.elapsed().as_secs_f64()
    );
    assert_eq!(repo_before, repo_after, "files appeared in the repository");
    assert!(
        counts.panics == 0 && counts.hangs == 0 && counts.unlocated == 0 && clean,
        "{counts:?}"
    );
    assert!(total >= 100_000, "{total}");
}

/// Finding of `fuzz_100k_mutants` (issue 28, item 7 — the diagnosis):
/// two gross *range* blunders. Mutant 31680: `example-04-encoder-harmonic`'s
/// `readings.csv` with `S6,T07`'s `d_mm` 10207.4 → 90 (and one reading
/// doubled, one dropped); mutant 37441: `example-02-range-scale`'s with
/// `S4,T10`'s `d_mm` 11079.2 → 2 (and `S5,T11`'s `time_s` → -90). Both load
/// for calibration, and their diagnosis exits with "the base adjustment's
/// normal matrix is singular on a cross-validation fold"
/// (src/diagnose/linear.rs:337), naming no reading. Since gross blunders
/// are screened out as whole readings before the diagnosis, both are
/// diagnosed.
#[test]
fn fuzz_finding_mutants_31680_and_37441_diagnose_or_name_a_reading() {
    let ex = examples();
    let tmp = tempfile::tempdir().unwrap();
    for n in [31680u64, 37441] {
        let mut r = Rng::new(n + 1);
        let e = &ex[r.below(ex.len())];
        let f = CAMPAIGN_FILES[r.below(CAMPAIGN_FILES.len())];
        let text = std::fs::read_to_string(e.join(f)).unwrap_or_default();
        let bytes = mutate(&text, &mut r);
        let dir = tmp.path().join(format!("m{n}"));
        write_campaign(&dir, e, f, Some(&bytes));
        let o = guarded(|| read_campaign(&dir, true));
        assert_eq!(o, Outcome::Accepted, "mutant {n} ({}, {f})", e.display());
    }
}

/// The kinds of [`crate::fuzz_files`] in the long run, and their counts:
/// the in-process readers carry most, the `ltcal` processes (three a case)
/// a few thousand.
const LONG_KINDS: &[(crate::fuzz_files::Kind, u64)] = {
    use crate::fuzz_files::Kind::*;
    &[
        (Slurm, 40_000),
        (Pack, 3_000),
        (Loose, 2_000),
        (Jobs, 2_000),
        (Files, 3_000),
    ]
};
