//! Section 10 (`pipelines/incidence.toml`): Table 9 as a data file, its two
//! fits, and the fitted vertex model as an effect the campaign simulator
//! takes.

use crate::util::{cell, col, pipeline_path, root, run_pipeline, strs, table};
use insta::assert_snapshot;
use ltcal::effects::{self, Incidence, IncidenceAngles, TABLE9_UM};
use std::path::Path;

/// The cells of a CSV or of the paper's tab-separated table, as text.
fn csv_rows(text: &str) -> Vec<Vec<String>> {
    text.lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(|l| l.split(',').map(|c| c.trim().to_string()).collect())
        .collect()
}

/// Table 9 as paper.md prints it (`docs/paper-table9.md`, its excerpt): the header row of α_h and nine rows
/// `α_v, nine readings`, each led by a tab.
fn paper_table9() -> Vec<Vec<String>> {
    let paper = std::fs::read_to_string(root().join("docs/paper-table9.md")).unwrap();
    let lines: Vec<&str> = paper.lines().collect();
    let caption = lines
        .iter()
        .position(|l| l.starts_with("Table 9."))
        .expect("Table 9's caption in paper.md");
    let header = (0..caption)
        .rev()
        .find(|&i| lines[i].starts_with("θ (deg)"))
        .expect("Table 9's header row");
    let cells = |l: &str| -> Vec<String> {
        l.split('\t')
            .map(str::trim)
            .filter(|c| !c.is_empty() && *c != "θ (deg)")
            .map(str::to_string)
            .collect()
    };
    lines[header..header + 10]
        .iter()
        .map(|l| cells(l))
        .collect()
}

#[test]
fn table9_file_reproduces_the_paper_exactly() {
    let file = csv_rows(&std::fs::read_to_string(pipeline_path("data/table9.csv")).unwrap());
    let paper = paper_table9();
    assert_eq!(file.len(), 10);
    assert_eq!(file[0][0], "alpha_v_deg");
    // Cell by cell, as written: the header's α_h, then α_v and the readings.
    assert_eq!(file[0][1..], paper[0][..]);
    for (f, p) in file[1..].iter().zip(&paper[1..]) {
        assert_eq!(f, p);
    }
    // And the same numbers as the table the simulator interpolates.
    let angles = effects::table9_angles_deg();
    for (i, row) in file[1..].iter().enumerate() {
        assert_eq!(row[0].parse::<f64>().unwrap(), angles[i]);
        assert_eq!(file[0][i + 1].parse::<f64>().unwrap(), angles[i]);
        for j in 0..9 {
            assert_eq!(
                row[j + 1].parse::<f64>().unwrap(),
                TABLE9_UM[i][j],
                "[{i}][{j}]"
            );
        }
    }
}

/// effects.md's angles of a Table 9 cell, computed by `incidence_angles`
/// itself: the SMR axis n = x̂ (so h = ẑ × n = ŷ, v = n × h = ẑ) and the beam
/// r ∝ n + tan α_h·h + tan α_v·v.
fn angles_of(alpha_v_deg: f64, alpha_h_deg: f64) -> IncidenceAngles {
    let n = nalgebra::Vector3::x();
    let h = nalgebra::Vector3::z().cross(&n).normalize();
    let v = n.cross(&h);
    let r =
        (n + alpha_h_deg.to_radians().tan() * h + alpha_v_deg.to_radians().tan() * v).normalize();
    let a = effects::incidence_angles(&n, &r);
    assert!((a.alpha_h.to_degrees() - alpha_h_deg).abs() < 1e-9);
    assert!((a.alpha_v.to_degrees() - alpha_v_deg).abs() < 1e-9);
    a
}

#[test]
fn both_fits_report_their_residuals_and_the_vertex_parameters_reproduce_the_data() {
    let dir = tempfile::tempdir().unwrap();
    run_pipeline(&pipeline_path("incidence.toml"), dir.path(), &[]);
    let t = |name| table(dir.path(), "incidence", "incidence", name);
    let (fits, res, grid) = (t("fits"), t("residuals"), t("grid"));
    assert_eq!(strs(&res, "model"), ["vertex", "poly"]);
    assert_eq!(col(&res, "n"), [81.0, 81.0]);
    let rms = |m| cell(&res, "model", m, "rms_um");
    let max = |m| cell(&res, "model", m, "max_um");
    // The numbers the README reports.
    assert!((rms("vertex") - 1.6516).abs() < 1e-4, "{}", rms("vertex"));
    assert!((rms("poly") - 0.1819).abs() < 1e-4, "{}", rms("poly"));
    assert!(rms("poly") < rms("vertex") / 5.0);

    // effects.md's Δd with the fitted e's, evaluated independently of the
    // stage at every cell, gives back the data to within the reported RMS.
    let models = strs(&fits, "model");
    let params = strs(&fits, "parameter");
    let value = |p: &str| {
        let i = (0..models.len())
            .find(|&i| models[i] == "vertex" && params[i] == p)
            .unwrap();
        col(&fits, "value")[i]
    };
    let inc = Incidence {
        e_axial_um: value("e_axial_um"),
        e_h_um: value("e_h_um"),
        e_v_um: value("e_v_um"),
        max_angle_deg: 30.0,
    };
    let (av, ah) = (col(&grid, "alpha_v_deg"), col(&grid, "alpha_h_deg"));
    let (data, vertex) = (col(&grid, "data_um"), col(&grid, "vertex_um"));
    let mut ss = 0.0;
    for i in 0..grid.height() {
        let model = inc.delta_d_um(&angles_of(av[i], ah[i]));
        assert!((model - vertex[i]).abs() < 1e-9, "cell {i}");
        assert!((data[i] - model).abs() <= max("vertex") + 1e-12, "cell {i}");
        ss += (data[i] - model).powi(2);
    }
    let rms_check = (ss / grid.height() as f64).sqrt();
    assert!(
        (rms_check - rms("vertex")).abs() < 1e-9,
        "{rms_check} vs {}",
        rms("vertex")
    );
    // The grid is Table 9.
    for i in 0..81 {
        assert_eq!(data[i], TABLE9_UM[i / 9][i % 9]);
    }
}

