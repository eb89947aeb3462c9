//! The error model of Section 4: a 6-DOF error transform per joint, its 18
//! parameters, how each parameter varies with its joint (Eq. 9 and 10), the
//! forward model with errors (Eq. 8) with its analytic Jacobian, and the exact
//! inverse a tracker with errors solves when it points at a reflector.
//!
//! # Where each error transform sits
//!
//! Read literally, Eq. (8) puts each error after its joint, so the rotation
//! errors of the beam would act after the beam travel and move nothing (NOTES
//! item 5). Table 2 labels the matrices `0Rerr1`, `1Rerr2`, `2Terr3`: each
//! joint's error is expressed **in the frame before that joint**. The chain is
//!
//! ```text
//! 0T3 = Rerr1 · 0A1(θ) · Rerr2 · 1A2(φ) · Terr3 · 2A3(d)
//! P   = R(ε1)·( R1(θ)·( R(ε2)·R2(φ)·p3 + δ2 ) ) + δ1
//! p3  = Terr3·(0, 0, d) = (εy3·d + δx3, −εx3·d + δy3, d + δz3)
//! ```
//!
//! This placement, and no other, reproduces the classification of Section 6
//! (NOTES item 11): every δ gives a constant error, εx1 and εy1 vary with θ, φ
//! and d, εx2 and εy2 with φ and d, εz2, εx3 and εy3 with d only, εz3 with
//! nothing. `sensitivity::tests::section6_classification` asserts it
//! parameter by parameter; εz1 is the one difference from the paper's wording (a rotation
//! about the vertical axis cannot vary with the azimuth: it varies with φ and d).
//!
//! Rotary errors use the exact rotation of Eq. (6), `R = R_x(εx)·R_y(εy)·R_z(εz)`;
//! the beam error uses the small-angle matrix of Eq. (7), as the paper does.
//!
//! # Units
//!
//! Parameter values are held in display units: µm for δ, µrad for ε (and µm/mᵏ,
//! µrad/mᵏ for the d-polynomial terms). Geometry inside is in mm and rad.
//!
//! # Other trackers
//!
//! The coefficient space is shared by every tracker model
//! ([`TrackerModel`], each a plug-in of [`crate::trackers`]): a [`ParamId`]
//! is one parameter of one model — the 18 DH parameters here, the
//! parameters of the other models in their plug-ins' tables, in registry
//! order — and a parameter set holds the parameters of one model. The DH
//! chain's mathematics stays here (its plug-in wraps it); shapes (Eq. 9 and
//! 10) are the DH chain's, every other model's parameters are constants.
//! Everything that fits or simulates goes through the [`Evaluator`] — a
//! point and its derivative by each coefficient, from the model's plug-in,
//! and the inverse — so identification, the bundle adjustment, the
//! diagnosis and simulation fit any tracker without knowing which.

pub use crate::kinematics::InverseError;
use crate::kinematics::{self, Face, Joints, Reading, link1_rotation, link2_rotation};
use crate::trackers::{self, Evaluate, Param, TrackerModel};
use multiversion::multiversion;
use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use std::cell::Cell;
use std::fmt;

/// Number of error parameters of the DH model: 6 per joint, 3 joints.
pub const N_PARAMS: usize = 18;

/// The joint an error transform belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Joint {
    /// Joint 1, the standing axis (θ).
    Theta,
    /// Joint 2, the elevation axis (φ).
    Phi,
    /// Joint 3, the beam (d).
    D,
}

impl Joint {
    pub fn number(self) -> usize {
        self as usize + 1
    }
    /// The paper's name of the joint variable.
    pub fn symbol(self) -> &'static str {
        match self {
            Joint::Theta => "θ",
            Joint::Phi => "φ",
            Joint::D => "d",
        }
    }
}

/// One error parameter of one tracker model: `δx, δy, δz, εx, εy, εz` of
/// joint 1, 2 or 3 of the DH model, or a parameter of another model, by its
/// place in the shared coefficient space (the registry's order).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ParamId(u8);

