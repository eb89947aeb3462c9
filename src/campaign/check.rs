//! The rules a campaign's *values* must keep (`campaign-format.md`, "Rules a
//! reader must keep"), in one place, so that a campaign read from a folder,
//! rebuilt from pipeline tables or about to be written is held to the same
//! ones. Each problem names the table, row and column it is about; the reader
//! turns that into `file:line:col`, the table code into a table row.
//!
//! What cannot even be represented in a [`Campaign`] (a missing column, text
//! in a number column, a truncated row) is the reader's business, not this
//! module's.

use super::{Campaign, CampaignReading};
use crate::kinematics::nominal_point;
use crate::trackers::TrackerModel;
use nalgebra::Vector3;
use rayon::prelude::*;
use std::collections::{BTreeMap, HashMap, HashSet, btree_map, hash_map};
use std::fmt;

/// How far (mm) every reflector a station sees may lie from one line for
/// the station still to count as seeing them "on one line". A station is
/// located from the reflectors it sees; reflectors on (or within the noise
/// of) a line leave its rotation about that line free. Reading noise is tens
/// of µm at 15 m and real layouts are spread over metres, so 1 mm separates
/// the two by more than an order of magnitude on either side.
pub const LINE_TOLERANCE_MM: f64 = 1.0;

/// The lowest and highest elevation reading, degrees: the front face reads
/// [−90°, 90°], the back face `180° − el`, i.e. [90°, 270°].
const EL_RANGE_DEG: (f64, f64) = (-90.0, 270.0);

/// Readings per parallel task of the checks (any split gives the same
/// issues, in row order).
const CHECK_CHUNK: usize = 4096;

/// The data tables of a campaign: a CSV file each (`readings.csv`), a
/// pipeline table each (`readings`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Table {
    Readings,
    Targets,
    Gauge,
}

impl Table {
    pub fn name(self) -> &'static str {
        match self {
            Table::Readings => "readings",
            Table::Targets => "targets",
            Table::Gauge => "gauge",
        }
    }
}

/// Where a problem is.
#[derive(Clone, Debug, PartialEq)]
pub enum Place {
    /// A dotted key of campaign.toml (`tracker.sigma_angle_urad`).
    Meta(&'static str),
    /// A table as a whole (it has no rows).
    Table(Table),
    /// A cell: the 0-based row and the column name.
    Cell {
        table: Table,
        row: usize,
        column: &'static str,
    },
}

/// One broken rule.
#[derive(Clone, Debug, PartialEq)]
pub struct Issue {
    pub place: Place,
    pub message: String,
}

impl Issue {
    fn cell(table: Table, row: usize, column: &'static str, message: String) -> Issue {
        Issue {
            place: Place::Cell { table, row, column },
            message,
        }
    }
}

/// As a table row, for campaigns that come from tables rather than files.
impl fmt::Display for Issue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.place {
            Place::Meta(key) => write!(f, "meta `{key}`: {}", self.message),
            Place::Table(t) => write!(f, "table `{}`: {}", t.name(), self.message),
            Place::Cell { table, row, column } => write!(
                f,
                "table `{}`, row {row}, column `{column}`: {}",
                table.name(),
                self.message
            ),
        }
    }
}

impl Campaign {
    /// Every rule of the format the campaign breaks; empty when it is valid.
    pub fn check(&self) -> Vec<Issue> {
        let mut out = Vec::new();
        self.check_meta(&mut out);
        self.check_targets(&mut out);
        self.check_readings(&mut out);
        self.check_gauge(&mut out);
        self.check_stations(&mut out);
        out
    }

