//! SVG figures with plotters. Each function takes plain data and returns the
//! SVG text; stages decide what to draw. Text is rendered without system
//! fonts (plotters estimates widths), so figures look the same everywhere.

use anyhow::{Result, anyhow};
use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

/// The viridis colour map, sampled at nine points and interpolated.
pub fn viridis(t: f64) -> RGBColor {
    const STOPS: [(u8, u8, u8); 9] = [
        (68, 1, 84),
        (71, 44, 122),
        (59, 81, 139),
        (44, 113, 142),
        (33, 144, 141),
        (39, 173, 129),
        (92, 200, 99),
        (170, 220, 50),
        (253, 231, 37),
    ];
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let x = t * (STOPS.len() - 1) as f64;
    let i = (x.floor() as usize).min(STOPS.len() - 2);
    let f = x - i as f64;
    let lerp = |a: u8, b: u8| (a as f64 + f * (b as f64 - a as f64)).round() as u8;
    let (a, b) = (STOPS[i], STOPS[i + 1]);
    RGBColor(lerp(a.0, b.0), lerp(a.1, b.1), lerp(a.2, b.2))
}

/// A column name as an axis title or legend entry: words, and the unit
/// its suffix names in parentheses (the project's units-in-names
/// convention read backwards): `sigma_angle_urad` → `σ angle (µrad)`,
/// `improvement_pct` → `improvement (%)`, `time_s` → `time (s)`. A name
/// without a known unit keeps its words.
pub fn axis_title(column: &str) -> String {
    // Longest suffixes first: `_um_per_min` before `_min`.
    const UNITS: [(&str, &str); 14] = [
        ("_um_per_min", "µm/min"),
        ("_ppm_per_c", "ppm/°C"),
        ("_urad", "µrad"),
        ("_ppm", "ppm"),
        ("_pct", "%"),
        ("_deg", "°"),
        ("_min", "min"),
        ("_um", "µm"),
        ("_mm", "mm"),
        ("_nm", "nm"),
        ("_m", "m"),
        ("_s", "s"),
        ("_h", "h"),
        ("_c", "°C"),
    ];
    let (stem, unit) = UNITS
        .iter()
        .find_map(|(suffix, unit)| {
            column
                .strip_suffix(suffix)
                .filter(|stem| !stem.is_empty())
                .map(|stem| (stem, Some(*unit)))
        })
        .unwrap_or((column, None));
    let words: Vec<&str> = stem
        .split('_')
        .filter(|w| !w.is_empty())
        .map(|w| if w == "sigma" { "σ" } else { w })
        .collect();
    let words = words.join(" ");
    match unit {
        Some(u) => format!("{words} ({u})"),
        None => words,
    }
}

fn err<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow!("drawing the figure: {e}")
}

/// The widest axis span drawn. plotters computes an axis's tick marks in a
/// loop that ends only for a finite span: one `time_s` of 1.8e308, padded
/// by 5 %, made the span ∞ and the loop spin forever. Spans beyond this are
/// refused too: nothing a tracker measures needs them, and near `f64::MAX`
/// the tick arithmetic overflows.
pub const MAX_SPAN: f64 = 1e300;

/// An axis that cannot be drawn: a non-finite end or a span beyond
/// [`MAX_SPAN`]. Callers that can do without the figure skip it with a note.
#[derive(Debug, thiserror::Error)]
#[error(
    "an axis from {lo:e} to {hi:e} cannot be drawn (its ends must be finite and its span at most 1e300)"
)]
pub struct Undrawable {
    pub lo: f64,
    pub hi: f64,
}

/// Every data-driven axis range goes through here, so no input can make a
/// figure hang.
fn span(lo: f64, hi: f64) -> std::result::Result<std::ops::Range<f64>, Undrawable> {
    if lo.is_finite() && hi.is_finite() && (hi - lo).abs() <= MAX_SPAN {
        Ok(lo..hi)
    } else {
        Err(Undrawable { lo, hi })
    }
}

/// The canvas every figure is drawn on.
type Canvas<'a> = DrawingArea<SVGBackend<'a>, Shift>;

/// The scaffold of every figure: a white SVG canvas of `size` pixels, which
/// `draw` fills, presented as SVG text.
fn figure(size: (u32, u32), draw: impl FnOnce(&Canvas<'_>) -> Result<()>) -> Result<String> {
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        root.fill(&WHITE).map_err(err)?;
        draw(&root)?;
        root.present().map_err(err)?;
    }
    Ok(svg)
}

/// The legend of every figure with one: a framed box on a nearly opaque
/// white ground, at `position`, in `font_size`-point text.
fn legend<'a, CT: CoordTranslate>(
    chart: &mut ChartContext<'a, SVGBackend<'a>, CT>,
    position: SeriesLabelPosition,
    font_size: u32,
) -> Result<()> {
    chart
        .configure_series_labels()
        .position(position)
        .background_style(WHITE.mix(0.9))
        .border_style(BLACK)
        .label_font(("sans-serif", font_size))
        .draw()
        .map_err(err)
}

/// The width in pixels of `text` in a sans-serif font of `font_px` pixels:
/// Helvetica's advance widths (the metrics of Arial and Liberation Sans,
/// which browsers substitute), 0.6 em for what the table lacks. plotters
/// measures no text without system fonts, so legends, label de-overlap and
/// the figure layout test (`tests/integration/figure_layout.rs`) all
/// estimate with this.
pub fn text_width_px(text: &str, font_px: f64) -> f64 {
    // Advance widths of ' ' to '~' in thousandths of an em.
    const ASCII: [u16; 95] = [
        278, 278, 355, 556, 556, 889, 667, 191, 333, 333, 389, 584, 278, 333, 278,
        278, // ' '–'/'
        556, 556, 556, 556, 556, 556, 556, 556, 556, 556, 278, 278, 584, 584, 584,
        556, // '0'–'?'
        1015, 667, 667, 722, 722, 667, 611, 778, 722, 278, 500, 667, 556, 833, 722,
        778, // '@'–'O'
        667, 778, 722, 667, 611, 722, 667, 944, 667, 667, 611, 278, 278, 278, 469,
        556, // 'P'–'_'
        333, 556, 556, 500, 556, 556, 278, 556, 556, 222, 222, 500, 222, 833, 556,
        556, // '`'–'o'
        556, 556, 333, 500, 278, 556, 500, 722, 500, 500, 500, 334, 260, 334,
        584, // 'p'–'~'
    ];
    let em: f64 = text
        .chars()
        .map(|c| match c {
            ' '..='~' => f64::from(ASCII[c as usize - 32]) / 1000.0,
            '°' => 0.4,
            '±' | '×' | 'µ' => 0.584,
            '—' => 1.0,
            '–' => 0.556,
            _ => 0.6,
        })
        .sum();
    em * font_px
}

/// A box in pixels, `[left, top, right, bottom]`.
pub type PixelBox = [f64; 4];

/// Where a label of `w` × `h` pixels goes: the first of `candidates` (its
/// left end, vertically centred) whose box meets none of `taken`, or the
/// first candidate when all do; its box is added to `taken`. Labels set
/// one after the other through here never print over each other while
/// there is room: edge labels of the stage graph converging on one stage
/// printed "points" over "errors".
pub fn place_label(
    candidates: impl IntoIterator<Item = (f64, f64)>,
    w: f64,
    h: f64,
    taken: &mut Vec<PixelBox>,
) -> (f64, f64) {
    let boxed = |(x, y): (f64, f64)| [x, y - h / 2.0, x + w, y + h / 2.0];
    let clear = |b: &PixelBox| {
        taken
            .iter()
            .all(|t| b[2] <= t[0] || t[2] <= b[0] || b[3] <= t[1] || t[3] <= b[1])
    };
    let mut first = None;
    let mut chosen = None;
    for at in candidates {
        first.get_or_insert(at);
        if clear(&boxed(at)) {
            chosen = Some(at);
            break;
        }
    }
    let at = chosen.or(first).unwrap_or((0.0, 0.0));
    taken.push(boxed(at));
    at
}

/// The pixel size plotters gives a font of `points` in SVG (it writes
/// `font-size` as points / 1.24).
pub fn font_px(points: f64) -> f64 {
    points / 1.24
}

/// The legend where it hides the fewest of `points` (data coordinates),
/// computed: its box, estimated from the labels' widths at `font_size`
/// ([`text_width_px`]) and grown by a marker's radius, is tried at the four
/// corners of the plotting area and then on an 8-pixel grid over it, and
/// the first place hiding the fewest points wins — a corner when one is as
/// good as anywhere. Corners alone hid ~78 markers of Figure 8 (noisy), the
/// ends of the coverage bars, and 65–113 points of Figures 6–8 whose empty
/// band lies mid-height.
fn legend_clear_of<'a, CT: CoordTranslate>(
    chart: &mut ChartContext<'a, SVGBackend<'a>, CT>,
    points: impl Iterator<Item = CT::From>,
    labels: &[&str],
    font_size: u32,
) -> Result<()> {
    let (xs, ys) = chart.plotting_area().get_pixel_range();
    let px = font_px(f64::from(font_size));
    let widest = labels
        .iter()
        .map(|l| text_width_px(l, px))
        .fold(0.0, f64::max);
    // plotters' box: the text, a 30-pixel marker column, 10-pixel margins;
    // a row of ~1.3 em.
    let (w, h) = (
        widest.ceil() as i32 + 50,
        (labels.len() as f64 * px * 1.3).ceil() as i32 + 20,
    );
    let pixels: Vec<(i32, i32)> = points
        .map(|p| chart.as_coord_spec().translate(&p))
        .collect();
    let (right, bottom) = (xs.end - xs.start - w - 5, ys.end - ys.start - h - 5);
    let corners = [(right, 5), (5, 5), (right, bottom), (5, bottom)];
    let grid = (5..=bottom.max(5))
        .step_by(8)
        .flat_map(|y| (5..=right.max(5)).step_by(8).map(move |x| (x, y)));
    const CLEARANCE: i32 = 4;
    let hidden = |&(x0, y0): &(i32, i32)| {
        let (x0, y0) = (xs.start + x0 - CLEARANCE, ys.start + y0 - CLEARANCE);
        pixels
            .iter()
            .filter(|(x, y)| {
                (x0..=x0 + w + 2 * CLEARANCE).contains(x)
                    && (y0..=y0 + h + 2 * CLEARANCE).contains(y)
            })
            .count()
    };
    let (x, y) = corners
        .into_iter()
        .chain(grid)
        .enumerate()
        .min_by_key(|(i, at)| (hidden(at), *i))
        .map(|(_, at)| at)
        .unwrap_or((right, 5));
    legend(chart, SeriesLabelPosition::Coordinate(x, y), font_size)
}