impl ParamId {
    /// The parameters of one tracker model, in table order.
    pub fn of(model: TrackerModel) -> impl Iterator<Item = ParamId> {
        let first = model.first_param();
        (first..first + model.params().len()).map(|i| ParamId(i as u8))
    }
    /// The model this parameter belongs to.
    pub fn tracker(self) -> TrackerModel {
        trackers::owner(self.index()).0
    }
    /// The place in the shared coefficient space: the DH model's first
    /// (`dx1` = 0 … `ez3` = 17), then every other model's in registry order.
    pub fn index(self) -> usize {
        self.0 as usize
    }
    pub fn from_index(i: usize) -> ParamId {
        assert!(i < trackers::n_params());
        ParamId(i as u8)
    }
    /// The place in its own model's table ([`TrackerModel::params`]).
    pub fn local(self) -> usize {
        trackers::owner(self.index()).1
    }
    /// Its entry in its model's table.
    pub fn param(self) -> &'static Param {
        let (model, k) = trackers::owner(self.index());
        &model.params()[k]
    }
    /// The joint whose variable its shape may follow; `None` for a
    /// constant-only parameter (every model's but the DH chain's).
    pub fn joint(self) -> Option<Joint> {
        self.param().joint
    }
    /// A rotation error ε or a tilt (as opposed to a translation δ or an offset).
    pub fn is_angular(self) -> bool {
        self.param().angular
    }
    /// The ASCII id used in TOML and tables: `dx1` … `ez3`, or another
    /// model's (`beam_offset_x` … `range_offset`).
    pub fn id(self) -> &'static str {
        self.param().id
    }
    /// The paper's symbol (`δx1` … `εz3`); another model's parameter's id.
    pub fn symbol(self) -> &'static str {
        self.param().symbol
    }
    /// The display unit of a constant value.
    pub fn unit(self) -> &'static str {
        if self.is_angular() { "µrad" } else { "µm" }
    }
    /// Display unit → internal unit (µm → mm, µrad → rad).
    pub fn scale(self) -> f64 {
        if self.is_angular() { 1e-6 } else { 1e-3 }
    }
    /// Accepts the ASCII id or the paper's symbol, of any model.
    pub fn parse(s: &str) -> Option<ParamId> {
        let s = s.trim();
        let all = || (0..trackers::n_params()).map(|i| ParamId(i as u8));
        all()
            .find(|p| p.id() == s)
            .or_else(|| all().find(|p| p.symbol() == s))
    }
    /// Every model's ids for messages: `dx1 … ez3 (δx1 … εz3) or a
    /// mirror-tracker parameter (beam_offset_x … range_offset)`.
    fn expected() -> String {
        let spans: Vec<String> = TrackerModel::ALL
            .iter()
            .filter_map(|m| {
                let (first, last) = (m.params().first()?, m.params().last()?);
                let ids = format!("{} … {}", first.id, last.id);
                Some(if *m == TrackerModel::default() {
                    format!("{ids} ({} … {})", first.symbol, last.symbol)
                } else {
                    format!("a {m} parameter ({ids})")
                })
            })
            .collect();
        spans.join(" or ")
    }
}

impl fmt::Display for ParamId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.symbol())
    }
}

impl Serialize for ParamId {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.id())
    }
}

impl<'de> Deserialize<'de> for ParamId {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        ParamId::parse(&s).ok_or_else(|| {
            serde::de::Error::custom(format!(
                "unknown error parameter `{s}`; expected one of {}",
                ParamId::expected()
            ))
        })
    }
}

/// How one parameter varies with the joint position.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum Shape {
    /// A constant (the default).
    #[default]
    Constant,
    /// Eq. (9): constant plus `n` harmonics in the joint angle,
    /// `c + Σₖ aₖ·sin(k·q) + bₖ·cos(k·q)` — the paper's `A·sin(2π/T·q + ϕ)`
    /// with `T = 2π/k`, written so that it is linear in its coefficients.
    Fourier(u32),
    /// Eq. (10): a polynomial of degree `n` in the distance,
    /// `c₀ + c₁·d + … + cₙ·dⁿ` with d in metres.
    Poly(u32),
}

impl fmt::Display for Shape {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Shape::Constant => f.write_str("constant"),
            Shape::Fourier(n) => write!(f, "fourier:{n}"),
            Shape::Poly(n) => write!(f, "poly:{n}"),
        }
    }
}

