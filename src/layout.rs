//! Reflector layouts and tracker stations of the paper's experiments, and
//! variations on them for layout design.
//!
//! * `corner` — Section 7 (NOTES item 12): reflectors in a room corner in
//!   three levels, 8 on the floor (lowest tilt), 8 on the walls at tracker
//!   height (zero tilt), 8 high up (highest tilt), spread over the pan angle
//!   (90°) seen from the stations; 5 stations on an arc in front of the corner.
//! * `cmm-table` — Section 5.2: 17 reflectors on a CMM table on stands of
//!   several heights, all with reference coordinates; 5 stations around it.
//! * `hall` — a larger hall: reflectors on the walls of a 20 m × 14 m hall.
//! * `network` — a large-scale metrology network (an assembly hall, 60 m ×
//!   30 m × 12 m): reflectors on the walls at four heights, on the floor, on
//!   the ceiling and on free-standing monuments, `per_level` per wall level
//!   (5.5 × `per_level` in all: 1 100 at the most), and stations on a grid
//!   over the floor — the size of network users bring from halls and
//!   tunnels, and the benches' series.
//!
//! The campaign frame has z up; the corner is at the origin with its walls
//! in the planes x = 0 and y = 0 and the floor at z = 0.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Which layout.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Kind {
    Corner,
    CmmTable,
    Hall,
    Network,
}

/// A reflector level of the corner layout.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Level {
    Floor,
    Wall,
    High,
}

/// The shape of a layout; every field has the paper's value by default.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Spec {
    pub kind: Kind,
    /// Number of tracker stations.
    #[serde(default = "five")]
    pub stations: usize,
    /// Corner: the pan angle the reflectors span, seen from the stations.
    #[serde(default = "ninety")]
    pub pan_deg: f64,
    /// Corner: which levels carry reflectors.
    #[serde(default = "all_levels")]
    pub levels: Vec<Level>,
    /// Corner and hall: reflectors per level.
    #[serde(default = "eight")]
    pub per_level: usize,
    /// Corner: distance from the corner to the stations (mm).
    #[serde(default = "six_m")]
    pub distance_mm: f64,
    /// Tracker height above the floor (mm).
    #[serde(default = "tracker_height")]
    pub tracker_height_mm: f64,
}

fn five() -> usize {
    5
}
fn ninety() -> f64 {
    90.0
}
fn eight() -> usize {
    8
}
fn six_m() -> f64 {
    6000.0
}
fn tracker_height() -> f64 {
    1500.0
}
fn all_levels() -> Vec<Level> {
    vec![Level::Floor, Level::Wall, Level::High]
}

impl Spec {
    pub fn new(kind: Kind) -> Spec {
        Spec {
            kind,
            stations: five(),
            pan_deg: ninety(),
            levels: all_levels(),
            per_level: eight(),
            distance_mm: six_m(),
            tracker_height_mm: tracker_height(),
        }
    }

    /// Settings that cannot work, as `(field, message)`.
    pub fn check(&self) -> Vec<(&'static str, String)> {
        let mut out = Vec::new();
        if !(2..=50).contains(&self.stations) {
            out.push((
                "stations",
                format!("`stations` must be 2 … 50, got {}", self.stations),
            ));
        }
        if !(self.pan_deg > 5.0 && self.pan_deg <= 120.0) {
            out.push((
                "pan_deg",
                format!("`pan_deg` must lie in (5, 120], got {}", self.pan_deg),
            ));
        }
        if self.levels.is_empty() {
            out.push((
                "levels",
                "`levels` needs at least one of floor, wall, high".into(),
            ));
        }
        if !(1..=200).contains(&self.per_level) {
            out.push((
                "per_level",
                format!("`per_level` must be 1 … 200, got {}", self.per_level),
            ));
        }
        if !(self.distance_mm >= 1000.0 && self.distance_mm <= 100_000.0) {
            out.push((
                "distance_mm",
                format!(
                    "`distance_mm` must lie in [1000, 100000], got {}",
                    self.distance_mm
                ),
            ));
        }
        if !(self.tracker_height_mm > 0.0 && self.tracker_height_mm < 3000.0) {
            out.push((
                "tracker_height_mm",
                "`tracker_height_mm` must lie in (0, 3000)".into(),
            ));
        }
        out
    }
}

