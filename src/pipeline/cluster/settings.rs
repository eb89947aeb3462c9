//! `[executor.slurm]`: how a pipeline's sweep goes out to a Slurm cluster.
//!
//! ```toml
//! [executor.slurm]
//! partition = "compute"           # sbatch --partition (the cluster's default if absent)
//! account = "metrology"           # sbatch --account
//! time_limit = "2:00:00"          # sbatch --time, per task, as Slurm reads it
//! memory_mb = 4000                # sbatch --mem, per task
//! cpus_per_task = 1               # sbatch --cpus-per-task; a task runs this many points at once
//! points_per_task = 50            # sweep points one array task runs
//! max_running = 100               # array tasks running at once (sbatch --array=…%N)
//! sbatch_options = ["--qos=long"] # anything else, one option per string (not
//!                                 # --array, --output, --error, --export, --chdir:
//!                                 # ltcal's own, refused under any name sbatch reads)
//! poll_seconds = 5                # how often the coordinator asks Slurm (squeue)
//! ```
//!
//! Every field can be set from the command line as well:
//! `--set executor.slurm.points_per_task=200`.

use serde::{Deserialize, Serialize};

/// The settings as written and overridden: every field has a default.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SlurmSettings {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub partition: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub account: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_limit: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub memory_mb: Option<u64>,
    #[serde(default = "one")]
    pub cpus_per_task: u32,
    #[serde(default = "default_points_per_task")]
    pub points_per_task: usize,
    #[serde(default = "default_max_running")]
    pub max_running: usize,
    #[serde(default)]
    pub sbatch_options: Vec<String>,
    #[serde(default = "default_poll_seconds")]
    pub poll_seconds: f64,
}

fn one() -> u32 {
    1
}

/// A task's fixed cost (Slurm starting it, ltcal loading the pipeline) is
/// about a second; 50 points of a few milliseconds to seconds each keep
/// it small while leaving hundreds of tasks to spread over the nodes of a
/// 10 000-point sweep. Cheap points want more (README: "Running on a
/// cluster").
fn default_points_per_task() -> usize {
    50
}

/// What clusters commonly allow one user without complaint.
fn default_max_running() -> usize {
    100
}

/// One `squeue` per job a few seconds apart is a load no controller
/// notices.
fn default_poll_seconds() -> f64 {
    5.0
}

impl Default for SlurmSettings {
    fn default() -> Self {
        serde_json::from_value(serde_json::json!({})).expect("every field has a default")
    }
}

impl SlurmSettings {
    /// What is wrong with the settings, field by field.
    pub fn problems(&self) -> Vec<String> {
        let mut out = Vec::new();
        if !(1..=1024).contains(&self.cpus_per_task) {
            out.push("`cpus_per_task` must be 1 … 1024".to_string());
        }
        if self.points_per_task == 0 {
            out.push("`points_per_task` must be at least 1".to_string());
        }
        if self.max_running == 0 {
            out.push("`max_running` must be at least 1".to_string());
        }
        if !(self.poll_seconds.is_finite() && (1.0..=600.0).contains(&self.poll_seconds)) {
            out.push("`poll_seconds` must be between 1 and 600".to_string());
        }
        // What sbatch reads back unchanged from `--name=value` in an
        // `#SBATCH` line: no quote, escape or comment sign, and not the
        // words it blanks out (`packjob`, `hetjob`).
        let plain = |s: &str| {
            let lower = s.to_lowercase();
            !s.is_empty()
                && s.chars()
                    .all(|c| c.is_ascii_graphic() && !matches!(c, '\'' | '"' | '\\' | '#'))
                && !lower.contains("packjob")
                && !lower.contains("hetjob")
        };
        for (name, v) in [
            ("partition", &self.partition),
            ("account", &self.account),
            ("time_limit", &self.time_limit),
        ] {
            if let Some(v) = v {
                if !plain(v) {
                    out.push(format!(
                        "`{name}` = {v:?}: a Slurm name has no spaces, quotes, `\\` or `#`"
                    ));
                }
            }
        }
        for o in &self.sbatch_options {
            if let Err(why) = check_sbatch_option(o) {
                out.push(format!("`sbatch_options` entry {o:?}: {why}"));
            }
        }
        out
    }
}