impl std::str::FromStr for Shape {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || {
            format!(
                "invalid shape `{s}`: expected \"constant\", \"fourier:N\" (N ≥ 1 harmonics) or \"poly:N\" (degree N ≥ 1)"
            )
        };
        if s == "constant" {
            return Ok(Shape::Constant);
        }
        let (kind, n) = s.split_once(':').ok_or_else(bad)?;
        let n: u32 = n.trim().parse().map_err(|_| bad())?;
        if n == 0 || n > 32 {
            return Err(bad());
        }
        match kind.trim() {
            "fourier" => Ok(Shape::Fourier(n)),
            "poly" => Ok(Shape::Poly(n)),
            _ => Err(bad()),
        }
    }
}

impl Serialize for Shape {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for Shape {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}

/// One term of a parameter's shape.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Term {
    Const,
    Sin(u32),
    Cos(u32),
    /// `dᵏ`, d in metres.
    Pow(u32),
}

/// One coefficient of the model: a parameter and one term of its shape.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Coef {
    pub param: ParamId,
    pub term: Term,
}

impl Coef {
    /// The coefficient's name in tables: `dx1`, `ez1.sin2`, `dz3.d2`.
    pub fn name(&self) -> String {
        match self.term {
            Term::Const => self.param.id().to_string(),
            Term::Sin(k) => format!("{}.sin{k}", self.param.id()),
            Term::Cos(k) => format!("{}.cos{k}", self.param.id()),
            Term::Pow(k) => format!("{}.d{k}", self.param.id()),
        }
    }
    /// Reads a name written by [`Coef::name`].
    pub fn parse(name: &str) -> Option<Coef> {
        let (p, term) = match name.split_once('.') {
            None => (name, Term::Const),
            Some((p, t)) => {
                let num = |prefix: &str| -> Option<u32> {
                    t.strip_prefix(prefix)?.parse().ok().filter(|&k| k >= 1)
                };
                let term = if let Some(k) = num("sin") {
                    Term::Sin(k)
                } else if let Some(k) = num("cos") {
                    Term::Cos(k)
                } else {
                    Term::Pow(num("d")?)
                };
                (p, term)
            }
        };
        let param = ParamId::parse(p)?;
        match (param.joint(), term) {
            // Constant-only parameters (every model's but the DH chain's).
            (None, Term::Const) | (Some(Joint::Theta | Joint::Phi), _) => {}
            (None, _) | (Some(Joint::D), Term::Sin(_) | Term::Cos(_)) => return None,
            (Some(Joint::D), _) => {}
        }
        Some(Coef { param, term })
    }

    /// The paper-style symbol: `δx1`, `εz1·sin2θ`, `δz3·d²`.
    pub fn symbol(&self) -> String {
        let q = self.param.joint().map_or("", Joint::symbol);
        match self.term {
            Term::Const => self.param.symbol().to_string(),
            Term::Sin(k) => format!("{}·sin{}{q}", self.param.symbol(), harmonic(k)),
            Term::Cos(k) => format!("{}·cos{}{q}", self.param.symbol(), harmonic(k)),
            Term::Pow(k) => format!("{}·d{}", self.param.symbol(), superscript(k)),
        }
    }
    pub fn unit(&self) -> String {
        match self.term {
            Term::Pow(k) => format!("{}/m{}", self.param.unit(), superscript(k)),
            _ => self.param.unit().to_string(),
        }
    }
    /// The term's value at the joints (the basis function).
    pub(crate) fn basis(&self, q: Joints) -> f64 {
        // The joint is looked up for harmonics only: a constant, the
        // common case, needs nothing of the parameter's table.
        let angle = || match self.param.joint() {
            Some(Joint::Theta) => q.theta,
            Some(Joint::Phi) => q.phi,
            Some(Joint::D) | None => 0.0,
        };
        match self.term {
            Term::Const => 1.0,
            Term::Sin(k) => (k as f64 * angle()).sin(),
            Term::Cos(k) => (k as f64 * angle()).cos(),
            Term::Pow(k) => (q.d * 1e-3).powi(k as i32),
        }
    }
}

fn harmonic(k: u32) -> String {
    if k == 1 { String::new() } else { k.to_string() }
}

