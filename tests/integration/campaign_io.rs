//! Campaign folders in and out (`campaign-format.md`): the shared example
//! campaigns read with their counts, export → import gives back the same
//! campaign and tables, and every rule of the format rejects a bad folder at
//! its file, line and column — through the library, and through `ltcal run`,
//! which then writes nothing.
//!
//! The bad folders are in `tests/data/bad-campaigns/`: `base/` is a small
//! valid campaign, every other folder is `base/` with one thing broken.

use crate::util::root;
use ltcal::campaign::{self, Campaign, Problem};
use ltcal::stages::export_campaign::ExportCampaignStage;
use ltcal::stages::{Context, StageInputs, StageKind};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

fn examples_dir() -> PathBuf {
    root().join("examples/campaigns")
}

fn bad_dir() -> PathBuf {
    root().join("tests/data/bad-campaigns")
}

/// (folder, readings, targets, gauge rows, stations)
const EXAMPLES: &[(&str, usize, usize, usize, usize)] = &[
    ("example-00-none", 120, 24, 6, 5),
    ("example-01-incidence", 200, 34, 6, 6),
    ("example-02-range-scale", 147, 30, 6, 5),
    ("example-03-air-refraction", 138, 36, 6, 4),
    ("example-04-encoder-harmonic", 159, 28, 6, 6),
    ("example-05-station-drift", 120, 24, 6, 5),
    ("example-06-target-shift", 108, 24, 6, 5),
];

