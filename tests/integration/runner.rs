//! The runner and its cache, asserted from the run report.

use crate::util::*;
use std::collections::BTreeSet;

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

#[test]
fn comments_and_whitespace_do_not_change_any_key() {
    let dir = tempfile::tempdir().unwrap();
    let file = pipeline_path("synthetic-validation.toml");
    run_pipeline(&file, dir.path(), &[]);
    let text = std::fs::read_to_string(&file).unwrap();
    let edited = dir.path().join("synthetic-validation.toml");
    let text = text
        .replace("\n[stages.", "\n# a comment\n\n[stages.")
        .replace(" = ", "   =   ");
    std::fs::write(&edited, text).unwrap();
    let r = run_pipeline(&edited, dir.path(), &[]);
    assert!(
        r.with_status("ran").is_empty(),
        "{:?}",
        r.with_status("ran")
    );
}