    fn check_meta(&self, out: &mut Vec<Issue>) {
        let m = &self.meta;
        let mut issue = |key, message: String| {
            out.push(Issue {
                place: Place::Meta(key),
                message,
            })
        };
        if m.format != 1 {
            issue(
                "format",
                format!(
                    "format {} is not supported: this ltcal reads campaign format 1",
                    m.format
                ),
            );
        }
        if m.name.is_empty() {
            issue("name", "`name` must not be empty".into());
        }
        // An id is matched exactly: "api-tracker3 " is not an id (a
        // reader that trims accepts what a stricter one refuses).
        if m.tracker.model.trim() != m.tracker.model {
            issue(
                "tracker.model",
                format!(
                    "tracker model \"{}\" has spaces around the id: write the id alone, one of {}",
                    m.tracker.model,
                    TrackerModel::expected()
                ),
            );
        } else if TrackerModel::parse(&m.tracker.model).is_none() {
            issue(
                "tracker.model",
                format!(
                    "the readings come from tracker model \"{}\", which ltcal does not know: \
                     it models {} (another kinematic chain would be calibrated wrongly)",
                    m.tracker.model,
                    TrackerModel::expected()
                ),
            );
        }
        let t = &m.tracker;
        for (key, v) in [
            ("tracker.sigma_angle_urad", t.sigma_angle_urad),
            ("tracker.sigma_range_um", t.sigma_range_um),
            ("tracker.sigma_range_ppm", t.sigma_range_ppm),
        ] {
            if let Some(v) = v {
                if let Some(m) = not_finite(v).or_else(|| {
                    (v < 0.0).then(|| format!("a standard deviation cannot be negative, got {v}"))
                }) {
                    issue(key, m);
                }
            }
        }
        if let Some(r) = m.smr_radius_mm {
            if let Some(msg) = not_finite(r)
                .or_else(|| (r <= 0.0).then(|| format!("the SMR radius must be > 0 mm, got {r}")))
            {
                issue("smr.radius_mm", msg);
            }
        }
    }

    fn check_targets(&self, out: &mut Vec<Issue>) {
        let t = Table::Targets;
        let mut seen = HashSet::new();
        for (i, target) in self.targets.iter().enumerate() {
            if target.id.is_empty() {
                out.push(Issue::cell(t, i, "target", "the target id is empty".into()));
            } else if !seen.insert(target.id.as_str()) {
                out.push(Issue::cell(
                    t,
                    i,
                    "target",
                    format!("duplicate target id `{}`: it is listed earlier", target.id),
                ));
            }
            if let Some(p) = target.reference {
                vector_finite(t, i, ["x_mm", "y_mm", "z_mm"], &p, out);
            }
            if let Some(u) = target.u_mm {
                uncertainty(t, i, u, out);
            }
            if let Some(p) = target.aim {
                vector_finite(t, i, ["aim_x_mm", "aim_y_mm", "aim_z_mm"], &p, out);
            }
        }
    }

    fn check_readings(&self, out: &mut Vec<Issue>) {
        let t = Table::Readings;
        if self.readings.is_empty() {
            out.push(Issue {
                place: Place::Table(t),
                message: "the campaign has no readings".into(),
            });
        }
        // Sets only asked whether they hold an id: hashed (a lookup per
        // reading, issue 34), their order never shows.
        let targets: HashSet<&str> = self.targets.iter().map(|t| t.id.as_str()).collect();
        // Each reading's checks are its own: chunks in parallel, their
        // issues then taken in row order (issue 34).
        let chunks: Vec<Vec<Issue>> = self
            .readings
            .par_chunks(CHECK_CHUNK)
            .enumerate()
            .map(|(c, chunk)| {
                let mut out = Vec::new();
                for (k, r) in chunk.iter().enumerate() {
                    check_reading(c * CHECK_CHUNK + k, r, &targets, &mut out);
                }
                out
            })
            .collect();
        out.extend(chunks.into_iter().flatten());
    }

    fn check_gauge(&self, out: &mut Vec<Issue>) {
        let t = Table::Gauge;
        if self.gauge.is_empty() {
            return;
        }
        let targets: HashSet<&str> = self.targets.iter().map(|t| t.id.as_str()).collect();
        let seen: HashSet<&str> = self.readings.iter().map(|r| r.target.as_str()).collect();
        for (i, g) in self.gauge.iter().enumerate() {
            for (column, id) in [("target_a", &g.target_a), ("target_b", &g.target_b)] {
                if id.is_empty() {
                    out.push(Issue::cell(t, i, column, "the target id is empty".into()));
                } else if !targets.contains(id.as_str()) {
                    out.push(Issue::cell(
                        t,
                        i,
                        column,
                        format!("target `{id}` is not in targets.csv"),
                    ));
                }
            }
            if !g.target_a.is_empty() && g.target_a == g.target_b {
                out.push(Issue::cell(
                    t,
                    i,
                    "target_b",
                    format!(
                        "a gauge joins two different reflectors: target_b is target_a ({})",
                        g.target_a
                    ),
                ));
            }
            if let Some(m) = not_finite(g.distance_mm).or_else(|| {
                (g.distance_mm <= 0.0)
                    .then(|| format!("a distance must be > 0, got {}", g.distance_mm))
            }) {
                out.push(Issue::cell(t, i, "distance_mm", m));
            }
            if let Some(u) = g.u_mm {
                uncertainty(t, i, u, out);
            }
            // Without readings no station shares anything: that is reported once.
            let shared = seen.contains(g.target_a.as_str()) || seen.contains(g.target_b.as_str());
            if !shared && !self.readings.is_empty() {
                out.push(Issue::cell(
                    t,
                    i,
                    "target_a",
                    format!(
                        "gauge row {} – {} shares no reflector with any station: no station reads {} or {}",
                        g.target_a, g.target_b, g.target_a, g.target_b
                    ),
                ));
            }
        }
    }

