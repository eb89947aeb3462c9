//! The runner and its cache, asserted from the run report; the cache key
//! against every setting of every stage kind; `plan`, `explain`, `graph`
//! and failure handling through the command line.

use crate::cli::*;
use crate::util::*;
use ltcal::pipeline::cache::KeyFields;
use ltcal::pipeline::resolve::{Override, Pipeline, Stage};
use ltcal::pipeline::source::Source;
use ltcal::pipeline::{self, plan, raw};
use ltcal::stages::{KINDS, StageConfig};
use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn set(v: Vec<&str>) -> BTreeSet<String> {
    v.into_iter().map(String::from).collect()
}

#[test]
fn second_run_recomputes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let file = pipeline_path("synthetic-validation.toml");
    let first = run_pipeline(&file, dir.path(), &[]);
    assert_eq!(first.with_status("ran").len(), first.stages.len());
    let second = run_pipeline(&file, dir.path(), &[]);
    assert!(
        second.with_status("ran").is_empty(),
        "{:?}",
        second.with_status("ran")
    );
    assert_eq!(second.with_status("cached").len(), second.stages.len());
}

#[test]
fn changing_one_parameter_reruns_that_stage_and_its_descendants_only() {
    let dir = tempfile::tempdir().unwrap();
    let file = pipeline_path("synthetic-validation.toml");
    run_pipeline(&file, dir.path(), &[]);
    let r = run_pipeline(&file, dir.path(), &["stages.measure_sphere_noisy.seed=2"]);
    assert_eq!(
        set(r.with_status("ran")),
        set(vec![
            "measure_sphere_noisy",
            "identify_sphere_noisy",
            "correct_sphere_noisy",
            "evaluate_sphere_noisy",
            "figure8_noisy"
        ])
    );
    let why = &r
        .stages
        .iter()
        .find(|s| s.stage == "measure_sphere_noisy")
        .unwrap()
        .reason;
    assert_eq!(why, "changed: seed: 1 → 2");
    // Changing it back finds the first results in the cache.
    let back = run_pipeline(&file, dir.path(), &[]);
    assert!(back.with_status("ran").is_empty());
}

#[test]
fn a_change_upstream_with_identical_output_stops_there() {
    let dir = tempfile::tempdir().unwrap();
    let file = pipeline_path("synthetic-validation.toml");
    run_pipeline(&file, dir.path(), &[]);
    // A cube whose x range ends a little further out: the mesh stage's
    // settings differ (its key changes) but its points do not (the next
    // value, 14000, is beyond either end), so nothing downstream reruns.
    let r = run_pipeline(&file, dir.path(), &["stages.cube.x.to=10001"]);
    assert_eq!(set(r.with_status("ran")), set(vec!["cube"]));
}

/// Every pipeline file under `pipelines/`, examples included.
fn example_pipelines() -> Vec<PathBuf> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        for e in std::fs::read_dir(dir).unwrap().flatten() {
            let p = e.path();
            // `pipelines/hypotheses/` holds hypothesis files, not pipelines.
            if p.is_dir() && !p.ends_with("pipelines/hypotheses") {
                walk(&p, out);
            } else if p.extension().is_some_and(|x| x == "toml") {
                out.push(p);
            }
        }
    }
    let mut out = Vec::new();
    walk(&root().join("pipelines"), &mut out);
    out.sort();
    assert!(!out.is_empty());
    out
}

/// A stage's key with a fixed content hash for each input: what the key
/// makes of the stage's own settings.
fn settings_key(s: &Stage) -> String {
    let inputs = s
        .wired_tables()
        .into_iter()
        .map(|(slot, _)| (slot, "0".repeat(64)))
        .collect();
    plan::key_fields(s, inputs).hash()
}

/// `text` with comments, blank lines, indentation and spacing added
/// everywhere TOML allows them (not inside multi-line strings).
fn reformat(text: &str) -> String {
    let mut out = String::new();
    let mut in_string = false;
    for line in text.lines() {
        let quotes = line.matches("\"\"\"").count() + line.matches("'''").count();
        if in_string {
            out.push_str(line);
            out.push('\n');
            in_string ^= quotes % 2 == 1;
            continue;
        }
        let trimmed = line.trim_start();
        if trimmed.starts_with('[') && !trimmed.starts_with("[[") {
            out.push_str("\n# a comment before a table\n\n");
        }
        let key_line = trimmed.starts_with(|c: char| c.is_ascii_alphanumeric() || c == '_');
        let mut l = match (key_line, line.split_once(" = ")) {
            (true, Some((k, v))) => format!("  {}   =   {v}", k.trim()),
            _ => line.to_string(),
        };
        if quotes % 2 == 1 {
            in_string = true;
        } else if !trimmed.is_empty() && !trimmed.starts_with('#') {
            l.push_str("    # a trailing comment");
        }
        out.push_str(&l);
        out.push('\n');
    }
    out
}