/// One mesh point with its error before and after calibration.
pub struct PointError {
    pub x_mm: f64,
    pub y_mm: f64,
    pub z_mm: f64,
    pub before_um: f64,
    pub after_um: f64,
}

/// Figures 6–8: the mesh in 3-D coloured by its error before calibration,
/// and every point's error before and after (log scale).
pub fn mesh_errors(title: &str, pts: &[PointError]) -> Result<String> {
    figure((1200, 560), |root| {
        let root = root.titled(title, ("sans-serif", 26)).map_err(err)?;
        let (left, right) = root.split_horizontally(560);
        let (mesh_area, bar_area) = left.split_horizontally(470);
        let emax = pts
            .iter()
            .map(|p| p.before_um)
            .fold(0.0, f64::max)
            .max(1e-12);
        mesh_3d(&mesh_area, pts, emax)?;
        colour_bar(
            &bar_area,
            0.0,
            emax,
            "error before (µm)",
            viridis,
            &FIGURE_BAR,
        )?;
        errors_by_point(&right, pts)?;
        Ok(())
    })
}

fn bounds(v: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = v.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
        (a.min(x), b.max(x))
    });
    if !lo.is_finite() {
        return (-1.0, 1.0);
    }
    let pad = ((hi - lo) * 0.05).max(1e-3);
    (lo - pad, hi + pad)
}

fn mesh_3d(area: &DrawingArea<SVGBackend, Shift>, pts: &[PointError], emax: f64) -> Result<()> {
    let m = |v: f64| v / 1000.0;
    // One span for the three axes, so that the mesh keeps its shape: a
    // plane mesh drawn on its own x range spread 2 mm over the whole width
    // and labelled 4.999 … 5.001.
    let ranges = [
        bounds(pts.iter().map(|p| m(p.x_mm))),
        bounds(pts.iter().map(|p| m(p.y_mm))),
        bounds(pts.iter().map(|p| m(p.z_mm))),
    ];
    let half = ranges
        .iter()
        .map(|(lo, hi)| (hi - lo) / 2.0)
        .fold(0.0, f64::max);
    let [x, y, z] = ranges.map(|(lo, hi)| {
        let mid = (lo + hi) / 2.0;
        span(mid - half, mid + half)
    });
    let (x, y, z) = (x?, y?, z?);
    let x_end = x.end;
    let mut chart = ChartBuilder::on(area)
        .margin(20)
        .margin_left(36)
        .caption("mesh, coloured by error before", ("sans-serif", 18))
        .build_cartesian_3d(x, z, y)
        .map_err(err)?;
    chart.with_projection(|mut p| {
        p.yaw = 0.6;
        p.pitch = 0.35;
        p.scale = 0.85;
        p.into_matrix()
    });
    chart
        .configure_axes()
        .x_labels(5)
        .y_labels(5)
        .z_labels(5)
        // x ends where y begins: a label near x's far end would print over
        // y's first ("10.010.0").
        .x_formatter(&|v| {
            if x_end - v < 0.15 * 2.0 * half {
                String::new()
            } else {
                format!("{v:.1}")
            }
        })
        .label_style(("sans-serif", 12))
        .draw()
        .map_err(err)?;
    chart
        .draw_series(pts.iter().map(|p| {
            let c = viridis(p.before_um / emax);
            Circle::new((m(p.x_mm), m(p.z_mm), m(p.y_mm)), 3, c.filled())
        }))
        .map_err(err)?;
    // plotters' 3-D axes carry no titles: say which is which.
    area.draw_text(
        "axes in m: x, z (up), y",
        &("sans-serif", 14).into_text_style(area),
        (20, area.dim_in_pixel().1 as i32 - 24),
    )
    .map_err(err)?;
    Ok(())
}

fn errors_by_point(area: &DrawingArea<SVGBackend, Shift>, pts: &[PointError]) -> Result<()> {
    let floor = 1e-9;
    let all = pts.iter().flat_map(|p| [p.before_um, p.after_um]);
    let (lo, hi) = all.fold((f64::INFINITY, 0.0f64), |(a, b), v| {
        (a.min(v.max(floor)), b.max(v))
    });
    let (lo, hi) = if lo.is_finite() && hi > 0.0 {
        (lo / 3.0, hi * 3.0)
    } else {
        (floor, 1.0)
    };
    let n = pts.len();
    let mut chart = ChartBuilder::on(area)
        .margin(20)
        .caption("error of each point", ("sans-serif", 18))
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d(0..n.max(1), span(lo, hi)?.log_scale())
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("point")
        .y_desc("error (µm, log scale)")
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .label_style(("sans-serif", 13))
        .draw()
        .map_err(err)?;
    let series = [
        ("before calibration", RGBColor(200, 60, 40), true),
        ("after calibration", RGBColor(30, 90, 200), false),
    ];
    for (name, colour, before) in series {
        let values: Vec<(usize, f64)> = pts
            .iter()
            .enumerate()
            .map(|(i, p)| (i, if before { p.before_um } else { p.after_um }.max(floor)))
            .collect();
        chart
            .draw_series(
                values
                    .iter()
                    .map(|&(i, v)| Circle::new((i, v), 2, colour.filled())),
            )
            .map_err(err)?
            .label(name)
            .legend(move |(x, y)| Circle::new((x, y), 4, colour.filled()));
    }
    let drawn = pts
        .iter()
        .enumerate()
        .flat_map(|(i, p)| [(i, p.before_um.max(floor)), (i, p.after_um.max(floor))]);
    legend_clear_of(&mut chart, drawn, &series.map(|(name, _, _)| name), 14)?;
    Ok(())
}

/// Figures 10 and 15–18: every compared quantity of a criterion (a
/// distance between stations, a reflector's coordinates) before and after
/// calibration, in the order of the larger error before.
pub fn criterion_errors(
    title: &str,
    y_label: &str,
    before: &[f64],
    after: &[f64],
) -> Result<String> {
    let mut order: Vec<usize> = (0..before.len()).collect();
    order.sort_by(|&a, &b| before[b].total_cmp(&before[a]));
    let top = before
        .iter()
        .chain(after)
        .copied()
        .fold(0.0, f64::max)
        .max(1e-9)
        * 1.05;
    figure((1000, 520), |root| {
        let mut chart = ChartBuilder::on(root)
            .margin(20)
            .caption(title, ("sans-serif", 22))
            .x_label_area_size(45)
            .y_label_area_size(70)
            .build_cartesian_2d(0..order.len().max(1), span(0.0, top)?)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc("compared quantity (sorted by error before calibration)")
            .y_desc(y_label)
            .label_style(("sans-serif", 13))
            .draw()
            .map_err(err)?;
        let series = [
            ("before calibration", RGBColor(200, 60, 40), before),
            ("after calibration", RGBColor(30, 90, 200), after),
        ];
        for (name, colour, values) in series {
            chart
                .draw_series(
                    order
                        .iter()
                        .enumerate()
                        .map(|(x, &i)| Circle::new((x, values[i]), 2, colour.filled())),
                )
                .map_err(err)?
                .label(name)
                .legend(move |(x, y)| Circle::new((x, y), 4, colour.filled()));
        }
        let drawn = order
            .iter()
            .enumerate()
            .flat_map(|(x, &i)| [(x, before[i]), (x, after[i])]);
        legend_clear_of(&mut chart, drawn, &series.map(|(name, _, _)| name), 14)?;
        Ok(())
    })
}

/// One panel of Figure 11: a parameter's error at every mesh point.
pub struct ParamField {
    /// E.g. "εx1 = 1 µrad".
    pub label: String,
    pub err_um: Vec<f64>,
    pub d_mm: Vec<f64>,
}

/// Figure 11: one small panel per parameter (6 × 3), the error of every
/// mesh point in mesh order, coloured by the point's distance d.
pub fn sensitivity_fields(title: &str, panels: &[ParamField]) -> Result<String> {
    let (d_lo, d_hi) = panels
        .iter()
        .flat_map(|p| p.d_mm.iter().copied())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), d| {
            (a.min(d), b.max(d))
        });
    let (d_lo, d_hi) = if d_lo < d_hi {
        (d_lo, d_hi)
    } else {
        (0.0, d_hi.max(1.0))
    };
    let rows = panels.len().div_ceil(3).max(1);
    figure((1250, 170 * rows as u32 + 60), |root| {
        let root = root.titled(title, ("sans-serif", 22)).map_err(err)?;
        let (grid, bar) = root.split_horizontally(1150);
        for (area, p) in grid.split_evenly((rows, 3)).iter().zip(panels) {
            let top = p.err_um.iter().copied().fold(0.0, f64::max);
            // A parameter that moves nothing gets a 1 µm axis, not a degenerate one.
            let top = if top > 1e-6 { top * 1.1 } else { 1.0 };
            let mut chart = ChartBuilder::on(area)
                .margin(6)
                .caption(&p.label, ("sans-serif", 14))
                .x_label_area_size(28)
                .y_label_area_size(48)
                .build_cartesian_2d(0..p.err_um.len().max(1), span(0.0, top)?)
                .map_err(err)?;
            chart
                .configure_mesh()
                .x_desc("mesh point")
                .y_desc("error (µm)")
                .x_labels(5)
                .y_labels(4)
                .label_style(("sans-serif", 10))
                .axis_desc_style(("sans-serif", 11))
                .draw()
                .map_err(err)?;
            chart
                .draw_series(
                    p.err_um
                        .iter()
                        .zip(&p.d_mm)
                        .enumerate()
                        .map(|(i, (&e, &d))| {
                            Circle::new((i, e), 1, viridis((d - d_lo) / (d_hi - d_lo)).filled())
                        }),
                )
                .map_err(err)?;
        }
        colour_bar(
            &bar,
            d_lo / 1000.0,
            d_hi / 1000.0,
            "distance d (m)",
            viridis,
            &FIGURE_BAR,
        )?;
        Ok(())
    })
}

