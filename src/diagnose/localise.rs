//! Where the residual the explanation set leaves lies, as a number a
//! researcher acts on.
//!
//! Why not binned means of the residuals ([`super::factors`]): after the
//! adjustment, the station poses and reflector positions have absorbed
//! whatever part of a structure resembles them, and a periodic pattern
//! averages out within bins — binned residual means point at the right
//! factor in a minority of campaigns. Here each factor's *basis* (smooth
//! or periodic functions of the factor, on the reading coordinate or on
//! the station pose) enters the adjustment as extra columns beside the
//! explanation set's members, and its Δχ² is the score test against that
//! augmented model ([`super::linear::LinearModel::fit`]: the columns
//! projected off everything the adjustment can absorb). The test is an F
//! test of the basis's Δχ² per column against the residual variance that
//! is left (so a stated noise too small does not make every basis
//! significant), Bonferroni-corrected over every factor and alternative
//! tried; a residual at rounding level (χ² per degree of freedom below
//! 1e-6) is never structure.
//!
//! What each factor tries:
//!
//! | factor | basis |
//! |---|---|
//! | `range` | a piecewise-linear function (8 knots) in d on each coordinate; sine and cosine of `2π·d/P` on d for periods P from 0.2 m to 5 m (the best period counted as alternatives) |
//! | `az`, `el` | a Fourier series in az (orders 1–4) on each coordinate, and a tilt of the standing axis as such a series (on az and el at once) / a piecewise-linear function (8 knots) in el, on each coordinate |
//! | `time` | a piecewise-linear function (8 knots) in `time_s` on each coordinate, and a growth of the reflector field about its centroid |
//! | `station × time` | a step of one station's pose (translation, rotation) and of its range after a time, at times on a grid (station and time counted as alternatives) |
//! | `station`, `reflector`, `face` | a range offset per station / per reflector, a face-2 offset on each coordinate |
//! | `incidence angle`, `temperature` | a piecewise-linear function (8 knots) on d |
//!
//! Each factor is reported with its best basis: its share of what is left
//! (Δχ² over the set's χ²), its p-value, the held-out gap a smooth function
//! of that factor would remove, and its fitted shape as a table.

/// The structure left along one factor.
#[derive(Clone, Debug)]
pub struct Localised {
    /// `range`, `az`, `el`, `time`, `station × time`, `station`,
    /// `reflector`, `face`, `incidence angle`, `temperature`.
    pub factor: &'static str,
    /// The best basis of the factor, in words (`periodic in d, period
    /// 812 mm`, `step of S3's pose after 1 840 s`, …).
    pub basis: String,
    /// Columns of that basis.
    pub columns: usize,
    /// Alternatives the basis was chosen from (counted in the correction).
    pub alternatives: usize,
    /// Its Δχ² against the augmented model.
    pub delta_chi2: f64,
    /// Δχ² as a share of the χ² the set leaves.
    pub share: f64,
    /// F statistic and p-value (before and after the correction).
    pub f: f64,
    pub p: f64,
    pub p_adjusted: f64,
    pub significant: bool,
    /// Held-out gap over the noise floor the basis removes, %.
    pub gap_removed_pct: f64,
    /// The fitted shape, its points along [`Localised::shape_x`], its
    /// values in [`Localised::shape_unit`].
    pub shape: Vec<ShapePoint>,
    pub shape_x: String,
    pub shape_unit: String,
    /// The fitted basis as a hypothesis file's entry (TOML), to edit, name
    /// and test on the next campaign with `--hypotheses`; `None` for a
    /// basis the expression language does not state.
    pub hypothesis: Option<String>,
}

use super::candidates::{ReadingInfo, put_point};
use super::f_test;
use super::linear::{LinearModel, Signature};
use nalgebra::Vector3;
use rayon::prelude::*;

/// Knots of a smooth basis (piecewise-linear hats: their coefficients are
/// the function's values at the knots, which is the shape reported).
const KNOTS: usize = 8;
/// Periods tried for a periodic function of the range, log-spaced (mm).
const PERIODS: usize = 40;
const PERIOD_MIN_MM: f64 = 200.0;
const PERIOD_MAX_MM: f64 = 5000.0;
/// Candidate times of a step per station: between every two readings up
/// to this many, else at as many quantiles (a step at the wrong time
/// leaves the readings between as false blunders).
const STEP_TIMES: usize = 24;
/// Per-reflector offsets are tried up to this many reflectors (beyond it
/// the basis costs more than the rest of the diagnosis).
const MAX_REFLECTOR_OFFSETS: usize = 400;
/// χ² per degree of freedom below which a residual is rounding, not
/// structure.
const ROUNDING_CHI2_PER_DOF: f64 = 1e-6;

