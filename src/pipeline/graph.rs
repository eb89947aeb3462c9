//! The stage graph drawn for people: Graphviz dot, Mermaid, or an SVG
//! (plotters, no system fonts) — each stage a box coloured by its status,
//! each input an arrow from producer to consumer labelled with its slot.
//!
//! The SVG uses a layered layout: one row per level of [`Graph`] (a stage
//! sits one row below its deepest input), and within a row stages ordered by
//! the mean position of their inputs, which keeps most arrows short and
//! uncrossed on pipelines like ours (parallel chains from shared sources).

use super::plan::Graph;
use super::resolve::Pipeline;
use anyhow::{Result, anyhow};
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use std::collections::BTreeMap;

/// A stage's status as drawn: `cached`, `run` (would run), and after a run
/// `ran`, `failed`, `skipped`.
pub type Statuses = BTreeMap<String, String>;

/// Fill colour and legend label of a status.
fn style(status: &str) -> (RGBColor, &'static str) {
    match status {
        "cached" => (RGBColor(198, 239, 206), "cached"),
        "run" => (RGBColor(255, 224, 178), "would run"),
        "ran" => (RGBColor(187, 222, 251), "ran"),
        "failed" => (RGBColor(255, 171, 171), "failed"),
        "skipped" => (RGBColor(224, 224, 224), "skipped"),
        _ => (RGBColor(255, 255, 255), "unknown"),
    }
}

fn hex(c: RGBColor) -> String {
    format!("#{:02x}{:02x}{:02x}", c.0, c.1, c.2)
}

fn status_of<'a>(statuses: &'a Statuses, stage: &str) -> &'a str {
    statuses.get(stage).map_or("", String::as_str)
}

/// `(producer, consumer, label)` for every input, in stage order. The label
/// is the slot, with the producer's table when it is not its first one.
fn edges(p: &Pipeline) -> Vec<(usize, usize, String)> {
    let mut out = Vec::new();
    for (j, s) in p.stages.iter().enumerate() {
        for (slot, r) in &s.inputs {
            let Some(i) = p.index(&r.stage) else { continue };
            let primary = p.stages[i].config.outputs()[0];
            let label = if r.table.is_empty() || r.table == primary {
                slot.clone()
            } else {
                format!("{slot} ← {}", r.table)
            };
            out.push((i, j, label));
        }
    }
    out
}

fn dot_quote(s: &str) -> String {
    let escaped = s
        .replace('\\', "\\\\")
        .replace('"', "\\\"")
        .replace('\n', "\\n");
    format!("\"{escaped}\"")
}

/// Graphviz dot.
pub fn dot(p: &Pipeline, statuses: &Statuses) -> String {
    let mut out = format!("digraph {} {{\n", dot_quote(&p.name));
    out.push_str("  rankdir=TB;\n");
    out.push_str("  node [shape=box, style=\"rounded,filled\", fontname=\"sans-serif\"];\n");
    out.push_str("  edge [fontname=\"sans-serif\", fontsize=10];\n");
    for s in &p.stages {
        let (fill, label) = style(status_of(statuses, &s.name));
        out.push_str(&format!(
            "  {} [label={}, fillcolor=\"{}\", tooltip={}];\n",
            dot_quote(&s.name),
            dot_quote(&format!("{}\n{}", s.name, s.config.kind())),
            hex(fill),
            dot_quote(label),
        ));
    }
    for (i, j, label) in edges(p) {
        out.push_str(&format!(
            "  {} -> {} [label={}];\n",
            dot_quote(&p.stages[i].name),
            dot_quote(&p.stages[j].name),
            dot_quote(&label)
        ));
    }
    out.push_str("}\n");
    out
}

/// Mermaid flowchart. Stage names become labels of ids `s<index>`: Mermaid
/// reads `-` in an id as the start of an arrow.
pub fn mermaid(p: &Pipeline, statuses: &Statuses) -> String {
    let mut out = String::from("flowchart TB\n");
    let escape = |s: &str| s.replace('"', "#quot;");
    for (i, s) in p.stages.iter().enumerate() {
        let status = status_of(statuses, &s.name);
        let class = if status.is_empty() {
            String::new()
        } else {
            format!(":::{status}")
        };
        out.push_str(&format!(
            "  s{i}[\"{}<br/><i>{}</i>\"]{class}\n",
            escape(&s.name),
            s.config.kind()
        ));
    }
    for (i, j, label) in edges(p) {
        out.push_str(&format!("  s{i} -->|\"{}\"| s{j}\n", escape(&label)));
    }
    let mut used: Vec<&str> = statuses.values().map(String::as_str).collect();
    used.sort();
    used.dedup();
    for st in used {
        out.push_str(&format!(
            "  classDef {st} fill:{},stroke:#555\n",
            hex(style(st).0)
        ));
    }
    out
}