#[test]
fn comments_and_whitespace_do_not_change_any_key() {
    // Through a run: nothing reruns.
    let dir = tempfile::tempdir().unwrap();
    let file = pipeline_path("synthetic-validation.toml");
    run_pipeline(&file, dir.path(), &[]);
    let edited = dir.path().join("synthetic-validation.toml");
    std::fs::write(&edited, reformat(&std::fs::read_to_string(&file).unwrap())).unwrap();
    let r = run_pipeline(&edited, dir.path(), &[]);
    assert!(
        r.with_status("ran").is_empty(),
        "{:?}",
        r.with_status("ran")
    );
    // And every stage of every pipeline in `pipelines/`: the same settings,
    // wiring and key.
    for path in example_pipelines() {
        let text = std::fs::read_to_string(&path).unwrap();
        let again = reformat(&text);
        assert_ne!(text, again);
        let a = pipeline::load_source(&Source::new(&path, text), &[])
            .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let b = pipeline::load_source(&Source::new(&path, again.clone()), &[])
            .unwrap_or_else(|e| panic!("{}, reformatted:\n{again}\n{e}", path.display()));
        assert_eq!(a.stages.len(), b.stages.len());
        for (x, y) in a.stages.iter().zip(&b.stages) {
            assert_eq!(x.name, y.name);
            assert_eq!(x.inputs, y.inputs, "{}: {}", path.display(), x.name);
            assert_eq!(x.config.to_json(), y.config.to_json());
            assert_eq!(
                settings_key(x),
                settings_key(y),
                "{}: {}",
                path.display(),
                x.name
            );
        }
    }
}

/// A path into a JSON value.
#[derive(Clone, Debug)]
enum Seg {
    Key(String),
    Index(usize),
}

/// Every leaf (number, string, bool, null) of a value, with its path.
fn leaves(v: &Value, path: Vec<Seg>, out: &mut Vec<(Vec<Seg>, Value)>) {
    match v {
        Value::Object(m) => {
            for (k, v) in m {
                let mut p = path.clone();
                p.push(Seg::Key(k.clone()));
                leaves(v, p, out);
            }
        }
        Value::Array(a) => {
            for (i, v) in a.iter().enumerate() {
                let mut p = path.clone();
                p.push(Seg::Index(i));
                leaves(v, p, out);
            }
        }
        _ => out.push((path, v.clone())),
    }
}

fn set_at(v: &mut Value, path: &[Seg], new: Value) {
    match path.split_first() {
        None => *v = new,
        Some((Seg::Key(k), rest)) => set_at(&mut v[k.as_str()], rest, new),
        Some((Seg::Index(i), rest)) => set_at(&mut v[*i], rest, new),
    }
}

fn show(path: &[Seg]) -> String {
    path.iter()
        .map(|s| match s {
            Seg::Key(k) => k.clone(),
            Seg::Index(i) => i.to_string(),
        })
        .collect::<Vec<_>>()
        .join(".")
}

/// The values a leaf is changed to, in order of preference. For a string,
/// first the alternatives the setting's own error message names (`expected
/// one of …`), which is how enums are found without knowing them.
fn candidates(v: &Value, named: &[String]) -> Vec<Value> {
    let mut out: Vec<Value> = match v {
        Value::Bool(b) => vec![Value::Bool(!b)],
        Value::Number(n) if n.is_u64() || n.is_i64() => {
            let n = n.as_i64().unwrap();
            [n + 1, n + 2, 2 * n, n - 1]
                .iter()
                .map(|&x| x.into())
                .collect()
        }
        Value::Number(n) => {
            let x = n.as_f64().unwrap();
            [x * 1.5 + 0.25, x + 1.0, x * 0.5, x * 2.0, -x, 0.5]
                .iter()
                .map(|&x| x.into())
                .collect()
        }
        Value::String(s) => named
            .iter()
            .map(|n| Value::String(n.clone()))
            .chain([format!("{s}x"), format!("x{s}"), s.to_uppercase()].map(Value::String))
            .collect(),
        _ => vec![1.into(), 0.5.into(), true.into(), "x".into()],
    };
    out.retain(|c| c != v);
    out
}