fn superscript(k: u32) -> String {
    const SUP: [char; 10] = ['⁰', '¹', '²', '³', '⁴', '⁵', '⁶', '⁷', '⁸', '⁹'];
    if k == 1 {
        return String::new();
    }
    k.to_string()
        .chars()
        .map(|c| SUP[c.to_digit(10).unwrap_or(0) as usize])
        .collect()
}

/// A tracker model and the shape of every parameter: which coefficients a
/// parameter set has.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct ErrorModel {
    tracker: TrackerModel,
    /// By the parameter's place in its model's table.
    shapes: Vec<Shape>,
}

impl Default for ErrorModel {
    fn default() -> ErrorModel {
        ErrorModel::of(TrackerModel::default())
    }
}

impl ErrorModel {
    /// The paper's model: 18 constants.
    pub fn constant() -> ErrorModel {
        ErrorModel::default()
    }

    /// A tracker model's parameters, every one a constant.
    pub fn of(tracker: TrackerModel) -> ErrorModel {
        ErrorModel {
            tracker,
            shapes: vec![Shape::Constant; tracker.params().len()],
        }
    }

    pub fn tracker(&self) -> TrackerModel {
        self.tracker
    }

    /// Sets one parameter's shape; it must be a parameter of this model,
    /// and Fourier needs a rotary joint (a joint angle).
    pub fn with_shape(mut self, p: ParamId, shape: Shape) -> Result<ErrorModel, String> {
        if p.tracker() != self.tracker {
            return Err(format!(
                "`{}` is a parameter of the {} model, not of the {} model",
                p.id(),
                p.tracker(),
                self.tracker
            ));
        }
        match (p.joint(), shape) {
            (_, Shape::Constant)
            | (Some(Joint::Theta | Joint::Phi), _)
            | (Some(Joint::D), Shape::Poly(_)) => {}
            (Some(Joint::D), _) => {
                return Err(format!(
                    "{} belongs to the beam joint, which has no angle: use \"poly:N\" (Eq. 10) instead of \"{shape}\"",
                    p.id()
                ));
            }
            (None, _) => {
                return Err(format!(
                    "`{}` is a misalignment of the {} model, a constant: it takes no shape",
                    p.id(),
                    p.tracker()
                ));
            }
        }
        self.shapes[p.local()] = shape;
        Ok(self)
    }

    /// A parameter's shape; a constant for another model's parameter.
    pub fn shape(&self, p: ParamId) -> Shape {
        if p.tracker() == self.tracker {
            self.shapes[p.local()]
        } else {
            Shape::Constant
        }
    }

    /// All coefficients, parameter by parameter, in a fixed order.
    pub fn coefs(&self) -> Vec<Coef> {
        let mut out = Vec::new();
        for p in ParamId::of(self.tracker) {
            out.push(Coef {
                param: p,
                term: Term::Const,
            });
            match self.shapes[p.local()] {
                Shape::Constant => {}
                Shape::Fourier(n) => {
                    for k in 1..=n {
                        out.push(Coef {
                            param: p,
                            term: Term::Sin(k),
                        });
                        out.push(Coef {
                            param: p,
                            term: Term::Cos(k),
                        });
                    }
                }
                Shape::Poly(n) => {
                    for k in 1..=n {
                        out.push(Coef {
                            param: p,
                            term: Term::Pow(k),
                        });
                    }
                }
            }
        }
        out
    }
}

/// A model with a value for every coefficient (display units).
#[derive(Clone, Debug, PartialEq)]
pub struct ErrorParams {
    tracker: TrackerModel,
    coefs: Vec<Coef>,
    values: Vec<f64>,
}

impl ErrorParams {
    pub fn zero(model: &ErrorModel) -> ErrorParams {
        let coefs = model.coefs();
        let values = vec![0.0; coefs.len()];
        ErrorParams {
            tracker: model.tracker,
            coefs,
            values,
        }
    }

    /// Table 2: every parameter 10 µm or 10 µrad (NOTES item 8).
    pub fn table2() -> ErrorParams {
        let mut p = ErrorParams::zero(&ErrorModel::constant());
        p.values.iter_mut().for_each(|v| *v = 10.0);
        p
    }

