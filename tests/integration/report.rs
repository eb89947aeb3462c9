//! `results/<pipeline>/index.html`: what it shows, that it escapes what it
//! quotes, and that a real browser renders every figure from the file
//! system.

use crate::cli::*;
use crate::util::pipeline_path;
use std::path::{Path, PathBuf};
use std::process::Command;

const PIPELINE: &str = "synthetic-validation";

fn run_synthetic(results: &Path) {
    let f = pipeline_path("synthetic-validation.toml");
    let out = ltcal(
        results.parent().unwrap(),
        &[
            "run",
            f.to_str().unwrap(),
            "--results",
            results.to_str().unwrap(),
            "-q",
        ],
    );
    assert_code(&out, 0);
}

/// Headless Chromium, which CI installs (`.ci/run`).
pub(crate) fn chromium() -> PathBuf {
    let path = std::env::var_os("PATH").unwrap_or_default();
    for dir in std::env::split_paths(&path).chain([PathBuf::from("/usr/bin")]) {
        for name in ["chromium", "chromium-browser"] {
            let p = dir.join(name);
            if p.is_file() {
                return p;
            }
        }
    }
    panic!(
        "this test needs Chromium to render index.html and none was found on PATH \
         (.ci/run installs it: apt-get install -y chromium)"
    );
}

/// `page` loaded by headless Chromium: its DOM after the load event, and
/// what Chromium wrote on stderr — with `console_log`, the page's console
/// messages among it (lines with `:CONSOLE`).
pub(crate) fn render(page: &Path, console_log: bool) -> (String, String) {
    let profile = tempfile::tempdir().unwrap();
    let mut args = vec![
        "--headless".to_string(),
        "--no-sandbox".into(),
        "--disable-gpu".into(),
        "--disable-quic".into(),
        "--no-first-run".into(),
        "--disable-background-networking".into(),
        "--disable-component-update".into(),
        "--disable-sync".into(),
    ];
    if console_log {
        args.extend(["--enable-logging=stderr".into(), "--v=0".into()]);
    }
    args.extend([
        format!("--user-data-dir={}", profile.path().display()),
        "--dump-dom".into(),
        format!("file://{}", page.display()),
    ]);
    let out = Command::new(chromium()).args(&args).output().unwrap();
    assert!(out.status.success(), "chromium: {}", stderr(&out));
    (stdout(&out), stderr(&out))
}

/// The DOM of `page` after its load event, as rendered by Chromium.
fn rendered_dom(page: &Path) -> String {
    render(page, false).0
}

/// Every `<img …>` tag of a DOM.
fn images(dom: &str) -> Vec<&str> {
    dom.match_indices("<img ")
        .map(|(i, _)| &dom[i..i + dom[i..].find('>').unwrap() + 1])
        .collect()
}

#[test]
fn chromium_renders_every_figure_of_index_html() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_synthetic(&results);
    let page = results.join(PIPELINE).join("index.html");
    let dom = rendered_dom(&page);
    assert!(
        dom.contains("<body data-images=\"checked\">"),
        "the page's check did not run:\n{dom}"
    );
    let imgs = images(&dom);
    let srcs: Vec<&str> = imgs
        .iter()
        .map(|t| t.split("src=\"").nth(1).unwrap().split('"').next().unwrap())
        .collect();
    assert_eq!(
        srcs,
        [
            "graph.svg",
            "figure6/figure6.svg",
            "figure7/figure7.svg",
            "figure8/figure8.svg",
            "figure8_noisy/figure8-noisy.svg"
        ]
    );
    for t in &imgs {
        assert!(t.contains("data-status=\"loaded\""), "not rendered: {t}");
    }
    // The check sees a missing figure: remove one and render again.
    std::fs::remove_file(results.join(PIPELINE).join("figure7/figure7.svg")).unwrap();
    let dom = rendered_dom(&page);
    let failed: Vec<&str> = images(&dom)
        .into_iter()
        .filter(|t| t.contains("data-status=\"failed\""))
        .collect();
    assert_eq!(failed.len(), 1, "{failed:?}");
    assert!(failed[0].contains("figure7/figure7.svg"));
    assert!(dom.contains("missing figure: figure7/figure7.svg"));
}

#[test]
fn index_html_shows_the_run_small_tables_and_links_large_ones() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_synthetic(&results);
    let page = results.join(PIPELINE).join("index.html");
    let html = std::fs::read_to_string(&page).unwrap();
    // The run: every stage with its status and why it ran.
    assert!(html.contains(
        "<tr><td><a href=\"#truth\">truth</a></td><td>inject</td><td class=\"ran\">ran</td>"
    ));
    assert_eq!(
        html.matches("<td class=\"reason\">never run</td>").count(),
        25
    );
    // A summary table, shown with its numbers.
    let sphere = &html[html.find("<h3 id=\"evaluate_sphere\">").unwrap()..];
    let sphere = &sphere[..1 + sphere[1..].find("<h3 ").unwrap()];
    assert!(sphere.contains(
        "<tr><th>statistic</th><th>before_um</th><th>after_um</th><th>reduction_pct</th></tr>"
    ));
    assert!(sphere.contains("<td>rms</td><td class=\"num\">243.159857</td><td class=\"num\">0.000000</td><td class=\"num\">100.000000</td>"), "{sphere}");
    // evaluate_sphere.points has 480 rows: linked, not shown.
    assert!(sphere.contains(
        "<p>480 rows, too many to show: <a href=\"evaluate_sphere/points.parquet\">points.parquet</a>."
    ), "{sphere}");
    // Every table link points at a file that exists.
    for (i, _) in html.match_indices("href=\"") {
        let target = html[i + 6..].split('"').next().unwrap();
        if target.starts_with('#') {
            continue;
        }
        assert!(
            results.join(PIPELINE).join(target).exists(),
            "broken link {target}"
        );
    }
    // A cached run rewrites the page with the new statuses.
    run_synthetic(&results);
    let html = std::fs::read_to_string(&page).unwrap();
    assert_eq!(html.matches("<td class=\"cached\">cached</td>").count(), 25);
    assert!(html.contains("25 cached, 0 failed"));
}

#[test]
fn index_html_escapes_what_it_quotes() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("p.toml");
    std::fs::write(
        &file,
        "[pipeline]\nname = \"esc\"\ndescription = \"<script>alert('x')</script> & <b>bold</b>\"\n\n\
         [stages.a]\nkind = \"mesh\"\nshape = \"plane\"\n",
    )
    .unwrap();
    let out = ltcal(dir.path(), &["run", "p.toml", "-q"]);
    assert_code(&out, 0);
    let html = std::fs::read_to_string(dir.path().join("results/esc/index.html")).unwrap();
    assert!(html.contains(
        "<p>&lt;script&gt;alert(&#39;x&#39;)&lt;/script&gt; &amp; &lt;b&gt;bold&lt;/b&gt;</p>"
    ));
    assert!(!html.contains("<b>bold</b>"));
    assert_eq!(
        html.matches("<script>").count(),
        1,
        "only the page's own script"
    );
}