/// Reflectors and station positions.
#[derive(Clone, Debug)]
pub struct Layout {
    /// `(id, centre)`, mm.
    pub targets: Vec<(String, Vector3<f64>)>,
    /// `(id, tracker origin)`, mm.
    pub stations: Vec<(String, Vector3<f64>)>,
    /// The four reflectors of the gauge (Eq. 15), part of the mesh.
    pub gauge: Vec<String>,
    /// Whether the reflectors' reference coordinates are known (a CMM).
    pub references: bool,
}

/// `T01 … T24` for reflectors; `S1 … S5` for stations (as the example
/// campaigns name them); reflector ids as wide as the largest.
fn ids(prefix: &str, n: usize) -> Vec<String> {
    let w = match (prefix, n) {
        ("S", _) => 1,
        _ => n.to_string().len().max(2),
    };
    (1..=n).map(|i| format!("{prefix}{i:0w$}")).collect()
}

pub fn build(spec: &Spec) -> Layout {
    match spec.kind {
        Kind::Corner => corner(spec),
        Kind::CmmTable => cmm_table(spec),
        Kind::Hall => hall(spec),
        Kind::Network => network(spec),
    }
}

/// Evenly spaced values over `[a, b]` (the midpoint when n = 1).
fn spread(a: f64, b: f64, n: usize) -> Vec<f64> {
    if n == 1 {
        return vec![(a + b) / 2.0];
    }
    (0..n)
        .map(|i| a + (b - a) * i as f64 / (n - 1) as f64)
        .collect()
}

/// Stations on an arc about `centre` (angles in the campaign frame).
fn arc(
    centre: Vector3<f64>,
    radius: f64,
    mid: f64,
    span: f64,
    n: usize,
    z: f64,
) -> Vec<(String, Vector3<f64>)> {
    ids("S", n)
        .into_iter()
        .zip(spread(mid - span / 2.0, mid + span / 2.0, n))
        .enumerate()
        .map(|(i, (id, a))| {
            // Stagger the radius so that the stations are not on one circle.
            let r = radius * (1.0 + 0.06 * ((i % 3) as f64 - 1.0));
            (
                id,
                Vector3::new(centre.x + r * a.cos(), centre.y + r * a.sin(), z),
            )
        })
        .collect()
}

fn corner(spec: &Spec) -> Layout {
    let h = spec.tracker_height_mm;
    let s = spec.distance_mm / std::f64::consts::SQRT_2;
    let c = Vector3::new(s, s, h);
    let pan = spec.pan_deg.to_radians();
    let mut pts = Vec::new();
    for &level in &spec.levels {
        let az = spread(PI + 0.05 * pan, PI + 0.95 * pan, spec.per_level)
            .into_iter()
            .map(|a| a - (pan - PI / 2.0) / 2.0);
        for (k, a) in az.enumerate() {
            let dir = Vector3::new(a.cos(), a.sin(), 0.0);
            // Where the horizontal ray from the centroid meets a wall.
            let t = [(-c.x / dir.x), (-c.y / dir.y)]
                .into_iter()
                .filter(|t| t.is_finite() && *t > 0.0)
                .fold(f64::INFINITY, f64::min);
            let wall = c + dir * t;
            let jitter = 150.0 * ((k % 3) as f64 - 1.0);
            let p = match level {
                Level::Wall => Vector3::new(wall.x, wall.y, h + jitter),
                Level::High => Vector3::new(wall.x, wall.y, h + 2200.0 + jitter),
                Level::Floor => {
                    let f = c + dir * (t * (0.45 + 0.05 * (k % 3) as f64));
                    Vector3::new(f.x, f.y, 0.0)
                }
            };
            pts.push(p);
        }
    }
    let targets: Vec<(String, Vector3<f64>)> = ids("T", pts.len()).into_iter().zip(pts).collect();
    let stations = arc(
        Vector3::zeros(),
        spec.distance_mm,
        PI / 4.0,
        (40f64).to_radians(),
        spec.stations,
        h,
    );
    let gauge = gauge_of(&targets);
    Layout {
        targets,
        stations,
        gauge,
        references: false,
    }
}

