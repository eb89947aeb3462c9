//! `b89_tests`: the ASME B89.4.19 two-face and length tests simulated
//! ([`crate::b89`]) — what a tracker with given errors shows in each, and
//! which test sees which error parameter.
//!
//! ```toml
//! [stages.b89]
//! kind = "b89_tests"
//! model = "api-tracker3"            # or "mirror-tracker" (`mirror`: its ten misalignments)
//! parameters = "physical"           # the sensitivity's parameters: "physical" (the 16
//!                                   # misalignments of `physical`) or "dh" (the paper's
//!                                   # 18 DH constants and the encoder harmonics)
//! length_m = 2.3                    # the reference length
//! length_distances_m = [1, 6]       # bar centre (near end when ranging), horizontal
//! length_heights_m = [0]            # bar centre above the tracker
//! two_face_distances_m = [1, 3, 6]
//! two_face_heights_m = [-1.5, 0, 1.5]   # above the tracker
//! azimuths_deg = [0, 90, 180, 270]
//! misalignments = { beam_offset_el = 10, transit_tilt = 5 }   # optional, µm / µrad,
//!                                   # by the model's ids
//! inputs = { params = "truth.params" }  # optional: a tracker's parameters of `model`
//!                                       # (`inject`, `identify`, `calibrate`: DH coefficients
//!                                       # or mirror misalignments), added to the above
//! ```
//!
//! Outputs:
//! * `tests` — `test`, `kind` (`two-face`, `length`), `orientation`,
//!   `distance_m`, `height_m`, `az_deg`, `err_um`: each test's error with the
//!   given errors, simulated exactly (the two-face separation; measured minus
//!   true length), zero (to rounding) without errors.
//! * `sensitivity` — `test`, `kind`, `parameter`, `unit`, `sens_um_per_unit`:
//!   each test's error per µm or µrad of each parameter (linear, at zero,
//!   through the model's Jacobian: analytic for the head-laser chain and,
//!   by the reflection's chain rule, for the mirror tracker).
//! * `visibility` — per parameter: `two_face_max_um`, `length_max_um` (the
//!   largest |sensitivity| over each kind of test) and `seen_by`.
//! * `b89-sensitivity.svg` — the sensitivity matrix, parameters by tests.

use super::{Context, Invalid, Slot, StageInputs, StageKind, StageOutput};
use crate::b89::{self, Direction, Positions, Test};
use crate::error_model::{Coef, ErrorModel, ErrorParams};
use crate::plots;
use crate::schema;
use crate::table::TableBuilder;
use crate::trackers::TrackerModel;
use anyhow::{Result, anyhow, bail};
use polars::prelude::DataFrame;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Which parameters the sensitivity is given for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Parameters {
    /// The misalignments of [`crate::physical`].
    #[default]
    Physical,
    /// Every coefficient of [`crate::physical::dh_model`].
    Dh,
}

#[derive(Clone, Debug, Serialize, Deserialize, documented::DocumentedFields)]
#[serde(deny_unknown_fields)]
pub struct B89TestsStage {
    /// The tracker model: `api-tracker3` or `mirror-tracker`.
    #[serde(default)]
    pub model: TrackerModel,
    /// The sensitivity's parameters: `physical` (16 misalignments) or `dh` (the
    /// 18 DH constants and encoder harmonics).
    #[serde(default)]
    pub parameters: Parameters,
    /// The reference length, m.
    #[serde(default = "default_length")]
    pub length_m: f64,
    /// Bar centre distances of the length tests, m (horizontal).
    #[serde(default = "default_length_distances")]
    pub length_distances_m: Vec<f64>,
    /// Bar centre heights above the tracker, m.
    #[serde(default = "default_length_heights")]
    pub length_heights_m: Vec<f64>,
    /// Distances of the two-face tests, m.
    #[serde(default = "default_two_face_distances")]
    pub two_face_distances_m: Vec<f64>,
    /// Heights of the two-face tests above the tracker, m.
    #[serde(default = "default_two_face_heights")]
    pub two_face_heights_m: Vec<f64>,
    /// Azimuths every test is repeated at, degrees.
    #[serde(default = "default_azimuths")]
    pub azimuths_deg: Vec<f64>,
    /// Misalignments by the model's ids, µm / µrad, added to any `params`
    /// input.
    #[serde(default)]
    pub misalignments: BTreeMap<String, f64>,
}

