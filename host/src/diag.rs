//! One-line diagnostics of the `loglio` command.
//!
//! Fatal problems travel as `anyhow::Error`s up to `main`, which prints `error: ...` on one line
//! and exits non-zero. Non-fatal problems (a cloud without a `ring` field, a dropped message) go
//! through [`warn`], which prints `warning: ...` on one line to stderr. Library code that can
//! repeat a warning (per message, per scan) keeps its own "already warned" flag and warns once,
//! with a count at the end where it matters.
//!
//! Tests capture warnings with [`capture`] instead of reading stderr.

use std::cell::RefCell;
use std::fmt::Display;
use std::sync::atomic::{AtomicU64, Ordering};

static WARNINGS: AtomicU64 = AtomicU64::new(0);

/// The progress bar on screen, if any: warnings are printed above it.
static BAR: std::sync::Mutex<Option<indicatif::ProgressBar>> = std::sync::Mutex::new(None);

/// Registers (or clears) the progress bar that warnings must not garble.
pub(crate) fn set_progress_bar(bar: Option<indicatif::ProgressBar>) {
    if let Ok(mut b) = BAR.lock() {
        *b = bar;
    }
}

thread_local! {
    static CAPTURED: RefCell<Option<Vec<String>>> = const { RefCell::new(None) };
}

/// Flattens a message onto one line: newlines and tabs become spaces, runs of spaces collapse.
pub fn one_line(msg: &str) -> String {
    let mut out = String::with_capacity(msg.len());
    let mut space = false;
    for c in msg.trim().chars() {
        if c.is_whitespace() {
            if !space {
                out.push(' ');
            }
            space = true;
        } else {
            out.push(c);
            space = false;
        }
    }
    out
}

/// Reports a non-fatal problem: `warning: <msg>` on one line of stderr (or into the current
/// [`capture`] on this thread).
pub fn warn(msg: impl Display) {
    WARNINGS.fetch_add(1, Ordering::Relaxed);
    let line = format!("warning: {}", one_line(&msg.to_string()));
    let captured = CAPTURED.with(|c| {
        if let Some(v) = c.borrow_mut().as_mut() {
            v.push(line.clone());
            true
        } else {
            false
        }
    });
    if !captured {
        let bar = BAR.lock().ok().and_then(|b| b.clone());
        match bar {
            Some(bar) if !bar.is_hidden() => bar.suspend(|| eprintln!("{line}")),
            _ => eprintln!("{line}"),
        }
    }
}

/// Number of warnings issued by this process so far.
pub fn warning_count() -> u64 {
    WARNINGS.load(Ordering::Relaxed)
}

/// Runs `f` and returns its result with the warnings it issued on this thread (each a full
/// `warning: ...` line), instead of printing them.
pub fn capture<R>(f: impl FnOnce() -> R) -> (R, Vec<String>) {
    let previous = CAPTURED.with(|c| c.borrow_mut().replace(Vec::new()));
    let r = f();
    let got = CAPTURED.with(|c| std::mem::replace(&mut *c.borrow_mut(), previous)).unwrap_or_default();
    (r, got)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_line_flattens() {
        assert_eq!(one_line("  a\n  b\tc  \n"), "a b c");
    }

    #[test]
    fn capture_collects_and_nests() {
        let ((), outer) = capture(|| {
            warn("first\nline");
            let ((), inner) = capture(|| warn("inner"));
            assert_eq!(inner, vec!["warning: inner".to_string()]);
            warn(format_args!("n = {}", 3));
        });
        assert_eq!(outer, vec!["warning: first line".to_string(), "warning: n = 3".to_string()]);
    }
}