/// One point of a fitted shape.
#[derive(Clone, Debug)]
pub struct ShapePoint {
    /// Where (`d = 2 400 mm`, `sin 2·az`, `x after 1 840 s`, a station id).
    pub at: String,
    /// The same as a number where it is one (the knot), else its index.
    pub x: f64,
    pub value: f64,
    pub u: f64,
}

const COMPONENT: [&str; 3] = ["az", "el", "d"];
const COMPONENT_UNIT: [&str; 3] = ["µrad", "µrad", "µm"];
/// A reading coordinate's change per unit of a column (µrad or µm).
const PER_UNIT: [f64; 3] = [1e-6, 1e-6, 1e-3];

/// How a basis's coefficients read as a shape.
#[derive(Clone)]
enum Shape {
    /// Values at the knots.
    Knots { x: Vec<f64>, x_name: &'static str },
    /// `a·sin(2π·d/P) + b·cos(2π·d/P)`, sampled over one period.
    Periodic { period_mm: f64 },
    /// One value per column, named.
    Labels(Vec<String>),
}

/// How a basis is written as a hypothesis ([`crate::hypothesis`]), so
/// that a structure found here can be named, edited and tested on the next
/// campaign.
#[derive(Clone)]
enum Template {
    /// Piecewise-linear in `var` (a hypothesis expression of the
    /// covariates, in the knots' unit) on coordinate `comp`.
    Smooth { var: &'static str, comp: usize },
    /// `a·sin(2π·d/P) + b·cos(2π·d/P)` on d.
    Periodic,
    /// A Fourier series of orders 1–4 in az on coordinate `comp`.
    Fourier { comp: usize },
    /// An offset on d per station or reflector (`scope`).
    Offsets { scope: &'static str },
    /// An offset of face 2 on coordinate `comp`.
    Face { comp: usize },
    /// A step of a station's origin and range `t0_s` after its first reading.
    Step { station: String, t0_s: f64 },
    /// Not written (the field's growth: a shape the expression language
    /// states only clumsily).
    None,
}

/// One basis of a factor.
#[derive(Clone)]
struct Basis {
    factor: &'static str,
    what: String,
    columns: Signature,
    shape: Shape,
    unit: &'static str,
    template: Template,
}

/// Evenly spaced knots over the values present.
struct Hats {
    knots: Vec<f64>,
    lo: f64,
    h: f64,
}

impl Hats {
    fn over(values: &[Option<f64>]) -> Option<Hats> {
        let (lo, hi) = values
            .iter()
            .flatten()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
                (l.min(v), h.max(v))
            });
        let span = hi - lo;
        if !span.is_finite() || span <= 1e-9 * hi.abs().max(1.0) {
            return None;
        }
        let h = span / (KNOTS - 1) as f64;
        let knots = (0..KNOTS).map(|k| lo + h * k as f64).collect();
        Some(Hats { knots, lo, h })
    }

