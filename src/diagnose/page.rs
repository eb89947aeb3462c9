//! `report.html`: the diagnosis as one page a metrologist reads top down —
//! the verdict, how far the gap shrinks, which effects (magnitude ± u),
//! where, with the residual figures beside the words, what is left, the
//! model comparison, what was tried. `report.md` says the same in the order
//! of the analysis and shows no figure; the page adds the figures, not
//! words: it renders the same Markdown parts ([`output::sections`]) with
//! pulldown-cmark.
//!
//! The page stands alone (one file to mail or archive): the figures are
//! inlined as SVG markup, the style is inline, nothing is fetched. The
//! campaign's text (its name, station and target ids) reaches the page
//! through the Markdown, where `<b>` would be raw HTML: every raw HTML
//! event is rendered as text, so it is escaped, never interpreted. The SVG
//! figures escape their own text (plotters' SVG backend).

use super::Diagnosis;
use super::output::{self, Figures};
use pulldown_cmark::{Event, Options, Parser, html};
use std::fmt::Write as _;

const STYLE: &str = "
body { font-family: sans-serif; margin: 2em auto; max-width: 70em; padding: 0 1em; color: #222; line-height: 1.4; }
p.verdict { font-size: 1.15em; background: #f4f7fb; border-left: 4px solid #3a6ea5; padding: 0.6em 0.9em; }
table { border-collapse: collapse; margin: 0.5em 0 1.2em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.2em 0.6em; }
th { background: #f0f0f0; }
td { font-variant-numeric: tabular-nums; }
figure { margin: 1em 0 2em; }
figure svg { max-width: 100%; height: auto; border: 1px solid #ddd; }
figcaption { font-size: 0.85em; color: #555; }
";

/// Markdown as HTML, with the tables extension; raw HTML (only campaign
/// text can carry it) rendered as escaped text.
fn markdown(md: &str) -> String {
    let events = Parser::new_ext(md, Options::ENABLE_TABLES).map(|e| match e {
        Event::Html(t) | Event::InlineHtml(t) => Event::Text(t),
        e => e,
    });
    let mut out = String::new();
    html::push_html(&mut out, events);
    out
}

/// Plain text, escaped for HTML.
fn text(s: &str) -> String {
    let mut out = String::new();
    html::push_html(&mut out, std::iter::once(Event::Text(s.into())));
    out
}

/// A figure written beside the page, inlined, with its file name as the
/// caption; nothing when it was not drawn.
fn figure(h: &mut String, figures: &Figures, name: &str) {
    if let Some((_, svg)) = figures.files.iter().find(|(n, _)| n == name) {
        let _ = write!(
            h,
            "<figure>\n{}\n<figcaption>{}</figcaption>\n</figure>\n",
            String::from_utf8_lossy(svg).trim(),
            text(name)
        );
    }
}

/// The page's HTML.
pub fn html(d: &Diagnosis, figures: &Figures) -> String {
    let s = output::sections(d);
    let mut h = String::new();
    let _ = write!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n\
         <title>Diagnosis of {} — ltcal</title>\n<style>{STYLE}</style>\n</head>\n<body>\n",
        text(&d.campaign)
    );
    h.push_str(&markdown(&s.title));
    h.push_str(&markdown(&s.verdict).replacen("<p>", "<p class=\"verdict\">", 1));
    h.push_str(&markdown(&s.how_far));
    h.push_str(&markdown(&s.which));
    h.push_str(&markdown(&s.ranking));
    h.push_str(&markdown(&s.blunders));
    h.push_str(&markdown(&s.place));
    // The significant factors' figures first (most variance first, as the
    // table), then every other factor's.
    let mut sig: Vec<_> = d.factors.iter().filter(|t| t.significant).collect();
    sig.sort_by(|a, b| b.eta2.total_cmp(&a.eta2));
    let mut order: Vec<&str> = Vec::new();
    for name in sig
        .iter()
        .map(|t| t.factor)
        .chain(d.factor_defs.iter().map(|f| f.name))
    {
        if !order.contains(&name) {
            order.push(name);
        }
    }
    for name in order {
        figure(&mut h, figures, &format!("residuals-{name}.svg"));
    }
    h.push_str(&markdown(&s.left));
    figure(&mut h, figures, "unexplained.svg");
    h.push_str(&markdown(&s.base));
    h.push_str(&markdown(&s.models));
    h.push_str("<h2>What was tried</h2>\n");
    h.push_str(&markdown(&s.tried));
    h.push_str(&markdown(&s.skipped));
    h.push_str(&markdown(&output::figures_left_out(&figures.notes)));
    h.push_str("</body>\n</html>\n");
    h
}

#[cfg(test)]
mod tests {
    use super::markdown;

    /// Campaign text in a table cell (a station id, a target name) is shown,
    /// not interpreted; the report's own Markdown still renders.
    #[test]
    fn raw_html_in_the_markdown_is_escaped_and_tables_render() {
        let h = markdown("| where |\n|---|\n| <b>S1</b> & <script>x</script> |\n\n<div>y</div>\n");
        assert!(h.contains("<table>"), "{h}");
        assert!(
            h.contains("<td>&lt;b&gt;S1&lt;/b&gt; &amp; &lt;script&gt;x&lt;/script&gt;</td>"),
            "{h}"
        );
        assert!(h.contains("&lt;div&gt;y&lt;/div&gt;"), "{h}");
        assert!(
            !h.contains("<b>") && !h.contains("<script") && !h.contains("<div"),
            "{h}"
        );
    }
}
