//! Every call the Python package makes into the `ltcal` library, in one
//! file and in plain Rust (no Python types): when a library function moves,
//! this file is the one to follow it. Each function does what the matching
//! CLI command does (`src/cli.rs`) and returns data — tables as the Parquet
//! bytes the library already holds them as, reports as JSON — so that
//! Python only converts.

use anyhow::Context as _;
use ltcal::campaign::{self, Problem};
use ltcal::pipeline::{self, cluster, publish, published, resolve::Override, run};
use ltcal::stages::{self, StageKind as _};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// Why a call failed, sorted the way Python raises it.
#[derive(Debug)]
pub enum Error {
    /// The input is wrong (the CLI's exit 2): each problem located.
    Input(Vec<Located>),
    /// The work did not succeed (the CLI's exit 1).
    Other(String),
}

/// One located problem: a file position (`file`, `line`, `column` as a
/// character column), or, in a campaign table, the `table`, its 0-based
/// `row` and the column's name.
#[derive(Debug, Default)]
pub struct Located {
    pub message: String,
    pub file: Option<String>,
    pub line: Option<usize>,
    pub column: Option<usize>,
    pub column_name: Option<String>,
    pub table: Option<String>,
    pub row: Option<usize>,
}

pub type Result<T> = std::result::Result<T, Error>;

/// Tables by name, each as its Parquet bytes.
pub type Tables = Vec<(String, Vec<u8>)>;

impl From<anyhow::Error> for Error {
    fn from(e: anyhow::Error) -> Error {
        if let Some(input) = e.downcast_ref::<pipeline::InputError>() {
            return Error::Input(input.0.iter().map(|p| locate(p, None)).collect());
        }
        if let Some(at) = e.downcast_ref::<ltcal::diagnostics::SourceError>() {
            return Error::Input(vec![located_source(at, None)]);
        }
        Error::Other(format!("{e:#}"))
    }
}

fn located_source(at: &ltcal::diagnostics::SourceError, names: Option<&Path>) -> Located {
    let (line, column) = at.line_col();
    let mut l = Located {
        message: at.to_string(),
        file: Some(at.source.path.display().to_string()),
        line: Some(line),
        column: Some(column),
        ..Default::default()
    };
    // A campaign's CSV file: the table it is, the 0-based data row, and the
    // header's name of the cell's column.
    let path = &at.source.path;
    if path.extension().is_some_and(|e| e == "csv") {
        l.table = path.file_stem().map(|s| s.to_string_lossy().into_owned());
        l.row = line.checked_sub(2);
        l.column_name = column_at(&at.source.text, at.span.start)
            .or_else(|| backticked_after(&at.message, "column `"));
        if names.is_some() {
            // Written from DataFrames: the user knows tables, rows and
            // columns, not the scratch files they passed through.
            l.file = None;
            l.line = None;
            l.column = None;
            l.message = in_table(&l, &at.message);
        }
    }
    l
}

/// "table `readings`, row 7, column `d_mm`: …", as [`campaign::Issue`]
/// says it for a campaign that comes from tables.
fn in_table(l: &Located, message: &str) -> String {
    let mut at = format!("table `{}`", l.table.as_deref().unwrap_or("?"));
    if let Some(row) = l.row {
        at += &format!(", row {row}");
    }
    if let Some(c) = &l.column_name {
        at += &format!(", column `{c}`");
    }
    format!("{at}: {message}")
}

fn locate(p: &Problem, names: Option<&Path>) -> Located {
    match p {
        Problem::At(at) => located_source(at, names),
        Problem::File { path, message } => Located {
            message: if names.is_some() {
                message.clone()
            } else {
                p.to_string()
            },
            file: path
                .as_ref()
                .filter(|_| names.is_none())
                .map(|p| p.display().to_string()),
            table: path
                .as_ref()
                .and_then(|p| p.file_stem())
                .map(|s| s.to_string_lossy().into_owned())
                .filter(|_| names.is_some()),
            column_name: backticked_after(message, "column `"),
            ..Default::default()
        },
    }
}

/// The header's name of the CSV field at byte `offset` (fields split at
/// unquoted commas, as the files ltcal writes and reads them).
fn column_at(text: &str, offset: usize) -> Option<String> {
    let start = text[..offset.min(text.len())]
        .rfind('\n')
        .map_or(0, |i| i + 1);
    if start == 0 {
        return None;
    }
    let mut quoted = false;
    let field = text[start..offset.min(text.len())]
        .chars()
        .filter(|&c| {
            if c == '"' {
                quoted = !quoted;
            }
            c == ',' && !quoted
        })
        .count();
    let header = text.lines().next()?;
    header
        .split(',')
        .nth(field)
        .map(|h| h.trim().trim_matches('"').to_string())
}

