//! Where the residual lies: the base calibration's residuals broken down by
//! station, reflector, face, incidence angle, range, azimuth and elevation
//! bands, time and temperature, with the share of residual variance each
//! factor explains (η², one-way analysis of variance) and whether that share
//! is significant (F test, Bonferroni-corrected over all factors and
//! components).

use rayon::prelude::*;

/// One reading's residual and the factor values it is grouped by.
#[derive(Clone, Debug)]
pub struct ResidualRow {
    /// Residual in az, el, d in units of σ.
    pub sigma_units: [f64; 3],
    /// The same in µrad, µrad, µm.
    pub physical: [f64; 3],
    pub station: String,
    pub target: String,
    pub face: i64,
    pub incidence_deg: Option<f64>,
    pub range_mm: f64,
    pub azimuth_deg: f64,
    pub elevation_deg: f64,
    pub time_s: Option<f64>,
    pub temperature_c: Option<f64>,
    /// Baarda's w and the redundancy of az, el and d (the base model's;
    /// `None` where not tested).
    pub w: Option<[(f64, f64); 3]>,
}

pub const COMPONENTS: [&str; 3] = ["az", "el", "d"];

/// A factor: how it groups the readings.
#[derive(Clone, Debug)]
pub struct Factor {
    pub name: &'static str,
    /// Each reading's group, an index into `labels` (`None`: the reading
    /// lacks the value). An index, not the label: the analysis sums by
    /// group, and a label per reading was a string cloned (and compared in
    /// a map) 24 000 times per factor on a big hall.
    pub group: Vec<Option<usize>>,
    /// A numeric position of each reading for plots.
    pub x: Vec<f64>,
    /// Group labels in plotting order (sorted).
    pub labels: Vec<String>,
}

/// The analysis of one factor on one residual component.
#[derive(Clone, Debug)]
pub struct FactorTest {
    pub factor: &'static str,
    pub component: &'static str,
    pub groups: usize,
    pub eta2: f64,
    pub f: f64,
    pub p: f64,
    pub significant: bool,
    /// The group whose mean residual is largest in size, and that mean (σ).
    pub worst_group: String,
    pub worst_mean_sigma: f64,
}

fn categorical(name: &'static str, values: &[Option<&str>]) -> Factor {
    let mut labels: Vec<&str> = values.iter().flatten().copied().collect();
    labels.sort_unstable();
    labels.dedup();
    let group: Vec<Option<usize>> = values
        .iter()
        .map(|v| v.and_then(|v| labels.binary_search(&v).ok()))
        .collect();
    Factor {
        name,
        x: group
            .iter()
            .map(|g| g.map_or(f64::NAN, |i| i as f64))
            .collect(),
        group,
        labels: labels.into_iter().map(String::from).collect(),
    }
}

/// Bins a continuous value into up to `n` groups of equal count.
fn binned(name: &'static str, values: Vec<Option<f64>>, n: usize, unit: &str) -> Factor {
    let mut sorted: Vec<f64> = values.iter().flatten().copied().collect();
    sorted.sort_by(f64::total_cmp);
    let edges: Vec<f64> = (1..n)
        .filter_map(|k| sorted.get(k * sorted.len() / n).copied())
        .collect();
    let mut edges = edges;
    edges.dedup();
    // Every value lies within `sorted`'s range, so a bin's label depends
    // on its index alone: each formed once, not once per reading (a
    // 24 000-reading hall formatted 24 000 labels per factor).
    let label = |k: usize| {
        let lo = if k == 0 {
            sorted.first().copied().unwrap_or(f64::NAN)
        } else {
            edges[k - 1]
        };
        let hi = edges
            .get(k)
            .copied()
            .unwrap_or(sorted.last().copied().unwrap_or(f64::NAN));
        format!("{k}: {lo:.1}…{hi:.1} {unit}")
    };
    let bin_labels: Vec<String> = (0..=edges.len()).map(label).collect();
    let bins: Vec<Option<usize>> = values
        .iter()
        .map(|v| v.map(|v| edges.iter().filter(|&&e| v >= e).count()))
        .collect();
    // The labels present, sorted: those of the bins some value falls in
    // (each bin's label is its own: it starts with the bin's index).
    let mut present = vec![false; bin_labels.len()];
    for &k in bins.iter().flatten() {
        present[k] = true;
    }
    let mut order: Vec<usize> = (0..bin_labels.len()).filter(|&k| present[k]).collect();
    order.sort_by(|&a, &b| bin_labels[a].cmp(&bin_labels[b]));
    let mut at = vec![usize::MAX; bin_labels.len()];
    for (g, &k) in order.iter().enumerate() {
        at[k] = g;
    }
    Factor {
        name,
        group: bins.iter().map(|b| b.map(|k| at[k])).collect(),
        x: values.iter().map(|v| v.unwrap_or(f64::NAN)).collect(),
        labels: order.into_iter().map(|k| bin_labels[k].clone()).collect(),
    }
}

