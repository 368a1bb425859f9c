//! The association split over threads, and the Ring FALS normals beside the downsampling's
//! voxel binning ([`loglio_core::parallel`]): the trajectory is bit-identical to one thread's,
//! for 2, 3 and 8 threads (each piece writes its own correspondences; the counts are integers
//! summed in piece order; the update accumulates in point order afterwards; the normals and the
//! voxels write disjoint storage, and the voxels' normals are summed in point order after both).
//! With more than one thread each scan's map insertion waits for the next scan's normals stage
//! (`Odometry::set_deferred_map`), and the downsampling's kept points are gathered in pieces into
//! a lent buffer (`Odometry::set_gather_buffer`); the map at the end is the same too. On two threads that
//! stage's jobs are put together in four ways (`parallel::Arrangement`: the free-space marks
//! with Ring FALS or with the voxel search, the normals' compaction and rotation in Ring FALS's
//! job or in two pieces after it); with the real clock used here another one is tried every 16
//! scans, each in turn, so each two-thread run below of 49 scans or more goes through all four.

use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use loglio_core::association::KnnScratch;
use loglio_core::odometry::{AssociationMode, Vlp32cStorage};
use loglio_core::parallel::{Job, MAX_WIDTH, Parallel};
use loglio_core::scan::{ScanPoint, ScanView};
use loglio_core::voxel_map::{MapPoint, VoxelMap};
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

/// Every scan's pose (bits) and association counts, then the map's voxel count and a digest of
/// its points, with `threads` (1: no split); and how many searches were split.
fn run(sc: &Scenario, threads: usize) -> (Vec<([u64; 7], u32)>, usize) {
    let pool = Threads(threads, AtomicUsize::new(0));
    let out = run_on(sc, &pool, AssociationMode::Full);
    (out, pool.1.load(Ordering::Relaxed))
}

/// [`run`]'s records with the jobs on `pool`.
fn run_on(sc: &Scenario, pool: &dyn Parallel, mode: AssociationMode) -> Vec<([u64; 7], u32)> {
    run_flushing(sc, pool, mode, false, false)
}

/// [`run_on`]; with `flush`, each scan's insertion goes in right after it (as the runner does
/// it between scans in a replay or a live run), so no insertion waits in the next scan's stage.
/// With `spoil`, every third scan holds returns the odometry refuses (no time, beyond range,
/// not finite), spread over both halves of the scan: the normals' compaction in two pieces
/// must start the second half where the valid points before the middle end.
fn run_flushing(
    sc: &Scenario,
    pool: &dyn Parallel,
    mode: AssociationMode,
    flush: bool,
    spoil: bool,
) -> Vec<([u64; 7], u32)> {
    let mut store = STORE.lock().unwrap_or_else(|e| e.into_inner());
    let threads = pool.width();
    let mut scratch = vec![KnnScratch::new(); MAX_WIDTH];
    let mut deferred = vec![MapPoint::default(); 32768];
    let mut gather = vec![ScanPoint::default(); 32768];
    let mut odo = store.odometry(&config_for(sc, mode)).unwrap();
    if threads > 1 {
        odo.set_parallel(pool, &mut scratch[..threads - 1]);
        odo.set_deferred_map(&mut deferred);
        odo.set_gather_buffer(&mut gather);
    }
    let mut clock = StdClock::default();
    let mut out = Vec::new();
    for ev in sc.events() {
        match ev {
            Event::Imu(s) => {
                odo.push_imu(s);
            }
            Event::Scan(s) => {
                let mut points = s.points.clone();
                if spoil && out.len() % 3 == 1 {
                    let n = points.len();
                    for (k, i) in (n / 3..n).step_by(211).enumerate() {
                        match k % 3 {
                            0 => points[i].t = -1.0,
                            1 => points[i].xyz = [5000.0, 0.0, 0.0],
                            _ => points[i].xyz[2] = f32::NAN,
                        }
                    }
                }
                let r =
                    odo.process_scan_timed(ScanView { start_ns: s.start_ns, points: &points }, &mut clock);
                let (p, q) = (r.pose.position, r.pose.rotation.coords);
                let bits = [p.x, p.y, p.z, q.x, q.y, q.z, q.w].map(f64::to_bits);
                out.push((bits, r.associations.accepted()));
                if flush {
                    odo.flush_map();
                }
            }
        }
    }
    if spoil {
        let scans = out.len() as u64;
        assert!(odo.stats().points_invalid >= scans / 3 * 100, "{:?}", odo.stats());
    }
    // The last scan's insertion waits with more than one thread; the flush puts it in.
    let points = |map: &VoxelMap<'_>| {
        let mut n = 0usize;
        map.for_each_point(|_, _, _| n += 1);
        n
    };
    let before = points(odo.map());
    odo.flush_map();
    let (after, voxels) = (points(odo.map()), odo.map().len());
    if threads > 1 && !flush {
        assert!(after > before, "the last scan's insertion did not wait ({before} -> {after} points)");
    } else {
        assert_eq!(after, before);
    }
    let mut digest = [0u64; 7];
    let mut k = 0u64;
    odo.map().for_each_point(|_, xyz, normal| {
        k += 1;
        let n = normal.unwrap_or([f32::NAN; 3]);
        for (d, v) in digest.iter_mut().zip(xyz.iter().chain(&n)) {
            *d = d.rotate_left(5) ^ u64::from(v.to_bits()) ^ k;
        }
    });
    digest[6] = k;
    out.push((digest, voxels as u32));
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
        let many = run_on(&sc, &pool, AssociationMode::Full);
        assert_eq!(many.len(), one.len());
        for (i, (a, b)) in one.iter().zip(&many).enumerate() {
            assert_eq!(a, b, "scan {i} differs on the host's pool of {width}");
        }
    }
}

/// Plain mode (no Ring FALS) defers the insertion too, beside the voxel search alone.
#[test]
fn plain_mode_gives_the_same_trajectory_and_map_on_two_threads() {
    let mut c = ScenarioConfig::new(ScenarioKind::Vehicle, SensorModel::Vlp32c, 5);
    c.duration_s = 4.0;
    let sc = Scenario::from_config(c).unwrap();
    let one = run_on(&sc, &Threads(1, AtomicUsize::new(0)), AssociationMode::Plain);
    let two = run_on(&sc, &Threads(2, AtomicUsize::new(0)), AssociationMode::Plain);
    assert!(one.iter().filter(|(_, n)| *n > 0).count() >= 15);
    assert_eq!(one, two);
}

/// With each insertion in before the next scan (a replay, a live run) the two-thread stage
/// starts with the normals' compaction and rotation in two pieces of their own after Ring
/// FALS's job (`parallel::Arrangement`'s first choice there) and tries the other three ways
/// every 16 scans: the same bits as one thread throughout, on scoped threads and on the host's
/// pool.
#[test]
fn with_the_map_flushed_between_scans_two_threads_give_the_same_bits() {
    let mut c = ScenarioConfig::new(ScenarioKind::Handheld, SensorModel::Vlp32c, 6);
    c.duration_s = 7.0;
    let sc = Scenario::from_config(c).unwrap();
    let one = run_flushing(&sc, &Threads(1, AtomicUsize::new(0)), AssociationMode::Full, true, true);
    assert!(one.iter().filter(|(_, n)| *n > 0).count() >= 40);
    let two = run_flushing(&sc, &Threads(2, AtomicUsize::new(0)), AssociationMode::Full, true, true);
    assert_eq!(one, two);
    let pool = loglio_host::run::pool::Pool::new(2);
    assert_eq!(one, run_flushing(&sc, &pool, AssociationMode::Full, true, true));
}