fn backticked_after(message: &str, marker: &str) -> Option<String> {
    let rest = &message[message.find(marker)? + marker.len()..];
    Some(rest[..rest.find('`')?].to_string())
}

fn input(message: impl Into<String>) -> Error {
    Error::Input(vec![Located {
        message: message.into(),
        ..Default::default()
    }])
}

/// Which pipeline results a call is about: the CLI's `PipelineArgs`.
pub struct Target {
    pub pipeline: PathBuf,
    pub set: Vec<String>,
    pub name: Option<String>,
    pub results: PathBuf,
}

impl Target {
    fn overrides(&self) -> Result<Vec<Override>> {
        self.set
            .iter()
            .map(|s| Override::parse(s))
            .collect::<anyhow::Result<Vec<_>>>()
            .map_err(|e| input(e.to_string()))
    }

    fn load(
        &self,
    ) -> Result<(
        pipeline::resolve::Pipeline,
        Option<pipeline::experiment::Experiment>,
    )> {
        Ok(pipeline::load_target(
            &self.pipeline,
            &self.overrides()?,
            self.name.as_deref(),
            &self.results,
        )?)
    }
}

/// What [`run`] reports while it works: `done` of `total` units (a
/// sweep's points, or else the pipeline's stages; cached counts as done)
/// and the unit's name. Returning `false` (Ctrl-C) stops the run.
pub type Progress<'a> = dyn FnMut(usize, usize, &'static str) -> bool + 'a;

/// `ltcal run`: runs the pipeline on a worker thread (local: a pool of
/// `jobs` threads; `slurm`: the pipeline's `[executor.slurm]`) while the
/// caller's thread polls `poll` every 100 ms with what is done so far.
/// When `poll` returns false (Ctrl-C), the run stops: locally nothing
/// starts after it and the stages and sweep points under way finish and
/// are cached (`pipeline::control`); a Slurm coordinator cancels its jobs.
/// The call returns once the run has stopped — or at once on a second
/// `false`, leaving what is under way to finish on its thread (each entry
/// lands whole in the cache, never half). Returns the run report as JSON.
pub fn run(
    t: &Target,
    jobs: Option<usize>,
    executor: &str,
    keep_going: bool,
    poll: &mut Progress<'_>,
) -> Result<String> {
    let (pipeline, e) = t.load()?;
    // Raised by the first `false` of `poll`: the run's stop, and the Slurm
    // coordinator's.
    let interrupted = Arc::new(AtomicBool::new(false));
    let opts = run::RunOptions {
        results_root: t.results.clone(),
        keep_going,
        progress: false,
        not_computed: None,
        experiment: e.clone(),
        control: Arc::new(pipeline::control::Control::with_flag(interrupted.clone())),
    };
    let control = opts.control.clone();
    let work: Box<dyn FnOnce() -> anyhow::Result<run::RunReport> + Send> = match executor {
        "local" => {
            let pipeline = pipeline.clone();
            match jobs {
                // All cores: rayon's global pool, as the command line.
                None => Box::new(move || publish::run(&pipeline, &opts)),
                // A pool of its own: the global one is sized once per process.
                Some(n) => {
                    let pool = rayon::ThreadPoolBuilder::new()
                        .num_threads(n)
                        .build()
                        .context("starting the worker threads")?;
                    Box::new(move || pool.install(|| publish::run(&pipeline, &opts)))
                }
            }
        }
        "slurm" => {
            // As `ltcal run --executor slurm`: tasks compute with every stage
            // override, recorded ones too, and the `executor.*` ones.
            let mut set_args: Vec<String> =
                e.iter().flat_map(|e| e.overrides.iter().cloned()).collect();
            set_args.extend(t.overrides()?.into_iter().filter_map(|o| {
                (o.path.first().map(String::as_str) != Some("stages")).then_some(o.text)
            }));
            let cluster = cluster::ClusterOptions {
                pipeline_file: t.pipeline.clone(),
                set_args,
                detach: false,
                interrupted: interrupted.clone(),
            };
            let pipeline = pipeline.clone();
            Box::new(move || {
                match cluster::run(&pipeline, &opts, &cluster, &cluster::slurm::Slurm)? {
                    cluster::Outcome::Finished(report) => Ok(*report),
                    cluster::Outcome::Detached { .. } => {
                        anyhow::bail!("the Slurm run was detached")
                    }
                }
            })
        }
        other => {
            return Err(input(format!(
                "executor `{other}`: expected `local` or `slurm`"
            )));
        }
    };
    // The run sends its outcome the moment it ends: a cached run returns
    // at once, not at the next poll.
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(caught(work));
    });
    // A sweep's progress is its points (its stages run at each), a
    // pipeline's its stages.
    let (total, unit) = match &pipeline.sweep {
        Some(sw) => (sw.len(), "point"),
        None => (pipeline.stages.len(), "stage"),
    };
    let done = || {
        let n = match pipeline.sweep {
            Some(_) => control.points_done(),
            None => control.stages_done(),
        };
        n.min(total)
    };
    let report = loop {
        match rx.recv_timeout(std::time::Duration::from_millis(100)) {
            Ok(outcome) => break outcome?,
            Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
                return Err(Error::Other("the run's thread ended unexpectedly".into()));
            }
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
        }
        // The first stop is the run's; the second stops the waiting for
        // what is under way.
        if !poll(done(), total, unit) && interrupted.swap(true, Ordering::SeqCst) {
            return Err(Error::Other("interrupted".into()));
        }
    };
    poll(total, total, unit);
    serde_json::to_string(&report).map_err(|e| Error::Other(e.to_string()))
}