/// The factors the readings carry (those without values are left out).
pub fn factors(rows: &[ResidualRow]) -> Vec<Factor> {
    // Each factor is a pass of its own over the readings (a sort, a
    // search per reading): the nine side by side, kept in their order.
    let all = |f: fn(&ResidualRow) -> Option<f64>| rows.iter().all(|r| f(r).is_some());
    let build = |n: usize| -> Option<Factor> {
        let num = |f: fn(&ResidualRow) -> Option<f64>| rows.iter().map(f).collect::<Vec<_>>();
        match n {
            0 => Some(categorical(
                "station",
                &rows
                    .iter()
                    .map(|r| Some(r.station.as_str()))
                    .collect::<Vec<_>>(),
            )),
            1 => Some(categorical(
                "reflector",
                &rows
                    .iter()
                    .map(|r| Some(r.target.as_str()))
                    .collect::<Vec<_>>(),
            )),
            2 => {
                let faces: Vec<String> = rows.iter().map(|r| r.face.to_string()).collect();
                Some(categorical(
                    "face",
                    &faces.iter().map(|f| Some(f.as_str())).collect::<Vec<_>>(),
                ))
            }
            3 => Some(binned("range_mm", num(|r| Some(r.range_mm)), 5, "mm")),
            4 => Some(binned("azimuth_deg", num(|r| Some(r.azimuth_deg)), 6, "°")),
            5 => Some(binned(
                "elevation_deg",
                num(|r| Some(r.elevation_deg)),
                5,
                "°",
            )),
            6 => all(|r| r.incidence_deg)
                .then(|| binned("incidence_deg", num(|r| r.incidence_deg), 5, "°")),
            7 => all(|r| r.time_s).then(|| binned("time_s", num(|r| r.time_s), 5, "s")),
            _ => all(|r| r.temperature_c)
                .then(|| binned("temperature_c", num(|r| r.temperature_c), 5, "°C")),
        }
    };
    let out: Vec<Option<Factor>> = (0..9).into_par_iter().map(build).collect();
    out.into_iter()
        .flatten()
        .filter(|f| f.labels.len() >= 2)
        .collect()
}

