//! The core's promise, tested: no heap allocation while it works on scans.
//!
//! A counting global allocator counts every allocation made on the current thread while
//! [`count_allocations`] runs its closure. Set-up (rendering scans, building tables, creating
//! output buffers) happens outside; the per-scan work happens inside and must count zero.
//!
//! To add a stage (the odometry, when it lands): prepare its inputs and caller-owned storage
//! before the counted closure, call it inside the closure next to Ring FALS, and keep the
//! `assert_eq!(allocations, 0)`.
// A global allocator must implement the unsafe `GlobalAlloc` trait; it only forwards to the
// system allocator and bumps a thread-local counter.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::Mutex;

use loglio_core::ring_fals::{
    PointNormal, RingFals, RingFals32x1800, RingFalsConfig, RingLearner, RingTable,
};
use loglio_tests::synth::{self, Rng, os1_16_layout, vlp32c_layout};

struct Counting;

thread_local! {
    static ACTIVE: Cell<bool> = const { Cell::new(false) };
    static COUNT: Cell<usize> = const { Cell::new(0) };
}

fn bump() {
    // `try_with`: the thread-local may already be gone while a thread shuts down.
    let _ = ACTIVE.try_with(|a| {
        if a.get() {
            let _ = COUNT.try_with(|c| c.set(c.get() + 1));
        }
    });
}

// SAFETY: every call is forwarded unchanged to the system allocator.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        bump();
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        bump();
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        bump();
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Runs `f` and returns its result with the number of heap allocations it made on this thread.
fn count_allocations<R>(f: impl FnOnce() -> R) -> (R, usize) {
    COUNT.with(|c| c.set(0));
    ACTIVE.with(|a| a.set(true));
    let r = f();
    ACTIVE.with(|a| a.set(false));
    (r, COUNT.with(|c| c.get()))
}

/// Caller-owned storage, in statics as firmware would hold it.
static FALS: Mutex<RingFals32x1800> = Mutex::new(RingFals::new());
static TABLE_32: Mutex<RingTable> = Mutex::new(RingTable::new());
static TABLE_16: Mutex<RingTable> = Mutex::new(RingTable::new());
static LEARNER: Mutex<RingLearner> = Mutex::new(RingLearner::new());

#[test]
fn the_counter_counts() {
    let (v, n) = count_allocations(|| vec![1u8; 10]);
    assert_eq!(v.len(), 10);
    assert!(n >= 1, "the counting allocator must see a Vec allocation");
}

#[test]
fn ring_fals_estimates_a_sequence_of_scans_without_allocating() {
    // Set-up, allowed to allocate: a street seen by two sensors over five scans, with dropouts
    // and noise; output buffers sized to the largest scan.
    let layouts = [vlp32c_layout(), os1_16_layout()];
    let scene = synth::street_scene();
    let mut scans = Vec::new();
    for (li, layout) in layouts.iter().enumerate() {
        for k in 0..5u64 {
            let mut drop = Rng::new(100 + k);
            let keep: Vec<bool> = (0..layout.pixels()).map(|_| drop.uniform() > 0.03).collect();
            let cols = layout.cols();
            let r = synth::render(layout, &scene, 0.01, &mut Rng::new(k), |row, col| keep[row * cols + col]);
            scans.push((li, r.points));
        }
    }
    let mut out = vec![PointNormal::INVALID; scans.iter().map(|s| s.1.len()).max().unwrap()];
    let mut fals = FALS.lock().unwrap();
    let mut tables = [TABLE_32.lock().unwrap(), TABLE_16.lock().unwrap()];
    let mut learner = LEARNER.lock().unwrap();

    // Counted: building the tables, learning a layout, and estimating every scan.
    let (valid, allocations) = count_allocations(|| {
        for (t, layout) in tables.iter_mut().zip(&layouts) {
            t.build(layout, &RingFalsConfig::DEFAULT).unwrap();
        }
        learner.reset(32, 1800, true).unwrap();
        let mut valid = 0u64;
        for (li, points) in &scans {
            let out = &mut out[..points.len()];
            let stats = fals.estimate(&tables[*li], points, out).unwrap();
            valid += stats.valid_points as u64;
            if *li == 0 {
                learner.observe(points);
            }
        }
        let learned = learner.layout(10).unwrap();
        tables[0].build(&learned, &RingFalsConfig::DEFAULT).unwrap();
        valid
    });
    assert_eq!(allocations, 0, "the core allocated {allocations} times");
    // The work was real: most points got normals.
    let total: usize = scans.iter().map(|s| s.1.len()).sum();
    assert!(valid as f64 > 0.8 * total as f64, "{valid} of {total} valid");
}