/// (case folder, `file:line:col` of the first problem, a phrase of its message)
const BAD: &[(&str, &str, &str)] = &[
    (
        "reading-unknown-target",
        "readings.csv:5:4",
        "target `T99` is not in targets.csv",
    ),
    (
        "gauge-unknown-target",
        "gauge.csv:3:5",
        "target `T77` is not in targets.csv",
    ),
    (
        "duplicate-target",
        "targets.csv:8:1",
        "duplicate target id `T03`",
    ),
    (
        "non-number-reading",
        "readings.csv:4:8",
        "`az_deg`: `12.3.4` is not a number",
    ),
    (
        "non-number-target",
        "targets.csv:7:12",
        "`y_mm`: `n/a` is not a number",
    ),
    (
        "non-number-gauge",
        "gauge.csv:2:9",
        "`distance_mm`: `330.05mm` is not a number",
    ),
    (
        "non-number-optional",
        "readings.csv:8:48",
        "`time_s`: `12:30` is not a number",
    ),
    (
        "non-number-spaces",
        "readings.csv:3:35",
        "has spaces around it",
    ),
    (
        "d-zero",
        "readings.csv:6:35",
        "a distance must be > 0, got d_mm = 0",
    ),
    (
        "d-negative",
        "readings.csv:9:35",
        "a distance must be > 0, got d_mm = -1234.5",
    ),
    (
        "el-below-range",
        "readings.csv:4:21",
        "el_deg must lie in [-90, 270]",
    ),
    (
        "el-above-range",
        "readings.csv:7:22",
        "el_deg must lie in [-90, 270]",
    ),
    (
        "missing-column-readings",
        "readings.csv:1:1",
        "readings.csv lacks the required column `d_mm`",
    ),
    (
        "missing-column-targets",
        "targets.csv:1:1",
        "targets.csv lacks the required column `target`",
    ),
    (
        "missing-column-gauge",
        "gauge.csv:1:1",
        "gauge.csv lacks the required column `distance_mm`",
    ),
    (
        "missing-column-misspelt",
        "readings.csv:1:16",
        "lacks the required column `az_deg`; the header has `Az_deg`",
    ),
    (
        "station-too-few-reflectors",
        "readings.csv:13:1",
        "station S3 cannot be located: it sees 2 reflectors (T02, T04)",
    ),
    (
        "station-on-one-line",
        "readings.csv:13:1",
        "station S3 cannot be located: the 3 reflectors it sees (T01, T02, T05) lie on one line",
    ),
    (
        "gauge-shares-no-reflector",
        "gauge.csv:4:1",
        "gauge row T90 – T91 shares no reflector with any station",
    ),
    ("nan-reading", "readings.csv:3:8", "NaN is not a value"),
    ("nan-optional", "readings.csv:10:55", "NaN is not a value"),
    ("nan-target", "targets.csv:7:24", "NaN is not a value"),
    (
        "inf-reading",
        "readings.csv:5:35",
        "`inf` is not a finite number",
    ),
    (
        "inf-gauge",
        "gauge.csv:3:9",
        "`-Infinity` is not a finite number",
    ),
    ("inf-overflow", "readings.csv:2:21", "`1e999` is too large"),
    ("nan-toml", "campaign.toml:8:18", "NaN is not a value"),
    ("inf-toml", "campaign.toml:13:13", "is not a finite number"),
    (
        "face-not-1-or-2",
        "readings.csv:6:46",
        "`face` is 1 (front) or 2 (back), got `3`",
    ),
    (
        "face-decimal",
        "readings.csv:6:46",
        "`face` is 1 (front) or 2 (back), got `1.0`",
    ),
    (
        "unknown-toml-key",
        "campaign.toml:10:1",
        "unknown field `sigma_range_nm`",
    ),
    (
        "unknown-toml-table",
        "campaign.toml:15:2",
        "unknown field `cmm`",
    ),
    (
        "format-version",
        "campaign.toml:1:10",
        "format 2 is not supported: this ltcal reads campaign format 1",
    ),
    (
        "format-not-integer",
        "campaign.toml:1:10",
        "`format` is the integer 1",
    ),
    (
        "format-missing",
        "campaign.toml:1:1",
        "campaign.toml has no `format`",
    ),
    ("name-missing", "campaign.toml:1:1", "missing field `name`"),
    (
        "tracker-model-unknown",
        "campaign.toml:6:9",
        "the readings come from tracker model \"leica-at960\", which ltcal does not know: it models \"api-tracker3\" or \"mirror-tracker\"",
    ),
    (
        "tracker-model-missing",
        "campaign.toml:5:1",
        "missing field `model`",
    ),
    (
        "aim-unknown",
        "campaign.toml:12:7",
        "[smr] aim is \"aim-columns\" or \"stations-centroid\", got \"centroid\"",
    ),
    (
        "sigma-negative",
        "campaign.toml:7:20",
        "a standard deviation cannot be negative",
    ),
    (
        "toml-cut-mid-line",
        "campaign.toml:11:4",
        "unclosed table, expected `]`",
    ),
    (
        "reference-partial",
        "targets.csv:7:12",
        "`y_mm` is empty but other coordinates of this point are given",
    ),
    (
        "reference-column-missing",
        "targets.csv:1:8",
        "targets.csv has `x_mm`, `y_mm` but not `z_mm`",
    ),
    (
        "required-cell-empty",
        "readings.csv:4:8",
        "`az_deg` is required, but this cell is empty",
    ),
    (
        "station-id-empty",
        "readings.csv:11:1",
        "the station id is empty",
    ),
    // Regression: a reflector paired with itself made the calibration's
    // Jacobian NaN (0/0) and nalgebra's SVD loop forever.
    (
        "gauge-joins-a-reflector-to-itself",
        "gauge.csv:2:5",
        "a gauge joins two different reflectors",
    ),
    (
        "gauge-distance-negative",
        "gauge.csv:2:9",
        "a distance must be > 0, got -330.05",
    ),
    (
        "truncated-readings",
        "readings.csv:12:31",
        "this row has 4 fields but the header has 10: the file may be cut short",
    ),
    (
        "truncated-gauge",
        "gauge.csv:3:7",
        "this row has 2 fields but the header has 4",
    ),
    (
        "truncated-open-quote",
        "targets.csv:8:1",
        "this quoted field has no closing quote",
    ),
    (
        "empty-readings",
        "readings.csv:1:1",
        "the file is empty: it needs a header row",
    ),
    (
        "no-readings",
        "readings.csv:2:1",
        "the campaign has no readings",
    ),
    (
        "too-many-fields",
        "readings.csv:4:72",
        "this row has 11 fields but the header has 10",
    ),
    (
        "duplicate-header",
        "readings.csv:1:87",
        "column `d_mm` appears twice in the header (first at column",
    ),
    ("not-utf8", "targets.csv:5:3", "not UTF-8: byte 0xff"),
    (
        "missing-targets-file",
        "targets.csv",
        "missing: a campaign needs campaign.toml, readings.csv and targets.csv",
    ),
];

