//! Effect hypotheses a researcher writes in TOML: an effect the catalogue of
//! `effects.md` does not name, stated as expressions over a reading's
//! covariates with named free parameters, so that ltcal can simulate it
//! (`simulate_campaign`) and test it (`diagnose --hypotheses`) like a
//! built-in effect — magnitude ± u, Δχ², held-out gap shrink, a step in
//! the explanation set.
//!
//! ```toml
//! [adm-cyclic]
//! doc = "the ADM's cyclic error, period 0.8 m"
//! acts_on = "d"                  # az | el | d | reflector | station
//! unit = "um"                    # the expression's unit: um or mm (d, positions), urad or rad (az, el)
//! expr = "a*sin(2*PI*d/800) + b*cos(2*PI*d/800)"
//! magnitude = "sqrt(a^2 + b^2)"  # what is reported (default: the first parameter)
//! magnitude_unit = "µm"
//!
//! [adm-cyclic.params]
//! a = { unit = "µm", value = 6.0 }   # scope = "campaign" (default) | "station" | "reflector" | "face"
//! b = { unit = "µm" }
//! ```
//!
//! A hypothesis acting on a reflector's or a station's position writes
//! `shift = { x = "…", y = "…", z = "…" }` (campaign frame) instead of
//! `expr`. `value` is what `simulate_campaign` injects (a number, or one per
//! station/reflector/face: `value = { S1 = 2.0 }`, the rest 0); `start` is
//! where the diagnosis linearises (default 0: exact for an expression
//! linear in its parameters, as amplitudes, scales and offsets are).
//!
//! Every mistake is reported at its place in the file, all at once: an
//! unknown variable (with the known ones), a parameter never used, a scope
//! that does not exist, a parameter inside a function without a
//! derivative. A value that is not finite at some reading is refused when
//! the hypothesis meets the campaign, naming the reading.

pub mod covariates;
pub mod expr;

use crate::diagnostics::{Source, SourceError, toml_error};
use covariates::Covariates;
use expr::Expression;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::ops::Range;
use std::path::Path;
use toml::Spanned;

/// Hypothesis files are small: a few kB of text.
pub const MAX_FILE_BYTES: u64 = 1 << 20;

/// What a hypothesis moves.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ActsOn {
    /// A reading coordinate: 0 az, 1 el, 2 d.
    Reading(usize),
    /// The reflector's centre (campaign frame).
    Reflector,
    /// The station's origin (campaign frame).
    Station,
}

/// Over what a parameter takes one value.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scope {
    Campaign,
    Station,
    Reflector,
    Face,
}

impl Scope {
    const NAMES: &[(&str, Scope)] = &[
        ("campaign", Scope::Campaign),
        ("station", Scope::Station),
        ("reflector", Scope::Reflector),
        ("face", Scope::Face),
    ];

    /// The instance a reading belongs to: `all`, its station, reflector or
    /// face.
    pub fn instance(self, cov: &Covariates) -> String {
        match self {
            Scope::Campaign => "all".into(),
            Scope::Station => cov.station.to_string(),
            Scope::Reflector => cov.reflector.to_string(),
            Scope::Face => format!("{}", cov.face),
        }
    }

    pub fn name(self) -> &'static str {
        Scope::NAMES
            .iter()
            .find(|(_, s)| *s == self)
            .map(|(n, _)| *n)
            .expect("every scope has a name")
    }
}

/// A value to inject: one for every instance, or one per instance named
/// (the others 0).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Value {
    Same(f64),
    Each(BTreeMap<String, f64>),
}

impl Value {
    pub fn at(&self, instance: &str) -> f64 {
        match self {
            Value::Same(v) => *v,
            Value::Each(m) => m.get(instance).copied().unwrap_or(0.0),
        }
    }
}

/// A free parameter.
#[derive(Clone, Debug)]
pub struct Param {
    pub name: String,
    pub scope: Scope,
    /// Its unit, for the report (a label: the expression fixes the scale).
    pub unit: String,
    pub value: Value,
    pub start: f64,
}

