//! Reading a campaign folder exactly as `campaign-format.md` (version 1)
//! defines it.
//!
//! Two passes. The first reads each file into what a [`Campaign`] can hold
//! and checks what is about the text itself: encoding, CSV shape, header,
//! required columns, number syntax, `face`, the keys and types of
//! campaign.toml; it remembers where every cell is. The second holds the
//! campaign to the format's rules ([`Campaign::check`], shared with the other
//! ways a campaign enters or leaves ltcal) and points each broken rule at its
//! `file:line:col` through those positions. Every problem is collected before
//! anything is returned, and a campaign with any problem is not returned at
//! all: nothing is half-read.
//!
//! Limits: a file of at most [`MAX_FILE_BYTES`] and [`MAX_ROWS`] data rows;
//! beyond either the file is refused (at its first excess row for rows).
//!
//! CSV is tokenized by `csv-core`, the parser under the `csv` crate, rather
//! than by `csv` itself: `csv` tells where a record starts but not where each
//! of its fields is, and every error must point at its cell. `csv-core`
//! reports how many input bytes each field took, so cells keep their exact
//! positions, quoted fields included.

use super::check::{Issue, Place, Table};
use super::{Aim, Campaign, CampaignReading, GaugeLength, Meta, Target, Tracker};
use crate::diagnostics::{Problem, Source, SourceError, toml_error};
use crate::kinematics::Face;
use csv_core::ReadFieldResult;
use nalgebra::Vector3;
use rayon::prelude::*;
use serde::Deserialize;
use std::collections::BTreeMap;
use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};
use toml::Spanned;

/// Why a campaign folder does not load: every problem found, in file order.
#[derive(Debug)]
pub struct CampaignError {
    pub dir: PathBuf,
    pub problems: Vec<Problem>,
}

/// Problems shown in full; a file broken on every line would bury the first
/// ones, which are what the user fixes first.
const SHOWN: usize = 20;

impl fmt::Display for CampaignError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let n = self.problems.len();
        write!(
            f,
            "the campaign in {} does not load ({n} problem{}):",
            self.dir.display(),
            if n == 1 { "" } else { "s" }
        )?;
        for p in self.problems.iter().take(SHOWN) {
            write!(f, "\n\n{p}")?;
        }
        if n > SHOWN {
            write!(f, "\n\n… and {} more", n - SHOWN)?;
        }
        Ok(())
    }
}

impl std::error::Error for CampaignError {}

/// Reads the campaign in `dir`; relative paths are relative to the current
/// directory.
pub fn read(dir: &Path) -> Result<Campaign, CampaignError> {
    read_checked(dir, Use::Format)
}

/// Reads the campaign in `dir` for a calibration or diagnosis: besides the
/// format's rules, what the format allows but a calibration cannot use
/// ([`Campaign::calibration_issues`]) is refused at its `file:line:col`.
pub fn read_for_calibration(dir: &Path) -> Result<Campaign, CampaignError> {
    read_checked(dir, Use::Calibration)
}

/// Reads the campaign in `dir` for a diagnosis: as [`read_for_calibration`],
/// and what a diagnosis cannot test against ([`Campaign::diagnosis_issues`]:
/// a stated noise of 0) refused at its `file:line:col` too.
pub fn read_for_diagnosis(dir: &Path) -> Result<Campaign, CampaignError> {
    read_checked(dir, Use::Diagnosis)
}

/// What the campaign is read for: each use refuses more than the last.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Use {
    Format,
    Calibration,
    Diagnosis,
}

fn read_checked(dir: &Path, usage: Use) -> Result<Campaign, CampaignError> {
    let fail = |problems| CampaignError {
        dir: dir.to_path_buf(),
        problems,
    };
    if !dir.is_dir() {
        return Err(fail(vec![Problem::file(
            dir,
            "not a folder: a campaign is a folder holding campaign.toml, readings.csv, \
             targets.csv and optionally gauge.csv",
        )]));
    }
    let mut problems = Vec::new();
    let meta = match load(&dir.join("campaign.toml"), true, &mut problems) {
        Some(src) => match parse_meta(&src) {
            Ok((meta, spans)) => Some((meta, spans, src)),
            Err(MetaError::Version(e)) => {
                // Another version may lay out every file differently: what
                // else the folder holds means nothing to this reader.
                return Err(fail(vec![Problem::At(e)]));
            }
            Err(MetaError::Other(e)) => {
                problems.push(Problem::At(e));
                None
            }
        },
        None => None,
    };
    let readings_src = load(&dir.join("readings.csv"), true, &mut problems);
    // Beyond the station limit, refused before a million rows are parsed.
    if usage >= Use::Calibration {
        if let Some(e) = readings_src.as_ref().and_then(station_beyond_limit) {
            return Err(fail(vec![Problem::At(e)]));
        }
    }
    let readings = readings_src
        .and_then(|s| Csv::parse(s, READINGS_COLUMNS, &mut problems))
        .and_then(|csv| parse_readings(csv, &mut problems));
    let targets = load(&dir.join("targets.csv"), true, &mut problems)
        .and_then(|s| Csv::parse(s, TARGETS_COLUMNS, &mut problems))
        .and_then(|csv| parse_targets(csv, &mut problems));
    let gauge = match load(&dir.join("gauge.csv"), false, &mut problems) {
        Some(s) => Csv::parse(s, GAUGE_COLUMNS, &mut problems)
            .and_then(|csv| parse_gauge(csv, &mut problems)),
        None => Some((Vec::new(), None)),
    };
    let (
        Some((meta, spans, toml_src)),
        Some((readings, readings_csv)),
        Some((targets, targets_csv)),
        Some((gauge, gauge_csv)),
    ) = (meta, readings, targets, gauge)
    else {
        return Err(fail(problems));
    };
    if !problems.is_empty() {
        return Err(fail(problems));
    }
    let campaign = Campaign {
        meta,
        readings,
        targets,
        gauge,
    };
    // Counts beyond ltcal's limits first, alone: the format's checks and
    // the rest are linear too, but need not run on what is refused anyway.
    let mut issues = if usage >= Use::Calibration {
        campaign.count_issues()
    } else {
        Vec::new()
    };
    if issues.is_empty() {
        issues = campaign.check();
    }
    if usage >= Use::Calibration && issues.is_empty() {
        issues = campaign.calibration_issues();
    }
    if usage >= Use::Diagnosis && issues.is_empty() {
        issues = campaign.diagnosis_issues();
    }
    if issues.is_empty() {
        return Ok(campaign);
    }
    let places = Places {
        toml: &toml_src,
        toml_spans: &spans,
        readings: &readings_csv,
        targets: &targets_csv,
        gauge: gauge_csv.as_ref(),
    };
    let mut located: Vec<(usize, usize, SourceError)> =
        issues.into_iter().map(|i| places.locate(i)).collect();
    located.sort_by_key(|(file, start, _)| (*file, *start));
    Err(fail(
        located
            .into_iter()
            .map(|(_, _, e)| Problem::At(e))
            .collect(),
    ))
}