    /// A value's weights on the knots (at most two non-zero).
    fn weights(&self, v: f64) -> [(usize, f64); 2] {
        let f = ((v - self.lo) / self.h).clamp(0.0, (KNOTS - 1) as f64);
        let k = (f.floor() as usize).min(KNOTS - 2);
        let t = f - k as f64;
        [(k, 1.0 - t), (k + 1, t)]
    }
}

/// A smooth function of `values` on reading coordinate `comp`.
fn smooth(
    infos: &[ReadingInfo],
    values: &[Option<f64>],
    comp: usize,
    factor: &'static str,
    (x_name, var): (&'static str, &'static str),
) -> Option<Basis> {
    let hats = Hats::over(values)?;
    let mut c = Signature::new(KNOTS);
    for (i, (r, v)) in infos.iter().zip(values).enumerate() {
        let Some(v) = v else { continue };
        for (k, w) in hats.weights(*v) {
            c.add(i, comp, k, w * PER_UNIT[comp] / r.sigma[comp]);
        }
    }
    Some(Basis {
        factor,
        what: format!("a smooth function of {x_name} on {}", COMPONENT[comp]),
        columns: c,
        shape: Shape::Knots {
            x: hats.knots,
            x_name,
        },
        unit: COMPONENT_UNIT[comp],
        template: Template::Smooth { var, comp },
    })
}

/// Every basis of every factor the readings allow.
fn bases(infos: &[ReadingInfo], stations: &[String], targets: &[String]) -> Vec<Basis> {
    let mut out = Vec::new();
    let of = |f: &dyn Fn(&ReadingInfo) -> Option<f64>| -> Vec<Option<f64>> {
        infos.iter().map(f).collect()
    };
    let d = of(&|r| Some(r.d));
    let el = of(&|r| Some(r.el.to_degrees()));
    let time = of(&|r| r.time_s);
    // Each basis is built on its own (a pass over every reading): the
    // families with many in parallel, collected in their order — the same
    // bases, in the same order, as one after another (which was a thread's
    // work while the other waited, before the ~450 fits).
    let smooths: Vec<Option<Basis>> = (0..9)
        .into_par_iter()
        .map(|n| match n % 3 {
            0 => smooth(infos, &d, n / 3, "range", ("d (mm)", "d")),
            1 => smooth(infos, &el, n / 3, "el", ("el (°)", "el*180/PI")),
            _ => smooth(infos, &time, n / 3, "time", ("time_s (s)", "time_s")),
        })
        .collect();
    out.extend(smooths.into_iter().flatten());
    // range: a cyclic error of the distance meter, whatever its period.
    out.par_extend(
        (0..PERIODS)
            .into_par_iter()
            .map(|p| periodic(infos, period_of(p as f64))),
    );
    // az: a Fourier series (the tracker turns full circles).
    for comp in 0..3 {
        let mut c = Signature::new(8);
        for (i, r) in infos.iter().enumerate() {
            for order in 1..=4 {
                let k = order as f64 * r.az;
                let col = 2 * (order - 1);
                c.add(i, comp, col, k.sin() * PER_UNIT[comp] / r.sigma[comp]);
                c.add(i, comp, col + 1, k.cos() * PER_UNIT[comp] / r.sigma[comp]);
            }
        }
        let labels = (1..=4)
            .flat_map(|o| [format!("sin {o}·az"), format!("cos {o}·az")])
            .collect();
        out.push(Basis {
            factor: "az",
            what: format!("a Fourier series in az (orders 1–4) on {}", COMPONENT[comp]),
            columns: c,
            shape: Shape::Labels(labels),
            unit: COMPONENT_UNIT[comp],
            template: Template::Fourier { comp },
        });
    }
    // az: the standing axis tilting as it turns (a worn bearing), tilts
    // `tx`, `ty` each a Fourier series in az. A tilt ω = (tx, ty, 0) of
    // the station frame moves a direction u by ω × u: the elevation by
    // `tx·sin az − ty·cos az`, the azimuth by `−tan el·(tx·cos az + ty·sin
    // az)` — on both angles at once, which one series per coordinate
    // cannot fit, and whose unfitted rest the w-tests took for blunders.
    {
        let mut c = Signature::new(16);
        for (i, r) in infos.iter().enumerate() {
            let (sa, ca, te) = (r.az.sin(), r.az.cos(), r.el.tan());
            let (w_az, w_el) = (PER_UNIT[0] / r.sigma[0], PER_UNIT[1] / r.sigma[1]);
            for order in 1..=4 {
                let k = order as f64 * r.az;
                for (h, f) in [k.sin(), k.cos()].into_iter().enumerate() {
                    let col = 4 * (order - 1) + 2 * h;
                    c.add(i, 0, col, -te * ca * f * w_az);
                    c.add(i, 1, col, sa * f * w_el);
                    c.add(i, 0, col + 1, -te * sa * f * w_az);
                    c.add(i, 1, col + 1, -ca * f * w_el);
                }
            }
        }
        let labels = (1..=4)
            .flat_map(|o| {
                [
                    format!("tx sin {o}·az"),
                    format!("ty sin {o}·az"),
                    format!("tx cos {o}·az"),
                    format!("ty cos {o}·az"),
                ]
            })
            .collect();
        out.push(Basis {
            factor: "az",
            what: "a tilt of the standing axis, a Fourier series in az (orders 1–4)".into(),
            columns: c,
            shape: Shape::Labels(labels),
            unit: "µrad",
            template: Template::None,
        });
    }
    // time: the reflectors' field growing about its centroid (a part
    // warming), `s = (x − c)·g(t)` in ppm.
    if let Some(hats) = Hats::over(&time) {
        let centroid =
            infos.iter().map(|r| r.point).sum::<Vector3<f64>>() / infos.len().max(1) as f64;
        let mut c = Signature::new(KNOTS);
        for (i, (r, t)) in infos.iter().zip(&time).enumerate() {
            let Some(t) = t else { continue };
            for (k, w) in hats.weights(*t) {
                put_point(&mut c, i, r, k, (r.point - centroid) * (1e-6 * w));
            }
        }
        out.push(Basis {
            factor: "time",
            what: "the reflectors' field growing about its centroid with time".into(),
            columns: c,
            shape: Shape::Knots {
                x: hats.knots,
                x_name: "time_s (s)",
            },
            unit: "ppm",
            template: Template::None,
        });
    }
    out.extend(station_steps(infos, stations));
    // station: a range offset per station; reflector: one per reflector
    // (two kinds of SMR).
    if stations.len() > 1 {
        out.push(offsets(infos, stations, |r| r.station, "station"));
    }
    if targets.len() > 1 && targets.len() <= MAX_REFLECTOR_OFFSETS {
        out.push(offsets(infos, targets, |r| r.target, "reflector"));
    }
    // face: an offset of the back face's readings.
    if infos.iter().any(|r| r.face == 2.0) && infos.iter().any(|r| r.face == 1.0) {
        for comp in 0..3 {
            let mut c = Signature::new(1);
            for (i, r) in infos.iter().enumerate().filter(|(_, r)| r.face == 2.0) {
                c.add(i, comp, 0, PER_UNIT[comp] / r.sigma[comp]);
            }
            out.push(Basis {
                factor: "face",
                what: format!("an offset of face 2 on {}", COMPONENT[comp]),
                columns: c,
                shape: Shape::Labels(vec!["face 2".into()]),
                unit: COMPONENT_UNIT[comp],
                template: Template::Face { comp },
            });
        }
    }
    let incidence = of(&|r| r.incidence.map(|a| a.alpha.to_degrees()));
    out.extend(smooth(
        infos,
        &incidence,
        2,
        "incidence angle",
        ("α (°)", "alpha*180/PI"),
    ));
    let temperature = of(&|r| r.temperature_c);
    out.extend(smooth(
        infos,
        &temperature,
        2,
        "temperature",
        ("temperature_c (°C)", "temperature_c"),
    ));
    out
}

/// The `p`-th period of the log-spaced grid (fractional `p` between).
fn period_of(p: f64) -> f64 {
    PERIOD_MIN_MM * (PERIOD_MAX_MM / PERIOD_MIN_MM).powf(p / (PERIODS - 1) as f64)
}

/// A cyclic error of the distance meter of period `period_mm`.
fn periodic(infos: &[ReadingInfo], period_mm: f64) -> Basis {
    let mut c = Signature::new(2);
    for (i, r) in infos.iter().enumerate() {
        let phase = 2.0 * std::f64::consts::PI * r.d / period_mm;
        c.add(i, 2, 0, 1e-3 * phase.sin() / r.sigma.z);
        c.add(i, 2, 1, 1e-3 * phase.cos() / r.sigma.z);
    }
    Basis {
        factor: "range",
        what: format!("periodic in d, period {period_mm:.0} mm"),
        columns: c,
        shape: Shape::Periodic { period_mm },
        unit: "µm",
        template: Template::Periodic,
    }
}

/// The grid's best period refined between its neighbours: over a few
/// metres of range a period 4 % off (half a grid step) loses the phase.
fn refine_period(
    lm: &LinearModel,
    members: &Signature,
    infos: &[ReadingInfo],
    best: (Basis, super::linear::Fit),
) -> (Basis, super::linear::Fit) {
    let Shape::Periodic { period_mm } = best.0.shape else {
        return best;
    };
    let p = (PERIODS - 1) as f64 * (period_mm / PERIOD_MIN_MM).ln()
        / (PERIOD_MAX_MM / PERIOD_MIN_MM).ln();
    // The 16 periods built and fitted in parallel (one thread's work
    // while the other waited), then taken in their order: the same choice.
    let tried: Vec<(Basis, super::linear::Fit)> = (-8..=8)
        .into_par_iter()
        .filter(|&j| j != 0)
        .map(|j| {
            let b = periodic(infos, period_of(p + j as f64 / 8.0));
            let f = lm.fit(&Signature::joined(members, &b.columns));
            (b, f)
        })
        .collect();
    tried.into_iter().fold(best, |a, b| {
        if b.1.delta_chi2 > a.1.delta_chi2 {
            b
        } else {
            a
        }
    })
}

/// A range offset per station or reflector (`scope`), `of` a reading's
/// index among `labels`.
fn offsets(
    infos: &[ReadingInfo],
    labels: &[String],
    of: fn(&ReadingInfo) -> usize,
    scope: &'static str,
) -> Basis {
    let mut c = Signature::new(labels.len());
    for (i, r) in infos.iter().enumerate() {
        c.add(i, 2, of(r), 1e-3 / r.sigma.z);
    }
    Basis {
        factor: scope,
        what: format!("a range offset per {scope}"),
        columns: c,
        shape: Shape::Labels(labels.to_vec()),
        unit: "µm",
        template: Template::Offsets { scope },
    }
}

/// `station × time`: one station's pose (translation, rotation) and range
/// stepping after a time, tried at quantiles of its readings' times.
fn station_steps(infos: &[ReadingInfo], stations: &[String]) -> Vec<Basis> {
    // Each station's steps on their own (passes over every reading): in
    // parallel, collected in station order — the same bases.
    let per_station: Vec<Vec<Basis>> = stations
        .par_iter()
        .enumerate()
        .map(|(s, id)| {
            let mut out = Vec::new();
            let mut times: Vec<f64> = infos
                .iter()
                .filter(|r| r.station == s)
                .filter_map(|r| r.since_station_s)
                .collect();
            times.sort_by(f64::total_cmp);
            times.dedup();
            // Not in the first or last three readings: a step there is a
            // blunder's business.
            if times.len() < 8 {
                return out;
            }
            let inner = &times[3..times.len() - 3];
            let n = inner.len().min(STEP_TIMES);
            for q in 0..n {
                let t0 = inner[q * inner.len() / n];
                let mut c = Signature::new(7);
                for (i, r) in infos.iter().enumerate() {
                    if r.station != s || r.since_station_s.is_none_or(|t| t < t0) {
                        continue;
                    }
                    let arm = r.point - r.station_pos;
                    for a in 0..3 {
                        let mut e = Vector3::zeros();
                        e[a] = 1.0;
                        // The origin moves by v: the reflector seems to move by −v.
                        put_point(&mut c, i, r, a, -1e-3 * e);
                        // The station turns by ω: the reflector seems to turn by −ω.
                        put_point(&mut c, i, r, 3 + a, -1e-6 * e.cross(&arm));
                    }
                    c.add(i, 2, 6, 1e-3 / r.sigma.z);
                }
                let labels = [
                    "x_um", "y_um", "z_um", "rx_urad", "ry_urad", "rz_urad", "d_um",
                ];
                out.push(Basis {
                    factor: "station × time",
                    what: format!(
                        "a step of {id}'s pose and range {t0:.0} s after its first reading"
                    ),
                    columns: c,
                    shape: Shape::Labels(labels.iter().map(|l| l.to_string()).collect()),
                    unit: "µm, µrad",
                    template: Template::Step {
                        station: id.clone(),
                        t0_s: t0,
                    },
                });
            }
            out
        })
        .collect();
    per_station.into_iter().flatten().collect()
}

/// What the explanation set leaves, and against what it is tested.
pub(super) struct Rest<'a> {
    pub lm: &'a LinearModel,
    /// The set's members' columns.
    pub members: &'a Signature,
    /// χ² the set leaves and its degrees of freedom.
    pub chi2: f64,
    pub dof: usize,
    /// Held-out RMS of the augmented model and the noise floor (µm).
    pub cv_rms_um: f64,
    pub floor: super::Floor,
    pub alpha: f64,
}

