//! A progress bar with ETA for replays and bags, drawn on stderr only when stderr is a terminal
//! (hidden in pipes, logs and CI). Warnings issued through [`crate::diag::warn`] while a bar is
//! shown are printed above it instead of through it.

use std::io::IsTerminal;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// A progress bar over a known total (bytes of a file, or messages).
#[derive(Debug, Clone)]
pub struct Progress {
    bar: ProgressBar,
}

impl Progress {
    /// A bar over `total` units; `bytes` formats the counts as bytes (file replays), otherwise
    /// as counts of `what` (e.g. "messages").
    pub fn new(total: u64, what: &str, bytes: bool) -> Progress {
        let target = if std::io::stderr().is_terminal() {
            ProgressDrawTarget::stderr_with_hz(5)
        } else {
            ProgressDrawTarget::hidden()
        };
        let bar = ProgressBar::with_draw_target(Some(total), target);
        let counts = if bytes { "{bytes}/{total_bytes}" } else { "{pos}/{len}" };
        let template = format!(
            "{{spinner}} [{{elapsed_precise}}] {{wide_bar}} {counts} {what} ({{percent}}%, ETA {{eta}}) {{msg}}"
        );
        if let Ok(style) = ProgressStyle::with_template(&template) {
            bar.set_style(style);
        }
        let p = Progress { bar };
        crate::diag::set_progress_bar(Some(p.bar.clone()));
        p
    }

    /// A bar that draws nothing.
    pub fn hidden() -> Progress {
        Progress { bar: ProgressBar::hidden() }
    }

    /// Whether anything is drawn.
    pub fn is_visible(&self) -> bool {
        !self.bar.is_hidden()
    }

    /// Sets the position (units done).
    pub fn set_position(&self, done: u64) {
        self.bar.set_position(done);
    }

    /// Advances by `n` units.
    pub fn inc(&self, n: u64) {
        self.bar.inc(n);
    }

    /// Units done so far.
    pub fn position(&self) -> u64 {
        self.bar.position()
    }

    /// Sets the text after the bar (e.g. the current rate or status).
    pub fn set_message(&self, msg: impl Into<String>) {
        self.bar.set_message(msg.into());
    }

    /// Removes the bar from the terminal.
    pub fn finish(&self) {
        self.bar.finish_and_clear();
        crate::diag::set_progress_bar(None);
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        // The last clone going away clears the terminal line; diag holds one clone.
        if !self.bar.is_finished() && !self.bar.is_hidden() {
            self.bar.finish_and_clear();
            crate::diag::set_progress_bar(None);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_even_when_hidden() {
        let p = Progress::new(1000, "bytes", true);
        // Tests do not run on a terminal in CI; either way the count is kept.
        p.set_position(10);
        p.inc(5);
        assert_eq!(p.position(), 15);
        p.finish();
        let h = Progress::hidden();
        assert!(!h.is_visible());
    }
}
