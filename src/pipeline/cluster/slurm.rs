//! Slurm as a [`Scheduler`]: the client commands `sbatch`, `squeue`,
//! `sacct` and `scancel`, found on `PATH` (and reading `SLURM_CONF`, which
//! they inherit, like every Slurm client).
//!
//! A wave is one `sbatch --array=0-(n-1)%max_running` of a job script that
//! reads its task's line of the wave's points file with the shell's own
//! `read` (it runs no tool but `ltcal`, by its absolute path: nothing is
//! looked up on `PATH`) — never the points
//! themselves inlined (Slurm refuses scripts over 4 MB; a 100 000-point
//! sweep's list would pass it) — and `exec`s `ltcal task` with its output
//! appended to `points-<first>-<last>.log` in the wave's folder under
//! `results/<pipeline>/slurm/`: one log per task, named by its points,
//! never in the home folder (Slurm's own `--output` and `--error` are
//! `/dev/null`: what
//! Slurm does to a task — cancelled, timed out, node failed — the
//! coordinator asks Slurm for and reports itself).
//!
//! Task states come from `squeue --states=all`, which also lists tasks
//! that ended within the controller's memory (`MinJobAge`, 300 s by
//! default); once the controller has forgotten a job, from `sacct` where
//! accounting exists.

use super::scheduler::{ArrayJob, Scheduler, TaskState};
use anyhow::{Context as _, Result, anyhow, bail};
use std::path::Path;
use std::process::Command;

/// The Slurm client commands on `PATH`.
pub struct Slurm;

/// `'…'` for `sh`, whatever the text holds.
pub fn quote(s: &str) -> String {
    format!("'{}'", s.replace('\'', r"'\''"))
}

fn run(cmd: &mut Command) -> Result<(bool, String, String)> {
    use std::os::unix::process::CommandExt as _;
    let name = format!("{:?}", cmd.get_program());
    // A process group of its own: a Ctrl-C at the terminal is the
    // coordinator's to act on (cancelling its jobs), not a kill of the
    // `squeue` or `scancel` it is running at that moment.
    let out = cmd
        .process_group(0)
        .output()
        .with_context(|| format!("running {name} (is Slurm's client on PATH?)"))?;
    Ok((
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).trim().to_string(),
    ))
}

impl Scheduler for Slurm {
    fn name(&self) -> &'static str {
        "Slurm"
    }

    fn script(&self, a: &ArrayJob) -> String {
        let s = a.settings;
        let mut h = String::from("#!/bin/sh\n");
        let mut opt = |o: String| {
            h.push_str("#SBATCH ");
            h.push_str(&o);
            h.push('\n');
        };
        opt(format!("--job-name=ltcal-{}", a.name));
        opt(format!(
            "--array=0-{}%{}",
            a.tasks - 1,
            s.max_running.min(a.tasks).max(1)
        ));
        opt("--output=/dev/null".into());
        opt("--error=/dev/null".into());
        // The environment the coordinator runs in; `sbatch_options` may
        // not change it (settings.rs), and the script below looks nothing
        // up on `PATH`.
        opt("--export=ALL".into());
        opt("--no-requeue".into());
        opt(format!("--cpus-per-task={}", s.cpus_per_task));
        if let Some(p) = &s.partition {
            opt(format!("--partition={p}"));
        }
        if let Some(x) = &s.account {
            opt(format!("--account={x}"));
        }
        if let Some(t) = &s.time_limit {
            opt(format!("--time={t}"));
        }
        if let Some(m) = s.memory_mb {
            opt(format!("--mem={m}M"));
        }
        for o in &s.sbatch_options {
            opt(o.clone());
        }
        let units = quote(&a.units.display().to_string());
        let wave = a.wave.display().to_string();
        h.push_str(&format!(
            "cd {} || exit 1\n",
            quote(&a.workdir.display().to_string())
        ));
        h.push_str(&format!(
            "# Task i runs line i+1 of the points file: \"<first>-<last> <points>\",\n\
             # read with the shell's own `read`: no tool is looked up on PATH.\n\
             i=0\n\
             found=\n\
             while IFS= read -r line; do\n\
             \x20 if [ \"$i\" -eq \"$SLURM_ARRAY_TASK_ID\" ]; then found=1; break; fi\n\
             \x20 i=$((i + 1))\n\
             done < {units}\n\
             [ -n \"$found\" ] || exit 1\n\
             range=${{line%% *}}\n\
             points=${{line#* }}\n\
             exec >>{}\"/points-$range.log\" 2>&1\n\
             exec {} --points \"$points\" --prefix \"slurm-${{SLURM_ARRAY_JOB_ID}}_${{SLURM_ARRAY_TASK_ID}}\"\n",
            quote(&wave),
            a.command
                .iter()
                .map(|c| quote(c))
                .collect::<Vec<_>>()
                .join(" ")
        ));
        h
    }

    fn submit(&self, script: &Path) -> Result<String> {
        let (ok, out, err) = run(Command::new("sbatch").arg("--parsable").arg(script))?;
        if !ok {
            bail!("sbatch refused the job: {err}");
        }
        // `<job id>` or `<job id>;<cluster>`.
        let id = out.trim().split(';').next().unwrap_or("").to_string();
        if id.is_empty() || !id.chars().all(|c| c.is_ascii_digit()) {
            bail!("sbatch answered {:?}, not a job id", out.trim());
        }
        Ok(id)
    }

    fn tasks(&self, job: &str) -> Result<Option<Vec<TaskState>>> {
        let (ok, out, err) = run(Command::new("squeue").args([
            "--noheader",
            "--array",
            "--states=all",
            "--jobs",
            job,
            "--format=%i|%T|%N",
        ]))?;
        if ok {
            let tasks = parse_squeue(job, &out);
            if !tasks.is_empty() {
                return Ok(Some(tasks));
            }
        } else if !err.contains("Invalid job id") {
            return Err(anyhow!("squeue failed: {err}"));
        }
        // Forgotten by the controller: accounting, where it exists.
        let Ok((true, out, _)) = run(Command::new("sacct").args([
            "--noheader",
            "--parsable2",
            "--allocations",
            "--jobs",
            job,
            "--format=JobID,State,NodeList",
        ])) else {
            return Ok(None);
        };
        let tasks: Vec<TaskState> = out
            .lines()
            .filter_map(|l| {
                let mut f = l.split('|');
                let (id, state, node) = (f.next()?, f.next()?, f.next()?);
                Some(TaskState {
                    index: task_index(job, id)?,
                    state: state.split_whitespace().next()?.to_string(),
                    node: node.to_string(),
                })
            })
            .collect();
        Ok((!tasks.is_empty()).then_some(tasks))
    }

    fn task_prefix(&self, job: &str, task: usize) -> String {
        format!("slurm-{job}_{task}")
    }

    fn cancel(&self, jobs: &[String]) -> Result<()> {
        if jobs.is_empty() {
            return Ok(());
        }
        let (ok, _, err) = run(Command::new("scancel").args(jobs))?;
        if !ok {
            bail!("scancel failed: {err}");
        }
        Ok(())
    }
}

