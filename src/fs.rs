//! The file-system primitives every other module uses, written once.
//!
//! - [`write_atomic`]: a file appears whole or not at all — a temporary file
//!   beside it, synced, then renamed over it — so a killed run never leaves a
//!   torn figure, table or record behind.
//! - [`temp_name`]: a name no other writer in any process uses, for the
//!   temporary file or folder that is renamed into place. Its form
//!   (`<pid>-<n>-<host>`) lets a later run tell which temporaries belong to
//!   a process that has ended and may be removed ([`temp_owner_gone`]) —
//!   and, on a cluster's shared folder, leave alone those of processes on
//!   other machines, whose liveness it cannot see.
//! - [`StagedFolder`]: a folder (a cache entry, a campaign, a diagnosis)
//!   built under a temporary name and published by one rename, so a full
//!   disk or a kill never leaves a partial folder that looks finished;
//!   [`publish_folder`] is its common use, replacing the folder there.
//! - [`read_regular_file`] (and [`open_regular_file`] for positioned
//!   reads): the one way to read a file the runner did not just write — a
//!   pipeline, a campaign, a cache entry, a pack, a published table — read
//!   only if it is a regular file of at most a size its kind allows, opened
//!   with `O_NONBLOCK`: a FIFO would block the run forever, `/dev/zero`
//!   would fill memory.
//! - [`confine`]: a folder ltcal owns (`results/<pipeline>`). Below it
//!   nothing is read or written through a symbolic link — a link there is
//!   refused with an error that names it, never followed — so a link cannot
//!   make a run write its tables or packs, or read its cache, outside the
//!   results folder. (The results folder itself, and what the user names
//!   with `--out` or `path`, may be links: the user chose them.)
//! - [`check_replaceable`]: a folder is replaced whole only when it is
//!   recognisably one ltcal wrote (its marker file, and nothing it would
//!   not write): `diagnose --out` and `export_campaign`'s `overwrite` never
//!   delete a user's files.

use anyhow::{Context as _, Result, anyhow};
use std::fmt;
use std::io::{Read as _, Write as _};
use std::path::{Path, PathBuf};
use std::sync::RwLock;
use std::sync::atomic::{AtomicU64, Ordering};

/// The folders ltcal owns ([`confine`]).
static TREES: RwLock<Vec<PathBuf>> = RwLock::new(Vec::new());

/// Declares `tree` (a pipeline's results folder) a folder ltcal owns: from
/// now on no read or write of this process below it goes through a
/// symbolic link — `tree` itself included, the folders above it not.
pub fn confine(tree: &Path) {
    let mut trees = TREES.write().unwrap_or_else(|e| e.into_inner());
    if !trees.iter().any(|t| t == tree) {
        trees.push(tree.to_path_buf());
    }
}

/// The first symbolic link on the way to `path` (`path` itself included)
/// below a folder ltcal owns, if any. Components that do not exist end the
/// walk: nothing below them exists either.
pub fn link_on_the_way(path: &Path) -> Option<PathBuf> {
    let trees = TREES.read().unwrap_or_else(|e| e.into_inner());
    let tree = trees.iter().find(|t| path.starts_with(t))?;
    let mut at = tree.clone();
    let rest = path.strip_prefix(tree).ok()?;
    for part in std::iter::once(None).chain(rest.components().map(Some)) {
        if let Some(part) = part {
            at.push(part);
        }
        match std::fs::symlink_metadata(&at) {
            Ok(m) if m.file_type().is_symlink() => return Some(at),
            Ok(_) => {}
            Err(_) => return None,
        }
    }
    None
}

/// Fails, naming the link, when `path` lies below a folder ltcal owns
/// through a symbolic link.
pub fn refuse_links(path: &Path) -> Result<()> {
    match link_on_the_way(path) {
        None => Ok(()),
        Some(link) => Err(link_error(&link)),
    }
}

fn link_error(link: &Path) -> anyhow::Error {
    let target = std::fs::read_link(link)
        .map(|t| format!(" (to {})", t.display()))
        .unwrap_or_default();
    anyhow!(
        "{} is a symbolic link{target}: ltcal neither writes nor reads through a link inside \
         the results folder — remove the link (the next run makes a real folder there)",
        link.display()
    )
}