/// Regression: `[smr] aim = "aim-columns"` with the aim columns missing, or
/// one aim cell empty, was rejected; campaign-format.md says a missing
/// optional column and an empty cell both mean "not known".
#[test]
fn aim_columns_without_aim_points_leave_those_axes_unknown() {
    let dir = root().join("tests/data/campaigns-with-unknowns");
    let missing = read_ok(&dir.join("aim-columns-missing"));
    assert_eq!(missing.meta.aim, campaign::Aim::AimColumns);
    assert!(missing.targets.iter().all(|t| t.aim.is_none()));
    let one_empty = read_ok(&dir.join("aim-columns-empty-cell"));
    let known: Vec<&str> = one_empty
        .targets
        .iter()
        .filter(|t| t.aim.is_some())
        .map(|t| t.id.as_str())
        .collect();
    assert_eq!(known, ["T01", "T02", "T04", "T05", "T06"]);
}

/// Regression: a column unknown to the format, named twice in the header,
/// was rejected as a duplicate; unknown columns are ignored, repeated or not.
#[test]
fn a_repeated_unknown_column_is_ignored() {
    let tmp = tempfile::tempdir().unwrap();
    let base = bad_dir().join("base");
    for f in ["campaign.toml", "targets.csv", "gauge.csv"] {
        std::fs::copy(base.join(f), tmp.path().join(f)).unwrap();
    }
    let text = std::fs::read_to_string(base.join("readings.csv")).unwrap();
    let with_notes: String = text
        .lines()
        .enumerate()
        .map(|(i, l)| {
            let extra = if i == 0 { ",note,note" } else { ",a,b" };
            format!("{l}{extra}\n")
        })
        .collect();
    std::fs::write(tmp.path().join("readings.csv"), with_notes).unwrap();
    assert_eq!(read_ok(tmp.path()), read_ok(&base));
}

fn read_ok(dir: &Path) -> Campaign {
    campaign::read(dir).unwrap_or_else(|e| panic!("{e}"))
}

fn subfolders(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap())
        .filter(|e| e.file_type().unwrap().is_dir())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

/// The campaign's tables as a stage receives them on the group slot `slot`.
fn as_inputs(c: &Campaign, slot: &str) -> StageInputs {
    let mut inputs = StageInputs::default();
    for (name, df) in c.to_tables().unwrap() {
        inputs.insert(
            &format!("{slot}.{name}"),
            format!("test.{name}"),
            Arc::new(df),
        );
    }
    inputs
}

fn assert_same_tables(a: &Campaign, b: &Campaign) {
    let (ta, tb) = (a.to_tables().unwrap(), b.to_tables().unwrap());
    assert_eq!(ta.len(), tb.len());
    for ((na, da), (nb, db)) in ta.iter().zip(&tb) {
        assert_eq!(na, nb);
        assert!(da.equals_missing(db), "table {na} differs:\n{da}\n{db}");
    }
}

#[test]
fn every_example_campaign_reads_with_its_counts() {
    let found = subfolders(&examples_dir());
    for (name, ..) in EXAMPLES {
        assert!(found.contains(&name.to_string()), "no example {name}");
    }
    for name in &found {
        let c = read_ok(&examples_dir().join(name));
        let Some(&(_, readings, targets, gauge, stations)) = EXAMPLES.iter().find(|e| e.0 == name)
        else {
            continue;
        };
        assert_eq!(c.readings.len(), readings, "{name}: readings");
        assert_eq!(c.targets.len(), targets, "{name}: targets");
        assert_eq!(c.gauge.len(), gauge, "{name}: gauge rows");
        let expected: Vec<String> = (1..=stations).map(|i| format!("S{i}")).collect();
        assert_eq!(c.stations(), expected, "{name}: stations");
        assert_eq!(c.meta.format, 1);
        assert_eq!(c.meta.name, *name);
        assert_eq!(c.meta.aim, campaign::Aim::StationsCentroid);
        assert_eq!(c.meta.smr_radius_mm, Some(19.05));
    }
}

