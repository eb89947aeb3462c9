//! Layer 2: the resolved pipeline. Applies `--set` overrides to the settings
//! as written, fills in every default, validates each stage (errors point at
//! the field in the file, or at the `--set` that changed it), and checks the
//! graph: every input names an existing stage and table, every required slot
//! is connected, and there is no cycle. Other top-level tables are resolved
//! by their own modules against the resolved stages ([`snapshot_spec`]).

use super::cluster::settings::SlurmSettings;
use super::error::InputError;
use super::raw::{RawPipeline, RawStage};
use super::snapshot_spec::{self, Snapshot};
use super::sweep;
use crate::diagnostics::Problem;
use crate::diagnostics::Source;
use crate::stages::{Invalid, ResolvedConfig, StageConfig};
use anyhow::Result;
use std::collections::BTreeMap;
use std::ops::Range;
use std::path::PathBuf;
use std::sync::Arc;

use super::overrides::get_path;
pub use super::overrides::{Override, set_path, split_path};

pub use super::names::InputRef;

/// A stage with every setting resolved.
#[derive(Clone, Debug)]
pub struct Stage {
    pub name: String,
    pub config: ResolvedConfig,
    pub inputs: BTreeMap<String, InputRef>,
    /// Content hash of the file or folder the stage reads, checked when
    /// the pipeline loaded ([`crate::stages::StageFile`]).
    pub file_hash: Option<String>,
}

/// The files stages read, checked once per load: `(kind, path)` → content
/// hash, or why it cannot be used.
type FileChecks = BTreeMap<(&'static str, PathBuf), Result<String, String>>;

impl Stage {
    /// Every table the stage reads, as `(input name, producer table)`: a
    /// single-table slot is named after the slot, each table of a group
    /// slot `<slot>.<table>`.
    pub fn wired_tables(&self) -> Vec<(String, InputRef)> {
        let slots = self.config.inputs();
        let mut out = Vec::new();
        for (slot, r) in &self.inputs {
            match slots.iter().find(|s| s.name == slot) {
                Some(spec) if !spec.group.is_empty() => {
                    for t in spec.group {
                        out.push((
                            format!("{slot}.{t}"),
                            InputRef {
                                stage: r.stage.clone(),
                                table: t.to_string(),
                            },
                        ));
                    }
                }
                _ => out.push((slot.clone(), r.clone())),
            }
        }
        out
    }
}

/// The resolved pipeline: what the planner and the runner work from.
#[derive(Clone, Debug)]
pub struct Pipeline {
    pub name: String,
    pub description: String,
    pub source: Source,
    pub stages: Vec<Stage>,
    /// `[snapshot]`, when the file has one.
    pub snapshot: Option<Snapshot>,
    /// `[sweep]`, expanded, when the file has one.
    pub sweep: Option<Sweep>,
    /// `[executor.slurm]` with `--set executor.slurm.…` applied (the
    /// defaults when the file has none): used when run on Slurm.
    pub slurm: SlurmSettings,
}

/// A sweep, expanded into its points. A point's stages are resolved when
/// they are needed ([`Sweep::point`]), not held: 100 000 points of
/// resolved stages would take gigabytes, their values a few megabytes.
/// Every point was resolved once at load, so a mistake any point's values
/// make is reported then, and `point` cannot fail.
#[derive(Clone, Debug)]
pub struct Sweep {
    pub axes: Vec<sweep::Axis>,
    /// Each point's value of each axis.
    pub values: Vec<Vec<serde_json::Value>>,
    /// The tables gathered over the points.
    pub gather: Vec<InputRef>,
    /// The stages that run once, after the points, on the gathered tables
    /// (those that read `sweep.…`, and their descendants).
    pub after: Vec<String>,
    resolver: Arc<PointResolver>,
}

/// What resolving a point's stages needs: the file as written, the
/// command line's overrides and the files the stages read (hashed at load).
#[derive(Debug)]
struct PointResolver {
    source: Source,
    stages: Vec<RawStage>,
    overrides: Vec<Override>,
    files: FileChecks,
    primary: BTreeMap<String, &'static str>,
    /// Beside each of `stages`, the stage resolved once when no axis sets
    /// anything of it (the same at every point: resolving it again per
    /// point was a tenth of a cached sweep's rerun).
    fixed: Vec<Option<Stage>>,
}

impl PointResolver {
    fn resolve(
        &self,
        axes: &[sweep::Axis],
        index: usize,
        values: &[serde_json::Value],
        files: &mut FileChecks,
    ) -> Result<Vec<Stage>, Vec<Problem>> {
        let mut all = self.overrides.clone();
        all.extend(
            sweep::PointValues {
                index,
                values: values.to_vec(),
            }
            .overrides(axes),
        );
        let mut problems = Vec::new();
        let mut stages = Vec::new();
        for (i, rs) in self.stages.iter().enumerate() {
            let resolved = match self.fixed.get(i).and_then(Option::as_ref) {
                Some(s) => Ok(s.clone()),
                None => resolve_stage(&self.source, rs, &all, files),
            };
            match resolved {
                Ok(s) => stages.push(s),
                Err(mut e) => problems.append(&mut e),
            }
        }
        if !problems.is_empty() {
            return Err(problems);
        }
        fill_tables(&mut stages, &self.primary);
        Ok(stages)
    }
}

/// One point of a sweep: its values and its stages resolved with them.
#[derive(Clone, Debug)]
pub struct SweepPoint {
    pub index: usize,
    pub values: Vec<serde_json::Value>,
    /// Every stage that runs per point, resolved with the point's values.
    pub stages: Vec<Stage>,
}

impl Sweep {
    /// One gatherer per table the sweep gathers, in `gather` order.
    pub fn gatherers(&self) -> Vec<sweep::Gatherer<'_>> {
        sweep::Gatherer::each(&self.axes, &self.values, self.gather.len())
    }

    /// The table names the pseudo-stage `sweep` offers: `stage.table`.
    pub fn table_names(&self) -> Vec<String> {
        self.gather.iter().map(|g| g.to_string()).collect()
    }

    /// How many points the sweep has.
    pub fn len(&self) -> usize {
        self.values.len()
    }

    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// Point `index` with its stages resolved.
    pub fn point(&self, index: usize) -> SweepPoint {
        let values = &self.values[index];
        let mut files = self.resolver.files.clone();
        let stages = self
            .resolver
            .resolve(&self.axes, index, values, &mut files)
            .expect("every point resolved once at load");
        SweepPoint {
            index,
            values: values.clone(),
            stages,
        }
    }

    /// The names of the stages that run per point, in file order.
    pub fn point_stages(&self) -> impl Iterator<Item = &str> {
        self.resolver.stages.iter().map(|s| s.name.as_str())
    }
}

