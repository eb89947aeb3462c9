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
//! - [`write_staged`]: a file inside a folder that is itself published by one
//!   rename (a cache entry, a campaign folder), where the folder's rename is
//!   what makes the whole appear at once.
//! - [`publish_folder`]: a whole folder of files built that way and renamed
//!   into place (replacing the folder there, if any), so a full disk or a
//!   kill never leaves a partial folder that looks finished.
//! - [`read_regular_file`]: what a user points ltcal at (a pipeline file, a
//!   campaign file, a data table) read only if it is a regular file of a sane
//!   size: a FIFO would block the run forever, `/dev/zero` would fill memory.

use anyhow::{Context as _, Result, anyhow, bail};
use std::fmt;
use std::io::{Read as _, Write as _};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

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
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy())
        .unwrap_or_default();
    let tmp = dir.join(format!(".{name}.{}.tmp", temp_name()));
    let write = || -> std::io::Result<()> {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    };
    write().map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        anyhow!("writing {}: {e}", path.display())
    })
}

/// Writes `bytes` as the new file `path` inside a folder that is still being
/// built under a [`temp_name`] and is published afterwards by one rename.
/// `sync` asks for the bytes to reach the disk before returning: a campaign
/// folder wants it; a cache entry does not (a killed process cannot tear an
/// entry, and what a power cut might tear its content hashes catch on reuse,
/// while syncing the thousands of files of a sweep would cost more than
/// computing them).
pub fn write_staged(path: &Path, bytes: &[u8], sync: bool) -> std::io::Result<()> {
    let mut f = std::fs::File::create(path)?;
    f.write_all(bytes)?;
    if sync {
        f.sync_all()?;
    }
    Ok(())
}

/// Publishes `files` (name, bytes) as the folder `dir`: built beside it as
/// `.<name>.<temp_name>.tmp` with every file synced, then renamed into
/// place. A folder already at `dir` is renamed away first and removed once
/// the new one is in place (put back if that rename fails); whether it may
/// be replaced at all is the caller's decision. On any failure nothing is
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
    std::fs::create_dir_all(&parent).with_context(|| format!("creating {}", parent.display()))?;
    let suffix = temp_name();
    let tmp = parent.join(format!(".{name}.{suffix}.tmp"));
    let built = (|| -> std::io::Result<()> {
        std::fs::create_dir(&tmp)?;
        for (file, bytes) in files {
            write_staged(&tmp.join(file), bytes, true)?;
        }
        Ok(())
    })();
    if let Err(e) = built {
        let _ = std::fs::remove_dir_all(&tmp);
        bail!("writing {}: {e}", tmp.display());
    }
    let placed = if std::fs::symlink_metadata(dir).is_ok() {
        let old = parent.join(format!(".{name}.{suffix}.old"));
        std::fs::rename(dir, &old)
            .and_then(|()| {
                std::fs::rename(&tmp, dir).inspect_err(|_| {
                    let _ = std::fs::rename(&old, dir);
                })
            })
            .map(|()| {
                let _ = std::fs::remove_dir_all(&old);
            })
    } else {
        std::fs::rename(&tmp, dir)
    };
    placed.map_err(|e| {
        let _ = std::fs::remove_dir_all(&tmp);
        anyhow!("moving the folder into {}: {e}", dir.display())
    })
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

/// Reads the regular file `path` if it holds at most `max_bytes`.
///
/// The kind of file is checked before it is opened (opening a FIFO blocks
/// until a writer appears), and at most `max_bytes + 1` bytes are read, so a
/// file that grows after the check is still refused rather than read whole.
pub fn read_regular_file(path: &Path, max_bytes: u64) -> Result<Vec<u8>, ReadError> {
    let fail = |reason| ReadError {
        path: path.to_path_buf(),
        reason,
    };
    let io = |e| fail(Reason::Io(e));
    let meta = std::fs::metadata(path).map_err(io)?;
    if !meta.is_file() {
        return Err(fail(Reason::NotRegular(kind_of(&meta.file_type()))));
    }
    if meta.len() > max_bytes {
        return Err(fail(Reason::TooLarge { max_bytes }));
    }
    let file = std::fs::File::open(path).map_err(io)?;
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    file.take(max_bytes.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(io)?;
    if bytes.len() as u64 > max_bytes {
        return Err(fail(Reason::TooLarge { max_bytes }));
    }
    Ok(bytes)
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
}