fn default_length() -> f64 {
    Positions::default().length_m
}
fn default_length_distances() -> Vec<f64> {
    Positions::default().length_distances_m
}
fn default_length_heights() -> Vec<f64> {
    Positions::default().length_heights_m
}
fn default_two_face_distances() -> Vec<f64> {
    Positions::default().two_face_distances_m
}
fn default_two_face_heights() -> Vec<f64> {
    Positions::default().two_face_heights_m
}
fn default_azimuths() -> Vec<f64> {
    Positions::default().azimuths_deg
}

/// A tracker's reach, m: farther positions are a typing mistake.
const MAX_DISTANCE_M: f64 = 200.0;
/// At most this many tests (36 two-face and 40 length tests by default).
const MAX_TESTS: usize = 20_000;

impl B89TestsStage {
    fn positions(&self) -> Positions {
        Positions {
            length_m: self.length_m,
            length_distances_m: self.length_distances_m.clone(),
            length_heights_m: self.length_heights_m.clone(),
            two_face_distances_m: self.two_face_distances_m.clone(),
            two_face_heights_m: self.two_face_heights_m.clone(),
            azimuths_deg: self.azimuths_deg.clone(),
        }
    }

    /// The parameters' rows and directions in the coefficients of `zero`.
    fn directions(&self, zero: &ErrorParams) -> Vec<(Row, Direction)> {
        let at = |c: Coef| {
            zero.coefs()
                .iter()
                .position(|x| *x == c)
                .expect("the model holds every coefficient named")
        };
        // `parameters = "dh"` is refused at load for a model without
        // coefficient rows.
        if self.parameters == Parameters::Dh && self.model.plugin().coefficient_rows() {
            zero.coefs()
                .iter()
                .enumerate()
                .map(|(i, c)| (Row::new(&c.name(), &c.unit(), &c.symbol()), (i, 1.0)))
                .collect()
        } else {
            self.model
                .plugin()
                .misalignments()
                .iter()
                .map(|m| {
                    let row = Row::new(m.id, m.unit, m.meaning);
                    (row, (at(m.coef), m.sign))
                })
                .collect()
        }
    }

    /// Each test's error and sensitivities, with the parameters' rows.
    fn evaluate(&self, tests: &[Test], inputs: &StageInputs) -> Result<Evaluated> {
        let errors = self.errors(inputs)?;
        let err_um = b89::simulate(tests, &errors).map_err(|e| anyhow!("with these errors {e}"))?;
        let zero = ErrorParams::zero(&self.model.b89_model());
        let (rows, dirs): (Vec<Row>, Vec<Direction>) = self.directions(&zero).into_iter().unzip();
        let sens = b89::sensitivity(tests, &zero, &dirs);
        Ok(Evaluated { rows, err_um, sens })
    }