/// The first reading of station [`super::MAX_STATIONS`] + 1, found by a
/// scan of the station column alone (the same message as
/// [`Campaign::count_issues`], which checks it again after the full parse).
/// `None` when the limit holds, or when the file is not plain enough to
/// scan (quotes): the full parse then decides.
fn station_beyond_limit(src: &Source) -> Option<SourceError> {
    let text: &str = &src.text;
    if text.contains('"') {
        return None;
    }
    let mut lines = text.split_inclusive('\n');
    let header = lines.next()?;
    let column = header
        .trim_end_matches(['\r', '\n'])
        .trim_start_matches('\u{feff}')
        .split(',')
        .position(|h| h.trim() == "station")?;
    let mut seen = std::collections::HashSet::new();
    let mut offset = header.len();
    for line in lines {
        let start = offset;
        offset += line.len();
        let row = line.trim_end_matches(['\r', '\n']);
        if row.trim().is_empty() {
            continue;
        }
        let mut at = start;
        let mut field = None;
        for (k, f) in row.split(',').enumerate() {
            if k == column {
                field = Some(f);
                break;
            }
            at += f.len() + 1;
        }
        let station = field?.trim();
        if seen.insert(station) && seen.len() > super::MAX_STATIONS {
            return Some(src.error(
                at..at + field?.len().max(1),
                format!(
                    "station {station} is station {}: valid per campaign-format.md, but ltcal \
                     calibrates and diagnoses at most {} stations (campaign::MAX_STATIONS; each \
                     station's pose is a block of the adjustment's dense part): split the campaign",
                    super::MAX_STATIONS + 1,
                    super::MAX_STATIONS
                ),
            ));
        }
    }
    None
}

/// The files of a campaign folder, all the reader ever looks at.
pub const FILES: [&str; 4] = ["campaign.toml", "readings.csv", "targets.csv", "gauge.csv"];

/// The largest campaign file ltcal reads: about ten million readings, far
/// beyond any campaign measured by hand, and still held in memory at once.
pub const MAX_FILE_BYTES: u64 = 1 << 30;

/// The most data rows a campaign file may hold (readings, targets or gauge
/// lengths). A million readings is about 100 MB of CSV — well inside
/// [`MAX_FILE_BYTES`] — and a diagnosis of 200 000 already takes minutes:
/// beyond this ltcal would run for hours or run out of memory holding every
/// cell, so the file is refused at its first excess row instead.
pub const MAX_ROWS: usize = 1_000_000;

/// The blake3 hash of what [`read`] would read in `dir`: each of [`FILES`]
/// by name, with its bytes or as absent. Two folders with the same hash read
/// the same; other files in the folder do not count.
pub fn content_hash(dir: &Path) -> std::io::Result<String> {
    let mut h = blake3::Hasher::new();
    for name in FILES {
        h.update(name.as_bytes());
        match crate::fs::read_regular_file(&dir.join(name), MAX_FILE_BYTES) {
            Ok(bytes) => {
                h.update(&(bytes.len() as u64).to_le_bytes());
                h.update(&bytes);
            }
            Err(e) if e.is_missing() => {
                h.update(b"\0absent");
            }
            Err(e) => return Err(std::io::Error::other(e)),
        }
    }
    Ok(h.finalize().to_hex().to_string())
}

/// A file's text: `None` (with a problem, if the file is required) when it
/// cannot be had. A UTF-8 byte-order mark is dropped so that columns count
/// as an editor shows them.
fn load(path: &Path, required: bool, problems: &mut Vec<Problem>) -> Option<Source> {
    let bytes = match crate::fs::read_regular_file(path, MAX_FILE_BYTES) {
        Ok(b) => b,
        Err(e) if e.is_missing() && !required => return None,
        Err(e) if e.is_missing() => {
            problems.push(Problem::file(
                path,
                "missing: a campaign needs campaign.toml, readings.csv and targets.csv",
            ));
            return None;
        }
        Err(e) => {
            problems.push(Problem::file(path, format!("cannot be read: {}", e.reason)));
            return None;
        }
    };
    let bytes = bytes
        .strip_prefix("\u{feff}".as_bytes())
        .unwrap_or(&bytes[..]);
    match std::str::from_utf8(bytes) {
        Ok(text) => Some(Source::new(path, text)),
        Err(e) => {
            // The text up to the bad byte is intact, so the position is exact;
            // the bad byte itself shows as one replacement character.
            let src = Source::new(path, String::from_utf8_lossy(bytes).into_owned());
            let at = e.valid_up_to();
            problems.push(Problem::At(src.error(
                at..at + char::REPLACEMENT_CHARACTER.len_utf8(),
                format!(
                    "not UTF-8: byte 0x{:02x} here is not valid UTF-8 (campaign files are UTF-8 text)",
                    bytes[at]
                ),
            )));
            None
        }
    }
}

// ---------------------------------------------------------------- numbers

