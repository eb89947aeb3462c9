//! Packs: many cache entries in one file, the way git packs loose objects.
//!
//! A sweep point's stages each make a cache entry, and a loose entry is a
//! folder of files (its tables, its figures, `manifest.json`): 22 files a
//! point for the noise sweep, 2.2 million for 100 000 points — the load a
//! parallel file system (Lustre, GPFS, CephFS) handles worst, since every
//! file is a metadata operation on one server. So the entries of a batch of
//! sweep points (a chunk of a local run, an array task on a cluster) are
//! written as **one pack**: `results/<pipeline>/.ltcal/packs/<name>.pack`,
//! built under a temporary name and published by one rename, so a reader
//! sees the whole pack or none — a task killed mid-write leaves no pack,
//! only its temporary file, which the next run removes.
//!
//! ```text
//! "LTCALPK1"
//! entry*        u32 manifest length, manifest JSON,
//!               then every table and file: u64 length, bytes (manifest order)
//! index         entries:  key [32], offset u64, length u64
//!               records:  point u32, stage (u32 length, UTF-8), key [32]
//!               failures: point u32, stage, reason (each u32 length, UTF-8)
//! trailer       index offset u64, index length u64, blake3(index) [32], "LTCALPKE"
//! ```
//!
//! An entry in a pack is read and verified exactly as a loose one (the
//! manifest belongs to its key, every table matches its hash), with one
//! positioned read instead of a file open per table. The index's hash
//! guards the offsets; a pack whose trailer or index does not check out is
//! not read at all (and reported), never half-trusted. A pack is opened
//! only as a regular file of at most [`MAX_PACK_BYTES`]
//! ([`crate::fs::open_regular_file`]: a FIFO or `/dev/zero` named `*.pack`
//! is refused, not waited on or read), and every positioned read lies
//! within the file's real length, whatever its index says.
//!
//! `records` are the stages that *ran* at each sweep point (what `explain`
//! compares with, 32 bytes a stage a point instead of a JSON record);
//! `failures` the stages that failed there and why — how a task on a
//! cluster tells the coordinator what went wrong at which point.

use anyhow::{Result, anyhow, bail};
use std::fs::File;
use std::os::unix::fs::FileExt as _;
use std::path::Path;

/// The largest pack ltcal opens: far beyond one (a pack holds a batch of
/// points, flushed every 256 points or second of work).
pub const MAX_PACK_BYTES: u64 = 1 << 40;

const MAGIC: &[u8; 8] = b"LTCALPK1";
const END: &[u8; 8] = b"LTCALPKE";
const TRAILER: usize = 8 + 8 + 32 + 8;
/// Nothing ltcal writes comes near: a bound on what a damaged length may ask for.
const MAX_INDEX_BYTES: u64 = 1 << 30;

/// A cache key as the 32 bytes its hex spells.
pub type Key = [u8; 32];

pub fn key_bytes(hex: &str) -> Option<Key> {
    if hex.len() != 64 {
        return None;
    }
    let mut out = [0u8; 32];
    for (i, o) in out.iter_mut().enumerate() {
        *o = u8::from_str_radix(hex.get(2 * i..2 * i + 2)?, 16).ok()?;
    }
    Some(out)
}

pub fn key_hex(k: &Key) -> String {
    k.iter().map(|b| format!("{b:02x}")).collect()
}

/// One entry's place in its pack.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Span {
    pub offset: u64,
    pub len: u64,
}

/// A stage that ran (or failed) at a sweep point.
#[derive(Clone, Debug, PartialEq)]
pub struct PointRecord {
    pub point: u32,
    pub stage: String,
    pub key: Key,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Failure {
    pub point: u32,
    pub stage: String,
    pub reason: String,
}

/// What a pack holds, read from its trailer.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Index {
    pub entries: Vec<(Key, Span)>,
    pub records: Vec<PointRecord>,
    pub failures: Vec<Failure>,
}

/// One entry as bytes: the manifest and, in its order, the tables' and the
/// files' bytes.
pub struct Blob<'a> {
    pub manifest: &'a [u8],
    pub parts: Vec<&'a [u8]>,
}

/// Builds a pack in memory; [`Builder::finish`] gives its bytes.
pub struct Builder {
    bytes: Vec<u8>,
    index: Index,
}

impl Default for Builder {
    fn default() -> Self {
        Builder {
            bytes: MAGIC.to_vec(),
            index: Index::default(),
        }
    }
}