impl Pipeline {
    pub fn index(&self, name: &str) -> Option<usize> {
        self.stages.iter().position(|s| s.name == name)
    }

    /// The stage a user named, or their mistake with the stages there are.
    pub fn stage(&self, name: &str) -> Result<&Stage> {
        self.stages.iter().find(|s| s.name == name).ok_or_else(|| {
            let names: Vec<&str> = self.stages.iter().map(|s| s.name.as_str()).collect();
            InputError::arg(format!(
                "the pipeline has no stage `{name}`; its stages are: {}{}",
                names.join(", "),
                crate::suggest::hint(name, names.iter().copied())
            ))
        })
    }
}

/// The pipeline's name (`[pipeline] name`, else the file's stem): it names
/// the results folder. Checked by [`resolve`].
pub fn name_of(raw: &RawPipeline) -> String {
    match &raw.meta.name {
        Some(n) => n.get_ref().clone(),
        None => raw
            .source
            .path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "pipeline".into()),
    }
}

/// Parses and resolves a pipeline file's text with overrides.
pub fn load_source(src: &Source, overrides: &[Override]) -> Result<Pipeline> {
    let raw = super::raw::parse(src)
        .map_err(|errs| InputError(errs.into_iter().map(Problem::At).collect()))?;
    Ok(resolve(&raw, overrides).map_err(InputError)?)
}

/// Resolves a parsed file with overrides.
pub fn resolve(raw: &RawPipeline, overrides: &[Override]) -> Result<Pipeline, Vec<Problem>> {
    resolve_checking(raw, overrides, None)
}