    /// Each station must see at least 3 reflectors not on one line, judged
    /// on the nominal points of its readings in its own frame (its pose is
    /// unknown, and the frame is all the file gives).
    fn check_stations(&self, out: &mut Vec<Issue>) {
        // (Put in row order below: hashed, their order never shows.) Each
        // chunk of readings is gathered on its own, in parallel, and the
        // chunks joined in row order: a station's first row, and each
        // reflector's first reading, are the whole file's (issue 34).
        let chunks: Vec<HashMap<&str, Seen>> = self
            .readings
            .par_chunks(CHECK_CHUNK)
            .enumerate()
            .map(|(c, chunk)| {
                let mut stations: HashMap<&str, Seen> = HashMap::new();
                // A reading without a station id is reported on its own.
                for (k, r) in chunk
                    .iter()
                    .enumerate()
                    .filter(|(_, r)| !r.station.is_empty())
                {
                    let seen = stations.entry(r.station.as_str()).or_insert_with(|| Seen {
                        first_row: c * CHECK_CHUNK + k,
                        points: BTreeMap::new(),
                        all_finite: true,
                    });
                    // A reading's nominal point is finite exactly when its
                    // three values are (products of a finite distance and
                    // sines and cosines), so it is made for the first
                    // reading of a reflector only (issue 34).
                    seen.all_finite &=
                        r.az_deg.is_finite() && r.el_deg.is_finite() && r.d_mm.is_finite();
                    if let btree_map::Entry::Vacant(v) = seen.points.entry(r.target.as_str()) {
                        v.insert(nominal_point(r.reading()));
                    }
                }
                stations
            })
            .collect();
        let mut stations: HashMap<&str, Seen> = HashMap::new();
        for chunk in chunks {
            for (station, later) in chunk {
                match stations.entry(station) {
                    hash_map::Entry::Vacant(v) => {
                        v.insert(later);
                    }
                    hash_map::Entry::Occupied(o) => {
                        let seen = o.into_mut();
                        seen.all_finite &= later.all_finite;
                        for (target, p) in later.points {
                            seen.points.entry(target).or_insert(p);
                        }
                    }
                }
            }
        }
        let mut by_row: Vec<_> = stations.into_iter().collect();
        by_row.sort_by_key(|(_, seen)| seen.first_row);
        for (station, seen) in by_row {
            let (row, points) = (seen.first_row, seen.points);
            let ids: Vec<&str> = points.keys().copied().collect();
            let message = if points.len() < 3 {
                format!(
                    "station {station} cannot be located: it sees {} reflector{} ({}), and it needs at least 3 not on one line",
                    points.len(),
                    if points.len() == 1 { "" } else { "s" },
                    ids.join(", ")
                )
            } else {
                let p: Vec<Vector3<f64>> = points.values().copied().collect();
                // A reading that is not a number is reported on its own and
                // leaves no geometry to judge.
                if !seen.all_finite || !on_one_line(&p, LINE_TOLERANCE_MM) {
                    continue;
                }
                format!(
                    "station {station} cannot be located: the {} reflectors it sees ({}) lie on one line \
                     (within {LINE_TOLERANCE_MM} mm), and it needs at least 3 not on one line",
                    p.len(),
                    ids.join(", ")
                )
            };
            out.push(Issue::cell(Table::Readings, row, "station", message));
        }
    }
}

