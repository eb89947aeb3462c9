//! The stage graph drawn for people: Graphviz dot, Mermaid, or an SVG
//! (plotters, no system fonts) — each stage a box coloured by its status,
//! each input an arrow from producer to consumer labelled with its slot.
//!
//! The SVG uses a layered layout: one row per level (a stage sits one row
//! below its deepest input, a sweep's gathered table counting as an input
//! from the per-point stage that produces it), and within a row stages ordered by
//! the mean position of their inputs, which keeps most arrows short and
//! uncrossed on pipelines like ours (parallel chains from shared sources).

use super::names::PSEUDO_STAGE;
use super::resolve::Pipeline;
use super::status::Status;
use crate::plots;
use anyhow::{Result, anyhow};
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use std::collections::BTreeMap;

/// A stage's status as drawn: planned (`cached`, `run`) or after a run
/// (`ran`, `failed`, `skipped`); a stage not in the map has none.
pub type Statuses = BTreeMap<String, Status>;

/// Fill colour and legend label of a status.
fn style(status: Option<Status>) -> (RGBColor, &'static str) {
    match status {
        Some(Status::Cached) => (RGBColor(198, 239, 206), "cached"),
        Some(Status::Run) => (RGBColor(255, 224, 178), "would run"),
        Some(Status::Ran) => (RGBColor(187, 222, 251), "ran"),
        Some(Status::Failed) => (RGBColor(255, 171, 171), "failed"),
        Some(Status::Skipped) => (RGBColor(224, 224, 224), "skipped"),
        None => (RGBColor(255, 255, 255), "unknown"),
    }
}

fn hex(c: RGBColor) -> String {
    format!("#{:02x}{:02x}{:02x}", c.0, c.1, c.2)
}

fn status_of(statuses: &Statuses, stage: &str) -> Option<Status> {
    statuses.get(stage).copied()
}

/// The statuses that occur, each once, in the order of their words (the
/// legend's order).
fn used(statuses: &Statuses) -> Vec<Status> {
    let mut used: Vec<Status> = statuses.values().copied().collect();
    used.sort_by_key(|s| s.as_str());
    used.dedup();
    used
}