const NO_SUCH_VALUE: &str = "ltcal-no-such-value";

/// The names an error message offers: backquoted ones, and the list after
/// its last "one of" or "expected" — but the value that caused it.
fn named_in(message: &str) -> Vec<String> {
    let quoted = message.split('`').skip(1).step_by(2);
    let tail = ["one of", "expected"]
        .iter()
        .filter_map(|w| message.rfind(w).map(|i| &message[i + w.len()..]))
        .next()
        .unwrap_or("");
    let listed = tail
        .split(|c: char| c.is_whitespace() || ",;:`'\"".contains(c))
        .filter(|w| *w != "or");
    let mut out: Vec<String> = Vec::new();
    for w in quoted.chain(listed) {
        if w != NO_SUCH_VALUE && !w.is_empty() && !out.iter().any(|o| o == w) {
            out.push(w.to_string());
        }
    }
    out
}

/// Resolved settings and key of a stage with one top-level setting replaced,
/// or why the replacement was rejected.
type KeyWith<'a> = dyn Fn(&str, &Value) -> Result<(Value, String), String> + 'a;

/// The typed path, without validation: the settings as JSON through the
/// kind's own type (`from_json`, `resolve`, `to_json`) into the key. A
/// setting that selects a variant (`plot = "criterion"`) cannot change
/// alone without other settings becoming invalid; its place in the key is
/// still checked this way.
fn typed_key(
    kind: &str,
    params: &Value,
) -> impl Fn(&str, &Value) -> Result<(Value, String), String> {
    let (kind, params) = (kind.to_string(), params.clone());
    move |top: &str, v: &Value| {
        let mut json = params.clone();
        json[top] = v.clone();
        // Settings that `resolve` derives and the file cannot hold are not
        // accepted as input: drop them, `resolve` fills them in again.
        let c = loop {
            match StageConfig::from_json(&kind, json.clone()) {
                Ok(c) => break c,
                Err(e) => {
                    let e = e.to_string();
                    let field = e
                        .split_once("unknown field `")
                        .and_then(|(_, r)| r.split_once('`'));
                    match field.map(|(f, _)| f) {
                        Some(f) if f != top && json.get(f).is_some() => {
                            json.as_object_mut().unwrap().remove(f);
                        }
                        _ => return Err(e),
                    }
                }
            }
        };
        let c = c.resolve();
        let key = KeyFields {
            ltcal_version: ltcal::VERSION.into(),
            code: ltcal::CODE_FINGERPRINT.into(),
            kind: kind.clone(),
            params: c.to_json(),
            inputs: BTreeMap::new(),
            file: None,
        }
        .hash();
        Ok((c.to_json(), key))
    }
}

/// Changes every leaf of `params` in turn and asserts that the key
/// changes: through `strict` (the user's way, `--set`, with validation),
/// or when no change passes validation through [`typed_key`]. A setting
/// that `resolve` derives and the file cannot hold (`unknown field` even
/// at its own value) is skipped: what it is derived from is in the key
/// through it. Returns how many leaves were changed.
fn perturb_every_leaf(what: &str, kind: &str, params: &Value, strict: &KeyWith) -> usize {
    let typed = typed_key(kind, params);
    let mut all = Vec::new();
    leaves(params, Vec::new(), &mut all);
    let mut changed = 0;
    for (path, value) in all {
        let Some(Seg::Key(top)) = path.first() else {
            panic!("{what}: settings are not a table");
        };
        let with = |key_with: &KeyWith, new: Value| {
            let mut p = params.clone();
            set_at(&mut p, &path, new);
            key_with(top, &p[top.as_str()])
        };
        if let Err(e) = with(strict, value.clone()) {
            assert!(e.contains(&format!("unknown field `{top}`")), "{what}: {e}");
            continue;
        }
        let named = match &value {
            Value::String(_) => {
                named_in(&with(strict, NO_SUCH_VALUE.into()).err().unwrap_or_default())
            }
            _ => Vec::new(),
        };
        let mut tried = Vec::new();
        let mut done = false;
        for key_with in [strict, &typed as &KeyWith] {
            // Setting a value to itself changes nothing.
            let (_, base) = with(key_with, value.clone()).unwrap_or_else(|e| panic!("{what}: {e}"));
            for c in candidates(&value, &named) {
                match with(key_with, c.clone()) {
                    Ok((resolved, key)) if resolved != *params => {
                        assert_ne!(
                            key,
                            base,
                            "{what}: `{}` changed from {value} to {c} but the key did not",
                            show(&path)
                        );
                        done = true;
                        break;
                    }
                    Ok(_) => tried.push(format!("{c}: resolved back to the same settings")),
                    Err(e) => tried.push(format!("{c}: {}", e.lines().next().unwrap_or(""))),
                }
            }
            if done {
                break;
            }
        }
        // An unset optional value (null) has no type to change it within.
        assert!(
            done || value.is_null(),
            "{what}: no change of `{}` = {value} was accepted:\n  {}",
            show(&path),
            tried.join("\n  ")
        );
        changed += done as usize;
    }
    changed
}

