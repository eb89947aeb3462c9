//! The architecture invariants of ARCHITECTURE.md that can be checked by
//! reading the source: a test fails the day a change breaks one, instead of
//! the layers eroding one convenient import at a time.

use std::path::{Path, PathBuf};

/// Every `.rs` file below `dir`, sorted.
fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let path = e.path();
        if path.is_dir() {
            out.extend(rust_files(&path));
        } else if path.extension().is_some_and(|x| x == "rs") {
            out.push(path);
        }
    }
    out.sort();
    out
}

/// The source, without `//` comments: a doc comment may mention the runner;
/// only code depends on it.
fn code(path: &Path) -> String {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .map(|l| l.split_once("//").map_or(l, |(code, _)| code))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The layers above the domain, as paths from the crate root.
const ABOVE: [&str; 3] = ["pipeline", "stages", "cli"];

/// Whether `code` names one of [`ABOVE`]: `crate::pipeline`,
/// `crate::{…, stages, …}`, `super::super::cli`.
fn names_a_layer_above(code: &str) -> Option<String> {
    names_one_of(code, &ABOVE)
}

/// Whether `code` names one of the crate's top-level modules `layers`
/// (`crate::x`, `crate::{…, x, …}`, `super::super::x`).
fn names_one_of(code: &str, layers: &[&str]) -> Option<String> {
    let compact: String = code.chars().filter(|c| !c.is_whitespace()).collect();
    for root in ["crate::", "super::"] {
        for (at, _) in compact.match_indices(root) {
            let mut rest = &compact[at + root.len()..];
            while let Some(r) = rest.strip_prefix("super::") {
                rest = r;
            }
            let names: Vec<&str> = match rest.strip_prefix('{') {
                Some(group) => group
                    .split('}')
                    .next()
                    .unwrap_or_default()
                    .split(',')
                    .collect(),
                None => vec![rest],
            };
            for name in names {
                let first = name
                    .split(|c: char| !(c.is_alphanumeric() || c == '_'))
                    .next()
                    .unwrap_or_default();
                if layers.contains(&first) {
                    return Some(format!("{root}{}", &rest[..rest.len().min(40)]));
                }
            }
        }
    }
    None
}

#[test]
fn the_domain_knows_nothing_of_pipeline_stages_or_cli() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let above = |p: &Path| {
        let rel = p.strip_prefix(&src).unwrap();
        let first = rel
            .components()
            .next()
            .unwrap()
            .as_os_str()
            .to_string_lossy();
        ["pipeline", "stages", "cli.rs", "main.rs", "lib.rs"].contains(&first.as_ref())
    };
    let domain: Vec<PathBuf> = rust_files(&src).into_iter().filter(|p| !above(p)).collect();
    assert!(
        domain.len() > 20,
        "found only {} domain files",
        domain.len()
    );
    let offending: Vec<String> = domain
        .iter()
        .filter_map(|p| {
            names_a_layer_above(&code(p))
                .map(|what| format!("{} names {what}", p.strip_prefix(&src).unwrap().display()))
        })
        .collect();
    assert!(
        offending.is_empty(),
        "the domain must not depend on the runner (ARCHITECTURE.md, invariants):\n  {}",
        offending.join("\n  ")
    );
}

#[test]
fn the_layering_check_sees_every_way_of_naming_a_layer() {
    assert!(names_a_layer_above("use crate::pipeline::cache;").is_some());
    assert!(names_a_layer_above("use crate::{table, stages::StageInputs};").is_some());
    assert!(names_a_layer_above("use super::super::cli;").is_some());
    assert!(names_a_layer_above("crate :: pipeline :: run()").is_some());
    assert!(names_a_layer_above("use crate::table; use super::check;").is_none());
    assert!(names_a_layer_above("use crate::pipelines_of_pipes;").is_none());
}