/// The published table `stage[.table]` of the run `t` names, checked against
/// the cache entry it came from (as `ltcal show`): its Parquet bytes, and why
/// it is not current if it is not.
pub fn table(t: &Target, table: &str) -> Result<(Vec<u8>, Option<String>)> {
    let (pipeline, e) = t.load()?;
    if let Some(e) = e.as_ref().filter(|_| t.name.is_some()) {
        pipeline::experiment::check_recorded(&run::pipeline_dir(&t.results, &pipeline), e)?;
    }
    let dir = run::results_dir(&t.results, &pipeline, e.as_ref());
    let (stage, name) = match table.split_once('.') {
        Some((s, n)) => (s, Some(n)),
        None => (table, None),
    };
    let store = run::store(&t.results, &pipeline, e.as_ref());
    let rerun = format!("ltcal.run({:?})", t.pipeline.display().to_string());
    let p = published::read(&pipeline, &store, &dir, stage, name, &rerun)?;
    Ok((p.bytes, p.stale))
}

/// The settings of a diagnosis: `ltcal diagnose`'s options.
pub struct DiagnoseOptions {
    pub effects: Vec<String>,
    pub folds: usize,
    pub mc_draws: usize,
    pub seed: u64,
    pub model: Option<String>,
    pub hypotheses: Option<PathBuf>,
}

/// What a diagnosis returns: the verdict, every table (name, Parquet bytes)
/// and the names of the files written to `out`.
pub struct Diagnosed {
    pub verdict: String,
    pub tables: Tables,
    pub files: Vec<String>,
}

/// `ltcal diagnose <campaign> --out <out>`; `names` is set when the folder
/// was written from DataFrames (errors then name tables, not files).
pub fn diagnose(campaign: &Path, out: &Path, o: DiagnoseOptions, names: bool) -> Result<Diagnosed> {
    let model = match o.model.as_deref() {
        None => None,
        Some(m) => Some(ltcal::trackers::TrackerModel::parse(m).ok_or_else(|| {
            input(format!(
                "unknown tracker model `{m}`; expected {}",
                ltcal::trackers::TrackerModel::expected()
            ))
        })?),
    };
    let stage = stages::diagnose::DiagnoseStage {
        model,
        effects: o.effects,
        folds: o.folds,
        mc_draws: o.mc_draws,
        seed: o.seed,
        hypotheses: o.hypotheses,
        ..Default::default()
    };
    if let Some(bad) = stage.validate().first() {
        return Err(input(bad.message.clone()));
    }
    if let Some(path) = &stage.hypotheses {
        ltcal::hypothesis::load(path)
            .map_err(|ps| Error::Input(ps.iter().map(|p| locate(p, None)).collect()))?;
    }
    stages::diagnose::remove_stale_temporaries(out, std::time::SystemTime::now());
    let c = campaign::read_for_diagnosis(campaign)
        .map_err(|e| campaign_error(&e, names.then_some(campaign)))?;
    ltcal::fs::check_replaceable(
        out,
        "a diagnosis",
        "diagnosis.csv",
        stages::diagnose::replaceable_folder_file,
    )
    .map_err(|why| input(format!("out: {why}")))?;
    let d = stage.diagnose(&c)?;
    let output = stages::diagnose::outputs(&d)?;
    let mut files: Vec<(String, Vec<u8>)> = Vec::new();
    let mut tables = Vec::new();
    for (name, df) in &output.tables {
        let bytes = ltcal::table::to_parquet_bytes(df)?;
        files.push((format!("{name}.parquet"), bytes.clone()));
        tables.push((name.clone(), bytes));
        if name == "where" {
            files.push(("where.csv".into(), ltcal::diagnose::output::csv(df)?));
        }
    }
    files.extend(output.files.iter().cloned());
    ltcal::fs::publish_folder(out, &files)?;
    Ok(Diagnosed {
        verdict: ltcal::diagnose::output::verdict(&d),
        tables,
        files: files.into_iter().map(|(n, _)| n).collect(),
    })
}