/// Every basis of every factor fitted beside the members of one model
/// state: what [`structure`] (at each step) and [`localise`] (at the end)
/// both read, computed once per state — ~450 fits on a big network.
pub(super) struct Fitted {
    all: Vec<Basis>,
    /// The χ² the members explain.
    members_chi2: f64,
    /// Each basis's fit beside the members, in the order of `all`.
    fits: Vec<super::linear::Fit>,
}

/// [`Fitted`] for the model `lm` with `members`.
pub(super) fn fitted(
    lm: &LinearModel,
    members: &Signature,
    infos: &[ReadingInfo],
    stations: &[String],
    targets: &[String],
) -> Fitted {
    let all = bases(infos, stations, targets);
    let members_chi2 = if members.ncols() == 0 {
        0.0
    } else {
        lm.fit(members).delta_chi2
    };
    // Without members, a station's steps (nested: each the one before on
    // its later readings) are fitted as one chain ([`LinearModel::fit_each`]).
    let fits = if members.ncols() == 0 {
        lm.fit_each(&all.iter().map(|b| &b.columns).collect::<Vec<_>>())
    } else {
        all.par_iter()
            .map(|b| lm.fit(&Signature::joined(members, &b.columns)))
            .collect()
    };
    Fitted {
        all,
        members_chi2,
        fits,
    }
}