/// `code` without its `#[cfg(test)]` items (test modules, test-only
/// functions and imports), each cut from the attribute to the end of its
/// item — the matching `}` of its first `{`, or its `;` — so that shipped
/// code after a test item is still read (splitting at the first
/// `#[cfg(test)]` left `sparse.rs:301–1080` and `linear.rs:151–787`
/// unchecked).
fn shipped(code: &str) -> String {
    let mut out = String::new();
    let mut rest = code;
    while let Some(at) = rest.find("#[cfg(test)]") {
        out.push_str(&rest[..at]);
        let item = &rest[at + "#[cfg(test)]".len()..];
        let end = match (item.find('{'), item.find(';')) {
            (Some(open), semi) if semi.is_none_or(|s| open < s) => {
                let mut depth = 0usize;
                item[open..]
                    .char_indices()
                    .find_map(|(i, c)| {
                        match c {
                            '{' => depth += 1,
                            '}' => depth -= 1,
                            _ => {}
                        }
                        (depth == 0).then_some(open + i + 1)
                    })
                    .unwrap_or(item.len())
            }
            (_, Some(semi)) => semi + 1,
            _ => item.len(),
        };
        rest = &item[end..];
    }
    out.push_str(rest);
    out
}

/// The files of `src/` (but `own`) whose shipped code contains one of
/// `calls`, each with the calls found.
fn calls_outside(own: &[&str], calls: &[&str]) -> Vec<String> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    rust_files(&src)
        .into_iter()
        .filter(|p| !own.iter().any(|o| p == &src.join(o)))
        .filter_map(|p| {
            let found = found_calls(&shipped(&code(&p)), calls);
            (!found.is_empty()).then(|| {
                format!(
                    "{} uses {}",
                    p.strip_prefix(&src).unwrap().display(),
                    found.join(", ")
                )
            })
        })
        .collect()
}

fn found_calls<'a>(code: &str, calls: &[&'a str]) -> Vec<&'a str> {
    calls.iter().copied().filter(|c| code.contains(c)).collect()
}

const WRITES: [&str; 4] = ["File::create", "fs::write(", "OpenOptions", "fs::copy("];
const READS: [&str; 3] = ["fs::read(", "fs::read_to_string(", "File::open("];

/// Unit tests may damage files on purpose: test items are not checked.
#[test]
fn every_file_ltcal_writes_goes_through_fs() {
    let offending = calls_outside(&["fs.rs"], &WRITES);
    assert!(
        offending.is_empty(),
        "files are written only by src/fs.rs (write_atomic, write_staged):\n  {}",
        offending.join("\n  ")
    );
}

/// ARCHITECTURE.md: a file ltcal did not just write is read through
/// `fs::read_regular_file` (a regular file, bounded). `code.rs` is exempt:
/// it is compiled into `build.rs` too, where `crate::fs` does not exist,
/// and reads only the crate's own sources; `source_scan.rs` is a test-only
/// module (declared under `#[cfg(test)]` in `lib.rs`).
#[test]
fn every_file_ltcal_reads_goes_through_read_regular_file() {
    let offending = calls_outside(&["fs.rs", "code.rs", "source_scan.rs"], &READS);
    assert!(
        offending.is_empty(),
        "read files through fs::read_regular_file:\n  {}",
        offending.join("\n  ")
    );
}

/// Both rules see a call after a test item, and neither sees one inside it.
#[test]
fn the_file_access_checks_read_past_test_items() {
    let planted = "fn a() {}\n#[cfg(test)]\nmod tests { fn t() { std::fs::write(p, b); std::fs::read(p); } }\n\
                   #[cfg(test)]\nuse std::fs::File;\nfn shipped() { let f = File::create(p); let b = std::fs::read_to_string(p); }\n";
    let code = shipped(planted);
    assert_eq!(found_calls(&code, &WRITES), ["File::create"]);
    assert_eq!(found_calls(&code, &READS), ["fs::read_to_string("]);
    assert!(!code.contains("mod tests") && !code.contains("use std::fs::File"));
}

/// ARCHITECTURE.md: `hypothesis/` knows nothing of campaigns, the
/// simulation or the diagnosis — they use it, not the other way round.
#[test]
fn hypothesis_knows_nothing_of_campaigns_the_simulation_or_the_diagnosis() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/hypothesis");
    let files = rust_files(&dir);
    assert!(files.len() >= 3, "{files:?}");
    for f in files {
        let code = code(&f);
        for forbidden in [
            "crate::campaign",
            "crate::simulate",
            "crate::diagnose",
            "crate::calibrate",
        ] {
            assert!(
                !code.contains(forbidden),
                "{} names {forbidden}",
                f.display()
            );
        }
    }
}