/// The checks of reading `i` on its own, its issues pushed onto `out`.
fn check_reading(i: usize, r: &CampaignReading, targets: &HashSet<&str>, out: &mut Vec<Issue>) {
    let t = Table::Readings;
    if r.station.is_empty() {
        out.push(Issue::cell(
            t,
            i,
            "station",
            "the station id is empty".into(),
        ));
    }
    if r.target.is_empty() {
        out.push(Issue::cell(t, i, "target", "the target id is empty".into()));
    } else if !targets.contains(r.target.as_str()) {
        out.push(Issue::cell(
            t,
            i,
            "target",
            format!("target `{}` is not in targets.csv", r.target),
        ));
    }
    if let Some(m) = not_finite(r.az_deg) {
        out.push(Issue::cell(t, i, "az_deg", m));
    }
    if let Some(m) = not_finite(r.el_deg).or_else(|| el_out_of_range(r.el_deg)) {
        out.push(Issue::cell(t, i, "el_deg", m));
    }
    if let Some(m) = not_finite(r.d_mm).or_else(|| {
        (r.d_mm <= 0.0).then(|| format!("a distance must be > 0, got d_mm = {}", r.d_mm))
    }) {
        out.push(Issue::cell(t, i, "d_mm", m));
    }
    for (column, v) in [
        ("time_s", r.time_s),
        ("temperature_c", r.temperature_c),
        ("pressure_hpa", r.pressure_hpa),
        ("humidity_pct", r.humidity_pct),
    ] {
        if let Some(m) = v.and_then(not_finite) {
            out.push(Issue::cell(t, i, column, m));
        }
    }
}

/// What one station sees: where it first appears, and the nominal point of
/// the first reading of each reflector, in its own frame.
struct Seen<'a> {
    first_row: usize,
    points: BTreeMap<&'a str, Vector3<f64>>,
    all_finite: bool,
}

/// Whether every point lies within `tol_mm` of the line through the two
/// points farthest apart (all points within `tol_mm` of each other count as
/// on one line: any line through them will do).
fn on_one_line(points: &[Vector3<f64>], tol_mm: f64) -> bool {
    if surely_off_one_line(points, tol_mm) {
        return false;
    }
    let mut far = (0, 0, 0.0);
    for (i, a) in points.iter().enumerate() {
        for (j, b) in points.iter().enumerate().skip(i + 1) {
            let d = (b - a).norm();
            if d > far.2 {
                far = (i, j, d);
            }
        }
    }
    let (a, b, span) = far;
    if span <= tol_mm {
        return true;
    }
    let u = (points[b] - points[a]) / span;
    points.iter().all(|p| {
        let v = p - points[a];
        (v - u * v.dot(&u)).norm() <= tol_mm
    })
}

/// Whether the points are certainly not within `tol_mm` of the line
/// through their farthest pair, found in linear time: the pair search of
/// [`on_one_line`] is quadratic, and a station may see thousands of
/// reflectors. `b` is the point farthest from the first, `c` the point
/// farthest from `b`; with `|bc| > 100·tol`, every point within `tol` of
/// the farthest pair's line is within `4.1·tol` of line `bc` (both `b` and
/// `c` lie within `tol` of it, and every point within `|bc|` of `b`), so a
/// point beyond `5·tol` of line `bc` settles it. Otherwise (nearly on a
/// line, or all close together) the exact test decides.
fn surely_off_one_line(points: &[Vector3<f64>], tol_mm: f64) -> bool {
    let farthest = |from: &Vector3<f64>| {
        points
            .iter()
            .max_by(|p, q| (*p - from).norm().total_cmp(&(*q - from).norm()))
            .copied()
    };
    let Some(b) = points.first().and_then(farthest) else {
        return false;
    };
    let Some(c) = farthest(&b) else {
        return false;
    };
    let span = (c - b).norm();
    if span.partial_cmp(&(100.0 * tol_mm)) != Some(std::cmp::Ordering::Greater) {
        return false;
    }
    let u = (c - b) / span;
    points.iter().any(|p| {
        let v = p - b;
        (v - u * v.dot(&u)).norm() > 5.0 * tol_mm
    })
}

fn not_finite(v: f64) -> Option<String> {
    if v.is_nan() {
        Some("NaN is not a value (leave the cell empty for \"not known\")".into())
    } else if v.is_infinite() {
        Some(format!("{v} is not a finite number"))
    } else {
        None
    }
}

fn el_out_of_range(el: f64) -> Option<String> {
    let (lo, hi) = EL_RANGE_DEG;
    (!(lo..=hi).contains(&el)).then(|| {
        format!(
            "el_deg must lie in [{lo}, {hi}] (front face [−90, 90], back face [90, 270]), got {el}"
        )
    })
}