/// The F test of a basis of `k` columns gaining `delta` of the `chi2`
/// (on `dof`) that the members leave: `(F, p)`.
fn f_test(delta: f64, k: usize, chi2: f64, dof: usize) -> (f64, f64) {
    let left = (chi2 - delta).max(1e-300);
    let dof_aug = dof.saturating_sub(k).max(1);
    let f = (delta / k as f64) / (left / dof_aug as f64);
    (f, f_test::p_value(k as f64, dof_aug as f64, f))
}

/// The dominant structure: the significant basis with the largest ΔBIC.
pub(super) struct Structure {
    pub columns: Signature,
    pub delta_bic: f64,
    /// Bases it was chosen from (the correction's factor), and α.
    tried: usize,
    alpha: f64,
}

impl Structure {
    /// Whether the structure is still significant, and gains by BIC,
    /// beside the columns `against` (the members and a candidate; `dof`
    /// the model's with them): if not, that candidate explains it.
    pub fn stands_beside(&self, lm: &LinearModel, against: &Signature, dof: usize) -> bool {
        let base = lm.fit(against).delta_chi2;
        let joint = lm
            .fit(&Signature::concat(against, &self.columns))
            .delta_chi2;
        let delta = (joint - base).max(0.0);
        let k = self.columns.ncols();
        let (_, p) = f_test(delta, k, lm.chi2() - base, dof);
        (p * self.tried as f64).min(1.0) < self.alpha
            && delta - k as f64 * (lm.rows() as f64).ln() > 0.0
    }
}

