//! `results/<pipeline>/index.html`: one page per pipeline (and one per
//! experiment, in its folder, naming its overrides), rewritten after
//! every run (a fully cached one too), readable straight from the file
//! system — every link and image is a relative path, nothing is fetched.
//!
//! It reads top down as a researcher does: what the pipeline reproduces
//! (the description line of its file), every SVG figure first, then the
//! stage graph coloured by status (`graph.svg`, beside the page), then the
//! tables grouped by stage — each stage a collapsible section, listed in an
//! index with its table count, so that a pipeline of 110 tables is a page of
//! headings, not a wall — then a sweep's gathered tables, then the run
//! (each stage's status, why it ran, how long it took). A table of at most
//! [`MAX_ROWS`] rows is shown whole, a larger one previewed by its first
//! [`PREVIEW_ROWS`] rows; each links its Parquet file.
//!
//! Numbers are rounded for reading only ([`cell_texts`]): to two
//! significant digits of their uncertainty where the table carries one
//! (`x` beside `x_u` or `u_x`, `value` beside `std`), else to 4 significant
//! digits. The Parquet (and CSV) files keep them in full.
//!
//! A small script marks each image `data-status="loaded"` or `"failed"` once
//! the page has loaded, and says so under a figure that failed, so that a
//! missing figure is visible (and testable in a headless browser); and it
//! opens a collapsed stage section that a link leads to.

use super::graph;
use super::names::PSEUDO_STAGE;
use super::resolve::Pipeline;
use super::run_report::{RunReport, StageReport, Tables};
use super::status::Status;
use crate::table;
use anyhow::Result;
use polars::prelude::{AnyValue, DataFrame};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Tables up to this many rows are shown whole; larger ones are previewed.
pub const MAX_ROWS: usize = 50;
/// Rows shown of a larger table.
pub const PREVIEW_ROWS: usize = 10;
/// Up to this many tables in all, every stage's section is open; beyond,
/// they start collapsed and the index leads to them.
const OPEN_TABLES: usize = 24;
/// Significant digits of a number without an uncertainty.
const SIGNIFICANT: i32 = 4;

/// Escapes text for HTML content and quoted attribute values.
pub fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            _ => out.push(c),
        }
    }
    out
}

/// A relative URL of path segments, each percent-encoded.
fn href(segments: &[&str]) -> String {
    let enc = |s: &str| {
        s.bytes()
            .map(|b| match b {
                b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => {
                    (b as char).to_string()
                }
                _ => format!("%{b:02X}"),
            })
            .collect::<String>()
    };
    segments
        .iter()
        .map(|s| enc(s))
        .collect::<Vec<_>>()
        .join("/")
}

