//! A check of the figures that cannot be fooled by eye (issue 33, item 4):
//! every SVG ltcal publishes — each pipeline's figures and stage graph, and
//! the figures of a diagnosis of every example campaign — is read back, its
//! text laid out with the font metrics the figures are drawn with
//! (`plots::text_width_px`), and it fails on text that overlaps other text
//! or leaves the canvas, and on a legend laid over data markers.
//!
//! What it reads of an SVG is what plotters and `pipeline::graph` write: a
//! `<text>` element's `x`, `y`, `dy` (top, middle or bottom anchoring),
//! `text-anchor`, `font-size` and a quarter-turn `transform`; a legend is
//! the white, 90 %-opaque `<rect>` plotters draws under its entries; data
//! markers are the `<circle>`s drawn before it.

use std::path::{Path, PathBuf};

/// A piece of text and the box its glyphs cover, in canvas pixels.
#[derive(Debug)]
struct TextBox {
    text: String,
    x0: f64,
    y0: f64,
    x1: f64,
    y1: f64,
}

/// The value of attribute `name` in the attributes of one tag.
fn attr<'a>(tag: &'a str, name: &str) -> Option<&'a str> {
    let key = format!(" {name}=\"");
    let start = tag.find(&key)? + key.len();
    let len = tag[start..].find('"')?;
    Some(&tag[start..start + len])
}

fn num(tag: &str, name: &str) -> f64 {
    attr(tag, name)
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no number {name} in {tag}"))
}

fn unescape(s: &str) -> String {
    s.replace("&lt;", "<")
        .replace("&gt;", ">")
        .replace("&quot;", "\"")
        .replace("&#39;", "'")
        .replace("&apos;", "'")
        .replace("&amp;", "&")
}

/// Every element `<name …>` of `svg`: its byte offset and its attributes.
fn tags<'a>(svg: &'a str, name: &str) -> Vec<(usize, &'a str)> {
    let open = format!("<{name} ");
    svg.match_indices(open.as_str())
        .map(|(at, _)| {
            let end = svg[at..].find('>').map_or(svg.len(), |e| at + e);
            (at, &svg[at + open.len() - 1..end])
        })
        .collect()
}

/// The boxes of every non-empty `<text>` of `svg`.
fn text_boxes(svg: &str) -> Vec<TextBox> {
    let mut out = Vec::new();
    for (at, tag) in tags(svg, "text") {
        let body_start = at + svg[at..].find('>').unwrap() + 1;
        let body_len = svg[body_start..].find("</text>").unwrap();
        let text = unescape(svg[body_start..body_start + body_len].trim());
        if text.is_empty() {
            continue;
        }
        let (x, y, size) = (num(tag, "x"), num(tag, "y"), num(tag, "font-size"));
        let w = ltcal::plots::text_width_px(&text, size);
        // Capitals and digits reach 0.72 em above the baseline; descenders
        // are left out, so that lines set close stay apart.
        let h = 0.72 * size;
        let x0 = match attr(tag, "text-anchor").unwrap_or("start") {
            "middle" => x - w / 2.0,
            "end" => x - w,
            _ => x,
        };
        // plotters anchors by `dy`: top (0.76 em down to the baseline),
        // middle (half an x-height, ~0.26 em) or bottom.
        let baseline = match attr(tag, "dy") {
            Some("0.76em") => y + 0.76 * size,
            Some("0.5ex") => y + 0.26 * size,
            Some("-0.5ex") => y - 0.26 * size,
            _ => y,
        };
        let (mut x0, mut y0, mut x1, mut y1) = (x0, baseline - h, x0 + w, baseline);
        if let Some(t) = attr(tag, "transform") {
            let args: Vec<f64> = t
                .trim_start_matches("rotate(")
                .trim_end_matches(')')
                .split(',')
                .map(|v| v.trim().parse().unwrap())
                .collect();
            let (turn, cx, cy) = (args[0].rem_euclid(360.0), args[1], args[2]);
            assert!(turn == 90.0 || turn == 270.0, "{t}");
            let s = if turn == 90.0 { 1.0 } else { -1.0 };
            let rotate = |px: f64, py: f64| (cx - s * (py - cy), cy + s * (px - cx));
            let (ax, ay) = rotate(x0, y0);
            let (bx, by) = rotate(x1, y1);
            (x0, y0, x1, y1) = (ax.min(bx), ay.min(by), ax.max(bx), ay.max(by));
        }
        out.push(TextBox {
            text,
            x0,
            y0,
            x1,
            y1,
        });
    }
    out
}

/// What is wrong with the layout of one SVG, one line a defect.
fn layout_defects(svg: &str) -> Vec<String> {
    let (_, head) = tags(svg, "svg")[0];
    let (width, height) = (num(head, "width"), num(head, "height"));
    let boxes = text_boxes(svg);
    let mut defects = Vec::new();
    // Half a pixel of slack: the metrics are Helvetica's, the browser's
    // substitute differs by less.
    for b in &boxes {
        if b.x0 < -0.5 || b.y0 < -0.5 || b.x1 > width + 0.5 || b.y1 > height + 0.5 {
            defects.push(format!(
                "{:?} leaves the {width}×{height} canvas: [{:.0}, {:.0}]–[{:.0}, {:.0}]",
                b.text, b.x0, b.y0, b.x1, b.y1
            ));
        }
    }
    for (i, a) in boxes.iter().enumerate() {
        for b in &boxes[i + 1..] {
            let dx = a.x1.min(b.x1) - a.x0.max(b.x0);
            let dy = a.y1.min(b.y1) - a.y0.max(b.y0);
            if dx > 1.5 && dy > 1.5 {
                defects.push(format!(
                    "{:?} and {:?} overlap by {dx:.0}×{dy:.0} px",
                    a.text, b.text
                ));
            }
        }
    }
    for (at, rect) in tags(svg, "rect") {
        if attr(rect, "opacity") != Some("0.9") || attr(rect, "fill") != Some("#FFFFFF") {
            continue;
        }
        let (x, y) = (num(rect, "x"), num(rect, "y"));
        let (w, h) = (num(rect, "width"), num(rect, "height"));
        let hidden = tags(&svg[..at], "circle")
            .into_iter()
            .filter(|(_, c)| {
                let (cx, cy) = (num(c, "cx"), num(c, "cy"));
                x < cx && cx < x + w && y < cy && cy < y + h
            })
            .count();
        if hidden > 0 {
            defects.push(format!(
                "the legend at ({x}, {y}), {w}×{h}, hides {hidden} data markers"
            ));
        }
    }
    defects
}