/// The basis, of any factor, that explains most of what `members` leave
/// by ΔBIC (`Δχ² − k·ln m`), if one is significant (F test, Bonferroni
/// over every basis) and gains: what the diagnosis tests candidates and
/// readings against when it explains more than any of them.
pub(super) fn structure(
    fitted: &Fitted,
    lm: &LinearModel,
    members: &Signature,
    dof: usize,
    alpha: f64,
    infos: &[ReadingInfo],
) -> Option<Structure> {
    let Fitted {
        all,
        members_chi2,
        fits,
    } = fitted;
    let members_chi2 = *members_chi2;
    let chi2 = lm.chi2() - members_chi2;
    if chi2 / (dof.max(1) as f64) < ROUNDING_CHI2_PER_DOF {
        return None;
    }
    let ln_m = (lm.rows() as f64).ln();
    let (best, delta_bic) = all
        .iter()
        .zip(fits)
        .enumerate()
        .filter_map(|(i, (b, f))| {
            let k = b.columns.ncols();
            let delta = (f.delta_chi2 - members_chi2).max(0.0);
            let (_, p) = f_test(delta, k, chi2, dof);
            let significant = (p * all.len() as f64).min(1.0) < alpha;
            let delta_bic = delta - k as f64 * ln_m;
            (significant && delta_bic > 0.0).then_some((i, delta_bic))
        })
        .max_by(|a, b| a.1.total_cmp(&b.1))?;
    let (b, f) = refine_period(lm, members, infos, (all[best].clone(), fits[best].clone()));
    let k = b.columns.ncols() as f64;
    Some(Structure {
        delta_bic: delta_bic.max(f.delta_chi2 - members_chi2 - k * ln_m),
        columns: b.columns,
        tried: all.len(),
        alpha,
    })
}

/// Every factor's best basis, most significant first (then by Δχ²).
pub(super) fn localise(rest: &Rest, fitted: &Fitted, infos: &[ReadingInfo]) -> Vec<Localised> {
    let Fitted {
        all,
        members_chi2,
        fits,
    } = fitted;
    let members_chi2 = *members_chi2;
    let k_m = rest.members.ncols();
    let gain = |f: &super::linear::Fit| (f.delta_chi2 - members_chi2).max(0.0);
    let tried = all.len();
    let rounding = rest.chi2 / (rest.dof.max(1) as f64) < ROUNDING_CHI2_PER_DOF;
    // Each factor once, in the order its first basis was built.
    let mut factors: Vec<&'static str> = Vec::new();
    for b in all {
        if !factors.contains(&b.factor) {
            factors.push(b.factor);
        }
    }
    let mut out: Vec<Localised> = factors
        .par_iter()
        .map(|&factor| {
            let of: Vec<usize> = (0..all.len())
                .filter(|&i| all[i].factor == factor)
                .collect();
            let best = *of
                .iter()
                .max_by(|&&a, &&b| gain(&fits[a]).total_cmp(&gain(&fits[b])))
                .expect("a factor has a basis");
            let (b, fit) = refine_period(
                rest.lm,
                rest.members,
                infos,
                (all[best].clone(), fits[best].clone()),
            );
            let (b, fit) = (&b, &fit);
            let k = b.columns.ncols();
            let delta = gain(fit);
            let (f, p) = f_test(delta, k, rest.chi2, rest.dof);
            let left = (rest.chi2 - delta).max(1e-300);
            let dof_aug = rest.dof.saturating_sub(k).max(1);
            let p_adjusted = (p * tried as f64).min(1.0);
            let joint = Signature::joined(rest.members, &b.columns);
            let cv = rest.lm.cv_rms_um(&joint);
            let gap = rest.cv_rms_um - rest.floor.um;
            let var_factor = (left / dof_aug as f64).max(1.0);
            let beta = &fit.beta[k_m..];
            let u: Vec<f64> = (0..k)
                .map(|c| (fit.cov[(k_m + c, k_m + c)] * var_factor).sqrt())
                .collect();
            let (shape, shape_x) = shape(b, beta, &u, &fit.cov, k_m, var_factor);
            let hypothesis = hypothesis(b, beta);
            Localised {
                factor,
                basis: b.what.clone(),
                columns: k,
                alternatives: of.len(),
                delta_chi2: delta,
                share: delta / rest.chi2.max(1e-300),
                f,
                p,
                p_adjusted,
                significant: !rounding && p_adjusted < rest.alpha,
                gap_removed_pct: if rest.floor.has_gap(gap) {
                    100.0 * (rest.cv_rms_um - cv) / gap
                } else {
                    0.0
                },
                shape,
                shape_x,
                shape_unit: b.unit.to_string(),
                hypothesis,
            }
        })
        .collect();
    out.sort_by(|a, b| {
        b.significant
            .cmp(&a.significant)
            .then(b.delta_chi2.total_cmp(&a.delta_chi2))
    });
    out
}