const STYLE: &str = "
body { font-family: sans-serif; margin: 2em auto; max-width: 80em; padding: 0 1em; color: #222; }
h1 { margin-bottom: 0.2em; }
p.lead { font-size: 1.15em; margin-top: 0; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.2em 0.6em; }
th { background: #f0f0f0; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
td.reason { max-width: 50em; }
tr.more td { color: #666; font-style: italic; }
.cached { background: #c6efce; } .ran { background: #bbdefb; }
.failed { background: #ffabab; } .skipped { background: #e0e0e0; }
figure { margin: 1em 0 2em; }
figure img { max-width: 100%; border: 1px solid #ddd; }
details { margin: 0.3em 0; }
details > summary { cursor: pointer; font-size: 1.1em; padding: 0.2em 0; }
details > div { margin-left: 1.2em; }
nav ul { columns: 3 16em; margin: 0.3em 0 1em; }
.note { color: #555; font-size: 0.9em; }
.broken { color: #b00; font-weight: bold; }
";

const SCRIPT: &str = "
window.addEventListener('load', function () {
  for (const img of document.images) {
    const ok = img.complete && img.naturalWidth > 0;
    img.dataset.status = ok ? 'loaded' : 'failed';
    if (!ok) {
      const note = document.createElement('p');
      note.className = 'broken';
      note.textContent = 'missing figure: ' + img.getAttribute('src');
      img.after(note);
    }
  }
  document.body.dataset.images = 'checked';
});
function openTarget() {
  const t = document.getElementById(decodeURIComponent(location.hash.slice(1)));
  if (t && t.tagName === 'DETAILS') { t.open = true; }
}
window.addEventListener('hashchange', openTarget);
window.addEventListener('load', openTarget);
";

/// The page's files for the pipeline's results folder `dir`, in the order
/// they are to land: `graph.svg`, then `index.html` (which shows it).
pub fn files(
    dir: &Path,
    p: &Pipeline,
    report: &RunReport,
    tables: &Tables,
) -> Result<[(PathBuf, Vec<u8>); 2]> {
    let statuses: graph::Statuses = report
        .stages
        .iter()
        .map(|s| (s.stage.clone(), s.status))
        .collect();
    Ok([
        (
            dir.join("graph.svg"),
            graph::svg(p, &statuses)?.into_bytes(),
        ),
        (
            dir.join(super::names::PAGE),
            page(p, report, tables).into_bytes(),
        ),
    ])
}

/// The page's HTML.
pub fn page(p: &Pipeline, report: &RunReport, tables: &Tables) -> String {
    let mut h = String::new();
    let title = escape(&p.name);
    let _ = write!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n\
         <title>{title} — ltcal</title>\n<style>{STYLE}</style>\n</head>\n<body>\n<h1>{title}</h1>\n"
    );
    if !p.description.is_empty() {
        let _ = writeln!(h, "<p class=\"lead\">{}</p>", escape(&p.description));
    }
    if let Some(e) = &report.experiment {
        let _ = writeln!(
            h,
            "<p><b>Experiment <code>{}</code></b>: <code>{}</code>. The pipeline's own results \
             are <a href=\"../../index.html\">there</a>.</p>",
            escape(&e.name),
            escape(&super::experiment::set_args(&e.overrides)),
        );
    }
    let count = |st: Status| report.with_status(st).len();
    let _ = writeln!(
        h,
        "<p>Run {} → {}: {} ran, {} cached, {} failed, {} skipped (<a href=\"#run\">the run</a>). \
         Pipeline file <code>{}</code>; the run as JSON: <a href=\"run.json\">run.json</a>.</p>",
        escape(&report.started),
        escape(&report.finished),
        count(Status::Ran),
        count(Status::Cached),
        count(Status::Failed),
        count(Status::Skipped),
        escape(&p.source.path.display().to_string()),
    );
    figures_section(&mut h, report);
    h.push_str("<h2>Stage graph</h2>\n");
    h.push_str(
        "<figure><img src=\"graph.svg\" alt=\"the stage graph, coloured by status\"></figure>\n",
    );
    tables_section(&mut h, p, report, tables);
    sweep_section(&mut h, p, report, tables);
    run_section(&mut h, report);
    let _ = write!(h, "<script>{SCRIPT}</script>\n</body>\n</html>\n");
    h
}

fn run_section(h: &mut String, report: &RunReport) {
    h.push_str("<h2 id=\"run\">Run</h2>\n<table>\n<tr><th>stage</th><th>kind</th><th>status</th><th>seconds</th><th>reason</th></tr>\n");
    for s in &report.stages {
        let mut reason = escape(&s.reason);
        if let Some(problem) = &s.cache_problem {
            reason = format!("{reason}<br><b>cache problem:</b> {}", escape(problem));
        }
        let _ = writeln!(
            h,
            "<tr><td><a href=\"#{}\">{}</a></td><td>{}</td><td class=\"{}\">{}</td>\
             <td class=\"num\">{:.3}</td><td class=\"reason\">{reason}</td></tr>",
            escape(&s.stage),
            escape(&s.stage),
            escape(&s.kind),
            s.status.as_str(),
            s.status.as_str(),
            s.seconds,
        );
    }
    h.push_str("</table>\n");
}

/// The SVG files a stage wrote, in its order.
fn figures_of(s: &StageReport) -> impl Iterator<Item = &str> {
    s.files
        .iter()
        .filter(|f| f.ends_with(".svg"))
        .map(String::as_str)
}

fn figures_section(h: &mut String, report: &RunReport) {
    if report.stages.iter().all(|s| figures_of(s).next().is_none()) {
        return;
    }
    h.push_str("<h2>Figures</h2>\n");
    for s in &report.stages {
        for file in figures_of(s) {
            let src = href(&[&s.stage, file]);
            let _ = writeln!(
                h,
                "<figure><img src=\"{}\" alt=\"{}\"><figcaption><a href=\"{}\">{}/{}</a> \
                 (stage <a href=\"#{}\">{}</a>)</figcaption></figure>",
                escape(&src),
                escape(&format!("{}: {file}", s.stage)),
                escape(&src),
                escape(&s.stage),
                escape(file),
                escape(&s.stage),
                escape(&s.stage),
            );
        }
    }
}

/// A stage's tables in its kind's declared order, then anything else it
/// produced.
fn ordered<'a>(
    p: &Pipeline,
    stage: &str,
    produced: &'a BTreeMap<String, Arc<DataFrame>>,
) -> Vec<&'a String> {
    let declared = p
        .index(stage)
        .map(|i| p.stages[i].config.outputs())
        .unwrap_or_default();
    let mut names: Vec<&String> = produced.keys().collect();
    names.sort_by_key(|n| {
        declared
            .iter()
            .position(|d| d == n)
            .unwrap_or(declared.len())
    });
    names
}

fn plural(n: usize, one: &str) -> String {
    if n == 1 {
        format!("1 {one}")
    } else {
        format!("{n} {one}s")
    }
}

fn tables_section(h: &mut String, p: &Pipeline, report: &RunReport, tables: &Tables) {
    h.push_str("<h2>Tables by stage</h2>\n");
    let total: usize = report
        .stages
        .iter()
        .map(|s| tables.get(&s.stage).map_or(0, BTreeMap::len))
        .sum();
    let per_point = |stage: &str| {
        p.sweep
            .as_ref()
            .is_some_and(|sw| !sw.after.iter().any(|a| a == stage))
    };
    // The index: every stage, what it holds, a link to its section.
    h.push_str("<nav><ul>\n");
    for s in &report.stages {
        let n = tables.get(&s.stage).map_or(0, BTreeMap::len);
        let what = if n > 0 {
            plural(n, "table")
        } else if per_point(&s.stage) {
            "per sweep point".to_string()
        } else {
            "no tables".to_string()
        };
        let _ = writeln!(
            h,
            "<li><a href=\"#{}\">{}</a> <small>({}, {what})</small></li>",
            escape(&s.stage),
            escape(&s.stage),
            escape(&s.kind),
        );
    }
    if tables.contains_key(PSEUDO_STAGE) {
        let _ = writeln!(
            h,
            "<li><a href=\"#sweep\">sweep</a> <small>(gathered tables)</small></li>"
        );
    }
    h.push_str("</ul></nav>\n");
    let _ = writeln!(
        h,
        "<p class=\"note\">Numbers are rounded for reading: to two significant digits of their \
         uncertainty where the table has one (<code>x</code> beside <code>x_u</code> or \
         <code>u_x</code>, <code>value</code> beside <code>std</code>), else to {SIGNIFICANT} \
         significant digits. The linked Parquet files hold them in full.</p>"
    );
    let open = if total <= OPEN_TABLES { " open" } else { "" };
    for s in &report.stages {
        let produced = tables.get(&s.stage);
        let n = produced.map_or(0, BTreeMap::len);
        let figures = figures_of(s).count();
        let mut what = vec![plural(n, "table")];
        if figures > 0 {
            what.push(plural(figures, "figure"));
        }
        let _ = writeln!(
            h,
            "<details id=\"{}\"{open}><summary><b>{}</b> <small>({}, {}; {})</small></summary><div>",
            escape(&s.stage),
            escape(&s.stage),
            escape(&s.kind),
            s.status.as_str(),
            what.join(", "),
        );
        match produced {
            Some(produced) if !produced.is_empty() => {
                for name in ordered(p, &s.stage, produced) {
                    table_block(h, &s.stage, name, &produced[name]);
                }
            }
            _ if per_point(&s.stage) => {
                let gathered: Vec<String> = p
                    .sweep
                    .iter()
                    .flat_map(|sw| &sw.gather)
                    .filter(|r| r.stage == s.stage)
                    .map(|r| format!("<a href=\"#sweep\">{}</a>", escape(&r.to_string())))
                    .collect();
                let _ = write!(
                    h,
                    "<p>Run at every sweep point; its tables stay in the cache, one set a point"
                );
                if gathered.is_empty() {
                    h.push_str(".</p>\n");
                } else {
                    let _ = writeln!(
                        h,
                        ", and are gathered over the points: {}.</p>",
                        gathered.join(", ")
                    );
                }
            }
            _ => {
                let _ = writeln!(h, "<p>No tables: the stage {}.</p>", s.status.as_str());
            }
        }
        h.push_str("</div></details>\n");
    }
}

/// A sweep's gathered tables, published under `sweep/`: linked and
/// previewed like a stage's.
fn sweep_section(h: &mut String, p: &Pipeline, report: &RunReport, tables: &Tables) {
    let (Some(sw), Some(counts)) = (&p.sweep, &report.sweep) else {
        return;
    };
    let _ = writeln!(
        h,
        "<h2 id=\"sweep\">Sweep</h2>\n<p>{} points ({} ran, {} cached, {} failed) over {}.</p>",
        counts.points,
        counts.ran,
        counts.cached,
        counts.failed,
        sw.axes
            .iter()
            .map(|a| format!("<code>{}</code>", escape(&a.name)))
            .collect::<Vec<_>>()
            .join(", "),
    );
    match tables.get(PSEUDO_STAGE) {
        Some(gathered) if !gathered.is_empty() => {
            for (name, df) in gathered {
                table_block(h, PSEUDO_STAGE, name, df);
            }
        }
        _ => h.push_str("<p>No gathered tables: no point produced them.</p>\n"),
    }
}

/// One table: its name, size and file, and its rows (all, or a preview).
fn table_block(h: &mut String, stage: &str, name: &str, df: &DataFrame) {
    let file = format!("{name}.parquet");
    let link = format!(
        "<a href=\"{}\">{}</a>",
        escape(&href(&[stage, &file])),
        escape(&file)
    );
    let (rows, cols) = (df.height(), df.width());
    if rows == 0 {
        let names: Vec<String> = df
            .get_column_names()
            .iter()
            .map(|c| escape(c.as_str()))
            .collect();
        let _ = writeln!(
            h,
            "<h4>{} <small>{link}</small></h4>\n<p>No rows. Columns: {}.</p>",
            escape(name),
            names.join(", ")
        );
        return;
    }
    let _ = writeln!(
        h,
        "<h4>{} <small>{link}, {} × {}</small></h4>",
        escape(name),
        plural(rows, "row"),
        plural(cols, "column"),
    );
    // Columns without a single value (a campaign's reference coordinates
    // when it has none) are named, not drawn: the corner campaign's
    // targets were 24 rows of empty cells.
    let (empty, kept): (Vec<&str>, Vec<&str>) = df
        .get_column_names()
        .iter()
        .map(|c| c.as_str())
        .partition(|c| df.column(c).is_ok_and(|c| c.null_count() == rows));
    if !empty.is_empty() {
        let _ = writeln!(
            h,
            "<p class=\"note\">Without a value in any row: {}.</p>",
            empty
                .iter()
                .map(|c| escape(c))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    let shown = if rows <= MAX_ROWS { rows } else { PREVIEW_ROWS };
    match df.select(kept) {
        Ok(valued) if valued.width() > 0 => html_table(h, &valued, shown, &link),
        _ => {}
    }
}

fn html_table(h: &mut String, df: &DataFrame, shown: usize, link: &str) {
    h.push_str("<table>\n<tr>");
    for c in df.get_column_names() {
        let _ = write!(h, "<th>{}</th>", escape(c.as_str()));
    }
    h.push_str("</tr>\n");
    let texts = cell_texts(df, shown);
    for i in 0..shown {
        h.push_str("<tr>");
        for (c, text) in df.columns().iter().zip(&texts) {
            let v = c.get(i).unwrap_or(AnyValue::Null);
            let class = if v.is_primitive_numeric() {
                " class=\"num\""
            } else {
                ""
            };
            let _ = write!(h, "<td{class}>{}</td>", escape(&text[i]));
        }
        h.push_str("</tr>\n");
    }
    if shown < df.height() {
        let _ = writeln!(
            h,
            "<tr class=\"more\"><td colspan=\"{}\">… {} more rows: {link}</td></tr>",
            df.width(),
            df.height() - shown
        );
    }
    h.push_str("</table>\n");
}

/// The uncertainty column of each column that has one: `x_u` or `u_x` for
/// `x`, `std` for `value`.
fn uncertainty_columns(names: &[&str]) -> BTreeMap<usize, usize> {
    let at = |n: &str| names.iter().position(|c| *c == n);
    names
        .iter()
        .enumerate()
        .filter_map(|(i, c)| {
            let u = at(&format!("{c}_u"))
                .or_else(|| at(&format!("u_{c}")))
                .or_else(|| (*c == "value").then(|| at("std")).flatten())?;
            Some((i, u))
        })
        .collect()
}

/// The first `shown` rows of every column as the page writes them:
/// floats rounded to what their uncertainty supports, an uncertainty to its
/// own two significant digits, any other float to [`SIGNIFICANT`] digits;
/// everything else as the tables' text.
pub fn cell_texts(df: &DataFrame, shown: usize) -> Vec<Vec<String>> {
    let names: Vec<&str> = df.get_column_names().iter().map(|c| c.as_str()).collect();
    let uncertain = uncertainty_columns(&names);
    let is_uncertainty = |col: usize| uncertain.values().any(|&u| u == col);
    let float = |col: usize, i: usize| -> Option<f64> {
        match df.columns()[col].get(i).ok()? {
            AnyValue::Float64(x) => Some(x),
            AnyValue::Float32(x) => Some(f64::from(x)),
            _ => None,
        }
    };
    (0..df.width())
        .map(|col| {
            (0..shown)
                .map(|i| {
                    let Some(x) = float(col, i) else {
                        let v = df.columns()[col].get(i).unwrap_or(AnyValue::Null);
                        return table::cell_text(&v, 6);
                    };
                    let u = uncertain.get(&col).and_then(|&u| float(u, i));
                    match u {
                        Some(u) => with_uncertainty(x, u),
                        None if is_uncertainty(col) => with_uncertainty(x, x),
                        None => significant(x, SIGNIFICANT),
                    }
                })
                .collect()
        })
        .collect()
}

/// `x` to `digits` significant digits, trailing zeros dropped; in
/// scientific notation below 1e-3 and from 1e6 on.
pub fn significant(x: f64, digits: i32) -> String {
    if !x.is_finite() {
        return x.to_string();
    }
    if x == 0.0 {
        return "0".into();
    }
    let e = x.abs().log10().floor() as i32;
    if !(-3..6).contains(&e) {
        let s = format!("{x:.*e}", (digits - 1).max(0) as usize);
        let (mantissa, exponent) = s.split_once('e').unwrap_or((&s, "0"));
        return format!("{}e{exponent}", trim_zeros(mantissa));
    }
    if e >= digits {
        let step = 10f64.powi(e + 1 - digits);
        return format!("{:.0}", (x / step).round() * step);
    }
    trim_zeros(&format!("{x:.*}", (digits - 1 - e) as usize))
}

/// Trailing zeros would claim digits nobody measured: 0.25, not 0.2500.
fn trim_zeros(s: &str) -> String {
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s.to_string()
    }
}

/// `x` to the decimal place of the second significant digit of its
/// standard uncertainty `u` (which that rounding suits too); to
/// [`SIGNIFICANT`] digits when `u` is not a positive finite number.
pub fn with_uncertainty(x: f64, u: f64) -> String {
    if !(x.is_finite() && u.is_finite() && u > 0.0) {
        return significant(x, SIGNIFICANT);
    }
    let place = u.log10().floor() as i32 - 1;
    if place >= 0 {
        let step = 10f64.powi(place);
        return format!("{:.0}", (x / step).round() * step);
    }
    if place < -12 {
        return significant(x, SIGNIFICANT);
    }
    let s = format!("{x:.*}", (-place) as usize);
    if s.trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        s.trim_start_matches('-').to_string()
    } else {
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn escapes_markup_and_encodes_paths() {
        assert_eq!(
            escape("<b a=\"1\">&'"),
            "&lt;b a=&quot;1&quot;&gt;&amp;&#39;"
        );
        assert_eq!(href(&["stage-1", "a b#.svg"]), "stage-1/a%20b%23.svg");
    }

    /// Regression (issue 33): the pages printed every number with six
    /// decimals whatever its uncertainty (`0.250000`, `243.159857`).
    #[test]
    fn numbers_printed_with_six_decimals_are_rounded_to_their_uncertainty_or_4_digits() {
        assert_eq!(significant(243.159857, 4), "243.2");
        assert_eq!(significant(0.25, 4), "0.25");
        assert_eq!(significant(100.0, 4), "100");
        assert_eq!(significant(-0.0, 4), "0");
        assert_eq!(significant(12345.678, 4), "12350");
        assert_eq!(significant(4.35e-9, 4), "4.35e-9");
        assert_eq!(significant(2.5e7, 4), "2.5e7");
        assert_eq!(significant(f64::NAN, 4), "NaN");
        assert_eq!(significant(0.012345, 2), "0.012");
        // Two significant digits of u fix the decimal place of x.
        assert_eq!(with_uncertainty(1.234567, 0.0123), "1.235");
        assert_eq!(with_uncertainty(7.883, 0.568), "7.88");
        assert_eq!(with_uncertainty(12345.6, 123.4), "12350");
        assert_eq!(with_uncertainty(-0.0004, 0.0123), "0.000");
        assert_eq!(with_uncertainty(5.0, 0.0), "5");
        assert_eq!(with_uncertainty(5.0, f64::NAN), "5");

        let df = polars::df!(
            "param" => ["a", "b"],
            "value" => [1.234567, 20.0],
            "std" => [0.0123, 0.5],
            "ratio" => [0.987654, 1.5],
            "ratio_u" => [0.01, 0.2],
            "x_mm" => [1.0, 2.345678],
            "u_x_mm" => [0.25, 0.001],
            "n" => [3i64, 4],
            "free" => [1.23456789, 2.0],
        )
        .unwrap();
        let texts = cell_texts(&df, 2);
        let want: [[&str; 2]; 9] = [
            ["a", "b"],
            ["1.235", "20.00"],
            ["0.012", "0.50"],
            ["0.988", "1.50"],
            ["0.010", "0.20"],
            ["1.00", "2.3457"],
            ["0.25", "0.0010"],
            ["3", "4"],
            ["1.235", "2"],
        ];
        assert_eq!(texts, want.map(|c| c.map(String::from).to_vec()).to_vec());
    }
}
