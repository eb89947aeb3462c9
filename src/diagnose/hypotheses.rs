//! A researcher's hypotheses ([`crate::hypothesis`]) as candidates: the
//! same signatures the catalogue's effects have, built from each
//! hypothesis's analytic Jacobian, so the explanation set, the F test, the
//! held-out score and the gap treat them as it treats `range-scale`.
//!
//! A parameter with a scope gets one column per instance present in the
//! readings (per station, reflector or face). The columns are the Jacobian
//! at the parameters' `start`, and the fit is of `θ − start`: exact for an
//! expression linear in its parameters.

use super::candidates::{Candidate, ReadingInfo, Skipped, put_d, put_point};
use super::linear::Signature;
use crate::diagnostics::SourceError;
use crate::hypothesis::covariates::Covariates;
use crate::hypothesis::{ActsOn, Hypothesis, Scope};
use std::sync::Arc;

/// The covariates of reading `r`.
pub fn covariates<'a>(
    r: &ReadingInfo,
    stations: &'a [String],
    targets: &'a [String],
) -> Covariates<'a> {
    Covariates {
        az: r.az,
        el: r.el,
        d: r.d,
        face: r.face,
        time_s: r.time_s,
        since_station_s: r.since_station_s,
        temperature_c: r.temperature_c,
        incidence: r.incidence,
        point: r.point,
        station_pos: r.station_pos,
        station: &stations[r.station],
        reflector: &targets[r.target],
    }
}

/// `S1/T07/1`: a reading as a diagnosis names it (with its readings.csv
/// line when `lines` knows it).
fn place(
    r: &ReadingInfo,
    i: usize,
    stations: &[String],
    targets: &[String],
    lines: &[Option<usize>],
) -> String {
    let mut p = format!("{}/{}/{}", stations[r.station], targets[r.target], r.face);
    if let Some(Some(l)) = lines.get(i) {
        p.push_str(&format!(", readings.csv line {l}"));
    }
    p
}

/// Each parameter's instances present in the readings, in order of first
/// appearance sorted by name, and its first column.
fn instances(h: &Hypothesis, covs: &[Covariates]) -> Vec<(usize, Vec<String>)> {
    let mut at = 0;
    h.params
        .iter()
        .map(|p| {
            let mut v: Vec<String> = covs.iter().map(|c| p.scope.instance(c)).collect();
            v.sort();
            v.dedup();
            let first = at;
            at += v.len();
            (first, v)
        })
        .collect()
}

/// The candidate of each hypothesis; one whose covariates the campaign
/// lacks is skipped with the reason. An expression that is not finite at
/// some reading is an error at its place in the hypothesis file.
pub fn build(
    hypotheses: &[Hypothesis],
    readings: &[ReadingInfo],
    stations: &[String],
    targets: &[String],
    lines: &[Option<usize>],
) -> Result<(Vec<Candidate>, Vec<Skipped>), SourceError> {
    let mut out = Vec::new();
    let mut skipped = Vec::new();
    let covs: Vec<Covariates> = readings
        .iter()
        .map(|r| covariates(r, stations, targets))
        .collect();
    'hyp: for h in hypotheses {
        for name in h.covariates() {
            let c = crate::hypothesis::covariates::Covariate::parse(name.trim_matches(['{', '}']))
                .expect("a parsed covariate");
            if let Some(i) = covs.iter().position(|cv| cv.value(&c).is_none()) {
                skipped.push(Skipped {
                    effect: h.name.clone(),
                    reason: format!(
                        "it reads `{name}`, which the campaign does not record (reading {})",
                        place(&readings[i], i, stations, targets, lines)
                    ),
                });
                continue 'hyp;
            }
        }
        let inst = instances(h, &covs);
        let ncols: usize = inst.iter().map(|(_, v)| v.len()).sum();
        let mut c = Signature::new(ncols);
        // Each column's sum of squares: a column that moves no reading
        // cannot be fitted (a step that never switches in this campaign).
        let mut norm2 = vec![0.0; ncols];
        for (i, (r, cov)) in readings.iter().zip(&covs).enumerate() {
            let theta = h.theta(cov, &|k, _| h.params[k].start);
            let jac = h.jacobian(cov, &theta, &place(r, i, stations, targets, lines))?;
            for (k, g) in jac.iter().enumerate() {
                let (first, names) = &inst[k];
                let me = h.params[k].scope.instance(cov);
                let col = first
                    + names
                        .binary_search(&me)
                        .expect("an instance of the readings");
                norm2[col] += (g.component_div(&r.sigma)).norm_squared();
                match h.acts_on {
                    ActsOn::Reading(2) => put_d(&mut c, i, r, col, g.z),
                    ActsOn::Reading(a) => c.add(i, a, col, g[a] / r.sigma[a]),
                    ActsOn::Reflector => put_point(&mut c, i, r, col, *g),
                    // The origin moves by s: the reflector seems to move by −s.
                    ActsOn::Station => put_point(&mut c, i, r, col, -*g),
                }
            }
        }
        if let Some(dead) = norm2.iter().position(|n| *n == 0.0) {
            let (k, (first, names)) = inst
                .iter()
                .enumerate()
                .rfind(|(_, (first, _))| *first <= dead)
                .expect("every column has a parameter");
            let at = match h.params[k].scope {
                Scope::Campaign => String::new(),
                s => format!(" at {} {}", s.name(), names[dead - first]),
            };
            skipped.push(Skipped {
                effect: h.name.clone(),
                reason: format!(
                    "`{}`{at} moves no reading of this campaign: its derivative is 0 everywhere",
                    h.params[k].name
                ),
            });
            continue;
        }
        out.push(Candidate {
            effect: h.name.clone(),
            place: "all".into(),
            columns: c,
            magnitude: magnitude(h, &inst),
            unit: unit(h),
            alternatives: 1,
            detail: detail(h, &inst),
        });
    }
    Ok((out, skipped))
}

