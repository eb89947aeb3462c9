//! Stage kinds: one small module per kind, each a typed, validated TOML table
//! and a function from input tables to output tables.
//!
//! A stage kind declares its input slots and output tables; the runner wires
//! slots to other stages' tables, caches outputs and never looks inside a
//! config except through [`StageConfig`]. Adding a kind means adding a module
//! and one line to [`stage_kinds!`].

pub mod b89_tests;
pub mod blind_check;
pub mod blind_summary;
pub mod calibrate;
mod campaign_tables;
pub mod compare_models;
pub mod correct;
pub mod counts;
pub mod diagnose;
pub mod evaluate;
pub mod evaluate_campaign;
pub mod export_campaign;
pub mod fitting;
pub mod identify;
pub mod import_campaign;
pub mod incidence_fit;
pub mod inject;
pub mod layout_design;
pub mod measure;
pub mod measurement_uncertainty;
pub mod mesh;
pub mod model_blind_check;
pub mod monte_carlo;
pub mod open_world_check;
pub mod paper_gap;
pub mod plot;
pub mod schema;
pub mod sensitivity;
pub mod settings;
pub mod simulate_campaign;
pub mod spread;

use crate::table::TableRef;
use anyhow::{Result, anyhow};
use polars::prelude::DataFrame;
use serde::{Serialize, de::DeserializeOwned};
use std::collections::BTreeMap;
use std::fmt::Debug;
use std::path::Path;
use std::sync::Arc;

/// An input slot of a stage kind: one table, or a group of tables that
/// travel together (a campaign is `readings`, `targets`, `gauge`, `meta`).
#[derive(Clone, Copy, Debug)]
pub struct Slot {
    pub name: &'static str,
    pub required: bool,
    pub doc: &'static str,
    /// For a group slot, the producer tables it takes; a stage reads them as
    /// `<slot>.<table>`. Empty for a single-table slot.
    pub group: &'static [&'static str],
}

impl Slot {
    pub const fn table(name: &'static str, required: bool, doc: &'static str) -> Slot {
        Slot {
            name,
            required,
            doc,
            group: &[],
        }
    }

    pub const fn group(
        name: &'static str,
        required: bool,
        doc: &'static str,
        tables: &'static [&'static str],
    ) -> Slot {
        Slot {
            name,
            required,
            doc,
            group: tables,
        }
    }
}

/// A setting that cannot work, with the dotted path of its field.
#[derive(Clone, Debug, PartialEq)]
pub struct Invalid {
    pub field: String,
    pub message: String,
}

impl Invalid {
    pub fn new(field: impl Into<String>, message: impl Into<String>) -> Invalid {
        Invalid {
            field: field.into(),
            message: message.into(),
        }
    }

    /// The problem of a stage's `noise` table, if it has one.
    pub fn noise(n: &crate::noise::Noise) -> Option<Invalid> {
        n.check().err().map(|(f, v)| {
            Invalid::new(
                format!("noise.{f}"),
                format!("`noise.{f}` must be a number ≥ 0, got {v}"),
            )
        })
    }

    /// The problems of a stage's `layout` table (a layout spec).
    pub fn layout(spec: &crate::layout::Spec) -> Vec<Invalid> {
        spec.check()
            .into_iter()
            .map(|(f, m)| Invalid::new(format!("layout.{f}"), m))
            .collect()
    }
}

/// The tables wired to a stage's slots.
#[derive(Default)]
pub struct StageInputs {
    tables: BTreeMap<String, (String, Arc<DataFrame>)>,
}

impl StageInputs {
    /// `label` names the table in messages, e.g. `measure_plane.readings`.
    pub fn insert(&mut self, slot: &str, label: String, df: Arc<DataFrame>) {
        self.tables.insert(slot.to_string(), (label, df));
    }

    pub fn get(&self, slot: &str) -> Result<TableRef<'_>> {
        self.optional(slot)
            .ok_or_else(|| anyhow!("input `{slot}` is not connected"))
    }

    pub fn optional(&self, slot: &str) -> Option<TableRef<'_>> {
        self.tables
            .get(slot)
            .map(|(label, df)| TableRef::new(label, df))
    }
}

/// What a stage produces: named tables (Parquet) and files (figures).
#[derive(Default)]
pub struct StageOutput {
    pub tables: Vec<(String, DataFrame)>,
    pub files: Vec<(String, Vec<u8>)>,
}

impl StageOutput {
    pub fn table(mut self, name: &str, df: DataFrame) -> Self {
        self.tables.push((name.to_string(), df));
        self
    }
    pub fn file(mut self, name: String, bytes: Vec<u8>) -> Self {
        self.files.push((name, bytes));
        self
    }
}

/// A column of an input table that a setting names.
#[derive(Clone, Debug, PartialEq)]
pub struct ColumnUse {
    pub slot: &'static str,
    /// The setting's dotted path (`filter.criterion`), for its location.
    pub field: String,
    pub column: String,
}

