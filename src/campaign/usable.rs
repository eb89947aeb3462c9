//! What a calibration needs beyond the format: values `campaign-format.md`
//! allows but that break the adjustment's numerics. Found before the
//! adjustment and named by their reading (or key), instead of surfacing as
//! "singular normal matrix" or "non-finite Jacobian" with nothing to fix.
//!
//! They are not [`Campaign::check`]'s rules: such a campaign still reads,
//! converts and exports — only calibrating and diagnosing it refuses.
//! [`super::read_for_calibration`] locates each issue at its
//! `file:line:col`; a campaign built from tables names its table row.

use super::Campaign;
use super::check::{Issue, Place, Table};
use rayon::prelude::*;

/// How close (in |cos el|) to the zenith or nadir a reading may come. At
/// the pole the azimuth turns the beam about itself: the reading's azimuth
/// is not determined by the point, and the adjustment's normal matrix is
/// singular. 1e-6 is 0.2″ from the pole — well inside one reading's noise,
/// so no usable reading is refused.
pub const POLE_COS_EL: f64 = 1e-6;

/// The longest distance reading a calibration takes, mm (10 km: a hundred
/// times a tracker's range); a gauge length may be twice it. Beyond it the range noise and the Jacobian's
/// products overflow (a `d_mm` of 1e15 gave a non-finite Jacobian).
pub const MAX_RANGE_MM: f64 = 1e7;

/// The range of a stated, non-zero σ (µrad, µm, ppm) a calibration can
/// weight by: readings are divided by σ, so 1e-300 overflows the weights.
/// (Zero means noise-free and is weighted by a floor, as before.)
pub const SIGMA_RANGE: (f64, f64) = (1e-6, 1e9);

/// The most stations a calibration or diagnosis takes. Each station's pose
/// is six unknowns of the adjustment's dense part, whose Schur complement
/// is factorised in full (memory and time grow with its square and cube);
/// the diagnosis also tries a range scale and a target shift per station.
/// Users bring 10–30; a campaign of 40 000 stations was accepted before and
/// aborted allocating 500 GB.
pub const MAX_STATIONS: usize = 50;

/// The most reflectors (rows of targets.csv) a calibration or diagnosis
/// takes: networks of hundreds to thousands, with room to spare. The
/// diagnosis tries a shift of each reflector from each station, so its
/// time grows with reflectors × stations.
pub const MAX_REFLECTORS: usize = 20_000;

/// The most gauge lengths a calibration or diagnosis takes. Each reflector
/// a gauge joins is three unknowns of the dense part (like a station's
/// pose), so a gauge of thousands of lengths would make it dense in the
/// reflectors; a calibrated gauge has a handful.
pub const MAX_GAUGE_LENGTHS: usize = 100;

impl Campaign {
    /// The counts beyond ltcal's processing limits ([`MAX_STATIONS`],
    /// [`MAX_REFLECTORS`], [`MAX_GAUGE_LENGTHS`]), each located at its first
    /// row beyond the limit. Linear in the rows: a campaign at the format's
    /// limits is refused in well under a second.
    pub fn count_issues(&self) -> Vec<Issue> {
        let mut out = Vec::new();
        let mut stations = std::collections::HashSet::new();
        let mut last: Option<&str> = None;
        for (i, r) in self.readings.iter().enumerate() {
            // Hashed only where the station changes (see `Campaign::stations`).
            if last == Some(r.station.as_str()) {
                continue;
            }
            last = Some(r.station.as_str());
            if stations.insert(r.station.as_str()) && stations.len() > MAX_STATIONS {
                out.push(Issue {
                    place: Place::Cell {
                        table: Table::Readings,
                        row: i,
                        column: "station",
                    },
                    message: format!(
                        "station {} is station {}: valid per campaign-format.md, but ltcal \
                         calibrates and diagnoses at most {MAX_STATIONS} stations \
                         (campaign::MAX_STATIONS; each station's pose is a block of the \
                         adjustment's dense part): split the campaign",
                        r.station,
                        MAX_STATIONS + 1
                    ),
                });
                break;
            }
        }
        for (table, rows, limit, column, what) in [
            (
                Table::Targets,
                self.targets.len(),
                MAX_REFLECTORS,
                "target",
                "reflectors (campaign::MAX_REFLECTORS; the diagnosis tries a shift of each \
                 reflector from each station)",
            ),
            (
                Table::Gauge,
                self.gauge.len(),
                MAX_GAUGE_LENGTHS,
                "target_a",
                "gauge lengths (campaign::MAX_GAUGE_LENGTHS; each reflector a gauge joins is \
                 a block of the adjustment's dense part)",
            ),
        ] {
            if rows > limit {
                out.push(Issue {
                    place: Place::Cell {
                        table,
                        row: limit,
                        column,
                    },
                    message: format!(
                        "{}.csv has {rows} rows: valid per campaign-format.md, but ltcal \
                         calibrates and diagnoses at most {limit} {what}",
                        table.name()
                    ),
                });
            }
        }
        out
    }

