//! Hostile files where ltcal reads and writes (issue 28): a user's folder
//! named as an export, FIFOs, `/dev/zero` and symbolic links inside the
//! results folder, damaged packs — nothing lost, nothing hangs, nothing
//! written outside, and one run leaves a cache `verify` passes.

use crate::cli::*;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// A cheap chain (inject, a one-point mesh, one reading of it); with
/// `points`, swept over that many seeds, gathering the readings.
fn cheap(dir: &Path, name: &str, points: Option<usize>) -> PathBuf {
    let mut text = format!(
        r#"
[pipeline]
name = "{name}"

[stages.truth]
kind = "inject"
preset = "table2"

[stages.target]
kind = "mesh"
shape = "plane"
x_mm = 3000.0
y = {{ from = 0, to = 0, step = 1 }}
z = {{ from = 0, to = 0, step = 1 }}

[stages.reading]
kind = "measure"
inputs = {{ points = "target", errors = "truth" }}
noise = {{ sigma_angle_urad = 1.0, sigma_range_um = 2.0 }}
seed = 0
"#
    );
    if let Some(n) = points {
        text += &format!(
            r#"
[[sweep.axis]]
path = "stages.reading.seed"
range = {{ from = 0, to = {}, step = 1 }}

[sweep]
gather = ["reading.readings"]
"#,
            n - 1
        );
    }
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(&path, text).unwrap();
    path
}

