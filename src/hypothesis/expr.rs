//! One expression of a hypothesis: parsed by `exmex`, its variables
//! resolved to covariates and parameters, its partial derivatives by the
//! parameters formed symbolically once, at load.
//!
//! `exmex` differentiates `+ − × ÷ ^`, roots, logarithms, exponentials and
//! the trigonometric and hyperbolic functions, but refuses to differentiate
//! a product that contains `abs`, `signum`, `floor`, … even when their
//! argument holds no parameter (`a·step(time_s − 600)`). Such a call whose
//! argument is free of parameters is a covariate of its own: it is cut out of
//! the text before differentiation and evaluated separately, per reading
//! (`{#0}`, `{#1}`, …). A parameter inside one is refused at load, at its
//! place: the derivative the adjustment needs does not exist there.

use super::covariates::{Covariate, Covariates};
use exmex::prelude::*;
use exmex::{Differentiate, FloatOpsFactory, MakeOperators, Operator};
use std::ops::Range;

/// `exmex`'s operators for floats, and `step(x)` (1 for x ≥ 0, else 0): the
/// switch a tripod knocked at a known time needs.
#[derive(Clone, Debug)]
pub struct Ops;

impl MakeOperators<f64> for Ops {
    fn make<'a>() -> Vec<Operator<'a, f64>> {
        let mut ops = FloatOpsFactory::<f64>::make();
        ops.push(Operator::make_unary("step", |x| {
            if x >= 0.0 { 1.0 } else { 0.0 }
        }));
        ops
    }
}

type Ex = FlatEx<f64, Ops>;

/// Functions without a derivative: allowed only around parameter-free
/// arguments.
pub const NOT_DIFFERENTIABLE: &[&str] = &[
    "abs", "signum", "floor", "round", "ceil", "trunc", "fract", "step", "min", "max", "atan2",
];

/// What one `exmex` variable of an expression stands for.
#[derive(Clone, Debug, PartialEq)]
enum Var {
    Covariate(Covariate),
    Parameter(usize),
    /// A parameter-free call of a function without a derivative.
    Cut(usize),
}

/// A mistake in an expression: a byte range inside its text, and what is
/// wrong.
#[derive(Clone, Debug, PartialEq)]
pub struct ExprError {
    pub at: Range<usize>,
    pub message: String,
}

/// A parsed expression over a reading's covariates and the hypothesis's
/// parameters.
#[derive(Clone, Debug)]
pub struct Expression {
    pub text: String,
    value: Ex,
    vars: Vec<Var>,
    cuts: Vec<(Ex, Vec<Covariate>)>,
    /// `∂value/∂parameter`, for every parameter the expression uses.
    partials: Vec<(usize, Ex)>,
}

fn err(at: Range<usize>, message: impl Into<String>) -> ExprError {
    ExprError {
        at,
        message: message.into(),
    }
}

/// The byte range of the first occurrence of `name` as a whole word in
/// `text` (or of `{name}`), else the whole text.
fn find_word(text: &str, name: &str) -> Range<usize> {
    let braced = format!("{{{name}}}");
    if let Some(i) = text.find(&braced) {
        return i..i + braced.len();
    }
    let is_word = |c: char| c.is_alphanumeric() || c == '_';
    let mut from = 0;
    while let Some(k) = text[from..].find(name) {
        let i = from + k;
        let before = text[..i].chars().next_back().is_none_or(|c| !is_word(c));
        let after = text[i + name.len()..]
            .chars()
            .next()
            .is_none_or(|c| !is_word(c));
        if before && after {
            return i..i + name.len();
        }
        from = i + name.len();
    }
    0..text.len()
}