/// Figure 12's data for one parameter: its error on a grid of directions at
/// one distance, as curves against θ (one per φ) and against φ (one per θ).
pub struct DirectionCurves {
    pub label: String,
    pub theta_deg: Vec<f64>,
    /// `(φ in degrees, error in µm at every θ)`.
    pub by_theta: Vec<(f64, Vec<f64>)>,
    pub phi_deg: Vec<f64>,
    /// `(θ in degrees, error in µm at every φ)`.
    pub by_phi: Vec<(f64, Vec<f64>)>,
}

/// Figure 12: for each parameter with a variable error, its error against θ
/// (left, one line per mesh φ) and against φ (right, one line per mesh θ)
/// at distance `d_mm`; a line's colour is its φ or θ, dark to light.
pub fn sensitivity_directions(title: &str, d_mm: f64, rows: &[DirectionCurves]) -> Result<String> {
    let n = rows.len().max(1);
    figure((1100, 230 * n as u32 + 80), |root| {
        let root = root
            .titled(
                &format!(
                    "{title} (d = {:.1} m; line colour: the other angle, low dark, high light)",
                    d_mm / 1000.0
                ),
                ("sans-serif", 18),
            )
            .map_err(err)?;
        let cells = root.split_evenly((n, 2));
        for (k, c) in rows.iter().enumerate() {
            let top = c
                .by_theta
                .iter()
                .chain(&c.by_phi)
                .flat_map(|l| l.1.iter().copied())
                .fold(0.0, f64::max)
                .max(1e-6)
                * 1.1;
            let panels = [
                (&cells[2 * k], "θ", &c.theta_deg, &c.by_theta, "φ"),
                (&cells[2 * k + 1], "φ", &c.phi_deg, &c.by_phi, "θ"),
            ];
            for (area, x, xs, lines, other) in panels {
                let (x0, x1) = (
                    xs.first().copied().unwrap_or(0.0),
                    xs.last().copied().unwrap_or(1.0),
                );
                let mut chart = ChartBuilder::on(area)
                    .margin(8)
                    .caption(
                        format!("{}, against {x} (one line per {other})", c.label),
                        ("sans-serif", 14),
                    )
                    .x_label_area_size(32)
                    .y_label_area_size(52)
                    .build_cartesian_2d(span(x0, x1)?, span(0.0, top)?)
                    .map_err(err)?;
                chart
                    .configure_mesh()
                    .x_desc(format!("{x} (deg)"))
                    .y_desc("error (µm)")
                    .x_label_formatter(&|v| format!("{v:.0}"))
                    .label_style(("sans-serif", 11))
                    .draw()
                    .map_err(err)?;
                let (lo, hi) = lines
                    .iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), l| {
                        (a.min(l.0), b.max(l.0))
                    });
                for (at, ys) in lines.iter() {
                    let t = if hi > lo { (at - lo) / (hi - lo) } else { 0.5 };
                    chart
                        .draw_series(LineSeries::new(
                            xs.iter().copied().zip(ys.iter().copied()),
                            viridis(0.9 * t).stroke_width(1),
                        ))
                        .map_err(err)?;
                }
            }
        }
        Ok(())
    })
}

/// The x range of points along a numeric `x`, or of one slot per category
/// (centred on 0, 1, …).
fn x_range(categories: Option<&[String]>, x: impl Iterator<Item = f64>) -> (f64, f64) {
    match categories {
        Some(c) => (-0.5, c.len() as f64 - 0.5),
        None => bounds(x),
    }
}

/// The axes and their titles; along categories, their names under the
/// axis (at most 24 labels), else numbers.
fn category_mesh<'a>(
    chart: &mut ChartContext<'a, SVGBackend<'a>, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    x_label: &str,
    y_label: &str,
    categories: Option<&[String]>,
) -> Result<()> {
    let cats = categories.map(|c| c.to_vec());
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc(y_label)
        .x_labels(categories.map_or(8, |c| c.len().min(24)))
        .x_label_formatter(&move |v| match &cats {
            Some(c) => c.get(v.round() as usize).cloned().unwrap_or_default(),
            None => format!("{v:.0}"),
        })
        .label_style(("sans-serif", 12))
        .draw()
        .map_err(err)
}

/// Markers a scatter panel draws at most: the residual figures of a
/// 24 000-reading network drew every reading, 9 MB a figure and a 66 MB
/// `report.html`.
pub const MAX_MARKERS: usize = 1500;

/// The markers to draw of `pixels` (each point's canvas position): all of
/// them when they are at most `max`; else the first point in each occupied
/// square cell of the canvas, the cell growing from 2 px by half its size
/// (2, 3, 4, 6, 9, 13, …) until at most `max` cells are occupied — with the
/// cell's size. Deterministic, and an isolated point (an outlier) always
/// keeps its marker: thinning only drops points drawn within a cell of one
/// that is drawn.
pub fn one_per_cell(pixels: &[(i32, i32)], max: usize) -> (Vec<usize>, Option<i32>) {
    if pixels.len() <= max {
        return ((0..pixels.len()).collect(), None);
    }
    let (lo, hi) = pixels.iter().fold(
        ((i32::MAX, i32::MAX), (i32::MIN, i32::MIN)),
        |(lo, hi), &(x, y)| ((lo.0.min(x), lo.1.min(y)), (hi.0.max(x), hi.1.max(y))),
    );
    let mut cell = 2;
    loop {
        let cell_of = |i: usize| (pixels[i].0.div_euclid(cell), pixels[i].1.div_euclid(cell));
        // The occupied cells marked on a grid over the points' extent (a
        // hash of every point's cell was most of a big network's figures),
        // by a hash only where that grid would be huge: the same cells.
        let c0 = (lo.0.div_euclid(cell) as i64, lo.1.div_euclid(cell) as i64);
        let c1 = (hi.0.div_euclid(cell) as i64, hi.1.div_euclid(cell) as i64);
        let (nx, ny) = (c1.0 - c0.0 + 1, c1.1 - c0.1 + 1);
        let kept: Vec<usize> = if nx * ny <= 1 << 22 {
            let mut seen = vec![false; (nx * ny) as usize];
            (0..pixels.len())
                .filter(|&i| {
                    let (cx, cy) = cell_of(i);
                    let at = (cy as i64 - c0.1) * nx + (cx as i64 - c0.0);
                    !std::mem::replace(&mut seen[at as usize], true)
                })
                .collect()
        } else {
            let mut seen = std::collections::HashSet::new();
            (0..pixels.len())
                .filter(|&i| seen.insert(cell_of(i)))
                .collect()
        };
        // A cell the size of any canvas holds one point: the loop ends.
        if kept.len() <= max || cell >= 1 << 16 {
            return (kept, Some(cell));
        }
        cell += (cell / 2).max(1);
    }
}

/// Residuals against one factor (the "where" of a diagnosis): three
/// stacked panels, az and el in µrad and d in µm, against the factor's
/// value — or its group, with the group names under the axis. A panel of
/// more than [`MAX_MARKERS`] readings draws one per occupied cell
/// ([`one_per_cell`]) and says so under its axis: "n of N readings drawn".
pub fn residuals_by_factor(
    title: &str,
    x_label: &str,
    categories: Option<&[String]>,
    x: &[f64],
    panels: [(&str, &[f64]); 3],
) -> Result<String> {
    let finite = |v: &[f64]| {
        v.iter()
            .copied()
            .filter(|x| x.is_finite())
            .collect::<Vec<f64>>()
    };
    let (x0, x1) = x_range(categories, finite(x).into_iter());
    figure((900, 820), |root| {
        let root = root.titled(title, ("sans-serif", 22)).map_err(err)?;
        for (area, (label, values)) in root.split_evenly((3, 1)).iter().zip(panels) {
            let m = finite(values)
                .iter()
                .fold(0.0f64, |a, v| a.max(v.abs()))
                .max(1e-9)
                * 1.1;
            let mut chart = ChartBuilder::on(area)
                .margin(10)
                .x_label_area_size(40)
                .y_label_area_size(70)
                .build_cartesian_2d(span(x0, x1)?, span(-m, m)?)
                .map_err(err)?;
            let points: Vec<(f64, f64)> = x
                .iter()
                .zip(values)
                .filter(|(a, b)| a.is_finite() && b.is_finite())
                .map(|(&a, &b)| (a, b))
                .collect();
            let pixels: Vec<(i32, i32)> = points.iter().map(|p| chart.backend_coord(p)).collect();
            let (kept, cell) = one_per_cell(&pixels, MAX_MARKERS);
            let x_desc = match cell {
                None => x_label.to_string(),
                Some(cell) => format!(
                    "{x_label} — {} of {} readings drawn (one per {cell}-px cell)",
                    kept.len(),
                    points.len()
                ),
            };
            category_mesh(&mut chart, &x_desc, label, categories)?;
            chart
                .draw_series(
                    kept.iter()
                        .map(|&k| Circle::new(points[k], 2, RGBColor(30, 90, 200).filled())),
                )
                .map_err(err)?;
            chart
                .draw_series(LineSeries::new([(x0, 0.0), (x1, 0.0)], BLACK.mix(0.4)))
                .map_err(err)?;
        }
        Ok(())
    })
}

