//! `ltcal snapshot`: the committed recording of the synthetic validation
//! holds; recording and checking with per-column tolerances; a difference is
//! shown row by row; mistakes in `[snapshot]` point into the file.

use crate::cli::*;
use crate::util::{pipeline_path, root, table};
use std::path::Path;

/// A one-mesh pipeline named `snap` with a `[snapshot]` of its points.
const SMALL: &str = "[pipeline]\nname = \"snap\"\n\n\
    [stages.a]\nkind = \"mesh\"\nshape = \"plane\"\n\n\
    [snapshot]\ntables = [\"a\"]\ndigits = 3\ntolerance = { x_mm = 0.01 }\n";

fn small(dir: &Path, text: &str) {
    std::fs::write(dir.join("p.toml"), text).unwrap();
}

#[test]
fn the_synthetic_validation_matches_its_recorded_snapshot() {
    let dir = tempfile::tempdir().unwrap();
    let f = pipeline_path("synthetic-validation.toml");
    let r = dir.path().join("results");
    let out = ltcal(
        &root(),
        &[
            "snapshot",
            "--check",
            f.to_str().unwrap(),
            "--results",
            r.to_str().unwrap(),
        ],
    );
    assert_code(&out, 0);
    let s = stdout(&out);
    assert_eq!(s.matches("  same     ").count(), 7, "{s}");
    assert!(
        s.contains(
            "snapshot check: 7 tables within tolerance of tests/snapshots/synthetic-validation"
        ),
        "{s}"
    );
}

#[test]
fn a_difference_beyond_tolerance_is_shown_row_by_row() {
    let dir = tempfile::tempdir().unwrap();
    let f = pipeline_path("synthetic-validation.toml");
    let r = dir.path().join("results");
    let out = ltcal(
        &root(),
        &[
            "snapshot",
            "--check",
            f.to_str().unwrap(),
            "--results",
            r.to_str().unwrap(),
            "--set",
            "stages.measure_sphere_noisy.seed=2",
            "--name",
            "seed2",
        ],
    );
    assert_code(&out, 1);
    let s = stdout(&out);
    // Only the noisy sphere changes; its three statistics in each column.
    assert_eq!(s.matches("  same     ").count(), 6, "{s}");
    assert!(
        s.contains(
            "  DIFFERS  evaluate_sphere_noisy.summary  (9 values in 3 rows beyond tolerance"
        ),
        "{s}"
    );
    // The run with --set is an experiment, published in its own folder.
    let now = table(
        &r,
        "synthetic-validation/runs/seed2",
        "evaluate_sphere_noisy",
        "summary",
    );
    let rms_after = crate::util::cell(&now, "statistic", "rms", "after_um");
    let recorded = std::fs::read_to_string(
        root().join("tests/snapshots/synthetic-validation/evaluate_sphere_noisy.summary.txt"),
    )
    .unwrap();
    assert!(
        recorded.contains("rms  243.836777  12.010510"),
        "{recorded}"
    );
    let line = s
        .lines()
        .skip_while(|l| !l.contains("row 2 (statistic = rms):"))
        .find(|l| l.trim_start().starts_with("after_um"))
        .unwrap_or_else(|| panic!("no rms after_um line in:\n{s}"));
    assert!(
        line.contains(&format!("recorded  12.010510  now  {rms_after:.6}")),
        "{line}"
    );
    let delta = format!("{:+.6}", rms_after - 12.010510);
    assert!(
        line.contains(&format!("off by {delta} (tolerance 0.0001)")),
        "{line}"
    );
    assert!(
        s.contains("if the change is intended, record it with `ltcal snapshot"),
        "{s}"
    );
}

