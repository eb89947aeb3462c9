//! Declared output columns: what lets a setting that names a column of
//! another stage's table (a plot's `x`, `y`, `series`, `filter`) be checked
//! when the pipeline loads rather than after a run. A declaration that
//! drifted from the table a stage really writes would refuse good pipelines
//! or pass bad ones, so every declaration is held against the tables in
//! `results/`, written by this commit's code.

use crate::util::root;
use ltcal::stages::declared_columns;
use std::path::Path;
use std::process::Command;

/// Tables whose columns depend on the data (one column per station) or on
/// the settings (`spread`'s leading columns are its `by` list).
const DATA_DEPENDENT: &[(&str, &str)] = &[
    ("evaluate_campaign", "table5"),
    ("evaluate_campaign", "table6"),
    ("spread", "spread"),
];

fn parquet_columns(path: &Path) -> Vec<String> {
    let bytes = std::fs::read(path).unwrap();
    let df = ltcal::table::from_parquet_bytes(&bytes).unwrap();
    df.get_column_names()
        .iter()
        .map(|c| c.to_string())
        .collect()
}

#[test]
fn every_declared_column_list_is_the_table_the_stage_writes() {
    let mut checked = 0;
    for run in std::fs::read_dir(root().join("results")).unwrap() {
        let dir = run.unwrap().path();
        let Ok(text) = std::fs::read_to_string(dir.join("run.json")) else {
            continue;
        };
        let run: serde_json::Value = serde_json::from_str(&text).unwrap();
        for stage in run["stages"].as_array().unwrap() {
            let kind = stage["kind"].as_str().unwrap();
            let name = stage["stage"].as_str().unwrap();
            for table in stage["tables"].as_object().unwrap().keys() {
                let file = dir.join(name).join(format!("{table}.parquet"));
                if !file.exists() {
                    continue;
                }
                let declared = declared_columns(kind, table);
                if DATA_DEPENDENT.contains(&(kind, table.as_str())) {
                    assert!(declared.is_none(), "{kind}.{table} depends on the data");
                    continue;
                }
                let declared =
                    declared.unwrap_or_else(|| panic!("{kind}.{table} declares no columns"));
                assert_eq!(
                    parquet_columns(&file),
                    declared,
                    "{kind}.{table} ({})",
                    file.display()
                );
                checked += 1;
            }
        }
    }
    assert!(checked >= 50, "only {checked} tables checked");
}

/// No committed pipeline has a `diagnose` stage; `ltcal diagnose` writes
/// the same tables.
#[test]
fn the_diagnosis_tables_have_their_declared_columns() {
    let out = tempfile::tempdir().unwrap();
    let folder = out.path().join("d");
    let status = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .arg("diagnose")
        .arg(root().join("examples/campaigns/example-01-incidence"))
        .arg("--out")
        .arg(&folder)
        .output()
        .unwrap();
    assert!(status.status.success(), "{status:?}");
    for table in ["diagnosis", "where", "residuals", "summary", "skipped"] {
        assert_eq!(
            parquet_columns(&folder.join(format!("{table}.parquet"))),
            declared_columns("diagnose", table).unwrap(),
            "diagnose.{table}"
        );
    }
}

/// Regression (issue 12): a plot naming a column another stage's table
/// does not have was checked at load only against `evaluate_campaign`; an
/// `identify` table is now checked too, at the place the column is named.
#[test]
fn a_plot_naming_a_missing_column_of_an_identify_table_is_refused_at_load() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("typo.toml");
    let text = r#"[pipeline]
name = "typo"

[stages.truth]
kind = "inject"
preset = "table2"

[stages.sphere]
kind = "mesh"
shape = "plane"

[stages.measure]
kind = "measure"
inputs = { points = "sphere", errors = "truth" }

[stages.identify]
kind = "identify"
inputs = { readings = "measure" }

[stages.figure]
kind = "plot"
inputs = { table = "identify.fit" }
plot = "metric"
x = "rank"
y = "valeu"
"#;
    std::fs::write(&file, text).unwrap();
    let err = ltcal::pipeline::load(&file, &[]).unwrap_err().to_string();
    let line = text.lines().position(|l| l.contains("valeu")).unwrap() + 1;
    assert!(err.contains(&format!("typo.toml:{line}:5")), "{err}");
    assert!(err.contains("column `valeu`"), "{err}");
    let out = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .args(["plan", file.to_str().unwrap()])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2), "{out:?}");
}
