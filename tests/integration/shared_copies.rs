//! The repository carries copies of the project's shared contracts — the
//! campaign format and the effects' definitions (`docs/`), the example
//! campaigns (`examples/campaigns/`) and the paper's Table 9
//! (`docs/paper-table9.md`) — so that a clone alone runs every pipeline and
//! test. The copies must stay the contracts: wherever `../shared` is
//! present (it is in the project's own checkouts), they are compared with
//! it byte for byte.

use crate::util::root;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Every regular file under `dir`, by its path relative to `dir`.
fn files(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let rel = p.strip_prefix(dir).unwrap().to_path_buf();
                out.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    out
}

#[test]
fn the_repositorys_copies_of_the_shared_contracts_are_byte_identical() {
    // What a clone alone has: the copies, whatever `../shared` holds.
    let campaigns = files(&root().join("examples/campaigns"));
    assert!(campaigns.len() >= 13 * 4, "{}", campaigns.len());
    for doc in ["campaign-format.md", "effects.md"] {
        assert!(root().join("docs").join(doc).is_file(), "{doc}");
    }
    let shared = root().join("../shared");
    if !shared.is_dir() {
        eprintln!("no ../shared beside the clone: the copies are not compared");
        return;
    }
    assert!(
        files(&shared.join("data/campaigns")) == campaigns,
        "examples/campaigns differs from ../shared/data/campaigns: copy it again"
    );
    for doc in ["campaign-format.md", "effects.md"] {
        assert_eq!(
            std::fs::read(root().join("docs").join(doc)).unwrap(),
            std::fs::read(shared.join("spec").join(doc)).unwrap(),
            "docs/{doc} differs from ../shared/spec/{doc}: copy it again"
        );
    }
    // The excerpt: the paper's lines from Table 9's header row to its caption.
    let paper = std::fs::read_to_string(shared.join("paper/paper.md")).unwrap();
    let lines: Vec<&str> = paper.lines().collect();
    let caption = lines
        .iter()
        .position(|l| l.starts_with("Table 9."))
        .unwrap();
    let header = (0..caption)
        .rev()
        .find(|&i| lines[i].starts_with("θ (deg)"))
        .unwrap();
    let excerpt = std::fs::read_to_string(root().join("docs/paper-table9.md")).unwrap();
    let table = lines[header..=caption].join("\n");
    assert!(
        excerpt.ends_with(&format!("{table}\n")),
        "docs/paper-table9.md is not the paper's Table 9"
    );
}
