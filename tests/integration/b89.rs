//! The B89.4.19 tests (`pipelines/b89.toml`): which test sees which
//! misalignment, against FIELD.md's two-face facts, the simulated errors of
//! a tracker against the sum of its parts, and bad settings located.

use crate::util::{col, pipeline_path, run_pipeline, strs, table};
use std::process::Command;

#[test]
fn b89_pipeline_says_which_test_sees_which_misalignment() {
    let dir = tempfile::tempdir().unwrap();
    run_pipeline(&pipeline_path("b89.toml"), dir.path(), &[]);
    let vis = table(dir.path(), "b89", "physical", "visibility");
    let (names, seen) = (strs(&vis, "parameter"), strs(&vis, "seen_by"));
    let (two_face, length) = (col(&vis, "two_face_max_um"), col(&vis, "length_max_um"));
    let row = |id: &str| names.iter().position(|n| n == id).unwrap();
    // FIELD.md: offsets separate the faces by 2·offset; beam tilt and
    // vertical index by 2·c·R (R = √(6² + 1.5²) m at the farthest test);
    // R0 and even encoder harmonics not at all.
    for id in ["beam_offset_el", "beam_offset_az", "transit_offset"] {
        assert!((two_face[row(id)] - 2.0).abs() < 1e-9, "{id}");
    }
    let far_m = (36.0f64 + 2.25).sqrt();
    for id in ["beam_tilt_el", "beam_tilt_az", "vertical_index"] {
        assert!((two_face[row(id)] - 2.0 * far_m).abs() < 1e-6, "{id}");
    }
    for id in ["range_offset", "az_h2_sin", "az_h2_cos"] {
        assert_eq!(two_face[row(id)], 0.0, "{id}");
    }
    assert_eq!(seen[row("range_offset")], "length only");
    // At the standard's four azimuths the cos 2az harmonic turns every bar
    // without changing its length: no test sees it.
    assert_eq!(seen[row("az_h2_cos")], "neither");
    assert!(length[row("range_offset")] > 1.0);

    // Raising and lowering the bars shows what the symmetric ones hide.
    let raised = table(dir.path(), "b89", "raised", "visibility");
    let length_raised = col(&raised, "length_max_um");
    for id in ["beam_tilt_el", "vertical_index", "el_ecc_cos"] {
        assert_eq!(length[row(id)], 0.0, "{id}");
        assert!(length_raised[row(id)] > 0.5, "{id}");
    }

    // The DH view: the tracker's placement (δ1, ε1, the constant εz1, δy2),
    // εy2 (≡ −εz1) and the rotation about the beam (εz3) show in no test.
    let dh = table(dir.path(), "b89", "dh", "visibility");
    let (dh_names, dh_seen) = (strs(&dh, "parameter"), strs(&dh, "seen_by"));
    for (n, s) in dh_names.iter().zip(&dh_seen) {
        let placement = [
            "dx1", "dy1", "dz1", "ex1", "ey1", "ez1", "dy2", "ey2", "ez3",
        ];
        if placement.contains(&n.as_str()) {
            assert_eq!(s, "neither", "{n}");
        }
    }
    // The Table 2 tracker (every DH parameter 10 µm / 10 µrad) fails a
    // two-face test by far more than a compensated tracker.
    let (t2, comp) = (
        table(dir.path(), "b89", "dh", "tests"),
        table(dir.path(), "b89", "physical", "tests"),
    );
    let worst = |df| col(df, "err_um").iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(
        worst(&t2) > 2.0 * worst(&comp),
        "{} vs {}",
        worst(&t2),
        worst(&comp)
    );
    assert!(std::path::Path::new(&dir.path().join("b89/physical/b89-sensitivity.svg")).exists());

    // The mirror tracker: the same plane reflects in both faces, so its
    // incoming beam's offset and tilt and the mirror's tilt separate no
    // faces; the mirror's offset, reversed with its normal, by 4 µm/µm.
    let m = table(dir.path(), "b89", "mirror", "visibility");
    let (m_names, m_two_face) = (strs(&m, "parameter"), col(&m, "two_face_max_um"));
    let m_row = |id: &str| m_names.iter().position(|n| n == id).unwrap();
    for id in [
        "beam_offset_x",
        "beam_offset_y",
        "beam_tilt_x",
        "beam_tilt_y",
        "mirror_tilt",
    ] {
        assert_eq!(m_two_face[m_row(id)], 0.0, "{id}");
        assert!(col(&m, "length_max_um")[m_row(id)] > 0.5, "{id}");
    }
    assert!((m_two_face[m_row("mirror_offset")] - 4.0).abs() < 1e-6);
}

/// Runs `ltcal run` on a pipeline of `text`; its exit code and stderr, and
/// that nothing was written.
fn run_bad(text: &str) -> (Option<i32>, String) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("bad.toml");
    std::fs::write(&file, text).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .args(["run", file.to_str().unwrap(), "--results"])
        .arg(dir.path().join("results"))
        .output()
        .unwrap();
    assert!(!dir.path().join("results").exists(), "results were written");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn b89_misalignment_of_the_other_model_is_located() {
    let (code, err) = run_bad(
        "[stages.t]\nkind = \"b89_tests\"\nmodel = \"mirror-tracker\"\nmisalignments = { beam_offset_el = 5 }\n",
    );
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("bad.toml:4:"), "{err}");
    assert!(
        err.contains("`beam_offset_el` is not a misalignment of the mirror-tracker model"),
        "{err}"
    );
}

#[test]
fn b89_unknown_misalignment_is_located() {
    let (code, err) =
        run_bad("[stages.t]\nkind = \"b89_tests\"\nmisalignments = { beam_offset = 5 }\n");
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("bad.toml:3:"), "{err}");
    assert!(err.contains("`beam_offset` is not a misalignment"), "{err}");
}

#[test]
fn b89_repeated_position_is_located() {
    let (code, err) =
        run_bad("[stages.t]\nkind = \"b89_tests\"\ntwo_face_distances_m = [1, 3, 1]\n");
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("bad.toml:3:"), "{err}");
    assert!(
        err.contains("`two_face_distances_m` holds 1 twice"),
        "{err}"
    );
}