/// A number cell: a plain decimal (`1234.5`, `-0.0012`, `1e-3`, also `+5`,
/// `.5`, `5.`, `1E3`) that is finite. `NaN`, `inf`, hexadecimal, thousands
/// separators and surrounding spaces are not plain decimals; an empty cell
/// is handled by the caller (it means "not known").
fn parse_number(text: &str) -> Result<f64, String> {
    // A plain decimal has no spaces and is neither NaN nor infinity, so the
    // tests below, which only choose the message, are for the rest (issue
    // 34: this runs for every number of a campaign).
    if is_plain_decimal(text) {
        return finite(text);
    }
    let plain = || {
        format!(
            "`{text}` is not a number (numbers are plain decimals like 1234.5, -0.0012 or 1e-3)"
        )
    };
    if text.trim() != text {
        return Err(format!(
            "`{text}` has spaces around it (numbers are plain decimals like 1234.5, written without spaces)"
        ));
    }
    // (Compared without case, not lowered into a new string: this runs
    // for every number of a campaign.)
    let unsigned = text.trim_start_matches(['+', '-']);
    if unsigned.eq_ignore_ascii_case("nan") {
        return Err("NaN is not a value (leave the cell empty for \"not known\")".into());
    }
    if unsigned.eq_ignore_ascii_case("inf") || unsigned.eq_ignore_ascii_case("infinity") {
        return Err(format!("`{text}` is not a finite number"));
    }
    Err(plain())
}

/// A plain decimal's value, if finite.
fn finite(text: &str) -> Result<f64, String> {
    // The grammar of [`is_plain_decimal`] is a subset of what
    // `f64::from_str` accepts.
    let v: f64 = text.parse().map_err(|_| {
        format!(
            "`{text}` is not a number (numbers are plain decimals like 1234.5, -0.0012 or 1e-3)"
        )
    })?;
    if v.is_infinite() {
        return Err(format!("`{text}` is too large: it is not a finite number"));
    }
    Ok(v)
}

/// `[+-]? (digits [. digits?] | . digits) ([eE] [+-]? digits)?`
fn is_plain_decimal(s: &str) -> bool {
    let b = s.as_bytes();
    let mut i = 0;
    let digits = |i: &mut usize| {
        let start = *i;
        while *i < b.len() && b[*i].is_ascii_digit() {
            *i += 1;
        }
        *i - start
    };
    if i < b.len() && (b[i] == b'+' || b[i] == b'-') {
        i += 1;
    }
    let mut mantissa = digits(&mut i);
    if i < b.len() && b[i] == b'.' {
        i += 1;
        mantissa += digits(&mut i);
    }
    if mantissa == 0 {
        return false;
    }
    if i < b.len() && (b[i] == b'e' || b[i] == b'E') {
        i += 1;
        if i < b.len() && (b[i] == b'+' || b[i] == b'-') {
            i += 1;
        }
        if digits(&mut i) == 0 {
            return false;
        }
    }
    i == b.len()
}

// ---------------------------------------------------------------- CSV

/// One cell: where its unquoted text sits in its file's [`Texts`] and its
/// bytes in the file.
#[derive(Clone, Debug)]
struct Cell {
    text: Range<usize>,
    span: Range<usize>,
}

/// Every cell's unquoted text of one file, end to end: one buffer instead
/// of a `String` per cell (a quarter of a million allocations for a
/// 24 000-reading campaign, issue 34).
struct Texts(String);

impl Texts {
    fn of(&self, cell: &Cell) -> &str {
        &self.0[cell.text.clone()]
    }
}

/// A CSV file: header, rows of exactly as many cells, and the text for errors.
struct Csv {
    src: Source,
    texts: Texts,
    header: Vec<Cell>,
    rows: Vec<Vec<Cell>>,
}

/// The columns campaign-format.md defines for each file; any other column
/// is ignored.
pub const READINGS_COLUMNS: &[&str] = &[
    "station",
    "target",
    "az_deg",
    "el_deg",
    "d_mm",
    "face",
    "time_s",
    "temperature_c",
    "pressure_hpa",
    "humidity_pct",
];
pub const TARGETS_COLUMNS: &[&str] = &[
    "target", "x_mm", "y_mm", "z_mm", "u_mm", "aim_x_mm", "aim_y_mm", "aim_z_mm",
];
pub const GAUGE_COLUMNS: &[&str] = &["target_a", "target_b", "distance_mm", "u_mm"];

impl Csv {
    /// Tokenizes a file and checks its shape: none of the `known` columns
    /// named twice in the header (a repeated unknown column is ignored like
    /// any unknown column), every row as wide as the header, every quote
    /// closed.
    fn parse(src: Source, known: &[&str], problems: &mut Vec<Problem>) -> Option<Csv> {
        let before = problems.len();
        let (records, texts) = tokenize(&src, problems);
        let mut records = records.into_iter();
        let Some(header) = records.next() else {
            problems.push(Problem::At(src.error(
                0..0,
                "the file is empty: it needs a header row naming its columns",
            )));
            return None;
        };
        let mut first: BTreeMap<&str, &Cell> = BTreeMap::new();
        for cell in header.iter().filter(|c| known.contains(&texts.of(c))) {
            if let Some(earlier) = first.insert(texts.of(cell), cell) {
                let (_, col) = src.line_col(earlier.span.start);
                problems.push(Problem::At(src.error(
                    cell.span.clone(),
                    format!(
                        "column `{}` appears twice in the header (first at column {col})",
                        texts.of(cell)
                    ),
                )));
            }
        }
        let width = header.len();
        let mut rows = Vec::new();
        for row in records {
            match row.len() {
                n if n < width => {
                    let end = row.last().map_or(0, |c| c.span.end);
                    problems.push(Problem::At(src.error(
                        end..end,
                        format!(
                            "this row has {n} field{} but the header has {width}: \
                             the file may be cut short, or a comma is missing",
                            if n == 1 { "" } else { "s" }
                        ),
                    )));
                }
                n if n > width => problems.push(Problem::At(src.error(
                    row[width].span.clone(),
                    format!("this row has {n} fields but the header has {width}"),
                ))),
                _ => rows.push(row),
            }
        }
        (problems.len() == before).then_some(Csv {
            src,
            texts,
            header,
            rows,
        })
    }

    fn text(&self, cell: &Cell) -> &str {
        self.texts.of(cell)
    }

    fn error(&self, span: Range<usize>, message: impl Into<String>) -> Problem {
        Problem::At(self.src.error(span, message))
    }
}