impl Builder {
    pub fn is_empty(&self) -> bool {
        self.index.entries.is_empty()
            && self.index.records.is_empty()
            && self.index.failures.is_empty()
    }

    pub fn add(&mut self, key: Key, blob: &Blob) {
        let offset = self.bytes.len() as u64;
        self.bytes
            .extend_from_slice(&(blob.manifest.len() as u32).to_le_bytes());
        self.bytes.extend_from_slice(blob.manifest);
        for p in &blob.parts {
            self.bytes
                .extend_from_slice(&(p.len() as u64).to_le_bytes());
            self.bytes.extend_from_slice(p);
        }
        let len = self.bytes.len() as u64 - offset;
        self.index.entries.push((key, Span { offset, len }));
    }

    /// Adds an entry as the bytes [`read_span`] gave for it (already laid
    /// out as [`Builder::add`] lays one out): how a damaged pack's good
    /// entries move to a new pack unchanged.
    pub fn add_entry(&mut self, key: Key, entry: &[u8]) {
        let offset = self.bytes.len() as u64;
        self.bytes.extend_from_slice(entry);
        let len = entry.len() as u64;
        self.index.entries.push((key, Span { offset, len }));
    }

    pub fn record(&mut self, r: PointRecord) {
        self.index.records.push(r);
    }

    pub fn fail(&mut self, f: Failure) {
        self.index.failures.push(f);
    }

    /// The pack's bytes and its index.
    pub fn finish(mut self) -> (Vec<u8>, Index) {
        let index = encode_index(&self.index);
        let offset = self.bytes.len() as u64;
        self.bytes.extend_from_slice(&index);
        self.bytes.extend_from_slice(&offset.to_le_bytes());
        self.bytes
            .extend_from_slice(&(index.len() as u64).to_le_bytes());
        self.bytes
            .extend_from_slice(blake3::hash(&index).as_bytes());
        self.bytes.extend_from_slice(END);
        (self.bytes, self.index)
    }
}

fn put_str(out: &mut Vec<u8>, s: &str) {
    out.extend_from_slice(&(s.len() as u32).to_le_bytes());
    out.extend_from_slice(s.as_bytes());
}

fn encode_index(ix: &Index) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(&(ix.entries.len() as u64).to_le_bytes());
    for (k, s) in &ix.entries {
        out.extend_from_slice(k);
        out.extend_from_slice(&s.offset.to_le_bytes());
        out.extend_from_slice(&s.len.to_le_bytes());
    }
    out.extend_from_slice(&(ix.records.len() as u64).to_le_bytes());
    for r in &ix.records {
        out.extend_from_slice(&r.point.to_le_bytes());
        put_str(&mut out, &r.stage);
        out.extend_from_slice(&r.key);
    }
    out.extend_from_slice(&(ix.failures.len() as u64).to_le_bytes());
    for f in &ix.failures {
        out.extend_from_slice(&f.point.to_le_bytes());
        put_str(&mut out, &f.stage);
        put_str(&mut out, &f.reason);
    }
    out
}

/// Reads fields off a byte slice, every length checked against what is left.
struct Cursor<'a>(&'a [u8]);

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        if n > self.0.len() {
            bail!("the index ends early");
        }
        let (a, b) = self.0.split_at(n);
        self.0 = b;
        Ok(a)
    }
    fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into()?))
    }
    fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into()?))
    }
    fn key(&mut self) -> Result<Key> {
        Ok(self.take(32)?.try_into()?)
    }
    fn string(&mut self) -> Result<String> {
        let n = self.u32()? as usize;
        Ok(String::from_utf8(self.take(n)?.to_vec())?)
    }
    /// A count of items of at least `min` bytes each: never more than the
    /// bytes left could hold, so a damaged count cannot allocate.
    fn count(&mut self, min: usize) -> Result<usize> {
        let n = self.u64()?;
        if n > (self.0.len() / min) as u64 {
            bail!("the index counts more items than it holds");
        }
        Ok(n as usize)
    }
}