fn campaign_error(e: &campaign::CampaignError, names: Option<&Path>) -> Error {
    Error::Input(e.problems.iter().map(|p| locate(p, names)).collect())
}

/// A campaign folder as tables (readings, targets, gauge: Parquet bytes,
/// every optional column present) and campaign.toml as JSON.
pub fn read_campaign(dir: &Path) -> Result<(Tables, String)> {
    let c = campaign::read(dir).map_err(|e| campaign_error(&e, None))?;
    let mut tables = Vec::new();
    for (name, mut df) in c.to_tables()? {
        if name == "meta" {
            continue;
        }
        // Where each reading was read from: the file's business, not the data's.
        if df.get_column_names().iter().any(|n| n.as_str() == "line") {
            df = df.drop("line").map_err(|e| Error::Other(e.to_string()))?;
        }
        tables.push((name, ltcal::table::to_parquet_bytes(&df)?));
    }
    let text = std::fs::read_to_string(dir.join("campaign.toml"))
        .map_err(|e| Error::Other(format!("{}: {e}", dir.display())))?;
    let meta: serde_json::Value = toml::from_str(&text).map_err(|e| Error::Other(e.to_string()))?;
    Ok((tables, meta.to_string()))
}

/// Writes a campaign given as tables (name, Parquet bytes) and its meta
/// (campaign.toml as JSON) as the folder `dir`, held to the format's rules
/// exactly as a folder is read: the files are written to a scratch folder,
/// read back by the campaign reader (every problem named by table, row and
/// column), and only a campaign that reads is written to `dir`.
pub fn write_campaign(
    dir: &Path,
    tables: &[(String, Vec<u8>)],
    meta_json: &str,
    overwrite: bool,
) -> Result<()> {
    let scratch = std::env::temp_dir().join(format!(
        "ltcal-campaign-{}-{}",
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos())
    ));
    let result = (|| {
        let mut files: Vec<(String, Vec<u8>)> = Vec::new();
        for (name, bytes) in tables {
            if !["readings", "targets", "gauge"].contains(&name.as_str()) {
                return Err(input(format!(
                    "table `{name}`: a campaign's tables are readings, targets and gauge"
                )));
            }
            let df = ltcal::table::from_parquet_bytes(bytes)?;
            files.push((format!("{name}.csv"), ltcal::table::to_csv(&df)?));
        }
        let meta: serde_json::Value =
            serde_json::from_str(meta_json).map_err(|e| input(format!("meta: {e}")))?;
        let text = toml::to_string(&meta).map_err(|e| input(format!("meta: {e}")))?;
        files.push(("campaign.toml".into(), text.into_bytes()));
        ltcal::fs::publish_folder(&scratch, &files)?;
        let c = campaign::read(&scratch).map_err(|e| campaign_error(&e, Some(&scratch)))?;
        if overwrite {
            campaign::overwrite(&c, dir)?;
        } else {
            campaign::write(&c, dir)?;
        }
        Ok(())
    })();
    let _ = std::fs::remove_dir_all(&scratch);
    result
}

/// Runs `f`, a panic turned into an error: no panic crosses into Python.
pub fn caught<T>(f: impl FnOnce() -> anyhow::Result<T>) -> Result<T> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r.map_err(Error::from),
        Err(payload) => {
            let why = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "a panic".into());
            Err(Error::Other(format!(
                "internal error (a bug in ltcal): {why}"
            )))
        }
    }
}