    /// Builds a parameter set from coefficients and values; every coefficient
    /// must belong to a shape that a model can hold, and all to one tracker
    /// model ([`ErrorParams::tracker_of`] checks coefficients from input).
    pub fn from_parts(coefs: Vec<Coef>, values: Vec<f64>) -> ErrorParams {
        assert_eq!(coefs.len(), values.len());
        let tracker = ErrorParams::tracker_of(&coefs).expect("coefficients of one tracker model");
        ErrorParams {
            tracker,
            coefs,
            values,
        }
    }

    /// The one tracker model these coefficients belong to (the paper's when
    /// there are none), or the first two that disagree.
    pub fn tracker_of(coefs: &[Coef]) -> Result<TrackerModel, (Coef, Coef)> {
        let Some(first) = coefs.first() else {
            return Ok(TrackerModel::default());
        };
        match coefs
            .iter()
            .find(|c| c.param.tracker() != first.param.tracker())
        {
            Some(other) => Err((*first, *other)),
            None => Ok(first.param.tracker()),
        }
    }

    /// The tracker model these parameters describe.
    pub fn tracker(&self) -> TrackerModel {
        self.tracker
    }

    pub fn coefs(&self) -> &[Coef] {
        &self.coefs
    }
    pub fn values(&self) -> &[f64] {
        &self.values
    }
    pub fn values_mut(&mut self) -> &mut [f64] {
        &mut self.values
    }

    /// These values with `delta[k]` added to coefficient `indices[k]`: how
    /// a fit in the coordinates of some coefficients moves the whole set.
    pub fn plus(&self, indices: &[usize], delta: &nalgebra::DVector<f64>) -> ErrorParams {
        let mut p = self.clone();
        for (k, &i) in indices.iter().enumerate() {
            p.values[i] += delta[k];
        }
        p
    }

    pub fn get(&self, c: &Coef) -> Option<f64> {
        self.coefs
            .iter()
            .position(|x| x == c)
            .map(|i| self.values[i])
    }

    /// The 18 parameters of a DH parameter set at a joint position, in
    /// internal units (mm, rad).
    pub fn base_at(&self, q: Joints) -> [f64; N_PARAMS] {
        debug_assert_eq!(self.tracker, TrackerModel::default());
        let mut base = [0.0; N_PARAMS];
        for (c, v) in self.coefs.iter().zip(&self.values) {
            base[c.param.local()] += v * c.basis(q) * c.param.scale();
        }
        base
    }

    /// Eq. (8) (or another model's forward model): the point a tracker with
    /// these errors reaches at these joints.
    pub fn point(&self, q: Joints) -> Vector3<f64> {
        self.evaluator().point(q, &Links::new(q))
    }

    /// The corrected coordinates of a reading: Eq. (8) at the reading's joints.
    pub fn correct(&self, r: Reading) -> Vector3<f64> {
        self.point(r.joints())
    }

    /// An evaluator for many readings with the same parameters: its
    /// model's forward model ([`crate::trackers::Model::evaluate`]).
    pub fn evaluator(&self) -> Evaluator<'_> {
        Evaluator {
            model: self.tracker.plugin().evaluate(self),
        }
    }
    /// Section 5.1, measuring: the reading a tracker with these errors takes
    /// when its beam reaches `target` ([`Evaluator::reading_of`]).
    pub fn reading_of(&self, target: &Vector3<f64>, face: Face) -> Result<Reading, InverseError> {
        self.evaluator().reading_of(target, face)
    }
}

/// Evaluates one parameter set at many joint positions, building what does
/// not depend on the joints once (its model's plug-in decides what).
pub struct Evaluator<'a> {
    model: Box<dyn Evaluate + 'a>,
}

