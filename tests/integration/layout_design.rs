//! Layout design (`pipelines/layout-design.toml`): the identifiability of
//! the error parameters for the paper's corner layout and alternatives,
//! with free station poses.

use crate::util::{cell, col, pipeline_path, run_pipeline, strs, table};
use insta::assert_snapshot;
use ltcal::calibrate::{Network, bundle};
use ltcal::campaign::Aim;
use ltcal::effects::Effects;
use ltcal::error_model::{ErrorModel, ErrorParams};
use ltcal::identifiability::DEFAULT_REL_TOL;
use ltcal::kinematics::Face;
use ltcal::layout::{self, Kind, Spec};
use ltcal::noise::Noise;
use ltcal::simulate::{self, CampaignSpec};
use polars::prelude::DataFrame;

fn layouts() -> (tempfile::TempDir, DataFrame) {
    let dir = tempfile::tempdir().unwrap();
    run_pipeline(&pipeline_path("layout-design.toml"), dir.path(), &[]);
    let t = table(dir.path(), "layout-design", "design", "layouts");
    (dir, t)
}

#[test]
fn the_paper_layout_ranks_above_two_stations_and_no_high_reflectors() {
    let (_dir, t) = layouts();
    let s = |name| cell(&t, "name", name, "sigma_min");
    let o1 = |name| cell(&t, "name", name, "o1");
    // By σ_min (which also rewards the paper's larger number of readings)…
    assert!(
        s("paper") > 2.0 * s("2 stations"),
        "{} vs {}",
        s("paper"),
        s("2 stations")
    );
    assert!(
        s("paper") > 2.0 * s("no high reflectors"),
        "{} vs {}",
        s("paper"),
        s("no high reflectors")
    );
    // …and by O1, which divides the number of readings out.
    assert!(o1("paper") > 1.2 * o1("2 stations"));
    assert!(o1("paper") > 1.2 * o1("no high reflectors"));
    // A narrower pan costs geometry itself: the same readings, half the σ_min.
    assert_eq!(cell(&t, "name", "pan 45°", "n_readings"), 104.0);
    assert!(s("pan 45°") < 0.55 * s("paper"));
    // Two faces raise σ_min far more than the √2 of doubling the readings
    // (FIELD.md, Identifiability).
    assert!(
        s("both faces") > 5.0 * s("paper"),
        "{}",
        s("both faces") / s("paper")
    );
    // The gauge's six lengths (0.5 µm) carry weight of their own.
    assert!(
        o1("paper") > 1.3 * o1("no gauge"),
        "{} vs {}",
        o1("paper"),
        o1("no gauge")
    );
    // The model's own null space is the same for every layout: rank 7 of 18.
    assert!(col(&t, "rank").iter().all(|&r| r == 7.0));
    for u in strs(&t, "undetermined") {
        assert!(u.contains("εz3 has no effect on the data"), "{u}");
        assert!(
            u.contains("δz2 − δy3 is not determined by the data (only δz2 + δy3 is)"),
            "{u}"
        );
    }
}

#[test]
fn an_input_campaign_is_evaluated_beside_the_layouts() {
    let (dir, t) = layouts();
    let svg =
        std::fs::read_to_string(dir.path().join("layout-design/design/layout-design.svg")).unwrap();
    for needle in ["σ_min", "O1", "corner campaign", "no high reflectors"] {
        assert!(svg.contains(needle), "layout-design.svg lacks {needle}");
    }
    assert_eq!(strs(&t, "name")[0], "corner campaign");
    // Noise and Table 2 errors barely move the Jacobian of the same layout.
    for c in ["sigma_min", "o1", "condition_number"] {
        let (a, b) = (
            cell(&t, "name", "corner campaign", c),
            cell(&t, "name", "paper", c),
        );
        assert!((a / b - 1.0).abs() < 1e-3, "{c}: {a} vs {b}");
    }
}

/// The paper's corner, noise-free, as `layout_design` simulates it.
fn corner_network(repeat: usize, gauge: bool) -> Network {
    let layout = layout::build(&Spec::new(Kind::Corner));
    let sim = simulate::simulate_campaign(&CampaignSpec {
        name: "corner".into(),
        layout: &layout,
        errors: None,
        faces: &[Face::Front],
        aim: Aim::StationsCentroid,
        max_angle_deg: 30.0,
        noise: Noise::default(),
        effects: &Effects::default(),
        gauge_u_mm: 0.0005,
        reference_u_mm: 0.002,
        level_urad: 1000.0,
        interval_s: 20.0,
        record_time: false,
        record_temperature: false,
        seed: 7,
    })
    .unwrap();
    let mut c = sim.campaign;
    c.meta.tracker.sigma_angle_urad = Some(1.0);
    c.meta.tracker.sigma_range_um = Some(2.0);
    c.meta.tracker.sigma_range_ppm = Some(0.0);
    if !gauge {
        c.gauge.clear();
    }
    let once = c.readings.clone();
    for _ in 1..repeat {
        c.readings.extend(once.iter().cloned());
    }
    Network::from_campaign(&c).unwrap()
}

#[test]
fn singular_values_grow_with_the_square_root_of_the_readings_and_o1_does_not() {
    let start = ErrorParams::zero(&ErrorModel::constant());
    let free = vec![true; start.coefs().len()];
    let analyse = |repeat, gauge| {
        let net = corner_network(repeat, gauge);
        let m = 3 * net.obs.len();
        let (a, _) = bundle::analyse(&net, &start, &free, DEFAULT_REL_TOL).unwrap();
        (a.singular_values.clone(), a.rank, a.observability(m).o1)
    };
    // Readings only: every reading four times, every σ exactly twice.
    let (s1, rank, o1) = analyse(1, false);
    let (s4, _, o4) = analyse(4, false);
    for k in 0..rank {
        let r = s4[k] / s1[k];
        assert!((r - 2.0).abs() < 1e-9, "σ{}: ratio {r}", k + 1);
    }
    assert!((o4 / o1 - 1.0).abs() < 1e-9, "{o1} vs {o4}");
    // The gauge's six lengths (0.5 µm) do not repeat: they add to every
    // σ, more than the 105 readings' weight alone would, so the ratio
    // falls short of 2.
    let (g1, _, go1) = analyse(1, true);
    let (g4, _, _) = analyse(4, true);
    for k in 0..rank {
        let r = g4[k] / g1[k];
        assert!(r > 1.8 && r < 2.0, "σ{}: ratio {r}", k + 1);
    }
    assert!(go1 > 1.5 * o1, "{go1} vs {o1}");
}

#[test]
fn snapshot_of_the_layout_comparison() {
    let (dir, t) = layouts();
    let sv = table(dir.path(), "layout-design", "design", "singular_values");
    let text = format!(
        "Numbers rounded to 4 decimals.\n\n# design.layouts\n{}\n# design.singular_values\n{}",
        ltcal::table::to_text(&t, 4),
        ltcal::table::to_text(&sv, 4)
    );
    assert_snapshot!(text);
}
