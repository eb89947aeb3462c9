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
//! | `range` | a cubic B-spline in d on each coordinate; sine and cosine of `2π·d/P` on d for periods P from 0.2 m to 5 m (the best period counted as alternatives) |
//! | `az`, `el` | a Fourier series in az (orders 2–4) / a cubic B-spline in el, on each coordinate |
//! | `time` | a cubic B-spline in `time_s` on each coordinate, and a growth of the reflector field about its centroid |
//! | `station × time` | a step of one station's pose (translation, rotation) and of its range after a time, at times on a grid (station and time counted as alternatives) |
//! | `station`, `reflector`, `face` | a range offset per station / per reflector, a face-2 offset on each coordinate |
//! | `incidence`, `temperature` | a cubic B-spline on d |
//!
//! Each factor is reported with its best basis: its share of what is left
//! (Δχ² over the set's χ²), its p-value, the held-out gap a smooth function
//! of that factor would remove, and its fitted shape as a table.

/// The structure left along one factor.
#[derive(Clone, Debug)]
pub struct Localised {
    /// `range`, `az`, `el`, `time`, `station × time`, `station`,
    /// `reflector`, `face`, `incidence`, `temperature`.
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

/// One basis of a factor.
#[derive(Clone)]
struct Basis {
    factor: &'static str,
    what: String,
    columns: Signature,
    shape: Shape,
    unit: &'static str,
}

/// Evenly spaced knots over the values present, and each value's weights
/// on them (at most two non-zero).
fn hats(values: &[Option<f64>]) -> Option<(Vec<f64>, impl Fn(f64) -> [(usize, f64); 2])> {
    let (lo, hi) = values
        .iter()
        .flatten()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    if !(hi - lo > 1e-9 * hi.abs().max(1.0)) || !(hi - lo).is_finite() {
        return None;
    }
    let h = (hi - lo) / (KNOTS - 1) as f64;
    let knots: Vec<f64> = (0..KNOTS).map(|k| lo + h * k as f64).collect();
    let weights = move |v: f64| {
        let f = ((v - lo) / h).clamp(0.0, (KNOTS - 1) as f64);
        let k = (f.floor() as usize).min(KNOTS - 2);
        let t = f - k as f64;
        [(k, 1.0 - t), (k + 1, t)]
    };
    Some((knots, weights))
}

/// A smooth function of `values` on reading coordinate `comp`.
fn smooth(
    infos: &[ReadingInfo],
    values: &[Option<f64>],
    comp: usize,
    factor: &'static str,
    x_name: &'static str,
) -> Option<Basis> {
    let (knots, weights) = hats(values)?;
    let mut c = Signature::new(KNOTS);
    for (i, (r, v)) in infos.iter().zip(values).enumerate() {
        let Some(v) = v else { continue };
        for (k, w) in weights(*v) {
            c.add(i, comp, k, w * PER_UNIT[comp] / r.sigma[comp]);
        }
    }
    Some(Basis {
        factor,
        what: format!("a smooth function of {x_name} on {}", COMPONENT[comp]),
        columns: c,
        shape: Shape::Knots { x: knots, x_name },
        unit: COMPONENT_UNIT[comp],
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
    for comp in 0..3 {
        out.extend(smooth(infos, &d, comp, "range", "d (mm)"));
        out.extend(smooth(infos, &el, comp, "el", "el (°)"));
        out.extend(smooth(infos, &time, comp, "time", "time_s (s)"));
    }
    // range: a cyclic error of the distance meter, whatever its period.
    for p in 0..PERIODS {
        let period_mm = PERIOD_MIN_MM
            * (PERIOD_MAX_MM / PERIOD_MIN_MM).powf(p as f64 / (PERIODS - 1) as f64);
        let mut c = Signature::new(2);
        for (i, r) in infos.iter().enumerate() {
            let phase = 2.0 * std::f64::consts::PI * r.d / period_mm;
            c.add(i, 2, 0, 1e-3 * phase.sin() / r.sigma.z);
            c.add(i, 2, 1, 1e-3 * phase.cos() / r.sigma.z);
        }
        out.push(Basis {
            factor: "range",
            what: format!("periodic in d, period {period_mm:.0} mm"),
            columns: c,
            shape: Shape::Periodic { period_mm },
            unit: "µm",
        });
    }
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
        });
    }
    // time: the reflectors' field growing about its centroid (a part
    // warming), `s = (x − c)·g(t)` in ppm.
    if let Some((knots, weights)) = hats(&time) {
        let centroid =
            infos.iter().map(|r| r.point).sum::<Vector3<f64>>() / infos.len().max(1) as f64;
        let mut c = Signature::new(KNOTS);
        for (i, (r, t)) in infos.iter().zip(&time).enumerate() {
            let Some(t) = t else { continue };
            for (k, w) in weights(*t) {
                put_point(&mut c, i, r, k, (r.point - centroid) * (1e-6 * w));
            }
        }
        out.push(Basis {
            factor: "time",
            what: "the reflectors' field growing about its centroid with time".into(),
            columns: c,
            shape: Shape::Knots {
                x: knots,
                x_name: "time_s (s)",
            },
            unit: "ppm",
        });
    }
    out.extend(station_steps(infos, stations));
    // station: a range offset per station.
    if stations.len() > 1 {
        let mut c = Signature::new(stations.len());
        for (i, r) in infos.iter().enumerate() {
            c.add(i, 2, r.station, 1e-3 / r.sigma.z);
        }
        out.push(Basis {
            factor: "station",
            what: "a range offset per station".into(),
            columns: c,
            shape: Shape::Labels(stations.to_vec()),
            unit: "µm",
        });
    }
    // reflector: a range offset per reflector (two kinds of SMR).
    if targets.len() > 1 && targets.len() <= MAX_REFLECTOR_OFFSETS {
        let mut c = Signature::new(targets.len());
        for (i, r) in infos.iter().enumerate() {
            c.add(i, 2, r.target, 1e-3 / r.sigma.z);
        }
        out.push(Basis {
            factor: "reflector",
            what: "a range offset per reflector".into(),
            columns: c,
            shape: Shape::Labels(targets.to_vec()),
            unit: "µm",
        });
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
            });
        }
    }
    let incidence = of(&|r| r.incidence.map(|a| a.alpha.to_degrees()));
    out.extend(smooth(infos, &incidence, 2, "incidence", "α (°)"));
    let temperature = of(&|r| r.temperature_c);
    out.extend(smooth(infos, &temperature, 2, "temperature", "temperature_c (°C)"));
    out
}