/// ARCHITECTURE.md: only an effect's own file knows the effect — the
/// simulator, the diagnosis, the blind check and the stages iterate the
/// catalogue (`effects::kinds()`), so no code outside `src/effects/`
/// matches a catalogue id.
#[test]
fn no_effect_id_is_matched_outside_its_plug_in() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let effects = src.join("effects");
    let ids: Vec<&str> = ltcal::effects::kinds().iter().map(|k| k.id).collect();
    assert!(ids.len() >= 7, "{ids:?}");
    for f in rust_files(&src)
        .into_iter()
        .filter(|f| !f.starts_with(&effects))
    {
        let code = code(&f);
        for id in &ids {
            assert!(
                !code.contains(&format!("\"{id}\"")),
                "{} matches the effect id \"{id}\": go through effects::kinds()",
                f.display()
            );
        }
    }
}

/// A tracker model's names in code: its id as a string literal, and its
/// plug-in type (the id in camel case, `mirror-tracker` → `MirrorTracker`,
/// which also catches a `TrackerModel::MirrorTracker` variant).
fn model_names(id: &str) -> [String; 2] {
    let camel: String = id
        .split('-')
        .map(|w| {
            let mut c = w.chars();
            c.next()
                .map_or(String::new(), |f| f.to_uppercase().chain(c).collect())
        })
        .collect();
    [format!("\"{id}\""), camel]
}

/// The first name of a model among `ids` that the shipped part of `code`
/// (before any `#[cfg(test)]`) uses. Unit tests may pick a model by its id.
fn names_a_tracker_model(code: &str, ids: &[&str]) -> Option<String> {
    let shipped = code.split("#[cfg(test)]").next().unwrap_or_default();
    ids.iter()
        .flat_map(|id| model_names(id))
        .find(|name| shipped.contains(name.as_str()))
}

/// ARCHITECTURE.md: only a tracker model's own file knows the model — code
/// outside `src/trackers/` asks a `TrackerModel` handle or iterates
/// `TrackerModel::ALL`, so no shipped code matches a model's id or names
/// its type. Unit tests are allowed to pick a model by its id
/// (`TrackerModel::parse("mirror-tracker")`), as these integration tests do.
#[test]
fn no_tracker_model_is_matched_outside_its_plug_in() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let trackers = src.join("trackers");
    let ids: Vec<&str> = ltcal::trackers::TrackerModel::ALL
        .iter()
        .map(|m| m.id())
        .collect();
    assert!(ids.len() >= 2, "{ids:?}");
    let offending: Vec<String> = rust_files(&src)
        .into_iter()
        .filter(|f| !f.starts_with(&trackers))
        .filter_map(|f| {
            names_a_tracker_model(&code(&f), &ids)
                .map(|name| format!("{} names {name}", f.strip_prefix(&src).unwrap().display()))
        })
        .collect();
    assert!(
        offending.is_empty(),
        "go through the TrackerModel handle or the registry (src/trackers/):\n  {}",
        offending.join("\n  ")
    );
}

#[test]
fn the_tracker_model_check_sees_a_planted_match() {
    let ids = ["api-tracker3", "mirror-tracker"];
    let planted = [
        "match m { TrackerModel::MirrorTracker => 1, _ => 0 }",
        "if m.id() == \"api-tracker3\" { dh() }",
        "let t = TrackerModel::parse(\"mirror-tracker\");",
        "use crate::trackers::ApiTracker3;",
    ];
    for code in planted {
        assert!(names_a_tracker_model(code, &ids).is_some(), "{code}");
    }
    for clean in [
        "let t = TrackerModel::default(); t.plugin().misalignments()",
        "fn f() {}\n#[cfg(test)]\nmod tests { const M: &str = \"mirror-tracker\"; }",
    ] {
        assert_eq!(names_a_tracker_model(clean, &ids), None, "{clean}");
    }
}

/// The files below `src/<dir>` whose code names one of `layers`.
fn files_naming(dir: &str, layers: &[&str]) -> Vec<String> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let files = rust_files(&src.join(dir));
    assert!(
        files.len() > 10,
        "found only {} files in {dir}",
        files.len()
    );
    files
        .iter()
        .filter_map(|p| {
            names_one_of(&code(p), layers)
                .map(|what| format!("{} names {what}", p.strip_prefix(&src).unwrap().display()))
        })
        .collect()
}

/// ARCHITECTURE.md: stages are adapters between tables and the domain; the
/// runner calls them, never the other way round (`StageInputs`, the stage
/// interface, lives in `stages/mod.rs`). Test modules included.
#[test]
fn stages_never_import_pipeline_or_cli() {
    let offending = files_naming("stages", &["pipeline", "cli"]);
    assert!(
        offending.is_empty(),
        "a stage must not depend on the runner or the command line:\n  {}",
        offending.join("\n  ")
    );
}