/// How many pieces a plain file is tokenized in: a fixed number, so that
/// the pieces are the same whatever the number of threads (any split gives
/// the same cells).
const TOKENIZE_PIECES: usize = 8;
/// The least size of a piece: a file smaller than eight of them is read
/// in one pass, cheaper than eight in parallel.
const TOKENIZE_PIECE_MIN_BYTES: usize = 16 * 1024;

/// Splits a file into records of cells, with their texts. A quote left
/// open is reported (it means a cut file: `csv-core` would silently run the
/// field to the end of the file), and its record dropped, as the width of
/// a cut record means nothing more.
///
/// A plain file — no quote, so that every line ending ends a record, and
/// too few line endings to pass [`MAX_ROWS`] — is tokenized in pieces
/// split after a line feed, in parallel: a reader starting after a line
/// feed is where the reader of the whole file stands there (at a record's
/// start, where blank lines are skipped), so the cells are the same (the
/// tokenizer was over a third of a 24 000-reading import, on one core;
/// issue 34).
fn tokenize(src: &Source, problems: &mut Vec<Problem>) -> (Vec<Vec<Cell>>, Texts) {
    let bytes = src.text.as_bytes();
    // The texts are UTF-8 (the file's text is a `String`; unquoting takes
    // only ASCII quotes out, and cells end at ASCII delimiters, pieces after
    // an ASCII line feed), so they are checked once, together, rather than
    // cell by cell (issue 34).
    let texts_of = |texts: Vec<u8>| {
        Texts(String::from_utf8(texts).expect("cells of UTF-8 text split at ASCII are UTF-8"))
    };
    let Some(pieces) = plain_pieces(bytes) else {
        let (records, texts) = tokenize_piece(src, 0..bytes.len(), problems);
        return (records, texts_of(texts));
    };
    let (records, texts) = tokenize_pieces(src, pieces, problems);
    (records, texts_of(texts))
}

/// The records of a plain file's `pieces` (see [`plain_pieces`]), each
/// tokenized on its own, in parallel, and joined in order; the pieces'
/// problems likewise (a plain piece has none: no quote can be left open in
/// it, and it holds fewer rows than the limit — but what a piece reports
/// is kept, not assumed away).
fn tokenize_pieces(
    src: &Source,
    pieces: Vec<Range<usize>>,
    problems: &mut Vec<Problem>,
) -> (Vec<Vec<Cell>>, Vec<u8>) {
    let parts: Vec<_> = pieces
        .into_par_iter()
        .map(|piece| {
            let mut found = Vec::new();
            let (records, texts) = tokenize_piece(src, piece, &mut found);
            (records, texts, found)
        })
        .collect();
    let mut records = Vec::with_capacity(parts.iter().map(|(r, _, _)| r.len()).sum());
    let mut texts: Vec<u8> = Vec::with_capacity(parts.iter().map(|(_, t, _)| t.len()).sum());
    for (part, part_texts, found) in parts {
        problems.extend(found);
        let shift = texts.len();
        texts.extend_from_slice(&part_texts);
        records.extend(part.into_iter().map(|mut record| {
            for cell in &mut record {
                cell.text = cell.text.start + shift..cell.text.end + shift;
            }
            record
        }));
    }
    (records, texts)
}

/// The byte ranges a plain file is tokenized in, each but the last ending
/// just after a line feed; `None` when the file is small, holds a quote,
/// or has more line endings than [`MAX_ROWS`] rows (then one pass finds
/// the first row too many, as a piece could not).
fn plain_pieces(bytes: &[u8]) -> Option<Vec<Range<usize>>> {
    if bytes.len() < TOKENIZE_PIECES * TOKENIZE_PIECE_MIN_BYTES || bytes.contains(&b'"') {
        return None;
    }
    let endings = bytes.iter().filter(|&&b| b == b'\n' || b == b'\r').count();
    if endings > MAX_ROWS {
        return None;
    }
    let mut pieces = Vec::with_capacity(TOKENIZE_PIECES);
    let mut start = 0;
    for k in 1..TOKENIZE_PIECES {
        let aim = (bytes.len() * k / TOKENIZE_PIECES).max(start);
        let Some(nl) = bytes[aim..].iter().position(|&b| b == b'\n') else {
            break;
        };
        let end = aim + nl + 1;
        pieces.push(start..end);
        start = end;
    }
    pieces.push(start..bytes.len());
    Some(pieces)
}