#[test]
fn export_then_import_gives_the_identical_campaign_and_tables() {
    let tmp = tempfile::tempdir().unwrap();
    for (name, ..) in EXAMPLES {
        let original = read_ok(&examples_dir().join(name));
        let out = tmp.path().join(name);
        campaign::write(&original, &out).unwrap();
        let back = read_ok(&out);
        assert_eq!(back, original, "{name}");
        assert_same_tables(&back, &original);
        let from_tables =
            Campaign::from_inputs(&as_inputs(&original, "campaign"), "campaign").unwrap();
        assert_eq!(*from_tables, original, "{name}: tables round trip");
    }
}

#[test]
fn every_column_and_value_survives_the_round_trip() {
    // The bad corpus's base has every optional column, a back-face reading,
    // empty optional cells and a reference point; aim columns are added here.
    let mut c = read_ok(&bad_dir().join("base"));
    c.meta.aim = campaign::Aim::AimColumns;
    for (i, t) in c.targets.iter_mut().enumerate() {
        t.aim = Some(nalgebra::Vector3::new(0.1 * i as f64, -1e-7, 1.0 / 3.0));
    }
    c.readings[2].az_deg = -0.0;
    c.readings[3].d_mm = 1.0e-300;
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("all");
    campaign::write(&c, &out).unwrap();
    let back = read_ok(&out);
    assert_eq!(back, c);
    assert!(back.readings[2].az_deg.is_sign_negative());
    assert_eq!(*Campaign::from_inputs(&as_inputs(&c, "x"), "x").unwrap(), c);
    let header = std::fs::read_to_string(out.join("readings.csv")).unwrap();
    assert!(
        header.starts_with(
            "station,target,az_deg,el_deg,d_mm,face,time_s,temperature_c,pressure_hpa,humidity_pct\n"
        ),
        "{header}"
    );
}

/// Rewrites a CSV text with its columns in another order, an unknown
/// column, every cell quoted and CRLF line ends, behind a byte-order mark.
fn shuffled_csv(text: &str) -> String {
    let rows: Vec<Vec<&str>> = text.lines().map(|l| l.split(',').collect()).collect();
    let mut out = String::from("\u{feff}");
    for (i, row) in rows.iter().enumerate() {
        let mut cells: Vec<String> = row.iter().rev().map(|c| format!("\"{c}\"")).collect();
        cells.insert(
            1,
            if i == 0 {
                "operator".into()
            } else {
                "\"A. N. Other, CMM lab\"".into()
            },
        );
        out.push_str(&cells.join(","));
        out.push_str("\r\n");
    }
    out.push_str("\r\n");
    out
}

#[test]
fn column_order_unknown_columns_quotes_crlf_and_a_bom_read_the_same() {
    let base = bad_dir().join("base");
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("shuffled");
    std::fs::create_dir(&dir).unwrap();
    std::fs::copy(base.join("campaign.toml"), dir.join("campaign.toml")).unwrap();
    for f in ["readings.csv", "targets.csv", "gauge.csv"] {
        let text = std::fs::read_to_string(base.join(f)).unwrap();
        std::fs::write(dir.join(f), shuffled_csv(&text)).unwrap();
    }
    assert_eq!(read_ok(&dir), read_ok(&base));
}

#[test]
fn a_campaign_without_gauge_survives_the_tables_through_parquet() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("no-gauge");
    let mut c = read_ok(&bad_dir().join("base"));
    c.gauge.clear();
    campaign::write(&c, &dir).unwrap();
    assert!(!dir.join("gauge.csv").exists());
    let back = read_ok(&dir);
    assert_eq!(back, c);
    let mut inputs = StageInputs::default();
    for (name, df) in back.to_tables().unwrap() {
        let bytes = ltcal::table::to_parquet_bytes(&df).unwrap();
        let df = ltcal::table::from_parquet_bytes(&bytes).unwrap();
        inputs.insert(&format!("c.{name}"), name.clone(), Arc::new(df));
    }
    assert_eq!(*Campaign::from_inputs(&inputs, "c").unwrap(), c);
}