impl Evaluator<'_> {
    /// Section 5.1, measuring: the reading a tracker with these errors takes
    /// when its beam reaches `target` — the joint values that solve Eq. (8)
    /// (or another model's forward model) exactly ([`kinematics::invert`]).
    pub fn reading_of(&self, target: &Vector3<f64>, face: Face) -> Result<Reading, InverseError> {
        self.reading_and_links_of(target, face).map(|(r, _)| r)
    }

    /// [`Self::reading_of`] with the reading's link rotations: the inverse's
    /// last evaluation is at the reading it returns, so a caller that goes
    /// on to evaluate there (the bundle's design network) need not build
    /// them again (issue 34).
    pub fn reading_and_links_of(
        &self,
        target: &Vector3<f64>,
        face: Face,
    ) -> Result<(Reading, Links), InverseError> {
        let last = Cell::new(None);
        let r = kinematics::invert(target, face, |r| {
            let q = r.joints();
            let links = Links::new(q);
            last.set(Some(links));
            self.point(q, &links)
        })?;
        // `invert` returns only after evaluating its answer.
        let links = last.get().unwrap_or_else(|| Links::new(r.joints()));
        Ok((r, links))
    }

    /// Eq. (8) at joints `q` whose link rotations are `links`.
    pub fn point(&self, q: Joints, links: &Links) -> Vector3<f64> {
        self.model.point(q, links)
    }

    /// The point and `∂P/∂value` for every coefficient (mm per display unit).
    pub fn point_with_jacobian(
        &self,
        q: Joints,
        links: &Links,
        jac: &mut Vec<Vector3<f64>>,
    ) -> Vector3<f64> {
        jac.clear();
        self.model.point_with_jacobian(q, links, jac)
    }
}

/// Eq. (6): `R_x(εx)·R_y(εy)·R_z(εz)`.
pub fn rotation_xyz(ex: f64, ey: f64, ez: f64) -> Matrix3<f64> {
    Rotation::new(ex, ey, ez).matrix()
}

/// The factors of Eq. (6), kept apart for its derivatives.
struct Rotation {
    rx: Matrix3<f64>,
    ry: Matrix3<f64>,
    rz: Matrix3<f64>,
}

impl Rotation {
    fn new(ex: f64, ey: f64, ez: f64) -> Rotation {
        let (sx, cx) = ex.sin_cos();
        let (sy, cy) = ey.sin_cos();
        let (sz, cz) = ez.sin_cos();
        Rotation {
            rx: Matrix3::new(1.0, 0.0, 0.0, 0.0, cx, -sx, 0.0, sx, cx),
            ry: Matrix3::new(cy, 0.0, sy, 0.0, 1.0, 0.0, -sy, 0.0, cy),
            rz: Matrix3::new(cz, -sz, 0.0, sz, cz, 0.0, 0.0, 0.0, 1.0),
        }
    }

    fn matrix(&self) -> Matrix3<f64> {
        self.rx * self.ry * self.rz
    }

    /// `∂R/∂εx, ∂R/∂εy, ∂R/∂εz`: `R_x' = R_x·[x̂]×` and likewise.
    fn derivatives(&self) -> [Matrix3<f64>; 3] {
        let k = |a: usize| {
            let mut e = Vector3::zeros();
            e[a] = 1.0;
            e.cross_matrix()
        };
        let ryz = self.ry * self.rz;
        [
            self.rx * k(0) * ryz,
            self.rx * self.ry * k(1) * self.rz,
            self.rx * ryz * k(2),
        ]
    }
}

/// The nominal link rotations at one joint position, computed once per
/// reading and reused while the error parameters change.
#[derive(Clone, Copy, Debug)]
pub struct Links {
    r1: Matrix3<f64>,
    r2: Matrix3<f64>,
    d: f64,
}

impl Links {
    pub fn new(q: Joints) -> Links {
        Links {
            r1: link1_rotation(q.theta),
            r2: link2_rotation(q.phi),
            d: q.d,
        }
    }
}

/// The error transforms of Eq. (6)–(7) at one joint position, with the
/// derivatives of the rotations. A model whose rotary parameters are
/// constants has the same frames at every reading, so they are built once.
#[derive(Clone, Debug)]
pub struct ErrorFrames {
    b: [f64; N_PARAMS],
    re1: Matrix3<f64>,
    re2: Matrix3<f64>,
    de1: [Matrix3<f64>; 3],
    de2: [Matrix3<f64>; 3],
}

impl ErrorFrames {
    /// `b`: the 18 parameters in mm and rad.
    pub fn new(b: &[f64; N_PARAMS]) -> ErrorFrames {
        let e1 = Rotation::new(b[3], b[4], b[5]);
        let e2 = Rotation::new(b[9], b[10], b[11]);
        ErrorFrames {
            b: *b,
            re1: e1.matrix(),
            re2: e2.matrix(),
            de1: e1.derivatives(),
            de2: e2.derivatives(),
        }
    }