/// `create_dir_all` that never creates through a link below a folder ltcal
/// owns: checked before (an existing link is refused, nothing created
/// beyond it) and after (a link made meanwhile).
pub fn create_dirs(dir: &Path) -> Result<()> {
    refuse_links(dir)?;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    refuse_links(dir)
}

/// `<pid>-<n>-<host>`: unique among every writer of every process on
/// every machine sharing the folder.
pub fn temp_name() -> String {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    format!(
        "{}-{}-{}",
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed),
        host()
    )
}

/// This machine's name as it is (for messages).
pub fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .or_else(|_| std::env::var("HOSTNAME"))
        .map(|h| h.trim().to_string())
        .unwrap_or_default()
}

/// This machine in temporary names: the first 12 hex digits of the blake3
/// of its name — letters and digits only (it sits inside names split at
/// `-` and `.`), and two machines' names do not collide the way they
/// would with their other characters dropped (`r1-12`, `r11-2`).
pub fn host() -> &'static str {
    static HOST: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    HOST.get_or_init(|| blake3::hash(host_name().as_bytes()).to_hex()[..12].to_string())
}

/// Whether the process that made `name` — a [`temp_name`], possibly
/// followed by more text — has ended: only ever for a process of this
/// machine (another machine's processes cannot be seen from here, and a
/// temporary of a live one must not be taken away from it). Names of
/// another form are not ours and are left.
pub fn temp_owner_gone(name: &str) -> bool {
    let mut parts = name.splitn(3, '-');
    let (Some(pid), Some(n), Some(rest)) = (parts.next(), parts.next(), parts.next()) else {
        return false;
    };
    let (Ok(pid), Ok(_)) = (pid.parse::<u32>(), n.parse::<u64>()) else {
        return false;
    };
    let machine: String = rest
        .chars()
        .take_while(char::is_ascii_alphanumeric)
        .collect();
    if machine != host() || pid == std::process::id() {
        return false;
    }
    // Without a cheap liveness check, leave it: nothing serves a temporary.
    cfg!(target_os = "linux") && !Path::new(&format!("/proc/{pid}")).exists()
}

/// Writes `bytes` to `path` atomically: a temporary file beside it
/// (`.<name>.<temp_name>.tmp`), synced, then renamed over it. Creates the
/// folder if needed.
///
/// Below a folder ltcal owns ([`confine`]) no folder on the way may be a
/// link; a link (or a FIFO, …) at `path` itself is replaced by the rename,
/// never written through.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    Staged::write(path, bytes)?.rename()
}

/// [`write_atomic`] in two halves, so that many files' syncs can overlap
/// before any of them lands: the bytes written to the temporary name and
/// synced ([`Staged::write`]), then renamed into place ([`Staged::rename`]).
/// Dropped without the rename, it removes its temporary.
struct Staged {
    tmp: PathBuf,
    path: PathBuf,
    renamed: bool,
}