#[test]
fn changing_any_resolved_setting_of_any_stage_kind_changes_the_key() {
    let mut covered: BTreeMap<&str, usize> = BTreeMap::new();
    let mut seen: BTreeSet<(String, String)> = BTreeSet::new();
    for path in example_pipelines() {
        let text = std::fs::read_to_string(&path).unwrap();
        let src = Source::new(&path, text);
        let base: Pipeline = pipeline::load_source(&src, &[]).unwrap();
        for s in &base.stages {
            let params = s.config.to_json();
            // Stages with the same settings have the same leaves.
            if !seen.insert((s.config.kind().to_string(), params.to_string())) {
                continue;
            }
            let what = format!(
                "{}: stage `{}` ({})",
                path.display(),
                s.name,
                s.config.kind()
            );
            let strict = |top: &str, v: &Value| -> Result<(Value, String), String> {
                let o = Override {
                    path: vec!["stages".into(), s.name.clone(), top.into()],
                    value: v.clone(),
                    text: format!("stages.{}.{top}={v}", s.name),
                    origin: None,
                };
                let p = pipeline::load_source(&src, &[o]).map_err(|e| e.to_string())?;
                let st = &p.stages[p.index(&s.name).unwrap()];
                Ok((st.config.to_json(), settings_key(st)))
            };
            let n = perturb_every_leaf(&what, s.config.kind(), &params, &strict);
            *covered.entry(s.config.kind()).or_default() += n;
        }
    }
    // A kind no example uses: `kind = "…"` alone gives its default settings.
    for kind in KINDS {
        if covered.contains_key(kind) {
            continue;
        }
        let src = Source::new("minimal.toml", format!("[stages.x]\nkind = \"{kind}\"\n"));
        let raw = raw::parse(&src).unwrap_or_else(|e| {
            panic!(
                "kind `{kind}` appears in no pipeline under pipelines/ and has required settings \
                 ({}): add an example pipeline that uses it",
                e[0].message
            )
        });
        let params = raw.stages[0].config.clone().resolve().to_json();
        let strict = |top: &str, v: &Value| -> Result<(Value, String), String> {
            let (resolved, key) = typed_key(kind, &params)(top, v)?;
            let c = StageConfig::from_json(kind, resolved.clone()).map_err(|e| e.to_string())?;
            match c.validate().first() {
                Some(inv) => Err(format!("`{}`: {}", inv.field, inv.message)),
                None => Ok((resolved, key)),
            }
        };
        let n = perturb_every_leaf(&format!("kind `{kind}`"), kind, &params, &strict);
        covered.insert(kind, n);
    }
    eprintln!("settings changed per kind: {covered:?}");
    // Every kind was exercised, and those with settings had them changed.
    assert_eq!(
        covered.keys().copied().collect::<BTreeSet<_>>(),
        KINDS.iter().copied().collect()
    );
    for kind in ["mesh", "inject", "measure", "identify", "plot"] {
        assert!(
            covered[kind] >= 2,
            "{kind}: only {} settings changed",
            covered[kind]
        );
    }
    // The other key fields: version, code, kind, each input's content and
    // the content of the file the stage reads.
    let k = KeyFields {
        ltcal_version: "0.1.0".into(),
        code: "c0de".into(),
        kind: "measure".into(),
        params: serde_json::json!({"seed": 1}),
        inputs: BTreeMap::from([("points".into(), "a".into()), ("errors".into(), "b".into())]),
        file: None,
    };
    let mut variants = vec![k.clone(); 6];
    variants[5].file = Some("f11e".into());
    variants[0].ltcal_version = "0.1.1".into();
    variants[4].code = "c0de2".into();
    variants[1].kind = "identify".into();
    variants[2].inputs.insert("points".into(), "c".into());
    variants[3].inputs.remove("errors");
    for v in &variants {
        assert_ne!(v.hash(), k.hash(), "{v:?}");
    }
}

