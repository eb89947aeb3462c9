//! Where the residual lies: the base calibration's residuals broken down by
//! station, reflector, face, incidence angle, range, azimuth and elevation
//! bands, time and temperature, with the share of residual variance each
//! factor explains (η², one-way analysis of variance) and whether that share
//! is significant (F test, Bonferroni-corrected over all factors and
//! components).

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
    /// Group label of each reading (`None`: the reading lacks the value).
    pub groups: Vec<Option<String>>,
    /// A numeric position of each reading for plots.
    pub x: Vec<f64>,
    /// Group labels in plotting order.
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

fn categorical(name: &'static str, values: Vec<Option<String>>) -> Factor {
    let mut labels: Vec<String> = values.iter().flatten().cloned().collect();
    labels.sort();
    labels.dedup();
    let x = values
        .iter()
        .map(|v| {
            v.as_ref()
                .and_then(|v| labels.binary_search(v).ok())
                .map_or(f64::NAN, |i| i as f64)
        })
        .collect();
    Factor {
        name,
        groups: values,
        x,
        labels,
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
    // The labels present, sorted: those of the bins some value falls in.
    let mut present = vec![false; bin_labels.len()];
    for &k in bins.iter().flatten() {
        present[k] = true;
    }
    let mut labels: Vec<String> = (0..bin_labels.len())
        .filter(|&k| present[k])
        .map(|k| bin_labels[k].clone())
        .collect();
    labels.sort();
    labels.dedup();
    let groups: Vec<Option<String>> = bins
        .iter()
        .map(|b| b.map(|k| bin_labels[k].clone()))
        .collect();
    Factor {
        name,
        groups,
        x: values.iter().map(|v| v.unwrap_or(f64::NAN)).collect(),
        labels,
    }
}

/// The factors the readings carry (those without values are left out).
pub fn factors(rows: &[ResidualRow]) -> Vec<Factor> {
    let mut out = vec![
        categorical(
            "station",
            rows.iter().map(|r| Some(r.station.clone())).collect(),
        ),
        categorical(
            "reflector",
            rows.iter().map(|r| Some(r.target.clone())).collect(),
        ),
        categorical(
            "face",
            rows.iter().map(|r| Some(r.face.to_string())).collect(),
        ),
        binned(
            "range_mm",
            rows.iter().map(|r| Some(r.range_mm)).collect(),
            5,
            "mm",
        ),
        binned(
            "azimuth_deg",
            rows.iter().map(|r| Some(r.azimuth_deg)).collect(),
            6,
            "°",
        ),
        binned(
            "elevation_deg",
            rows.iter().map(|r| Some(r.elevation_deg)).collect(),
            5,
            "°",
        ),
    ];
    if rows.iter().all(|r| r.incidence_deg.is_some()) {
        out.push(binned(
            "incidence_deg",
            rows.iter().map(|r| r.incidence_deg).collect(),
            5,
            "°",
        ));
    }
    if rows.iter().all(|r| r.time_s.is_some()) {
        out.push(binned(
            "time_s",
            rows.iter().map(|r| r.time_s).collect(),
            5,
            "s",
        ));
    }
    if rows.iter().all(|r| r.temperature_c.is_some()) {
        out.push(binned(
            "temperature_c",
            rows.iter().map(|r| r.temperature_c).collect(),
            5,
            "°C",
        ));
    }
    out.retain(|f| f.labels.len() >= 2);
    out
}

/// One-way analysis of variance of every component by every factor.
pub fn analyse(rows: &[ResidualRow], factors: &[Factor], alpha: f64) -> Vec<FactorTest> {
    let n_tests = (factors.len() * COMPONENTS.len()).max(1);
    let mut out = Vec::new();
    for f in factors {
        for (c, &component) in COMPONENTS.iter().enumerate() {
            let mut sums: std::collections::BTreeMap<&str, (f64, usize)> = Default::default();
            let mut all = Vec::new();
            for (r, g) in rows.iter().zip(&f.groups) {
                if let Some(g) = g {
                    let e = sums.entry(g.as_str()).or_insert((0.0, 0));
                    e.0 += r.sigma_units[c];
                    e.1 += 1;
                    all.push(r.sigma_units[c]);
                }
            }
            let n = all.len();
            let g = sums.len();
            if g < 2 || n <= g {
                continue;
            }
            let grand = all.iter().sum::<f64>() / n as f64;
            let ss_total: f64 = all.iter().map(|x| (x - grand).powi(2)).sum();
            let ss_between: f64 = sums
                .values()
                .map(|(s, k)| *k as f64 * (s / *k as f64 - grand).powi(2))
                .sum();
            let ss_within = (ss_total - ss_between).max(1e-300);
            let f_stat = (ss_between / (g - 1) as f64) / (ss_within / (n - g) as f64);
            let p = super::f_test::p_value((g - 1) as f64, (n - g) as f64, f_stat);
            let (worst, mean) = sums
                .iter()
                .map(|(k, (s, m))| (k.to_string(), s / *m as f64))
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
                worst_group: worst,
                worst_mean_sigma: mean,
            });
        }
    }
    out
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
            rows.iter().map(|r| Some(r.station.clone())).collect(),
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
            rows.iter().map(|r| Some(r.station.clone())).collect(),
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