/// [`resolve`], resolving at load only the sweep points `points` (all when
/// `None`): a cluster task runs a few points of a sweep the coordinator
/// has checked whole, and resolving 100 000 points would cost it a second.
pub fn resolve_checking(
    raw: &RawPipeline,
    overrides: &[Override],
    points: Option<&[usize]>,
) -> Result<Pipeline, Vec<Problem>> {
    let src = &raw.source;
    let mut problems = Vec::new();
    for o in overrides {
        match o.path.as_slice() {
            [s, name, _, ..] if s == "stages" => {
                if !raw.stages.iter().any(|st| &st.name == name) {
                    let hint =
                        crate::suggest::hint(name, raw.stages.iter().map(|st| st.name.as_str()));
                    problems.push(o.problem(src, format!("the pipeline has no stage `{name}`{hint}")));
                }
            }
            [e, s, _] if e == "executor" && s == "slurm" => {}
            _ => problems.push(o.problem(
                src,
                "a path starts with `stages.<stage>.` (e.g. stages.measure.seed=3) or is `executor.slurm.<setting>`",
            )),
        }
    }
    let slurm = match resolve_slurm(raw, overrides) {
        Ok(s) => s,
        Err(mut p) => {
            problems.append(&mut p);
            SlurmSettings::default()
        }
    };
    let mut files = FileChecks::new();
    let mut stages = Vec::new();
    for rs in &raw.stages {
        match resolve_stage(src, rs, overrides, &mut files) {
            Ok(s) => stages.push(s),
            Err(mut p) => problems.append(&mut p),
        }
    }
    if !problems.is_empty() {
        return Err(problems);
    }
    let name = name_of(raw);
    if !super::raw::valid_name(&name) {
        let message = format!(
            "the pipeline name `{name}` may only use letters, digits, `_` and `-` (it names the results folder)"
        );
        return Err(vec![match &raw.meta.name {
            Some(n) => Problem::At(src.error(n.span(), message)),
            None => Problem::file(&src.path, message),
        }]);
    }
    let gather_names: Vec<String> = raw
        .sweep
        .iter()
        .flat_map(|(sw, _)| sw.gather.iter().map(|g| g.get_ref().clone()))
        .collect();
    let mut pipeline = Pipeline {
        name,
        description: raw.meta.description.clone(),
        source: src.clone(),
        stages,
        snapshot: None,
        sweep: None,
        slurm,
    };
    check_graph(
        raw,
        &mut pipeline,
        raw.sweep.is_some().then_some(&gather_names[..]),
    )?;
    if let Some((sw, _)) = &raw.sweep {
        pipeline.sweep = Some(resolve_sweep(
            raw, sw, &pipeline, overrides, &mut files, points,
        )?);
    }
    check_columns(raw, &pipeline)?;
    if let Some((snap, header)) = &raw.snapshot {
        let stages: Vec<(&str, &ResolvedConfig)> = pipeline
            .stages
            .iter()
            .map(|s| (s.name.as_str(), &s.config))
            .collect();
        pipeline.snapshot = Some(snapshot_spec::resolve(src, snap, header.clone(), &stages)?);
    }
    Ok(pipeline)
}