/// `station × time`: one station's pose (translation, rotation) and range
/// stepping after a time, tried at quantiles of its readings' times.
fn station_steps(infos: &[ReadingInfo], stations: &[String]) -> Vec<Basis> {
    let mut out = Vec::new();
    for (s, id) in stations.iter().enumerate() {
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
            continue;
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
            let labels = ["x_um", "y_um", "z_um", "rx_urad", "ry_urad", "rz_urad", "d_um"];
            out.push(Basis {
                factor: "station × time",
                what: format!("a step of {id}'s pose and range {t0:.0} s after its first reading"),
                columns: c,
                shape: Shape::Labels(labels.iter().map(|l| l.to_string()).collect()),
                unit: "µm, µrad",
            });
        }
    }
    out
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
    pub floor_um: f64,
    pub alpha: f64,
}

/// Every basis fitted beside `members`: the χ² the members explain, and
/// each basis's fit.
fn fits(
    lm: &LinearModel,
    members: &Signature,
    all: &[Basis],
) -> (f64, Vec<super::linear::Fit>) {
    let members_chi2 = if members.ncols() == 0 {
        0.0
    } else {
        lm.fit(members).delta_chi2
    };
    let fits = all
        .par_iter()
        .map(|b| lm.fit(&Signature::concat(members, &b.columns)))
        .collect();
    (members_chi2, fits)
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
}

/// The basis, of any factor, that explains most of what `members` leave
/// by ΔBIC (`Δχ² − k·ln m`), if one is significant (F test, Bonferroni
/// over every basis) and gains: what the diagnosis tests candidates and
/// readings against when it explains more than any of them.
pub(super) fn structure(
    lm: &LinearModel,
    members: &Signature,
    dof: usize,
    alpha: f64,
    infos: &[ReadingInfo],
    stations: &[String],
    targets: &[String],
) -> Option<Structure> {
    let all = bases(infos, stations, targets);
    let (members_chi2, fits) = fits(lm, members, &all);
    let chi2 = lm.chi2() - members_chi2;
    if chi2 / (dof.max(1) as f64) < ROUNDING_CHI2_PER_DOF {
        return None;
    }
    let ln_m = (lm.rows() as f64).ln();
    let (best, delta_bic) = all
        .iter()
        .zip(&fits)
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
    Some(Structure {
        columns: all[best].columns.clone(),
        delta_bic,
    })
}

/// Every factor's best basis, most significant first (then by Δχ²).
pub(super) fn localise(
    rest: &Rest,
    infos: &[ReadingInfo],
    stations: &[String],
    targets: &[String],
) -> Vec<Localised> {
    let all = bases(infos, stations, targets);
    let k_m = rest.members.ncols();
    let (members_chi2, fits) = fits(rest.lm, rest.members, &all);
    let gain = |f: &super::linear::Fit| (f.delta_chi2 - members_chi2).max(0.0);
    let tried = all.len();
    let rounding = rest.chi2 / (rest.dof.max(1) as f64) < ROUNDING_CHI2_PER_DOF;
    let mut factors: Vec<&'static str> = all.iter().map(|b| b.factor).collect();
    factors.dedup();
    let mut out: Vec<Localised> = factors
        .par_iter()
        .map(|&factor| {
            let of: Vec<usize> = (0..all.len()).filter(|&i| all[i].factor == factor).collect();
            let best = *of
                .iter()
                .max_by(|&&a, &&b| gain(&fits[a]).total_cmp(&gain(&fits[b])))
                .expect("a factor has a basis");
            let (b, fit) = (&all[best], &fits[best]);
            let k = b.columns.ncols();
            let delta = gain(fit);
            let (f, p) = f_test(delta, k, rest.chi2, rest.dof);
            let left = (rest.chi2 - delta).max(1e-300);
            let dof_aug = rest.dof.saturating_sub(k).max(1);
            let p_adjusted = (p * tried as f64).min(1.0);
            let joint = Signature::concat(rest.members, &b.columns);
            let cv = rest.lm.cv_rms_um(&joint);
            let gap = rest.cv_rms_um - rest.floor_um;
            let var_factor = (left / dof_aug as f64).max(1.0);
            let beta = &fit.beta[k_m..];
            let u: Vec<f64> = (0..k)
                .map(|c| (fit.cov[(k_m + c, k_m + c)] * var_factor).sqrt())
                .collect();
            let (shape, shape_x) = shape(b, beta, &u, &fit.cov, k_m, var_factor);
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
                gap_removed_pct: if gap > 0.0 {
                    100.0 * (rest.cv_rms_um - cv) / gap
                } else {
                    0.0
                },
                shape,
                shape_x,
                shape_unit: b.unit.to_string(),
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