/// The sbatch options ltcal sets itself — the array, the logs, the
/// environment and the folder its job script relies on — with their short
/// forms: no `sbatch_options` entry may set them.
const OWN: &[(&str, Option<char>)] = &[
    ("array", Some('a')),
    ("output", Some('o')),
    ("error", Some('e')),
    ("export", None),
    ("export-file", None),
    ("chdir", Some('D')),
    // `--chdir`'s name before Slurm 17.11.
    ("workdir", None),
];

/// Short options that take an argument in every sbatch: the rest of their
/// word (or the next word) is their value. Any other letter is read as a
/// flag, so the letters after it are checked too — wrong only towards
/// refusing.
const SHORT_WITH_VALUE: &str = "AcCdJnNpqtwx";

/// The words of an `#SBATCH` line as sbatch splits them: whitespace
/// separates, `"…"` and `'…'` group, `\` escapes the next character but
/// unquoted whitespace (which still ends the word), an unquoted `#` starts
/// a comment.
fn sbatch_words(line: &str) -> Vec<String> {
    let mut words = Vec::new();
    let mut chars = line.chars().peekable();
    loop {
        while chars.next_if(|c| c.is_whitespace()).is_some() {}
        if chars.peek().is_none() {
            return words;
        }
        let mut w = String::new();
        let mut quote: Option<char> = None;
        let mut started = false;
        while let Some(&c) = chars.peek() {
            if quote.is_none() && c.is_whitespace() {
                break;
            }
            chars.next();
            if quote.is_none() && c == '#' {
                if started {
                    words.push(w);
                }
                return words;
            }
            started = true;
            match (quote, c) {
                // sbatch ends an unquoted word at whitespace even right
                // after a backslash (which it drops): `--hold\ --ar=1` is
                // two words there, the second `--array`.
                (None, '\\') if chars.peek().is_some_and(|n| n.is_whitespace()) => break,
                (_, '\\') => w.extend(chars.next()),
                (Some(q), c) if c == q => quote = None,
                (Some(_), c) => w.push(c),
                (None, '"' | '\'') => quote = Some(c),
                (None, c) => w.push(c),
            }
        }
        words.push(w);
    }
}

