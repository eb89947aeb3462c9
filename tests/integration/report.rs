//! `results/<pipeline>/index.html`: what it shows (figures first, tables by
//! stage behind an index, a sweep's gathered tables, numbers rounded for
//! reading), that it escapes what it quotes, and that a real browser
//! renders every figure from the file system without a console error.

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

/// Headless Chromium, if installed.
pub(crate) fn find_chromium() -> Option<PathBuf> {
    let path = std::env::var_os("PATH").unwrap_or_default();
    for dir in std::env::split_paths(&path).chain([PathBuf::from("/usr/bin")]) {
        for name in ["chromium", "chromium-browser"] {
            let p = dir.join(name);
            if p.is_file() {
                return Some(p);
            }
        }
    }
    None
}

/// Headless Chromium, which CI installs (`.ci/run`).
pub(crate) fn chromium() -> PathBuf {
    find_chromium().unwrap_or_else(|| {
        panic!(
            "this test needs Chromium to render index.html and none was found on PATH \
         (.ci/run installs it: apt-get install -y chromium)"
        )
    })
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
            "figure6/figure6.svg",
            "figure7/figure7.svg",
            "figure8/figure8.svg",
            "figure8_noisy/figure8-noisy.svg",
            "graph.svg",
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
    let sphere = &html[html.find("<details id=\"evaluate_sphere\"").unwrap()..];
    let sphere = &sphere[..sphere.find("</details>").unwrap()];
    assert!(sphere.contains(
        "<tr><th>statistic</th><th>before_um</th><th>after_um</th><th>reduction_pct</th></tr>"
    ));
    // Rounded to 4 significant digits (no uncertainty column): 243.159857,
    // 0.000000 and 100.000000 with six decimals whatever they meant.
    let rms = "<tr><td>rms</td><td class=\"num\">243.2</td><td class=\"num\">";
    let after = &sphere[sphere.find(rms).expect(sphere) + rms.len()..];
    let (after_um, rest) = after.split_once("</td>").unwrap();
    // Noise-free: zero up to rounding (4.35e-9 here), no longer "0.000000".
    assert!(after_um.parse::<f64>().unwrap().abs() < 1e-6, "{after_um}");
    assert!(
        rest.starts_with("<td class=\"num\">100</td></tr>"),
        "{rest}"
    );
    // evaluate_sphere.points has 480 rows: previewed and linked.
    assert!(sphere.contains(
        "<h4>points <small><a href=\"evaluate_sphere/points.parquet\">points.parquet</a>, 480 rows × "
    ), "{sphere}");
    assert!(sphere.contains(&format!(
        "… {} more rows: <a href=\"evaluate_sphere/points.parquet\">points.parquet</a></td></tr>",
        480 - 10
    )), "{sphere}");
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
        "<p class=\"lead\">&lt;script&gt;alert(&#39;x&#39;)&lt;/script&gt; &amp; &lt;b&gt;bold&lt;/b&gt;</p>"
    ));
    assert!(!html.contains("<b>bold</b>"));
    assert_eq!(
        html.matches("<script>").count(),
        1,
        "only the page's own script"
    );
}

/// A sweep of two noise levels over the corner campaign, its criteria
/// gathered and plotted.
fn small_sweep(dir: &Path) -> PathBuf {
    let path = dir.join("small-sweep.toml");
    std::fs::write(
        &path,
        r#"[pipeline]
name = "small-sweep"
description = "Two noise levels, gathered and plotted"

[stages.truth]
kind = "inject"

[stages.corner]
kind = "simulate_campaign"
inputs = { errors = "truth" }
layout = { kind = "corner", stations = 3 }
noise = { sigma_angle_urad = 1.0, sigma_range_um = 2.0 }

[stages.calibration]
kind = "calibrate"
inputs = { campaign = "corner" }
objective = "bundle"

[stages.evaluation]
kind = "evaluate_campaign"
inputs = { campaign = "corner", params = "calibration" }

[[sweep.axis]]
path = "stages.corner.noise.sigma_angle_urad"
values = [0.5, 1.0]

[sweep]
gather = ["evaluation.criteria"]

[stages.figure]
kind = "plot"
plot = "metric"
inputs = { table = "sweep.evaluation.criteria" }
x = "sigma_angle_urad"
y = "improvement_pct"
filter = { criterion = "coordinates", station = "all", statistic = "average" }
file = "figure.svg"
"#,
    )
    .unwrap();
    path
}

fn run_into(file: &Path, results: &Path) {
    let out = ltcal(
        results.parent().unwrap(),
        &[
            "run",
            file.to_str().unwrap(),
            "--results",
            results.to_str().unwrap(),
            "-q",
        ],
    );
    assert_code(&out, 0);
}