fn decode_index(bytes: &[u8], file_len: u64) -> Result<Index> {
    let mut c = Cursor(bytes);
    let mut ix = Index::default();
    for _ in 0..c.count(48)? {
        let key = c.key()?;
        let span = Span {
            offset: c.u64()?,
            len: c.u64()?,
        };
        if span
            .offset
            .checked_add(span.len)
            .is_none_or(|e| e > file_len)
        {
            bail!("an entry lies outside the pack");
        }
        ix.entries.push((key, span));
    }
    for _ in 0..c.count(40)? {
        ix.records.push(PointRecord {
            point: c.u32()?,
            stage: c.string()?,
            key: c.key()?,
        });
    }
    for _ in 0..c.count(12)? {
        ix.failures.push(Failure {
            point: c.u32()?,
            stage: c.string()?,
            reason: c.string()?,
        });
    }
    if !c.0.is_empty() {
        bail!("the index has trailing bytes");
    }
    Ok(ix)
}

/// Reads a pack's index, checking its trailer and its hash.
pub fn read_index(path: &Path) -> Result<Index> {
    open_index(path).map(|(ix, _)| ix)
}

/// [`read_index`], and the pack kept open: the entries it indexes are then
/// read by position through this file ([`read_span_at`],
/// [`read_manifest_at`]), not by opening the pack — and checking every
/// folder on its way for links — once per entry.
pub fn open_index(path: &Path) -> Result<(Index, File)> {
    let (f, len) = open(path)?;
    if len < (MAGIC.len() + TRAILER) as u64 {
        bail!("too short to be a pack");
    }
    let mut trailer = [0u8; TRAILER];
    f.read_exact_at(&mut trailer, len - TRAILER as u64)?;
    if &trailer[48..] != END {
        bail!("no pack trailer (not a pack, or truncated)");
    }
    let offset = u64::from_le_bytes(trailer[0..8].try_into()?);
    let n = u64::from_le_bytes(trailer[8..16].try_into()?);
    if n > MAX_INDEX_BYTES || offset.checked_add(n) != Some(len - TRAILER as u64) {
        bail!("the trailer's index position is wrong");
    }
    let mut index = vec![0u8; n as usize];
    f.read_exact_at(&mut index, offset)?;
    if blake3::hash(&index).as_bytes() != &trailer[16..48] {
        bail!("the index does not match its hash (corrupted)");
    }
    Ok((decode_index(&index, offset)?, f))
}

/// Opens a pack: a regular file of at most [`MAX_PACK_BYTES`]; its length.
fn open(path: &Path) -> Result<(File, u64)> {
    crate::fs::open_regular_file(path, MAX_PACK_BYTES).map_err(|e| anyhow!("{}", e.reason))
}

/// Opens a pack to read entries of it by position.
pub fn open_pack(path: &Path) -> Result<File> {
    open(path).map(|(f, _)| f)
}

/// Checks that `span` lies within the open pack `f` as it is now (a pack
/// cut short since its index was read).
fn within(f: &File, span: Span) -> Result<()> {
    let len = f.metadata()?.len();
    if span
        .offset
        .checked_add(span.len)
        .is_none_or(|end| end > len)
    {
        bail!("the entry lies beyond the pack's end (the pack was cut short)");
    }
    Ok(())
}

/// Reads one entry's bytes from a pack.
pub fn read_span(path: &Path, span: Span) -> Result<Vec<u8>> {
    let f = open_pack(path)?;
    within(&f, span)?;
    read_span_at(&f, span)
}

/// Reads one entry's bytes from an open pack. Its index bounded `span` by
/// the pack's length when it was read; a pack cut short since fails the
/// read (no length is asked per entry: a cached sweep reads thousands).
pub fn read_span_at(f: &File, span: Span) -> Result<Vec<u8>> {
    let mut buf = vec![0u8; span.len as usize];
    read_at(f, &mut buf, span.offset)?;
    Ok(buf)
}

/// Splits an entry's bytes into its manifest and `parts` parts.
pub fn split(bytes: &[u8], parts: impl FnOnce(&[u8]) -> Result<usize>) -> Result<Blob<'_>> {
    let mut c = Cursor(bytes);
    let n = c.u32()? as usize;
    let manifest = c.take(n).map_err(|_| anyhow!("the manifest ends early"))?;
    let count = parts(manifest)?;
    let mut out = Vec::with_capacity(count.min(1024));
    for _ in 0..count {
        let n = c.u64()?;
        if n > c.0.len() as u64 {
            bail!("a table ends early");
        }
        out.push(c.take(n as usize)?);
    }
    if !c.0.is_empty() {
        bail!("the entry has trailing bytes");
    }
    Ok(Blob {
        manifest,
        parts: out,
    })
}