#[test]
fn recording_then_checking_with_a_column_tolerance() {
    let dir = tempfile::tempdir().unwrap();
    small(dir.path(), SMALL);
    let out = ltcal(dir.path(), &["snapshot", "p.toml"]);
    assert_code(&out, 0);
    assert_eq!(stdout(&out), "recorded tests/snapshots/snap/a.points.txt\n");
    let text =
        std::fs::read_to_string(dir.path().join("tests/snapshots/snap/a.points.txt")).unwrap();
    let points = table(&dir.path().join("results"), "snap", "a", "points");
    assert_eq!(text, ltcal::table::to_text(&points, 3));
    let header: Vec<&str> = text.lines().next().unwrap().split_whitespace().collect();
    assert_eq!(header, ["target", "x_mm", "y_mm", "z_mm"]);
    assert!(
        text.contains("\n  P001  5000.000  -10000.000  -1500.000\n"),
        "{text}"
    );
    assert_eq!(text.lines().count(), 211);

    assert_code(&ltcal(dir.path(), &["snapshot", "--check", "p.toml"]), 0);
    // Within the 0.01 mm of x_mm …
    let within = ltcal(
        dir.path(),
        &[
            "snapshot",
            "--check",
            "p.toml",
            "--set",
            "stages.a.x_mm=5000.008",
        ],
    );
    assert_code(&within, 0);
    // … and beyond it: every row, located by its target.
    let beyond = ltcal(
        dir.path(),
        &[
            "snapshot",
            "--check",
            "p.toml",
            "--set",
            "stages.a.x_mm=5000.02",
        ],
    );
    assert_code(&beyond, 1);
    let s = stdout(&beyond);
    assert!(
        s.contains("DIFFERS  a.points  (210 values in 210 rows beyond tolerance"),
        "{s}"
    );
    assert!(s.contains("row 1 (target = P001):\n             x_mm  recorded 5000.000  now 5000.020  off by +0.020 (tolerance 0.01)"), "{s}");
    assert!(s.contains("… and 190 more rows"), "{s}");
    // Another column has no tolerance of its own: default 0, exact as recorded.
    let shift_y = ["stages.a.y.from=-9999", "stages.a.y.to=9881"];
    let args = |file: &'static str| {
        vec![
            "snapshot", "--check", file, "--set", shift_y[0], "--set", shift_y[1],
        ]
    };
    let y = ltcal(dir.path(), &args("p.toml"));
    assert_code(&y, 1);
    assert!(
        stdout(&y)
            .contains("y_mm  recorded -10000.000  now -9999.000  off by +1.000 (tolerance 0)"),
        "{}",
        stdout(&y)
    );
    // With a default tolerance that covers it, it passes.
    small(
        dir.path(),
        &SMALL.replace("digits = 3", "digits = 3\ndefault_tolerance = 2.0"),
    );
    assert_code(&ltcal(dir.path(), &args("p.toml")), 0);
}

#[test]
fn a_table_not_yet_recorded_fails_the_check_and_dir_chooses_the_folder() {
    let dir = tempfile::tempdir().unwrap();
    small(dir.path(), SMALL);
    let out = ltcal(
        dir.path(),
        &["snapshot", "--check", "p.toml", "--dir", "snaps"],
    );
    assert_code(&out, 1);
    assert!(
        stdout(&out)
            .contains("MISSING  a.points  (not recorded: snaps/snap/a.points.txt does not exist)"),
        "{}",
        stdout(&out)
    );
    assert_code(
        &ltcal(dir.path(), &["snapshot", "p.toml", "--dir", "snaps"]),
        0,
    );
    assert!(dir.path().join("snaps/snap/a.points.txt").exists());
    assert!(!dir.path().join("tests").exists());
    assert_code(
        &ltcal(
            dir.path(),
            &["snapshot", "--check", "p.toml", "--dir", "snaps"],
        ),
        0,
    );
}

/// `ltcal snapshot` on a broken `[snapshot]`: exit 2 and the place.
fn located(text: &str, line_col: &str, message: &str) {
    let dir = tempfile::tempdir().unwrap();
    small(dir.path(), text);
    let out = ltcal(dir.path(), &["snapshot", "p.toml"]);
    assert_code(&out, 2);
    let err = stderr(&out);
    assert!(
        err.contains(&format!("p.toml:{line_col}")),
        "no {line_col} in:\n{err}"
    );
    assert!(err.contains(message), "no `{message}` in:\n{err}");
    assert!(err.contains('^'), "{err}");
}

#[test]
fn snapshot_mistakes_point_at_the_file() {
    located(
        &SMALL.replace("[\"a\"]", "[\"a\", \"b.summary\"]"),
        "9:16",
        "[snapshot]: `b.summary` names no stage `b`; the stages are: a",
    );
    located(
        &SMALL.replace("[\"a\"]", "[\"a.pts\"]"),
        "9:11",
        "[snapshot]: stage `a` (mesh) has no table `pts`; its tables are: points",
    );
    located(
        &SMALL.replace("x_mm = 0.01", "x_mm = 0.01, xmm = 1"),
        "11:28",
        "[snapshot]: no snapshot table has a column `xmm`; their columns are: target, x_mm, y_mm, z_mm",
    );
    located(
        &SMALL.replace("digits = 3", "digts = 3"),
        "10:1",
        "[snapshot]: unknown field `digts`, expected one of `tables`, `digits`, `tolerance`, `default_tolerance`",
    );
    located(
        &SMALL.replace("x_mm = 0.01", "x_mm = -1"),
        "11:22",
        "[snapshot]: the tolerance of `x_mm` must be a finite number ≥ 0",
    );
    let dir = tempfile::tempdir().unwrap();
    small(dir.path(), &SMALL[..SMALL.find("[snapshot]").unwrap()]);
    let out = ltcal(dir.path(), &["snapshot", "p.toml"]);
    assert_code(&out, 2);
    assert!(
        stderr(&out).contains("p.toml has no [snapshot] table"),
        "{}",
        stderr(&out)
    );
}
