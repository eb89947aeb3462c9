//! The code fingerprint: one blake3 hash of the sources ltcal is built
//! from, computed by `build.rs` (which includes this file) and compiled in
//! as [`crate::CODE_FINGERPRINT`].
//!
//! It enters every cache key, so that a build from other code never serves
//! what the old code computed: a fix in a stage, a helper it calls or a
//! dependency upgrade reruns the stages. It covers every file under `src/`,
//! `build.rs`, `Cargo.toml` and `Cargo.lock` (which pins the dependencies).
//!
//! It is one fingerprint for the whole crate, not one per stage kind: any
//! change under `src/` reruns every stage. A per-stage fingerprint would
//! have to know every module a stage's output can depend on, and one missed
//! call path would serve a stale result; over-invalidation costs time,
//! under-invalidation costs trust. Correctness first.
//!
//! Not covered: the compiler and its flags. Tests, benches, docs and
//! pipelines are not code that computes a stage and are left out.

use std::io;
use std::path::Path;

/// The files hashed besides everything under `src/`, relative to the crate
/// root. A missing one (`Cargo.lock` of a crate built as a dependency) is
/// left out.
pub const TOP_FILES: [&str; 3] = ["build.rs", "Cargo.toml", "Cargo.lock"];

/// The fingerprint of the crate at `root`: blake3 over every file under
/// `src/` and the [`TOP_FILES`], in sorted order of their `/`-separated
/// paths relative to `root`, each as its path and its bytes, both
/// length-prefixed (so that no rename or move of bytes between a name and
/// a content, or between two files, gives the same stream).
pub fn fingerprint(root: &Path) -> io::Result<String> {
    let mut files = Vec::new();
    walk(root, Path::new("src"), &mut files)?;
    for f in TOP_FILES {
        if root.join(f).is_file() {
            files.push(f.to_string());
        }
    }
    files.sort();
    let mut h = blake3::Hasher::new();
    for f in &files {
        let bytes = std::fs::read(root.join(f))?;
        h.update(&(f.len() as u64).to_le_bytes());
        h.update(f.as_bytes());
        h.update(&(bytes.len() as u64).to_le_bytes());
        h.update(&bytes);
    }
    Ok(h.finalize().to_hex().to_string())
}

/// Every file under `root/dir`, as a `/`-separated path relative to `root`
/// (the same on every platform).
fn walk(root: &Path, dir: &Path, out: &mut Vec<String>) -> io::Result<()> {
    for e in std::fs::read_dir(root.join(dir))? {
        let e = e?;
        let rel = dir.join(e.file_name());
        if e.file_type()?.is_dir() {
            walk(root, &rel, out)?;
        } else {
            let parts: Vec<String> = rel
                .components()
                .map(|c| c.as_os_str().to_string_lossy().into_owned())
                .collect();
            out.push(parts.join("/"));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs;

    /// A crate root with two sources, a build script and both manifests.
    fn crate_root() -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        let r = dir.path();
        fs::create_dir_all(r.join("src/stages")).unwrap();
        fs::write(r.join("src/lib.rs"), "pub mod stages;").unwrap();
        fs::write(r.join("src/stages/mesh.rs"), "fn f() {}").unwrap();
        fs::write(r.join("build.rs"), "fn main() {}").unwrap();
        fs::write(r.join("Cargo.toml"), "[package]").unwrap();
        fs::write(r.join("Cargo.lock"), "version = 4").unwrap();
        dir
    }

    #[test]
    fn the_fingerprint_changes_with_any_source_file_name_or_content_and_the_lockfile() {
        let dir = crate_root();
        let r = dir.path();
        let base = fingerprint(r).unwrap();
        assert_eq!(base.len(), 64);
        assert_eq!(fingerprint(r).unwrap(), base, "deterministic");

        let changed = |edit: &dyn Fn(), undo: &dyn Fn()| {
            edit();
            let h = fingerprint(r).unwrap();
            undo();
            assert_eq!(fingerprint(r).unwrap(), base, "undone");
            h != base
        };
        let write = |p: &'static str, s: &'static str| move || fs::write(r.join(p), s).unwrap();
        let mv =
            |a: &'static str, b: &'static str| move || fs::rename(r.join(a), r.join(b)).unwrap();
        // A file's content, deep in `src/`.
        assert!(changed(
            &write("src/stages/mesh.rs", "fn f() { 1; }"),
            &write("src/stages/mesh.rs", "fn f() {}")
        ));
        // A file's name, same content.
        assert!(changed(
            &mv("src/stages/mesh.rs", "src/stages/mesh2.rs"),
            &mv("src/stages/mesh2.rs", "src/stages/mesh.rs")
        ));
        // A new file.
        assert!(changed(&write("src/new.rs", ""), &|| fs::remove_file(
            r.join("src/new.rs")
        )
        .unwrap()));
        // A dependency upgrade, the manifest and the build script.
        for (f, old) in [
            ("Cargo.lock", "version = 4"),
            ("Cargo.toml", "[package]"),
            ("build.rs", "fn main() {}"),
        ] {
            assert!(changed(&write(f, "x"), &write(f, old)), "{f}");
        }
        // Bytes moved from one file's end to the next file's start.
        assert!(changed(
            &|| {
                fs::write(r.join("src/lib.rs"), "pub mod stages;f").unwrap();
                fs::write(r.join("src/stages/mesh.rs"), "n f() {}").unwrap();
            },
            &|| {
                fs::write(r.join("src/lib.rs"), "pub mod stages;").unwrap();
                fs::write(r.join("src/stages/mesh.rs"), "fn f() {}").unwrap();
            }
        ));
        // Files that compute no stage: tests, benches, docs.
        fs::create_dir_all(r.join("tests")).unwrap();
        fs::write(r.join("tests/t.rs"), "#[test] fn t() {}").unwrap();
        fs::write(r.join("README.md"), "# x").unwrap();
        assert_eq!(fingerprint(r).unwrap(), base);
    }
}