/// A pipeline with two stages that fail (a figure of a table that lacks
/// its columns), one that depends on a failure, and one independent of
/// both in a later level.
const FAILING: &str = r#"
[stages.a]
kind = "mesh"
shape = "plane"

[stages.t]
kind = "inject"

[stages.bad1]
kind = "plot"
plot = "mesh-errors"
inputs = { table = "a" }

[stages.bad2]
kind = "plot"
plot = "mesh-errors"
inputs = { table = "t" }

[stages.m]
kind = "measure"
inputs = { points = "a", errors = "t" }

[stages.after]
kind = "plot"
plot = "mesh-errors"
inputs = { table = "bad1.figure" }

[stages.i]
kind = "identify"
inputs = { readings = "m" }
"#;

fn status_and_reason(results: &Path) -> BTreeMap<String, (String, String)> {
    stages(&run_json(results, "p"))
        .into_iter()
        .map(|(n, s)| {
            let st = s["status"].as_str().unwrap().to_string();
            (n, (st, s["reason"].as_str().unwrap().to_string()))
        })
        .collect()
}

#[test]
fn a_failure_stops_the_run_after_its_level_unless_keep_going() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("p.toml"), FAILING).unwrap();
    let results = dir.path().join("results");
    let fail_a = "table `a.points` has no column `x_ref_mm` (it has: target, x_mm, y_mm, z_mm)";
    let fail_t = "table `t.params` has no column `x_ref_mm`";

    let out = ltcal(dir.path(), &["run", "p.toml"]);
    assert_code(&out, 1);
    let st = status_and_reason(&results);
    assert_eq!(st["bad1"], ("failed".into(), fail_a.into()));
    assert_eq!(st["bad2"].0, "failed");
    assert!(st["bad2"].1.starts_with(fail_t));
    // The failures' level finishes; nothing after it starts.
    assert_eq!(st["m"].0, "ran");
    assert_eq!(
        st["after"],
        ("skipped".into(), "its input bad1 did not complete".into())
    );
    assert_eq!(
        st["i"],
        (
            "skipped".into(),
            "the run stopped at the first failure (use --keep-going)".into()
        )
    );
    let err = stderr(&out);
    assert!(err.contains("p: 3 ran, 0 cached, 2 FAILED"), "{err}");
    assert!(
        err.contains(&format!("stage `bad1` (plot) failed:\n  {fail_a}")),
        "{err}"
    );
    assert!(
        err.contains("stage `bad2` (plot) failed:\n  table `t.params`"),
        "{err}"
    );
    // The failures are listed last, after the summary.
    assert!(err.find("2 FAILED").unwrap() < err.find("stage `bad1` (plot) failed").unwrap());

    let out = ltcal(dir.path(), &["run", "p.toml", "--keep-going"]);
    assert_code(&out, 1);
    let st = status_and_reason(&results);
    assert_eq!(st["i"].0, "ran");
    assert_eq!(st["m"].0, "cached");
    assert_eq!(st["after"].0, "skipped");
    assert_eq!(st["bad1"].0, "failed");
    assert_eq!(st["bad2"].0, "failed");
    let err = stderr(&out);
    assert!(err.contains("p: 1 ran, 3 cached, 2 FAILED"), "{err}");
    assert!(
        err.contains(&format!("stage `bad1` (plot) failed:\n  {fail_a}")),
        "{err}"
    );
}

/// A results folder with the synthetic validation run in it.
fn synthetic_results() -> (tempfile::TempDir, String) {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_pipeline(&pipeline_path("synthetic-validation.toml"), &results, &[]);
    let r = results.to_string_lossy().into_owned();
    (dir, r)
}

/// `ltcal <cmd> pipelines/synthetic-validation.toml --results <r> <extra>`,
/// from the repository root.
fn synthetic(cmd: &str, r: &str, extra: &[&str]) -> std::process::Output {
    let mut args = vec![cmd, "pipelines/synthetic-validation.toml", "--results", r];
    args.extend(extra);
    ltcal(&root(), &args)
}