/// A file or folder a stage reads, named by one of its settings. The
/// runner, not the stage, reads it when the pipeline loads — once per
/// path, however many sweep points name it — refuses it at that setting's
/// place when [`StageFile::check`] does, and puts the content hash it
/// returns in the cache key, so an edited file is never answered from the
/// cache.
#[derive(Clone, Copy)]
pub struct StageFile<'a> {
    /// The setting that names it.
    pub field: &'static str,
    pub path: &'a Path,
    /// Reads and checks it: its content hash, or why it cannot be used.
    pub check: fn(&Path) -> Result<String, String>,
}

/// What a running stage knows about where it runs.
pub struct Context<'a> {
    pub pipeline: &'a str,
    pub stage: &'a str,
    /// The content hash the runner recorded for the stage's
    /// [`StageKind::file`] when the pipeline loaded: what the stage checks
    /// its file still has.
    pub file_hash: Option<&'a str>,
}

/// A stage kind: its TOML table (with `deny_unknown_fields`), its slots and
/// tables, and what it does.
pub trait StageKind: Serialize + DeserializeOwned + Clone + Debug + Send + Sync + 'static {
    /// The `kind = "…"` value.
    const KIND: &'static str;
    /// One line for `ltcal kinds` and the README.
    const SUMMARY: &'static str;
    const INPUTS: &'static [Slot];
    /// Output tables; the first is the one an input reference without a
    /// table name (`"stage"` rather than `"stage.table"`) means.
    const OUTPUTS: &'static [&'static str];

    /// The settings with the defaults that depend on other settings filled
    /// in, so that the cache key sees every value the stage will use.
    fn resolved(self) -> Self {
        self
    }

    /// The file or folder the stage reads, if any ([`StageFile`]).
    fn file(&self) -> Option<StageFile<'_>> {
        None
    }

    /// Settings that cannot work, each naming its field.
    fn validate(&self) -> Vec<Invalid> {
        Vec::new()
    }

    /// The columns of output `table` when the kind fixes them; `None` when
    /// they depend on the data (one column per station) or are not
    /// declared. Settings of other stages that name these columns are
    /// checked at load ([`StageKind::columns_named`]); against an
    /// undeclared table they are checked only when the stage runs.
    fn columns(_table: &str) -> Option<&'static [&'static str]> {
        None
    }

    /// The input columns the settings name, checked at load against the
    /// producing stage's [`StageKind::columns`].
    fn columns_named(&self) -> Vec<ColumnUse> {
        Vec::new()
    }

    fn run(&self, ctx: &Context, inputs: &StageInputs) -> Result<StageOutput>;
}

/// The settings of one stage after resolution — every default filled in —
/// made only by [`StageConfig::resolve`]. A stage runs from this type alone
/// and the cache key hashes its JSON ([`StageConfig::to_json`], reached
/// through `Deref` with the other read-only queries), so settings as
/// written can neither run nor key a cache entry.
#[derive(Clone, Debug)]
pub struct ResolvedConfig(StageConfig);

impl std::ops::Deref for ResolvedConfig {
    type Target = StageConfig;
    fn deref(&self) -> &StageConfig {
        &self.0
    }
}