const BOX_H: i32 = 46;
const ROW_GAP: i32 = 56;
const COL_GAP: i32 = 28;
const MARGIN: i32 = 24;
const LEGEND_H: i32 = 40;

/// plotters' SVG backend writes a font of size `s` as `font-size = s / 1.24`.
const FONT_SCALE: f64 = 1.24;

/// A sans-serif font of `px` pixels, anchored at `pos`.
fn font(px: f64, colour: RGBColor, pos: Pos) -> TextStyle<'static> {
    ("sans-serif", px * FONT_SCALE)
        .into_font()
        .color(&colour)
        .pos(pos)
}

/// Generous width of text in a sans-serif font of `px` pixels (average
/// glyphs are about 0.55 em wide), without reading any font.
fn text_width(s: &str, px: f64) -> i32 {
    (s.chars().count() as f64 * px * 0.6).ceil() as i32
}

/// Stage → (column, row) of the layered layout.
fn layout(p: &Pipeline) -> (Vec<Vec<usize>>, Vec<(usize, usize)>) {
    let graph = Graph::new(p);
    let mut pos = vec![(0usize, 0usize); p.stages.len()];
    let mut rows: Vec<Vec<usize>> = Vec::new();
    // Rows are drawn centred, so a stage's horizontal place is its column
    // less half its row's width.
    let centred = |rows: &[Vec<usize>], (col, row): (usize, usize)| {
        col as f64 - (rows[row].len() as f64 - 1.0) / 2.0
    };
    for (row, level) in graph.levels.iter().enumerate() {
        let mut order: Vec<(f64, usize)> = level
            .iter()
            .map(|&i| {
                let cols: Vec<f64> = p.stages[i]
                    .inputs
                    .values()
                    .filter_map(|r| p.index(&r.stage))
                    .map(|j| centred(&rows, pos[j]))
                    .collect();
                let centre = if cols.is_empty() {
                    f64::INFINITY
                } else {
                    cols.iter().sum::<f64>() / cols.len() as f64
                };
                (centre, i)
            })
            .collect();
        // Stages without inputs keep file order; others follow their inputs.
        order.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        for (col, &(_, i)) in order.iter().enumerate() {
            pos[i] = (col, row);
        }
        rows.push(order.into_iter().map(|(_, i)| i).collect());
    }
    (rows, pos)
}

fn draw_err<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow!("drawing the stage graph: {e}")
}

/// The graph as an SVG, each stage coloured by its status, with a legend.
pub fn svg(p: &Pipeline, statuses: &Statuses) -> Result<String> {
    let (rows, pos) = layout(p);
    let box_w = p
        .stages
        .iter()
        .map(|s| text_width(&s.name, 14.0).max(text_width(s.config.kind(), 12.0)))
        .max()
        .unwrap_or(80)
        + 20;
    let widest = rows.iter().map(Vec::len).max().unwrap_or(1) as i32;
    let content_w = widest * box_w + (widest - 1) * COL_GAP;
    let title = format!("{}: stage graph", p.name);
    let width = (content_w + 2 * MARGIN)
        .max(text_width(&title, 18.0) + 2 * MARGIN)
        .max(520);
    let height = 2 * MARGIN + 30 + rows.len() as i32 * (BOX_H + ROW_GAP) - ROW_GAP + LEGEND_H;
    // Each row centred: rows narrower than the widest one sit in the middle.
    let at = |i: usize| -> (i32, i32) {
        let (col, row) = pos[i];
        let n = rows[row].len() as i32;
        let row_w = n * box_w + (n - 1) * COL_GAP;
        let x = (width - row_w) / 2 + col as i32 * (box_w + COL_GAP);
        let y = MARGIN + 30 + row as i32 * (BOX_H + ROW_GAP);
        (x, y)
    };
    let mut out = String::new();
    {
        let root =
            SVGBackend::with_string(&mut out, (width as u32, height as u32)).into_drawing_area();
        root.fill(&WHITE).map_err(draw_err)?;
        let centre = Pos::new(HPos::Center, VPos::Center);
        let left = Pos::new(HPos::Left, VPos::Center);
        root.draw(&Text::new(
            title.clone(),
            (width / 2, MARGIN),
            font(18.0, BLACK, centre),
        ))
        .map_err(draw_err)?;
        let line = RGBColor(90, 90, 90);
        for (i, j, label) in edges(p) {
            let (x0, y0) = at(i);
            let (x1, y1) = at(j);
            let from = (x0 + box_w / 2, y0 + BOX_H);
            let to = (x1 + box_w / 2, y1);
            root.draw(&PathElement::new(vec![from, to], line.stroke_width(1)))
                .map_err(draw_err)?;
            let head = arrow_head(from, to);
            root.draw(&Polygon::new(head, line.filled()))
                .map_err(draw_err)?;
            // The slot name near the consumer, where arrows are apart.
            let t = 0.72;
            let lx = from.0 as f64 + t * (to.0 - from.0) as f64;
            let ly = from.1 as f64 + t * (to.1 - from.1) as f64;
            root.draw(&Text::new(
                label,
                (lx as i32 + 4, ly as i32),
                font(11.0, RGBColor(60, 60, 60), left),
            ))
            .map_err(draw_err)?;
        }
        for (i, s) in p.stages.iter().enumerate() {
            let (x, y) = at(i);
            let (fill, _) = style(status_of(statuses, &s.name));
            root.draw(&Rectangle::new(
                [(x, y), (x + box_w, y + BOX_H)],
                fill.filled(),
            ))
            .map_err(draw_err)?;
            root.draw(&Rectangle::new(
                [(x, y), (x + box_w, y + BOX_H)],
                line.stroke_width(1),
            ))
            .map_err(draw_err)?;
            root.draw(&Text::new(
                s.name.clone(),
                (x + box_w / 2, y + 16),
                font(14.0, BLACK, centre),
            ))
            .map_err(draw_err)?;
            root.draw(&Text::new(
                s.config.kind().to_string(),
                (x + box_w / 2, y + 33),
                font(12.0, RGBColor(80, 80, 80), centre),
            ))
            .map_err(draw_err)?;
        }
        let mut used: Vec<&str> = statuses.values().map(String::as_str).collect();
        used.sort();
        used.dedup();
        let mut x = MARGIN;
        let y = height - MARGIN - 14;
        for st in used {
            let (fill, label) = style(st);
            root.draw(&Rectangle::new([(x, y), (x + 18, y + 14)], fill.filled()))
                .map_err(draw_err)?;
            root.draw(&Rectangle::new(
                [(x, y), (x + 18, y + 14)],
                line.stroke_width(1),
            ))
            .map_err(draw_err)?;
            root.draw(&Text::new(label, (x + 24, y + 7), font(13.0, BLACK, left)))
                .map_err(draw_err)?;
            x += 24 + text_width(label, 13.0) + 24;
        }
        root.present().map_err(draw_err)?;
    }
    Ok(out)
}