/// One stage as written made a resolved stage: overrides applied, defaults
/// filled, settings validated, its file checked, every problem at its place.
///
/// Long on purpose (issue 31): each step reports at the field the user
/// wrote or the `--set` that changed it, and needs the spans of the steps
/// before it.
fn resolve_stage(
    src: &Source,
    rs: &RawStage,
    overrides: &[Override],
    files: &mut FileChecks,
) -> Result<Stage, Vec<Problem>> {
    let mut problems = Vec::new();
    let mut json = rs.config.to_json();
    // An override inside a value the file leaves to its default (`x.step`
    // of a default mesh range) starts from that default.
    let defaults = rs.config.clone().resolve().to_json();
    let mut inputs: BTreeMap<String, String> = rs
        .inputs
        .iter()
        .map(|i| (i.slot.clone(), i.target.clone()))
        .collect();
    let mine: Vec<(&Override, &[String])> = overrides
        .iter()
        .filter_map(|o| o.within(&rs.name).map(|rest| (o, rest)))
        .collect();
    let set = |json: &mut serde_json::Value, rest: &[String], value: &serde_json::Value| {
        for k in 1..rest.len() {
            let prefix = &rest[..k];
            if get_path(json, prefix).is_none_or(|v| v.is_null()) {
                if let Some(d) = get_path(&defaults, prefix) {
                    let _ = set_path(json, prefix, d.clone());
                }
            }
        }
        set_path(json, rest, value.clone())
    };
    for &(o, rest) in &mine {
        match rest {
            [k] if k == "kind" => {
                problems.push(o.problem(src, "a stage's kind cannot be overridden"))
            }
            [k, slot] if k == "inputs" => match o.value.as_str() {
                Some(t) => {
                    inputs.insert(slot.clone(), t.to_string());
                }
                None => problems.push(o.problem(src, "an input names a stage, as a string")),
            },
            _ => {
                if let Err(e) = set(&mut json, rest, &o.value) {
                    problems.push(o.problem(src, e));
                }
            }
        }
    }
    if !problems.is_empty() {
        return Err(problems);
    }
    let config = if mine.is_empty() {
        rs.config.clone()
    } else {
        StageConfig::from_json(&rs.kind, json).map_err(|e| {
            // Blame the override that fails on its own (a sweep axis with a
            // misspelt field among several axes of one stage); only an
            // interaction between several is reported against all of them.
            let alone: Vec<Problem> = mine
                .iter()
                .filter(|(_, rest)| !matches!(rest, [k, ..] if k == "inputs"))
                .filter_map(|&(o, rest)| {
                    let mut j = rs.config.to_json();
                    set(&mut j, rest, &o.value).ok()?;
                    let e = StageConfig::from_json(&rs.kind, j).err()?;
                    Some(o.problem(src, e))
                })
                .collect();
            if !alone.is_empty() {
                return alone;
            }
            let sets: Vec<String> = mine.iter().map(|(o, _)| o.name()).collect();
            vec![Problem::arg(format!("{}: {e}", sets.join(", ")))]
        })?
    };
    let config = config.resolve();
    let mut invalid = config.validate();
    let file_hash = config.file().and_then(|f| {
        let checked = files
            .entry((config.kind(), f.path.to_path_buf()))
            .or_insert_with(|| (f.check)(f.path));
        match checked {
            Ok(hash) => Some(hash.clone()),
            Err(why) => {
                invalid.push(Invalid::new(f.field, why.clone()));
                None
            }
        }
    });
    for inv in invalid {
        let overridden = mine.iter().find(|(_, rest)| {
            let p = rest.join(".");
            inv.field == p
                || inv.field.starts_with(&format!("{p}."))
                || p.starts_with(&format!("{}.", inv.field))
        });
        match overridden {
            Some((o, _)) => problems.push(o.problem(src, &inv.message)),
            None => {
                let span = rs
                    .fields
                    .get(&inv.field)
                    .cloned()
                    .unwrap_or_else(|| rs.span.clone());
                problems.push(Problem::At(
                    src.error(span, format!("stage `{}`: {}", rs.name, inv.message)),
                ));
            }
        }
    }
    if !problems.is_empty() {
        return Err(problems);
    }
    let inputs = inputs
        .into_iter()
        .map(|(slot, target)| {
            let r = match target.split_once('.') {
                Some((s, t)) => InputRef {
                    stage: s.to_string(),
                    table: t.to_string(),
                },
                None => InputRef {
                    stage: target.clone(),
                    table: String::new(),
                },
            };
            (slot, r)
        })
        .collect();
    Ok(Stage {
        name: rs.name.clone(),
        config,
        inputs,
        file_hash,
    })
}

/// Checks slots, references and cycles; fills in default table names.
fn check_graph(
    raw: &RawPipeline,
    p: &mut Pipeline,
    gathered: Option<&[String]>,
) -> Result<(), Vec<Problem>> {
    let src = &raw.source;
    let mut problems = Vec::new();
    for s in &p.stages {
        for (slot, r) in &s.inputs {
            problems.extend(check_input(raw, p, s, slot, r, gathered));
        }
        problems.extend(check_required(raw, s));
    }
    if !problems.is_empty() {
        return Err(problems);
    }
    let primary: BTreeMap<String, &'static str> = p
        .stages
        .iter()
        .map(|s| (s.name.clone(), s.config.outputs()[0]))
        .collect();
    fill_tables(&mut p.stages, &primary);
    match find_cycle(p) {
        Some(cycle) => {
            let (first, slot) = (&cycle[0].0, &cycle[0].1);
            let names: Vec<&str> = cycle.iter().map(|(s, _)| s.as_str()).collect();
            Err(vec![Problem::At(src.error(
                input_span(raw, first, slot, false),
                format!(
                    "the stage inputs form a cycle: {} → {} (each reads the next)",
                    names.join(" → "),
                    names[0]
                ),
            ))])
        }
        None => Ok(()),
    }
}

