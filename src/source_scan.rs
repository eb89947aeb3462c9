//! Test-only: the source scan behind the plug-in recipes' tests. A
//! plug-in (an effect, a tracker model) must be its own file and one
//! registry line; these tests read every `.rs` file under `src/` but the
//! plug-in's and list the lines that mention it.

use std::path::Path;

/// Every line (`path:line: text`) of a `.rs` file under `src/`, other than
/// the file ending in `own`, for which `mentions` holds.
pub(crate) fn mentions_outside(own: &str, mentions: impl Fn(&str) -> bool) -> Vec<String> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut found = Vec::new();
    let mut stack = vec![src];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(dir).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") && !p.ends_with(own) {
                let text = std::fs::read_to_string(&p).unwrap();
                for (n, line) in text.lines().enumerate() {
                    if mentions(line) {
                        found.push(format!("{}:{}: {line}", p.display(), n + 1));
                    }
                }
            }
        }
    }
    found
}
