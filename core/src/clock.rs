//! The caller's clock for stage timing: the core reads none itself (determinism).

/// A monotonic clock the caller lends for stage timing (the core has none).
pub trait Clock {
    /// Now, nanoseconds (any origin).
    fn now_ns(&mut self) -> u64;
}

/// A clock that always reads 0 (no timing).
#[derive(Clone, Copy, Debug, Default)]
pub struct NoClock;

impl Clock for NoClock {
    fn now_ns(&mut self) -> u64 {
        0
    }
}