/// Where input `slot` of `stage` is written (its key when `key`, else its
/// value), or the stage's header when the file does not write it.
fn input_span(raw: &RawPipeline, stage: &str, slot: &str, key: bool) -> Range<usize> {
    let rs = raw.stages.iter().find(|s| s.name == stage);
    rs.and_then(|rs| rs.inputs.iter().find(|i| i.slot == slot))
        .map(|i| {
            if key {
                i.slot_span.clone()
            } else {
                i.span.clone()
            }
        })
        .or_else(|| rs.map(|rs| rs.span.clone()))
        .unwrap_or(0..0)
}

/// What is wrong with input `slot` of stage `s`, reading `r`: a slot the
/// kind does not have, a table the sweep does not gather, a stage or
/// table that does not exist, a group of tables named by one table.
fn check_input(
    raw: &RawPipeline,
    p: &Pipeline,
    s: &Stage,
    slot: &str,
    r: &InputRef,
    gathered: Option<&[String]>,
) -> Vec<Problem> {
    let src = &raw.source;
    let slots = s.config.inputs();
    let mut problems = Vec::new();
    if !slots.iter().any(|x| x.name == slot) {
        let known: Vec<&str> = slots.iter().map(|x| x.name).collect();
        problems.push(Problem::At(src.error(
            input_span(raw, &s.name, slot, true),
            format!(
                "stage `{}` ({}) has no input `{slot}`; its inputs are: {}",
                s.name,
                s.config.kind(),
                if known.is_empty() {
                    "none".to_string()
                } else {
                    known.join(", ")
                }
            ),
        )));
        return problems;
    }
    if let (sweep::PSEUDO_STAGE, Some(g)) = (r.stage.as_str(), gathered) {
        if !g.contains(&r.table) {
            problems.push(Problem::At(src.error(
                input_span(raw, &s.name, slot, false),
                format!(
                    "`sweep.{}` is not gathered; [sweep] gather has: {}",
                    r.table,
                    if g.is_empty() {
                        "nothing".into()
                    } else {
                        g.join(", ")
                    }
                ),
            )));
        }
        return problems;
    }
    let Some(producer) = p.stages.iter().find(|x| x.name == r.stage) else {
        let names: Vec<&str> = p.stages.iter().map(|x| x.name.as_str()).collect();
        problems.push(Problem::At(src.error(
            input_span(raw, &s.name, slot, false),
            format!(
                "input `{slot}` of stage `{}` names no stage `{}`; the stages are: {}{}",
                s.name,
                r.stage,
                names.join(", "),
                crate::suggest::hint(&r.stage, names.iter().copied())
            ),
        )));
        return problems;
    };
    let tables = producer.config.outputs();
    let spec = slots
        .iter()
        .find(|x| x.name == slot)
        .expect("checked above");
    if !spec.group.is_empty() {
        if !r.table.is_empty() {
            problems.push(Problem::At(src.error(
                input_span(raw, &s.name, slot, false),
                format!(
                    "input `{slot}` takes the tables {} of a stage together: name the stage alone, `\"{}\"`",
                    spec.group.join(", "),
                    r.stage
                ),
            )));
        }
        let missing: Vec<&str> = spec
            .group
            .iter()
            .copied()
            .filter(|t| !tables.contains(t))
            .collect();
        if !missing.is_empty() {
            problems.push(Problem::At(src.error(
                input_span(raw, &s.name, slot, false),
                format!(
                    "input `{slot}` needs the tables {} but stage `{}` ({}) lacks {}",
                    spec.group.join(", "),
                    producer.name,
                    producer.config.kind(),
                    missing.join(", ")
                ),
            )));
        }
        return problems;
    }
    if !r.table.is_empty() && !tables.contains(&r.table.as_str()) {
        problems.push(Problem::At(src.error(
            input_span(raw, &s.name, slot, false),
            format!(
                "stage `{}` ({}) has no table `{}`; its tables are: {}{}",
                producer.name,
                producer.config.kind(),
                r.table,
                tables.join(", "),
                crate::suggest::hint(&r.table, tables.iter().copied())
            ),
        )));
    }
    problems
}

/// Each required input slot of stage `s` that the file leaves unconnected.
fn check_required(raw: &RawPipeline, s: &Stage) -> Vec<Problem> {
    let src = &raw.source;
    let mut problems = Vec::new();
    for slot in s.config.inputs().iter().filter(|x| x.required) {
        if !s.inputs.contains_key(slot.name) {
            problems.push(Problem::At(src.error(
                input_span(raw, &s.name, "", true),
                format!(
                    "stage `{}` ({}) needs input `{}`: {}; add `inputs = {{ {} = \"<stage>\" }}`",
                    s.name,
                    s.config.kind(),
                    slot.name,
                    slot.doc,
                    slot.name
                ),
            )));
        }
    }
    problems
}

