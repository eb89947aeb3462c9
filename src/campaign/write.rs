//! Writing a campaign folder in the exact format it is read in
//! (`campaign-format.md`, version 1), so that what ltcal makes — simulated
//! campaigns above all — is read by any other tool as written, and by ltcal
//! back into an identical [`Campaign`].
//!
//! Numbers are written in Rust's shortest round-trip form, so each one parses
//! back to the same `f64`. An optional column appears only when some row
//! knows a value (`face` only when some reading is back face, since front is
//! the default), and gauge.csv only when there are gauge lengths.
//!
//! The folder is built beside its destination under a temporary name and
//! renamed into place: the destination holds a whole campaign or nothing,
//! even after a crash. A campaign that breaks the format's rules is refused
//! before anything is written. A folder that already holds exactly the files
//! to be written is left alone and counts as written: writing the same
//! campaign twice (an export rerun after its cache was cleared) is not an
//! overwrite. [`overwrite`] replaces only a folder that is recognisably a
//! campaign ([`crate::fs::check_replaceable`], as `ltcal diagnose --out`):
//! `campaign.toml` and nothing but campaign files — never a folder of the
//! user's other files, which replacing it whole would delete.

use super::{Campaign, check::Issue};
use anyhow::{Context as _, Result, anyhow, bail};
use serde::Serialize;
use std::collections::BTreeSet;
use std::fs;
use std::path::Path;

/// Writes `c` as the folder `dir`, which must not exist yet (or hold
/// exactly this campaign already).
pub fn write(c: &Campaign, dir: &Path) -> Result<()> {
    publish(c, dir, false)
}

/// Writes `c` as the folder `dir`, replacing the campaign folder there if
/// any: the old one is renamed away, the new one renamed in, then the old
/// one removed. A folder there that is not a campaign is refused.
pub fn overwrite(c: &Campaign, dir: &Path) -> Result<()> {
    publish(c, dir, true)
}

fn publish(c: &Campaign, dir: &Path, replace: bool) -> Result<()> {
    refuse_invalid(c, dir)?;
    let files = files(c)?;
    let exists = fs::symlink_metadata(dir).ok();
    if exists.as_ref().is_some_and(|m| m.is_dir()) && holds(dir, &files) {
        return Ok(());
    }
    if exists.is_some() && !replace {
        bail!(
            "{} already exists: choose another folder, or allow overwriting it",
            dir.display()
        );
    }
    crate::fs::check_replaceable(dir, "a campaign", "campaign.toml", |name| {
        super::FILES.contains(&name)
    })
    .map_err(|why| anyhow!("{why} (`overwrite` replaces only a campaign folder)"))?;
    crate::fs::publish_folder(dir, &files)
}

/// Whether `dir` holds exactly `files`, byte for byte, and nothing else.
fn holds(dir: &Path, files: &[(&str, Vec<u8>)]) -> bool {
    let Ok(entries) = fs::read_dir(dir) else {
        return false;
    };
    let names: BTreeSet<String> = entries
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.len() == files.len()
        && files.iter().all(|(name, bytes)| {
            names.contains(*name)
                && crate::fs::read_regular_file(&dir.join(name), super::MAX_FILE_BYTES)
                    .is_ok_and(|b| b == *bytes)
        })
}

/// Fails, listing every broken rule, unless `c` is a valid campaign.
fn refuse_invalid(c: &Campaign, dir: &Path) -> Result<()> {
    let issues = c.check();
    if issues.is_empty() {
        return Ok(());
    }
    let list: Vec<String> = issues.iter().map(Issue::to_string).collect();
    bail!(
        "the campaign is not written to {}: it breaks the campaign format's rules:\n  {}",
        dir.display(),
        list.join("\n  ")
    )
}

/// The files of the folder, by name.
fn files(c: &Campaign) -> Result<Vec<(&'static str, Vec<u8>)>> {
    let mut out = vec![
        ("campaign.toml", campaign_toml(c)?.into_bytes()),
        ("readings.csv", readings_csv(c)?),
        ("targets.csv", targets_csv(c)?),
    ];
    if !c.gauge.is_empty() {
        out.push(("gauge.csv", gauge_csv(c)?));
    }
    Ok(out)
}

#[derive(Serialize)]
struct MetaOut<'a> {
    format: i64,
    name: &'a str,
    #[serde(skip_serializing_if = "str::is_empty")]
    description: &'a str,
    tracker: TrackerOut<'a>,
    smr: SmrOut,
}

