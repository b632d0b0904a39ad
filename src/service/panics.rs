//! A panic in the service goes to its log with a backtrace, and a job's with the job's id: a
//! job whose work panics fails (its status says where and why), the other jobs and the
//! service go on, and the log holds what an operator needs to report it.
//!
//! The hook ([`log_panics`]) logs every panic where it happens, with the id of the job whose
//! thread it is ([`as_job`]); a panic on one of the work's helper threads (rayon's) has no id
//! there, and the job's failure, logged next with its id and the panic's message, ties the
//! two together.

use std::backtrace::Backtrace;
use std::cell::RefCell;
use std::sync::Once;

thread_local! {
    /// The job whose work this thread runs.
    static JOB: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// Logs every panic of the process (`tracing::error!`: the job's id if the thread runs one,
/// where, the message and a backtrace), then hands it to the hook that was set before (which
/// prints it to stderr as Rust does by default). Installed once, however often called.
pub fn log_panics() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let job = JOB.try_with(|j| j.borrow().clone()).ok().flatten();
            let location = info
                .location()
                .map_or_else(String::new, ToString::to_string);
            let message = info.payload_as_str().unwrap_or("(no message)");
            let backtrace = Backtrace::force_capture();
            match job {
                Some(id) => {
                    tracing::error!(id, %location, message, %backtrace, "a job panicked");
                }
                None => tracing::error!(%location, message, %backtrace, "a thread panicked"),
            }
            previous(info);
        }));
    });
}

/// Runs `work` on this thread as job `id`'s: a panic in it is logged with the id.
pub fn as_job<T>(id: &str, work: impl FnOnce() -> T) -> T {
    /// Puts the thread's previous job back, however `work` ends.
    struct Restore(Option<String>);
    impl Drop for Restore {
        fn drop(&mut self) {
            let previous = self.0.take();
            let _ = JOB.try_with(|j| *j.borrow_mut() = previous);
        }
    }
    let previous = JOB.with(|j| j.replace(Some(id.to_owned())));
    let _restore = Restore(previous);
    work()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::{Arc, Mutex};

    /// A writer into a shared buffer, for a subscriber whose output the test reads.
    #[derive(Clone, Default)]
    struct Captured(Arc<Mutex<Vec<u8>>>);

    impl std::io::Write for Captured {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            self.0.lock().unwrap().extend_from_slice(buf);
            Ok(buf.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    /// A job's panic is logged with its id, its message, where it happened and a backtrace;
    /// the thread's job is forgotten once the work is over.
    #[test]
    fn a_jobs_panic_is_logged_with_its_id_and_a_backtrace() {
        log_panics();
        let captured = Captured::default();
        let writer = captured.clone();
        let subscriber = tracing_subscriber::fmt()
            .with_writer(move || writer.clone())
            .with_ansi(false)
            .finish();
        tracing::subscriber::with_default(subscriber, || {
            let outcome = std::panic::catch_unwind(|| {
                as_job("0123456789abcdef", || panic!("the cutter lost an edge"))
            });
            assert_eq!(
                crate::control::panic_message(outcome.unwrap_err().as_ref()),
                "the cutter lost an edge"
            );
            assert_eq!(JOB.with(|j| j.borrow().clone()), None);
        });
        let log = String::from_utf8(captured.0.lock().unwrap().clone()).unwrap();
        assert!(
            log.contains("a job panicked")
                && log.contains("id=\"0123456789abcdef\"")
                && log.contains("the cutter lost an edge")
                && log.contains("panics.rs")
                && log.contains("backtrace="),
            "{log}"
        );
    }
}
