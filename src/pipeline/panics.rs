//! Stage panics as stage failures. A stage that panics is caught
//! (`catch_unwind`) and reported as a failure of that stage with the panic's
//! message and place — once, in the run's summary. The default panic hook
//! would also print `thread '<unnamed>' panicked at …` the moment it
//! happens, interleaved with the progress lines of the stages running
//! beside it; [`catch`] keeps it quiet.
//!
//! A panic hook is process-wide, so it is installed once and stays: it stays
//! silent only for panics on a thread that is running a stage, or on a rayon
//! worker while any stage runs (a stage's own parallel work, whose panic
//! reaches the stage through rayon); every other panic — a test's, a
//! library user's — goes to the hook that was there before.

use std::any::Any;
use std::cell::{Cell, RefCell};
use std::panic::{self, AssertUnwindSafe};
use std::sync::Once;
use std::sync::atomic::{AtomicUsize, Ordering};

thread_local! {
    static IN_STAGE: Cell<bool> = const { Cell::new(false) };
    /// Where the last panic on this thread happened, recorded by the hook.
    static PLACE: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// Stages running in this process.
static RUNNING: AtomicUsize = AtomicUsize::new(0);

fn install_hook() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        let previous = panic::take_hook();
        panic::set_hook(Box::new(move |info| {
            let in_stage = IN_STAGE.with(Cell::get);
            let stage_worker =
                RUNNING.load(Ordering::SeqCst) > 0 && rayon::current_thread_index().is_some();
            if in_stage || stage_worker {
                if let Some(l) = info.location() {
                    let place = format!("{}:{}:{}", l.file(), l.line(), l.column());
                    PLACE.with(|p| *p.borrow_mut() = Some(place));
                }
            } else {
                previous(info);
            }
        }));
    });
}

/// Runs `f`; a panic becomes `Err("<message> (at <file>:<line>:<col>)")`
/// and prints nothing.
pub fn catch<T>(f: impl FnOnce() -> T) -> Result<T, String> {
    install_hook();
    RUNNING.fetch_add(1, Ordering::SeqCst);
    let was = IN_STAGE.with(|s| s.replace(true));
    PLACE.with(|p| p.borrow_mut().take());
    let outcome = panic::catch_unwind(AssertUnwindSafe(f));
    IN_STAGE.with(|s| s.set(was));
    RUNNING.fetch_sub(1, Ordering::SeqCst);
    outcome.map_err(|payload| {
        let msg = message(payload.as_ref());
        match PLACE.with(|p| p.borrow_mut().take()) {
            Some(place) => format!("{msg} (at {place})"),
            None => msg,
        }
    })
}

fn message(payload: &(dyn Any + Send)) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "a panic without a message".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_becomes_its_message_and_place() {
        let e = catch(|| -> u32 { panic!("boom {}", 7) }).unwrap_err();
        assert!(e.starts_with("boom 7 (at src/pipeline/panics.rs:"), "{e}");
        assert_eq!(catch(|| 3), Ok(3));
    }

    #[test]
    fn a_panic_in_a_stages_parallel_work_is_caught_with_its_message() {
        use rayon::prelude::*;
        let e = catch(|| {
            (0..64)
                .into_par_iter()
                .map(|i| if i == 40 { panic!("item {i}") } else { i })
                .sum::<i32>()
        })
        .unwrap_err();
        assert!(e.starts_with("item 40"), "{e}");
    }
}