/// A fitted shape with its standard uncertainty (the "what is left" of a
/// diagnosis): each point's value with a ±2u bar, joined by a line along a
/// numeric x, or one bar per named column (`categories`) — with the zero
/// line, against which a shape is judged.
pub fn fitted_shape(
    title: &str,
    x_label: &str,
    y_label: &str,
    categories: Option<&[String]>,
    points: &[(f64, f64, f64)],
) -> Result<String> {
    let ok: Vec<(f64, f64, f64)> = points
        .iter()
        .copied()
        .filter(|p| p.0.is_finite() && p.1.is_finite())
        .map(|(x, v, u)| (x, v, if u.is_finite() { 2.0 * u } else { 0.0 }))
        .collect();
    let (x0, x1) = x_range(categories, ok.iter().map(|p| p.0));
    let (y0, y1) = bounds(ok.iter().flat_map(|p| [p.1 - p.2, p.1 + p.2]).chain([0.0]));
    figure((1000, 560), |root| {
        let mut chart = ChartBuilder::on(root)
            .margin(20)
            .caption(title, ("sans-serif", 20))
            .x_label_area_size(if categories.is_some() { 70 } else { 45 })
            .y_label_area_size(70)
            .build_cartesian_2d(span(x0, x1)?, span(y0, y1)?)
            .map_err(err)?;
        category_mesh(
            &mut chart,
            x_label,
            &format!("fitted value ({y_label}), bars ± 2u"),
            categories,
        )?;
        let colour = RGBColor(30, 90, 200);
        chart
            .draw_series(LineSeries::new([(x0, 0.0), (x1, 0.0)], BLACK.mix(0.4)))
            .map_err(err)?;
        if categories.is_none() {
            chart
                .draw_series(LineSeries::new(
                    ok.iter().map(|p| (p.0, p.1)),
                    colour.stroke_width(2),
                ))
                .map_err(err)?;
        }
        chart
            .draw_series(ok.iter().map(|p| {
                ErrorBar::new_vertical(p.0, p.1 - p.2, p.1, p.1 + p.2, colour.filled(), 6)
            }))
            .map_err(err)?;
        Ok(())
    })
}

/// A diverging colour map for signed values: blue (0) through white (0.5)
/// to red (1).
pub fn diverging(t: f64) -> RGBColor {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.5
    };
    let (lo, mid, hi) = (
        (33.0, 102.0, 172.0),
        (247.0, 247.0, 247.0),
        (178.0, 24.0, 43.0),
    );
    let (a, b, f) = if t < 0.5 {
        (lo, mid, t * 2.0)
    } else {
        (mid, hi, t * 2.0 - 1.0)
    };
    let lerp = |x: f64, y: f64| (x + f * (y - x)).round() as u8;
    RGBColor(lerp(a.0, b.0), lerp(a.1, b.1), lerp(a.2, b.2))
}

/// Where a colour bar sits in its area: the mesh figures give it a tall
/// strip of their own, the heat maps a narrow one beside each panel.
struct BarLayout {
    margin_top: u32,
    margin_bottom: u32,
    margin_right: u32,
    labels_px: u32,
    font_px: u32,
}

/// The bar beside a mesh figure.
const FIGURE_BAR: BarLayout = BarLayout {
    margin_top: 60,
    margin_bottom: 60,
    margin_right: 10,
    labels_px: 55,
    font_px: 12,
};

/// The bar beside one heat-map panel.
const PANEL_BAR: BarLayout = BarLayout {
    margin_top: 30,
    margin_bottom: 40,
    margin_right: 4,
    labels_px: 50,
    font_px: 11,
};

/// A vertical colour bar from `lo` to `hi` in the colour map `map`.
fn colour_bar(
    area: &DrawingArea<SVGBackend, Shift>,
    lo: f64,
    hi: f64,
    label: &str,
    map: fn(f64) -> RGBColor,
    layout: &BarLayout,
) -> Result<()> {
    let mut chart = ChartBuilder::on(area)
        .margin_top(layout.margin_top)
        .margin_bottom(layout.margin_bottom)
        .margin_right(layout.margin_right)
        .y_label_area_size(0)
        .right_y_label_area_size(layout.labels_px)
        .build_cartesian_2d(0.0..1.0, span(lo, hi)?)
        .map_err(err)?;
    chart
        .configure_mesh()
        .disable_x_mesh()
        .disable_y_mesh()
        .disable_x_axis()
        .y_desc(label)
        .y_labels(6)
        .label_style(("sans-serif", layout.font_px))
        .draw()
        .map_err(err)?;
    let n = 64;
    let step = (hi - lo) / n as f64;
    chart
        .draw_series((0..n).map(|i| {
            let a = lo + i as f64 * step;
            Rectangle::new(
                [(0.0, a), (1.0, a + step)],
                map((i as f64 + 0.5) / n as f64).filled(),
            )
        }))
        .map_err(err)?;
    Ok(())
}

/// One heat map: `z[i][j]` at `(x[j], y[i])`, each cell a rectangle with its
/// value written in it, coloured by `map` over `lo … hi`.
struct HeatMap<'a> {
    caption: &'a str,
    x_desc: &'a str,
    y_desc: &'a str,
    x: &'a [f64],
    y: &'a [f64],
    z: &'a [Vec<f64>],
    lo: f64,
    hi: f64,
    map: fn(f64) -> RGBColor,
    bar_label: &'a str,
}

fn heat_map(area: &DrawingArea<SVGBackend, Shift>, h: &HeatMap) -> Result<()> {
    let (plot, bar) = area.split_horizontally(area.dim_in_pixel().0 as i32 - 85);
    // Cells centred on the grid values, as wide as the spacing.
    let half = |v: &[f64], k: usize| {
        // A lone value gets a cell of width 1.
        let left = if k > 0 {
            v[k] - v[k - 1]
        } else if v.len() > 1 {
            v[1] - v[0]
        } else {
            1.0
        };
        let right = if k + 1 < v.len() {
            v[k + 1] - v[k]
        } else {
            left
        };
        (v[k] - left / 2.0, v[k] + right / 2.0)
    };
    let (x0, x1) = (half(h.x, 0).0, half(h.x, h.x.len() - 1).1);
    let (y0, y1) = (half(h.y, 0).0, half(h.y, h.y.len() - 1).1);
    let mut chart = ChartBuilder::on(&plot)
        .margin(8)
        .caption(h.caption, ("sans-serif", 14))
        .x_label_area_size(34)
        .y_label_area_size(44)
        .build_cartesian_2d(span(x0, x1)?, span(y0, y1)?)
        .map_err(err)?;
    chart
        .configure_mesh()
        .disable_mesh()
        .x_desc(h.x_desc)
        .y_desc(h.y_desc)
        .x_labels(0)
        .y_labels(0)
        .label_style(("sans-serif", 10))
        .draw()
        .map_err(err)?;
    // A label at each cell's centre: plotters' own round ticks (every 10°)
    // fell between cells 7.5° apart.
    let tick = |anchor: Pos| ("sans-serif", 10).into_text_style(&plot).pos(anchor);
    let (bx, by) = plot.get_base_pixel();
    let at = |v| {
        let (px, py) = chart.backend_coord(&v);
        (px - bx, py - by)
    };
    for &x in h.x {
        let (px, py) = at((x, y0));
        plot.draw_text(
            &format!("{x}"),
            &tick(Pos::new(HPos::Center, VPos::Top)),
            (px, py + 4),
        )
        .map_err(err)?;
    }
    for &y in h.y {
        let (px, py) = at((x0, y));
        plot.draw_text(
            &format!("{y}"),
            &tick(Pos::new(HPos::Right, VPos::Center)),
            (px - 4, py),
        )
        .map_err(err)?;
    }
    let span = (h.hi - h.lo).max(1e-12);
    for (i, row) in h.z.iter().enumerate() {
        // A cell without a value (NaN) stays blank.
        for (j, &v) in row.iter().enumerate().filter(|(_, v)| v.is_finite()) {
            let ((a, b), (c, d)) = (half(h.x, j), half(h.y, i));
            let t = (v - h.lo) / span;
            chart
                .draw_series(std::iter::once(Rectangle::new(
                    [(a, c), (b, d)],
                    (h.map)(t).filled(),
                )))
                .map_err(err)?;
            // Dark text on light cells, light on dark.
            let RGBColor(r, g, bl) = (h.map)(t);
            let light = 0.299 * r as f64 + 0.587 * g as f64 + 0.114 * bl as f64 > 140.0;
            let colour = if light { BLACK } else { WHITE };
            chart
                .draw_series(std::iter::once(Text::new(
                    crate::table::format_float(v, 1),
                    (h.x[j], h.y[i]),
                    ("sans-serif", 9).into_font().color(&colour).pos(
                        plotters::style::text_anchor::Pos::new(
                            plotters::style::text_anchor::HPos::Center,
                            plotters::style::text_anchor::VPos::Center,
                        ),
                    ),
                )))
                .map_err(err)?;
        }
    }
    colour_bar(&bar, h.lo, h.hi, h.bar_label, h.map, &PANEL_BAR)
}

/// One fitted model of an incidence grid, for [`incidence_maps`].
pub struct FitMaps<'a> {
    pub label: String,
    pub fitted: &'a [Vec<f64>],
}

