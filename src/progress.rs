//! What a batch shows while it works: on a terminal, a bar per stage with its ETA (indicatif),
//! following the stage's [`Control`]; in a log (CI), one plain line per stage.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use crate::control::Control;

/// Progress of a batch: on a terminal, a bar per stage with its ETA (indicatif), following the
/// stage's [`Control`]; otherwise (CI logs) one plain line per stage.
pub struct Progress {
    bar: Option<indicatif::ProgressBar>,
    ticker: Option<(Arc<AtomicBool>, std::thread::JoinHandle<()>)>,
}

impl Progress {
    /// Resolution of the bar: the stage's fraction in thousandths.
    const STEPS: u64 = 1000;

    /// A renderer following `control`'s fraction: a bar if standard error is a terminal.
    #[must_use]
    pub fn new(control: Arc<Control>) -> Self {
        use std::io::IsTerminal;
        if !std::io::stderr().is_terminal() {
            return Self {
                bar: None,
                ticker: None,
            };
        }
        let bar = indicatif::ProgressBar::new(Self::STEPS);
        if let Ok(style) = indicatif::ProgressStyle::with_template(
            "{msg:64!} [{bar:30}] {percent:>3}% {elapsed:>4} ETA {eta:>4}",
        ) {
            bar.set_style(style.progress_chars("=> "));
        }
        let stop = Arc::new(AtomicBool::new(false));
        let ticker = {
            let (bar, stop) = (bar.clone(), stop.clone());
            std::thread::spawn(move || {
                while !stop.load(Ordering::Relaxed) {
                    bar.set_position((control.fraction() * Self::STEPS as f64) as u64);
                    std::thread::sleep(std::time::Duration::from_millis(100));
                }
            })
        };
        Self {
            bar: Some(bar),
            ticker: Some((stop, ticker)),
        }
    }

    /// A stage starts.
    pub fn stage(&self, prefix: &str, line: &str) {
        match &self.bar {
            Some(bar) => {
                bar.reset();
                bar.set_message(format!("{prefix} {line}"));
            }
            None => eprintln!("{prefix} {line}"),
        }
    }

    /// A line that stays (a scene's outcome).
    pub fn line(&self, line: &str) {
        match &self.bar {
            Some(bar) => bar.println(line),
            None => eprintln!("{line}"),
        }
    }

    /// The bar cleared and its ticker stopped.
    pub fn finish(self) {
        if let Some((stop, ticker)) = self.ticker {
            stop.store(true, Ordering::Relaxed);
            let _ = ticker.join();
        }
        if let Some(bar) = self.bar {
            bar.finish_and_clear();
        }
    }
}