/// Regression (issue 33): a sweep's page said "No tables: the stage
/// cached." for every per-point stage and never linked the gathered
/// tables; its stage graph drew the plot after the sweep unconnected.
#[test]
fn sweep_page_said_no_tables_and_never_linked_the_gathered_tables() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_into(&small_sweep(dir.path()), &results);
    let folder = results.join("small-sweep");
    let html = std::fs::read_to_string(folder.join("index.html")).unwrap();
    assert!(!html.contains("No tables"), "{html}");
    // The description line, then the figure before any table.
    assert!(html.contains("<p class=\"lead\">Two noise levels, gathered and plotted</p>"));
    let figure = html.find("<img src=\"figure/figure.svg\"").unwrap();
    assert!(figure < html.find("<table>").unwrap());
    // The gathered table: linked, sized and previewed; the stage that
    // produces it at each point leads there.
    let sweep = &html[html.find("<h2 id=\"sweep\">Sweep</h2>").unwrap()..];
    assert!(
        sweep.contains(
            "<p>2 points (2 ran, 0 cached, 0 failed) over <code>sigma_angle_urad</code>.</p>"
        ),
        "{sweep}"
    );
    let rows = 2 * 16;
    assert!(
        sweep.contains(&format!(
            "<h4>evaluation.criteria <small><a href=\"sweep/evaluation.criteria.parquet\">\
         evaluation.criteria.parquet</a>, {rows} rows × 9 columns</small></h4>"
        )),
        "{sweep}"
    );
    // Up to 50 rows, shown whole (larger ones: their first 10).
    let table = &sweep[..sweep.find("</table>").unwrap()];
    assert_eq!(table.matches("<tr><td").count(), rows, "{table}");
    assert!(folder.join("sweep/evaluation.criteria.parquet").is_file());
    assert!(
        html.contains(
            "<p>Run at every sweep point; its tables stay in the cache, one set a point, and are \
         gathered over the points: <a href=\"#sweep\">evaluation.criteria</a>.</p>"
        ),
        "{html}"
    );
    // The swept value as written: 0.5, not 0.500000.
    assert!(sweep.contains("<td class=\"num\">0.5</td>"), "{sweep}");
    // The graph draws the gathered table's edge into the plot.
    let graph = std::fs::read_to_string(folder.join("graph.svg")).unwrap();
    assert!(
        graph.contains(">\ntable ← sweep.evaluation.criteria\n</text>"),
        "{graph}"
    );
}

/// Regression (issue 33): the corner pipeline's page listed its 110 tables
/// flat, one of them 24 rows of empty cells. Now an index of the stages
/// leads to collapsed sections, and columns without a value are named,
/// not drawn.
#[test]
fn a_page_of_110_tables_was_a_flat_list_now_collapsed_stage_sections_behind_an_index() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_into(&pipeline_path("corner.toml"), &results);
    let html = std::fs::read_to_string(results.join("corner/index.html")).unwrap();
    let stages = 24;
    let nav = &html[html.find("<nav>").unwrap()..html.find("</nav>").unwrap()];
    assert_eq!(nav.matches("<li>").count(), stages, "{nav}");
    assert!(nav.contains("<li><a href=\"#corner\">corner</a> <small>(simulate_campaign, "));
    assert_eq!(html.matches("<details id=").count(), stages);
    assert_eq!(
        html.matches(" open>").count(),
        0,
        "a big page starts collapsed"
    );
    assert!(html.matches("<h4>").count() >= 110);
    // The targets of a campaign without reference coordinates.
    let corner = &html[html.find("<details id=\"corner\"").unwrap()..];
    let corner = &corner[..corner.find("</details>").unwrap()];
    assert!(corner.contains(
        "<p class=\"note\">Without a value in any row: x_mm, y_mm, z_mm, u_mm, aim_x_mm, aim_y_mm, aim_z_mm.</p>"
    ), "{corner}");
    assert!(!html.contains("<td></td><td></td><td></td>"));
    // A link to a collapsed section opens it (the page's script).
    assert!(html.contains("if (t && t.tagName === 'DETAILS') { t.open = true; }"));
}

/// The rendered DOM of `page` and its console messages; `None` (printed)
/// when Chromium is not installed.
fn render_checked(page: &Path) -> Option<(String, Vec<String>)> {
    if find_chromium().is_none() {
        eprintln!("skipped: no chromium on PATH to render {}", page.display());
        return None;
    }
    let (dom, log) = render(page, true);
    let console = log
        .lines()
        .filter(|l| l.contains(":CONSOLE"))
        .map(str::to_string)
        .collect();
    Some((dom, console))
}

/// Issue 33, item 4: two pipeline pages — a plain one and a sweep's —
/// render in headless Chromium without a console message, every image
/// loaded, including the stage graph.
#[test]
fn chromium_renders_two_pipeline_pages_without_console_errors_and_every_image_loaded() {
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    run_synthetic(&results);
    run_into(&small_sweep(dir.path()), &results);
    for (name, figures) in [(PIPELINE, 5), ("small-sweep", 2)] {
        let page = results.join(name).join("index.html");
        let Some((dom, console)) = render_checked(&page) else {
            return;
        };
        assert_eq!(console, Vec::<String>::new(), "{name}");
        assert!(
            dom.contains("<body data-images=\"checked\">"),
            "{name}: {dom}"
        );
        let imgs = images(&dom);
        assert_eq!(imgs.len(), figures, "{name}: {imgs:?}");
        for t in &imgs {
            assert!(
                t.contains("data-status=\"loaded\""),
                "{name}: not rendered: {t}"
            );
        }
    }
}