/// `ltcal <args>` in `cwd`, killed and failed if it takes over a minute
/// (what a FIFO read would do: block forever).
fn within_a_minute(cwd: &Path, args: &[&str]) -> Output {
    let mut child = Command::new(BIN)
        .current_dir(cwd)
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if t0.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
            let out = child.wait_with_output().unwrap();
            panic!(
                "`ltcal {}` hung (killed after 60 s):\n{}",
                args.join(" "),
                stderr(&out)
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

/// `ltcal <command> <file> --results <results> [extra…]`.
fn cmd(command: &str, file: &Path, results: &Path, extra: &[&str]) -> Output {
    let (f, r) = (file.to_str().unwrap(), results.to_str().unwrap());
    let mut args = vec![command, f, "--results", r];
    args.extend(extra);
    within_a_minute(results.parent().unwrap(), &args)
}

fn mkfifo(path: &Path) {
    let made = Command::new("mkfifo").arg(path).status().unwrap();
    assert!(made.success(), "mkfifo {}", path.display());
}

fn replace_with_symlink(path: &Path, target: &Path) {
    if let Ok(m) = std::fs::symlink_metadata(path) {
        if m.is_dir() {
            std::fs::remove_dir_all(path).unwrap();
        } else {
            std::fs::remove_file(path).unwrap();
        }
    }
    std::os::unix::fs::symlink(target, path).unwrap();
}

fn files_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .map(|rd| {
            rd.flatten()
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

fn packs(results: &Path, name: &str) -> Vec<PathBuf> {
    let dir = results.join(name).join(".ltcal/packs");
    files_in(&dir)
        .into_iter()
        .filter(|n| n.ends_with(".pack"))
        .map(|n| dir.join(n))
        .collect()
}

fn gathered(results: &Path, name: &str) -> Vec<u8> {
    std::fs::read(results.join(name).join("sweep/reading.readings.parquet")).unwrap()
}

/// The key of a stage in the last run's report.
fn key_of(results: &Path, name: &str, stage: &str) -> String {
    stages(&run_json(results, name))[stage]["key"]
        .as_str()
        .unwrap()
        .to_string()
}

/// Regression (issue 28, 1): `export_campaign` with `overwrite = true`
/// replaced whatever folder `path` named — a folder of a user's files was
/// deleted, and the run exited 0 without a word. Now it is replaced only
/// when it is a campaign folder, as `diagnose --out` is.
#[test]
fn export_campaign_overwrite_refuses_a_folder_that_is_not_a_campaign() {
    let tmp = tempfile::tempdir().unwrap();
    let campaign =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("examples/campaigns/example-00-none");
    let mine = tmp.path().join("mine");
    std::fs::create_dir_all(mine.join("sub")).unwrap();
    std::fs::write(mine.join("thesis.tex"), "\\chapter{One}").unwrap();
    std::fs::write(mine.join("sub/raw.dat"), "1 2 3").unwrap();
    let file = tmp.path().join("export.toml");
    let write = |path: &Path| {
        std::fs::write(
            &file,
            format!(
                "[stages.campaign]\nkind = \"import_campaign\"\npath = '{}'\n\n\
                 [stages.export]\nkind = \"export_campaign\"\ninputs = {{ campaign = \"campaign\" }}\n\
                 path = '{}'\noverwrite = true\n",
                campaign.display(),
                path.display()
            ),
        )
        .unwrap()
    };
    write(&mine);
    let results = tmp.path().join("results");
    let out = cmd("run", &file, &results, &[]);
    assert_code(&out, 1);
    let err = stderr(&out);
    assert!(
        err.contains("stage `export` (export_campaign) failed"),
        "{err}"
    );
    assert!(
        err.contains("is not a campaign ltcal wrote (it holds sub, thesis.tex)"),
        "{err}"
    );
    assert!(
        err.contains("`overwrite` replaces only a campaign folder"),
        "{err}"
    );
    assert_eq!(
        std::fs::read_to_string(mine.join("thesis.tex")).unwrap(),
        "\\chapter{One}"
    );
    assert_eq!(std::fs::read(mine.join("sub/raw.dat")).unwrap(), b"1 2 3");
    assert_eq!(files_in(&mine), ["sub", "thesis.tex"]);
    // A file, or a link to a folder: refused too, nothing followed.
    let link = tmp.path().join("link");
    std::os::unix::fs::symlink(&mine, &link).unwrap();
    write(&link);
    let out = cmd("run", &file, &results, &[]);
    assert_code(&out, 1);
    assert!(
        stderr(&out).contains("exists and is not a folder (a symbolic link)"),
        "{}",
        stderr(&out)
    );
    assert_eq!(files_in(&mine), ["sub", "thesis.tex"]);
    // A campaign folder (an earlier export, stale) is replaced whole.
    let old = tmp.path().join("old");
    std::fs::create_dir(&old).unwrap();
    std::fs::write(old.join("campaign.toml"), "stale").unwrap();
    std::fs::write(old.join("gauge.csv"), "stale").unwrap();
    write(&old);
    assert_code(&cmd("run", &file, &results, &[]), 0);
    assert_eq!(
        files_in(&old),
        ["campaign.toml", "gauge.csv", "readings.csv", "targets.csv"]
    );
    assert_eq!(ltcal::campaign::read(&old).unwrap().readings.len(), 120);
}

/// Regression (issue 28, 4): a FIFO named `*.pack`, as a loose manifest or
/// as a published table blocked `run`, `verify`, `plan`, `status` and
/// `show` forever. Now each is refused as not a regular file, said so, and
/// the run's result is the clean one.
#[test]
fn a_fifo_named_pack_does_not_hang_run_or_verify() {
    let tmp = tempfile::tempdir().unwrap();
    let file = cheap(tmp.path(), "fifo", Some(6));
    let results = tmp.path().join("results");
    assert_code(&cmd("run", &file, &results, &[]), 0);
    let clean = gathered(&results, "fifo");
    let dir = results.join("fifo");
    mkfifo(&dir.join(".ltcal/packs/00000000000000000000-local-000000000000.pack"));
    let published = dir.join("sweep/reading.readings.parquet");
    std::fs::remove_file(&published).unwrap();
    mkfifo(&published);
    // A loose entry (a pipeline without a sweep) with a FIFO manifest, and
    // a FIFO as its published table.
    let loose_file = cheap(tmp.path(), "fifo-loose", None);
    assert_code(&cmd("run", &loose_file, &results, &[]), 0);
    let loose_clean = std::fs::read(results.join("fifo-loose/reading/readings.parquet")).unwrap();
    let manifest = results
        .join("fifo-loose/.ltcal/cache")
        .join(key_of(&results, "fifo-loose", "target"))
        .join("manifest.json");
    std::fs::remove_file(&manifest).unwrap();
    mkfifo(&manifest);
    let loose_published = results.join("fifo-loose/reading/readings.parquet");
    std::fs::remove_file(&loose_published).unwrap();
    mkfifo(&loose_published);
    let v = cmd("verify", &loose_file, &results, &[]);
    assert_code(&v, 1);
    assert!(
        stderr(&v).contains("manifest.json is a FIFO, not a regular file"),
        "{}",
        stderr(&v)
    );
    assert_code(&cmd("plan", &loose_file, &results, &[]), 0);
    let show = cmd("show", &loose_file, &results, &["reading"]);
    assert_code(&show, 1);
    assert!(stderr(&show).contains("is a FIFO"), "{}", stderr(&show));
    let out = cmd("run", &loose_file, &results, &[]);
    assert_code(&out, 0);
    let st = stages(&run_json(&results, "fifo-loose"));
    assert!(
        st["target"]["cache_problem"]
            .as_str()
            .unwrap()
            .contains("manifest.json is a FIFO"),
        "{}",
        st["target"]
    );
    assert_eq!(std::fs::read(&loose_published).unwrap(), loose_clean);
    assert_code(&cmd("verify", &loose_file, &results, &[]), 0);

    let v = cmd("verify", &file, &results, &[]);
    assert_code(&v, 1);
    assert!(
        stderr(&v).contains("is a FIFO, not a regular file"),
        "{}",
        stderr(&v)
    );
    assert_code(&cmd("plan", &file, &results, &[]), 0);
    assert_code(&cmd("status", &file, &results, &[]), 0);
    let show = cmd("show", &file, &results, &["sweep.reading.readings"]);
    assert_code(&show, 1);
    assert!(
        stderr(&show).contains("is a FIFO, not a regular file"),
        "{}",
        stderr(&show)
    );
    let out = cmd("run", &file, &results, &[]);
    assert_code(&out, 0);
    let err = stderr(&out);
    assert!(
        err.contains("DAMAGED pack, not read") && err.contains("a FIFO"),
        "{err}"
    );
    assert!(err.contains("healed the cache"), "{err}");
    assert_eq!(gathered(&results, "fifo"), clean);
    assert_code(&cmd("verify", &file, &results, &[]), 0);
    assert_code(
        &cmd("show", &file, &results, &["sweep.reading.readings"]),
        0,
    );
}

/// Regression (issue 28, 4): a symbolic link to `/dev/zero` as a cached
/// table, a manifest or a published table was read until memory ran out.
/// Now it is refused unread (a link inside the results folder is never
/// followed), the stage recomputed, the published table restored.
#[test]
fn a_symlink_to_dev_zero_as_a_table_is_refused_not_read() {
    let tmp = tempfile::tempdir().unwrap();
    let file = cheap(tmp.path(), "zero", None);
    let results = tmp.path().join("results");
    assert_code(&cmd("run", &file, &results, &[]), 0);
    let dir = results.join("zero");
    let clean = std::fs::read(dir.join("reading/readings.parquet")).unwrap();
    let cache = dir.join(".ltcal/cache");
    let zero = Path::new("/dev/zero");
    replace_with_symlink(
        &cache
            .join(key_of(&results, "zero", "reading"))
            .join("readings.parquet"),
        zero,
    );
    replace_with_symlink(
        &cache
            .join(key_of(&results, "zero", "target"))
            .join("manifest.json"),
        zero,
    );
    replace_with_symlink(&dir.join("reading/readings.parquet"), zero);
    let show = cmd("show", &file, &results, &["reading"]);
    assert_code(&show, 1);
    assert!(
        stderr(&show).contains("goes through the symbolic link"),
        "{}",
        stderr(&show)
    );
    assert_code(&cmd("verify", &file, &results, &[]), 1);
    let out = cmd("run", &file, &results, &[]);
    assert_code(&out, 0);
    let st = stages(&run_json(&results, "zero"));
    for stage in ["reading", "target"] {
        assert_eq!(st[stage]["status"], "ran", "{stage}: {}", stderr(&out));
        assert!(
            st[stage]["cache_problem"]
                .as_str()
                .unwrap()
                .contains("goes through the symbolic link"),
            "{stage}: {}",
            st[stage]
        );
    }
    let published = dir.join("reading/readings.parquet");
    assert!(!published.symlink_metadata().unwrap().is_symlink());
    assert_eq!(std::fs::read(&published).unwrap(), clean);
    assert_code(&cmd("verify", &file, &results, &[]), 0);
}

/// Regression (issue 28, 3): a symbolic link inside the results folder — a
/// stage's folder, the packs folder, the pipeline's folder — was followed,
/// and the run wrote its tables or packs into the link's target, outside
/// the results folder. Now the link is refused with an error naming it,
/// and nothing is written through it.
#[test]
fn a_symlinked_stage_folder_is_not_written_through() {
    let tmp = tempfile::tempdir().unwrap();
    let outside = tmp.path().join("outside");
    std::fs::create_dir(&outside).unwrap();
    let results = tmp.path().join("results");

    // A stage's folder.
    let file = cheap(tmp.path(), "stage-link", None);
    let dir = results.join("stage-link");
    std::fs::create_dir_all(&dir).unwrap();
    std::os::unix::fs::symlink(&outside, dir.join("reading")).unwrap();
    let out = cmd("run", &file, &results, &[]);
    assert_code(&out, 1);
    let link = dir.join("reading").display().to_string();
    assert!(
        stderr(&out).contains(&format!(
            "{link} is a symbolic link (to {}",
            outside.display()
        )),
        "{}",
        stderr(&out)
    );
    assert!(files_in(&outside).is_empty(), "{:?}", files_in(&outside));
    // Once the link is gone, the run makes a real folder there.
    std::fs::remove_file(dir.join("reading")).unwrap();
    assert_code(&cmd("run", &file, &results, &[]), 0);
    assert!(dir.join("reading/readings.parquet").is_file());

    // The packs folder of a sweep.
    let file = cheap(tmp.path(), "packs-link", Some(4));
    let ltcal_dir = results.join("packs-link/.ltcal");
    std::fs::create_dir_all(&ltcal_dir).unwrap();
    std::os::unix::fs::symlink(&outside, ltcal_dir.join("packs")).unwrap();
    let out = cmd("run", &file, &results, &[]);
    assert_code(&out, 1);
    assert!(
        stderr(&out).contains("is a symbolic link"),
        "{}",
        stderr(&out)
    );
    assert!(files_in(&outside).is_empty(), "{:?}", files_in(&outside));

    // The pipeline's folder.
    let file = cheap(tmp.path(), "pipeline-link", None);
    std::os::unix::fs::symlink(&outside, results.join("pipeline-link")).unwrap();
    let out = cmd("run", &file, &results, &[]);
    assert_code(&out, 1);
    assert!(
        stderr(&out).contains("is a symbolic link"),
        "{}",
        stderr(&out)
    );
    assert!(files_in(&outside).is_empty(), "{:?}", files_in(&outside));
}

/// A way to damage a pack in place.
type Spoil = Box<dyn Fn(&Path)>;

/// Regression (issue 28, 6): a flipped byte in a packed table nothing
/// reads was reported by `verify` forever while `run` served it as
/// cached; a damaged pack's points were recomputed but the pack stayed,
/// and `verify` exited 1 forever. Now the run takes out what is damaged
/// (keeping a pack's good entries), says so, and `verify` passes after it;
/// the next run recomputes what was taken out, equal to a clean run.
#[test]
fn run_heals_what_verify_finds_damaged() {
    let tmp = tempfile::tempdir().unwrap();
    let file = cheap(tmp.path(), "heal", Some(6));
    let results = tmp.path().join("results");
    assert_code(&cmd("run", &file, &results, &[]), 0);
    let clean = gathered(&results, "heal");
    let pack = packs(&results, "heal").remove(0);
    let bytes = std::fs::read(&pack).unwrap();
    use ltcal::pipeline::pack;
    let ix = pack::read_index(&pack).unwrap();
    // The target (the same at every point, so one entry): on a cached
    // rerun only its manifest is read, never its table — flip the last
    // byte of that table.
    let target = ix
        .entries
        .iter()
        .map(|(_, span)| *span)
        .find(|span| {
            let m: serde_json::Value =
                serde_json::from_slice(&pack::read_manifest(&pack, *span).unwrap()).unwrap();
            m["stage"] == "target"
        })
        .expect("a packed target");
    let mut flipped = bytes.clone();
    flipped[(target.offset + target.len - 1) as usize] ^= 0x01;
    std::fs::write(&pack, &flipped).unwrap();
    assert_code(&cmd("verify", &file, &results, &[]), 1);
    let out = cmd("run", &file, &results, &[]);
    assert_code(&out, 0);
    let err = stderr(&out);
    assert!(
        err.contains("0 ran, "),
        "served as cached in this run: {err}"
    );
    assert!(err.contains("healed the cache"), "{err}");
    assert!(err.contains("1 damaged entry"), "{err}");
    assert!(
        err.contains("good entries and its records rewritten as"),
        "{err}"
    );
    let healed = run_json(&results, "heal")["healed"].clone();
    assert_eq!(healed.as_array().unwrap().len(), 1, "{healed}");
    assert!(
        healed[0]["damage"]
            .as_str()
            .unwrap()
            .contains("does not match its manifest"),
        "{healed}"
    );
    let v = cmd("verify", &file, &results, &[]);
    assert_code(&v, 0);
    assert!(stdout(&v).contains(", 0 damaged"), "{}", stdout(&v));
    // The next run recomputes the entry taken out.
    let out = cmd("run", &file, &results, &[]);
    assert_code(&out, 0);
    let st = stages(&run_json(&results, "heal"));
    assert_eq!(st["target"]["status"], "ran", "{}", stderr(&out));
    assert_eq!(st["reading"]["status"], "cached", "{}", stderr(&out));
    assert_eq!(gathered(&results, "heal"), clean);
    assert_code(&cmd("verify", &file, &results, &[]), 0);

    // Whole packs damaged every way: each is recomputed, taken out, and
    // `verify` passes after one run.
    let damage: Vec<(&str, Spoil)> = vec![
        (
            "truncated",
            Box::new(|p: &Path| {
                let b = std::fs::read(p).unwrap();
                std::fs::write(p, &b[..b.len() / 2]).unwrap();
            }),
        ),
        (
            "zeroed trailer",
            Box::new(|p: &Path| {
                let mut b = std::fs::read(p).unwrap();
                let n = b.len();
                b[n - 56..].fill(0);
                std::fs::write(p, &b).unwrap();
            }),
        ),
        (
            "flipped index",
            Box::new(|p: &Path| {
                let mut b = std::fs::read(p).unwrap();
                let n = b.len();
                b[n - 60] ^= 0x01;
                std::fs::write(p, &b).unwrap();
            }),
        ),
        (
            "chmod 000",
            Box::new(|p: &Path| {
                use std::os::unix::fs::PermissionsExt as _;
                std::fs::set_permissions(p, std::fs::Permissions::from_mode(0o000)).unwrap();
            }),
        ),
        (
            "a directory",
            Box::new(|p: &Path| {
                std::fs::remove_file(p).unwrap();
                std::fs::create_dir(p).unwrap();
                std::fs::write(p.join("x"), "x").unwrap();
            }),
        ),
        (
            "a /dev/zero link",
            Box::new(|p: &Path| replace_with_symlink(p, Path::new("/dev/zero"))),
        ),
    ];
    for (what, spoil) in &damage {
        for p in packs(&results, "heal") {
            spoil(&p);
        }
        // (`chmod 000` hides nothing from root: then nothing is damaged.)
        let damaged = cmd("verify", &file, &results, &[]).status.code() == Some(1);
        assert!(damaged || *what == "chmod 000", "{what}");
        let out = cmd("run", &file, &results, &[]);
        assert_code(&out, 0);
        assert_eq!(
            stderr(&out).contains("healed the cache"),
            damaged,
            "{what}: {}",
            stderr(&out)
        );
        assert_eq!(gathered(&results, "heal"), clean, "{what}");
        let v = cmd("verify", &file, &results, &[]);
        assert_code(&v, 0);
        assert!(stdout(&v).contains(", 0 damaged"), "{what}: {}", stdout(&v));
        assert!(!stderr(&v).contains("damaged"), "{what}: {}", stderr(&v));
    }
    // A rerun with nothing damaged reads nothing again and heals nothing.
    let out = cmd("run", &file, &results, &[]);
    assert_code(&out, 0);
    assert!(!stderr(&out).contains("healed"), "{}", stderr(&out));
    assert_eq!(run_json(&results, "heal")["healed"], serde_json::json!([]));
}

/// `ltcal verify --repair` takes out what is damaged, says what it did,
/// and leaves a cache `verify` passes; the next run recomputes only that.
#[test]
fn verify_repair_takes_out_what_is_damaged_and_verify_passes_after_it() {
    let tmp = tempfile::tempdir().unwrap();
    let file = cheap(tmp.path(), "repair", Some(4));
    let results = tmp.path().join("results");
    assert_code(&cmd("run", &file, &results, &[]), 0);
    let clean = gathered(&results, "repair");
    let pack = packs(&results, "repair").remove(0);
    let b = std::fs::read(&pack).unwrap();
    std::fs::write(&pack, &b[..b.len() - 1]).unwrap();
    let v = cmd("verify", &file, &results, &[]);
    assert_code(&v, 1);
    assert!(stderr(&v).contains("verify --repair"), "{}", stderr(&v));
    let r = cmd("verify", &file, &results, &["--repair"]);
    assert_code(&r, 0);
    let said = stdout(&r);
    assert!(
        said.contains(&format!("repaired {}", pack.display())) && said.contains("removed"),
        "{said}"
    );
    assert!(said.contains("the cache is good again"), "{said}");
    assert!(!pack.exists());
    assert_code(&cmd("verify", &file, &results, &[]), 0);
    let out = cmd("run", &file, &results, &[]);
    assert_code(&out, 0);
    assert_eq!(
        run_json(&results, "repair")["sweep"]["ran"],
        4,
        "{}",
        stderr(&out)
    );
    assert_eq!(gathered(&results, "repair"), clean);
}