/// The calls of functions without a derivative in `text`, outermost first
/// and not nested in one another: `(start, end)` byte ranges of
/// `name(…)`.
fn nondifferentiable_calls(text: &str) -> Vec<(Range<usize>, &'static str)> {
    let bytes = text.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            // A braced variable name may hold anything, parentheses too.
            b'{' => {
                i = text[i..].find('}').map_or(bytes.len(), |k| i + k + 1);
                continue;
            }
            c if c.is_ascii_alphabetic() || c == b'_' => {
                let start = i;
                while i < bytes.len() && (bytes[i].is_ascii_alphanumeric() || bytes[i] == b'_') {
                    i += 1;
                }
                let word = &text[start..i];
                let Some(&name) = NOT_DIFFERENTIABLE.iter().find(|n| **n == word) else {
                    continue;
                };
                let mut j = i;
                while j < bytes.len() && bytes[j] == b' ' {
                    j += 1;
                }
                if j >= bytes.len() || bytes[j] != b'(' {
                    continue;
                }
                let mut depth = 0usize;
                let mut end = None;
                for (k, &c) in bytes.iter().enumerate().skip(j) {
                    match c {
                        b'(' => depth += 1,
                        b')' => {
                            depth -= 1;
                            if depth == 0 {
                                end = Some(k + 1);
                                break;
                            }
                        }
                        _ => {}
                    }
                }
                // Unbalanced: exmex reports it when the whole is parsed.
                let Some(end) = end else { return out };
                out.push((start..end, name));
                i = end;
            }
            _ => i += 1,
        }
    }
    out
}

/// The first number written with an exponent (`1e6`, `2.5E-3`), which
/// `exmex` reads as a number followed by a variable.
fn exponent_literal(text: &str) -> Option<Range<usize>> {
    let b = text.as_bytes();
    let word = |c: u8| c.is_ascii_alphanumeric() || c == b'_';
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'{' {
            i = text[i..].find('}').map_or(b.len(), |k| i + k + 1);
            continue;
        }
        if b[i].is_ascii_digit() && (i == 0 || !word(b[i - 1]) && b[i - 1] != b'.') {
            let start = i;
            while i < b.len() && (b[i].is_ascii_digit() || b[i] == b'.') {
                i += 1;
            }
            if i < b.len() && (b[i] == b'e' || b[i] == b'E') {
                let mut j = i + 1;
                if j < b.len() && (b[j] == b'+' || b[j] == b'-') {
                    j += 1;
                }
                if j < b.len() && b[j].is_ascii_digit() {
                    while j < b.len() && b[j].is_ascii_digit() {
                        j += 1;
                    }
                    return Some(start..j);
                }
            }
            continue;
        }
        i += 1;
    }
    None
}

fn parse(text: &str) -> Result<Ex, ExprError> {
    Ex::parse(text).map_err(|e| {
        err(
            0..text.len(),
            format!("cannot parse the expression: {}", e.msg()),
        )
    })
}

