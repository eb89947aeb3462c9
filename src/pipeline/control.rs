//! How a caller follows a run under way and stops it: the Python package's
//! progress bar and its Ctrl-C, the command line's first Ctrl-C.
//!
//! A stop is cooperative. No stage and no sweep point starts after it; the
//! ones under way finish (a stage is never cut midway, so its cache entry
//! lands whole or not at all); the sweep points finished are written to the
//! cache; and the run ends with [`Interrupted`] instead of a report. Nothing
//! more is published: no gathered table of a part of the sweep, no
//! `run.json` or page of a part of the run. A rerun takes what was finished
//! from the cache and goes on.
//!
//! The counts are for display only: the run's report, not these, says what
//! ran.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

/// The flag a caller raises to stop a run, and what the run has done so far.
#[derive(Debug, Default)]
pub struct Control {
    /// Raised by the caller (or a signal handler) to stop the run.
    stop: Arc<AtomicBool>,
    /// Set by the run when the stop kept a stage or point from starting:
    /// a stop that came after the last one started changes nothing.
    cut: AtomicBool,
    /// Stages of the pipeline (not of a sweep point) done: ran, cached,
    /// failed or skipped.
    stages: AtomicUsize,
    /// Sweep points done: ran, cached or failed.
    points: AtomicUsize,
}

/// What a run stopped by [`Control::stop`] (or a Slurm coordinator stopped
/// by Ctrl-C) returns instead of its report: the command line's exit 130.
#[derive(Debug, thiserror::Error)]
pub enum Interrupted {
    /// A run here: the stages of the pipeline (a sweep point's are counted
    /// as its point) and the sweep points done before the stop.
    #[error(
        "interrupted: nothing started after the stop; {} finished before it {} cached \
         (a rerun takes {} and goes on); nothing of the unfinished run was published",
        finished(*stages, *points),
        if stages + points == 1 { "is" } else { "are" },
        if stages + points == 1 { "it" } else { "them" }
    )]
    Here { stages: usize, points: usize },
    /// A Slurm coordinator, saying what it cancelled.
    #[error("interrupted: {0}")]
    Cluster(String),
}

fn finished(stages: usize, points: usize) -> String {
    let count = |n: usize, what: &str| format!("{n} {what}{}", if n == 1 { "" } else { "s" });
    match (stages, points) {
        (s, 0) => format!("the {}", count(s, "stage")),
        (0, p) => format!("the {}", count(p, "sweep point")),
        (s, p) => format!("the {} and {}", count(p, "sweep point"), count(s, "stage")),
    }
}

impl Control {
    /// A control whose stop is `flag`: a signal handler's flag
    /// (`signal_hook::flag::register`) stops the run it is given to.
    pub fn with_flag(flag: Arc<AtomicBool>) -> Control {
        Control {
            stop: flag,
            ..Control::default()
        }
    }

    /// Asks the run to stop: nothing starts after this.
    pub fn stop(&self) {
        self.stop.store(true, Ordering::SeqCst);
    }

    /// Whether the stop was asked for.
    pub fn stopping(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }

    /// Called by the run before it starts a stage or point: `true` (and
    /// the run marked as cut short) when it must not start.
    pub(super) fn refuses(&self) -> bool {
        let stop = self.stopping();
        if stop {
            self.cut.store(true, Ordering::SeqCst);
        }
        stop
    }

    /// [`Interrupted`] when the stop kept something from starting.
    pub(super) fn check(&self) -> Result<(), Interrupted> {
        if self.cut.load(Ordering::SeqCst) {
            return Err(Interrupted::Here {
                stages: self.stages_done(),
                points: self.points_done(),
            });
        }
        Ok(())
    }

    pub(super) fn stage_done(&self) {
        self.stages.fetch_add(1, Ordering::Relaxed);
    }

    pub(super) fn point_done(&self) {
        self.points.fetch_add(1, Ordering::Relaxed);
    }

    /// Stages of the pipeline done so far (a sweep point's stages are
    /// counted as its point).
    pub fn stages_done(&self) -> usize {
        self.stages.load(Ordering::Relaxed)
    }

    /// Sweep points done so far.
    pub fn points_done(&self) -> usize {
        self.points.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stop_after_the_last_start_is_no_interruption() {
        let c = Control::default();
        assert!(!c.refuses());
        c.stop();
        assert!(c.check().is_ok(), "nothing was kept from starting");
        assert!(c.refuses());
        c.stage_done();
        let e = c.check().unwrap_err();
        assert!(matches!(
            e,
            Interrupted::Here {
                stages: 1,
                points: 0
            }
        ));
        assert!(
            e.to_string()
                .contains("the 1 stage finished before it is cached"),
            "{e}"
        );
        c.point_done();
        c.point_done();
        let e = c.check().unwrap_err().to_string();
        assert!(e.contains("the 2 sweep points and 1 stage finished before it are cached"));
    }

    #[test]
    fn a_signal_flag_stops_the_run_it_is_given_to() {
        let flag = Arc::new(AtomicBool::new(false));
        let c = Control::with_flag(flag.clone());
        assert!(!c.stopping());
        flag.store(true, Ordering::SeqCst);
        assert!(c.stopping());
    }
}