const SEED2: [&str; 2] = ["--set", "stages.measure_sphere_noisy.seed=2"];

#[test]
fn plan_check_and_json_say_what_would_run() {
    let (_dir, r) = synthetic_results();
    let out = synthetic("plan", &r, &["--check"]);
    assert_code(&out, 0);
    assert_eq!(
        stdout(&out)
            .lines()
            .filter(|l| l.starts_with("cached  "))
            .count(),
        25
    );

    let out = synthetic("plan", &r, &[SEED2[0], SEED2[1], "--check"]);
    assert_code(&out, 1);
    assert!(
        stderr(&out).contains("plan --check: 5 of 25 stages would run"),
        "{}",
        stderr(&out)
    );
    assert!(
        stdout(&out).contains("   run  measure_sphere_noisy    measure    changed: seed: 1 → 2\n")
    );

    let out = synthetic("plan", &r, &[SEED2[0], SEED2[1], "--json"]);
    assert_code(&out, 0);
    let items: Vec<Value> = serde_json::from_str(&stdout(&out)).unwrap();
    assert_eq!(items.len(), 25);
    let by: BTreeMap<&str, &Value> = items
        .iter()
        .map(|i| (i["stage"].as_str().unwrap(), i))
        .collect();
    assert_eq!(by["truth"]["status"], "cached");
    assert_eq!(by["truth"]["key"].as_str().unwrap().len(), 64);
    assert_eq!(by["measure_sphere_noisy"]["reason"], "changed: seed: 1 → 2");
    assert_eq!(
        by["identify_sphere_noisy"]["reason"],
        "its input stage `measure_sphere_noisy` will run"
    );
    assert!(by["identify_sphere_noisy"]["key"].is_null());
    let running: Vec<&str> = items
        .iter()
        .filter(|i| i["status"] == "run")
        .map(|i| i["stage"].as_str().unwrap())
        .collect();
    assert_eq!(
        running,
        [
            "measure_sphere_noisy",
            "identify_sphere_noisy",
            "correct_sphere_noisy",
            "evaluate_sphere_noisy",
            "figure8_noisy"
        ]
    );
}