impl Staged {
    fn write(path: &Path, bytes: &[u8]) -> Result<Staged> {
        let dir = path.parent().unwrap_or(Path::new("."));
        create_dirs(dir)?;
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy())
            .unwrap_or_default();
        let staged = Staged {
            tmp: dir.join(format!(".{name}.{}.tmp", temp_name())),
            path: path.to_path_buf(),
            renamed: false,
        };
        let write = || -> std::io::Result<()> {
            let mut f = std::fs::File::create(&staged.tmp)?;
            f.write_all(bytes)?;
            f.sync_all()
        };
        write().map_err(|e| anyhow!("writing {}: {e}", path.display()))?;
        Ok(staged)
    }

    fn rename(mut self) -> Result<()> {
        std::fs::rename(&self.tmp, &self.path)
            .map_err(|e| anyhow!("writing {}: {e}", self.path.display()))?;
        self.renamed = true;
        Ok(())
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        if !self.renamed {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// At most this many files are written at once by [`write_groups_atomic`].
const PUBLISH_THREADS: usize = 16;

/// Writes every `(path, bytes)` with [`write_atomic`], each on a thread of
/// its own so that their syncs overlap instead of queueing: one after
/// another they were most of a small calibration's process on a busy disk
/// (a stage's published tables; issue 34).
/// The first failure is returned, after every started write has ended.
pub fn write_all_atomic<B: AsRef<[u8]> + Sync>(writes: &[(PathBuf, B)]) -> Result<()> {
    write_groups_atomic(&[writes])
}

/// Writes `groups` of files atomically, a group landing only once every
/// file of the groups before it has: every file of every group is written
/// and synced under its temporary name at once (a thread each, so that the
/// syncs overlap: a stage's tables and then its record, or a run's record
/// and then its page, synced one after another were a fifth of a small
/// calibration's process on a busy disk; issue 34), then the groups are
/// renamed into place in order. Within a group each file lands or fails on
/// its own, as with [`write_all_atomic`]; after a group with a failure the
/// later groups' temporaries are removed and nothing of them lands — what a
/// later group's file names (a record naming the tables it follows) is
/// never missing. The first failure is returned.
pub fn write_groups_atomic<B: AsRef<[u8]> + Sync>(groups: &[&[(PathBuf, B)]]) -> Result<()> {
    let all: Vec<&(PathBuf, B)> = groups.iter().flat_map(|g| g.iter()).collect();
    let mut staged: Vec<Result<Staged>> = Vec::with_capacity(all.len());
    for chunk in all.chunks(PUBLISH_THREADS) {
        std::thread::scope(|s| {
            let writing: Vec<_> = chunk
                .iter()
                .map(|(path, bytes)| s.spawn(move || Staged::write(path, bytes.as_ref())))
                .collect();
            staged.extend(
                writing
                    .into_iter()
                    .map(|w| w.join().unwrap_or_else(|p| std::panic::resume_unwind(p))),
            );
        });
    }
    let mut staged = staged.into_iter();
    for group in groups {
        let landed: Vec<Result<()>> = staged
            .by_ref()
            .take(group.len())
            .map(|s| s.and_then(Staged::rename))
            .collect();
        // The later groups' temporaries are dropped (removed) with `staged`.
        landed.into_iter().collect::<Result<()>>()?;
    }
    Ok(())
}

/// A folder built under a temporary name beside its final place and
/// published by one rename, so that it appears whole or not at all: the one
/// way ltcal publishes a folder (a cache entry, a campaign, a diagnosis).
/// Dropped unpublished, it removes itself. `sync` asks for every file's
/// bytes to reach the disk before the rename: a campaign or a diagnosis
/// wants it; a cache entry does not (a killed process cannot tear an entry,
/// and what a power cut might tear its content hashes catch on reuse, while
/// syncing the thousands of files of a sweep would cost more than computing
/// them).
pub struct StagedFolder {
    tmp: PathBuf,
    sync: bool,
    published: bool,
}

impl StagedFolder {
    /// Creates the empty temporary folder `tmp` (named by the caller with a
    /// [`temp_name`], so that [`temp_owner_gone`] can tell a dead run's).
    pub fn create(tmp: PathBuf, sync: bool) -> std::io::Result<StagedFolder> {
        std::fs::create_dir(&tmp)?;
        Ok(StagedFolder {
            tmp,
            sync,
            published: false,
        })
    }

    /// Creates the sub-folder `rel` inside.
    pub fn folder(&self, rel: impl AsRef<Path>) -> std::io::Result<()> {
        std::fs::create_dir(self.tmp.join(rel))
    }

    /// Writes `bytes` as the new file `rel` inside (its folder must exist:
    /// a name the caller did not plan for is an error, not a new folder).
    pub fn write(&self, rel: impl AsRef<Path>, bytes: &[u8]) -> std::io::Result<()> {
        let mut f = std::fs::File::create(self.tmp.join(rel))?;
        f.write_all(bytes)?;
        if self.sync {
            f.sync_all()?;
        }
        Ok(())
    }

    /// Renames the folder to `dir` if nothing but an empty folder is there;
    /// otherwise the error, the staged folder kept for another try.
    pub fn place(&mut self, dir: &Path) -> std::io::Result<()> {
        std::fs::rename(&self.tmp, dir)?;
        self.published = true;
        Ok(())
    }

    /// Renames the folder to `dir`, replacing the folder there, if any: that
    /// one is renamed away first and removed once the new one is in place
    /// (put back if that rename fails). Whether it may be replaced at all is
    /// the caller's decision ([`check_replaceable`]).
    pub fn replace(mut self, dir: &Path, parent: &Path, name: &str) -> std::io::Result<()> {
        if std::fs::symlink_metadata(dir).is_err() {
            return self.place(dir);
        }
        let old = parent.join(format!(".{name}.{}.old", temp_name()));
        std::fs::rename(dir, &old)?;
        if let Err(e) = self.place(dir) {
            let _ = std::fs::rename(&old, dir);
            return Err(e);
        }
        let _ = std::fs::remove_dir_all(&old);
        Ok(())
    }
}

impl Drop for StagedFolder {
    fn drop(&mut self) {
        if !self.published {
            let _ = std::fs::remove_dir_all(&self.tmp);
        }
    }
}

/// Publishes `files` (name, bytes) as the folder `dir` through a
/// [`StagedFolder`] built beside it as `.<name>.<temp_name>.tmp`, every file
/// synced, replacing the folder there, if any. On any failure nothing is
/// left but what was there before.
pub fn publish_folder<N: AsRef<Path>>(dir: &Path, files: &[(N, Vec<u8>)]) -> Result<()> {
    let name = dir
        .file_name()
        .ok_or_else(|| anyhow!("{}: the folder needs a name", dir.display()))?
        .to_string_lossy()
        .into_owned();
    let parent = match dir.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    create_dirs(&parent)?;
    let tmp = parent.join(format!(".{name}.{}.tmp", temp_name()));
    let staged = StagedFolder::create(tmp.clone(), true)
        .and_then(|staged| {
            for (file, bytes) in files {
                staged.write(file, bytes)?;
            }
            Ok(staged)
        })
        .map_err(|e| anyhow!("writing {}: {e}", tmp.display()))?;
    staged
        .replace(dir, &parent, &name)
        .map_err(|e| anyhow!("moving the folder into {}: {e}", dir.display()))
}

/// Whether the folder `dir` may be replaced whole by one ltcal writes
/// ([`publish_folder`]): when nothing is there, when it is an empty folder,
/// or when it is recognisably one ltcal wrote — it holds the regular file
/// `marker`, and every entry in it is a regular file whose name `ours`
/// accepts. Anything else (a folder of the user's files, a file, a link)
/// is refused with the reason, `what` naming what ltcal writes there
/// ("a diagnosis", "a campaign"), so that replacing it never deletes a
/// user's files.
pub fn check_replaceable(
    dir: &Path,
    what: &str,
    marker: &str,
    ours: impl Fn(&str) -> bool,
) -> Result<(), String> {
    let Ok(meta) = std::fs::symlink_metadata(dir) else {
        return Ok(());
    };
    if !meta.is_dir() {
        return Err(format!(
            "{} exists and is not a folder ({}): it is not replaced by {what}",
            dir.display(),
            if meta.file_type().is_symlink() {
                "a symbolic link"
            } else {
                kind_of(&meta.file_type())
            }
        ));
    }
    let entries = std::fs::read_dir(dir).map_err(|e| format!("reading {}: {e}", dir.display()))?;
    let mut has_marker = false;
    let mut foreign = Vec::new();
    let mut empty = true;
    for e in entries {
        let e = e.map_err(|e| format!("reading {}: {e}", dir.display()))?;
        empty = false;
        let name = e.file_name().to_string_lossy().into_owned();
        let regular = e.file_type().is_ok_and(|t| t.is_file());
        if regular && name == marker {
            has_marker = true;
        } else if !regular || !ours(&name) {
            foreign.push(name);
        }
    }
    if empty || (has_marker && foreign.is_empty()) {
        return Ok(());
    }
    foreign.sort();
    let shown: Vec<&str> = foreign.iter().take(3).map(String::as_str).collect();
    Err(format!(
        "{} is not {what} ltcal wrote ({}): it would be replaced whole, so its files are left \
         alone — name a new folder, or an earlier {}",
        dir.display(),
        if foreign.is_empty() {
            format!("no {marker}")
        } else {
            format!(
                "it holds {}{}",
                shown.join(", "),
                if foreign.len() > 3 { ", …" } else { "" }
            )
        },
        what.trim_start_matches("a ").trim_start_matches("an ")
    ))
}

/// Why a file the user named was not read.
#[derive(Debug)]
pub struct ReadError {
    pub path: PathBuf,
    pub reason: Reason,
}

/// What was wrong with the file, without its name (callers that show the
/// name elsewhere quote only this).
#[derive(Debug)]
pub enum Reason {
    /// A folder, FIFO, socket or device: reading it could block or never end.
    NotRegular(&'static str),
    /// Larger than the caller allows.
    TooLarge { max_bytes: u64 },

    /// An error of the system, a missing file among them.
    Io(std::io::Error),
}

impl ReadError {
    fn new(path: &Path, reason: Reason) -> ReadError {
        ReadError {
            path: path.to_path_buf(),
            reason,
        }
    }

    pub fn is_missing(&self) -> bool {
        matches!(&self.reason, Reason::Io(e) if e.kind() == std::io::ErrorKind::NotFound)
    }
}

impl fmt::Display for Reason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Reason::NotRegular(what) => write!(f, "is {what}, not a regular file"),
            Reason::TooLarge { max_bytes } => {
                write!(f, "is larger than the {max_bytes} bytes ltcal reads")
            }
            Reason::Io(e) => write!(f, "{e}"),
        }
    }
}