macro_rules! stage_kinds {
    ($($variant:ident => $ty:ty),* $(,)?) => {
        /// The settings of one stage, of any kind, as written (the raw
        /// layer): defaults that depend on other settings not yet filled in.
        /// [`StageConfig::resolve`] makes the [`ResolvedConfig`] a stage
        /// runs from.
        #[derive(Clone, Debug)]
        pub enum StageConfig {
            $($variant(Box<$ty>)),*
        }

        /// Every kind name, for messages.
        pub const KINDS: &[&str] = &[$(<$ty as StageKind>::KIND),*];

        impl StageConfig {
            /// Deserializes a stage table of the named kind; `None` for an
            /// unknown kind.
            pub fn deserialize<'de, D>(kind: &str, de: D) -> Option<Result<StageConfig, D::Error>>
            where
                D: serde::Deserializer<'de>,
            {
                match kind {
                    $(<$ty as StageKind>::KIND => Some(
                        <$ty as serde::Deserialize>::deserialize(de).map(|c| StageConfig::$variant(Box::new(c))),
                    ),)*
                    _ => None,
                }
            }

            /// The `///` doc of setting `name` of stage kind `kind`, read
            /// from its settings struct ([`documented::DocumentedFields`]);
            /// `None` for an unknown kind or setting.
            pub fn setting_doc(kind: &str, name: &str) -> Option<&'static str> {
                use documented::DocumentedFields;
                match kind {
                    $(<$ty as StageKind>::KIND => <$ty>::get_field_docs(name).ok(),)*
                    _ => None,
                }
            }

            pub fn kind(&self) -> &'static str {
                match self { $(StageConfig::$variant(_) => <$ty as StageKind>::KIND),* }
            }
            pub fn inputs(&self) -> &'static [Slot] {
                match self { $(StageConfig::$variant(_) => <$ty as StageKind>::INPUTS),* }
            }
            pub fn outputs(&self) -> &'static [&'static str] {
                match self { $(StageConfig::$variant(_) => <$ty as StageKind>::OUTPUTS),* }
            }
            /// The resolved settings: every default filled in
            /// ([`StageKind::resolved`]).
            pub fn resolve(self) -> ResolvedConfig {
                ResolvedConfig(match self {
                    $(StageConfig::$variant(c) => StageConfig::$variant(Box::new(c.resolved()))),*
                })
            }
            pub fn file(&self) -> Option<StageFile<'_>> {
                match self { $(StageConfig::$variant(c) => c.file()),* }
            }
            /// The kind's fixed columns of output `table` ([`StageKind::columns`]).
            pub fn columns(&self, table: &str) -> Option<&'static [&'static str]> {
                match self { $(StageConfig::$variant(_) => <$ty as StageKind>::columns(table)),* }
            }
            pub fn columns_named(&self) -> Vec<ColumnUse> {
                match self { $(StageConfig::$variant(c) => c.columns_named()),* }
            }
            /// The kind's own checks, then the bound on every count
            /// ([`counts`]) the kind has not already refused.
            pub fn validate(&self) -> Vec<Invalid> {
                let mut out = match self { $(StageConfig::$variant(c) => c.validate()),* };
                let more: Vec<Invalid> = counts::check(&self.to_json())
                    .into_iter()
                    .filter(|c| !out.iter().any(|o| o.field == c.field))
                    .collect();
                out.extend(more);
                out
            }
            /// The settings as JSON: what the cache key hashes and what
            /// overrides patch.
            pub fn to_json(&self) -> serde_json::Value {
                match self {
                    $(StageConfig::$variant(c) => serde_json::to_value(c)
                        .expect("stage settings serialize to JSON")),*
                }
            }
            pub fn from_json(kind: &str, v: serde_json::Value) -> Result<StageConfig> {
                StageConfig::deserialize(kind, v)
                    .ok_or_else(|| anyhow!("unknown stage kind `{kind}`"))?
                    .map_err(|e| anyhow!("{}", crate::suggest::serde_message(&e.to_string())))
            }
        }

        impl ResolvedConfig {
            /// Runs the stage: only resolved settings run.
            pub fn run(&self, ctx: &Context, inputs: &StageInputs) -> Result<StageOutput> {
                match &self.0 { $(StageConfig::$variant(c) => c.run(ctx, inputs)),* }
            }
        }

        /// The columns kind `kind` declares for its output `table`
        /// ([`StageKind::columns`]); `None` for an unknown kind or a table
        /// whose columns depend on the data.
        pub fn declared_columns(kind: &str, table: &str) -> Option<&'static [&'static str]> {
            match kind {
                $(<$ty as StageKind>::KIND => <$ty as StageKind>::columns(table),)*
                _ => None,
            }
        }

        /// `(kind, summary)` of every stage kind.
        pub fn summaries() -> Vec<(&'static str, &'static str)> {
            vec![$((<$ty as StageKind>::KIND, <$ty as StageKind>::SUMMARY)),*]
        }
    };
}

stage_kinds! {
    Mesh => mesh::MeshStage,
    Inject => inject::InjectStage,
    Measure => measure::MeasureStage,
    Identify => identify::IdentifyStage,
    Correct => correct::CorrectStage,
    Evaluate => evaluate::EvaluateStage,
    Plot => plot::PlotStage,
    SimulateCampaign => simulate_campaign::SimulateCampaignStage,
    Calibrate => calibrate::CalibrateStage,
    EvaluateCampaign => evaluate_campaign::EvaluateCampaignStage,
    Diagnose => diagnose::DiagnoseStage,
    BlindCheck => blind_check::BlindCheckStage,
    BlindSummary => blind_summary::BlindSummaryStage,
    PaperGap => paper_gap::PaperGapStage,
    ImportCampaign => import_campaign::ImportCampaignStage,
    ExportCampaign => export_campaign::ExportCampaignStage,
    Sensitivity => sensitivity::SensitivityStage,
    IncidenceFit => incidence_fit::IncidenceFitStage,
    LayoutDesign => layout_design::LayoutDesignStage,
    MonteCarlo => monte_carlo::MonteCarloStage,
    Spread => spread::SpreadStage,
    MeasurementUncertainty => measurement_uncertainty::MeasurementUncertaintyStage,
    B89Tests => b89_tests::B89TestsStage,
    CompareModels => compare_models::CompareModelsStage,
    ModelBlindCheck => model_blind_check::ModelBlindCheckStage,
    OpenWorldCheck => open_world_check::OpenWorldCheckStage,
}