/// One hypothesis, checked.
#[derive(Clone, Debug)]
pub struct Hypothesis {
    pub name: String,
    pub doc: String,
    pub acts_on: ActsOn,
    /// The expression's unit in rad (angles) or mm (lengths).
    pub scale: f64,
    /// One expression (a reading coordinate) or three (x, y, z of a
    /// shift; `None`: that component is 0).
    pub exprs: Vec<Option<Expression>>,
    pub params: Vec<Param>,
    pub magnitude: Option<Expression>,
    pub magnitude_unit: String,
    pub source: Source,
    /// Each expression's place in the file, for errors found later.
    pub spans: Vec<Range<usize>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawShift {
    x: Option<Spanned<String>>,
    y: Option<Spanned<String>>,
    z: Option<Spanned<String>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawParam {
    scope: Option<Spanned<String>>,
    #[serde(default)]
    unit: String,
    value: Option<Value>,
    #[serde(default)]
    start: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawHypothesis {
    #[serde(default)]
    doc: String,
    acts_on: Spanned<String>,
    unit: Spanned<String>,
    expr: Option<Spanned<String>>,
    shift: Option<Spanned<RawShift>>,
    magnitude: Option<Spanned<String>>,
    magnitude_unit: Option<String>,
    #[serde(default)]
    params: BTreeMap<Spanned<String>, Spanned<RawParam>>,
}

/// Where the text of a TOML string starts inside its span (after the
/// opening quotes, and the newline a multi-line string may open with).
fn content_start(src: &str, span: &Range<usize>) -> usize {
    let s = &src[span.start.min(src.len())..];
    let skip = if s.starts_with("\"\"\"") || s.starts_with("'''") {
        let nl = match s.as_bytes().get(3) {
            Some(b'\n') => 1,
            Some(b'\r') => 2,
            _ => 0,
        };
        3 + nl
    } else if s.starts_with('"') || s.starts_with('\'') {
        1
    } else {
        0
    };
    span.start + skip
}

/// The catalogue's ids and ltcal's own rows: a hypothesis may not take them.
fn reserved(name: &str) -> bool {
    crate::effects::is_reserved(name) || name == "model"
}

fn valid_param_name(name: &str) -> bool {
    let mut c = name.chars();
    c.next()
        .is_some_and(|f| f.is_ascii_alphabetic() || f == '_')
        && c.all(|x| x.is_ascii_alphanumeric() || x == '_')
}

/// Reads and checks a hypothesis file.
pub fn load(path: &Path) -> Result<Vec<Hypothesis>, Vec<crate::diagnostics::Problem>> {
    use crate::diagnostics::Problem;
    let bytes = crate::fs::read_regular_file(path, MAX_FILE_BYTES)
        .map_err(|e| vec![Problem::file(path, e.to_string())])?;
    let text = String::from_utf8(bytes)
        .map_err(|_| vec![Problem::file(path, "the hypothesis file is not UTF-8 text")])?;
    parse(Source::new(path, text)).map_err(|es| es.into_iter().map(Problem::At).collect())
}

/// Parses and checks the hypotheses of one file, every mistake at its
/// place.
pub fn parse(src: Source) -> Result<Vec<Hypothesis>, Vec<SourceError>> {
    let raw: BTreeMap<Spanned<String>, Spanned<RawHypothesis>> =
        toml::from_str(&src.text).map_err(|e| vec![toml_error(&src, e, 0..0)])?;
    let mut out = Vec::new();
    let mut errors = Vec::new();
    let mut written: Vec<_> = raw.into_iter().collect();
    written.sort_by_key(|(name, _)| name.span().start);
    for (name, body) in written {
        match one(&src, &name, body) {
            Ok(h) => out.push(h),
            Err(mut e) => errors.append(&mut e),
        }
    }
    if errors.is_empty() {
        Ok(out)
    } else {
        Err(errors)
    }
}

fn one(
    src: &Source,
    name: &Spanned<String>,
    body: Spanned<RawHypothesis>,
) -> Result<Hypothesis, Vec<SourceError>> {
    let mut errors = Vec::new();
    let hname = name.get_ref().clone();
    if hname.is_empty()
        || !hname
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
    {
        errors.push(src.error(
            name.span(),
            format!("hypothesis name `{hname}`: use letters, digits, `-` and `_`"),
        ));
    } else if reserved(&hname) {
        errors.push(src.error(
            name.span(),
            format!("`{hname}` is an effect of effects.md or a row of the diagnosis: name your hypothesis otherwise"),
        ));
    }
    let body_span = body.span();
    let raw = body.into_inner();
    let acts_on = match raw.acts_on.get_ref().as_str() {
        "az" => Some(ActsOn::Reading(0)),
        "el" => Some(ActsOn::Reading(1)),
        "d" => Some(ActsOn::Reading(2)),
        "reflector" => Some(ActsOn::Reflector),
        "station" => Some(ActsOn::Station),
        other => {
            errors.push(src.error(
                raw.acts_on.span(),
                format!("`acts_on = \"{other}\"`: one of az, el, d, reflector, station"),
            ));
            None
        }
    };
    let angle = matches!(acts_on, Some(ActsOn::Reading(0 | 1)));
    let scale = match (raw.unit.get_ref().as_str(), angle) {
        ("urad" | "µrad", true) => Some(1e-6),
        ("rad", true) => Some(1.0),
        ("um" | "µm", false) => Some(1e-3),
        ("mm", false) => Some(1.0),
        (other, _) => {
            let allowed = if angle { "urad or rad" } else { "um or mm" };
            errors.push(src.error(
                raw.unit.span(),
                format!("`unit = \"{other}\"`: the expression's unit here is {allowed}"),
            ));
            None
        }
    };
    // Parameters first: the expressions are parsed against their names.
    let mut params = Vec::new();
    let mut param_spans = Vec::new();
    // In the order written: "the first parameter" is the file's first.
    let mut written: Vec<_> = raw.params.into_iter().collect();
    written.sort_by_key(|(name, _)| name.span().start);
    for (pname, p) in written {
        let (pspan, p) = (p.span(), p.into_inner());
        let n = pname.get_ref().clone();
        if !valid_param_name(&n) || covariates::Covariate::parse(&n).is_some() {
            errors.push(src.error(
                pname.span(),
                format!(
                    "parameter name `{n}`: letters, digits and `_`, starting with a letter, and not a covariate's name"
                ),
            ));
        } else if exmex::parse::<f64>(&n).is_ok_and(|e| exmex::Express::var_names(&e).is_empty()) {
            errors.push(src.error(
                pname.span(),
                format!("parameter name `{n}` is a constant of the expression language"),
            ));
        }
        let scope = match &p.scope {
            None => Scope::Campaign,
            Some(s) => match Scope::NAMES.iter().find(|(k, _)| *k == s.get_ref()) {
                Some((_, sc)) => *sc,
                None => {
                    errors.push(src.error(
                        s.span(),
                        format!(
                            "scope `{}` does not exist: one of campaign, station, reflector, face",
                            s.get_ref()
                        ),
                    ));
                    Scope::Campaign
                }
            },
        };
        let finite = |v: &f64| v.is_finite();
        let value = p.value.unwrap_or(Value::Same(0.0));
        let all_finite = match &value {
            Value::Same(v) => finite(v),
            Value::Each(m) => m.values().all(finite),
        } && p.start.is_finite();
        if !all_finite {
            errors.push(src.error(
                pspan.clone(),
                format!("parameter `{n}`: values must be finite"),
            ));
        }
        if let (Value::Each(_), Scope::Campaign) = (&value, scope) {
            errors.push(src.error(
                pspan.clone(),
                format!("parameter `{n}` has one value per instance but the scope `campaign`: give a number, or a scope"),
            ));
        }
        params.push(Param {
            name: n,
            scope,
            unit: p.unit,
            value,
            start: p.start,
        });
        param_spans.push(pname.span());
    }
    let names: Vec<String> = params.iter().map(|p| p.name.clone()).collect();
    let parse_at = |s: &Spanned<String>, errors: &mut Vec<SourceError>| {
        let at = content_start(&src.text, &s.span());
        match Expression::parse(s.get_ref(), &names) {
            Ok(e) => Some(e),
            Err(e) => {
                errors.push(src.error(at + e.at.start..at + e.at.end, e.message));
                None
            }
        }
    };
    let mut exprs = Vec::new();
    let mut spans = Vec::new();
    match (acts_on, &raw.expr, &raw.shift) {
        (Some(ActsOn::Reading(_)), Some(e), None) => {
            exprs.push(parse_at(e, &mut errors));
            spans.push(e.span());
        }
        (Some(ActsOn::Reflector | ActsOn::Station), None, Some(s)) => {
            let sh = s.get_ref();
            for c in [&sh.x, &sh.y, &sh.z] {
                exprs.push(c.as_ref().and_then(|c| parse_at(c, &mut errors)));
                spans.push(c.as_ref().map_or(s.span(), |c| c.span()));
            }
            if exprs.iter().all(Option::is_none) && sh.x.is_none() && sh.y.is_none() && sh.z.is_none() {
                errors.push(src.error(s.span(), "`shift` needs at least one of x, y, z"));
            }
        }
        (Some(ActsOn::Reading(_)), _, _) => errors.push(src.error(
            body_span.start..body_span.start,
            format!("hypothesis `{hname}` acts on a reading: it needs `expr = \"…\"` (and no `shift`)"),
        )),
        (Some(_), _, _) => errors.push(src.error(
            body_span.start..body_span.start,
            format!("hypothesis `{hname}` moves a position: it needs `shift = {{ x = \"…\", y = \"…\", z = \"…\" }}` (and no `expr`)"),
        )),
        (None, _, _) => {}
    }
    // Every parameter must act somewhere.
    for (k, p) in params.iter().enumerate() {
        let used = exprs
            .iter()
            .flatten()
            .any(|e| e.parameters().any(|j| j == k));
        if !used && errors.is_empty() {
            errors.push(src.error(
                param_spans[k].clone(),
                format!("parameter `{}` is never used in the expression", p.name),
            ));
        }
    }
    let magnitude = raw.magnitude.as_ref().and_then(|m| {
        let e = parse_at(m, &mut errors)?;
        if let Some(c) = e.covariates().first() {
            errors.push(src.error(
                m.span(),
                format!("`magnitude` is a function of the parameters alone, not of `{}`", c.name()),
            ));
        }
        if let Some(k) = e.parameters().find(|k| params[*k].scope != Scope::Campaign) {
            errors.push(src.error(
                m.span(),
                format!(
                    "`magnitude` uses `{}`, which has one value per {}: a magnitude is of campaign-wide parameters",
                    params[k].name,
                    params[k].scope.name()
                ),
            ));
        }
        Some(e)
    });
    if !errors.is_empty() {
        return Err(errors);
    }
    let magnitude_unit = raw
        .magnitude_unit
        .or_else(|| params.first().map(|p| p.unit.clone()))
        .unwrap_or_default();
    Ok(Hypothesis {
        name: hname,
        doc: raw.doc,
        acts_on: acts_on.expect("checked"),
        scale: scale.expect("checked"),
        exprs,
        params,
        magnitude,
        magnitude_unit,
        source: src.clone(),
        spans,
    })
}

impl Hypothesis {
    /// The error of a hypothesis that cannot be evaluated at a reading
    /// (`place`, e.g. `S1/T07/1, readings.csv line 12`).
    fn at_reading(&self, k: usize, place: &str, what: &str) -> SourceError {
        let span = self.spans[k].clone();
        let at = content_start(&self.source.text, &span);
        self.source.error(
            at..span.end.saturating_sub(1).max(at + 1),
            format!("hypothesis `{}`: {what} at reading {place}", self.name),
        )
    }

    /// The parameters' values at one reading, by parameter index, from
    /// `value(param, instance)`.
    pub fn theta(&self, cov: &Covariates, value: &dyn Fn(usize, &str) -> f64) -> Vec<f64> {
        self.params
            .iter()
            .enumerate()
            .map(|(k, p)| value(k, &p.scope.instance(cov)))
            .collect()
    }

    /// What the hypothesis does at one reading with parameters `theta`:
    /// `(Δaz, Δel, Δd)` (rad, rad, mm) for a reading coordinate, the
    /// displacement (mm, campaign frame) for a position.
    pub fn apply(
        &self,
        cov: &Covariates,
        theta: &[f64],
        place: &str,
    ) -> Result<Vector3<f64>, SourceError> {
        let mut out = Vector3::zeros();
        for (k, e) in self.exprs.iter().enumerate() {
            let Some(e) = e else { continue };
            let v = e
                .eval(cov, theta)
                .map_err(|m| self.at_reading(k, place, &missing(&m)))?;
            if !v.is_finite() {
                return Err(self.at_reading(k, place, &format!("the value is {v}")));
            }
            out[self.component(k)] += v * self.scale;
        }
        Ok(out)
    }

    /// `∂apply/∂θ_k` at one reading, for every parameter `k` (physical
    /// units per unit of the parameter).
    pub fn jacobian(
        &self,
        cov: &Covariates,
        theta: &[f64],
        place: &str,
    ) -> Result<Vec<Vector3<f64>>, SourceError> {
        let mut out = vec![Vector3::zeros(); self.params.len()];
        for (k, e) in self.exprs.iter().enumerate() {
            let Some(e) = e else { continue };
            let g = e
                .gradient(cov, theta)
                .map_err(|m| self.at_reading(k, place, &missing(&m)))?;
            for (p, v) in g {
                if !v.is_finite() {
                    return Err(self.at_reading(
                        k,
                        place,
                        &format!("the derivative by `{}` is {v}", self.params[p].name),
                    ));
                }
                out[p][self.component(k)] += v * self.scale;
            }
        }
        Ok(out)
    }

    /// The vector component expression `k` acts on.
    fn component(&self, k: usize) -> usize {
        match self.acts_on {
            ActsOn::Reading(axis) => axis,
            ActsOn::Reflector | ActsOn::Station => k,
        }
    }

    /// The covariates the hypothesis reads, by name.
    pub fn covariates(&self) -> Vec<String> {
        let mut v: Vec<String> = self
            .exprs
            .iter()
            .flatten()
            .flat_map(|e| e.covariates().into_iter().map(|c| c.name()))
            .collect();
        v.sort();
        v.dedup();
        v
    }

    /// The file's `magnitude` expression at parameter values `theta` (in
    /// parameter order; it reads campaign-wide parameters only), or `None`
    /// when the file gives none (the first parameter is reported then).
    pub fn magnitude_of(&self, theta: &[f64]) -> Option<f64> {
        let m = self.magnitude.as_ref()?;
        let cov = covariates::Covariates::dummy();
        m.eval(&cov, theta).ok()
    }
}

fn missing(m: &str) -> String {
    if m.starts_with('{') || m.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
        format!("the campaign does not record `{m}`")
    } else {
        m.to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse_str(text: &str) -> Result<Vec<Hypothesis>, Vec<SourceError>> {
        parse(Source::new("h.toml", text))
    }

    fn first_error(text: &str) -> SourceError {
        parse_str(text).unwrap_err().remove(0)
    }

    #[test]
    fn a_cyclic_range_error_loads() {
        let h = parse_str(
            "[adm-cyclic]\nacts_on = \"d\"\nunit = \"um\"\nexpr = \"a*sin(2*PI*d/800) + b*cos(2*PI*d/800)\"\nmagnitude = \"sqrt(a^2+b^2)\"\n[adm-cyclic.params]\na = { unit = \"µm\", value = 6.0 }\nb = {}\n",
        )
        .unwrap();
        assert_eq!(h.len(), 1);
        assert_eq!(h[0].acts_on, ActsOn::Reading(2));
        assert_eq!(h[0].scale, 1e-3);
        assert_eq!(h[0].params[0].value, Value::Same(6.0));
        assert_eq!(h[0].magnitude_of(&[3.0, 4.0]), Some(5.0));
        assert_eq!(h[0].magnitude_unit, "µm");
    }

    #[test]
    fn an_unknown_variable_is_refused_at_its_line_and_column() {
        let e = first_error(
            "[h]\nacts_on = \"d\"\nunit = \"um\"\nexpr = \"a*cos(elevation)\"\n[h.params]\na = {}\n",
        );
        assert_eq!(e.line_col(), (4, 15));
        assert!(e.to_string().contains("^^^^^^^^^"), "{e}");
        assert!(e.message.contains("unknown variable `elevation`"));
    }

    #[test]
    fn a_parameter_never_used_is_refused_at_its_key() {
        let e = first_error(
            "[h]\nacts_on = \"d\"\nunit = \"um\"\nexpr = \"a*d\"\n[h.params]\na = {}\nb = {}\n",
        );
        assert_eq!(e.line_col(), (7, 1));
        assert!(e.message.contains("`b` is never used"), "{}", e.message);
    }

    #[test]
    fn a_scope_that_does_not_exist_is_refused_at_its_value() {
        let e = first_error(
            "[h]\nacts_on = \"d\"\nunit = \"um\"\nexpr = \"a*d\"\n[h.params]\na = { scope = \"tripod\" }\n",
        );
        assert_eq!(e.line_col(), (6, 15));
        assert!(e.message.contains("scope `tripod` does not exist"));
    }

    #[test]
    fn a_catalogue_id_is_not_a_hypothesis_name() {
        let e = first_error(
            "[range-scale]\nacts_on = \"d\"\nunit = \"um\"\nexpr = \"a*d\"\n[range-scale.params]\na = {}\n",
        );
        assert!(e.message.contains("effects.md"));
    }

    #[test]
    fn a_tripod_knocked_moves_the_station_after_a_time() {
        let h = parse_str(
            "[knock]\nacts_on = \"station\"\nunit = \"um\"\nshift = { x = \"dx*step(time_s - 600)\", z = \"dz*step(time_s - 600)\" }\n[knock.params]\ndx = { scope = \"station\", value = { S2 = 30.0 } }\ndz = { scope = \"station\" }\n",
        )
        .unwrap();
        let cov = Covariates {
            time_s: Some(900.0),
            station: "S2",
            ..Covariates::dummy()
        };
        let theta = h[0].theta(&cov, &|k, inst| h[0].params[k].value.at(inst));
        assert_eq!(theta, vec![30.0, 0.0]);
        let v = h[0].apply(&cov, &theta, "S2/T1/1").unwrap();
        assert!((v - Vector3::new(0.03, 0.0, 0.0)).norm() < 1e-15);
        let j = h[0].jacobian(&cov, &theta, "S2/T1/1").unwrap();
        assert_eq!(j[1], Vector3::new(0.0, 0.0, 1e-3));
    }

    #[test]
    fn a_division_by_zero_at_a_reading_names_the_reading() {
        let h = parse_str(
            "[h]\nacts_on = \"d\"\nunit = \"um\"\nexpr = \"a/(d - 1000)\"\n[h.params]\na = {}\n",
        )
        .unwrap();
        let cov = Covariates {
            d: 1000.0,
            ..Covariates::dummy()
        };
        let e = h[0]
            .jacobian(&cov, &[1.0], "S1/T2/1, readings.csv line 9")
            .unwrap_err();
        assert_eq!(e.line_col().0, 4);
        assert!(e.message.contains("readings.csv line 9"), "{}", e.message);
    }
}