/// Just the manifest of an entry: its length, then its bytes.
pub fn read_manifest(path: &Path, span: Span) -> Result<Vec<u8>> {
    let f = open_pack(path)?;
    within(&f, span)?;
    read_manifest_at(&f, span)
}

/// [`read_manifest`] from an open pack (as [`read_span_at`]).
pub fn read_manifest_at(f: &File, span: Span) -> Result<Vec<u8>> {
    if span.len < 4 {
        bail!("the manifest ends early");
    }
    let mut n = [0u8; 4];
    read_at(f, &mut n, span.offset)?;
    let n = u32::from_le_bytes(n) as u64;
    if n + 4 > span.len {
        bail!("the manifest ends early");
    }
    let mut buf = vec![0u8; n as usize];
    read_at(f, &mut buf, span.offset + 4)?;
    Ok(buf)
}

/// A positioned read of a whole buffer; the pack's end reached first is
/// said as such.
fn read_at(f: &File, buf: &mut [u8], offset: u64) -> Result<()> {
    f.read_exact_at(buf, offset).map_err(|e| {
        if e.kind() == std::io::ErrorKind::UnexpectedEof {
            anyhow!("the entry lies beyond the pack's end (the pack was cut short)")
        } else {
            e.into()
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pack_reads_back_what_was_added_and_a_flipped_index_byte_is_refused() {
        let mut b = Builder::default();
        let k = [7u8; 32];
        b.add(
            k,
            &Blob {
                manifest: b"{\"m\":1}",
                parts: vec![b"table one", b""],
            },
        );
        b.record(PointRecord {
            point: 3,
            stage: "calibration".into(),
            key: k,
        });
        b.fail(Failure {
            point: 4,
            stage: "evaluation".into(),
            reason: "singular".into(),
        });
        let (bytes, _) = b.finish();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.pack");
        std::fs::write(&path, &bytes).unwrap();
        let ix = read_index(&path).unwrap();
        assert_eq!(ix.entries.len(), 1);
        assert_eq!(ix.records[0].stage, "calibration");
        assert_eq!(ix.failures[0].reason, "singular");
        let blob = read_span(&path, ix.entries[0].1).unwrap();
        let parts = split(&blob, |_| Ok(2)).unwrap();
        assert_eq!(parts.manifest, b"{\"m\":1}");
        assert_eq!(parts.parts, vec![&b"table one"[..], &b""[..]]);
        assert_eq!(read_manifest(&path, ix.entries[0].1).unwrap(), b"{\"m\":1}");
        // Any damaged byte of the index or trailer: the pack is not read.
        for at in [bytes.len() - 60, bytes.len() - 40, bytes.len() - 1] {
            let mut bad = bytes.clone();
            bad[at] ^= 1;
            std::fs::write(&path, &bad).unwrap();
            assert!(read_index(&path).is_err(), "byte {at}");
        }
        std::fs::write(&path, &bytes[..bytes.len() - 1]).unwrap();
        assert!(read_index(&path).is_err());
    }

    /// Regression (issue 28, 4): a span was read as its index said, so a
    /// pack cut short after its index was read made a read past its end.
    /// Every positioned read lies within the pack's real length, and a
    /// FIFO named `*.pack` is refused without blocking.
    #[test]
    fn a_read_inside_a_pack_is_bounded_by_its_real_length() {
        let mut b = Builder::default();
        b.add(
            [1u8; 32],
            &Blob {
                manifest: b"{}",
                parts: vec![b"0123456789"],
            },
        );
        let (bytes, ix) = b.finish();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.pack");
        std::fs::write(&path, &bytes[..20]).unwrap();
        let span = ix.entries[0].1;
        let e = read_span(&path, span).unwrap_err().to_string();
        assert!(e.contains("beyond the pack's end"), "{e}");
        let huge = Span {
            offset: 8,
            len: u64::MAX - 4,
        };
        assert!(read_manifest(&path, huge).is_err());
        let fifo = dir.path().join("b.pack");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status();
        if made.is_ok_and(|s| s.success()) {
            let e = read_index(&fifo).unwrap_err().to_string();
            assert_eq!(e, "is a FIFO, not a regular file");
        }
    }

    #[test]
    fn keys_round_trip_through_hex() {
        let hex = blake3::hash(b"x").to_hex().to_string();
        assert_eq!(key_hex(&key_bytes(&hex).unwrap()), hex);
        assert!(key_bytes("zz").is_none());
    }
}