    /// What a diagnosis needs beyond a calibration: a stated noise that is
    /// not zero. The diagnosis tests every residual against the stated
    /// noise, so a noise of 0 (weighted by a floor of 1e-3) makes every
    /// reading a blunder and every effect significant — a verdict of
    /// nonsense (8 blunders and "−72.8 % of the gap removed" on a clean
    /// campaign). A key left out takes the default noise instead.
    pub fn diagnosis_issues(&self) -> Vec<Issue> {
        let t = &self.meta.tracker;
        let zero = |key: &'static str, what: &str| Issue {
            place: Place::Meta(key),
            message: format!(
                "a stated noise of 0 cannot be diagnosed: the diagnosis tests every residual \
                 against the stated noise, and {what} no residual is noise; state the \
                 tracker's noise (1 σ) or leave the key out for the default"
            ),
        };
        let mut out = Vec::new();
        if t.sigma_angle_urad == Some(0.0) {
            out.push(zero(
                "tracker.sigma_angle_urad",
                "with an angular noise of 0",
            ));
        }
        // The range noise is √(σ_um² + (σ_ppm·d)²): zero only when both are.
        let ppm_zero = t.sigma_range_ppm.unwrap_or(0.0) == 0.0;
        if t.sigma_range_um == Some(0.0) && ppm_zero {
            out.push(zero("tracker.sigma_range_um", "with a range noise of 0"));
        }
        out
    }

    /// The values the format allows but a calibration cannot use; empty
    /// when the campaign can be calibrated.
    pub fn calibration_issues(&self) -> Vec<Issue> {
        let mut out = self.count_issues();
        let t = &self.meta.tracker;
        let (lo, hi) = SIGMA_RANGE;
        for (key, v) in [
            ("tracker.sigma_angle_urad", t.sigma_angle_urad),
            ("tracker.sigma_range_um", t.sigma_range_um),
            ("tracker.sigma_range_ppm", t.sigma_range_ppm),
        ] {
            if let Some(v) = v.filter(|&v| v != 0.0 && !(lo..=hi).contains(&v)) {
                out.push(Issue {
                    place: Place::Meta(key),
                    message: format!(
                        "{v:e} is valid per campaign-format.md but unusable for calibration: \
                         a stated noise must be 0 or lie in [{lo:e}, {hi:e}], or the weights \
                         of the adjustment overflow"
                    ),
                });
            }
        }
        // Each reading's checks on their own (a cosine each: milliseconds
        // at 24 000 readings on one core, issue 34), its issues in order.
        let per_reading = self
            .readings
            .par_iter()
            .enumerate()
            .with_min_len(1024)
            .flat_map_iter(|(i, r)| {
                let mut out = Vec::new();
                let cell = |column: &'static str, message: String| Issue {
                    place: Place::Cell {
                        table: Table::Readings,
                        row: i,
                        column,
                    },
                    message,
                };
                if r.el_deg.to_radians().cos().abs() < POLE_COS_EL {
                    out.push(cell(
                        "el_deg",
                        format!(
                            "el_deg = {} points at the zenith or nadir: valid per \
                             campaign-format.md but unusable for calibration (the azimuth of a \
                             reading at the pole is undetermined, the adjustment singular); \
                             remove the reading of {} from {}",
                            r.el_deg, r.target, r.station
                        ),
                    ));
                }
                if r.d_mm > MAX_RANGE_MM {
                    out.push(cell(
                        "d_mm",
                        format!(
                            "d_mm = {:e} is valid per campaign-format.md but unusable for \
                             calibration: ltcal calibrates distances up to {MAX_RANGE_MM:e} mm",
                            r.d_mm
                        ),
                    ));
                }
                out
            });
        out.par_extend(per_reading);
        // Both ends are seen from stations within MAX_RANGE_MM, so no
        // usable gauge is longer than twice that (a fuzzed 1e23 mm one left
        // the normal matrix singular).
        for (i, g) in self.gauge.iter().enumerate() {
            if g.distance_mm > 2.0 * MAX_RANGE_MM {
                out.push(Issue {
                    place: Place::Cell {
                        table: Table::Gauge,
                        row: i,
                        column: "distance_mm",
                    },
                    message: format!(
                        "distance_mm = {:e} is valid per campaign-format.md but unusable for \
                         calibration: its reflectors are seen from at most {MAX_RANGE_MM:e} mm, \
                         so a gauge is at most {:e} mm",
                        g.distance_mm,
                        2.0 * MAX_RANGE_MM
                    ),
                });
            }
        }
        out
    }
}