/// Table 9 and its fits: one row per model — the data, the fit and the
/// residual (data − fit) as heat maps over `(α_h, α_v)`. Data and fits share
/// one colour scale; residuals share a symmetric one.
pub fn incidence_maps(
    title: &str,
    alpha_h_deg: &[f64],
    alpha_v_deg: &[f64],
    data_um: &[Vec<f64>],
    fits: &[FitMaps],
) -> Result<String> {
    let all = data_um
        .iter()
        .chain(fits.iter().flat_map(|f| f.fitted.iter()))
        .flatten()
        .copied();
    let (lo, hi) = all.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
        (a.min(v), b.max(v))
    });
    let residuals: Vec<Vec<Vec<f64>>> = fits
        .iter()
        .map(|f| {
            data_um
                .iter()
                .zip(f.fitted)
                .map(|(d, m)| d.iter().zip(m).map(|(a, b)| a - b).collect())
                .collect()
        })
        .collect();
    let r = residuals
        .iter()
        .flatten()
        .flatten()
        .fold(0.0f64, |a, v| a.max(v.abs()))
        .max(1e-9);
    let rows = fits.len().max(1);
    figure((1500, 440 * rows as u32 + 50), |root| {
        let root = root.titled(title, ("sans-serif", 22)).map_err(err)?;
        let cells = root.split_evenly((rows, 3));
        for (k, f) in fits.iter().enumerate() {
            let data_caption = "Table 9: measured (µm)".to_string();
            let fit_caption = format!("{}: fit (µm)", f.label);
            let res_caption = format!("{}: data − fit (µm)", f.label);
            let maps = [
                HeatMap {
                    caption: &data_caption,
                    x_desc: "α_h (deg)",
                    y_desc: "α_v (deg)",
                    x: alpha_h_deg,
                    y: alpha_v_deg,
                    z: data_um,
                    lo,
                    hi,
                    map: viridis,
                    bar_label: "reading (µm)",
                },
                HeatMap {
                    caption: &fit_caption,
                    x_desc: "α_h (deg)",
                    y_desc: "α_v (deg)",
                    x: alpha_h_deg,
                    y: alpha_v_deg,
                    z: f.fitted,
                    lo,
                    hi,
                    map: viridis,
                    bar_label: "reading (µm)",
                },
                HeatMap {
                    caption: &res_caption,
                    x_desc: "α_h (deg)",
                    y_desc: "α_v (deg)",
                    x: alpha_h_deg,
                    y: alpha_v_deg,
                    z: &residuals[k],
                    lo: -r,
                    hi: r,
                    map: diverging,
                    bar_label: "residual (µm)",
                },
            ];
            for (c, m) in maps.iter().enumerate() {
                heat_map(&cells[3 * k + c], m)?;
            }
        }
        Ok(())
    })
}

/// One view of an uncertainty field, for [`uncertainty_field`]: `u_um[i][j]`
/// at `(x_m[j], y_m[i])`, NaN where nothing is measured.
pub struct FieldView<'a> {
    pub caption: String,
    pub x_desc: &'a str,
    pub y_desc: &'a str,
    pub x_m: &'a [f64],
    pub y_m: &'a [f64],
    pub u_um: &'a [Vec<f64>],
}

/// The uncertainty of a measurement after calibration over the volume
/// (SpatialAnalyzer's "uncertainty field"): one heat map per view, two per
/// row, all on one colour scale from zero.
pub fn uncertainty_field(title: &str, views: &[FieldView]) -> Result<String> {
    let hi = views
        .iter()
        .flat_map(|v| v.u_um.iter().flatten())
        .copied()
        .filter(|u| u.is_finite())
        .fold(0.0f64, f64::max)
        .max(1e-9);
    let rows = views.len().div_ceil(2).max(1);
    figure((1500, 640 * rows as u32 + 50), |root| {
        let root = root.titled(title, ("sans-serif", 22)).map_err(err)?;
        for (area, v) in root.split_evenly((rows, 2)).iter().zip(views) {
            heat_map(
                area,
                &HeatMap {
                    caption: &v.caption,
                    x_desc: v.x_desc,
                    y_desc: v.y_desc,
                    x: v.x_m,
                    y: v.y_m,
                    z: v.u_um,
                    lo: 0.0,
                    hi,
                    map: viridis,
                    bar_label: "standard uncertainty (µm)",
                },
            )?;
        }
        Ok(())
    })
}

/// One row of [`coverage_intervals`]: a quantity's Monte Carlo coverage
/// interval in units of its linear standard uncertainty, about the
/// nominal value (`low_u`, `high_u`), and the linear interval's half-width
/// (1.96 for 95 %).
pub struct CoverageRow {
    pub label: String,
    pub low_u: f64,
    pub high_u: f64,
    pub linear_u: f64,
}

/// Monte Carlo coverage intervals beside the linear ones, one row per
/// quantity, all in units of the linear standard uncertainty: where the
/// problem is linear the two bars coincide.
pub fn coverage_intervals(title: &str, rows: &[CoverageRow]) -> Result<String> {
    let n = rows.len().max(1);
    let reach = rows
        .iter()
        .flat_map(|r| [r.low_u.abs(), r.high_u.abs(), r.linear_u])
        .filter(|v| v.is_finite())
        .fold(2.0f64, f64::max)
        * 1.15;
    // Room on the right beyond the longest bar, where the legend goes.
    let (left, right) = (-reach, reach * 1.6);
    figure((900, 90 + 30 * n as u32 + 70), |root| {
        let root = root.titled(title, ("sans-serif", 18)).map_err(err)?;
        let mut chart = ChartBuilder::on(&root)
            .margin(14)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(span(left, right)?, (0..n - 1).into_segmented())
            .map_err(err)?;
        chart
            .configure_mesh()
            .disable_y_mesh()
            .x_desc("coverage interval about the nominal value, in linear standard uncertainties")
            .y_labels(n)
            .y_label_formatter(&|v| match v {
                SegmentValue::CenterOf(i) => rows
                    .get(n - 1 - *i)
                    .map(|r| r.label.clone())
                    .unwrap_or_default(),
                _ => String::new(),
            })
            .label_style(("sans-serif", 12))
            .draw()
            .map_err(err)?;
        let linear = RGBColor(190, 190, 190);
        let mc = RGBColor(44, 113, 142);
        chart
            .draw_series(rows.iter().rev().enumerate().map(|(i, r)| {
                let mut bar = Rectangle::new(
                    [
                        (-r.linear_u, SegmentValue::Exact(i)),
                        (r.linear_u, SegmentValue::Exact(i + 1)),
                    ],
                    linear.filled(),
                );
                bar.set_margin(4, 4, 0, 0);
                bar
            }))
            .map_err(err)?
            .label(format!(
                "linear: ±{:.2} u",
                rows.first().map_or(1.96, |r| r.linear_u)
            ))
            .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 14, y + 5)], linear.filled()));
        chart
            .draw_series(rows.iter().rev().enumerate().map(|(i, r)| {
                let mut bar = Rectangle::new(
                    [
                        (r.low_u, SegmentValue::Exact(i)),
                        (r.high_u, SegmentValue::Exact(i + 1)),
                    ],
                    mc.filled(),
                );
                bar.set_margin(11, 11, 0, 0);
                bar
            }))
            .map_err(err)?
            .label("Monte Carlo")
            .legend(move |(x, y)| Rectangle::new([(x, y - 3), (x + 14, y + 3)], mc.filled()));
        let ends = rows.iter().rev().enumerate().flat_map(|(i, r)| {
            [r.low_u, r.high_u, -r.linear_u, r.linear_u]
                .into_iter()
                .flat_map(move |x| [(x, SegmentValue::Exact(i)), (x, SegmentValue::Exact(i + 1))])
        });
        let linear_label = format!(
            "linear: ±{:.2} u",
            rows.first().map_or(1.96, |r| r.linear_u)
        );
        legend_clear_of(&mut chart, ends, &[&linear_label, "Monte Carlo"], 12)?;
        Ok(())
    })
}

/// A reflector or station in plan (metres) for [`uncertainty_ellipses`],
/// with the covariance of its x, y (mm²: `[xx, xy, yy]`) when it has one.
pub struct PlanPoint {
    pub label: String,
    pub x_m: f64,
    pub y_m: f64,
    pub cov_xy_mm2: Option<[f64; 3]>,
}

/// The standard deviations along the principal axes of a 2×2 covariance
/// `[xx, xy, yy]`, largest first, and the angle of the first from x (rad).
fn principal_axes(c: &[f64; 3]) -> (f64, f64, f64) {
    let [xx, xy, yy] = *c;
    let mean = (xx + yy) / 2.0;
    let r = (((xx - yy) / 2.0).powi(2) + xy * xy).sqrt();
    let angle = 0.5 * (2.0 * xy).atan2(xx - yy);
    (
        (mean + r).max(0.0).sqrt(),
        (mean - r).max(0.0).sqrt(),
        angle,
    )
}

