//! `report.html`, the page a diagnosis writes beside `report.md`: the same
//! verdict, every figure inlined in the order a reader asks, nothing
//! fetched, the campaign's text escaped, and a real browser renders it
//! without a console error. And `report.md`'s ranking: the `none` row (what
//! the set leaves) is said in words, never a ranked member.

use crate::cli::{assert_code, ltcal, stdout};
use std::path::{Path, PathBuf};

fn example(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("examples/campaigns")
        .join(name)
}

/// `ltcal diagnose <campaign> --out <dir>/out <extra>`: the verdict line
/// it prints and the output folder.
fn diagnose(dir: &Path, campaign: &Path, extra: &[&str]) -> (String, PathBuf) {
    let out = dir.join("out");
    let mut args = vec![
        "diagnose",
        campaign.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    let o = ltcal(dir, &args);
    assert_code(&o, 0);
    (stdout(&o).trim_end().to_string(), out)
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap()
}

/// The `.svg` files a diagnosis wrote, sorted.
fn svg_files(out: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(out)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".svg"))
        .collect();
    v.sort();
    v
}

/// Where `needle` first occurs in `hay` (panics, naming it, when absent).
fn at(hay: &str, needle: &str) -> usize {
    hay.find(needle)
        .unwrap_or_else(|| panic!("{needle:?} not on the page"))
}

/// example-07 with only `range-scale` tried: the station drift is left, so
/// the page also carries `unexplained.svg`.
#[test]
fn report_html_stands_alone_with_every_figure_inlined_in_reading_order() {
    let dir = tempfile::tempdir().unwrap();
    let (verdict, out) = diagnose(
        dir.path(),
        &example("example-07-drift-and-range-scale"),
        &["--effect", "range-scale"],
    );
    let md = read(&out.join("report.md"));
    let html = read(&out.join("report.html"));
    // The same verdict as report.md's (and as printed).
    assert!(verdict.starts_with("partly explained: range-scale at all"));
    assert!(md.contains(&format!("**Verdict:** {verdict}.")));
    assert!(html.contains(&format!("<strong>Verdict:</strong> {verdict}.")));
    // Every figure written is inlined, once.
    let svgs = svg_files(&out);
    assert_eq!(svgs.len(), 9, "{svgs:?}");
    assert!(svgs.contains(&"unexplained.svg".to_string()));
    assert_eq!(html.matches("<svg").count(), svgs.len());
    for name in &svgs {
        assert_eq!(
            html.matches(&format!("<figcaption>{name}</figcaption>"))
                .count(),
            1,
            "{name}"
        );
    }
    // Nothing fetched.
    for external in [
        "<script",
        "<link",
        "<img",
        "src=\"http",
        "href=\"http",
        "url(",
    ] {
        assert!(!html.contains(external), "{external} on the page");
    }
    // The order a metrologist reads.
    let order = [
        "<p class=\"verdict\">",
        "<h2>How far</h2>",
        "<h2>Which</h2>",
        "<h2>Where</h2>",
        "<figcaption>residuals-station.svg",
        "<figcaption>residuals-time_s.svg",
        "<figcaption>residuals-reflector.svg",
        "<h2>What is left</h2>",
        "<figcaption>unexplained.svg",
        "<h2>Base calibration</h2>",
        "<h2>Which tracker model</h2>",
        "<h2>What was tried</h2>",
        "candidate explanations were tried",
    ];
    let positions: Vec<usize> = order.iter().map(|n| at(&html, n)).collect();
    assert!(
        positions.windows(2).all(|w| w[0] < w[1]),
        "{order:?} at {positions:?}"
    );
    // The significant factors' figures first, most variance first: as the
    // Where table of report.md.
    assert!(md.contains("| station | d | 0.722 |"));
    assert!(md.contains("| time_s | d | 0.146 |"));
    // The numbers as report.md writes them.
    assert!(html.contains("<td>7.883 ± 0.568 ppm (largest)</td>"));
    assert!(md.contains("| 7.883 ± 0.568 ppm (largest) |"));
}

