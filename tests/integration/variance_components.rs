//! Issue 31: the `identify` stage's uncertainty is right by default — the
//! reading noise is the stage's, else the one its readings carry from
//! `measure`, else estimated from the residuals by variance components; the
//! textbook `s²·(JᵀJ)⁻¹` only on request (`std = "residual-scatter"`).

use crate::util::{col, run_pipeline, strs, table};
use ltcal::error_model::{ErrorModel, ErrorParams, ParamId};
use ltcal::identify::{self, KnownPoint, Settings};
use ltcal::table::TableRef;
use polars::prelude::DataFrame;

const PIPELINE: &str = r#"[pipeline]
name = "vc"

[stages.truth]
kind = "inject"
preset = "table2"

[stages.sphere]
kind = "mesh"
shape = "sphere"

[stages.noisy]
kind = "measure"
inputs = { points = "sphere", errors = "truth" }
noise = { sigma_angle_urad = 1.0, sigma_range_um = 2.0 }
seed = 3

[stages.exact]
kind = "measure"
inputs = { points = "sphere", errors = "truth" }

# The noise the readings carry.
[stages.carried]
kind = "identify"
inputs = { readings = "noisy" }
fixed = ["dz1", "dy2", "ez3"]

# The stage's own noise wins over the readings'.
[stages.stated]
kind = "identify"
inputs = { readings = "noisy" }
fixed = ["dz1", "dy2", "ez3"]
noise = { sigma_angle_urad = 0.5, sigma_range_um = 1.0 }

# Exact readings carry no noise; δx1 held at 0 leaves its 10 µm unexplained:
# the residuals are all there is to go by.
[stages.estimated]
kind = "identify"
inputs = { readings = "exact" }
fixed = ["dz1", "dy2", "ez3", "dx1"]

[stages.estimated_weighted]
kind = "identify"
inputs = { readings = "exact" }
fixed = ["dz1", "dy2", "ez3", "dx1"]
weighting = "noise"

[stages.scatter]
kind = "identify"
inputs = { readings = "exact" }
fixed = ["dz1", "dy2", "ez3", "dx1"]
std = "residual-scatter"

[stages.round_off]
kind = "identify"
inputs = { readings = "exact" }
fixed = ["dz1", "dy2", "ez3"]
"#;

struct Fit(DataFrame);

impl Fit {
    fn str(&self, c: &str) -> String {
        strs(&self.0, c)[0].clone()
    }
    fn f64(&self, c: &str) -> Option<f64> {
        TableRef::new("fit", &self.0).opt_f64(c).unwrap()[0]
    }
    fn i64(&self, c: &str) -> Option<i64> {
        TableRef::new("fit", &self.0).opt_i64(c).unwrap()[0]
    }
}

