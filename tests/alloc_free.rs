//! The core's promise, tested: no heap allocation while it works on scans.
//!
//! A counting global allocator counts every allocation made on the current thread while
//! [`count_allocations`] runs its closure. Set-up (rendering scans, building tables, creating
//! output buffers) happens outside; the per-scan work happens inside and must count zero.
//!
//! The whole odometry is counted too (`odometry_runs_a_sequence_without_allocating_and_repeats_bit_for_bit`):
//! the scenario's events and the result buffer are made outside, IMU ingestion and every
//! `process_scan` inside; the same test shows a second run over the same storage gives
//! bit-identical poses.
// A global allocator must implement the unsafe `GlobalAlloc` trait; it only forwards to the
// system allocator and bumps a thread-local counter.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::Mutex;

use loglio_core::odometry::{AssociationMode, Os1_16Storage};
use loglio_core::output::{ScanResult, Status};
use loglio_core::ring_fals::{
    PointNormal, RingFals, RingFals32x1800, RingFalsConfig, RingLearner, RingTable,
};
use loglio_core::scan::ScanView;
use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::scenario::{Event, Scenario, ScenarioConfig, ScenarioKind};
use loglio_tests::odom::config_for;
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
/// The odometry's storage (scan buffers, ring table, voxel pool: 58 MB), as firmware holds it.
static ODOMETRY: Mutex<Os1_16Storage> = Mutex::new(Os1_16Storage::new());

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

#[test]
fn odometry_runs_a_sequence_without_allocating_and_repeats_bit_for_bit() {
    // Set-up, allowed to allocate: 6 s of the handheld scenario with an OS1-16 (2 s at rest for
    // the IMU initialisation, then walking), every event generated up front.
    let mut c = ScenarioConfig::new(ScenarioKind::Handheld, SensorModel::Os1_16, 3);
    c.duration_s = 6.0;
    let sc = Scenario::from_config(c).unwrap();
    let events: Vec<Event> = sc.events().collect();
    let scans = events.iter().filter(|e| matches!(e, Event::Scan(_))).count();
    let cfg = config_for(&sc, AssociationMode::Full);
    let mut storage = ODOMETRY.lock().unwrap_or_else(|e| e.into_inner());

    let mut runs: Vec<Vec<ScanResult>> = Vec::new();
    for run in 0..2 {
        let mut results: Vec<ScanResult> = Vec::with_capacity(scans);
        let mut odo = storage.odometry(&cfg).unwrap();
        // Counted: IMU ingestion and every scan through the whole pipeline.
        let ((), allocations) = count_allocations(|| {
            for ev in &events {
                match ev {
                    Event::Imu(s) => {
                        odo.push_imu(*s);
                    }
                    Event::Scan(scan) => {
                        // Within the capacity reserved above: no allocation.
                        results.push(
                            odo.process_scan(ScanView { start_ns: scan.start_ns, points: &scan.points }),
                        );
                    }
                }
            }
        });
        assert_eq!(allocations, 0, "run {run}: the odometry allocated {allocations} times");
        runs.push(results);
    }
    // The work was real: after the initialisation the LiDAR updated the state.
    let tracked = runs[0].iter().filter(|r| matches!(r.status, Status::Ok | Status::Degraded { .. })).count();
    assert!(tracked >= 30, "{tracked} of {scans} scans updated");
    // Same input, same storage, a fresh odometry: bit-identical poses and covariances.
    let bits = |r: &ScanResult| {
        let p = &r.pose;
        let mut v: Vec<u64> =
            p.position.iter().chain(p.rotation.coords.iter()).map(|x| x.to_bits()).collect();
        v.extend(p.covariance.iter().map(|x| x.to_bits()));
        (p.t_ns, v)
    };
    assert_eq!(runs[0].len(), runs[1].len());
    for (i, (a, b)) in runs[0].iter().zip(&runs[1]).enumerate() {
        assert_eq!(bits(a), bits(b), "scan {i} differs between two runs");
        assert_eq!(a.status, b.status);
    }
}