/// `<job>_<index>` → index.
fn task_index(job: &str, id: &str) -> Option<usize> {
    id.strip_prefix(job)?.strip_prefix('_')?.parse().ok()
}

/// `squeue --array` lines `<job>_<index>|<STATE>|<nodes>`.
fn parse_squeue(job: &str, out: &str) -> Vec<TaskState> {
    out.lines()
        .filter_map(|l| {
            let mut f = l.trim().splitn(3, '|');
            let (id, state, node) = (f.next()?, f.next()?, f.next()?);
            Some(TaskState {
                index: task_index(job, id)?,
                state: state.to_string(),
                node: node.to_string(),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn squeue_lines_are_read_per_array_task() {
        let out = "12_0|COMPLETED|n1\n12_1|NODE_FAIL|n2\n12_2|PENDING|\n13_0|RUNNING|n3\n";
        let t = parse_squeue("12", out);
        assert_eq!(t.len(), 3);
        assert_eq!(
            (t[1].index, t[1].state.as_str(), t[1].node.as_str()),
            (1, "NODE_FAIL", "n2")
        );
        assert!(t[2].pending());
    }

    #[test]
    fn the_job_script_runs_its_task_with_no_tool_looked_up_on_path() {
        let dir = tempfile::tempdir().unwrap();
        let units = dir.path().join("points.txt");
        std::fs::write(&units, "0-1 0-1\n2-3 2,3\n4-5 4-5\n").unwrap();
        let settings = super::super::settings::SlurmSettings {
            sbatch_options: vec!["--qos=long".into()],
            ..Default::default()
        };
        let job = ArrayJob {
            name: "p",
            tasks: 3,
            settings: &settings,
            workdir: dir.path(),
            wave: dir.path(),
            units: &units,
            command: vec!["/bin/echo".into(), "task".into()],
        };
        let script = Slurm.script(&job);
        // ltcal's own options come before the pipeline's.
        let at = |o: &str| script.find(o).unwrap_or_else(|| panic!("{o}: {script}"));
        for own in [
            "--array=0-2%3",
            "--output=/dev/null",
            "--error=/dev/null",
            "--export=ALL",
        ] {
            assert!(at(own) < at("--qos=long"), "{script}");
        }
        let path = dir.path().join("job.sh");
        std::fs::write(&path, &script).unwrap();
        // A PATH that finds nothing (what `--export=PATH=…` would have
        // pointed at a folder of impostors).
        let run = |task: &str| {
            Command::new("/bin/sh")
                .arg(&path)
                .env_clear()
                .env("PATH", dir.path().join("nothing"))
                .env("SLURM_ARRAY_TASK_ID", task)
                .env("SLURM_ARRAY_JOB_ID", "7")
                .status()
                .unwrap()
        };
        assert!(run("1").success());
        let log = std::fs::read_to_string(dir.path().join("points-2-3.log")).unwrap();
        assert_eq!(log, "task --points 2,3 --prefix slurm-7_1\n");
        // A task beyond the points file runs nothing.
        assert!(!run("3").success());
    }

    #[test]
    fn quoting_survives_quotes() {
        assert_eq!(quote("a'b c"), r"'a'\''b c'");
    }
}