/// Names the producer's first table where an input names a stage alone.
fn fill_tables(stages: &mut [Stage], primary: &BTreeMap<String, &'static str>) {
    for s in stages {
        let slots = s.config.inputs();
        for (slot, r) in s.inputs.iter_mut() {
            let group = slots.iter().any(|x| x.name == slot && !x.group.is_empty());
            if r.table.is_empty() && !group {
                if let Some(t) = primary.get(&r.stage) {
                    r.table = t.to_string();
                }
            }
        }
    }
}

/// Checks every input column a stage's settings name (a plot's `filter`,
/// `x`, `y`, `series`) against the columns the producing stage's kind fixes
/// for that table — a gathered table adds `point` and its axes — so a
/// misspelt column is reported at load, at its place, not after a whole
/// sweep has run. Tables whose columns depend on the data are checked when
/// the stage runs.
fn check_columns(raw: &RawPipeline, p: &Pipeline) -> Result<(), Vec<Problem>> {
    let mut problems = Vec::new();
    for s in &p.stages {
        for u in s.config.columns_named() {
            let Some(r) = s.inputs.get(u.slot) else {
                continue;
            };
            let (producer, table, mut extra): (&str, String, Vec<&str>) =
                if r.stage == sweep::PSEUDO_STAGE {
                    let Some(sw) = &p.sweep else { continue };
                    let Some(g) = sw.gather.iter().find(|g| g.to_string() == r.table) else {
                        continue;
                    };
                    let axes = sw.axes.iter().map(|a| a.name.as_str());
                    (
                        &g.stage,
                        g.table.clone(),
                        std::iter::once("point").chain(axes).collect(),
                    )
                } else {
                    (&r.stage, r.table.clone(), Vec::new())
                };
            let Some(fixed) = p
                .stages
                .iter()
                .find(|x| x.name == producer)
                .and_then(|x| x.config.columns(&table))
            else {
                continue;
            };
            if fixed.contains(&u.column.as_str()) || extra.contains(&u.column.as_str()) {
                continue;
            }
            extra.extend(fixed);
            let rs = raw.stages.iter().find(|x| x.name == s.name);
            let span = rs
                .and_then(|rs| {
                    let top = u.field.split('.').next().unwrap_or_default();
                    rs.fields
                        .get(&u.field)
                        .or_else(|| rs.fields.get(top))
                        .or(Some(&rs.span))
                })
                .cloned()
                .unwrap_or(0..0);
            problems.push(Problem::At(raw.source.error(
                span,
                format!(
                    "stage `{}`: `{}` names column `{}`, which `{r}` does not have; its columns are: {}",
                    s.name,
                    u.field,
                    u.column,
                    extra.join(", ")
                ),
            )));
        }
    }
    if problems.is_empty() {
        Ok(())
    } else {
        Err(problems)
    }
}

/// `[executor.slurm]` with the command line's `executor.slurm.<setting>`
/// overrides applied, checked.
fn resolve_slurm(raw: &RawPipeline, overrides: &[Override]) -> Result<SlurmSettings, Vec<Problem>> {
    let src = &raw.source;
    let written = raw
        .executor
        .as_ref()
        .and_then(|(x, span)| Some((x.slurm.clone()?, span.clone())));
    let mut json =
        serde_json::to_value(written.as_ref().map(|(s, _)| s.clone()).unwrap_or_default())
            .expect("settings serialize");
    let mut problems = Vec::new();
    for o in overrides
        .iter()
        .filter(|o| o.path.first().is_some_and(|p| p == "executor"))
    {
        if let [_, _, field] = o.path.as_slice() {
            json[field.as_str()] = o.value.clone();
            if let Err(e) = serde_json::from_value::<SlurmSettings>(json.clone()) {
                problems.push(o.problem(src, format!("not a valid Slurm setting: {e}")));
                return Err(problems);
            }
        }
    }
    let settings: SlurmSettings = serde_json::from_value(json).expect("checked above");
    for why in settings.problems() {
        problems.push(match &written {
            Some((_, span)) => {
                Problem::At(src.error(span.clone(), format!("[executor.slurm]: {why}")))
            }
            None => Problem::arg(format!("--set executor.slurm: {why}")),
        });
    }
    if problems.is_empty() {
        Ok(settings)
    } else {
        Err(problems)
    }
}