/// ARCHITECTURE.md: the command line calls `pipeline`, never the other
/// way round. Test modules included.
#[test]
fn pipeline_never_imports_cli() {
    let offending = files_naming("pipeline", &["cli"]);
    assert!(
        offending.is_empty(),
        "the runner must not depend on the command line:\n  {}",
        offending.join("\n  ")
    );
}

#[test]
fn the_stage_and_cli_rules_see_planted_imports() {
    let stage = "use crate::table;\nfn f() { let p = crate::pipeline::load(path); }";
    assert!(names_one_of(stage, &["pipeline", "cli"]).is_some());
    assert!(names_one_of("use crate::{cli::Cli, table};", &["pipeline", "cli"]).is_some());
    assert!(names_one_of("use super::super::cli::dispatch;", &["cli"]).is_some());
    assert!(names_one_of("use crate::stages::StageInputs;", &["pipeline", "cli"]).is_none());
    assert!(names_one_of("use super::cache; use crate::client;", &["cli"]).is_none());
}

/// The layers of `src/pipeline/`, first to last: a module imports only
/// modules of earlier layers, so the runner's imports form no circle
/// (ARCHITECTURE.md, "The runner's layers"). `""` is `mod.rs`, the facade
/// the rest of the crate calls.
const PIPELINE_LAYERS: &[&[&str]] = &[
    &[
        "error",
        "names",
        "overrides",
        "pack",
        "panics",
        "status",
        "cluster::settings",
        "control",
    ],
    &["cache", "cluster::scheduler", "sweep"],
    &["raw", "cluster::slurm"],
    &["snapshot_spec", "experiment"],
    &["resolve", "run_report"],
    &["plan", "select"],
    &["explain", "gc", "graph", "published", "summary"],
    &["run"],
    &["report"],
    &["publish"],
    &["snapshot", "cluster", "diagnose"],
    &[""],
];

fn pipeline_layer(module: &str) -> Option<usize> {
    PIPELINE_LAYERS.iter().position(|l| l.contains(&module))
}

/// Splits `a, b::{c, d}, e` at its top-level commas.
fn top_level_items(group: &str) -> Vec<&str> {
    let (mut out, mut depth, mut from) = (Vec::new(), 0usize, 0);
    for (i, c) in group.char_indices() {
        match c {
            '{' => depth += 1,
            '}' if depth == 0 => {
                out.push(&group[from..i]);
                return out;
            }
            '}' => depth -= 1,
            ',' if depth == 0 => {
                out.push(&group[from..i]);
                from = i + 1;
            }
            _ => {}
        }
    }
    out.push(&group[from..]);
    out
}

/// The modules of `pipeline/` (`"resolve"`, `"cluster::slurm"`, `""` for
/// `mod.rs`'s own items) that the code of module `module` names through
/// `super::` or `crate::pipeline::`. Inline modules (`mod tests {` at the
/// start of a line up to the `}` that closes it at the start of a line, as
/// rustfmt lays them out) are read too: their `super::` is the file.
fn pipeline_imports(module: &str, code: &str, modules: &[String]) -> Vec<String> {
    let own: Vec<&str> = module.split("::").filter(|s| !s.is_empty()).collect();
    let mut out = Vec::new();
    let mut inline = false;
    for line in code.lines() {
        let t = line.trim_end();
        if !line.starts_with(' ') && t.ends_with('{') && t.split_whitespace().any(|w| w == "mod") {
            inline = true;
        } else if t == "}" {
            inline = false;
        }
        let here: Vec<&str> = own
            .iter()
            .copied()
            .chain(inline.then_some("tests"))
            .collect();
        let compact: String = line.chars().filter(|c| !c.is_whitespace()).collect();
        let mut at = 0;
        while at < compact.len() {
            let rest = &compact[at..];
            let (mut base, mut path): (Vec<&str>, &str) =
                if let Some(r) = rest.strip_prefix("crate::pipeline::") {
                    (Vec::new(), r)
                } else if let Some(r) = rest.strip_prefix("super::") {
                    (here[..here.len().saturating_sub(1)].to_vec(), r)
                } else {
                    at += rest.chars().next().map_or(1, char::len_utf8);
                    continue;
                };
            while let Some(r) = path.strip_prefix("super::") {
                base.pop();
                path = r;
            }
            at = compact.len() - path.len();
            let items = match path.strip_prefix('{') {
                Some(group) => top_level_items(group),
                None => vec![path],
            };
            for item in items {
                let mut target = base.clone();
                for seg in item.split("::") {
                    let name: String = seg
                        .chars()
                        .take_while(|c| c.is_alphanumeric() || *c == '_')
                        .collect();
                    let mut next = target.clone();
                    next.push(name.as_str());
                    if name.is_empty() || !modules.contains(&next.join("::")) {
                        break;
                    }
                    target.push(seg.get(..name.len()).unwrap_or_default());
                }
                let target = target.join("::");
                if target != module && !out.contains(&target) {
                    out.push(target);
                }
            }
        }
    }
    out
}