#[test]
fn explain_compares_the_key_with_the_last_run_field_by_field() {
    let (_dir, r) = synthetic_results();
    let max_iters = "stages.identify_sphere_noisy.max_iters=50";
    let out = synthetic(
        "explain",
        &r,
        &[
            "identify_sphere_noisy",
            SEED2[0],
            SEED2[1],
            "--set",
            max_iters,
        ],
    );
    assert_code(&out, 0);
    let s = stdout(&out);
    let lines: Vec<&str> = s.lines().collect();
    assert_eq!(
        lines[0],
        "stage `identify_sphere_noisy` (identify): would run: its input stage `measure_sphere_noisy` will run"
    );
    assert!(lines[1].starts_with("key now —, at the last run "), "{s}");
    // Each row: marker, field, last run, now.
    let row = |field: &str| -> Vec<String> {
        let l = lines
            .iter()
            .find(|l| l.len() > 4 && l[4..].starts_with(&format!("{field} ")))
            .unwrap_or_else(|| panic!("no {field} in:\n{s}"));
        let mut cells = vec![l[..4].trim().to_string()];
        cells.extend(
            l[4..]
                .split("  ")
                .map(str::trim)
                .filter(|c| !c.is_empty())
                .map(String::from),
        );
        cells
    };
    assert_eq!(row("max_iters"), ["*", "max_iters", "100", "50"]);
    assert_eq!(row("rank_tol"), ["", "rank_tol", "1e-9", "1e-9"]);
    assert_eq!(row("kind"), ["", "kind", "identify", "identify"]);
    let readings = row("input `readings`");
    assert_eq!(readings[0], "", "an input not yet known is not a change");
    assert_eq!(readings[3], "(known once `measure_sphere_noisy` has run)");

    // A cached stage: its key is the last run's, nothing changed.
    let out = synthetic("explain", &r, &["evaluate_sphere", "--json"]);
    assert_code(&out, 0);
    let e: Value = serde_json::from_str(&stdout(&out)).unwrap();
    assert_eq!(e["status"], "cached");
    assert_eq!(e["key"], e["last_key"]);
    let rows = e["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 5, "version, code, kind, two inputs: {rows:?}");
    assert_eq!(rows[1]["field"], "code");
    assert_eq!(rows[1]["now"], &ltcal::CODE_FINGERPRINT[..12]);
    assert!(rows.iter().all(|r| r["changed"] == false));

    // A misspelt stage is the user's input error (exit 2), like a bad flag.
    let out = synthetic("explain", &r, &["evaluate_spher"]);
    assert_code(&out, 2);
    assert!(stderr(&out).contains("the pipeline has no stage `evaluate_spher`"));
}

#[test]
fn graph_draws_every_stage_and_input_with_its_status() {
    let (_dir, r) = synthetic_results();
    let dot = synthetic("graph", &r, &SEED2);
    assert_code(&dot, 0);
    let d = stdout(&dot);
    assert!(d.starts_with("digraph \"synthetic-validation\" {"));
    // One edge per input: 4 measures × 2, 5 identifies, 4 corrects × 2,
    // 4 evaluates × 2, 4 plots.
    let edges = d.matches(" -> ").count();
    assert_eq!(edges, 8 + 5 + 8 + 8 + 4);
    assert_eq!(d.matches("[label=\"").count() - edges, 25);
    assert!(d.contains("\"measure_sphere\" -> \"identify_sphere_table3\" [label=\"readings\"];"));
    assert!(d.contains("\"evaluate_plane\" -> \"figure6\" [label=\"table ← points\"];"));
    assert_eq!(
        d.matches("fillcolor=\"#ffe0b2\", tooltip=\"would run\"")
            .count(),
        5
    );
    assert_eq!(
        d.matches("fillcolor=\"#c6efce\", tooltip=\"cached\"")
            .count(),
        20
    );

    let m = stdout(&synthetic("graph", &r, &["--format", "mermaid"]));
    assert!(m.starts_with("flowchart TB\n"));
    assert_eq!(m.matches(":::cached\n").count(), 25);
    assert_eq!(m.matches(" -->|").count(), edges);

    let svg = stdout(&synthetic(
        "graph",
        &r,
        &[SEED2[0], SEED2[1], "--format", "svg"],
    ));
    assert!(svg.starts_with("<svg ") && svg.trim_end().ends_with("</svg>"));
    assert_eq!(
        svg.matches("fill=\"#FFE0B2\"").count(),
        5 + 1,
        "5 boxes and the legend"
    );
    assert_eq!(svg.matches("fill=\"#C6EFCE\"").count(), 20 + 1);
    for s in ["truth", "figure8_noisy", "identify_sphere_table3"] {
        assert!(svg.contains(&format!("\n{s}\n</text>")), "{s}");
    }
}

#[test]
fn show_prints_a_table_and_refuses_one_edited_after_publishing() {
    let (_dir, r) = synthetic_results();
    let out = synthetic("show", &r, &["evaluate_sphere.summary", "--digits", "3"]);
    assert_code(&out, 0);
    let text = stdout(&out);
    assert!(
        text.starts_with("statistic") && text.contains("reduction_pct"),
        "{text}"
    );
    assert!(
        text.lines()
            .any(|l| l.trim_start().starts_with("rms") && l.ends_with("100.000")),
        "{text}"
    );

    let out = synthetic("show", &r, &["evaluate_sphere.nope"]);
    assert_code(&out, 2);
    assert!(stderr(&out).contains("its tables are: summary, points"));

    // A published table changed by hand is not shown as if it were the result.
    let published = Path::new(&r)
        .join("synthetic-validation")
        .join("evaluate_sphere")
        .join("summary.parquet");
    let mut bytes = std::fs::read(&published).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x20;
    std::fs::write(&published, bytes).unwrap();
    let out = synthetic("show", &r, &["evaluate_sphere.summary"]);
    assert_code(&out, 1);
    assert!(
        stderr(&out).contains("differs from the result it was published from"),
        "{}",
        stderr(&out)
    );

    // `run` puts the cached result back, and says so.
    let out = synthetic("run", &r, &["-q"]);
    assert_code(&out, 0);
    assert!(
        stderr(&out).contains("note: restored")
            && stderr(&out).contains("differed from the cached result of `evaluate_sphere`"),
        "{}",
        stderr(&out)
    );
    assert_code(&synthetic("show", &r, &["evaluate_sphere.summary"]), 0);
}