/// Expands `[sweep]`: checks its paths and gathered tables against the
/// stages, and resolves every point's stages with the point's values.
fn resolve_sweep(
    raw: &RawPipeline,
    sw: &sweep::RawSweep,
    p: &Pipeline,
    overrides: &[Override],
    files: &mut FileChecks,
    check: Option<&[usize]>,
) -> Result<Sweep, Vec<Problem>> {
    let src = &raw.source;
    let mut problems = Vec::new();
    // The stages after the sweep: readers of `sweep`, and their readers.
    let mut after: Vec<String> = Vec::new();
    loop {
        let more: Vec<String> = p
            .stages
            .iter()
            .filter(|s| !after.contains(&s.name))
            .filter(|s| {
                s.inputs
                    .values()
                    .any(|r| r.stage == sweep::PSEUDO_STAGE || after.contains(&r.stage))
            })
            .map(|s| s.name.clone())
            .collect();
        if more.is_empty() {
            break;
        }
        after.extend(more);
    }
    let per_point =
        |name: &str| p.stages.iter().any(|s| s.name == name) && !after.iter().any(|a| a == name);
    for a in &sw.axes {
        match split_path(a.path.get_ref()).as_deref() {
            Some([st, name, _, ..]) if st == "stages" && per_point(name) => {}
            Some([st, name, _, ..]) if st == "stages" && after.iter().any(|x| x == name) => {
                problems.push(Problem::At(src.error(
                    a.path.span(),
                    format!("stage `{name}` runs after the sweep, on gathered tables: sweep the stages it gathers from"),
                )))
            }
            _ => problems.push(Problem::At(src.error(
                a.path.span(),
                "an axis sweeps `stages.<stage>.<field>` of a stage of this pipeline",
            ))),
        }
    }
    let mut gather = Vec::new();
    for g in &sw.gather {
        let found = g.get_ref().split_once('.').and_then(|(st, t)| {
            let stage = p.stages.iter().find(|s| s.name == st && per_point(st))?;
            stage.config.outputs().contains(&t).then(|| InputRef {
                stage: st.to_string(),
                table: t.to_string(),
            })
        });
        match found {
            Some(r) => gather.push(r),
            None => problems.push(Problem::At(src.error(
                g.span(),
                format!(
                    "`{}` is not `stage.table` of a stage that runs per sweep point",
                    g.get_ref()
                ),
            ))),
        }
    }
    if !problems.is_empty() {
        return Err(problems);
    }
    let (axes, values) = sweep::expand(src, sw)?;
    let primary: BTreeMap<String, &'static str> = p
        .stages
        .iter()
        .map(|s| (s.name.clone(), s.config.outputs()[0]))
        .collect();
    let resolver = PointResolver {
        source: src.clone(),
        stages: raw
            .stages
            .iter()
            .filter(|rs| per_point(&rs.name))
            .cloned()
            .collect(),
        overrides: overrides.to_vec(),
        files: FileChecks::new(),
        primary,
        fixed: Vec::new(),
    };
    // A stage no axis sets anything of resolves alike at every point (its
    // mistakes, if any, are reported by the per-point resolution below).
    let fixed = resolver
        .stages
        .iter()
        .map(|rs| {
            let swept = axes.iter().any(
                |a| matches!(a.path.as_slice(), [s, name, ..] if s == "stages" && *name == rs.name),
            );
            if swept {
                return None;
            }
            resolve_stage(src, rs, overrides, files).ok()
        })
        .collect();
    let resolver = PointResolver { fixed, ..resolver };
    // Every point resolved once, to report any point's mistakes now; the
    // stages are dropped, the files they read kept (hashed once).
    let checked = values
        .iter()
        .filter(|v| check.is_none_or(|c| c.binary_search(&v.index).is_ok()));
    for v in checked {
        if let Err(mut e) = resolver.resolve(&axes, v.index, &v.values, files) {
            problems.append(&mut e);
            return Err(problems);
        }
    }
    let resolver = PointResolver {
        files: files.clone(),
        ..resolver
    };
    Ok(Sweep {
        axes,
        values: values.into_iter().map(|v| v.values).collect(),
        gather,
        after,
        resolver: Arc::new(resolver),
    })
}

