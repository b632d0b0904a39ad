//! Progress and cancellation of long work (tracing, sampling, solving), shared between the
//! thread doing it and whoever watches it: the bake command's progress bar, the service's
//! status document and its DELETE.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

/// Why lines could not be added.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum TraceError {
    /// The list would hold more crossings than its 32-bit offsets address (about 32 GiB of
    /// crossings: far beyond any memory budget, so a caller's budget check comes first).
    #[error("more than 2^32 crossings in one intersection list: use fewer lines")]
    TooManyHits,
    /// [`Control::cancel`] was called; the list is as it was before.
    #[error("cancelled")]
    Cancelled,
}

/// Why long work stopped before its end: a cancel, or an error to report (its message).
#[derive(Debug)]
pub enum Stop {
    /// [`Control::cancel`] was called.
    Cancelled,
    /// The work failed; why, as the user reads it.
    Failed(String),
}

impl From<TraceError> for Stop {
    fn from(e: TraceError) -> Self {
        match e {
            TraceError::Cancelled => Self::Cancelled,
            e => Self::Failed(e.to_string()),
        }
    }
}

/// Progress and cancellation shared between a running trace and whoever watches it (another
/// thread): checked between bundles, so a cancel takes effect within one bundle's work.
#[derive(Debug, Default)]
pub struct Control {
    cancelled: AtomicBool,
    /// Line traversals done and to do (a line counts once for the static geometry and once
    /// per frame for the moving objects).
    done: AtomicU64,
    total: AtomicU64,
}

impl Control {
    /// Asks the trace to stop.
    pub fn cancel(&self) {
        self.cancelled.store(true, Ordering::Relaxed);
    }

    /// Whether [`Control::cancel`] was called.
    #[must_use]
    pub fn is_cancelled(&self) -> bool {
        self.cancelled.load(Ordering::Relaxed)
    }

    /// Fraction of the current stage's work done (the tracing, unless a caller started another
    /// stage), in [0, 1].
    #[must_use]
    pub fn fraction(&self) -> f64 {
        let total = self.total.load(Ordering::Relaxed);
        if total == 0 {
            0.0
        } else {
            self.done.load(Ordering::Relaxed) as f64 / total as f64
        }
    }

    /// Starts measuring a new stage of `work` units from zero (a trace adds its own work to
    /// it); cancellation is unaffected.
    pub fn start_stage(&self, work: u64) {
        self.done.store(0, Ordering::Relaxed);
        self.total.store(work, Ordering::Relaxed);
    }

    /// Adds `work` units to do in the current stage.
    pub fn add_work(&self, work: u64) {
        self.total.fetch_add(work, Ordering::Relaxed);
    }

    /// Records `work` more units done in the current stage.
    pub fn advance(&self, work: u64) {
        self.done.fetch_add(work, Ordering::Relaxed);
    }

    pub(crate) fn check(&self) -> Result<(), TraceError> {
        if self.is_cancelled() {
            Err(TraceError::Cancelled)
        } else {
            Ok(())
        }
    }
}

/// A panic's message, from its payload (what `panic!` was given, if text).
#[must_use]
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> &str {
    (payload.downcast_ref::<&str>().copied())
        .or_else(|| payload.downcast_ref::<String>().map(String::as_str))
        .unwrap_or("(no message)")
}
