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
                if ABOVE.contains(&first) {
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