impl fmt::Display for ReadError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "cannot read {}: {}", self.path.display(), self.reason)
    }
}

impl std::error::Error for ReadError {}

/// Reads the regular file `path` if it holds at most `max_bytes`: the one
/// way ltcal reads a file it did not just write. At most `max_bytes + 1`
/// bytes are read, so a file that grows after the check is still refused
/// rather than read whole.
pub fn read_regular_file(path: &Path, max_bytes: u64) -> Result<Vec<u8>, ReadError> {
    let (file, len) = open_regular_file(path, max_bytes)?;
    let mut bytes = Vec::with_capacity(len as usize);
    file.take(max_bytes.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(|e| ReadError::new(path, Reason::Io(e)))?;
    if bytes.len() as u64 > max_bytes {
        return Err(ReadError::new(path, Reason::TooLarge { max_bytes }));
    }
    Ok(bytes)
}

/// Opens the regular file `path` of at most `max_bytes` for reading, and
/// gives its length — for positioned reads (a pack), which the caller
/// bounds by that length.
///
/// The kind of file is checked before it is opened, and it is opened with
/// `O_NONBLOCK` (a FIFO put there in between opens at once instead of
/// waiting for a writer) and checked again on the open file. Below a
/// folder ltcal owns ([`confine`]) a symbolic link on the way, or as the
/// file, is refused (and the file opened with `O_NOFOLLOW`); elsewhere (a
/// file the user names) a link is followed.
pub fn open_regular_file(path: &Path, max_bytes: u64) -> Result<(std::fs::File, u64), ReadError> {
    use std::os::unix::fs::OpenOptionsExt as _;
    let fail = |reason| ReadError::new(path, reason);
    let confined = match link_on_the_way(path) {
        Some(link) => {
            return Err(fail(Reason::Io(std::io::Error::other(format!(
                "goes through the symbolic link {}, and ltcal reads nothing inside the results \
                 folder through a link (remove the link)",
                link.display()
            )))));
        }
        None => TREES
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .iter()
            .any(|t| path.starts_with(t)),
    };
    let regular = |meta: &std::fs::Metadata| {
        if !meta.is_file() {
            return Err(fail(Reason::NotRegular(kind_of(&meta.file_type()))));
        }
        if meta.len() > max_bytes {
            return Err(fail(Reason::TooLarge { max_bytes }));
        }
        Ok(meta.len())
    };
    regular(&std::fs::metadata(path).map_err(|e| fail(Reason::Io(e)))?)?;
    let mut flags = libc::O_NONBLOCK;
    if confined {
        flags |= libc::O_NOFOLLOW;
    }
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(flags)
        .open(path)
        .map_err(|e| fail(Reason::Io(e)))?;
    let len = regular(&file.metadata().map_err(|e| fail(Reason::Io(e)))?)?;
    Ok((file, len))
}

/// "a folder", "a FIFO", …: what a path that is not a regular file is.
fn kind_of(t: &std::fs::FileType) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt as _;
        if t.is_fifo() {
            return "a FIFO";
        }
        if t.is_char_device() || t.is_block_device() {
            return "a device";
        }
        if t.is_socket() {
            return "a socket";
        }
    }
    if t.is_dir() { "a folder" } else { "not a file" }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Regression (issue 12): `ltcal diagnose` on a full disk left a partial
    /// `--out` folder that looked finished. A folder whose writing fails
    /// midway (here its second file cannot be created) is not published,
    /// and its temporary is gone.
    #[test]
    fn diagnose_out_folder_failing_midway_is_not_published() {
        let root = scratch("publish");
        let out = root.join("out");
        let files = vec![
            ("a.csv".to_string(), b"x".to_vec()),
            ("no/such/folder.csv".to_string(), b"y".to_vec()),
        ];
        assert!(publish_folder(&out, &files).is_err());
        assert!(!out.exists());
        assert_eq!(std::fs::read_dir(&root).unwrap().count(), 0);
        // A whole folder replaces the one there, stale files included.
        std::fs::create_dir(&out).unwrap();
        std::fs::write(out.join("stale.svg"), b"old").unwrap();
        publish_folder(&out, &files[..1]).unwrap();
        let names: Vec<_> = std::fs::read_dir(&out)
            .unwrap()
            .flatten()
            .map(|e| e.file_name())
            .collect();
        assert_eq!(names, ["a.csv"]);
        assert_eq!(std::fs::read_dir(&root).unwrap().count(), 1);
        std::fs::remove_dir_all(&root).unwrap();
    }

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("ltcal-fs-{name}-{}", temp_name()));
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn write_atomic_replaces_the_file_and_leaves_no_temporary() {
        let dir = scratch("atomic");
        let path = dir.join("a.txt");
        write_atomic(&path, b"one").unwrap();
        write_atomic(&path, b"two").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"two");
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1);
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn read_regular_file_refuses_folders_devices_and_files_over_the_limit() {
        let dir = scratch("read");
        let path = dir.join("a.csv");
        std::fs::write(&path, b"12345").unwrap();
        assert_eq!(read_regular_file(&path, 5).unwrap(), b"12345");
        let big = read_regular_file(&path, 4).unwrap_err();
        assert!(matches!(big.reason, Reason::TooLarge { max_bytes: 4 }));
        assert!(big.to_string().contains("a.csv"), "{big}");
        let folder = read_regular_file(&dir, 100).unwrap_err();
        assert!(folder.to_string().contains("a folder"), "{folder}");
        assert!(
            read_regular_file(&dir.join("none"), 100)
                .unwrap_err()
                .is_missing()
        );
        if cfg!(unix) {
            let zero = read_regular_file(Path::new("/dev/zero"), 100).unwrap_err();
            assert!(zero.to_string().contains("a device"), "{zero}");
        }
        std::fs::remove_dir_all(dir).unwrap();
    }

    /// Regression (issue 28, 1): only a folder ltcal wrote is replaced.
    #[test]
    fn check_replaceable_accepts_only_an_empty_folder_or_one_of_ours() {
        let root = scratch("replace");
        let ours = |n: &str| n == "a.csv" || n == "m.csv";
        let dir = root.join("d");
        assert!(check_replaceable(&dir, "a thing", "m.csv", ours).is_ok());
        std::fs::create_dir(&dir).unwrap();
        assert!(check_replaceable(&dir, "a thing", "m.csv", ours).is_ok());
        std::fs::write(dir.join("a.csv"), "x").unwrap();
        let e = check_replaceable(&dir, "a thing", "m.csv", ours).unwrap_err();
        assert!(e.contains("is not a thing ltcal wrote (no m.csv)"), "{e}");
        std::fs::write(dir.join("m.csv"), "x").unwrap();
        assert!(check_replaceable(&dir, "a thing", "m.csv", ours).is_ok());
        std::fs::create_dir(dir.join("sub")).unwrap();
        std::fs::write(dir.join("notes.txt"), "keep").unwrap();
        let e = check_replaceable(&dir, "a thing", "m.csv", ours).unwrap_err();
        assert!(e.contains("(it holds notes.txt, sub)"), "{e}");
        assert!(e.contains("or an earlier thing"), "{e}");
        std::fs::remove_dir_all(&root).unwrap();
    }

    /// Regression (issue 28, 3): below a confined folder, nothing is
    /// written or read through a link; above it, links are followed.
    #[test]
    fn nothing_is_written_or_read_through_a_link_below_a_confined_folder() {
        let root = scratch("confine");
        let outside = root.join("outside");
        std::fs::create_dir(&outside).unwrap();
        std::fs::write(outside.join("t.parquet"), "x").unwrap();
        let tree = root.join("results").join("p");
        std::fs::create_dir_all(&tree).unwrap();
        std::os::unix::fs::symlink(&outside, tree.join("stage")).unwrap();
        // Not confined yet: the link is followed.
        assert_eq!(
            read_regular_file(&tree.join("stage/t.parquet"), 10).unwrap(),
            b"x"
        );
        confine(&tree);
        let e = write_atomic(&tree.join("stage/new.parquet"), b"y").unwrap_err();
        assert!(
            e.to_string().contains("stage is a symbolic link (to "),
            "{e}"
        );
        let e = read_regular_file(&tree.join("stage/t.parquet"), 10).unwrap_err();
        assert!(
            e.to_string().contains("goes through the symbolic link"),
            "{e}"
        );
        let e = create_dirs(&tree.join("stage/deeper")).unwrap_err();
        assert!(e.to_string().contains("is a symbolic link"), "{e}");
        assert_eq!(std::fs::read_dir(&outside).unwrap().count(), 1);
        // A link as the file itself is replaced by the rename, not followed.
        std::fs::create_dir(tree.join("real")).unwrap();
        std::os::unix::fs::symlink(outside.join("t.parquet"), tree.join("real/f")).unwrap();
        write_atomic(&tree.join("real/f"), b"z").unwrap();
        assert_eq!(std::fs::read(outside.join("t.parquet")).unwrap(), b"x");
        assert_eq!(read_regular_file(&tree.join("real/f"), 10).unwrap(), b"z");
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn read_regular_file_does_not_block_on_a_fifo() {
        let dir = scratch("fifo");
        let fifo = dir.join("pipe");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status();
        if made.is_ok_and(|s| s.success()) {
            let e = read_regular_file(&fifo, 100).unwrap_err();
            assert!(e.to_string().contains("a FIFO"), "{e}");
        }
        std::fs::remove_dir_all(dir).unwrap();
    }

    /// One way to publish a folder (issue 31): a staged folder dropped
    /// unpublished leaves nothing; `place` refuses a non-empty folder (a
    /// cache entry another writer published first is kept) and keeps the
    /// staged one for another try.
    #[test]
    fn a_staged_folder_appears_whole_once_or_not_at_all() {
        let root = scratch("staged");
        {
            let s = StagedFolder::create(root.join(".a.tmp"), false).unwrap();
            s.write("x.parquet", b"x").unwrap();
        }
        assert_eq!(std::fs::read_dir(&root).unwrap().count(), 0);
        let dest = root.join("entry");
        std::fs::create_dir(&dest).unwrap();
        std::fs::write(dest.join("first"), b"theirs").unwrap();
        let mut s = StagedFolder::create(root.join(".b.tmp"), false).unwrap();
        s.folder("files").unwrap();
        s.write("files/f.svg", b"<svg/>").unwrap();
        assert!(s.write("no/such.csv", b"y").is_err());
        assert!(s.place(&dest).is_err());
        assert_eq!(std::fs::read(dest.join("first")).unwrap(), b"theirs");
        std::fs::remove_dir_all(&dest).unwrap();
        s.place(&dest).unwrap();
        drop(s);
        assert_eq!(std::fs::read(dest.join("files/f.svg")).unwrap(), b"<svg/>");
        assert_eq!(std::fs::read_dir(&root).unwrap().count(), 1);
        std::fs::remove_dir_all(&root).unwrap();
    }

    /// Issue 34: a stage's published files are written in parallel, in chunks of
    /// [`PUBLISH_THREADS`]; every one must land whole, and a failing one
    /// must fail the publication.
    #[test]
    fn published_files_written_in_parallel_all_land_and_a_failure_is_reported() {
        let dir = tempfile::tempdir().unwrap();
        let bytes: Vec<Vec<u8>> = (0..2 * PUBLISH_THREADS + 3)
            .map(|i| vec![i as u8; 1000 + i])
            .collect();
        let writes: Vec<(PathBuf, &Vec<u8>)> = bytes
            .iter()
            .enumerate()
            .map(|(i, b)| (dir.path().join(format!("s/t{i}.parquet")), b))
            .collect();
        write_all_atomic(&writes).unwrap();
        for (path, b) in &writes {
            assert_eq!(&std::fs::read(path).unwrap(), *b);
        }
        let names = std::fs::read_dir(dir.path().join("s")).unwrap().count();
        assert_eq!(names, writes.len(), "no temporary file left");
        // A file where a folder must be: that write fails, the others land.
        std::fs::write(dir.path().join("f"), b"x").unwrap();
        let bad = vec![
            (dir.path().join("s/ok.parquet"), &bytes[0]),
            (dir.path().join("f/t.parquet"), &bytes[1]),
        ];
        let e = write_all_atomic(&bad).unwrap_err().to_string();
        assert!(e.contains("f/t.parquet") || e.contains("creating"), "{e}");
        assert_eq!(
            std::fs::read(dir.path().join("s/ok.parquet")).unwrap(),
            bytes[0]
        );
    }

    /// Issue 34: groups written at once land in order — a later group (a
    /// stage's record, a run's page) only once every file before it has;
    /// after a failing group nothing later lands and no temporary is left.
    #[test]
    fn write_groups_atomic_lands_a_group_only_after_the_ones_before_it() {
        let dir = tempfile::tempdir().unwrap();
        let at = |n: &str| dir.path().join(n);
        let tables = [
            (at("s/a.parquet"), b"a".to_vec()),
            (at("s/b.parquet"), b"b".to_vec()),
        ];
        let record = [(at("last.json"), b"r1".to_vec())];
        write_groups_atomic(&[&tables[..], &record[..]]).unwrap();
        assert_eq!(std::fs::read(at("s/b.parquet")).unwrap(), b"b");
        assert_eq!(std::fs::read(at("last.json")).unwrap(), b"r1");
        // A table that cannot be written: the other table lands, the record
        // after them does not, and neither group leaves a temporary.
        std::fs::write(at("f"), b"x").unwrap();
        let tables = [
            (at("s/a.parquet"), b"a2".to_vec()),
            (at("f/t.parquet"), b"t".to_vec()),
        ];
        let record = [(at("last.json"), b"r2".to_vec())];
        let e = write_groups_atomic(&[&tables[..], &record[..]]).unwrap_err();
        let e = e.to_string();
        assert!(e.contains("f/t.parquet") || e.contains("creating"), "{e}");
        assert_eq!(std::fs::read(at("s/a.parquet")).unwrap(), b"a2");
        assert_eq!(std::fs::read(at("last.json")).unwrap(), b"r1");
        let names = |d: &str| {
            let mut v: Vec<String> = std::fs::read_dir(at(d))
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect();
            v.sort();
            v
        };
        assert_eq!(names("."), ["f", "last.json", "s"]);
        assert_eq!(names("s"), ["a.parquet", "b.parquet"]);
    }
}