impl Expression {
    /// Parses `text`; `params` are the hypothesis's parameter names, in
    /// their order; every other name must be a covariate
    /// ([`super::covariates::COVARIATES`] or an indicator).
    pub fn parse(text: &str, params: &[String]) -> Result<Expression, ExprError> {
        if text.trim().is_empty() {
            return Err(err(0..text.len(), "the expression is empty"));
        }
        if let Some(at) = exponent_literal(text) {
            return Err(err(
                at.clone(),
                format!(
                    "`{}`: the expression language has no exponent notation; write it as a plain number or with `10^…`",
                    &text[at]
                ),
            ));
        }
        // Cut out parameter-free calls without a derivative.
        let mut rewritten = String::new();
        let mut cuts = Vec::new();
        let mut last = 0;
        for (range, name) in nondifferentiable_calls(text) {
            let call = parse(&text[range.clone()]).map_err(|e| ExprError {
                at: range.clone(),
                ..e
            })?;
            if let Some(p) = call.var_names().iter().find(|v| params.contains(v)) {
                let inner = find_word(&text[range.clone()], p);
                return Err(err(
                    range.start + inner.start..range.start + inner.end,
                    format!(
                        "parameter `{p}` inside `{name}(…)`: ltcal fits a hypothesis by its derivatives, \
                         and `{name}` has none; a parameter may stand outside {} only",
                        NOT_DIFFERENTIABLE.join(", ")
                    ),
                ));
            }
            let covs = call
                .var_names()
                .iter()
                .map(|v| Covariate::parse(v).ok_or_else(|| unknown(text, v, params, range.start)))
                .collect::<Result<Vec<_>, _>>()?;
            rewritten.push_str(&text[last..range.start]);
            rewritten.push_str(&format!("{{#{}}}", cuts.len()));
            cuts.push((call, covs));
            last = range.end;
        }
        rewritten.push_str(&text[last..]);
        let value = parse(&rewritten)?;
        let vars = value
            .var_names()
            .iter()
            .map(|v| {
                if let Some(k) = v.strip_prefix('#') {
                    return Ok(Var::Cut(k.parse().expect("ltcal's own cut names")));
                }
                if let Some(k) = params.iter().position(|p| p == v) {
                    return Ok(Var::Parameter(k));
                }
                Covariate::parse(v)
                    .map(Var::Covariate)
                    .ok_or_else(|| unknown(text, v, params, 0))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let mut partials = Vec::new();
        for (idx, v) in vars.iter().enumerate() {
            if let Var::Parameter(k) = v {
                let d = value.clone().partial(idx).map_err(|e| {
                    err(
                        find_word(text, &params[*k]),
                        format!("cannot differentiate by `{}`: {}", params[*k], e.msg()),
                    )
                })?;
                partials.push((*k, d));
            }
        }
        Ok(Expression {
            text: text.to_string(),
            value,
            vars,
            cuts,
            partials,
        })
    }

    /// The parameters the expression uses.
    pub fn parameters(&self) -> impl Iterator<Item = usize> + '_ {
        self.partials.iter().map(|(k, _)| *k)
    }

    /// The covariates the expression reads (cut calls' included).
    pub fn covariates(&self) -> Vec<&Covariate> {
        let mut out: Vec<&Covariate> = self
            .vars
            .iter()
            .filter_map(|v| match v {
                Var::Covariate(c) => Some(c),
                _ => None,
            })
            .collect();
        out.extend(self.cuts.iter().flat_map(|(_, c)| c));
        out
    }

    /// The values of the expression's variables at one reading; `None`
    /// when a covariate is missing there (the name of it).
    fn vars_at(&self, cov: &Covariates, theta: &[f64]) -> Result<Vec<f64>, String> {
        self.vars
            .iter()
            .map(|v| match v {
                Var::Covariate(c) => cov.value(c).ok_or_else(|| c.name()),
                Var::Parameter(k) => Ok(theta[*k]),
                Var::Cut(k) => {
                    let (ex, covs) = &self.cuts[*k];
                    let vals = covs
                        .iter()
                        .map(|c| cov.value(c).ok_or_else(|| c.name()))
                        .collect::<Result<Vec<_>, _>>()?;
                    ex.eval(&vals).map_err(|e| e.msg().to_string())
                }
            })
            .collect()
    }

    /// The value at one reading with parameters `theta`.
    pub fn eval(&self, cov: &Covariates, theta: &[f64]) -> Result<f64, String> {
        let vals = self.vars_at(cov, theta)?;
        self.value.eval(&vals).map_err(|e| e.msg().to_string())
    }

    /// `∂value/∂θ_k` for every parameter `k` used, at one reading.
    pub fn gradient(&self, cov: &Covariates, theta: &[f64]) -> Result<Vec<(usize, f64)>, String> {
        let vals = self.vars_at(cov, theta)?;
        self.partials
            .iter()
            .map(|(k, d)| {
                d.eval(&vals)
                    .map(|v| (*k, v))
                    .map_err(|e| e.msg().to_string())
            })
            .collect()
    }
}

fn unknown(text: &str, name: &str, params: &[String], offset: usize) -> ExprError {
    let at = find_word(&text[offset..], name);
    let mut known: Vec<String> = super::covariates::COVARIATES
        .iter()
        .map(|c| c.name.to_string())
        .collect();
    known.push("{station=ID}".into());
    known.push("{reflector=ID}".into());
    let params = if params.is_empty() {
        "none".to_string()
    } else {
        params.join(", ")
    };
    err(
        offset + at.start..offset + at.end,
        format!(
            "unknown variable `{name}`: the covariates are {}; the parameters (from `params`) are {params}",
            known.join(", ")
        ),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn cov() -> Covariates<'static> {
        Covariates {
            az: 0.3,
            el: -0.1,
            d: 4321.0,
            face: 1.0,
            time_s: Some(700.0),
            since_station_s: Some(100.0),
            temperature_c: Some(21.5),
            incidence: None,
            point: Vector3::new(1.0, 2.0, 3.0),
            station_pos: Vector3::new(-1.0, 0.0, 0.5),
            station: "S1",
            reflector: "T07",
        }
    }

    fn p(names: &[&str]) -> Vec<String> {
        names.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn a_cyclic_range_error_and_its_derivatives_by_hand() {
        let e =
            Expression::parse("a*sin(2*PI*d/800) + b*cos(2*PI*d/800)", &p(&["a", "b"])).unwrap();
        let c = cov();
        let ph = 2.0 * std::f64::consts::PI * c.d / 800.0;
        let v = e.eval(&c, &[2.0, -1.0]).unwrap();
        assert!((v - (2.0 * ph.sin() - ph.cos())).abs() < 1e-12);
        let g = e.gradient(&c, &[2.0, -1.0]).unwrap();
        assert_eq!(g.len(), 2);
        assert!((g[0].1 - ph.sin()).abs() < 1e-12 && g[0].0 == 0);
        assert!((g[1].1 - ph.cos()).abs() < 1e-12 && g[1].0 == 1);
    }

    #[test]
    fn a_step_in_time_is_cut_out_and_differentiated_around() {
        let e = Expression::parse("dx*step(time_s - 600) + 0*abs(el)", &p(&["dx"])).unwrap();
        let c = cov();
        assert_eq!(e.eval(&c, &[5.0]).unwrap(), 5.0);
        assert_eq!(e.gradient(&c, &[5.0]).unwrap(), vec![(0, 1.0)]);
        let early = Covariates {
            time_s: Some(500.0),
            ..cov()
        };
        assert_eq!(e.gradient(&early, &[5.0]).unwrap(), vec![(0, 0.0)]);
    }

    #[test]
    fn nonlinear_parameters_have_their_symbolic_derivative() {
        let e = Expression::parse("a*exp(-d/L)", &p(&["L", "a"])).unwrap();
        let c = cov();
        let theta = [1500.0, 3.0];
        let h = 1e-4;
        for (k, g) in e.gradient(&c, &theta).unwrap() {
            let mut up = theta;
            let mut dn = theta;
            up[k] += h;
            dn[k] -= h;
            let fd = (e.eval(&c, &up).unwrap() - e.eval(&c, &dn).unwrap()) / (2.0 * h);
            assert!(
                (g - fd).abs() <= 1e-7 * fd.abs().max(1e-12),
                "{k}: {g} vs {fd}"
            );
        }
    }

    #[test]
    fn a_parameter_inside_a_step_is_refused_at_its_place() {
        let text = "a*step(time_s - t0)";
        let e = Expression::parse(text, &p(&["a", "t0"])).unwrap_err();
        assert_eq!(&text[e.at.clone()], "t0");
        assert!(e.message.contains("`step`"), "{}", e.message);
    }

    #[test]
    fn an_unknown_variable_is_named_at_its_place_with_the_known_ones() {
        let text = "a*sin(azimuth)";
        let e = Expression::parse(text, &p(&["a"])).unwrap_err();
        assert_eq!(&text[e.at.clone()], "azimuth");
        assert!(e.message.contains("unknown variable `azimuth`"));
        assert!(e.message.contains("time_s") && e.message.contains("{station=ID}"));
    }

    #[test]
    fn indicators_of_stations_and_reflectors() {
        let e = Expression::parse("a*{station=S1} + b*{reflector=T08}", &p(&["a", "b"])).unwrap();
        assert_eq!(e.eval(&cov(), &[2.0, 3.0]).unwrap(), 2.0);
    }

    #[test]
    fn a_number_with_an_exponent_is_refused_at_its_place() {
        let text = "k*step(time_s - 1e6) + 2.5E-3*k";
        let e = Expression::parse(text, &p(&["k"])).unwrap_err();
        assert_eq!(&text[e.at.clone()], "1e6");
        assert!(Expression::parse("k*x2e3", &p(&["k"])).is_err_and(|e| e.message.contains("x2e3")));
    }
}