/// The records of `src`'s bytes in `range`, read from a record's start,
/// with their cells' texts (positions in the file; texts from 0).
fn tokenize_piece(
    src: &Source,
    range: Range<usize>,
    problems: &mut Vec<Problem>,
) -> (Vec<Vec<Cell>>, Vec<u8>) {
    let bytes = &src.text.as_bytes()[..range.end];
    let mut reader = csv_core::Reader::new();
    let mut out = vec![0u8; 1024];
    // Unquoting takes only quotes (ASCII) out of UTF-8 text: the cells'
    // texts together are at most the piece's size.
    let mut texts: Vec<u8> = Vec::with_capacity(range.len());
    let mut records = Vec::new();
    // A record as wide as the header, grown only for a wider row.
    let mut width = 0;
    let mut record: Vec<Cell> = Vec::new();
    let mut open_quote = false;
    let mut pos = range.start;
    loop {
        let start = pos;
        let mut written = 0;
        let record_end = loop {
            // Once the input is used up, the empty slice tells csv-core
            // that the file has ended.
            let (res, read, wrote) = reader.read_field(&bytes[pos..], &mut out[written..]);
            pos += read;
            written += wrote;
            match res {
                ReadFieldResult::InputEmpty => {}
                ReadFieldResult::OutputFull => out.resize(out.len() * 2, 0),
                ReadFieldResult::Field { record_end } => break Some(record_end),
                ReadFieldResult::End => break None,
            }
        };
        let Some(record_end) = record_end else {
            return (records, texts);
        };
        // A field's bytes run from where the previous one stopped to its
        // delimiter; at a record's start they include the line ending of the
        // previous record and any blank lines, which csv-core skips.
        let mut a = start;
        if record.is_empty() {
            while a < pos && matches!(bytes[a], b'\r' | b'\n') {
                a += 1;
            }
        }
        let mut b = pos;
        if record_end {
            if b > a && bytes[b - 1] == b'\n' {
                b -= 1;
            }
            if b > a && bytes[b - 1] == b'\r' {
                b -= 1;
            }
        } else if b > a && bytes[b - 1] == b',' {
            b -= 1;
        }
        let raw = &bytes[a..b];
        if raw.first() == Some(&b'"') && (raw.len() == 1 || raw.last() != Some(&b'"')) {
            open_quote = true;
            problems.push(Problem::At(src.error(
                a..a + 1,
                "this quoted field has no closing quote: the file may be cut short",
            )));
        }
        let t0 = texts.len();
        texts.extend_from_slice(&out[..written]);
        record.push(Cell {
            text: t0..texts.len(),
            span: a..b,
        });
        if record_end {
            width = width.max(record.len());
            let cells = std::mem::replace(&mut record, Vec::with_capacity(width));
            if !std::mem::take(&mut open_quote) {
                records.push(cells);
            }
            // The header and MAX_ROWS rows: one more row is refused here,
            // before the rest of the file is held as cells.
            if records.len() > MAX_ROWS + 1 {
                let row = records
                    .last()
                    .and_then(|r| r.first())
                    .map_or(a, |c| c.span.start);
                problems.push(Problem::At(src.error(
                    row..row,
                    format!(
                        "more than {MAX_ROWS} rows: ltcal reads at most {MAX_ROWS} rows per \
                         campaign file (about one million readings; a bundle adjustment of \
                         that many already takes minutes)"
                    ),
                )));
                return (records, texts);
            }
        }
    }
}

/// The header of one file: which column is where.
struct Columns<'a> {
    csv: &'a Csv,
    index: BTreeMap<&'a str, usize>,
}

