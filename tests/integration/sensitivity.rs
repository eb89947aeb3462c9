//! Section 6 (`pipelines/sensitivity.toml`): each parameter's error over
//! the paper's sphere, classified against the paper, and the Figure 12
//! check of where the variable errors are largest and smallest.

use crate::util::{col, pipeline_path, run_pipeline, strs, table};
use insta::assert_snapshot;
use polars::prelude::DataFrame;

fn run() -> (tempfile::TempDir, DataFrame, DataFrame, DataFrame) {
    let dir = tempfile::tempdir().unwrap();
    run_pipeline(&pipeline_path("sensitivity.toml"), dir.path(), &[]);
    let t = |name| table(dir.path(), "sensitivity", "sensitivity", name);
    let (c, f, e) = (t("classification"), t("field"), t("extremes"));
    (dir, c, f, e)
}

fn bools(df: &DataFrame, name: &str) -> Vec<bool> {
    ltcal::table::TableRef::new("t", df).bool(name).unwrap()
}

#[test]
fn classification_matches_the_paper_except_ez1_which_is_explained() {
    let (_dir, c, _, _) = run();
    let (params, ours, paper) = (strs(&c, "parameter"), strs(&c, "ours"), strs(&c, "paper"));
    let (agrees, notes) = (bools(&c, "agrees"), strs(&c, "note"));
    assert_eq!(params.len(), 18);
    for i in 0..18 {
        if params[i] == "ez1" {
            assert!(!agrees[i]);
            assert_eq!(paper[i], "varies with θ, φ, d");
            assert_eq!(ours[i], "varies with φ, d");
            assert!(
                notes[i].contains("rotation about the vertical")
                    && notes[i].contains("cannot vary with the azimuth θ"),
                "{}",
                notes[i]
            );
        } else {
            assert!(
                agrees[i],
                "{}: ours {} paper {}",
                params[i], ours[i], paper[i]
            );
            assert_eq!(ours[i], paper[i], "{}", params[i]);
            assert_eq!(notes[i], "", "{}", params[i]);
        }
    }
    // The magnitudes behind the words: δ's move every point by exactly
    // 1 µm, rotations about the beam axis of joints 2 and 3 by d·1 µrad
    // (1 … 15 µm on the sphere), εz3 by nothing.
    let (min, max) = (col(&c, "min_um"), col(&c, "max_um"));
    for i in 0..18 {
        let p = params[i].as_str();
        if p.starts_with('d') {
            // The exact inverse stops at its rounding floor, 1e-9 mm.
            assert!(
                (min[i] - 1.0).abs() < 1e-5 && (max[i] - 1.0).abs() < 1e-5,
                "{p}: {} … {}",
                min[i],
                max[i]
            );
        }
        if ["ez2", "ex3", "ey3"].contains(&p) {
            assert!(
                (min[i] - 1.0).abs() < 1e-6 && (max[i] - 15.0).abs() < 1e-6,
                "{p}"
            );
        }
        if p == "ez3" {
            assert!(max[i] < 1e-5, "{p}: {}", max[i]);
        }
    }
}

#[test]
fn the_ez1_field_is_d_cos_phi_at_every_mesh_point() {
    let (_dir, _, f, _) = run();
    assert_eq!(f.height(), 18 * 480);
    let params = strs(&f, "parameter");
    let (el, d, err) = (col(&f, "el_deg"), col(&f, "d_mm"), col(&f, "err_um"));
    let mut n = 0;
    for i in (0..f.height()).filter(|&i| params[i] == "ez1") {
        // 1 µrad × d (mm) = 1e-3·d µm, times the horizontal part cos φ.
        let want = 1e-3 * d[i] * el[i].to_radians().cos();
        assert!(
            (err[i] - want).abs() < 1e-6,
            "row {i}: {} vs {want}",
            err[i]
        );
        n += 1;
    }
    assert_eq!(n, 480);
}

#[test]
fn figure12_extremes_sit_at_zero_or_extreme_phi_and_at_multiples_of_quarter_pi() {
    let (dir, _, _, e) = run();
    let params = strs(&e, "parameter");
    assert_eq!(params, ["ex1", "ey1", "ez1", "ex2", "ey2"]);
    assert!(bools(&e, "as_paper").iter().all(|&b| b));
    let text = strs(&e, "extremes");
    // The extremes in θ fall every π/2 — a subset of the paper's "every π/4".
    assert_eq!(
        text[0],
        "max 15.0000 µm at θ = −180°, 0° (any φ); min 0.0000 µm at θ = −90°, 90°, φ = 0°"
    );
    assert_eq!(
        text[2],
        "max 15.0000 µm at φ = 0° (any θ); min 3.3743 µm at φ = 77° (any θ)"
    );
    for (file, needles) in [
        (
            "figure11.svg",
            &["Figure 11", "error (µm)", "distance d (m)", "εz3 = 1 µrad"][..],
        ),
        (
            "figure12.svg",
            &["Figure 12", "θ (deg)", "φ (deg)", "error (µm)"][..],
        ),
    ] {
        let svg =
            std::fs::read_to_string(dir.path().join("sensitivity/sensitivity").join(file)).unwrap();
        for n in needles {
            assert!(svg.contains(n), "{file} lacks {n}");
        }
    }
}

#[test]
fn snapshot_of_the_section6_classification() {
    let (_dir, c, _, e) = run();
    let text = format!(
        "Numbers rounded to 6 decimals.\n\n# sensitivity.classification\n{}\n# sensitivity.extremes\n{}",
        ltcal::table::to_text(&c, 6),
        ltcal::table::to_text(&e, 6)
    );
    assert_snapshot!(text);
}