/// Whether an `sbatch_options` entry is options sbatch reads as options,
/// none of them one of ltcal's own ([`OWN`]) under any name sbatch accepts
/// for it: a unique prefix of the long name (`--arr=`), the `=` or the
/// space form, a short form alone or in a cluster of short flags (`-Ho`).
/// Every word is read as getopt would; where that depends on whether an
/// option takes a value, both readings are checked.
pub fn check_sbatch_option(entry: &str) -> Result<(), String> {
    if entry.chars().any(char::is_control) {
        return Err("an option is one line, without control characters".into());
    }
    // sbatch blanks these words out wherever they stand in an `#SBATCH`
    // line (they separate the parts of a heterogeneous job).
    let lower = entry.to_lowercase();
    if lower.contains("packjob") || lower.contains("hetjob") {
        return Err("`packjob` and `hetjob` split a job: ltcal submits one".into());
    }
    let words = sbatch_words(entry);
    if words.is_empty() {
        return Err("empty".into());
    }
    let own = |what: String| {
        Err(format!(
            "{what}: ltcal sets the array, the logs (`--output`, `--error`), the environment \
             (`--export`) and the working folder (`--chdir`) itself"
        ))
    };
    // Whether the previous word left an option waiting for its value.
    let mut value_may_follow = false;
    for w in &words {
        if let Some(long) = w.strip_prefix("--") {
            let name = long.split_once('=').map_or(long, |(n, _)| n);
            if name.is_empty() {
                return Err("`--` ends sbatch's options".into());
            }
            if let Some((full, _)) = OWN.iter().find(|(full, _)| full.starts_with(name)) {
                return own(format!("`--{name}` is read by sbatch as `--{full}`"));
            }
            value_may_follow = !long.contains('=');
        } else if let Some(short) = w.strip_prefix('-').filter(|s| !s.is_empty()) {
            value_may_follow = false;
            for (i, c) in short.char_indices() {
                if let Some((full, _)) = OWN.iter().find(|(_, s)| *s == Some(c)) {
                    return own(format!("`-{c}` is `--{full}`"));
                }
                if SHORT_WITH_VALUE.contains(c) {
                    value_may_follow = i + c.len_utf8() == short.len();
                    break;
                }
            }
        } else if value_may_follow {
            // The previous option's value (or, if it takes none, a word
            // that ends sbatch's options: harmless, ltcal's come first).
            value_may_follow = false;
        } else {
            return Err(format!(
                "`{w}` is not an option (write options as `--name=value`)"
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_and_problems() {
        let s = SlurmSettings::default();
        assert_eq!(
            (s.points_per_task, s.max_running, s.cpus_per_task),
            (50, 100, 1)
        );
        assert!(s.problems().is_empty());
        let bad = SlurmSettings {
            points_per_task: 0,
            partition: Some("a b".into()),
            sbatch_options: vec!["--array=1-3".into(), "-o x".into(), "-p x".into()],
            ..s
        };
        let p = bad.problems();
        assert_eq!(p.len(), 4, "{p:?}");
    }

    #[test]
    fn sbatch_option_prefixes_cannot_override_the_array_or_the_logs() {
        // The bypasses found: unique prefixes, the space form, short forms
        // and clusters, `--export`, several options in one entry.
        for bad in [
            "--arr=0-99",
            "--outpu=/tmp/x",
            "--erro=/tmp/x",
            "--array 0-3",
            "--arr 0-3",
            "--output /tmp/x",
            "-a 0-3",
            "-a0-3",
            "-o/tmp/x",
            "-e /tmp/x",
            "-D /tmp",
            "-Ho/tmp/x",
            "-array=0-3",
            "--export=ALL,PATH=/tmp/evil",
            "--exp=ALL",
            "--export-file=/tmp/env",
            "--chdir=/tmp",
            "--ch=/tmp",
            "--workdir=/tmp",
            "--qos=long --arr=1",
            "--qos=long -o /tmp/x",
            "--qos=\"long\" --outp=/tmp/x",
            "--comment=x packjob --arr=1",
            "--qos=long\n--array=1",
            "--",
            "--qos=long stray",
        ] {
            let s = SlurmSettings {
                sbatch_options: vec![bad.to_string()],
                ..SlurmSettings::default()
            };
            let p = s.problems();
            assert_eq!(p.len(), 1, "{bad:?} passed: {p:?}");
        }
        let e = check_sbatch_option("--arr=0-99").unwrap_err();
        assert!(e.contains("`--arr` is read by sbatch as `--array`"), "{e}");
        let e = check_sbatch_option("-Ho/tmp/x").unwrap_err();
        assert!(e.contains("`-o` is `--output`"), "{e}");
        // What a pipeline may set, in the forms sbatch reads.
        for good in [
            "--qos=long",
            "--qos long",
            "-q long",
            "-qlong",
            "--exclusive",
            "--comment=\"a run # not a comment\"",
            "--comment=--array=1",
            "-J ltcal-o",
            "-Jname-o",
            "--mail-type=END --mail-user=me@example.org",
            "--account-x=1",
        ] {
            assert_eq!(check_sbatch_option(good), Ok(()), "{good:?}");
        }
    }

    #[test]
    fn sbatch_words_split_as_sbatch_splits_them() {
        assert_eq!(
            sbatch_words(r#"  --a="b c" 'd e'f\ g # --array=1"#),
            vec!["--a=b c", "d ef", "g"]
        );
    }
}