/// Each import of module `module` that does not run to an earlier layer.
fn layer_violations(module: &str, code: &str, modules: &[String]) -> Vec<String> {
    let Some(layer) = pipeline_layer(module) else {
        return vec![format!(
            "`{module}` is in no layer of PIPELINE_LAYERS: add it"
        )];
    };
    pipeline_imports(module, code, modules)
        .into_iter()
        .filter(|t| pipeline_layer(t).is_none_or(|l| l >= layer))
        .map(|t| format!("`{module}` imports `{t}`, which is not in an earlier layer"))
        .collect()
}

/// The modules of `src/pipeline/` and their files.
fn pipeline_modules() -> Vec<(String, PathBuf)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/pipeline");
    rust_files(&dir)
        .into_iter()
        .map(|p| {
            let rel = p.strip_prefix(&dir).unwrap().with_extension("");
            let mut segs: Vec<String> = rel
                .components()
                .map(|c| c.as_os_str().to_string_lossy().into_owned())
                .collect();
            if segs.last().is_some_and(|s| s == "mod") {
                segs.pop();
            }
            (segs.join("::"), p)
        })
        .collect()
}

#[test]
fn pipeline_imports_run_only_to_earlier_layers() {
    let files = pipeline_modules();
    assert!(
        files.len() > 20,
        "found only {} pipeline modules",
        files.len()
    );
    let modules: Vec<String> = files.iter().map(|(m, _)| m.clone()).collect();
    let offending: Vec<String> = files
        .iter()
        .flat_map(|(m, p)| layer_violations(m, &code(p), &modules))
        .collect();
    assert!(
        offending.is_empty(),
        "src/pipeline/ must import one way (tests/integration/layering.rs, PIPELINE_LAYERS):\n  {}",
        offending.join("\n  ")
    );
}

#[test]
fn the_pipeline_layer_check_sees_planted_imports() {
    let modules: Vec<String> = [
        "", "cache", "raw", "resolve", "run", "names", "sweep", "cluster",
    ]
    .iter()
    .chain(&["cluster::settings", "cluster::slurm", "cluster::scheduler"])
    .map(|s| s.to_string())
    .collect();
    let check = |module: &str, code: &str| layer_violations(module, code, &modules);
    // Earlier layers, the file's own test module, a child's `super::super`.
    assert!(check("raw", "use super::names::valid_name;\nuse super::{sweep::RawSweep, cluster::settings::SlurmSettings};").is_empty());
    assert!(
        check(
            "raw",
            "fn f() {}\n#[cfg(test)]\nmod tests {\n    use super::*;\n}\n"
        )
        .is_empty()
    );
    assert!(
        check(
            "cluster::slurm",
            "mod tests {\n    use super::super::settings::SlurmSettings;\n}\n"
        )
        .is_empty()
    );
    // Later layers, however named.
    assert_eq!(check("raw", "use super::resolve::Pipeline;").len(), 1);
    assert_eq!(
        check("raw", "use super::{names, cache::{self, Store}, run};"),
        ["`raw` imports `run`, which is not in an earlier layer"]
    );
    assert_eq!(
        check("resolve", "fn f() { crate::pipeline::run::run(p, o) }").len(),
        1
    );
    assert_eq!(
        check("cache", "fn f() { super::load(p) }"),
        ["`cache` imports ``, which is not in an earlier layer"]
    );
    assert_eq!(check("cluster::slurm", "use super::Scheduler;").len(), 1);
    assert_eq!(
        check(
            "sweep",
            "mod tests {\n    use super::super::resolve::Sweep;\n}\n"
        )
        .len(),
        1
    );
    // A module in no layer.
    assert_eq!(check("brand_new", "").len(), 1);
}