/// Reflector uncertainty ellipses from the network in plan: each
/// reflector's 95 % ellipse of (x, y) — `2.448 σ` along the covariance's
/// principal axes — magnified by the factor in the caption; stations as
/// triangles.
pub fn uncertainty_ellipses(
    title: &str,
    stations: &[PlanPoint],
    targets: &[PlanPoint],
) -> Result<String> {
    let axes = principal_axes;
    let all = stations.iter().chain(targets);
    let (mut x0, mut x1, mut y0, mut y1) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    for p in all.clone() {
        x0 = x0.min(p.x_m);
        x1 = x1.max(p.x_m);
        y0 = y0.min(p.y_m);
        y1 = y1.max(p.y_m);
    }
    let extent = (x1 - x0).max(y1 - y0).max(1.0);
    let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
    let half = extent * 0.6;
    let largest_mm = targets
        .iter()
        .filter_map(|p| p.cov_xy_mm2.as_ref())
        .map(|c| axes(c).0 * 2.448)
        .fold(0.0f64, f64::max);
    // A round magnification that makes the largest ellipse 4 % of the
    // plot: 1, 2 or 5 times a power of ten.
    let magnification = if largest_mm > 0.0 {
        round_below(0.04 * extent * 1000.0 / largest_mm)
    } else {
        1.0
    };
    figure((900, 900), |root| {
        let caption = format!("{title} — 95 % ellipses magnified ×{magnification}");
        let root = root.titled(&caption, ("sans-serif", 16)).map_err(err)?;
        let mut chart = ChartBuilder::on(&root)
            .margin(14)
            .x_label_area_size(40)
            .y_label_area_size(50)
            .build_cartesian_2d(span(cx - half, cx + half)?, span(cy - half, cy + half)?)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc("x (m)")
            .y_desc("y (m)")
            .label_style(("sans-serif", 12))
            .draw()
            .map_err(err)?;
        let ink = RGBColor(44, 113, 142);
        let red = RGBColor(200, 60, 40);
        let k = 2.448 * magnification / 1000.0;
        let rings: Vec<Vec<(f64, f64)>> = targets
            .iter()
            .filter_map(|p| {
                let (a, b, angle) = axes(p.cov_xy_mm2.as_ref()?);
                let (sn, cs) = angle.sin_cos();
                Some(
                    (0..=64)
                        .map(|i| {
                            let t = i as f64 / 64.0 * std::f64::consts::TAU;
                            let (u, v) = (k * a * t.cos(), k * b * t.sin());
                            (p.x_m + u * cs - v * sn, p.y_m + u * sn + v * cs)
                        })
                        .collect(),
                )
            })
            .collect();
        chart
            .draw_series(
                rings
                    .iter()
                    .map(|ring| PathElement::new(ring.clone(), ink.stroke_width(2))),
            )
            .map_err(err)?
            .label(format!("95 % ellipse, ×{magnification}"))
            .legend(move |(x, y)| Circle::new((x + 8, y), 6, ink.stroke_width(2)));
        chart
            .draw_series(
                targets
                    .iter()
                    .map(|p| Circle::new((p.x_m, p.y_m), 2, BLACK.filled())),
            )
            .map_err(err)?
            .label("reflector")
            .legend(|(x, y)| Circle::new((x + 8, y), 2, BLACK.filled()));
        chart
            .draw_series(
                stations
                    .iter()
                    .map(|s| TriangleMarker::new((s.x_m, s.y_m), 7, red.filled())),
            )
            .map_err(err)?
            .label("station")
            .legend(move |(x, y)| TriangleMarker::new((x + 8, y), 7, red.filled()));
        // Reflectors at one plan position (several heights) share a label:
        // one each printed "T09" over "T17".
        let mut places: Vec<(f64, f64, Vec<&str>)> = Vec::new();
        for p in targets {
            match places
                .iter_mut()
                .find(|(x, y, _)| (x - p.x_m).hypot(y - p.y_m) < 0.01 * extent)
            {
                Some((_, _, names)) => names.push(&p.label),
                None => places.push((p.x_m, p.y_m, vec![&p.label])),
            }
        }
        chart
            .draw_series(places.iter().map(|(x, y, names)| {
                Text::new(names.join(", "), (*x, *y), ("sans-serif", 10).into_font())
            }))
            .map_err(err)?;
        chart
            .draw_series(stations.iter().map(|s| {
                Text::new(
                    s.label.clone(),
                    (s.x_m, s.y_m),
                    ("sans-serif", 12).into_font(),
                )
            }))
            .map_err(err)?;
        // The magnification's scale: a round true length whose drawn
        // segment fits the legend's marker column.
        let at = |x: f64| chart.as_coord_spec().translate(&(x, cy)).0;
        let px_per_mm = f64::from(at(cx + k) - at(cx)) / 2.448;
        let scale_mm = round_below(24.0 / px_per_mm.max(1e-300));
        let scale_px = (scale_mm * px_per_mm).round() as i32;
        chart
            .draw_series(std::iter::empty::<Circle<(f64, f64), i32>>())
            .map_err(err)?
            .label(format!("{} (true size)", length_label(scale_mm)))
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + scale_px, y)], BLACK.stroke_width(2))
            });
        let drawn: Vec<(f64, f64)> = rings
            .iter()
            .flatten()
            .copied()
            .chain(stations.iter().chain(targets).map(|p| (p.x_m, p.y_m)))
            .collect();
        let labels = [
            format!("95 % ellipse, ×{magnification}"),
            "reflector".into(),
            "station".into(),
            format!("{} (true size)", length_label(scale_mm)),
        ];
        let labels: Vec<&str> = labels.iter().map(String::as_str).collect();
        legend_clear_of(&mut chart, drawn.into_iter(), &labels, 12)?;
        Ok(())
    })
}

/// The largest 1, 2 or 5 × 10ⁿ not above `v` (> 0).
fn round_below(v: f64) -> f64 {
    let p = 10f64.powf(v.log10().floor());
    [5.0, 2.0, 1.0]
        .into_iter()
        .map(|m| m * p)
        .find(|m| *m <= v)
        .unwrap_or(p)
}

/// A length in mm written in the unit that keeps it between 1 and 1000:
/// "20 nm", "5 µm", "2 mm".
fn length_label(mm: f64) -> String {
    if mm >= 1.0 {
        format!("{mm} mm")
    } else if mm >= 1e-3 {
        format!("{} µm", (mm * 1e3 * 1e6).round() / 1e6)
    } else {
        format!("{} nm", (mm * 1e6 * 1e6).round() / 1e6)
    }
}

/// Layout design: one panel of horizontal bars per quantity (σ_min, O1, …),
/// one bar per layout, the value written at its end.
pub fn layout_bars(title: &str, names: &[&str], panels: &[(&str, &[f64])]) -> Result<String> {
    let n = names.len().max(1);
    figure((1200, 60 + 34 * n as u32 + 120), |root| {
        let root = root.titled(title, ("sans-serif", 20)).map_err(err)?;
        let areas = root.split_evenly((1, panels.len().max(1)));
        for (area, (label, values)) in areas.iter().zip(panels) {
            let top = values.iter().copied().fold(0.0, f64::max).max(1e-12) * 1.25;
            let mut chart = ChartBuilder::on(area)
                .margin(12)
                .x_label_area_size(40)
                .y_label_area_size(150)
                // n segments, the first layout at the top.
                .build_cartesian_2d(span(0.0, top)?, (0..n - 1).into_segmented())
                .map_err(err)?;
            chart
                .configure_mesh()
                .disable_y_mesh()
                .light_line_style(WHITE)
                .x_desc(*label)
                .y_labels(n)
                .y_label_formatter(&|v| match v {
                    SegmentValue::CenterOf(i) => {
                        names.get(n - 1 - *i).copied().unwrap_or("").to_string()
                    }
                    _ => String::new(),
                })
                .label_style(("sans-serif", 12))
                .draw()
                .map_err(err)?;
            chart
                .draw_series(values.iter().rev().enumerate().map(|(i, &v)| {
                    let mut bar = Rectangle::new(
                        [
                            (0.0, SegmentValue::Exact(i)),
                            (v, SegmentValue::Exact(i + 1)),
                        ],
                        RGBColor(44, 113, 142).filled(),
                    );
                    bar.set_margin(5, 5, 0, 0);
                    bar
                }))
                .map_err(err)?;
            chart
                .draw_series(values.iter().rev().enumerate().map(|(i, &v)| {
                    Text::new(
                        format!(" {v:.3}"),
                        (v, SegmentValue::CenterOf(i)),
                        ("sans-serif", 11).into_font().color(&BLACK).pos(
                            plotters::style::text_anchor::Pos::new(
                                plotters::style::text_anchor::HPos::Left,
                                plotters::style::text_anchor::VPos::Center,
                            ),
                        ),
                    )
                }))
                .map_err(err)?;
        }
        Ok(())
    })
}

/// A 12-point label on a drawing area at pixel `at`, anchored as given.
fn label_at(
    area: &DrawingArea<SVGBackend, Shift>,
    text: &str,
    at: (i32, i32),
    h: HPos,
) -> Result<()> {
    let style = ("sans-serif", 12)
        .into_text_style(area)
        .pos(Pos::new(h, VPos::Top));
    area.draw_text(text, &style, at).map_err(err)
}

/// A confusion matrix: counts of true classes (rows) against named ones
/// (columns), the diagonal shaded green and the rest red by count.
pub fn confusion_matrix(title: &str, labels: &[String], counts: &[Vec<usize>]) -> Result<String> {
    let n = labels.len();
    let max = counts.iter().flatten().copied().max().unwrap_or(0).max(1) as f64;
    figure((980, 760), |root| {
        let mut chart = ChartBuilder::on(root)
            .margin(20)
            .caption(title, ("sans-serif", 18))
            .x_label_area_size(90)
            .y_label_area_size(150)
            .build_cartesian_2d(-0.5..n as f64 - 0.5, -0.5..n as f64 - 0.5)
            .map_err(err)?;
        chart
            .configure_mesh()
            .disable_mesh()
            .x_labels(0)
            .y_labels(0)
            .x_desc("named by the diagnosis")
            .y_desc("true effect")
            .label_style(("sans-serif", 12))
            .draw()
            .map_err(err)?;
        let green = |t: f64| {
            RGBColor(
                (230.0 - 170.0 * t) as u8,
                (245.0 - 85.0 * t) as u8,
                (230.0 - 170.0 * t) as u8,
            )
        };
        let red = |t: f64| RGBColor(250, (225.0 - 150.0 * t) as u8, (225.0 - 150.0 * t) as u8);
        let centred = ("sans-serif", 16)
            .into_font()
            .into_text_style(root)
            .pos(Pos::new(HPos::Center, VPos::Center));
        for (i, row) in counts.iter().enumerate() {
            for (j, &c) in row.iter().enumerate() {
                let y = (n - 1 - i) as f64 - 0.5;
                let x = j as f64 - 0.5;
                let t = c as f64 / max;
                let colour = if c == 0 {
                    RGBColor(245, 245, 245)
                } else if i == j {
                    green(t)
                } else {
                    red(t)
                };
                chart
                    .draw_series(std::iter::once(Rectangle::new(
                        [(x + 0.03, y + 0.03), (x + 0.97, y + 0.97)],
                        colour.filled(),
                    )))
                    .map_err(err)?;
                chart
                    .draw_series(std::iter::once(Text::new(
                        c.to_string(),
                        (x + 0.5, y + 0.5),
                        centred.clone(),
                    )))
                    .map_err(err)?;
            }
        }
        // The colour key, under the row names: a shade per count, green
        // where the diagnosis named the true effect, red where it did not.
        for (k, (name, shade)) in [
            ("named right", &green as &dyn Fn(f64) -> RGBColor),
            ("named wrong", &red),
        ]
        .into_iter()
        .enumerate()
        {
            let y = 690 + 24 * k as i32;
            label_at(root, name, (20, y), HPos::Left)?;
            for step in 0..10 {
                let x = 100 + 8 * step;
                root.draw(&Rectangle::new(
                    [(x, y), (x + 8, y + 14)],
                    shade((step as f64 + 0.5) / 10.0).filled(),
                ))
                .map_err(err)?;
            }
            label_at(root, "1", (96, y), HPos::Right)?;
            label_at(root, &format!("{max}"), (184, y), HPos::Left)?;
        }
        // The class names under and beside the cells' centres.
        for (i, name) in labels.iter().enumerate() {
            let (px, py) = chart.backend_coord(&(i as f64, -0.5));
            label_at(root, name, (px, py + 8), HPos::Center)?;
            let (px, py) = chart.backend_coord(&(-0.5, (n - 1 - i) as f64));
            label_at(root, name, (px - 8, py - 6), HPos::Right)?;
        }
        Ok(())
    })
}