/// A cycle as `(stage, slot)` edges: each stage reads the next one's table
/// through that slot, and the last reads the first.
fn find_cycle(p: &Pipeline) -> Option<Vec<(String, String)>> {
    #[derive(Clone, Copy, PartialEq)]
    enum Mark {
        New,
        Active,
        Done,
    }
    fn visit(
        p: &Pipeline,
        i: usize,
        marks: &mut [Mark],
        path: &mut Vec<(String, String)>,
    ) -> Option<Vec<(String, String)>> {
        marks[i] = Mark::Active;
        for (slot, r) in &p.stages[i].inputs {
            let Some(j) = p.index(&r.stage) else { continue };
            path.push((p.stages[i].name.clone(), slot.clone()));
            match marks[j] {
                Mark::Active => {
                    let start = path.iter().position(|(s, _)| *s == p.stages[j].name)?;
                    return Some(path[start..].to_vec());
                }
                Mark::New => {
                    if let Some(c) = visit(p, j, marks, path) {
                        return Some(c);
                    }
                }
                Mark::Done => {}
            }
            path.pop();
        }
        marks[i] = Mark::Done;
        None
    }
    let mut marks = vec![Mark::New; p.stages.len()];
    (0..p.stages.len()).find_map(|i| {
        (marks[i] == Mark::New)
            .then(|| visit(p, i, &mut marks, &mut Vec::new()))
            .flatten()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const TEXT: &str = "[stages.a]\nkind = \"mesh\"\nshape = \"plane\"\n\
        [stages.t]\nkind = \"inject\"\n\
        [stages.m]\nkind = \"measure\"\ninputs = { points = \"a\", errors = \"t\" }\n";

    fn raw(text: &str) -> RawPipeline {
        super::super::raw::parse(&Source::new("p.toml", text)).unwrap()
    }

    fn messages(problems: Vec<Problem>) -> String {
        problems
            .iter()
            .map(|p| p.to_string())
            .collect::<Vec<_>>()
            .join("\n")
    }

    #[test]
    fn resolve_fills_defaults_applies_overrides_and_leaves_the_file_as_written() {
        let raw = raw(TEXT);
        let seven = Override::parse("stages.m.seed=7").unwrap();
        let p = resolve(&raw, &[seven]).unwrap();
        let m = p.stage("m").unwrap().config.to_json();
        assert_eq!(m["seed"], 7);
        // Defaults the file does not write are filled in.
        assert!(m.get("noise").is_some() && m.get("face").is_some(), "{m}");
        // An input naming a stage alone reads its first table.
        let points = &p.stage("m").unwrap().inputs["points"];
        assert_eq!(
            (points.stage.as_str(), points.table.as_str()),
            ("a", "points")
        );
        // The raw pipeline is not changed by resolving it: without the
        // override, the seed is the default again.
        let again = resolve(&raw, &[]).unwrap();
        assert_eq!(again.stage("m").unwrap().config.to_json()["seed"], 0);
        assert_eq!(p.name, "p");
    }

    #[test]
    fn check_graph_names_a_missing_stage_an_unknown_slot_and_a_missing_input() {
        let text = "[stages.a]\nkind = \"mesh\"\nshape = \"plane\"\n\
            [stages.m]\nkind = \"measure\"\ninputs = { points = \"b\", pionts = \"a\" }\n\
            [stages.c]\nkind = \"correct\"\ninputs = { readings = \"m\" }\n";
        let e = messages(resolve(&raw(text), &[]).unwrap_err());
        assert!(e.contains("names no stage `b`"), "{e}");
        assert!(e.contains("has no input `pionts`"), "{e}");
        assert!(e.contains("needs input `params`"), "{e}");
    }

    #[test]
    fn check_graph_reports_a_cycle_at_its_first_input() {
        let text = "[stages.t]\nkind = \"inject\"\n\
            [stages.a]\nkind = \"correct\"\ninputs = { readings = \"b\", params = \"t\" }\n\
            [stages.b]\nkind = \"correct\"\ninputs = { readings = \"a\", params = \"t\" }\n";
        let e = messages(resolve(&raw(text), &[]).unwrap_err());
        assert!(e.contains("the stage inputs form a cycle"), "{e}");
        // At an input of the cycle, where the file writes it.
        assert!(e.contains("p.toml:5:") || e.contains("p.toml:7:"), "{e}");
    }
}