    /// Eq. (7) applied to (0, 0, d): its rotation about z (εz3) moves nothing.
    #[inline]
    fn beam_point(&self, d: f64) -> Vector3<f64> {
        let b = &self.b;
        Vector3::new(b[16] * d + b[12], -b[15] * d + b[13], d + b[14])
    }

    /// Eq. (8) with the placement of the module doc.
    pub fn forward(&self, l: &Links) -> Vector3<f64> {
        let b = &self.b;
        let v = self.re2 * (l.r2 * self.beam_point(l.d)) + Vector3::new(b[6], b[7], b[8]);
        self.re1 * (l.r1 * v) + Vector3::new(b[0], b[1], b[2])
    }

    /// [`Self::forward`] and its derivative with respect to each of the 18
    /// parameters (mm per mm or per rad).
    pub fn forward_with_jacobian(&self, l: &Links) -> (Vector3<f64>, [Vector3<f64>; N_PARAMS]) {
        forward_with_jacobian(self, l)
    }
}

/// [`ErrorFrames::forward_with_jacobian`], once per reading at every
/// linearisation of a bundle adjustment. Compiled also for AVX2 and
/// AVX-512, chosen at run time (its 3 × 3 products are what they widen):
/// the same operations in the same order, so the same numbers on every CPU
/// (Rust never fuses a multiply and an add; issue 34).
#[multiversion(targets("x86_64+avx512f+avx512vl", "x86_64+avx2+fma"))]
fn forward_with_jacobian(f: &ErrorFrames, l: &Links) -> (Vector3<f64>, [Vector3<f64>; N_PARAMS]) {
    let b = &f.b;
    let u = l.r2 * f.beam_point(l.d);
    let v = f.re2 * u + Vector3::new(b[6], b[7], b[8]);
    let w = l.r1 * v;
    let p = f.re1 * w + Vector3::new(b[0], b[1], b[2]);

    let m1 = f.re1 * l.r1;
    let m3 = m1 * f.re2 * l.r2;
    let mut j = [Vector3::zeros(); N_PARAMS];
    for a in 0..3 {
        j[a][a] = 1.0;
        j[3 + a] = f.de1[a] * w;
        j[6 + a] = m1.column(a).into();
        j[9 + a] = m1 * (f.de2[a] * u);
        j[12 + a] = m3.column(a).into();
    }
    j[15] = -l.d * m3.column(1);
    j[16] = l.d * m3.column(0);
    // j[17] (εz3) stays zero: a rotation about the beam moves nothing.
    (p, j)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::nominal_reading;

    fn sphere_points() -> Vec<Vector3<f64>> {
        // The paper's spherical mesh (NOTES item 7).
        let mut pts = Vec::new();
        for h in 0..12 {
            for v in 0..8 {
                for r in 0..5 {
                    let h = (33.0 * h as f64).to_radians();
                    let v = (77.0 - 20.0 * v as f64).to_radians();
                    let r = 1000.0 + 3500.0 * r as f64;
                    pts.push(Vector3::new(
                        r * v.cos() * h.cos(),
                        r * v.cos() * h.sin(),
                        r * v.sin(),
                    ));
                }
            }
        }
        pts
    }

    #[test]
    fn eq6_matches_its_printed_matrix() {
        let (ex, ey, ez) = (0.3, -0.2, 0.5);
        let r = rotation_xyz(ex, ey, ez);
        // Eq. (6), first and last rows as printed (with ε_Z for θ_Z).
        assert!((r[(0, 0)] - ey.cos() * ez.cos()).abs() < 1e-15);
        assert!((r[(0, 2)] - ey.sin()).abs() < 1e-15);
        let r20 = ex.sin() * ez.sin() - ex.cos() * ey.sin() * ez.cos();
        assert!((r[(2, 0)] - r20).abs() < 1e-15);
        assert!((r[(2, 2)] - ex.cos() * ey.cos()).abs() < 1e-15);
        assert!((r.determinant() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn zero_errors_reproduce_the_nominal_chain() {
        let e = ErrorParams::zero(&ErrorModel::constant());
        for p in sphere_points() {
            let r = nominal_reading(&p, Face::Front);
            assert!((e.correct(r) - p).norm() < 1e-9);
        }
    }

    /// Issue 34: `forward_with_jacobian` runs the code compiled for this
    /// CPU's widest vectors; `forward`, the same products in the same
    /// order, the baseline's. The point must be the same to the last bit.
    #[test]
    fn the_point_with_the_jacobian_is_forward_s_bit_for_bit() {
        let b: [f64; N_PARAMS] = std::array::from_fn(|i| 1e-3 * (i as f64 * 0.7).sin());
        let frames = ErrorFrames::new(&b);
        for (theta, phi, d) in [
            (0.7, -0.4, 4321.0),
            (-2.9, 1.1, 812.5),
            (3.1, 0.05, 17_004.0),
        ] {
            let l = Links::new(Joints { theta, phi, d });
            let (p, _) = frames.forward_with_jacobian(&l);
            let bits = |v: Vector3<f64>| v.map(f64::to_bits);
            assert_eq!(bits(p), bits(frames.forward(&l)));
        }
    }

    #[test]
    fn analytic_jacobian_matches_finite_differences() {
        let mut b = [0.0; N_PARAMS];
        for (i, v) in b.iter_mut().enumerate() {
            *v = if ParamId::from_index(i).is_angular() {
                3e-3
            } else {
                0.2
            } * (i as f64 - 8.0);
        }
        let q = Joints {
            theta: 0.7,
            phi: -0.4,
            d: 4321.0,
        };
        let l = Links::new(q);
        let (_, j) = ErrorFrames::new(&b).forward_with_jacobian(&l);
        for i in 0..N_PARAMS {
            let h = 1e-7;
            let mut bp = b;
            bp[i] += h;
            let mut bm = b;
            bm[i] -= h;
            let fd =
                (ErrorFrames::new(&bp).forward(&l) - ErrorFrames::new(&bm).forward(&l)) / (2.0 * h);
            assert!(
                (fd - j[i]).norm() < 1e-5 * (1.0 + fd.norm()),
                "{}: {fd} vs {}",
                ParamId::from_index(i),
                j[i]
            );
        }
    }

    #[test]
    fn inverse_round_trip_holds_to_1e9_mm_in_both_faces() {
        let mut e = ErrorParams::table2();
        e.values_mut().iter_mut().for_each(|v| *v *= 30.0);
        for p in sphere_points() {
            for face in [Face::Front, Face::Back] {
                let r = e.reading_of(&p, face).unwrap();
                assert_eq!(r.face(), face);
                assert!((e.correct(r) - p).norm() < 1e-9);
            }
        }
    }

    #[test]
    fn fourier_and_polynomial_terms_follow_their_joint() {
        let model = ErrorModel::constant()
            .with_shape(ParamId::parse("ez1").unwrap(), Shape::Fourier(2))
            .unwrap()
            .with_shape(ParamId::parse("dz3").unwrap(), Shape::Poly(2))
            .unwrap();
        let coefs = model.coefs();
        assert_eq!(coefs.len(), 18 + 4 + 2);
        let names: Vec<String> = coefs.iter().map(Coef::name).collect();
        for (c, n) in coefs.iter().zip(&names) {
            assert_eq!(Coef::parse(n), Some(*c));
        }
        assert_eq!(Coef::parse("dz3.sin1"), None);
        assert!(names.contains(&"ez1.sin2".to_string()));
        assert!(names.contains(&"dz3.d2".to_string()));
        let mut e = ErrorParams::zero(&model);
        let i = names.iter().position(|n| n == "dz3.d2").unwrap();
        e.values_mut()[i] = 5.0; // 5 µm/m²
        let q = Joints {
            theta: 0.1,
            phi: 0.2,
            d: 3000.0,
        };
        assert!((e.base_at(q)[14] - 5.0 * 9.0 * 1e-3).abs() < 1e-15);
        assert!(
            ErrorModel::constant()
                .with_shape(ParamId::parse("dz3").unwrap(), Shape::Fourier(1))
                .is_err()
        );
    }
}
