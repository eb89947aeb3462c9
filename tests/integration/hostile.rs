//! Hostile but spec-valid campaigns (issue 12): extreme finite values, and
//! readings that break the numerics. Each test is named after its finding.

use crate::cli::{assert_code, ltcal, stderr};
use std::path::{Path, PathBuf};

/// A copy of an example campaign in `dir`, with `edit` applied to the text
/// of one of its files.
pub fn mutated_example(
    dir: &Path,
    example: &str,
    file: &str,
    edit: impl FnOnce(&str) -> String,
) -> PathBuf {
    let src = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("examples/campaigns")
        .join(example);
    let dst = dir.join(example);
    std::fs::create_dir_all(&dst).unwrap();
    for e in std::fs::read_dir(&src).unwrap().flatten() {
        std::fs::copy(e.path(), dst.join(e.file_name())).unwrap();
    }
    let text = std::fs::read_to_string(dst.join(file)).unwrap();
    std::fs::write(dst.join(file), edit(&text)).unwrap();
    dst
}

/// The text of one of example-00's files.
fn example_text(file: &str) -> String {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("examples/campaigns/example-00-none");
    std::fs::read_to_string(dir.join(file)).unwrap()
}

/// Replaces the last cell of data line `line` (1-based, the header is 1).
pub fn set_last_cell(text: &str, line: usize, value: &str) -> String {
    replace_cell(text, line, usize::MAX, value)
}

/// Replaces cell `col` (0-based; `usize::MAX`: the last) of line `line`.
pub fn replace_cell(text: &str, line: usize, col: usize, value: &str) -> String {
    text.lines()
        .enumerate()
        .map(|(i, l)| {
            if i + 1 != line {
                return l.to_string();
            }
            let mut cells: Vec<&str> = l.split(',').collect();
            let k = col.min(cells.len() - 1);
            cells[k] = value;
            cells.join(",")
        })
        .collect::<Vec<_>>()
        .join("\n")
        + "\n"
}

/// Regression: a `temperature_c` or gauge `distance_mm` of ±1e308 made the
/// F statistic NaN and statrs' `FisherSnedecor::sf` panicked (exit 101).
/// The temperature is diagnosed; the gauge length, beyond what a
/// calibration can use (fuzzing found 1e23 leaves the adjustment singular),
/// is refused at its place.
#[test]
fn f_test_panic_on_extreme_temperature_or_gauge_distance() {
    let tmp = tempfile::tempdir().unwrap();
    let cases = [
        (
            "readings.csv",
            set_last_cell(
                &set_last_cell(&example_text("readings.csv"), 2, "1e308"),
                3,
                "-1e308",
            ),
        ),
        (
            "gauge.csv",
            replace_cell(&example_text("gauge.csv"), 2, 2, "1e308"),
        ),
    ];
    for (i, ((file, text), code)) in cases.into_iter().zip([0, 2]).enumerate() {
        let case = tmp.path().join(i.to_string());
        let dir = mutated_example(&case, "example-00-none", file, |_| text);
        let o = ltcal(&case, &["diagnose", dir.to_str().unwrap(), "--out", "out"]);
        assert_code(&o, code);
        if code == 2 {
            assert!(stderr(&o).contains("gauge.csv:2:"), "{}", stderr(&o));
        }
    }
}

/// Regression: one `time_s = 1.7976931348623157e308` made the figure of
/// residuals against time spin forever in plotters' tick computation. The
/// figure is left out with a note in the report; the test simply finishes.
#[test]
fn endless_loop_in_plots_on_a_time_of_f64_max() {
    let tmp = tempfile::tempdir().unwrap();
    // time_s is the second-to-last column of example-00's readings.
    let dir = mutated_example(tmp.path(), "example-00-none", "readings.csv", |t| {
        replace_cell(t, 2, 5, "1.7976931348623157e308")
    });
    let o = ltcal(
        tmp.path(),
        &["diagnose", dir.to_str().unwrap(), "--out", "out"],
    );
    assert_code(&o, 0);
    let out = tmp.path().join("out");
    assert!(!out.join("residuals-time_s.svg").exists());
    assert!(out.join("residuals-station.svg").exists(), "{}", stderr(&o));
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(
        report.contains("No figure of the residuals by time_s"),
        "{report}"
    );
}

/// `ltcal diagnose` on a campaign whose `file` is edited: exit 2, and the
/// error holds every one of `expected`.
fn diagnose_refuses(file: &str, edit: impl FnOnce(&str) -> String, expected: &[&str]) {
    let tmp = tempfile::tempdir().unwrap();
    let dir = mutated_example(tmp.path(), "example-00-none", file, edit);
    let o = ltcal(
        tmp.path(),
        &["diagnose", dir.to_str().unwrap(), "--out", "out"],
    );
    assert_code(&o, 2);
    let err = stderr(&o);
    for e in expected {
        assert!(err.contains(e), "no `{e}` in:\n{err}");
    }
    assert!(!tmp.path().join("out").exists());
}