    /// The tracker's errors: the `params` input's coefficients plus the
    /// settings' misalignments (the head-laser's physical ones mapped onto
    /// its DH coefficients, the mirror tracker's its own parameters).
    fn errors(&self, inputs: &StageInputs) -> Result<ErrorParams> {
        let mut values: BTreeMap<Coef, f64> = BTreeMap::new();
        if let Some(t) = inputs.optional("params") {
            let p = schema::params_from(&t)?;
            if p.tracker() != self.model {
                bail!(
                    "`{}` holds parameters of the {} model: set `model = \"{}\"`",
                    t.name,
                    p.tracker(),
                    p.tracker()
                );
            }
            for (c, v) in p.coefs().iter().zip(p.values()) {
                *values.entry(*c).or_default() += v;
            }
        }
        let unknown =
            |id: &str| anyhow!("`{id}` is not a misalignment of the {} model", self.model);
        let given: Vec<(&str, f64)> = self
            .misalignments
            .iter()
            .map(|(id, v)| (id.as_str(), *v))
            .collect();
        let mapped = self
            .model
            .plugin()
            .misaligned(&given)
            .map_err(|id| unknown(&id))?;
        for (c, v) in mapped {
            *values.entry(c).or_default() += v;
        }
        if values.is_empty() {
            // No error at all: a perfect tracker of this model.
            return Ok(ErrorParams::zero(&ErrorModel::of(self.model)));
        }
        let (coefs, vals) = values.into_iter().unzip();
        Ok(ErrorParams::from_parts(coefs, vals))
    }
}