/// A pipeline with a `simulate_campaign` stage named `simulated` and the
/// snippet pasted after it, as the snippet's comment says.
fn pipeline_with(snippet: &str) -> String {
    format!(
        "[stages.simulated]\nkind = \"simulate_campaign\"\nlayout = {{ kind = \"corner\" }}\n\n{snippet}"
    )
}

#[test]
fn the_fitted_effect_is_accepted_by_simulate_campaign() {
    let dir = tempfile::tempdir().unwrap();
    run_pipeline(&pipeline_path("incidence.toml"), dir.path(), &[]);
    let out = dir.path().join("incidence/incidence");
    let snippet = std::fs::read_to_string(out.join("incidence-effect.toml")).unwrap();
    let effect = table(dir.path(), "incidence", "incidence", "effect");
    assert_eq!(strs(&effect, "toml"), std::slice::from_ref(&snippet));
    assert!(snippet.contains("[stages.simulated.effects.incidence]"));
    let svg = std::fs::read_to_string(out.join("table9-fits.svg")).unwrap();
    for needle in [
        "α_h (deg)",
        "α_v (deg)",
        "reading (µm)",
        "residual (µm)",
        "polynomial of order 3",
    ] {
        assert!(svg.contains(needle), "table9-fits.svg lacks {needle}");
    }

    let file = dir.path().join("sim.toml");
    std::fs::write(&file, pipeline_with(&snippet)).unwrap();
    run_pipeline(&file, dir.path(), &[]);
    let truth = table(dir.path(), "sim", "simulated", "truth_effects");
    let fits = table(dir.path(), "incidence", "incidence", "fits");
    let got = |p: &str| cell(&truth, "parameter", p, "value");
    let want = |p: &str| cell(&fits, "parameter", p, "value");
    for p in ["e_axial_um", "e_h_um", "e_v_um"] {
        // The snippet carries 4 decimals.
        assert!(
            (got(p) - want(p)).abs() < 5e-5,
            "{p}: {} vs {}",
            got(p),
            want(p)
        );
    }
    assert_eq!(got("max_angle_deg"), 30.0);
}

#[test]
fn an_edited_table_file_is_not_answered_from_the_cache() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("t9.csv");
    std::fs::copy(pipeline_path("data/table9.csv"), &csv).unwrap();
    let set = format!("stages.incidence.path={}", path_text(&csv));
    let first = run_pipeline(&pipeline_path("incidence.toml"), dir.path(), &[&set]);
    assert_eq!(first.with_status("ran"), ["incidence"]);
    let again = run_pipeline(&pipeline_path("incidence.toml"), dir.path(), &[&set]);
    assert_eq!(again.with_status("cached"), ["incidence"]);
    let text = std::fs::read_to_string(&csv)
        .unwrap()
        .replace("\n-30,13.4,", "\n-30,14.4,");
    std::fs::write(&csv, text).unwrap();
    let edited = run_pipeline(&pipeline_path("incidence.toml"), dir.path(), &[&set]);
    assert_eq!(edited.with_status("ran"), ["incidence"]);
    let grid = table(dir.path(), "incidence", "incidence", "grid");
    assert_eq!(col(&grid, "data_um")[0], 14.4);
}

fn path_text(p: &Path) -> String {
    format!("\"{}\"", p.display().to_string().replace('\\', "\\\\"))
}

#[test]
fn snapshot_of_the_table9_fits() {
    let dir = tempfile::tempdir().unwrap();
    run_pipeline(&pipeline_path("incidence.toml"), dir.path(), &[]);
    let t = |name| table(dir.path(), "incidence", "incidence", name);
    let fits = t("fits");
    // Coefficients span 1e-5 … 10: four significant digits each.
    let (m, p, u) = (
        strs(&fits, "model"),
        strs(&fits, "parameter"),
        strs(&fits, "unit"),
    );
    let (v, s) = (col(&fits, "value"), col(&fits, "std"));
    let mut text = String::from(
        "Values and standard errors to 4 significant digits; residuals to 4 decimals.\n\n# incidence.fits\n",
    );
    for i in 0..fits.height() {
        text.push_str(&format!(
            "{:<7}{:<18}{:>12.3e} ± {:<10.3e}{}\n",
            m[i], p[i], v[i], s[i], u[i]
        ));
    }
    text.push_str(&format!(
        "\n# incidence.residuals\n{}",
        ltcal::table::to_text(&t("residuals"), 4)
    ));
    assert_snapshot!(text);
}
