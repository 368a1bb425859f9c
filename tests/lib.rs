//! Shared helpers for loglio's cross-crate tests (the tests themselves are the `[[test]]`
//! targets beside this file).

pub mod odom;
pub mod synth;