impl StageKind for B89TestsStage {
    const KIND: &'static str = "b89_tests";
    const SUMMARY: &'static str = "the ASME B89.4.19 two-face and length tests simulated: each test's error and its sensitivity to each parameter";
    const INPUTS: &'static [Slot] = &[Slot::table(
        "params",
        false,
        "a tracker's error parameters (`inject`, `identify`, `calibrate`)",
    )];
    const OUTPUTS: &'static [&'static str] = &["tests", "sensitivity", "visibility"];

    fn columns(table: &str) -> Option<&'static [&'static str]> {
        match table {
            "tests" => Some(&[
                "test",
                "kind",
                "orientation",
                "distance_m",
                "height_m",
                "az_deg",
                "err_um",
            ]),
            "sensitivity" => Some(&["test", "kind", "parameter", "unit", "sens_um_per_unit"]),
            "visibility" => Some(&[
                "parameter",
                "unit",
                "meaning",
                "two_face_max_um",
                "length_max_um",
                "seen_by",
            ]),
            _ => None,
        }
    }

    fn validate(&self) -> Vec<Invalid> {
        let mut out = Vec::new();
        if !(self.length_m.is_finite() && self.length_m > 0.0 && self.length_m <= MAX_DISTANCE_M) {
            out.push(Invalid::new(
                "length_m",
                format!(
                    "`length_m` must lie in (0, {MAX_DISTANCE_M}], got {}",
                    self.length_m
                ),
            ));
        }
        let lists: [(&str, &[f64], f64, f64); 5] = [
            (
                "length_distances_m",
                &self.length_distances_m,
                0.0,
                MAX_DISTANCE_M,
            ),
            (
                "length_heights_m",
                &self.length_heights_m,
                -MAX_DISTANCE_M,
                MAX_DISTANCE_M,
            ),
            (
                "two_face_distances_m",
                &self.two_face_distances_m,
                0.0,
                MAX_DISTANCE_M,
            ),
            (
                "two_face_heights_m",
                &self.two_face_heights_m,
                -MAX_DISTANCE_M,
                MAX_DISTANCE_M,
            ),
            ("azimuths_deg", &self.azimuths_deg, -360.0, 360.0),
        ];
        for (name, values, lo, hi) in lists {
            for (i, &v) in values.iter().enumerate() {
                // Distances must stay off the standing axis: above zero.
                let (above, open) = if lo == 0.0 {
                    (v > lo, "(")
                } else {
                    (v >= lo, "[")
                };
                if !(v.is_finite() && above && v <= hi) {
                    out.push(Invalid::new(
                        format!("{name}.{i}"),
                        format!("`{name}` values must lie in {open}{lo}, {hi}], got {v}"),
                    ));
                } else if values[..i].contains(&v) {
                    // Each test is named by its position: no two alike.
                    out.push(Invalid::new(
                        format!("{name}.{i}"),
                        format!("`{name}` holds {v} twice"),
                    ));
                }
            }
        }
        let n_az = self.azimuths_deg.len();
        // Saturating: lists long enough to overflow are refused all the same.
        let n_tests = [
            self.two_face_distances_m.len(),
            self.two_face_heights_m.len(),
            n_az,
        ]
        .iter()
        .fold(1usize, |a, &b| a.saturating_mul(b))
        .saturating_add(
            [
                b89::Orientation::ALL.len(),
                self.length_distances_m.len(),
                self.length_heights_m.len(),
                n_az,
            ]
            .iter()
            .fold(1usize, |a, &b| a.saturating_mul(b)),
        );
        if n_tests == 0 {
            // Name the first empty list that leaves no test.
            let empty = [
                ("azimuths_deg", n_az),
                ("two_face_distances_m", self.two_face_distances_m.len()),
                ("two_face_heights_m", self.two_face_heights_m.len()),
                ("length_distances_m", self.length_distances_m.len()),
                ("length_heights_m", self.length_heights_m.len()),
            ]
            .into_iter()
            .find(|(_, n)| *n == 0)
            .map_or("azimuths_deg", |(name, _)| name);
            out.push(Invalid::new(
                empty,
                "no test: give at least one azimuth and one distance",
            ));
        } else if n_tests > MAX_TESTS {
            out.push(Invalid::new(
                "azimuths_deg",
                format!("{n_tests} tests: at most {MAX_TESTS}"),
            ));
        }
        let known: Vec<&str> = self
            .model
            .plugin()
            .misalignments()
            .iter()
            .map(|m| m.id)
            .collect();
        for (id, v) in &self.misalignments {
            let field = format!("misalignments.{id}");
            if !known.contains(&id.as_str()) {
                out.push(Invalid::new(
                    field,
                    format!(
                        "`{id}` is not a misalignment of the {} model: one of {}",
                        self.model.id(),
                        known.join(", ")
                    ),
                ));
            } else if !v.is_finite() {
                out.push(Invalid::new(
                    field,
                    format!("`{id}` must be finite, got {v}"),
                ));
            }
        }
        if !self.model.plugin().coefficient_rows() && self.parameters == Parameters::Dh {
            out.push(Invalid::new(
                "parameters",
                format!(
                    "the {} model has no DH parameters: use `parameters = \"physical\"`",
                    self.model
                ),
            ));
        }
        out
    }

    fn run(&self, _: &Context, inputs: &StageInputs) -> Result<StageOutput> {
        let tests = b89::tests(&self.positions());
        let Evaluated { rows, err_um, sens } = self.evaluate(&tests, inputs)?;
        let labels: Vec<String> = rows
            .iter()
            .map(|r| format!("{} ({})", r.name, r.unit))
            .collect();
        // Rows of the figure: parameters; columns: tests.
        let by_param: Vec<Vec<f64>> = (0..rows.len())
            .map(|k| sens.iter().map(|row| row[k]).collect())
            .collect();
        let svg = plots::sensitivity_matrix(
            &format!(
                "B89.4.19 tests, {}: each test's error per unit of each parameter",
                self.model.id()
            ),
            &labels,
            &column_groups(&tests),
            &tests
                .iter()
                .map(|t| format!("{} m, {:+} m, {}°", t.distance_m, t.height_m, t.az_deg))
                .collect::<Vec<_>>(),
            &by_param,
        )?;
        Ok(StageOutput::default()
            .table("tests", tests_table(&tests, &err_um)?)
            .table("sensitivity", sensitivity_table(&tests, &rows, &sens)?)
            .table("visibility", visibility_table(&tests, &rows, &sens)?)
            .file("b89-sensitivity.svg".into(), svg.into_bytes()))
    }
}

/// A parameter as the tables name it.
struct Row {
    name: String,
    unit: String,
    meaning: String,
}