/// One-way analysis of variance of every component by every factor.
pub fn analyse(rows: &[ResidualRow], factors: &[Factor], alpha: f64) -> Vec<FactorTest> {
    let n_tests = (factors.len() * COMPONENTS.len()).max(1);
    // Each factor's tests are its own: the factors in parallel, their
    // tests kept in order.
    let each: Vec<Vec<FactorTest>> = factors
        .par_iter()
        .map(|f| {
            let mut out = Vec::new();
            for (c, &component) in COMPONENTS.iter().enumerate() {
                // Per group (in the labels' order, which is the sorted
                // order a map by label kept): the sum and the count, each
                // summed in reading order.
                let mut sums = vec![(0.0, 0usize); f.labels.len()];
                let mut all = Vec::new();
                for (r, g) in rows.iter().zip(&f.group) {
                    if let Some(g) = *g {
                        let e = &mut sums[g];
                        e.0 += r.sigma_units[c];
                        e.1 += 1;
                        all.push(r.sigma_units[c]);
                    }
                }
                let present = || {
                    f.labels
                        .iter()
                        .zip(&sums)
                        .filter(|(_, (_, k))| *k > 0)
                        .map(|(l, s)| (l, *s))
                };
                let n = all.len();
                let g = present().count();
                if g < 2 || n <= g {
                    continue;
                }
                let grand = all.iter().sum::<f64>() / n as f64;
                let ss_total: f64 = all.iter().map(|x| (x - grand).powi(2)).sum();
                let ss_between: f64 = present()
                    .map(|(_, (s, k))| k as f64 * (s / k as f64 - grand).powi(2))
                    .sum();
                let ss_within = (ss_total - ss_between).max(1e-300);
                let f_stat = (ss_between / (g - 1) as f64) / (ss_within / (n - g) as f64);
                let p = super::f_test::p_value((g - 1) as f64, (n - g) as f64, f_stat);
                let (worst, mean) = present()
                    .map(|(l, (s, m))| (l, s / m as f64))
                    .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
                    .expect("two groups");
                out.push(FactorTest {
                    factor: f.name,
                    component,
                    groups: g,
                    eta2: if ss_total > 0.0 {
                        ss_between / ss_total
                    } else {
                        0.0
                    },
                    f: f_stat,
                    p,
                    significant: p * (n_tests as f64) < alpha,
                    worst_group: worst.clone(),
                    worst_mean_sigma: mean,
                });
            }
            out
        })
        .collect();
    each.into_iter().flatten().collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(station: &str, d: f64) -> ResidualRow {
        ResidualRow {
            sigma_units: [0.0, 0.0, d],
            physical: [0.0, 0.0, d],
            station: station.into(),
            target: "T".into(),
            face: 1,
            incidence_deg: None,
            range_mm: 1000.0,
            azimuth_deg: 0.0,
            elevation_deg: 0.0,
            time_s: None,
            temperature_c: None,
            w: None,
        }
    }

    /// Regression (issue 12): residuals of ±1e308 made the sums of squares
    /// ∞ − ∞ = NaN and the F test panicked; now the test is simply not
    /// significant.
    #[test]
    fn f_test_panic_on_extreme_residuals_is_not_significant() {
        let rows: Vec<ResidualRow> = (0..12)
            .map(|i| {
                let sign = if i % 2 == 0 { 1.0 } else { -1.0 };
                row(if i % 3 == 0 { "S1" } else { "S2" }, sign * 1e308)
            })
            .collect();
        let f = vec![categorical(
            "station",
            &rows
                .iter()
                .map(|r| Some(r.station.as_str()))
                .collect::<Vec<_>>(),
        )];
        for t in analyse(&rows, &f, 0.01) {
            assert!(!t.significant && t.p == 1.0, "{t:?}");
        }
    }

    #[test]
    fn a_station_offset_is_found_and_noise_is_not() {
        let mut rows = Vec::new();
        for i in 0..60 {
            let noise = ((i * 7919) % 13) as f64 / 13.0 - 0.5;
            rows.push(row(
                if i % 3 == 0 { "S1" } else { "S2" },
                noise + if i % 3 == 0 { 3.0 } else { 0.0 },
            ));
        }
        let f = vec![categorical(
            "station",
            &rows
                .iter()
                .map(|r| Some(r.station.as_str()))
                .collect::<Vec<_>>(),
        )];
        let t = analyse(&rows, &f, 0.01);
        let d = t.iter().find(|t| t.component == "d").unwrap();
        assert!(
            d.significant && d.eta2 > 0.8 && d.worst_group == "S1",
            "{d:?}"
        );
        let az = t.iter().find(|t| t.component == "az");
        assert!(az.is_none_or(|a| !a.significant));
    }
}