/// A filled triangle at `to`, pointing along `from → to`.
fn arrow_head(from: (i32, i32), to: (i32, i32)) -> Vec<(i32, i32)> {
    let (dx, dy) = ((to.0 - from.0) as f64, (to.1 - from.1) as f64);
    let len = dx.hypot(dy).max(1e-9);
    let (ux, uy) = (dx / len, dy / len);
    let (l, w) = (9.0, 4.0);
    let base = (to.0 as f64 - l * ux, to.1 as f64 - l * uy);
    vec![
        to,
        (
            (base.0 - w * uy).round() as i32,
            (base.1 + w * ux).round() as i32,
        ),
        (
            (base.0 + w * uy).round() as i32,
            (base.1 - w * ux).round() as i32,
        ),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::{load_source, source::Source};

    fn pipeline() -> Pipeline {
        let text = "[stages.a]\nkind = \"mesh\"\nshape = \"plane\"\n\
            [stages.t]\nkind = \"inject\"\n\
            [stages.m]\nkind = \"measure\"\ninputs = { points = \"a\", errors = \"t\" }\n";
        load_source(&Source::new("p.toml", text), &[]).unwrap()
    }

    #[test]
    fn dot_and_mermaid_name_every_stage_and_input() {
        let p = pipeline();
        let st: Statuses = [("a", "cached"), ("t", "cached"), ("m", "run")]
            .iter()
            .map(|(a, b)| (a.to_string(), b.to_string()))
            .collect();
        let d = dot(&p, &st);
        assert!(d.contains("\"a\" -> \"m\" [label=\"points\"];"), "{d}");
        assert!(d.contains("\"t\" -> \"m\" [label=\"errors\"];"), "{d}");
        assert!(
            d.contains("\"m\" [label=\"m\\nmeasure\", fillcolor=\"#ffe0b2\""),
            "{d}"
        );
        let m = mermaid(&p, &st);
        assert!(m.contains("s0 -->|\"points\"| s2"), "{m}");
        assert!(m.contains("s2[\"m<br/><i>measure</i>\"]:::run"), "{m}");
        assert!(m.contains("classDef cached fill:#c6efce"), "{m}");
    }

    #[test]
    fn layout_puts_each_stage_below_its_inputs() {
        let p = pipeline();
        let (rows, pos) = layout(&p);
        assert_eq!(rows, vec![vec![0, 1], vec![2]]);
        assert_eq!(pos[2], (0, 1));
        let s = svg(&p, &Statuses::new()).unwrap();
        assert!(
            s.starts_with("<svg") && s.contains(">\nmeasure\n</text>"),
            "{s}"
        );
    }
}
