//! Cooperative cancellation of a whole-run computation on a thread of its own.
//!
//! The Python bindings run a long call (a run's features or twin, the
//! observer's reversals, an estimate, the road observer's blocks) on a thread
//! of its own and stop waiting for it at Ctrl-C (`dt-py`,
//! `gil::interruptible`). With no way to tell it, the computation ran on to
//! its end, a core busy for a result nobody would read. [`with_flag`] gives
//! the thread a flag; the loops over a run's samples
//! ([`crate::features::compute_features`], [`crate::features::compute_twin`],
//! [`crate::features::compute_reversals`], [`crate::estimator::estimate_log`],
//! [`crate::road::read_run`]) and the whole-file log reader's loop over its
//! messages ([`crate::log::read_log_bytes`]) look at it every [`CHECK_EVERY`]
//! samples ([`requested_at`]) and, once it is set, stop taking samples and
//! return what they have. That result is incomplete: whoever sets the flag has stopped
//! waiting and must drop it. A thread without a flag (the daemon, `replay`)
//! is never stopped.

use std::cell::RefCell;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// The sample loops look at the flag once per this many samples (about a
/// second of a run at 1 kHz on three topics: under a millisecond of the
/// estimator's work, tens of milliseconds where the observer fits 4 Hz
/// reversals).
pub const CHECK_EVERY: usize = 4096;

thread_local! {
    static FLAG: RefCell<Option<Arc<AtomicBool>>> = const { RefCell::new(None) };
}

/// Runs `f` with `flag` as this thread's cancellation flag (the one before
/// it back after `f`, also when `f` panics).
pub fn with_flag<T>(flag: Arc<AtomicBool>, f: impl FnOnce() -> T) -> T {
    struct Restore(Option<Arc<AtomicBool>>);
    impl Drop for Restore {
        fn drop(&mut self) {
            let before = self.0.take();
            FLAG.with(|c| *c.borrow_mut() = before);
        }
    }
    let _restore = Restore(FLAG.with(|c| c.borrow_mut().replace(flag)));
    f()
}

/// Whether this thread's computation was asked to stop (never without a
/// flag).
#[must_use]
pub fn requested() -> bool {
    FLAG.with(|c| {
        c.borrow()
            .as_ref()
            .is_some_and(|f| f.load(Ordering::Relaxed))
    })
}

/// [`requested`], looked at for every [`CHECK_EVERY`]-th sample `k` only.
#[must_use]
pub fn requested_at(k: usize) -> bool {
    k % CHECK_EVERY == 0 && requested()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flag_holds_for_its_call_only_and_only_once_set() {
        assert!(!requested());
        let flag = Arc::new(AtomicBool::new(false));
        with_flag(Arc::clone(&flag), || {
            assert!(!requested() && !requested_at(0));
            flag.store(true, Ordering::Relaxed);
            assert!(requested() && requested_at(CHECK_EVERY));
            assert!(!requested_at(1), "looked at every CHECK_EVERY samples only");
            // a nested call has its own, then this one's is back
            with_flag(Arc::new(AtomicBool::new(false)), || assert!(!requested()));
            assert!(requested());
        });
        assert!(!requested(), "the flag ends with its call");
        // also when the call panics
        let caught = std::panic::catch_unwind(|| with_flag(Arc::clone(&flag), || panic!("boom")));
        assert!(caught.is_err() && !requested());
        // another thread never sees this one's flag
        with_flag(flag, || {
            assert!(requested());
            assert!(!std::thread::spawn(requested).join().unwrap());
        });
    }
}
