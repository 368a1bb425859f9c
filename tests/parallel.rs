//! The association split over threads, and the Ring FALS normals beside the downsampling's
//! voxel binning ([`loglio_core::parallel`]): the trajectory is bit-identical to one thread's,
//! for 2, 3 and 8 threads (each piece writes its own correspondences; the counts are integers
//! summed in piece order; the update accumulates in point order afterwards; the normals and the
//! voxels write disjoint storage, and the voxels' normals are summed in point order after both).

use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use loglio_core::association::KnnScratch;
use loglio_core::odometry::{AssociationMode, Vlp32cStorage};
use loglio_core::parallel::{Job, MAX_WIDTH, Parallel};
use loglio_core::scan::ScanView;
use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::scenario::{Event, Scenario, ScenarioConfig, ScenarioKind};
use loglio_tests::odom::{StdClock, config_for};

static STORE: Mutex<Vlp32cStorage> = Mutex::new(Vlp32cStorage::new());

/// Scoped threads, one per job but the first; counts the split runs. (The host's pool, whose
/// threads live as long as it, is run below too.)
struct Threads(usize, AtomicUsize);

impl Parallel for Threads {
    fn width(&self) -> usize {
        self.0
    }
    fn run(&self, jobs: &mut [Job<'_>]) {
        if jobs.len() > 1 {
            self.1.fetch_add(1, Ordering::Relaxed);
        }
        if let [first, rest @ ..] = jobs {
            std::thread::scope(|s| {
                for j in rest.iter_mut() {
                    s.spawn(j);
                }
                first();
            });
        }
    }
}

/// Every scan's pose (bits) and association counts with `threads` (1: no split), and how many
/// searches were split.
fn run(sc: &Scenario, threads: usize) -> (Vec<([u64; 7], u32)>, usize) {
    let pool = Threads(threads, AtomicUsize::new(0));
    let out = run_on(sc, &pool);
    (out, pool.1.load(Ordering::Relaxed))
}

/// Every scan's pose (bits) and association counts with the jobs on `pool`.
fn run_on(sc: &Scenario, pool: &dyn Parallel) -> Vec<([u64; 7], u32)> {
    let mut store = STORE.lock().unwrap_or_else(|e| e.into_inner());
    let threads = pool.width();
    let mut scratch = vec![KnnScratch::new(); MAX_WIDTH];
    let mut odo = store.odometry(&config_for(sc, AssociationMode::Full)).unwrap();
    if threads > 1 {
        odo.set_parallel(pool, &mut scratch[..threads - 1]);
    }
    let mut clock = StdClock::default();
    let mut out = Vec::new();
    for ev in sc.events() {
        match ev {
            Event::Imu(s) => {
                odo.push_imu(s);
            }
            Event::Scan(s) => {
                let r =
                    odo.process_scan_timed(ScanView { start_ns: s.start_ns, points: &s.points }, &mut clock);
                let (p, q) = (r.pose.position, r.pose.rotation.coords);
                let bits = [p.x, p.y, p.z, q.x, q.y, q.z, q.w].map(f64::to_bits);
                out.push((bits, r.associations.accepted()));
            }
        }
    }
    out
}

#[test]
fn threads_give_the_same_trajectory_bit_for_bit() {
    let mut c = ScenarioConfig::new(ScenarioKind::Vehicle, SensorModel::Vlp32c, 4);
    c.duration_s = 6.0;
    let sc = Scenario::from_config(c).unwrap();
    let (one, split) = run(&sc, 1);
    assert_eq!(split, 0);
    let tracked = one.iter().filter(|(_, n)| *n > 0).count();
    assert!(tracked >= 30, "{tracked} scans associated");
    for threads in [2, 3, MAX_WIDTH] {
        let (many, split) = run(&sc, threads);
        assert!(split >= tracked, "{split} searches split over {threads} threads");
        assert_eq!(many.len(), one.len());
        for (i, (a, b)) in one.iter().zip(&many).enumerate() {
            assert_eq!(a, b, "scan {i} differs with {threads} threads");
        }
    }
    // The host's pool (workers started once, waiting between batches).
    for width in [2, 3] {
        let pool = loglio_host::run::pool::Pool::new(width);
        let many = run_on(&sc, &pool);
        assert_eq!(many.len(), one.len());
        for (i, (a, b)) in one.iter().zip(&many).enumerate() {
            assert_eq!(a, b, "scan {i} differs on the host's pool of {width}");
        }
    }
}