#[derive(Serialize)]
struct TrackerOut<'a> {
    model: &'a str,
    #[serde(skip_serializing_if = "Option::is_none")]
    sigma_angle_urad: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    sigma_range_um: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    sigma_range_ppm: Option<f64>,
}

#[derive(Serialize)]
struct SmrOut {
    aim: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    radius_mm: Option<f64>,
}

fn campaign_toml(c: &Campaign) -> Result<String> {
    let m = &c.meta;
    let out = MetaOut {
        format: m.format,
        name: &m.name,
        description: &m.description,
        tracker: TrackerOut {
            model: &m.tracker.model,
            sigma_angle_urad: m.tracker.sigma_angle_urad,
            sigma_range_um: m.tracker.sigma_range_um,
            sigma_range_ppm: m.tracker.sigma_range_ppm,
        },
        smr: SmrOut {
            aim: m.aim.as_str(),
            radius_mm: m.smr_radius_mm,
        },
    };
    toml::to_string(&out).context("writing campaign.toml")
}

/// A table to write: columns that are always there, and optional ones kept
/// only when some row has a value.
struct CsvOut {
    header: Vec<&'static str>,
    rows: Vec<Vec<String>>,
}

impl CsvOut {
    fn new(rows: usize) -> CsvOut {
        CsvOut {
            header: Vec::new(),
            rows: vec![Vec::new(); rows],
        }
    }

    fn column(mut self, name: &'static str, cells: impl Iterator<Item = String>) -> CsvOut {
        self.header.push(name);
        for (row, cell) in self.rows.iter_mut().zip(cells) {
            row.push(cell);
        }
        self
    }

    fn optional(self, name: &'static str, values: impl Iterator<Item = Option<f64>>) -> CsvOut {
        let values: Vec<Option<f64>> = values.collect();
        if values.iter().all(Option::is_none) {
            return self;
        }
        self.column(
            name,
            values.into_iter().map(|v| v.map_or_else(String::new, num)),
        )
    }

    fn bytes(self) -> Result<Vec<u8>> {
        let mut w = csv::WriterBuilder::new()
            .terminator(csv::Terminator::Any(b'\n'))
            .from_writer(Vec::new());
        w.write_record(&self.header)?;
        for row in &self.rows {
            w.write_record(row)?;
        }
        w.into_inner().map_err(|e| anyhow!("writing CSV: {e}"))
    }
}

/// Shortest text that parses back to the same `f64`.
fn num(v: f64) -> String {
    v.to_string()
}

fn readings_csv(c: &Campaign) -> Result<Vec<u8>> {
    let r = &c.readings;
    let mut t = CsvOut::new(r.len())
        .column("station", r.iter().map(|r| r.station.clone()))
        .column("target", r.iter().map(|r| r.target.clone()))
        .column("az_deg", r.iter().map(|r| num(r.az_deg)))
        .column("el_deg", r.iter().map(|r| num(r.el_deg)))
        .column("d_mm", r.iter().map(|r| num(r.d_mm)));
    if r.iter().any(|r| r.face != crate::kinematics::Face::Front) {
        t = t.column("face", r.iter().map(|r| r.face.number().to_string()));
    }
    t.optional("time_s", r.iter().map(|r| r.time_s))
        .optional("temperature_c", r.iter().map(|r| r.temperature_c))
        .optional("pressure_hpa", r.iter().map(|r| r.pressure_hpa))
        .optional("humidity_pct", r.iter().map(|r| r.humidity_pct))
        .bytes()
}

fn targets_csv(c: &Campaign) -> Result<Vec<u8>> {
    let t = &c.targets;
    let reference = |k: usize| t.iter().map(move |t| t.reference.map(|p| p[k]));
    let aim = |k: usize| t.iter().map(move |t| t.aim.map(|p| p[k]));
    CsvOut::new(t.len())
        .column("target", t.iter().map(|t| t.id.clone()))
        .optional("x_mm", reference(0))
        .optional("y_mm", reference(1))
        .optional("z_mm", reference(2))
        .optional("u_mm", t.iter().map(|t| t.u_mm))
        .optional("aim_x_mm", aim(0))
        .optional("aim_y_mm", aim(1))
        .optional("aim_z_mm", aim(2))
        .bytes()
}

fn gauge_csv(c: &Campaign) -> Result<Vec<u8>> {
    let g = &c.gauge;
    CsvOut::new(g.len())
        .column("target_a", g.iter().map(|g| g.target_a.clone()))
        .column("target_b", g.iter().map(|g| g.target_b.clone()))
        .column("distance_mm", g.iter().map(|g| num(g.distance_mm)))
        .optional("u_mm", g.iter().map(|g| g.u_mm))
        .bytes()
}