/// The fitted function as points, with their standard uncertainties.
fn shape(
    b: &Basis,
    beta: &[f64],
    u: &[f64],
    cov: &nalgebra::DMatrix<f64>,
    k_m: usize,
    var_factor: f64,
) -> (Vec<ShapePoint>, String) {
    match &b.shape {
        Shape::Knots { x, x_name } => (
            x.iter()
                .zip(beta.iter().zip(u))
                .map(|(&x, (&value, &u))| ShapePoint {
                    at: format!("{x:.4}"),
                    x,
                    value,
                    u,
                })
                .collect(),
            x_name.to_string(),
        ),
        Shape::Periodic { period_mm } => {
            let n = 12;
            let points = (0..n)
                .map(|s| {
                    let x = period_mm * s as f64 / n as f64;
                    let phase = 2.0 * std::f64::consts::PI * x / period_mm;
                    let g = [phase.sin(), phase.cos()];
                    let value = g[0] * beta[0] + g[1] * beta[1];
                    let var: f64 = (0..2)
                        .flat_map(|a| (0..2).map(move |c| (a, c)))
                        .map(|(a, c)| g[a] * g[c] * cov[(k_m + a, k_m + c)])
                        .sum();
                    ShapePoint {
                        at: format!("{x:.1}"),
                        x,
                        value,
                        u: (var * var_factor).max(0.0).sqrt(),
                    }
                })
                .collect();
            (points, "d mod period (mm)".into())
        }
        Shape::Labels(labels) => (
            labels
                .iter()
                .zip(beta.iter().zip(u))
                .enumerate()
                .map(|(i, (l, (&value, &u)))| ShapePoint {
                    at: l.clone(),
                    x: i as f64,
                    value,
                    u,
                })
                .collect(),
            "column".into(),
        ),
    }
}