impl Row {
    fn new(name: &str, unit: &str, meaning: &str) -> Row {
        Row {
            name: name.into(),
            unit: unit.into(),
            meaning: meaning.into(),
        }
    }
}

/// What [`B89TestsStage::evaluate`] finds: the parameters, each test's
/// error (µm) and `[test][parameter]` sensitivities.
struct Evaluated {
    rows: Vec<Row>,
    err_um: Vec<f64>,
    sens: Vec<Vec<f64>>,
}

fn visibility_table(tests: &[Test], rows: &[Row], sens: &[Vec<f64>]) -> Result<DataFrame> {
    let max_over = |k: usize, kind: &str| {
        tests
            .iter()
            .zip(sens)
            .filter(|(t, _)| t.kind() == kind)
            .map(|(_, row)| row[k].abs())
            .fold(0.0, f64::max)
    };
    let two_face: Vec<f64> = (0..rows.len()).map(|k| max_over(k, "two-face")).collect();
    let length: Vec<f64> = (0..rows.len()).map(|k| max_over(k, "length")).collect();
    let seen = |v: f64| v > 0.0;
    let seen_by: Vec<&str> = two_face
        .iter()
        .zip(&length)
        .map(|(&a, &b)| match (seen(a), seen(b)) {
            (true, true) => "both",
            (true, false) => "two-face only",
            (false, true) => "length only",
            (false, false) => "neither",
        })
        .collect();
    let names: Vec<&str> = rows.iter().map(|r| r.name.as_str()).collect();
    let units: Vec<&str> = rows.iter().map(|r| r.unit.as_str()).collect();
    let meaning: Vec<&str> = rows.iter().map(|r| r.meaning.as_str()).collect();
    TableBuilder::new()
        .str("parameter", &names)
        .str("unit", &units)
        .str("meaning", &meaning)
        .f64("two_face_max_um", two_face)
        .f64("length_max_um", length)
        .str("seen_by", &seen_by)
        .build()
}

fn tests_table(tests: &[Test], err_um: &[f64]) -> Result<DataFrame> {
    let ids: Vec<&str> = tests.iter().map(|t| t.id.as_str()).collect();
    let kinds: Vec<&str> = tests.iter().map(Test::kind).collect();
    let orient: Vec<&str> = tests
        .iter()
        .map(|t| t.orientation.map_or("", |o| o.name()))
        .collect();
    TableBuilder::new()
        .str("test", &ids)
        .str("kind", &kinds)
        .str("orientation", &orient)
        .f64("distance_m", tests.iter().map(|t| t.distance_m).collect())
        .f64("height_m", tests.iter().map(|t| t.height_m).collect())
        .f64("az_deg", tests.iter().map(|t| t.az_deg).collect())
        .f64("err_um", err_um.to_vec())
        .build()
}

fn sensitivity_table(tests: &[Test], rows: &[Row], sens: &[Vec<f64>]) -> Result<DataFrame> {
    let (mut test, mut kind, mut param, mut unit, mut value) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for (t, row) in tests.iter().zip(sens) {
        for (r, v) in rows.iter().zip(row) {
            test.push(t.id.as_str());
            kind.push(t.kind());
            param.push(r.name.as_str());
            unit.push(r.unit.as_str());
            value.push(*v);
        }
    }
    TableBuilder::new()
        .str("test", &test)
        .str("kind", &kind)
        .str("parameter", &param)
        .str("unit", &unit)
        .f64("sens_um_per_unit", value)
        .build()
}

/// The figure's column groups: runs of tests of one kind and orientation.
fn column_groups(tests: &[Test]) -> Vec<(String, usize)> {
    let mut out: Vec<(String, usize)> = Vec::new();
    for t in tests {
        let label = t.orientation.map_or("two-face", |o| o.name()).to_string();
        match out.last_mut() {
            Some((l, n)) if *l == label => *n += 1,
            _ => out.push((label, 1)),
        }
    }
    out
}