/// One line of [`metric_lines`]: `(x, mean, sd, n)` per point.
pub struct MetricLine {
    pub name: String,
    pub points: Vec<(f64, f64, f64, usize)>,
}

/// A metric against a swept parameter: one line per series, each point the
/// mean over repeats (seeds) with a ±1 standard deviation bar.
pub fn metric_lines(
    title: &str,
    x_label: &str,
    y_label: &str,
    lines: &[MetricLine],
) -> Result<String> {
    let all = lines.iter().flat_map(|l| l.points.iter());
    let (x0, x1) = bounds(all.clone().map(|p| p.0));
    let (y0, y1) = bounds(all.flat_map(|p| [p.1 - p.2, p.1 + p.2]));
    figure((1000, 600), |root| {
        let mut chart = ChartBuilder::on(root)
            .margin(20)
            .caption(title, ("sans-serif", 22))
            .x_label_area_size(45)
            .y_label_area_size(70)
            .build_cartesian_2d(span(x0, x1)?, span(y0, y1)?)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc(format!("{y_label} (mean ± 1 sd over repeats)"))
            .label_style(("sans-serif", 13))
            .draw()
            .map_err(err)?;
        for (k, line) in lines.iter().enumerate() {
            let colour = viridis(
                if lines.len() > 1 {
                    k as f64 / (lines.len() - 1) as f64
                } else {
                    0.3
                } * 0.9,
            );
            // A marker shape per line as well as a colour: ten viridis
            // lines cannot be told apart in greyscale, or by many readers.
            let marker = k % 4;
            let shape = move |(x, y): (f64, f64),
                              c: RGBColor|
                  -> DynElement<'static, SVGBackend, (f64, f64)> {
                match marker {
                    0 => Circle::new((x, y), 4, c.filled()).into_dyn(),
                    1 => TriangleMarker::new((x, y), 5, c.filled()).into_dyn(),
                    2 => Cross::new((x, y), 4, c.stroke_width(2)).into_dyn(),
                    _ => Rectangle::new([(x, y), (x, y)], c.stroke_width(7)).into_dyn(),
                }
            };
            chart
                .draw_series(LineSeries::new(
                    line.points.iter().map(|p| (p.0, p.1)),
                    colour.stroke_width(2),
                ))
                .map_err(err)?
                .label(line.name.clone())
                .legend(move |(x, y)| {
                    EmptyElement::at((x, y))
                        + PathElement::new(vec![(0, 0), (20, 0)], colour.stroke_width(2))
                        + match marker {
                            0 => Circle::new((10, 0), 4, colour.filled()).into_dyn(),
                            1 => TriangleMarker::new((10, 0), 5, colour.filled()).into_dyn(),
                            2 => Cross::new((10, 0), 4, colour.stroke_width(2)).into_dyn(),
                            _ => Rectangle::new([(7, -3), (13, 3)], colour.filled()).into_dyn(),
                        }
                });
            chart
                .draw_series(line.points.iter().map(|p| shape((p.0, p.1), colour)))
                .map_err(err)?;
            chart
                .draw_series(line.points.iter().map(|p| {
                    ErrorBar::new_vertical(p.0, p.1 - p.2, p.1, p.1 + p.2, colour.filled(), 6)
                }))
                .map_err(err)?;
        }
        let names: Vec<&str> = lines.iter().map(|l| l.name.as_str()).collect();
        legend_clear_of(
            &mut chart,
            lines
                .iter()
                .flat_map(|l| l.points.iter().map(|p| (p.0, p.1))),
            &names,
            14,
        )?;
        Ok(())
    })
}

/// Grouped bars: one group per category, one bar per series, with a
/// dashed reference level per series.
pub fn grouped_bars(
    title: &str,
    y_label: &str,
    categories: &[String],
    series: &[(String, Vec<f64>)],
    references: &[f64],
) -> Result<String> {
    let n_s = series.len().max(1);
    let (lo, hi) = series
        .iter()
        .flat_map(|s| s.1.iter().copied())
        .chain(references.iter().copied())
        .filter(|v| v.is_finite())
        .fold((0.0f64, 0.0f64), |(a, b), v| (a.min(v), b.max(v)));
    // Head room for the legend above the tallest bar.
    let hi = hi.max(1.0) * 1.35;
    let lo = if lo < 0.0 { lo * 1.08 } else { 0.0 };
    figure((1200, 620), |root| {
        let mut chart = ChartBuilder::on(root)
            .margin(20)
            .caption(title, ("sans-serif", 20))
            .x_label_area_size(60)
            .y_label_area_size(70)
            .build_cartesian_2d(-0.5..categories.len() as f64 - 0.5, span(lo, hi)?)
            .map_err(err)?;
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_labels(0)
            .y_desc(y_label)
            .label_style(("sans-serif", 12))
            .draw()
            .map_err(err)?;
        let width = 0.8 / n_s as f64;
        for (k, (name, values)) in series.iter().enumerate() {
            let colour = viridis(k as f64 / (n_s.max(2) - 1) as f64 * 0.85);
            chart
                .draw_series(
                    values
                        .iter()
                        .enumerate()
                        .filter(|(_, v)| v.is_finite())
                        .map(|(i, &v)| {
                            let x = i as f64 - 0.4 + k as f64 * width;
                            Rectangle::new([(x, 0.0), (x + width * 0.9, v)], colour.filled())
                        }),
                )
                .map_err(err)?
                .label(name.clone())
                .legend(move |(x, y)| {
                    Rectangle::new([(x, y - 5), (x + 12, y + 5)], colour.filled())
                });
            if let Some(&r) = references.get(k) {
                chart
                    .draw_series(DashedLineSeries::new(
                        [(-0.5, r), (categories.len() as f64 - 0.5, r)],
                        6,
                        4,
                        colour.stroke_width(2),
                    ))
                    .map_err(err)?;
            }
        }
        legend(&mut chart, SeriesLabelPosition::UpperRight, 13)?;
        // Category names under each group, long ones over two lines.
        for (i, name) in categories.iter().enumerate() {
            let (px, py) = chart.backend_coord(&(i as f64, lo));
            let lines: Vec<&str> = match name.split_once(" + ") {
                Some((a, b)) if name.len() > 18 => vec![a, b],
                _ => vec![name.as_str()],
            };
            for (k, line) in lines.iter().enumerate() {
                let text = if k > 0 {
                    format!("+ {line}")
                } else {
                    line.to_string()
                };
                label_at(root, &text, (px, py + 8 + 15 * k as i32), HPos::Center)?;
            }
        }
        Ok(())
    })
}