/// The hypothesis file entry of a fitted basis: its expression, its
/// parameters at the fitted values (`value`, what a simulation injects).
fn hypothesis(b: &Basis, beta: &[f64]) -> Option<String> {
    let name = format!(
        "discovered-{}",
        b.factor.replace(" × ", "-").replace(' ', "-")
    );
    let acts = |comp: usize| (COMPONENT[comp], ["urad", "urad", "um"][comp]);
    let params = |names: &[String], unit: &str| -> String {
        names
            .iter()
            .zip(beta)
            .map(|(n, v)| format!("{n} = {{ unit = \"{unit}\", value = {v:.6} }}\n"))
            .collect()
    };
    let rms = |names: &[String]| {
        let squares: Vec<String> = names.iter().map(|n| format!("{n}^2")).collect();
        format!("sqrt(({})/{})", squares.join(" + "), names.len())
    };
    let entry = |acts_on: &str, unit: &str, expr: &str, magnitude: &str, params: &str| {
        format!(
            "[{name}]\ndoc = \"{}, found by ltcal diagnose\"\nacts_on = \"{acts_on}\"\nunit = \"{unit}\"\n\
             expr = \"{expr}\"\nmagnitude = \"{magnitude}\"\n\n[{name}.params]\n{params}",
            b.what
        )
    };
    match (&b.template, &b.shape) {
        (Template::Smooth { var, comp }, Shape::Knots { x, .. }) => {
            let h = x[1] - x[0];
            let names: Vec<String> = (0..x.len()).map(|k| format!("v{k}")).collect();
            let terms: Vec<String> = x
                .iter()
                .zip(&names)
                .map(|(xk, n)| {
                    let hat = format!("(1 - abs({var} - ({xk:.6}))/{h:.6})");
                    format!("{n}*step{hat}*{hat}")
                })
                .collect();
            let (acts_on, unit) = acts(*comp);
            Some(entry(
                acts_on,
                unit,
                &terms.join(" + "),
                &rms(&names),
                &params(&names, COMPONENT_UNIT[*comp]),
            ))
        }
        (Template::Periodic, Shape::Periodic { period_mm }) => {
            let names = vec!["a".to_string(), "b".to_string()];
            Some(entry(
                "d",
                "um",
                &format!("a*sin(2*PI*d/{period_mm:.3}) + b*cos(2*PI*d/{period_mm:.3})"),
                "sqrt(a^2 + b^2)",
                &params(&names, "µm"),
            ))
        }
        (Template::Fourier { comp }, _) => {
            let names: Vec<String> = (1..=4)
                .flat_map(|o| [format!("a{o}"), format!("b{o}")])
                .collect();
            let terms: Vec<String> = (1..=4)
                .map(|o| format!("a{o}*sin({o}*az) + b{o}*cos({o}*az)"))
                .collect();
            let (acts_on, unit) = acts(*comp);
            Some(entry(
                acts_on,
                unit,
                &terms.join(" + "),
                &rms(&names),
                &params(&names, COMPONENT_UNIT[*comp]),
            ))
        }
        (Template::Offsets { scope }, Shape::Labels(labels)) => {
            let values: Vec<String> = labels
                .iter()
                .zip(beta)
                .map(|(l, v)| format!("\"{l}\" = {v:.6}"))
                .collect();
            let params = format!(
                "c = {{ unit = \"µm\", scope = \"{scope}\", value = {{ {} }} }}\n",
                values.join(", ")
            );
            Some(entry("d", "um", "c", "c", &params))
        }
        (Template::Face { comp }, _) => {
            let (acts_on, unit) = acts(*comp);
            let names = vec!["c".to_string()];
            Some(entry(
                acts_on,
                unit,
                "c*(face - 1)",
                "c",
                &params(&names, COMPONENT_UNIT[*comp]),
            ))
        }
        (Template::Step { station, t0_s }, _) => {
            // The origin's translation and the range step; the station's
            // small turn (columns 3–5) is left out: a hypothesis moves a
            // position or one coordinate.
            let on = format!("{{station={station}}}*step(since_station_s - {t0_s:.1})");
            let shift = format!(
                "[{name}]\ndoc = \"{}: its origin, found by ltcal diagnose\"\nacts_on = \"station\"\nunit = \"um\"\n\
                 shift = {{ x = \"dx*{on}\", y = \"dy*{on}\", z = \"dz*{on}\" }}\nmagnitude = \"sqrt(dx^2 + dy^2 + dz^2)\"\n\n\
                 [{name}.params]\n{}",
                b.what,
                params(&["dx".into(), "dy".into(), "dz".into()], "µm")
            );
            let range = format!(
                "\n[{name}-range]\ndoc = \"{}: its range, found by ltcal diagnose\"\nacts_on = \"d\"\nunit = \"um\"\n\
                 expr = \"c*{on}\"\nmagnitude = \"c\"\n\n[{name}-range.params]\nc = {{ unit = \"µm\", value = {:.6} }}\n",
                b.what, beta[6]
            );
            Some(shift + &range)
        }
        _ => None,
    }
}

/// `discovered.toml`: the most significant structure's hypothesis, to
/// test on the next campaign (`ltcal diagnose --hypotheses discovered.toml`).
pub fn discovered(campaign: &str, unexplained: &[Localised]) -> Option<String> {
    let l = unexplained.iter().find(|l| l.significant)?;
    let entry = l.hypothesis.as_ref()?;
    Some(format!(
        "# What the explanation set left in `{campaign}`, along {}: {} ({:.0} % of the χ² left).\n\
         # Written by ltcal diagnose as a hypothesis (README, \"Your own effects\"): rename it,\n\
         # edit it, and test it on the next campaign with `ltcal diagnose --hypotheses`.\n\n{entry}",
        l.factor,
        l.basis,
        100.0 * l.share
    ))
}