/// Regression: one reading at `el_deg = 90` failed with "singular normal
/// matrix", the reading not named. The zenith is valid per the format (the
/// campaign still reads) but unusable for calibration, and is named so.
#[test]
fn a_reading_at_the_zenith_is_named_at_its_file_line_col() {
    // el_deg is the fourth column; data line 4 is the file's line 4.
    diagnose_refuses(
        "readings.csv",
        |t| replace_cell(t, 4, 3, "90"),
        &["readings.csv:4:", "zenith", "unusable for calibration"],
    );
    let tmp = tempfile::tempdir().unwrap();
    let dir = mutated_example(tmp.path(), "example-00-none", "readings.csv", |t| {
        replace_cell(t, 4, 3, "-90")
    });
    let c = ltcal::campaign::read(&dir).expect("valid per the format");
    let e = ltcal::calibrate::Network::from_campaign(&c).unwrap_err();
    assert!(e.to_string().contains("row 2, column `el_deg`"), "{e}");
}

/// Regression: `d_mm = 1e15` failed with "non-finite Jacobian".
#[test]
fn a_non_finite_jacobian_from_a_huge_distance_names_the_reading() {
    diagnose_refuses(
        "readings.csv",
        |t| replace_cell(t, 7, 4, "1e15"),
        &["readings.csv:7:", "d_mm", "unusable for calibration"],
    );
}

/// Regression: `sigma_angle_urad = 1e-300` failed with "non-finite
/// Jacobian"; the key is named at its place in campaign.toml.
#[test]
fn a_non_finite_jacobian_from_a_tiny_sigma_names_the_key() {
    diagnose_refuses(
        "campaign.toml",
        |t| t.replace("sigma_angle_urad = 0.635", "sigma_angle_urad = 1e-300"),
        &["campaign.toml:7:", "unusable for calibration"],
    );
}

/// Regression: `ltcal diagnose` wrote its `--out` files one by one, so a
/// full disk or a kill left a partial folder that looked finished. Now the
/// folder is published by one rename: a failed diagnosis leaves none (see
/// also `diagnose_refuses`), a new one replaces an earlier one whole, no
/// temporary is left beside it, and a folder of other files is refused.
#[test]
fn diagnose_writes_its_out_folder_atomically() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = mutated_example(tmp.path(), "example-00-none", "readings.csv", |t| {
        replace_cell(t, 3, 3, "90")
    });
    let fails = ltcal(
        tmp.path(),
        &["diagnose", dir.to_str().unwrap(), "--out", "out"],
    );
    assert_code(&fails, 2);
    assert!(!tmp.path().join("out").exists());

    let good = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("examples/campaigns/example-00-none");
    let out = tmp.path().join("out");
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("diagnosis.csv"), "stale").unwrap();
    std::fs::write(out.join("residuals-stale.svg"), "stale").unwrap();
    let o = ltcal(
        tmp.path(),
        &["diagnose", good.to_str().unwrap(), "--out", "out"],
    );
    assert_code(&o, 0);
    assert!(!out.join("residuals-stale.svg").exists());
    assert!(out.join("report.md").is_file());
    let beside: Vec<_> = std::fs::read_dir(tmp.path())
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(beside.is_empty(), "{beside:?}");

    let mine = tmp.path().join("mine");
    std::fs::create_dir(&mine).unwrap();
    std::fs::write(mine.join("notes.txt"), "keep").unwrap();
    let o = ltcal(
        tmp.path(),
        &["diagnose", good.to_str().unwrap(), "--out", "mine"],
    );
    assert_code(&o, 2);
    assert!(stderr(&o).contains("not a diagnosis"), "{}", stderr(&o));
    assert!(mine.join("notes.txt").is_file());
}

/// Regression (issue 12): 200 000 readings took minutes and gigabytes with
/// no word of a limit. A campaign file beyond `MAX_ROWS` data rows is
/// refused at its first excess row, before the rest is held as cells.
#[test]
fn a_campaign_file_beyond_the_row_limit_is_refused_at_its_first_excess_row() {
    let tmp = tempfile::tempdir().unwrap();
    let text = example_text("readings.csv");
    let row = text.lines().nth(1).unwrap().to_string() + "\n";
    let mut big = String::with_capacity(row.len() * (ltcal::campaign::MAX_ROWS + 2));
    big.push_str(text.lines().next().unwrap());
    big.push('\n');
    for _ in 0..ltcal::campaign::MAX_ROWS + 1 {
        big.push_str(&row);
    }
    let dir = mutated_example(tmp.path(), "example-00-none", "readings.csv", |_| big);
    let e = ltcal::campaign::read(&dir).unwrap_err().to_string();
    let line = ltcal::campaign::MAX_ROWS + 2;
    assert!(e.contains(&format!("readings.csv:{line}:1")), "{e}");
    assert!(e.contains("at most 1000000 rows"), "{e}");
}