/// The magnitude from the fitted `θ − start`, one per column: the file's
/// `magnitude` expression of the campaign-wide parameters, else the first
/// parameter (its largest instance in size when it has a scope).
fn magnitude(h: &Hypothesis, inst: &[(usize, Vec<String>)]) -> super::candidates::Magnitude {
    let h = h.clone();
    let inst: Vec<(usize, usize)> = inst.iter().map(|(f, v)| (*f, v.len())).collect();
    Arc::new(move |beta: &[f64]| {
        let theta: Vec<f64> = h
            .params
            .iter()
            .zip(&inst)
            .map(|(p, (first, _))| p.start + beta[*first])
            .collect();
        if let Some(m) = h.magnitude_of(&theta) {
            return m;
        }
        let (first, n) = inst[0];
        let start = h.params[0].start;
        if h.params[0].scope == Scope::Campaign {
            start + beta[first]
        } else {
            beta[first..first + n]
                .iter()
                .map(|b| start + b)
                .fold(0.0, |m: f64, x| if x.abs() > m.abs() { x } else { m })
        }
    })
}

fn unit(h: &Hypothesis) -> String {
    if h.magnitude.is_none() && h.params.first().is_some_and(|p| p.scope != Scope::Campaign) {
        format!("{} (largest)", h.magnitude_unit)
    } else {
        h.magnitude_unit.clone()
    }
}

/// The hypothesis in words for the `detail` column: its parameters, each
/// with its scope and number of instances.
fn detail(h: &Hypothesis, inst: &[(usize, Vec<String>)]) -> String {
    let params: Vec<String> = h
        .params
        .iter()
        .zip(inst)
        .map(|(p, (_, v))| match p.scope {
            Scope::Campaign => p.name.clone(),
            s => format!("{} per {} ({})", p.name, s.name(), v.len()),
        })
        .collect();
    format!("hypothesis: {}", params.join(", "))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diagnostics::Source;
    use nalgebra::{Matrix3, Vector3};

    fn reading(station: usize, d: f64) -> ReadingInfo {
        ReadingInfo {
            station,
            target: 0,
            az: 0.1,
            el: 0.2,
            d,
            sigma: Vector3::new(1e-6, 1e-6, 1e-3),
            jinv: Matrix3::identity(),
            rotation: Matrix3::identity(),
            since_station_s: Some(0.0),
            temperature_c: None,
            incidence: None,
            face: 1.0,
            time_s: Some(10.0),
            point: Vector3::zeros(),
            station_pos: Vector3::zeros(),
        }
    }

    #[test]
    fn a_per_station_scale_has_one_column_per_station_in_sigma_units() {
        let h = crate::hypothesis::parse(Source::new(
            "h.toml",
            "[scale]\nacts_on = \"d\"\nunit = \"um\"\nexpr = \"k*d/1000\"\n[scale.params]\nk = { scope = \"station\", unit = \"µm/m\" }\n",
        ))
        .unwrap();
        let rs = [reading(0, 2000.0), reading(1, 5000.0)];
        let st = ["S1".to_string(), "S2".to_string()];
        let tg = ["T1".to_string()];
        let (c, s) = build(&h, &rs, &st, &tg, &[]).unwrap();
        assert!(s.is_empty());
        assert_eq!(c[0].columns.ncols(), 2);
        // ∂Δd/∂k = d/1000 µm = 2 µm = 2e-3 mm, over σ_d = 1e-3 mm: 2.
        let t = c[0].columns.times(&[1.0, 0.0]);
        assert_eq!(
            t,
            vec![(0, Vector3::new(0.0, 0.0, 2.0)), (1, Vector3::zeros())]
        );
        assert_eq!((c[0].magnitude)(&[1.0, -3.0]), -3.0);
        assert_eq!(c[0].unit, "µm/m (largest)");
    }

    #[test]
    fn a_hypothesis_on_temperature_is_skipped_without_it() {
        let h = crate::hypothesis::parse(Source::new(
            "h.toml",
            "[warm]\nacts_on = \"d\"\nunit = \"um\"\nexpr = \"k*(temperature_c-20)\"\n[warm.params]\nk = {}\n",
        ))
        .unwrap();
        let rs = [reading(0, 2000.0)];
        let (c, s) = build(&h, &rs, &["S1".into()], &["T1".into()], &[Some(2)]).unwrap();
        assert!(c.is_empty());
        assert!(
            s[0].reason.contains("temperature_c") && s[0].reason.contains("line 2"),
            "{}",
            s[0].reason
        );
    }

    #[test]
    fn a_step_that_never_switches_is_skipped_with_the_reason() {
        let h = crate::hypothesis::parse(Source::new(
            "h.toml",
            "[late]\nacts_on = \"d\"\nunit = \"um\"\nexpr = \"k*step(time_s - 1000000)\"\n[late.params]\nk = { scope = \"station\" }\n",
        ))
        .unwrap();
        let rs = [reading(0, 2000.0), reading(1, 3000.0)];
        let (c, s) = build(&h, &rs, &["S1".into(), "S2".into()], &["T1".into()], &[]).unwrap();
        assert!(c.is_empty());
        assert_eq!(
            s[0].reason,
            "`k` at station S1 moves no reading of this campaign: its derivative is 0 everywhere"
        );
    }
}