#[test]
fn the_tables_have_the_files_columns() {
    let c = read_ok(&bad_dir().join("base"));
    let tables = c.to_tables().unwrap();
    let names: Vec<&str> = tables.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, campaign::TABLES);
    let columns = |i: usize| -> Vec<String> {
        tables[i]
            .1
            .get_column_names()
            .iter()
            .map(|s| s.to_string())
            .collect()
    };
    assert_eq!(
        columns(0),
        [
            "station",
            "target",
            "az_deg",
            "el_deg",
            "d_mm",
            "face",
            "time_s",
            "temperature_c",
            "pressure_hpa",
            "humidity_pct",
            "line"
        ]
    );
    assert_eq!(
        columns(1),
        [
            "target", "x_mm", "y_mm", "z_mm", "u_mm", "aim_x_mm", "aim_y_mm", "aim_z_mm"
        ]
    );
    assert_eq!(columns(2), ["target_a", "target_b", "distance_mm", "u_mm"]);
    assert_eq!(
        columns(3),
        [
            "format",
            "name",
            "description",
            "tracker_model",
            "sigma_angle_urad",
            "sigma_range_um",
            "sigma_range_ppm",
            "smr_aim",
            "smr_radius_mm"
        ]
    );
    assert_eq!(tables[3].1.height(), 1);
}

#[test]
fn optional_columns_are_written_only_when_known() {
    let c = read_ok(&examples_dir().join("example-00-none"));
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("c");
    campaign::write(&c, &out).unwrap();
    let first_line = |f: &str| {
        std::fs::read_to_string(out.join(f))
            .unwrap()
            .lines()
            .next()
            .unwrap()
            .to_string()
    };
    // All front face: no `face`; no reference coordinates: `target` alone.
    assert_eq!(
        first_line("readings.csv"),
        "station,target,az_deg,el_deg,d_mm,time_s,temperature_c"
    );
    assert_eq!(first_line("targets.csv"), "target");
    assert_eq!(
        first_line("gauge.csv"),
        "target_a,target_b,distance_mm,u_mm"
    );
}

#[test]
fn writing_is_atomic_and_overwrites_only_when_asked() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("c");
    let mut c = read_ok(&bad_dir().join("base"));
    campaign::write(&c, &out).unwrap();
    // The same campaign again is no overwrite.
    campaign::write(&c, &out).unwrap();
    c.readings[0].d_mm += 1.0;
    let e = campaign::write(&c, &out).unwrap_err().to_string();
    assert!(e.contains("already exists"), "{e}");
    assert_ne!(read_ok(&out), c);
    campaign::overwrite(&c, &out).unwrap();
    assert_eq!(read_ok(&out), c);
    // Nothing but the folder is left beside it.
    assert_eq!(subfolders(tmp.path()), vec!["c".to_string()]);
    assert_eq!(std::fs::read_dir(tmp.path()).unwrap().count(), 1);
}

#[test]
fn an_invalid_campaign_is_not_written() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("c");
    let mut c = read_ok(&bad_dir().join("base"));
    c.readings[1].d_mm = -5.0;
    c.readings[2].el_deg = f64::NAN;
    let e = campaign::write(&c, &out).unwrap_err().to_string();
    assert!(
        e.contains("table `readings`, row 1, column `d_mm`: a distance must be > 0"),
        "{e}"
    );
    assert!(
        e.contains("table `readings`, row 2, column `el_deg`: NaN is not a value"),
        "{e}"
    );
    assert_eq!(std::fs::read_dir(tmp.path()).unwrap().count(), 0);
    assert!(Campaign::from_inputs(&as_inputs(&c, "campaign"), "campaign").is_err());
}

#[test]
fn the_export_stage_writes_nothing_for_an_invalid_campaign() {
    let tmp = tempfile::tempdir().unwrap();
    let mut c = read_ok(&bad_dir().join("base"));
    c.targets.push(c.targets[0].clone());
    let stage = ExportCampaignStage {
        path: tmp.path().join("out"),
        overwrite: true,
    };
    let ctx = Context {
        pipeline: "test",
        stage: "export",
        file_hash: None,
    };
    let e = stage.run(&ctx, &as_inputs(&c, "campaign")).err().unwrap();
    assert!(
        format!("{e:#}").contains("duplicate target id `T01`"),
        "{e:#}"
    );
    assert_eq!(std::fs::read_dir(tmp.path()).unwrap().count(), 0);
}

