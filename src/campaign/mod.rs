//! Campaign data: what a laser-tracker user brings home — readings of a set
//! of reflectors from several stations, reference coordinates where known,
//! calibrated gauge lengths — as `campaign-format.md` (version 1) defines it.
//!
//! The same [`Campaign`] comes from a folder ([`read()`]), from the simulator
//! ([`crate::simulate`]) or from pipeline tables ([`Campaign::from_inputs`]),
//! and goes back to a folder ([`write()`]) or tables ([`Campaign::to_tables`])
//! without loss: angles stay in the degrees they were written in and are
//! converted to radians only when a [`Reading`] is asked for. Whatever the
//! way in or out, [`Campaign::check`] holds it to the same rules. The tables
//! are the pipeline's business, so that way in and out is written in
//! `stages` (`stages/campaign_tables.rs`); this module knows only files.

mod check;
mod read;
mod usable;
mod write;

pub use crate::diagnostics::Problem;
pub use check::{Issue, LINE_TOLERANCE_MM, Place, Table};
pub use read::{
    CampaignError, FILES, GAUGE_COLUMNS, MAX_FILE_BYTES, MAX_ROWS, READINGS_COLUMNS,
    TARGETS_COLUMNS, content_hash, read, read_for_calibration, read_for_diagnosis,
};
pub use usable::{
    MAX_GAUGE_LENGTHS, MAX_RANGE_MM, MAX_REFLECTORS, MAX_STATIONS, POLE_COS_EL, SIGMA_RANGE,
};
pub use write::{overwrite, write};

use crate::kinematics::{Face, Reading};
use crate::trackers::TrackerModel;
use nalgebra::Vector3;

/// The tables a campaign travels as between stages (a group input slot:
/// `Slot::group("campaign", …, TABLES)`).
pub const TABLES: &[&str] = &["readings", "targets", "gauge", "meta"];

/// `campaign.toml [tracker]`.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Tracker {
    pub model: String,
    pub sigma_angle_urad: Option<f64>,
    pub sigma_range_um: Option<f64>,
    pub sigma_range_ppm: Option<f64>,
}

/// How the SMR axes are known (`[smr] aim`), and how a simulating stage
/// sets them (its `aim` setting, the same words).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Aim {
    /// From the `aim_*_mm` columns of targets.csv.
    #[default]
    AimColumns,
    /// Every SMR faces the centroid of all station positions (Section 10).
    StationsCentroid,
}

impl Aim {
    /// A simulating stage's default: every SMR faces the stations' centroid,
    /// as in the paper's simulations (Section 10). A campaign file's default
    /// stays [`Aim::AimColumns`], the format's.
    pub fn simulated_default() -> Aim {
        Aim::StationsCentroid
    }
    pub fn as_str(self) -> &'static str {
        match self {
            Aim::AimColumns => "aim-columns",
            Aim::StationsCentroid => "stations-centroid",
        }
    }
    pub fn parse(s: &str) -> Option<Aim> {
        match s {
            "aim-columns" => Some(Aim::AimColumns),
            "stations-centroid" => Some(Aim::StationsCentroid),
            _ => None,
        }
    }
}

/// `campaign.toml`.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Meta {
    pub format: i64,
    pub name: String,
    pub description: String,
    pub tracker: Tracker,
    pub aim: Aim,
    pub smr_radius_mm: Option<f64>,
}

/// One row of readings.csv.
#[derive(Clone, Debug, PartialEq)]
pub struct CampaignReading {
    pub station: String,
    pub target: String,
    pub az_deg: f64,
    pub el_deg: f64,
    pub d_mm: f64,
    pub face: Face,
    pub time_s: Option<f64>,
    pub temperature_c: Option<f64>,
    pub pressure_hpa: Option<f64>,
    pub humidity_pct: Option<f64>,
    /// The line of `readings.csv` the reading was read from (1: the
    /// header); `None` for a reading ltcal made.
    pub line: Option<usize>,
}

impl CampaignReading {
    /// The reading in radians and mm.
    pub fn reading(&self) -> Reading {
        Reading {
            az: self.az_deg.to_radians(),
            el: self.el_deg.to_radians(),
            d: self.d_mm,
        }
    }
}

/// One row of targets.csv.
#[derive(Clone, Debug, PartialEq)]
pub struct Target {
    pub id: String,
    /// Reference coordinates (e.g. from a CMM), mm: a *nominal* point.
    pub reference: Option<Vector3<f64>>,
    pub u_mm: Option<f64>,
    /// The point the SMR opening faces, mm.
    pub aim: Option<Vector3<f64>>,
}

/// One row of gauge.csv.
#[derive(Clone, Debug, PartialEq)]
pub struct GaugeLength {
    pub target_a: String,
    pub target_b: String,
    pub distance_mm: f64,
    pub u_mm: Option<f64>,
}

/// A whole campaign.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Campaign {
    pub meta: Meta,
    pub readings: Vec<CampaignReading>,
    pub targets: Vec<Target>,
    pub gauge: Vec<GaugeLength>,
}

impl Campaign {
    /// Station ids in order of first appearance.
    pub fn stations(&self) -> Vec<String> {
        // A set beside the list: a search of the list per reading was
        // quadratic (40 000 stations in a million readings took minutes).
        // A station's readings mostly follow one another: the one before is
        // compared first, the set hashed only when the station changes.
        let mut seen = std::collections::HashSet::new();
        let mut out: Vec<String> = Vec::new();
        let mut last: Option<&str> = None;
        for r in &self.readings {
            if last == Some(r.station.as_str()) {
                continue;
            }
            last = Some(r.station.as_str());
            if seen.insert(r.station.as_str()) {
                out.push(r.station.clone());
            }
        }
        out
    }

    pub fn target(&self, id: &str) -> Option<&Target> {
        self.targets.iter().find(|t| t.id == id)
    }

    /// The tracker model of `[tracker] model` (the paper's when the id is
    /// unknown, which [`Campaign::check`] reports).
    pub fn tracker_model(&self) -> TrackerModel {
        TrackerModel::parse(&self.meta.tracker.model).unwrap_or_default()
    }
}
