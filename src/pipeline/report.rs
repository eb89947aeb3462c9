//! `results/<pipeline>/index.html`: one page per pipeline (and one per
//! experiment, in its folder, naming its overrides), rewritten after
//! every run (a fully cached one too), readable straight from the file
//! system — every link and image is a relative path, nothing is fetched.
//!
//! It shows the run (each stage's status, why it ran, how long it took), the
//! stage graph coloured by status (`graph.svg`, beside the page), every SVG
//! figure, and every summary-like table — those of at most [`MAX_ROWS`]
//! rows — as an HTML table; larger tables are linked as Parquet files.
//!
//! A small script marks each image `data-status="loaded"` or `"failed"` once
//! the page has loaded, and says so under a figure that failed, so that a
//! missing figure is visible (and testable in a headless browser).

use super::graph;
use super::resolve::Pipeline;
use super::run_report::RunReport;
use super::status::Status;
use crate::fs::write_atomic;
use crate::table;
use anyhow::Result;
use polars::prelude::{AnyValue, DataFrame};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;
use std::sync::Arc;

/// Tables up to this many rows are shown; larger ones are linked.
pub const MAX_ROWS: usize = 50;
/// Decimal places of numbers in the shown tables.
const DIGITS: usize = 6;

/// Stage → table → frame, as the run produced or reused them.
pub type Tables = BTreeMap<String, BTreeMap<String, Arc<DataFrame>>>;

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
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.2em 0.6em; }
th { background: #f0f0f0; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
td.reason { max-width: 50em; }
.cached { background: #c6efce; } .ran { background: #bbdefb; }
.failed { background: #ffabab; } .skipped { background: #e0e0e0; }
figure { margin: 1em 0 2em; }
figure img { max-width: 100%; border: 1px solid #ddd; }
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
";

/// Writes `index.html` (and `graph.svg`) into the pipeline's results folder.
pub fn write(dir: &Path, p: &Pipeline, report: &RunReport, tables: &Tables) -> Result<()> {
    let statuses: graph::Statuses = report
        .stages
        .iter()
        .map(|s| (s.stage.clone(), s.status))
        .collect();
    write_atomic(&dir.join("graph.svg"), graph::svg(p, &statuses)?.as_bytes())?;
    write_atomic(
        &dir.join(super::names::PAGE),
        page(p, report, tables).as_bytes(),
    )
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
        let _ = writeln!(h, "<p>{}</p>", escape(&p.description));
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
        "<p>Run {} → {}: {} ran, {} cached, {} failed, {} skipped. \
         Pipeline file <code>{}</code>; the run as JSON: <a href=\"run.json\">run.json</a>.</p>",
        escape(&report.started),
        escape(&report.finished),
        count(Status::Ran),
        count(Status::Cached),
        count(Status::Failed),
        count(Status::Skipped),
        escape(&p.source.path.display().to_string()),
    );
    run_section(&mut h, report);
    h.push_str("<h2>Stage graph</h2>\n");
    h.push_str(
        "<figure><img src=\"graph.svg\" alt=\"the stage graph, coloured by status\"></figure>\n",
    );
    figures_section(&mut h, report);
    tables_section(&mut h, p, report, tables);
    let _ = write!(h, "<script>{SCRIPT}</script>\n</body>\n</html>\n");
    h
}

fn run_section(h: &mut String, report: &RunReport) {
    h.push_str("<h2>Run</h2>\n<table>\n<tr><th>stage</th><th>kind</th><th>status</th><th>seconds</th><th>reason</th></tr>\n");
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

fn figures_section(h: &mut String, report: &RunReport) {
    let figures: Vec<(&str, &str)> = report
        .stages
        .iter()
        .flat_map(|s| {
            s.files
                .iter()
                .filter(|f| f.ends_with(".svg"))
                .map(|f| (s.stage.as_str(), f.as_str()))
        })
        .collect();
    if figures.is_empty() {
        return;
    }
    h.push_str("<h2>Figures</h2>\n");
    for (stage, file) in figures {
        let src = href(&[stage, file]);
        let _ = writeln!(
            h,
            "<figure><img src=\"{}\" alt=\"{}\"><figcaption><a href=\"{}\">{}/{}</a></figcaption></figure>",
            escape(&src),
            escape(&format!("{stage}: {file}")),
            escape(&src),
            escape(stage),
            escape(file),
        );
    }
}

fn tables_section(h: &mut String, p: &Pipeline, report: &RunReport, tables: &Tables) {
    h.push_str("<h2>Tables</h2>\n");
    for s in &report.stages {
        let _ = writeln!(
            h,
            "<h3 id=\"{}\">{} <small>({})</small></h3>",
            escape(&s.stage),
            escape(&s.stage),
            escape(&s.kind)
        );
        let Some(produced) = tables.get(&s.stage) else {
            let _ = writeln!(h, "<p>No tables: the stage {}.</p>", s.status.as_str());
            continue;
        };
        // The kind's declared order, then anything else it produced.
        let declared = p
            .index(&s.stage)
            .map(|i| p.stages[i].config.outputs())
            .unwrap_or_default();
        let mut names: Vec<&String> = produced.keys().collect();
        names.sort_by_key(|n| {
            declared
                .iter()
                .position(|d| d == n)
                .unwrap_or(declared.len())
        });
        for name in names {
            let df = &produced[name];
            let file = format!("{name}.parquet");
            let link = format!(
                "<a href=\"{}\">{}</a>",
                escape(&href(&[&s.stage, &file])),
                escape(&file)
            );
            if df.height() <= MAX_ROWS {
                let _ = writeln!(h, "<h4>{} <small>{link}</small></h4>", escape(name));
                html_table(h, df);
            } else {
                let cols: Vec<String> = df
                    .get_column_names()
                    .iter()
                    .map(|c| escape(c.as_str()))
                    .collect();
                let _ = writeln!(
                    h,
                    "<h4>{}</h4>\n<p>{} rows, too many to show: {link}. Columns: {}.</p>",
                    escape(name),
                    df.height(),
                    cols.join(", ")
                );
            }
        }
    }
}

fn html_table(h: &mut String, df: &DataFrame) {
    h.push_str("<table>\n<tr>");
    for c in df.get_column_names() {
        let _ = write!(h, "<th>{}</th>", escape(c.as_str()));
    }
    h.push_str("</tr>\n");
    for i in 0..df.height() {
        h.push_str("<tr>");
        for c in df.columns() {
            let v = c.get(i).unwrap_or(AnyValue::Null);
            let class = if v.is_primitive_numeric() {
                " class=\"num\""
            } else {
                ""
            };
            let _ = write!(
                h,
                "<td{class}>{}</td>",
                escape(&table::cell_text(&v, DIGITS))
            );
        }
        h.push_str("</tr>\n");
    }
    h.push_str("</table>\n");
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
}