#[test]
fn the_base_of_the_bad_corpus_is_valid_and_every_case_is_listed() {
    read_ok(&bad_dir().join("base"));
    let mut cases: Vec<String> = BAD.iter().map(|b| b.0.to_string()).collect();
    cases.push("base".into());
    cases.sort();
    assert_eq!(subfolders(&bad_dir()), cases);
}

#[test]
fn every_bad_campaign_is_rejected_at_its_file_line_and_column() {
    let mut wrong = Vec::new();
    for (case, location, phrase) in BAD {
        let dir = bad_dir().join(case);
        let e = match campaign::read(&dir) {
            Ok(_) => {
                wrong.push(format!("{case}: read without error"));
                continue;
            }
            Err(e) => e,
        };
        let first = &e.problems[0];
        let expected = dir.join(location).display().to_string();
        let caret = match first {
            Problem::At(src) => src.to_string().contains('^'),
            Problem::File { .. } => true,
        };
        if first.location() != expected
            || !first.message().contains(phrase)
            || e.problems.len() != 1
            || !caret
        {
            wrong.push(format!(
                "{case}: expected one problem at {location} saying `{phrase}`, got:\n{e}"
            ));
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n\n"));
}

/// Runs `ltcal run` on import → export of `campaign_dir`; returns the exit
/// code and stderr, and asserts that neither the export folder nor any
/// result appeared.
fn run_import_export(campaign_dir: &Path) -> (i32, String) {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("p.toml");
    let export = tmp.path().join("exported");
    std::fs::write(
        &file,
        format!(
            "[stages.campaign]\nkind = \"import_campaign\"\npath = '{}'\n\n\
             [stages.export]\nkind = \"export_campaign\"\ninputs = {{ campaign = \"campaign\" }}\npath = '{}'\n",
            campaign_dir.display(),
            export.display()
        ),
    )
    .unwrap();
    let results = tmp.path().join("results");
    let out = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .args([
            "run",
            file.to_str().unwrap(),
            "--results",
            results.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(!export.exists(), "the export folder was written");
    assert!(!results.exists(), "results were written");
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn ltcal_run_rejects_every_bad_campaign_and_writes_nothing() {
    for (case, location, phrase) in BAD {
        let dir = bad_dir().join(case);
        let (code, err) = run_import_export(&dir);
        assert_eq!(code, 2, "{case}:\n{err}");
        let at = dir.join(location).display().to_string();
        assert!(err.contains(&at), "{case}: no {at} in:\n{err}");
        assert!(err.contains(phrase), "{case}: no `{phrase}` in:\n{err}");
        assert!(
            err.contains("p.toml:3:8"),
            "{case}: the pipeline's `path` is not pointed at:\n{err}"
        );
    }
}

#[test]
fn the_import_export_pipeline_round_trips_example_00() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let run = || {
        Command::new(env!("CARGO_BIN_EXE_ltcal"))
            .current_dir(root())
            .args([
                "run",
                "pipelines/examples/import-export.toml",
                "--results",
                tmp.path().join("results").to_str().unwrap(),
                "--set",
                &format!("stages.export.path='{}'", out.display()),
                "--name",
                "to-tmp",
            ])
            .output()
            .unwrap()
    };
    let first = run();
    assert!(
        first.status.success(),
        "{}",
        String::from_utf8_lossy(&first.stderr)
    );
    assert_eq!(
        read_ok(&out),
        read_ok(&examples_dir().join("example-00-none"))
    );
    // A run with --set is an experiment, published in its own folder.
    let export = crate::util::table(
        &tmp.path().join("results"),
        "import-export/runs/to-tmp",
        "export",
        "export",
    );
    assert_eq!(crate::util::col(&export, "readings"), vec![120.0]);
    assert_eq!(crate::util::col(&export, "gauge_rows"), vec![6.0]);
    let second = run();
    let err = String::from_utf8_lossy(&second.stderr);
    assert!(second.status.success(), "{err}");
    assert!(err.contains("0 ran, 2 cached"), "{err}");
}

#[test]
fn an_edited_campaign_file_is_not_answered_from_the_cache() {
    let tmp = tempfile::tempdir().unwrap();
    let src = tmp.path().join("campaign");
    std::fs::create_dir(&src).unwrap();
    for f in campaign::FILES {
        std::fs::copy(bad_dir().join("base").join(f), src.join(f)).unwrap();
    }
    let out = tmp.path().join("out");
    let file = tmp.path().join("p.toml");
    std::fs::write(
        &file,
        format!(
            "[stages.campaign]\nkind = \"import_campaign\"\npath = '{}'\n\n\
             [stages.export]\nkind = \"export_campaign\"\ninputs = {{ campaign = \"campaign\" }}\npath = '{}'\noverwrite = true\n",
            src.display(),
            out.display()
        ),
    )
    .unwrap();
    let results = tmp.path().join("results");
    let run = || {
        let o = Command::new(env!("CARGO_BIN_EXE_ltcal"))
            .args([
                "run",
                file.to_str().unwrap(),
                "--results",
                results.to_str().unwrap(),
            ])
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8_lossy(&o.stderr).into_owned()
    };
    run();
    let text = std::fs::read_to_string(src.join("readings.csv")).unwrap();
    std::fs::write(
        src.join("readings.csv"),
        text.replace("4610.10042", "4610.10043"),
    )
    .unwrap();
    // The runner read the folder when the pipeline loaded: `plan` names it.
    let plan = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .args([
            "plan",
            file.to_str().unwrap(),
            "--results",
            results.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    let said =
        String::from_utf8_lossy(&plan.stdout).into_owned() + &String::from_utf8_lossy(&plan.stderr);
    assert!(said.contains("its file changed"), "{said}");
    let err = run();
    assert!(err.contains("2 ran, 0 cached"), "{err}");
    assert_eq!(read_ok(&out).readings[0].d_mm, 4610.10043);
}

/// The folder's hash is the runner's (the key's `file` field), never a
/// setting a user could write and so lie about.
#[test]
fn content_hash_is_not_a_setting() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("p.toml");
    std::fs::write(
        &file,
        format!(
            "[stages.campaign]\nkind = \"import_campaign\"\npath = '{}'\ncontent_hash = \"0\"\n",
            bad_dir().join("base").display()
        ),
    )
    .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .args([
            "plan",
            file.to_str().unwrap(),
            "--results",
            tmp.path().join("r").to_str().unwrap(),
        ])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("p.toml:4:1") && err.contains("unknown field `content_hash`"),
        "{err}"
    );
}

/// A valid campaign folder in `dir`: `stations` stations reading reflectors
/// `T0`… (each station three, not on one line), `targets` rows in
/// targets.csv (at least 3) and `gauge` gauge lengths between T0 and T1.
fn counted_campaign(dir: &Path, stations: usize, targets: usize, gauge: usize) -> PathBuf {
    let c = dir.join("counted");
    std::fs::create_dir_all(&c).unwrap();
    std::fs::write(
        c.join("campaign.toml"),
        "format = 1\nname = \"counted\"\n\n[tracker]\nmodel = \"api-tracker3\"\n\n[smr]\naim = \"stations-centroid\"\n",
    )
    .unwrap();
    let mut readings = String::from("station,target,az_deg,el_deg,d_mm\n");
    for s in 0..stations {
        for (t, az) in [(0, 10.0), (1, 50.0), (2, 120.0)] {
            readings.push_str(&format!("S{s},T{t},{az},{},{}\n", 5 * t, 3000 + 100 * t));
        }
    }
    std::fs::write(c.join("readings.csv"), readings).unwrap();
    let targets: String = (0..targets).map(|t| format!("T{t}\n")).collect();
    std::fs::write(c.join("targets.csv"), format!("target\n{targets}")).unwrap();
    let lengths: String = (0..gauge).map(|_| "T0,T1,1000\n").collect();
    std::fs::write(
        c.join("gauge.csv"),
        format!("target_a,target_b,distance_mm\n{lengths}"),
    )
    .unwrap();
    c
}

/// `ltcal diagnose` on `dir`: exit 2, in under a second, with every phrase
/// of `expected` in stderr.
fn refused_at_load_in_a_second(dir: &Path, expected: &[&str]) {
    let start = std::time::Instant::now();
    let o = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .args(["diagnose", dir.to_str().unwrap(), "--out"])
        .arg(dir.with_extension("out"))
        .output()
        .unwrap();
    let took = start.elapsed();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    for e in expected {
        assert!(err.contains(e), "no `{e}` in:\n{err}");
    }
    assert!(took.as_secs_f64() < 1.0, "refused after {took:?}");
    // Only a calibration refuses: the format allows the counts.
    assert!(campaign::read(dir).is_ok());
}

/// Regression (issue 28): a million readings over 40 000 stations were
/// accepted, ran 9 minutes and aborted allocating 500 GB (the adjustment's
/// dense part holds six unknowns per station). Now the station beyond
/// `MAX_STATIONS` is refused at its first reading, the limit named.
#[test]
fn a_campaign_over_the_station_limit_is_refused_at_load() {
    let tmp = tempfile::tempdir().unwrap();
    let n = campaign::MAX_STATIONS;
    let at_limit = counted_campaign(tmp.path(), n, 3, 0);
    assert!(campaign::read_for_calibration(&at_limit).is_ok());
    let over = counted_campaign(&tmp.path().join("over"), n + 1, 3, 0);
    // The first reading of station n + 1: line 2 + 3·n.
    refused_at_load_in_a_second(
        &over,
        &[
            &format!("readings.csv:{}:1", 2 + 3 * n),
            &format!("at most {n} stations"),
            "campaign::MAX_STATIONS",
        ],
    );
    // The case of the issue, at the scale of a test: 40 000 stations.
    let many = counted_campaign(&tmp.path().join("many"), 40_000, 3, 0);
    refused_at_load_in_a_second(&many, &[&format!("readings.csv:{}:1", 2 + 3 * n)]);
}

/// Regression (issue 28): the reflector and gauge counts are checked at
/// load too, each at its first row beyond the limit (the gauge joined
/// reflectors were looked up once per target and gauge row: quadratic).
#[test]
fn a_campaign_over_the_reflector_or_gauge_limit_is_refused_at_load() {
    let tmp = tempfile::tempdir().unwrap();
    let r = campaign::MAX_REFLECTORS;
    let at_limit = counted_campaign(tmp.path(), 3, r, campaign::MAX_GAUGE_LENGTHS);
    assert!(campaign::read_for_calibration(&at_limit).is_ok());
    let targets = counted_campaign(&tmp.path().join("targets"), 3, r + 1, 0);
    refused_at_load_in_a_second(
        &targets,
        &[
            &format!("targets.csv:{}:1", r + 2),
            &format!("at most {r} reflectors"),
        ],
    );
    let g = campaign::MAX_GAUGE_LENGTHS;
    let gauge = counted_campaign(&tmp.path().join("gauge"), 3, 3, g + 1);
    refused_at_load_in_a_second(
        &gauge,
        &[
            &format!("gauge.csv:{}:1", g + 2),
            &format!("at most {g} gauge lengths"),
        ],
    );
}

/// Regression (issue 28): `model = "api-tracker3 "` (a trailing space) was
/// accepted: the id was trimmed before it was matched. Now it is refused
/// at its place, the known ids listed.
#[test]
fn a_tracker_model_with_a_trailing_space_is_refused_at_its_place() {
    let tmp = tempfile::tempdir().unwrap();
    let dir =
        crate::hostile::mutated_example(tmp.path(), "example-00-none", "campaign.toml", |t| {
            t.replace("\"api-tracker3\"", "\"api-tracker3 \"")
        });
    let e = campaign::read(&dir).unwrap_err().to_string();
    assert!(e.contains("campaign.toml:6:"), "{e}");
    assert!(
        e.contains("\"api-tracker3 \" has spaces around the id"),
        "{e}"
    );
    assert!(e.contains("\"api-tracker3\" or \"mirror-tracker\""), "{e}");
}