/// `(producer, consumer, label)` for every input, in stage order. The label
/// is the slot, with the producer's table when it is not its first one. A
/// sweep's gathered table (`sweep.evaluation.criteria`) is drawn from the
/// per-point stage that produces it (`evaluation`), labelled with the whole
/// reference: the stage after the sweep was drawn unconnected.
fn edges(p: &Pipeline) -> Vec<(usize, usize, String)> {
    let mut out = Vec::new();
    for (j, s) in p.stages.iter().enumerate() {
        for (slot, r) in &s.inputs {
            if r.stage == PSEUDO_STAGE {
                let producer = r.table.split_once('.').map_or("", |(stage, _)| stage);
                if let Some(i) = p.index(producer) {
                    out.push((i, j, format!("{slot} ← {r}")));
                }
                continue;
            }
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
        let class = match status_of(statuses, &s.name) {
            None => String::new(),
            Some(status) => format!(":::{status}"),
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
    for st in used(statuses) {
        out.push_str(&format!(
            "  classDef {st} fill:{},stroke:#555\n",
            hex(style(Some(st)).0)
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

/// The width of text in a sans-serif font of `px` pixels, whole pixels
/// (the figures' estimate, `plots::text_width_px`).
fn text_width(s: &str, px: f64) -> i32 {
    plots::text_width_px(s, px).ceil() as i32
}

/// One place in a row of the layout: a stage's box, or where an edge that
/// spans several levels crosses this row (so that it passes between boxes,
/// never under one).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Item {
    Stage(usize),
    Edge(usize),
}

const EDGE_W: i32 = 12;

/// The layered layout, x centred on 0.
#[derive(Debug)]
struct Layout {
    /// Each row's items left to right, with their left x.
    rows: Vec<Vec<(Item, i32)>>,
    /// Stage → (left x, row).
    stage: Vec<(i32, usize)>,
    /// Edge → (centre x, row) of each row it crosses.
    crossings: Vec<Vec<(i32, usize)>>,
    /// Of the widest row.
    width: i32,
}

/// Each stage's row: one below its deepest producer along `edges` — the
/// plan's levels, except that a stage reading a sweep's gathered table sits
/// below the per-point stage that produces it, not in the first row.
fn levels(n: usize, edges: &[(usize, usize, String)]) -> (Vec<usize>, Vec<Vec<usize>>) {
    let mut level = vec![0; n];
    // The resolver rejected cycles: `n` rounds of relaxation settle it.
    for _ in 0..n {
        let mut changed = false;
        for &(i, j, _) in edges {
            if level[j] < level[i] + 1 {
                level[j] = level[i] + 1;
                changed = true;
            }
        }
        if !changed {
            break;
        }
    }
    let depth = level.iter().copied().max().map_or(0, |m| m + 1);
    let mut rows = vec![Vec::new(); depth];
    for (i, &l) in level.iter().enumerate() {
        rows[l].push(i);
    }
    (level, rows)
}

fn layout(p: &Pipeline, edges: &[(usize, usize, String)], box_w: i32) -> Layout {
    let (level, rows) = levels(p.stages.len(), edges);
    let width_of = |it: Item| match it {
        Item::Stage(_) => box_w,
        Item::Edge(_) => EDGE_W,
    };
    let mut centre: BTreeMap<(usize, usize), f64> = BTreeMap::new(); // (row, item id) → x
    let id = |it: Item| match it {
        Item::Stage(i) => 2 * i,
        Item::Edge(k) => 2 * k + 1,
    };
    let mut out = Layout {
        rows: Vec::new(),
        stage: vec![(0, 0); p.stages.len()],
        crossings: vec![Vec::new(); edges.len()],
        width: 0,
    };
    for (row, stages) in rows.iter().enumerate() {
        let mut items: Vec<Item> = stages.iter().map(|&i| Item::Stage(i)).collect();
        items.extend(
            edges
                .iter()
                .enumerate()
                .filter(|(_, (i, j, _))| level[*i] < row && row < level[*j])
                .map(|(k, _)| Item::Edge(k)),
        );
        // What each item hangs from in the row above: a stage's inputs (or
        // their crossings), an edge's producer (or its own crossing).
        let above = |it: Item| -> Vec<Item> {
            let from = |k: usize| {
                let i = edges[k].0;
                if level[i] + 1 == row {
                    Item::Stage(i)
                } else {
                    Item::Edge(k)
                }
            };
            match it {
                Item::Stage(j) => edges
                    .iter()
                    .enumerate()
                    .filter(|(_, e)| e.1 == j)
                    .map(|(k, _)| from(k))
                    .collect(),
                Item::Edge(k) => vec![from(k)],
            }
        };
        let mut keyed: Vec<(f64, usize, Item)> = items
            .into_iter()
            .map(|it| {
                let xs: Vec<f64> = above(it)
                    .into_iter()
                    .filter_map(|a| centre.get(&(row.wrapping_sub(1), id(a))).copied())
                    .collect();
                let bary = if xs.is_empty() {
                    f64::INFINITY
                } else {
                    xs.iter().sum::<f64>() / xs.len() as f64
                };
                (bary, id(it), it)
            })
            .collect();
        // Stages without inputs keep file order; the rest follow their inputs.
        keyed.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let row_w: i32 = keyed.iter().map(|&(_, _, it)| width_of(it)).sum::<i32>()
            + (keyed.len() as i32 - 1).max(0) * COL_GAP;
        out.width = out.width.max(row_w);
        let mut x = -row_w / 2;
        let mut placed = Vec::new();
        for (_, _, it) in keyed {
            let w = width_of(it);
            centre.insert((row, id(it)), (x + w / 2) as f64);
            match it {
                Item::Stage(i) => out.stage[i] = (x, row),
                Item::Edge(k) => out.crossings[k].push((x + w / 2, row)),
            }
            placed.push((it, x));
            x += w + COL_GAP;
        }
        out.rows.push(placed);
    }
    out
}

fn draw_err<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow!("drawing the stage graph: {e}")
}

/// The graph as an SVG, each stage coloured by its status, with a legend.
pub fn svg(p: &Pipeline, statuses: &Statuses) -> Result<String> {
    let edges = edges(p);
    let box_w = p
        .stages
        .iter()
        .map(|s| text_width(&s.name, 14.0).max(text_width(s.config.kind(), 12.0)))
        .max()
        .unwrap_or(80)
        + 20;
    let lay = layout(p, &edges, box_w);
    let title = format!("{}: stage graph", p.name);
    // Room for the longest edge label beside a middle edge, on either side.
    let label_w = edges
        .iter()
        .map(|(_, _, l)| text_width(l, 11.0) + 12)
        .max()
        .unwrap_or(0);
    let width = (lay.width + 2 * MARGIN)
        .max(text_width(&title, 18.0) + 2 * MARGIN)
        .max(2 * label_w + 2 * MARGIN)
        .max(520);
    let top = MARGIN + 30;
    let height = top + lay.rows.len() as i32 * (BOX_H + ROW_GAP) - ROW_GAP + MARGIN + LEGEND_H;
    let x0 = width / 2;
    let row_y = |row: usize| top + row as i32 * (BOX_H + ROW_GAP);
    // Each edge as a polyline: out of its producer's bottom, through the
    // rows it crosses, into its consumer's top.
    let mut paths: Vec<Vec<(i32, i32)>> = edges
        .iter()
        .enumerate()
        .map(|(k, (i, j, _))| {
            let (xi, ri) = lay.stage[*i];
            let (xj, rj) = lay.stage[*j];
            let mut pts = vec![(x0 + xi + box_w / 2, row_y(ri) + BOX_H)];
            for &(x, r) in &lay.crossings[k] {
                pts.push((x0 + x, row_y(r)));
                pts.push((x0 + x, row_y(r) + BOX_H));
            }
            pts.push((x0 + xj + box_w / 2, row_y(rj)));
            pts
        })
        .collect();
    // Edges leave and enter a box at their own points along its side,
    // ordered by where they go or come from, so that they do not meet.
    for i in 0..p.stages.len() {
        let left = x0 + lay.stage[i].0;
        let mut outs: Vec<(i32, usize)> = (0..edges.len())
            .filter(|&k| edges[k].0 == i)
            .map(|k| (paths[k][1].0, k))
            .collect();
        outs.sort();
        for (rank, &(_, k)) in outs.iter().enumerate() {
            paths[k][0].0 = left + box_w * (rank as i32 + 1) / (outs.len() as i32 + 1);
        }
        let mut ins: Vec<(i32, usize)> = (0..edges.len())
            .filter(|&k| edges[k].1 == i)
            .map(|k| (paths[k][paths[k].len() - 2].0, k))
            .collect();
        ins.sort();
        for (rank, &(_, k)) in ins.iter().enumerate() {
            let last = paths[k].len() - 1;
            paths[k][last].0 = left + box_w * (rank as i32 + 1) / (ins.len() as i32 + 1);
        }
    }
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
        // The boxes labels must keep off: the stages, and all beyond the
        // canvas's sides (a long label beside the rightmost edge of the
        // uncertainty-check graph ran off it) and below its last row (the
        // legend).
        let (far, cw, ch) = (1e6, f64::from(width), f64::from(height));
        let mut taken: Vec<plots::PixelBox> = (0..p.stages.len())
            .map(|i| {
                let (x, y) = (x0 + lay.stage[i].0, row_y(lay.stage[i].1));
                [x, y, x + box_w, y + BOX_H].map(f64::from)
            })
            .chain([
                [-far, -far, 0.0, far],
                [cw, -far, far, far],
                [-far, -far, far, 0.0],
                [-far, ch - f64::from(MARGIN + LEGEND_H) + 8.0, far, far],
            ])
            .collect();
        for (path, (_, _, label)) in paths.iter().zip(&edges) {
            root.draw(&PathElement::new(path.clone(), line.stroke_width(1)))
                .map_err(draw_err)?;
            let (a, b) = (path[path.len() - 2], path[path.len() - 1]);
            root.draw(&Polygon::new(arrow_head(a, b), line.filled()))
                .map_err(draw_err)?;
            // The slot's name beside its edge, near the consumer if there
            // is room, else further up the last stretch, else beside an
            // earlier one.
            let along = |(a, b): ((i32, i32), (i32, i32)), t: f64| {
                (
                    f64::from(a.0) + t * f64::from(b.0 - a.0) + 4.0,
                    f64::from(a.1) + t * f64::from(b.1 - a.1),
                )
            };
            let stretches: Vec<((i32, i32), (i32, i32))> =
                path.windows(2).rev().map(|w| (w[0], w[1])).collect();
            let w = plots::text_width_px(label, 11.0);
            let right: Vec<(f64, f64)> = stretches
                .iter()
                .flat_map(|&s| [0.7, 0.5, 0.3, 0.85, 0.15].map(move |t| along(s, t)))
                .collect();
            // The same places on the left of the edge, for a label that
            // would run off the canvas's right side.
            let leftward = right.iter().map(|&(x, y)| (x - 8.0 - w, y));
            let (mut lx, ly) =
                plots::place_label(right.iter().copied().chain(leftward), w, 11.0, &mut taken);
            // Crowded everywhere: on the canvas at least.
            let clamped = lx.clamp(2.0, (f64::from(width) - 2.0 - w).max(2.0));
            if clamped != lx {
                lx = clamped;
                if let Some(b) = taken.last_mut() {
                    *b = [lx, b[1], lx + w, b[3]];
                }
            }
            root.draw(&Text::new(
                label.as_str(),
                (lx.round() as i32, ly.round() as i32),
                font(11.0, RGBColor(60, 60, 60), left),
            ))
            .map_err(draw_err)?;
        }
        for (i, s) in p.stages.iter().enumerate() {
            let (x, y) = (x0 + lay.stage[i].0, row_y(lay.stage[i].1));
            let (fill, _) = style(status_of(statuses, &s.name));
            let corners = [(x, y), (x + box_w, y + BOX_H)];
            root.draw(&Rectangle::new(corners, fill.filled()))
                .map_err(draw_err)?;
            root.draw(&Rectangle::new(corners, line.stroke_width(1)))
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
        let mut x = MARGIN;
        let y = height - MARGIN - 14;
        for st in used(statuses) {
            let (fill, label) = style(Some(st));
            let corners = [(x, y), (x + 18, y + 14)];
            root.draw(&Rectangle::new(corners, fill.filled()))
                .map_err(draw_err)?;
            root.draw(&Rectangle::new(corners, line.stroke_width(1)))
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
    use crate::diagnostics::Source;
    use crate::pipeline::resolve::load_source;

    fn pipeline() -> Pipeline {
        let text = "[stages.a]\nkind = \"mesh\"\nshape = \"plane\"\n\
            [stages.t]\nkind = \"inject\"\n\
            [stages.m]\nkind = \"measure\"\ninputs = { points = \"a\", errors = \"t\" }\n";
        load_source(&Source::new("p.toml", text), &[]).unwrap()
    }

    #[test]
    fn dot_and_mermaid_name_every_stage_and_input() {
        let p = pipeline();
        let st: Statuses = [
            ("a", Status::Cached),
            ("t", Status::Cached),
            ("m", Status::Run),
        ]
        .iter()
        .map(|(a, b)| (a.to_string(), *b))
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

    /// Regression (issue 33): in noise-sweep the plot stage after the sweep
    /// was drawn in the first row, unconnected: its input, the gathered
    /// `sweep.evaluation.criteria`, named no stage of the graph.
    fn sweep_pipeline(e: &str) -> Pipeline {
        let text = format!(
            "[stages.t]\nkind = \"inject\"\n\
             [stages.c]\nkind = \"simulate_campaign\"\ninputs = {{ errors = \"t\" }}\n\
             layout = {{ kind = \"corner\", stations = 3 }}\n\
             [stages.{e}]\nkind = \"calibrate\"\ninputs = {{ campaign = \"c\" }}\nobjective = \"bundle\"\n\
             [[sweep.axis]]\npath = \"stages.c.seed\"\nvalues = [1, 2]\n\
             [sweep]\ngather = [\"{e}.params\"]\n\
             [stages.s]\nkind = \"spread\"\ninputs = {{ table = \"sweep.{e}.params\" }}\n"
        );
        load_source(&Source::new("p.toml", text.as_str()), &[]).unwrap_or_else(|e| panic!("{e:#}"))
    }

    #[test]
    fn plot_stage_after_a_sweep_was_drawn_unconnected() {
        let p = sweep_pipeline("e");
        let e = edges(&p);
        assert_eq!(
            e.last().unwrap(),
            &(2, 3, "table ← sweep.e.params".to_string())
        );
        let lay = layout(&p, &e, 100);
        let rows: Vec<usize> = lay.stage.iter().map(|&(_, row)| row).collect();
        assert_eq!(rows, [0, 1, 2, 3]);
        let d = dot(&p, &Statuses::new());
        assert!(
            d.contains("\"e\" -> \"s\" [label=\"table ← sweep.e.params\"];"),
            "{d}"
        );
    }

    /// A long label beside the rightmost edge stays on the canvas (it ran
    /// off it in the uncertainty-check graph).
    #[test]
    fn edge_labels_stay_on_the_canvas() {
        let p = sweep_pipeline("a_calibration_whose_name_makes_a_long_label");
        let s = svg(&p, &Statuses::new()).unwrap();
        assert!(s.contains("table ← sweep.a_calibration_whose_name_makes_a_long_label.params"));
        let width: f64 = s["<svg width=\"".len()..]
            .split('"')
            .next()
            .unwrap()
            .parse()
            .unwrap();
        for (at, _) in s.match_indices("<text ") {
            let tag = &s[at..at + s[at..].find('>').unwrap()];
            let body = s[at + tag.len() + 1..]
                .split("</text>")
                .next()
                .unwrap()
                .trim();
            let x: f64 = tag
                .split(" x=\"")
                .nth(1)
                .unwrap()
                .split('"')
                .next()
                .unwrap()
                .parse()
                .unwrap();
            let size: f64 = tag
                .split("font-size=\"")
                .nth(1)
                .unwrap()
                .split('"')
                .next()
                .unwrap()
                .parse()
                .unwrap();
            let w = plots::text_width_px(body, size);
            let (x0, x1) = if tag.contains("text-anchor=\"middle\"") {
                (x - w / 2.0, x + w / 2.0)
            } else {
                (x, x + w)
            };
            assert!(
                x0 >= -0.5 && x1 <= width + 0.5,
                "{body:?} at {x0}..{x1} of {width}"
            );
        }
    }

    #[test]
    fn layout_puts_each_stage_below_its_inputs() {
        let p = pipeline();
        let lay = layout(&p, &edges(&p), 100);
        let items: Vec<Vec<Item>> = lay
            .rows
            .iter()
            .map(|r| r.iter().map(|&(it, _)| it).collect())
            .collect();
        assert_eq!(
            items,
            [vec![Item::Stage(0), Item::Stage(1)], vec![Item::Stage(2)]]
        );
        // Two boxes of 100 and a gap, centred; the consumer below between.
        assert_eq!(
            lay.stage,
            [
                (-(200 + COL_GAP) / 2, 0),
                (-(200 + COL_GAP) / 2 + 100 + COL_GAP, 0),
                (-50, 1)
            ]
        );
        let s = svg(&p, &Statuses::new()).unwrap();
        assert!(
            s.starts_with("<svg") && s.contains(">\nmeasure\n</text>"),
            "{s}"
        );
    }
}