/// Every SVG under `dir`, the cache (`.ltcal/`) left out.
fn svgs_under(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            if path.file_name().is_some_and(|n| n != ".ltcal") {
                svgs_under(&path, out);
            }
        } else if path.extension().is_some_and(|e| e == "svg") {
            out.push(path);
        }
    }
}

#[test]
fn every_published_figure_keeps_its_text_apart_inside_the_canvas_and_its_legends_off_the_data() {
    let mut files = Vec::new();
    svgs_under(&crate::util::root().join("results"), &mut files);
    files.sort();
    // 49 figures and 18 stage graphs at the time of writing.
    assert!(files.len() >= 60, "{} figures", files.len());
    let defects: Vec<String> = files
        .iter()
        .flat_map(|f| {
            let svg = std::fs::read_to_string(f).unwrap();
            layout_defects(&svg)
                .into_iter()
                .map(move |d| format!("{}: {d}", f.display()))
        })
        .collect();
    assert!(defects.is_empty(), "{}", defects.join("\n"));
}

#[test]
fn every_figure_of_a_diagnosis_of_each_example_campaign_passes_the_layout_check() {
    let dir = crate::util::root().join("examples/campaigns");
    let mut campaigns: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_dir())
        .collect();
    campaigns.sort();
    assert_eq!(campaigns.len(), 13);
    let mut defects = Vec::new();
    let mut figures = 0;
    for c in &campaigns {
        let campaign = ltcal::campaign::read(c).unwrap();
        let d =
            ltcal::diagnose::diagnose(&campaign, &ltcal::diagnose::Settings::default()).unwrap();
        for (name, bytes) in ltcal::diagnose::output::figures(&d).unwrap().files {
            figures += 1;
            let svg = String::from_utf8(bytes).unwrap();
            defects.extend(
                layout_defects(&svg)
                    .into_iter()
                    .map(|x| format!("{}/{name}: {x}", c.display())),
            );
        }
    }
    // Eight figures a campaign, where its columns allow.
    assert!(figures >= 90, "{figures} figures");
    assert!(defects.is_empty(), "{}", defects.join("\n"));
}

/// The check's self-test: a clean figure passes, and each planted defect —
/// a legend moved over the data, a label printed over another, a tick label
/// pushed off the canvas — is caught.
#[test]
fn the_layout_check_catches_a_legend_over_data_overlapping_text_and_clipped_text() {
    let before: Vec<f64> = (0..60).map(|i| 100.0 + f64::from(i)).collect();
    let after: Vec<f64> = (0..60).map(|i| 1.0 + f64::from(i % 7)).collect();
    let svg = ltcal::plots::criterion_errors("planted", "error (µm)", &before, &after).unwrap();
    assert_eq!(layout_defects(&svg), Vec::<String>::new());

    // The legend drawn over the first markers, as a fixed corner did.
    let (at, rect) = tags(&svg, "rect")
        .into_iter()
        .find(|(_, r)| attr(r, "opacity") == Some("0.9"))
        .unwrap();
    let (_, circle) = tags(&svg, "circle")[0];
    let (cx, cy) = (num(circle, "cx"), num(circle, "cy"));
    let moved = rect
        .replacen(
            &format!("x=\"{}\"", attr(rect, "x").unwrap()),
            &format!("x=\"{}\"", cx - 5.0),
            1,
        )
        .replacen(
            &format!("y=\"{}\"", attr(rect, "y").unwrap()),
            &format!("y=\"{}\"", cy - 5.0),
            1,
        );
    let planted = format!("{}{}{}", &svg[..at + 5], moved, &svg[at + 5 + rect.len()..]);
    assert!(
        layout_defects(&planted)
            .iter()
            .any(|d| d.contains("legend") && d.contains("hides")),
        "{:?}",
        layout_defects(&planted)
    );

    // A second label printed over the title.
    let (t_at, title) = tags(&svg, "text")[0];
    let end = t_at + svg[t_at..].find("</text>").unwrap() + "</text>".len();
    let planted = format!("{}{}{}", &svg[..end], &svg[t_at..end], &svg[end..]);
    assert!(
        layout_defects(&planted)
            .iter()
            .any(|d| d.contains("overlap")),
        "{title}"
    );

    // The title pushed past the left edge.
    let x = attr(title, "x").unwrap();
    let planted = svg.replacen(&format!("x=\"{x}\""), "x=\"-40\"", 1);
    assert!(
        layout_defects(&planted)
            .iter()
            .any(|d| d.contains("leaves the")),
        "{:?}",
        layout_defects(&planted)
    );
}