fn cmm_table(spec: &Spec) -> Layout {
    // A 4 × 4 grid on the table (1.8 m × 1.2 m) on stands of four heights,
    // and one reflector high in the middle: 17.
    let mut pts = Vec::new();
    for (i, x) in spread(0.0, 1800.0, 4).into_iter().enumerate() {
        for (j, y) in spread(0.0, 1200.0, 4).into_iter().enumerate() {
            pts.push(Vector3::new(x, y, 150.0 * ((i + j) % 4) as f64));
        }
    }
    pts.push(Vector3::new(900.0, 600.0, 600.0));
    let targets: Vec<(String, Vector3<f64>)> = ids("T", pts.len()).into_iter().zip(pts).collect();
    // The SMRs face the stations' centroid and accept ±30°: the stations
    // stand on a 50° arc in front of the table, the tracker head 0.7 m
    // above its surface.
    let centre = Vector3::new(900.0, 600.0, 0.0);
    let stations = arc(
        centre,
        3500.0,
        -PI / 2.0,
        50f64.to_radians(),
        spec.stations,
        spec.tracker_height_mm - 800.0,
    );
    let gauge = gauge_of(&targets);
    Layout {
        targets,
        stations,
        gauge,
        references: true,
    }
}

fn hall(spec: &Spec) -> Layout {
    let (lx, ly) = (20_000.0, 14_000.0);
    let heights = [500.0, spec.tracker_height_mm, 4500.0];
    let mut pts = Vec::new();
    for (l, z) in heights.iter().enumerate() {
        for k in 0..spec.per_level {
            // Walk the perimeter, offset per level so that levels interleave.
            let f = (k as f64 + 0.5 + l as f64 / 3.0) / spec.per_level as f64;
            pts.push(on_walls(f * 2.0 * (lx + ly), lx, ly, *z));
        }
    }
    let targets: Vec<(String, Vector3<f64>)> = ids("T", pts.len()).into_iter().zip(pts).collect();
    let centre = Vector3::new(lx / 2.0, ly / 2.0, 0.0);
    let stations = arc(
        centre,
        3000.0,
        0.0,
        2.0 * PI * (1.0 - 1.0 / spec.stations as f64),
        spec.stations,
        spec.tracker_height_mm,
    );
    let gauge = gauge_of(&targets);
    Layout {
        targets,
        stations,
        gauge,
        references: false,
    }
}

/// The point at arc length `s` along the walls of an `lx × ly` hall
/// (walking from the origin along x first), at height `z`.
fn on_walls(s: f64, lx: f64, ly: f64, z: f64) -> Vector3<f64> {
    if s < lx {
        Vector3::new(s, 0.0, z)
    } else if s < lx + ly {
        Vector3::new(lx, s - lx, z)
    } else if s < 2.0 * lx + ly {
        Vector3::new(2.0 * lx + ly - s, ly, z)
    } else {
        Vector3::new(0.0, 2.0 * (lx + ly) - s, z)
    }
}