impl<'a> Columns<'a> {
    fn new(csv: &'a Csv) -> Columns<'a> {
        let index = csv
            .header
            .iter()
            .enumerate()
            .map(|(i, c)| (csv.text(c), i))
            .collect();
        Columns { csv, index }
    }

    fn optional(&self, name: &str) -> Option<usize> {
        self.index.get(name).copied()
    }

    /// A required column.
    fn require(&self, name: &str, problems: &mut Vec<Problem>) -> Option<usize> {
        if let Some(i) = self.optional(name) {
            return Some(i);
        }
        let file = file_name(&self.csv.src);
        // A header cell that is the name but for case or spaces is surely
        // meant as it: point there. Otherwise at the header as a whole.
        let near = self
            .csv
            .header
            .iter()
            .find(|c| self.csv.text(c).trim().eq_ignore_ascii_case(name));
        let (span, hint) = match near {
            Some(c) => (
                c.span.clone(),
                format!(
                    "; the header has `{}` — column names are exact",
                    self.csv.text(c)
                ),
            ),
            None => {
                let end = self.csv.header.last().map_or(0, |c| c.span.end);
                (0..end, String::new())
            }
        };
        problems.push(self.csv.error(
            span,
            format!("{file} lacks the required column `{name}`{hint}"),
        ));
        None
    }

    /// Three columns that go together (`x_mm`, `y_mm`, `z_mm`): all or none.
    fn triple(&self, names: [&str; 3], problems: &mut Vec<Problem>) -> Option<[usize; 3]> {
        let found = names.map(|n| self.optional(n));
        if found.iter().all(Option::is_none) {
            return None;
        }
        if let [Some(x), Some(y), Some(z)] = found {
            return Some([x, y, z]);
        }
        let (have, lack): (Vec<_>, Vec<_>) =
            names.iter().zip(found).partition(|(_, f)| f.is_some());
        let at = have[0].1.map_or(0..0, |i| self.csv.header[i].span.clone());
        let list = |v: Vec<(&&str, Option<usize>)>| {
            v.iter()
                .map(|(n, _)| format!("`{n}`"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        problems.push(self.csv.error(
            at,
            format!(
                "{} has {} but not {}: {} go together",
                file_name(&self.csv.src),
                list(have),
                list(lack),
                names.join(", ")
            ),
        ));
        None
    }
}

fn file_name(src: &Source) -> String {
    src.path.file_name().map_or_else(
        || src.path.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    )
}

/// The typed cells of one row, collecting what is wrong with them.
struct RowCells<'a> {
    csv: &'a Csv,
    row: &'a [Cell],
    problems: Vec<Problem>,
}

impl<'a> RowCells<'a> {
    fn new(csv: &'a Csv, row: &'a [Cell]) -> RowCells<'a> {
        RowCells {
            csv,
            row,
            problems: Vec::new(),
        }
    }

    fn text(&self, col: usize) -> String {
        self.csv.text(&self.row[col]).to_string()
    }

    /// Whether cell `col` is empty.
    fn empty(&self, col: usize) -> bool {
        self.row[col].text.is_empty()
    }

    /// The name of column `col`, as the header has it.
    fn name(&self, col: usize) -> &'a str {
        self.csv.text(&self.csv.header[col])
    }

    fn number(&mut self, col: usize) -> Option<f64> {
        let (csv, row) = (self.csv, self.row);
        let cell = &row[col];
        if cell.text.is_empty() {
            let name = self.name(col);
            self.problems.push(csv.error(
                cell.span.clone(),
                format!("`{name}` is required, but this cell is empty"),
            ));
            return None;
        }
        self.parse(col)
    }

    /// `None` for an absent column or an empty cell (not known) — and for a
    /// bad cell, which is then reported.
    fn opt_number(&mut self, col: Option<usize>) -> Option<f64> {
        let col = col?;
        if self.empty(col) {
            return None;
        }
        self.parse(col)
    }

    fn parse(&mut self, col: usize) -> Option<f64> {
        let (csv, row) = (self.csv, self.row);
        let cell = &row[col];
        match parse_number(csv.text(cell)) {
            Ok(v) => Some(v),
            Err(m) => {
                let name = self.name(col);
                self.problems
                    .push(csv.error(cell.span.clone(), format!("`{name}`: {m}")));
                None
            }
        }
    }

    /// Three optional numbers that go together: all known or all empty.
    fn opt_vector(&mut self, cols: Option<[usize; 3]>) -> Option<Vector3<f64>> {
        let cols = cols?;
        let empty = cols.map(|c| self.empty(c));
        if empty.iter().all(|e| *e) {
            return None;
        }
        if let Some(k) = empty.iter().position(|e| *e) {
            let names = cols.map(|c| self.name(c));
            self.problems.push(self.csv.error(
                self.row[cols[k]].span.clone(),
                format!(
                    "`{}` is empty but other coordinates of this point are given: {} go together",
                    names[k],
                    names.join(", ")
                ),
            ));
            return None;
        }
        let [x, y, z] = cols.map(|c| self.parse(c));
        Some(Vector3::new(x?, y?, z?))
    }

    fn face(&mut self, col: Option<usize>) -> Face {
        let Some(col) = col else {
            return Face::Front;
        };
        let (csv, row) = (self.csv, self.row);
        let cell = &row[col];
        match csv.text(cell) {
            "" | "1" => Face::Front,
            "2" => Face::Back,
            other => {
                self.problems.push(csv.error(
                    cell.span.clone(),
                    format!("`face` is 1 (front) or 2 (back), got `{other}`"),
                ));
                Face::Front
            }
        }
    }

    /// The row's value, or its problems.
    fn finish<T>(self, value: Option<T>, problems: &mut Vec<Problem>) -> Option<T> {
        if self.problems.is_empty() {
            value
        } else {
            problems.extend(self.problems);
            None
        }
    }
}

/// Rows into values; `None` when any row has a problem. Each row is its
/// own: parsed in parallel, the values and problems then taken in row
/// order (the same whatever the number of threads; issue 34).
fn rows<T: Send>(
    csv: &Csv,
    problems: &mut Vec<Problem>,
    parse_row: impl Fn(&mut RowCells) -> Option<T> + Sync,
) -> Option<Vec<T>> {
    let parsed: Vec<Result<T, Vec<Problem>>> = csv
        .rows
        .par_iter()
        .with_min_len(1024)
        .map(|row| {
            let mut cells = RowCells::new(csv, row);
            let value = parse_row(&mut cells);
            let mut own = Vec::new();
            cells.finish(value, &mut own).ok_or(own)
        })
        .collect();
    let mut out = Vec::with_capacity(parsed.len());
    let mut ok = true;
    for row in parsed {
        match row {
            Ok(v) => out.push(v),
            Err(own) => {
                problems.extend(own);
                ok = false;
            }
        }
    }
    ok.then_some(out)
}

fn parse_readings(csv: Csv, problems: &mut Vec<Problem>) -> Option<(Vec<CampaignReading>, Csv)> {
    let c = Columns::new(&csv);
    let required =
        ["station", "target", "az_deg", "el_deg", "d_mm"].map(|n| c.require(n, problems));
    let [Some(station), Some(target), Some(az), Some(el), Some(d)] = required else {
        return None;
    };
    let face = c.optional("face");
    let [time, temperature, pressure, humidity] =
        ["time_s", "temperature_c", "pressure_hpa", "humidity_pct"].map(|n| c.optional(n));
    // Each record's line, from one pass over the line starts (a search
    // per record: `Source::line_col` from the top would cost the file's
    // length per record).
    let newlines: Vec<usize> = csv
        .src
        .text
        .bytes()
        .enumerate()
        .filter_map(|(i, b)| (b == b'\n').then_some(i))
        .collect();
    let readings = rows(&csv, problems, |r| {
        let line = r
            .row
            .first()
            .map(|cell| newlines.partition_point(|&n| n < cell.span.start) + 1);
        let (az, el, d) = (r.number(az), r.number(el), r.number(d));
        let face = r.face(face);
        let (time_s, temperature_c, pressure_hpa, humidity_pct) = (
            r.opt_number(time),
            r.opt_number(temperature),
            r.opt_number(pressure),
            r.opt_number(humidity),
        );
        Some(CampaignReading {
            station: r.text(station),
            target: r.text(target),
            az_deg: az?,
            el_deg: el?,
            d_mm: d?,
            face,
            time_s,
            temperature_c,
            pressure_hpa,
            humidity_pct,
            line,
        })
    })?;
    Some((readings, csv))
}

fn parse_targets(csv: Csv, problems: &mut Vec<Problem>) -> Option<(Vec<Target>, Csv)> {
    let c = Columns::new(&csv);
    let before = problems.len();
    let id = c.require("target", problems);
    let reference = c.triple(["x_mm", "y_mm", "z_mm"], problems);
    let u = c.optional("u_mm");
    // With `[smr] aim = "aim-columns"`, a target without its aim point has
    // an SMR axis that is not known (campaign-format.md: a missing optional
    // column and an empty cell both mean "not known").
    let aim_cols = c.triple(["aim_x_mm", "aim_y_mm", "aim_z_mm"], problems);
    let id = id?;
    if problems.len() > before {
        return None;
    }
    let targets = rows(&csv, problems, |r| {
        let reference = r.opt_vector(reference);
        let u_mm = r.opt_number(u);
        let aim = r.opt_vector(aim_cols);
        Some(Target {
            id: r.text(id),
            reference,
            u_mm,
            aim,
        })
    })?;
    Some((targets, csv))
}

fn parse_gauge(csv: Csv, problems: &mut Vec<Problem>) -> Option<(Vec<GaugeLength>, Option<Csv>)> {
    let c = Columns::new(&csv);
    let required = ["target_a", "target_b", "distance_mm"].map(|n| c.require(n, problems));
    let [Some(a), Some(b), Some(distance)] = required else {
        return None;
    };
    let u = c.optional("u_mm");
    let gauge = rows(&csv, problems, |r| {
        let distance_mm = r.number(distance);
        let u_mm = r.opt_number(u);
        Some(GaugeLength {
            target_a: r.text(a),
            target_b: r.text(b),
            distance_mm: distance_mm?,
            u_mm,
        })
    })?;
    Some((gauge, Some(csv)))
}

// ---------------------------------------------------------------- campaign.toml

#[derive(Deserialize)]
struct Version {
    format: Option<Spanned<toml::Value>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MetaFile {
    // Checked before this struct is read; named so that the key is known.
    #[serde(rename = "format")]
    _format: serde::de::IgnoredAny,
    name: Spanned<String>,
    description: Option<String>,
    tracker: TrackerFile,
    smr: SmrFile,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TrackerFile {
    model: Spanned<String>,
    sigma_angle_urad: Option<Spanned<f64>>,
    sigma_range_um: Option<Spanned<f64>>,
    sigma_range_ppm: Option<Spanned<f64>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SmrFile {
    aim: Spanned<String>,
    radius_mm: Option<Spanned<f64>>,
}

enum MetaError {
    /// Not format 1: nothing else can be read.
    Version(SourceError),
    Other(SourceError),
}

/// The span of every campaign.toml value, by dotted key.
type Spans = BTreeMap<&'static str, Range<usize>>;

fn parse_meta(src: &Source) -> Result<(Meta, Spans), MetaError> {
    let text = &src.text;
    let version: Version =
        toml::from_str(text).map_err(|e| MetaError::Other(toml_error(src, e, 0..0)))?;
    let format = version.format.ok_or_else(|| {
        MetaError::Version(src.error(
            0..0,
            "campaign.toml has no `format`: a campaign file starts with `format = 1`",
        ))
    })?;
    match format.get_ref() {
        toml::Value::Integer(1) => {}
        toml::Value::Integer(n) => {
            return Err(MetaError::Version(src.error(
                format.span(),
                format!("format {n} is not supported: this ltcal reads campaign format 1"),
            )));
        }
        _ => {
            return Err(MetaError::Version(src.error(
                format.span(),
                "`format` is the integer 1 (the version of the campaign format)",
            )));
        }
    }
    let file: MetaFile =
        toml::from_str(text).map_err(|e| MetaError::Other(toml_error(src, e, 0..0)))?;
    let aim = Aim::parse(file.smr.aim.get_ref()).ok_or_else(|| {
        MetaError::Other(src.error(
            file.smr.aim.span(),
            format!(
                "[smr] aim is \"aim-columns\" or \"stations-centroid\", got \"{}\"",
                file.smr.aim.get_ref()
            ),
        ))
    })?;
    let mut spans = Spans::new();
    spans.insert("format", format.span());
    spans.insert("name", file.name.span());
    spans.insert("tracker.model", file.tracker.model.span());
    spans.insert("smr.aim", file.smr.aim.span());
    let mut value = |key: &'static str, v: Option<Spanned<f64>>| {
        v.map(|s| {
            spans.insert(key, s.span());
            s.into_inner()
        })
    };
    let t = file.tracker;
    let tracker = Tracker {
        model: t.model.into_inner(),
        sigma_angle_urad: value("tracker.sigma_angle_urad", t.sigma_angle_urad),
        sigma_range_um: value("tracker.sigma_range_um", t.sigma_range_um),
        sigma_range_ppm: value("tracker.sigma_range_ppm", t.sigma_range_ppm),
    };
    let smr_radius_mm = value("smr.radius_mm", file.smr.radius_mm);
    let meta = Meta {
        format: 1,
        name: file.name.into_inner(),
        description: file.description.unwrap_or_default(),
        tracker,
        aim,
        smr_radius_mm,
    };
    Ok((meta, spans))
}

// ---------------------------------------------------------------- locating issues

/// Where each part of a read campaign came from.
struct Places<'a> {
    toml: &'a Source,
    toml_spans: &'a Spans,
    readings: &'a Csv,
    targets: &'a Csv,
    gauge: Option<&'a Csv>,
}

impl Places<'_> {
    /// The issue as an error in its file, with the file's rank and the
    /// offset to sort by.
    fn locate(&self, issue: Issue) -> (usize, usize, SourceError) {
        let (rank, src, span) = match issue.place {
            Place::Meta(key) => (
                0,
                self.toml,
                self.toml_spans.get(key).cloned().unwrap_or(0..0),
            ),
            Place::Table(t) => {
                let (rank, csv) = self.csv(t);
                let end = csv.src.text.len();
                (rank, &csv.src, end..end)
            }
            Place::Cell { table, row, column } => {
                let (rank, csv) = self.csv(table);
                let cells = &csv.rows[row];
                let span = match Columns::new(csv).optional(column) {
                    Some(i) => cells[i].span.clone(),
                    None => cells[0].span.start..cells[0].span.start,
                };
                (rank, &csv.src, span)
            }
        };
        (rank, span.start, src.error(span, issue.message))
    }