/// A campaign named with markup (and backticks that end report.md's code
/// span around the name): the page shows it as text.
#[test]
fn report_html_escapes_the_campaign_name() {
    let dir = tempfile::tempdir().unwrap();
    let campaign =
        crate::hostile::mutated_example(dir.path(), "example-00-none", "campaign.toml", |t| {
            t.replace(
                "name = \"example-00-none\"",
                "name = \"a`<b>bold</b>`z & co\"",
            )
        });
    let (_, out) = diagnose(dir.path(), &campaign, &[]);
    let html = read(&out.join("report.html"));
    assert!(
        !html.contains("<b>"),
        "markup from the campaign on the page"
    );
    assert!(
        html.contains("<title>Diagnosis of a`&lt;b&gt;bold&lt;/b&gt;`z &amp; co — ltcal</title>")
    );
    assert!(html.contains(
        "<h1>Diagnosis of <code>a</code>&lt;b&gt;bold&lt;/b&gt;<code>z &amp; co</code></h1>"
    ));
    // Every figure's title too (plotters escapes the SVG's text).
    assert_eq!(
        html.matches("a`&lt;b&gt;bold&lt;/b&gt;`z &amp; co: residuals by")
            .count(),
        svg_files(&out).len()
    );
    // A folder with report.html is an earlier diagnosis: replaced again.
    assert_eq!(diagnose(dir.path(), &campaign, &[]).1, out);
}

/// The console messages Chromium logs while it loads `page`.
fn console_messages(page: &Path) -> Vec<String> {
    let (dom, log) = crate::report::render(page, true);
    assert!(dom.contains("</svg>"), "{dom}");
    log.lines()
        .filter(|l| l.contains(":CONSOLE"))
        .map(str::to_string)
        .collect()
}

#[test]
fn chromium_renders_report_html_without_console_errors() {
    let dir = tempfile::tempdir().unwrap();
    let (_, out) = diagnose(
        dir.path(),
        &example("example-07-drift-and-range-scale"),
        &["--effect", "range-scale"],
    );
    assert_eq!(
        console_messages(&out.join("report.html")),
        Vec::<String>::new()
    );
    // The check sees an error when there is one.
    let broken = dir.path().join("broken.html");
    std::fs::write(
        &broken,
        "<!DOCTYPE html><html><body><svg></svg><script>console.error('boom')</script></body></html>",
    )
    .unwrap();
    let seen = console_messages(&broken);
    assert!(seen.len() == 1 && seen[0].contains("boom"), "{seen:?}");
}

/// Regression (issue 33): report.md's ranking showed
/// `| 3 | | none | all | 1.131 χ²/dof | 0.0 | yes | …`, the rest of the
/// residual as if it were a significant member. It is said in words below
/// the table, and the page says the same.
#[test]
fn report_md_which_table_has_no_none_row_named_significant() {
    for (campaign, rank, consistent) in [
        ("example-07-drift-and-range-scale", 3, "yes."),
        ("example-00-none", 1, "yes."),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let (_, out) = diagnose(dir.path(), &example(campaign), &[]);
        let md = read(&out.join("report.md"));
        let which = &md[at(&md, "## Which\n")..at(&md, "## How far")];
        let rows: Vec<&str> = which.lines().filter(|l| l.starts_with("| ")).collect();
        assert!(rows.len() > 2, "{which}");
        for row in &rows {
            assert!(!row.contains("| none |"), "{campaign}: {row}");
        }
        let words = format!(
            "What the explanation set leaves (rank {rank}, `none`: not a candidate) has χ²/dof = "
        );
        assert!(which.contains(&words), "{campaign}: {which}");
        assert!(
            which.contains(&format!(
                "Rest consistent with the stated noise: {consistent}"
            )),
            "{campaign}: {which}"
        );
        let html = read(&out.join("report.html"));
        assert!(html.contains("Rest consistent with the stated noise: yes."));
        assert!(!html.contains("<td>none</td>"));
        // The tables keep their `none` row.
        let csv = read(&out.join("diagnosis.csv"));
        assert_eq!(
            csv.lines()
                .filter(|l| l.split(',').nth(1) == Some("none"))
                .count(),
            1
        );
    }
    // When the rest is not consistent with the noise, the words say why.
    let dir = tempfile::tempdir().unwrap();
    let (_, out) = diagnose(
        dir.path(),
        &example("example-07-drift-and-range-scale"),
        &["--effect", "range-scale"],
    );
    let md = read(&out.join("report.md"));
    assert!(md.contains(
        "Rest consistent with the stated noise: no (unexplained structure along station × time: a step of S4's pose and range"
    ));
}