/// The `network` layout (see the module doc). Walls at four heights, then
/// floor, ceiling and monuments, each spread evenly; stations on two or
/// three rows along the hall.
fn network(spec: &Spec) -> Layout {
    let (lx, ly, lz) = (60_000.0, 30_000.0, 12_000.0);
    let n = spec.per_level;
    let mut pts = Vec::new();
    // Walls: walk the perimeter, levels interleaved.
    let perimeter = 2.0 * (lx + ly);
    for (l, z) in [800.0, spec.tracker_height_mm, 5000.0, 9000.0]
        .iter()
        .enumerate()
    {
        for k in 0..n {
            let s = (k as f64 + 0.5 + l as f64 / 4.0) / n as f64 * perimeter;
            pts.push(on_walls(s, lx, ly, *z));
        }
    }
    // Floor and ceiling: a grid inset from the walls, n / 2 each.
    let grid = |count: usize, z: f64, pts: &mut Vec<Vector3<f64>>| {
        let cols = ((count as f64 * 2.0).sqrt().ceil() as usize).max(1);
        let rows = count.div_ceil(cols).max(1);
        for k in 0..count {
            let (i, j) = (k % cols, k / cols);
            pts.push(Vector3::new(
                lx * (0.1 + 0.8 * (i as f64 + 0.5) / cols as f64),
                ly * (0.1 + 0.8 * (j as f64 + 0.5) / rows as f64),
                z,
            ));
        }
    };
    grid(n / 2, 0.0, &mut pts);
    grid(n / 2, lz, &mut pts);
    // Monuments: pillars with five reflectors each, 0.5 … 4.5 m high.
    let monuments = (n / 2).div_ceil(5);
    for k in 0..n / 2 {
        let m = k / 5;
        let a = 2.0 * PI * (m as f64 + 0.5) / monuments.max(1) as f64;
        let base = Vector3::new(
            lx / 2.0 + 0.3 * lx * a.cos(),
            ly / 2.0 + 0.3 * ly * a.sin(),
            0.0,
        );
        pts.push(base + Vector3::new(0.0, 0.0, 500.0 + 1000.0 * (k % 5) as f64));
    }
    let targets: Vec<(String, Vector3<f64>)> = ids("T", pts.len()).into_iter().zip(pts).collect();
    // Stations: rows along the hall, staggered so that no three are on a line.
    let rows = if spec.stations >= 12 { 3 } else { 2 };
    let per_row = spec.stations.div_ceil(rows);
    let stations = ids("S", spec.stations)
        .into_iter()
        .enumerate()
        .map(|(k, id)| {
            let (row, i) = (k / per_row, k % per_row);
            let x = lx * (0.15 + 0.7 * (i as f64 + 0.5) / per_row as f64);
            let y =
                ly * (0.3 + 0.4 * row as f64 / (rows - 1) as f64) + 700.0 * ((k % 3) as f64 - 1.0);
            (id, Vector3::new(x, y, spec.tracker_height_mm))
        })
        .collect();
    let gauge = gauge_of(&targets);
    Layout {
        targets,
        stations,
        gauge,
        references: false,
    }
}

/// Four reflectors spread over the layout: the first, and then the ones
/// farthest from those already chosen — a gauge that spans the volume.
fn gauge_of(targets: &[(String, Vector3<f64>)]) -> Vec<String> {
    let mut chosen = vec![0usize];
    while chosen.len() < 4.min(targets.len()) {
        let next = (0..targets.len())
            .filter(|i| !chosen.contains(i))
            .max_by(|&a, &b| {
                let da = chosen
                    .iter()
                    .map(|&c| (targets[a].1 - targets[c].1).norm())
                    .fold(f64::INFINITY, f64::min);
                let db = chosen
                    .iter()
                    .map(|&c| (targets[b].1 - targets[c].1).norm())
                    .fold(f64::INFINITY, f64::min);
                da.total_cmp(&db)
            })
            .expect("targets left");
        chosen.push(next);
    }
    chosen.sort();
    chosen.into_iter().map(|i| targets[i].0.clone()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_layouts_have_the_paper_counts() {
        let c = build(&Spec::new(Kind::Corner));
        assert_eq!(
            (c.targets.len(), c.stations.len(), c.gauge.len()),
            (24, 5, 4)
        );
        let t = build(&Spec::new(Kind::CmmTable));
        assert_eq!((t.targets.len(), t.stations.len()), (17, 5));
        assert!(t.references);
        // 136 reflector pairs on the CMM table (Section 5.2).
        assert_eq!(t.targets.len() * (t.targets.len() - 1) / 2, 136);
    }

    #[test]
    fn corner_levels_and_pan() {
        let c = build(&Spec::new(Kind::Corner));
        let z: Vec<f64> = c.targets.iter().map(|t| t.1.z).collect();
        assert_eq!(z.iter().filter(|&&z| z == 0.0).count(), 8);
        assert_eq!(
            z.iter().filter(|&&z| (z - 1500.0).abs() <= 150.0).count(),
            8
        );
        assert_eq!(z.iter().filter(|&&z| z > 3000.0).count(), 8);
        // Seen from the stations' centroid the reflectors span ≈ 90° of pan.
        let centroid: Vector3<f64> = c.stations.iter().map(|s| s.1).sum::<Vector3<f64>>() / 5.0;
        let az: Vec<f64> = c
            .targets
            .iter()
            .map(|t| {
                (t.1.y - centroid.y)
                    .atan2(t.1.x - centroid.x)
                    .rem_euclid(2.0 * PI)
                    .to_degrees()
            })
            .collect();
        let span = az.iter().cloned().fold(f64::MIN, f64::max)
            - az.iter().cloned().fold(f64::MAX, f64::min);
        assert!((75.0..=100.0).contains(&span), "pan {span}");
    }
}