    fn csv(&self, t: Table) -> (usize, &Csv) {
        match t {
            Table::Readings => (1, self.readings),
            Table::Targets => (2, self.targets),
            Table::Gauge => (
                3,
                self.gauge
                    .expect("a gauge issue comes from a gauge row, so gauge.csv was read"),
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plain_decimals_parse_exactly() {
        for (text, v) in [
            ("1234.5", 1234.5),
            ("-0.0012", -0.0012),
            ("1e-3", 1e-3),
            ("0", 0.0),
            ("+5", 5.0),
            (".5", 0.5),
            ("5.", 5.0),
            ("1E3", 1000.0),
            ("-2.5e+2", -250.0),
            ("4610.10042", 4610.10042),
            ("0.1", 0.1),
        ] {
            assert_eq!(parse_number(text), Ok(v), "{text}");
        }
        assert!(parse_number("-0").unwrap().is_sign_negative());
    }

    #[test]
    fn what_is_not_a_plain_decimal_is_refused_with_a_reason() {
        for (text, phrase) in [
            ("NaN", "NaN is not a value"),
            ("nan", "NaN is not a value"),
            ("-NaN", "NaN is not a value"),
            ("inf", "not a finite number"),
            ("-Infinity", "not a finite number"),
            ("1e999", "too large"),
            (" 1.5", "spaces around it"),
            ("1.5 ", "spaces around it"),
            ("abc", "is not a number"),
            ("1,5", "is not a number"),
            ("0x10", "is not a number"),
            ("1_000", "is not a number"),
            ("1e", "is not a number"),
            (".", "is not a number"),
            ("-", "is not a number"),
            ("e5", "is not a number"),
            ("1.2.3", "is not a number"),
            ("--1", "is not a number"),
        ] {
            let e = parse_number(text).unwrap_err();
            assert!(e.contains(phrase), "{text}: {e}");
        }
    }

    #[test]
    fn shortest_round_trip_display_parses_back_to_the_same_bits() {
        use proptest::prelude::*;
        proptest!(|(bits in any::<u64>())| {
            let v = f64::from_bits(bits);
            prop_assume!(v.is_finite());
            prop_assert_eq!(parse_number(&v.to_string()).map(f64::to_bits), Ok(bits));
        });
    }

    fn cells(text: &str) -> Vec<Vec<(String, String)>> {
        let src = Source::new("t.csv", text);
        let mut problems = Vec::new();
        let (records, texts) = tokenize(&src, &mut problems);
        assert!(problems.is_empty(), "{problems:?}");
        records
            .into_iter()
            .map(|r| {
                r.into_iter()
                    .map(|c| (texts.of(&c).to_string(), text[c.span].to_string()))
                    .collect()
            })
            .collect()
    }

    #[test]
    fn cells_keep_their_exact_place_with_quotes_crlf_and_blank_lines() {
        let r = cells("a,b\r\nc,\"d,\"\"x\"\"\"\n\n\ne,\n");
        let pairs = |v: &[(&str, &str)]| -> Vec<(String, String)> {
            v.iter()
                .map(|(a, b)| (a.to_string(), b.to_string()))
                .collect()
        };
        assert_eq!(r[0], pairs(&[("a", "a"), ("b", "b")]));
        assert_eq!(r[1], pairs(&[("c", "c"), ("d,\"x\"", "\"d,\"\"x\"\"\"")]));
        assert_eq!(r[2], pairs(&[("e", "e"), ("", "")]));
        assert_eq!(r.len(), 3);
        // The last line without its newline is a whole record.
        assert_eq!(cells("a,b\n1,2")[1], pairs(&[("1", "1"), ("2", "2")]));
    }

    /// A plain file tokenized in pieces split after any of its line feeds
    /// gives the cells of one pass over it: texts, places and records, with
    /// CR, CRLF, blank lines, empty cells, multi-byte text and a last line
    /// with or without its ending.
    #[test]
    fn a_plain_file_tokenized_in_pieces_is_the_file_tokenized_in_one_pass() {
        use proptest::prelude::*;
        let piece = "[a1é,\\.\\- ]{0,6}";
        let line = prop::collection::vec(piece, 1..4).prop_map(|c| c.join(","));
        let ending = prop::sample::select(vec!["\n", "\r\n", "\r", "\n\n", "\r\n\r\n"]);
        let lines = prop::collection::vec((line, ending), 1..40);
        proptest!(|(lines in lines, last in any::<bool>(), cuts in prop::collection::vec(any::<prop::sample::Index>(), 0..6))| {
            let mut text: String = lines.iter().map(|(l, e)| format!("{l}{e}")).collect();
            if !last {
                text.pop();
            }
            let src = Source::new("t.csv", text.as_str());
            let feeds: Vec<usize> = text.match_indices('\n').map(|(i, _)| i + 1).collect();
            let mut ends: Vec<usize> = cuts
                .iter()
                .filter(|_| !feeds.is_empty())
                .map(|c| feeds[c.index(feeds.len())])
                .collect();
            ends.sort();
            ends.dedup();
            let mut pieces = Vec::new();
            let mut start = 0;
            for end in ends {
                pieces.push(start..end);
                start = end;
            }
            pieces.push(start..text.len());
            let mut problems = Vec::new();
            let (whole, whole_texts) = tokenize_piece(&src, 0..text.len(), &mut problems);
            let (split, split_texts) = tokenize_pieces(&src, pieces, &mut problems);
            prop_assert!(problems.is_empty());
            let show = |records: &[Vec<Cell>], texts: &[u8]| -> Vec<Vec<(Vec<u8>, Range<usize>)>> {
                records
                    .iter()
                    .map(|r| r.iter().map(|c| (texts[c.text.clone()].to_vec(), c.span.clone())).collect())
                    .collect()
            };
            prop_assert_eq!(show(&whole, &whole_texts), show(&split, &split_texts));
            prop_assert_eq!(whole_texts, split_texts);
        });
    }

    #[test]
    fn plain_pieces_end_after_line_feeds_and_cover_the_file() {
        let row = "S01,T0001,12.345678901,-3.210987654,12345.678901,1\n";
        let text = format!(
            "station,target,az_deg,el_deg,d_mm,face\n{}",
            row.repeat(20_000)
        );
        let pieces = plain_pieces(text.as_bytes()).expect("a large plain file is split");
        assert_eq!(pieces.len(), TOKENIZE_PIECES);
        assert_eq!(pieces[0].start, 0);
        assert_eq!(pieces.last().unwrap().end, text.len());
        for w in pieces.windows(2) {
            assert_eq!(w[0].end, w[1].start);
            assert_eq!(text.as_bytes()[w[0].end - 1], b'\n');
        }
        // A quote anywhere, or a small file: one pass.
        assert!(plain_pieces(format!("{text}\"x\"\n").as_bytes()).is_none());
        assert!(plain_pieces(&text.as_bytes()[..1000]).is_none());
        let src = Source::new("t.csv", text.as_str());
        let mut problems = Vec::new();
        let (records, texts) = tokenize(&src, &mut problems);
        assert!(problems.is_empty());
        assert_eq!(records.len(), 20_001);
        assert_eq!(texts.of(&records[20_000][4]), "12345.678901");
        assert_eq!(&text[records[20_000][4].span.clone()], "12345.678901");
    }

    #[test]
    fn an_open_quote_at_the_end_is_a_cut_file() {
        let src = Source::new("t.csv", "a,b\n1,\"2");
        let mut problems = Vec::new();
        tokenize(&src, &mut problems);
        assert_eq!(problems.len(), 1);
        assert_eq!(problems[0].location(), "t.csv:2:3");
    }
}
