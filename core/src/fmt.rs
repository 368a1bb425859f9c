//! Logging shim (after embassy's `fmt.rs`): the core logs through `defmt` on firmware, through
//! `log` on the host, and through nothing in tests, so no build needs a logger it does not have.
//! Arguments are still evaluated (by reference) when logging is off, so they never become unused.
#![allow(unused_macros)]

#[cfg(all(feature = "defmt", feature = "log"))]
compile_error!("loglio-core: enable at most one of the `defmt` and `log` features");

macro_rules! trace {
    ($s:literal $(, $x:expr)* $(,)?) => {{
        #[cfg(feature = "defmt")] ::defmt::trace!($s $(, $x)*);
        #[cfg(feature = "log")] ::log::trace!($s $(, $x)*);
        #[cfg(not(any(feature = "defmt", feature = "log")))] let _ = ($(&$x),*);
    }};
}

macro_rules! debug {
    ($s:literal $(, $x:expr)* $(,)?) => {{
        #[cfg(feature = "defmt")] ::defmt::debug!($s $(, $x)*);
        #[cfg(feature = "log")] ::log::debug!($s $(, $x)*);
        #[cfg(not(any(feature = "defmt", feature = "log")))] let _ = ($(&$x),*);
    }};
}

macro_rules! info {
    ($s:literal $(, $x:expr)* $(,)?) => {{
        #[cfg(feature = "defmt")] ::defmt::info!($s $(, $x)*);
        #[cfg(feature = "log")] ::log::info!($s $(, $x)*);
        #[cfg(not(any(feature = "defmt", feature = "log")))] let _ = ($(&$x),*);
    }};
}

macro_rules! warn {
    ($s:literal $(, $x:expr)* $(,)?) => {{
        #[cfg(feature = "defmt")] ::defmt::warn!($s $(, $x)*);
        #[cfg(feature = "log")] ::log::warn!($s $(, $x)*);
        #[cfg(not(any(feature = "defmt", feature = "log")))] let _ = ($(&$x),*);
    }};
}

macro_rules! error {
    ($s:literal $(, $x:expr)* $(,)?) => {{
        #[cfg(feature = "defmt")] ::defmt::error!($s $(, $x)*);
        #[cfg(feature = "log")] ::log::error!($s $(, $x)*);
        #[cfg(not(any(feature = "defmt", feature = "log")))] let _ = ($(&$x),*);
    }};
}