/// The B89 sensitivity matrix: one row per parameter, one column per test
/// (named under it, rotated), each cell `|value| / the row's largest` on
/// viridis (grey where the test does not see the parameter), the row's
/// largest written at its end, the tests grouped under their columns, and
/// the colour scale beside.
pub fn sensitivity_matrix(
    title: &str,
    rows: &[String],
    col_groups: &[(String, usize)],
    col_labels: &[String],
    values: &[Vec<f64>],
) -> Result<String> {
    let (n_rows, n_cols) = (rows.len().max(1), values.first().map_or(1, Vec::len).max(1));
    let (cell_w, cell_h) = (12_i32, 22_i32);
    let (left, top) = (190_i32, 60_i32);
    let label_font = 10.0;
    let label_len = col_labels
        .iter()
        .map(|l| text_width_px(l, font_px(label_font)))
        .fold(0.0, f64::max)
        .ceil() as i32;
    let cells_right = left + cell_w * n_cols as i32;
    let width = cells_right + 110 + 120;
    let cells_bottom = top + cell_h * n_rows as i32;
    let height = cells_bottom + 8 + label_len + 50;
    figure((width as u32, height as u32), |root| {
        let style = ("sans-serif", 18).into_text_style(root);
        root.draw_text(title, &style, (20, 16)).map_err(err)?;
        for (i, (label, row)) in rows.iter().zip(values).enumerate() {
            let y = top + cell_h * i as i32;
            label_at(root, label, (left - 8, y + 4), HPos::Right)?;
            let max = row.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
            for (j, v) in row.iter().enumerate() {
                let x = left + cell_w * j as i32;
                let colour = if *v != 0.0 {
                    viridis(v.abs() / max)
                } else {
                    RGBColor(240, 240, 240)
                };
                root.draw(&Rectangle::new(
                    [(x, y), (x + cell_w - 1, y + cell_h - 2)],
                    colour.filled(),
                ))
                .map_err(err)?;
            }
            label_at(
                root,
                &format!("{max:.3}"),
                (cells_right + 8, y + 4),
                HPos::Left,
            )?;
        }
        // Each test's distance, height and azimuth, read downwards.
        let turned = ("sans-serif", label_font)
            .into_font()
            .transform(FontTransform::Rotate90)
            .into_text_style(root)
            .pos(Pos::new(HPos::Left, VPos::Center));
        for (j, label) in col_labels.iter().enumerate() {
            let x = left + cell_w * j as i32 + cell_w / 2;
            root.draw_text(label, &turned, (x, cells_bottom + 4))
                .map_err(err)?;
        }
        // The test groups under the columns, with a tick at each boundary.
        let y_axis = cells_bottom + 8 + label_len;
        let mut at = 0_i32;
        for (label, count) in col_groups {
            let (x0, w) = (left + cell_w * at, cell_w * *count as i32);
            root.draw(&PathElement::new(
                [(x0, y_axis), (x0, y_axis + 30)],
                BLACK.stroke_width(1),
            ))
            .map_err(err)?;
            label_at(root, label, (x0 + w / 2, y_axis + 14), HPos::Center)?;
            at += *count as i32;
        }
        label_at(
            root,
            "largest |sensitivity| of the row (µm per µm or µrad)",
            (cells_right + 100, top - 22),
            HPos::Right,
        )?;
        let bar = root.clone().shrink(
            (cells_right + 110, top - 10),
            (110, (cells_bottom - top + 20) as u32),
        );
        let layout = BarLayout {
            margin_top: 10,
            margin_bottom: 10,
            ..FIGURE_BAR
        };
        colour_bar(
            &bar,
            0.0,
            1.0,
            "|sensitivity| / row's largest",
            viridis,
            &layout,
        )?;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Helvetica's digits are 0.556 em, a space 0.278 em.
    #[test]
    fn text_widths_follow_helvetica_metrics() {
        assert!((text_width_px("10.0", 10.0) - 19.46).abs() < 1e-9);
        assert!((text_width_px("a b", 20.0) - 27.8).abs() < 1e-9);
        assert_eq!(text_width_px("", 12.0), 0.0);
    }

    /// Regression (issue 33): two edge labels aimed at one place; the
    /// second goes to its next candidate, and when every candidate is
    /// taken, to its first.
    #[test]
    fn a_label_goes_to_its_first_candidate_clear_of_the_others() {
        let mut taken = vec![[0.0, 0.0, 10.0, 10.0]];
        let at = place_label([(5.0, 5.0), (20.0, 5.0)], 8.0, 4.0, &mut taken);
        assert_eq!(at, (20.0, 5.0));
        assert_eq!(taken[1], [20.0, 3.0, 28.0, 7.0]);
        let at = place_label([(22.0, 5.0), (1.0, 1.0)], 8.0, 4.0, &mut taken);
        assert_eq!(at, (22.0, 5.0));
        assert_eq!(taken.len(), 3);
    }

    #[test]
    fn axis_titles_read_the_unit_from_the_column_name() {
        assert_eq!(axis_title("sigma_angle_urad"), "σ angle (µrad)");
        assert_eq!(axis_title("improvement_pct"), "improvement (%)");
        assert_eq!(axis_title("time_s"), "time (s)");
        assert_eq!(axis_title("velocity_um_per_min"), "velocity (µm/min)");
        assert_eq!(axis_title("table7_coordinates"), "table7 coordinates");
        // A bare unit is a word, not an empty stem.
        assert_eq!(axis_title("s"), "s");
        assert_eq!(axis_title("face"), "face");
    }

    /// An ellipse 3 × 1 turned by 30°: its covariance `R·diag(9, 1)·Rᵀ`
    /// gives back the axes and the angle.
    #[test]
    fn principal_axes_of_a_turned_covariance() {
        let (s, c) = 30f64.to_radians().sin_cos();
        let cov = [9.0 * c * c + s * s, 8.0 * c * s, 9.0 * s * s + c * c];
        let (a, b, angle) = principal_axes(&cov);
        assert!(
            (a - 3.0).abs() < 1e-12 && (b - 1.0).abs() < 1e-12,
            "{a} {b}"
        );
        assert!((angle - 30f64.to_radians()).abs() < 1e-12, "{angle}");
    }

    /// Regression (issue 12): a value of f64::MAX on an axis made the
    /// span ∞ and plotters' tick loop never ended; now it is refused.
    #[test]
    fn endless_loop_in_plots_is_an_undrawable_axis() {
        let x = [0.0, 10.0, f64::MAX];
        let r = [1.0, -1.0, 0.5];
        let e = residuals_by_factor("t", "time_s", None, &x, [("a", &r), ("b", &r), ("c", &r)])
            .unwrap_err();
        assert!(e.downcast_ref::<Undrawable>().is_some(), "{e}");
        let huge = [1.0, f64::MAX];
        assert!(
            residuals_by_factor(
                "t",
                "x",
                None,
                &x[..2],
                [("a", &huge[..]), ("b", &r[..2]), ("c", &r[..2])]
            )
            .is_err()
        );
    }

    /// Regression: the diagnosis page of a 24 000-reading network was
    /// 66 MB, each residual figure drawing every reading (9 MB an SVG). A
    /// panel now draws at most `MAX_MARKERS`, an outlier among them, and
    /// says how many of how many.
    #[test]
    fn report_html_of_a_big_network_was_66_mb_residual_figures_draw_at_most_max_markers() {
        let n = 24_000;
        let x: Vec<f64> = (0..n).map(|i| i as f64).collect();
        // Deterministic noise in ±1, and one outlier at 40.
        let mut r: Vec<f64> = (0..n)
            .map(|i| ((i * 7919 % 1000) as f64 / 500.0) - 1.0)
            .collect();
        r[12_345] = 40.0;
        let svg = residuals_by_factor(
            "big",
            "time (s)",
            None,
            &x,
            [("a", &r[..]), ("b", &r[..]), ("c", &r[..])],
        )
        .unwrap();
        let markers = svg.matches("<circle").count();
        assert!(markers <= 3 * MAX_MARKERS, "{markers} markers");
        assert!(markers >= 3 * MAX_MARKERS / 4, "{markers} markers");
        assert!(svg.len() < 500_000, "{} bytes", svg.len());
        let said = format!("of {n} readings drawn (one per ");
        assert_eq!(svg.matches(&said).count(), 3, "{said}");
        // The outlier is drawn in each panel: the topmost marker sits high.
        let tops: Vec<f64> = svg
            .match_indices("<circle")
            .map(|(at, _)| {
                let tag = &svg[at..at + svg[at..].find('>').unwrap()];
                let cy = tag
                    .split("cy=\"")
                    .nth(1)
                    .unwrap()
                    .split('"')
                    .next()
                    .unwrap();
                cy.parse::<f64>().unwrap()
            })
            .collect();
        let high = tops.iter().filter(|&&cy| cy < 60.0).count();
        assert!(high >= 1, "the outlier was thinned out");
        // Few readings: every one drawn, nothing said.
        let svg = residuals_by_factor(
            "small",
            "time (s)",
            None,
            &x[..100],
            [("a", &r[..100]), ("b", &r[..100]), ("c", &r[..100])],
        )
        .unwrap();
        assert_eq!(svg.matches("<circle").count(), 300);
        assert!(!svg.contains("readings drawn"));
    }

    #[test]
    fn one_per_cell_keeps_the_first_point_of_each_cell_and_every_isolated_one() {
        let pixels = [(0, 0), (1, 1), (10, 10), (11, 10), (100, 3)];
        assert_eq!(one_per_cell(&pixels, 5), (vec![0, 1, 2, 3, 4], None));
        assert_eq!(one_per_cell(&pixels, 4), (vec![0, 2, 4], Some(2)));
        // Cells of 13 px (2, 3, 4, 6, 9, 13): (0,0) and (10,10) share one.
        assert_eq!(one_per_cell(&pixels, 2), (vec![0, 4], Some(13)));
    }

    #[test]
    fn one_per_cell_on_a_grid_keeps_the_cells_a_hash_keeps() {
        // The definition: the first point of each cell, by a hash of cells.
        let by_hash = |pixels: &[(i32, i32)], max: usize| {
            let mut cell = 2;
            loop {
                let mut seen = std::collections::HashSet::new();
                let kept: Vec<usize> = (0..pixels.len())
                    .filter(|&i| {
                        seen.insert((pixels[i].0.div_euclid(cell), pixels[i].1.div_euclid(cell)))
                    })
                    .collect();
                if kept.len() <= max || cell >= 1 << 16 {
                    return (kept, Some(cell));
                }
                cell += (cell / 2).max(1);
            }
        };
        let mut state = 12345u64;
        let mut next = |m: i32| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 33) % m as u64) as i32 - m / 4
        };
        let canvas: Vec<(i32, i32)> = (0..5000).map(|_| (next(900), next(820))).collect();
        let mut spread = canvas.clone();
        // An outlier far off the canvas: the grid would be huge, a hash serves.
        spread.push((i32::MAX - 3, i32::MIN + 5));
        for pixels in [&canvas, &spread] {
            for max in [100, 1500, 4000] {
                assert_eq!(one_per_cell(pixels, max), by_hash(pixels, max));
            }
        }
    }

    #[test]
    fn mesh_errors_svg_has_title_axes_and_points() {
        let pts: Vec<PointError> = (0..20)
            .map(|i| PointError {
                x_mm: i as f64 * 100.0,
                y_mm: 50.0,
                z_mm: -20.0 * i as f64,
                before_um: 10.0 + i as f64,
                after_um: 0.01,
            })
            .collect();
        let svg = mesh_errors("Figure 6: errors in a plane mesh", &pts).unwrap();
        assert!(svg.starts_with("<svg"));
        assert!(svg.contains("Figure 6: errors in a plane mesh"));
        assert!(svg.contains("error (µm, log scale)"));
        assert!(svg.matches("<circle").count() >= 40);
    }
}