fn uncertainty(t: Table, row: usize, u: f64, out: &mut Vec<Issue>) {
    if let Some(m) = not_finite(u).or_else(|| {
        (u < 0.0).then(|| format!("a standard uncertainty cannot be negative, got {u}"))
    }) {
        out.push(Issue::cell(t, row, "u_mm", m));
    }
}

fn vector_finite(
    t: Table,
    row: usize,
    columns: [&'static str; 3],
    p: &Vector3<f64>,
    out: &mut Vec<Issue>,
) {
    for (column, v) in columns.into_iter().zip(p.iter()) {
        if let Some(m) = not_finite(*v) {
            out.push(Issue::cell(t, row, column, m));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn v(x: f64, y: f64, z: f64) -> Vector3<f64> {
        Vector3::new(x, y, z)
    }

    /// The readings are checked in chunks in parallel: the issues still
    /// come in row order, and a station first seen in one chunk and read
    /// again in a later one is judged on all its readings, at its first row.
    #[test]
    fn issues_of_readings_checked_in_chunks_come_in_row_order_at_each_stations_first_row() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("examples/campaigns/example-00-none");
        let mut c = crate::campaign::read(&dir).unwrap();
        let base = c.readings.clone();
        c.readings = (0..3 * CHECK_CHUNK)
            .map(|i| base[i % base.len()].clone())
            .collect();
        let (t0, t1) = (c.targets[0].id.clone(), c.targets[1].id.clone());
        for (row, target) in [
            (CHECK_CHUNK + 5, &t0),
            (2 * CHECK_CHUNK + 7, &t1),
            (2 * CHECK_CHUNK + 9, &t0),
        ] {
            c.readings[row].station = "late".into();
            c.readings[row].target = target.clone();
        }
        c.readings[CHECK_CHUNK - 1].el_deg = f64::NAN;
        c.readings[2 * CHECK_CHUNK].target = "nowhere".into();
        let issues = c.check();
        let places: Vec<(usize, &str)> = issues
            .iter()
            .map(|i| match &i.place {
                Place::Cell { row, column, .. } => (*row, *column),
                p => panic!("not a cell: {p:?}"),
            })
            .collect();
        assert_eq!(
            places,
            [
                (CHECK_CHUNK - 1, "el_deg"),
                (2 * CHECK_CHUNK, "target"),
                (CHECK_CHUNK + 5, "station"),
            ]
        );
        assert!(
            issues[2]
                .message
                .contains(&format!("it sees 2 reflectors ({t0}, {t1})")),
            "{}",
            issues[2].message
        );
    }

    #[test]
    fn three_points_off_a_line_are_not_on_one_line() {
        let p = [v(0.0, 0.0, 0.0), v(1000.0, 0.0, 0.0), v(500.0, 300.0, 0.0)];
        assert!(!on_one_line(&p, LINE_TOLERANCE_MM));
    }

    #[test]
    fn points_along_a_line_within_the_tolerance_are_on_one_line() {
        // 0.9 mm off a 6 m line: inside the 1 mm tolerance.
        let p = [
            v(1000.0, 2000.0, 100.0),
            v(4000.0, -1000.0, 400.0),
            v(2500.0, 500.0, 250.9),
            v(7000.0, -4000.0, 700.0),
        ];
        assert!(on_one_line(&p, LINE_TOLERANCE_MM));
        // 1.1 mm off: not.
        let mut q = p;
        q[2].z = 251.1;
        assert!(!on_one_line(&q, LINE_TOLERANCE_MM));
    }

    #[test]
    fn coincident_points_are_on_one_line() {
        let p = [v(5.0, 5.0, 5.0), v(5.0, 5.5, 5.0), v(5.2, 5.0, 5.0)];
        assert!(on_one_line(&p, LINE_TOLERANCE_MM));
    }

    #[test]
    fn the_line_is_judged_from_the_farthest_pair_not_the_first_points() {
        // The first two points are close together, so a line through them
        // points the wrong way; the farthest pair gives the true line.
        let p = [
            v(0.0, 0.0, 0.0),
            v(0.5, 0.5, 0.0),
            v(3000.0, 0.0, 0.0),
            v(6000.0, 0.0, 0.0),
        ];
        assert!(on_one_line(&p, LINE_TOLERANCE_MM));
    }
}