#[test]
fn identify_without_noise_estimates_it_by_variance_components() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("vc.toml");
    std::fs::write(&file, PIPELINE).unwrap();
    let results = dir.path().join("results");
    run_pipeline(&file, &results, &[]);
    let fit = |stage: &str| Fit(table(&results, "vc", stage, "fit"));

    // The noise travels with the readings from `measure`.
    let readings = table(&results, "vc", "noisy", "readings");
    assert!(col(&readings, "sigma_angle_urad").iter().all(|v| *v == 1.0));
    assert!(col(&readings, "sigma_range_um").iter().all(|v| *v == 2.0));
    assert!(col(&readings, "sigma_range_ppm").iter().all(|v| *v == 0.0));
    let f = fit("carried");
    assert_eq!(f.str("std_from"), "sandwich");
    assert_eq!(f.str("noise_from"), "readings");
    assert_eq!(f.f64("sigma_angle_urad"), Some(1.0));
    assert_eq!(f.f64("sigma_range_um"), Some(2.0));
    assert_eq!(f.f64("sigma_angle_urad_u"), None);
    assert_eq!(f.i64("vc_iterations"), None);
    assert_eq!(f.str("note"), "");

    let f = fit("stated");
    assert_eq!(f.str("noise_from"), "stage");
    assert_eq!(f.f64("sigma_angle_urad"), Some(0.5));
    assert_eq!(f.f64("sigma_range_um"), Some(1.0));

    // No noise anywhere: estimated, the same as the library's estimate on
    // the same readings, with its uncertainty.
    let exact = table(&results, "vc", "exact", "readings");
    assert!(col(&exact, "sigma_angle_urad").iter().all(|v| *v == 0.0));
    let obs: Vec<KnownPoint> = ltcal::schema::readings_from(&TableRef::new("r", &exact))
        .unwrap()
        .iter()
        .map(|r| KnownPoint {
            reading: r.reading,
            reference: r.reference,
        })
        .collect();
    let start = ErrorParams::zero(&ErrorModel::constant());
    let free: Vec<bool> = (0..18)
        .map(|i| !["dz1", "dy2", "ez3", "dx1"].contains(&ParamId::from_index(i).id()))
        .collect();
    let c = identify::variance_components(&obs, &start, &free, &Settings::default()).unwrap();
    assert!(c.converged, "{c:?}");
    for stage in ["estimated", "estimated_weighted"] {
        let f = fit(stage);
        assert_eq!(f.str("std_from"), "variance-components", "{stage}");
        assert_eq!(f.str("noise_from"), "residuals", "{stage}");
        assert_eq!(f.str("note"), "", "{stage}");
        assert_eq!(f.i64("vc_iterations"), Some(c.iterations as i64));
        let (sa, sr) = (
            f.f64("sigma_angle_urad").unwrap(),
            f.f64("sigma_range_um").unwrap(),
        );
        assert!(
            (sa / c.sigma_angle_urad - 1.0).abs() < 1e-9,
            "{sa} vs {c:?}"
        );
        assert!((sr / c.sigma_range_um - 1.0).abs() < 1e-9, "{sr} vs {c:?}");
        let (ua, ur) = (
            f.f64("sigma_angle_urad_u").unwrap(),
            f.f64("sigma_range_um_u").unwrap(),
        );
        assert!(
            ua > 0.0 && ua < 0.05 * sa && ur > 0.0 && ur < 0.05 * sr,
            "{ua} {ur}"
        );
        assert_eq!(f.f64("sigma_range_ppm"), Some(0.0));
        // The uncertainty is that of the noise found, not zero.
        let params = table(&results, "vc", stage, "params");
        let std = TableRef::new("params", &params).opt_f64("std").unwrap();
        assert!(std.iter().flatten().any(|s| *s > 0.01), "{stage}: {std:?}");
    }
    assert_eq!(fit("estimated").str("weighting"), "unweighted");
    assert_eq!(fit("estimated_weighted").str("weighting"), "noise");

    let f = fit("scatter");
    assert_eq!(f.str("std_from"), "residual-scatter");
    assert_eq!(f.str("note"), "");

    // Exact readings and the full model: the residuals are round-off, and
    // the fit says so rather than iterating on them.
    let f = fit("round_off");
    assert_eq!(f.str("std_from"), "variance-components");
    assert_eq!(f.i64("vc_iterations"), Some(1));
    assert!(f.f64("sigma_angle_urad").unwrap() < 1e-6);
    assert!(f.str("note").contains("round-off"), "{}", f.str("note"));
}

/// A readings table whose rows disagree on their noise is refused, naming
/// the row: one identification takes one noise.
#[test]
fn readings_whose_noise_differs_by_row_are_refused() {
    let df = polars::df!(
        "sigma_angle_urad" => [1.0, 1.0, 2.0],
        "sigma_range_um" => [2.0, 2.0, 2.0],
        "sigma_range_ppm" => [0.0, 0.0, 0.0],
    )
    .unwrap();
    let err = ltcal::schema::readings_noise(&TableRef::new("m.readings", &df)).unwrap_err();
    assert_eq!(
        err.to_string(),
        "table `m.readings`, row 2: its reading noise differs from row 0's; the readings of \
         one identification share one noise"
    );
    let df = polars::df!(
        "sigma_angle_urad" => [-1.0],
        "sigma_range_um" => [2.0],
        "sigma_range_ppm" => [0.0],
    )
    .unwrap();
    let err = ltcal::schema::readings_noise(&TableRef::new("m.readings", &df)).unwrap_err();
    assert!(
        err.to_string().contains("`sigma_angle_urad`, row 0"),
        "{err}"
    );
    let old = polars::df!("az_deg" => [1.0]).unwrap();
    assert_eq!(
        ltcal::schema::readings_noise(&TableRef::new("old", &old)).unwrap(),
        None
    );
}
