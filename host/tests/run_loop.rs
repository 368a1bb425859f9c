//! The run loop as a library and as the commands use it: every scan's result and the
//! IMU-rate pose reach an embedding program's channel; the files follow the run; a signal ends
//! a run with everything written.

mod common;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::scenario::{Event as SimEvent, ScenarioKind};
use loglio_host::cmd::sim::{self, SimOptions};
use loglio_host::config::KnnReach;
use loglio_host::eval::{Format, read_trajectory};
use loglio_host::run::runner::OwnedScan;
use loglio_host::run::{self, Event, RunOptions};
use loglio_host::sink::files::OutputOptions;
use loglio_host::sink::{ChannelSink, LiveStatus, SinkEvent, SinkOptions, Sinks, Wants};

/// Poses in a TUM text (comment lines left out).
fn poses(tum: &str) -> usize {
    tum.lines().filter(|l| !l.starts_with('#')).count()
}

fn handheld(seconds: f64) -> SimOptions {
    SimOptions {
        kind: ScenarioKind::Handheld,
        sensor: SensorModel::Os1_16,
        seed: 1,
        duration_s: Some(seconds),
        mode: None,
        max_points: None,
        knn_search: KnnReach::Block,
        out: None,
        no_actors: false,
        progress: false,
        realtime: None,
        sinks: Default::default(),
        no_imu: false,
        standstill: true,
        keep_free_space: false,
        fixed_offset: false,
        imu_clock_offset_ns: 0,
        realism: Default::default(),
        lidar_imu_offset_s: 0.0,
    }
}

/// An embedding program's channel gets every scan's pose (equal to the trajectory written to
/// disk), the scan's points in the world frame, the map every 2 s of data, and between scans
/// the IMU-propagated pose at the IMU's rate, in time order.
#[test]
fn a_channel_receives_every_scan_the_cloud_the_map_and_the_imu_rate_pose() {
    let opt = handheld(6.0);
    let sc = sim::scenario(&opt).unwrap();
    let cfg = sim::scenario_config(&sc, sim::preset_of(opt.sensor), None);
    let dir = common::scratch("run-loop", "channel");
    let (sink, rx) = ChannelSink::new(Wants { cloud: true, map: true, imu_pose: true }, 1 << 16);
    // A queue that holds the whole run: the odometry runs far faster than real time here.
    let mut sinks = Sinks::new(SinkOptions { queue: 1 << 16, map_every_s: 2.0, finish_timeout_s: 10.0 });
    sinks.add(Box::new(sink)).unwrap();
    let mut events = sc.events().map(|ev| match ev {
        SimEvent::Imu(s) => Event::Imu(s),
        SimEvent::Scan(s) => {
            Event::Scan { scan: OwnedScan { start_ns: s.start_ns, points: s.points }, arrival_ns: 0 }
        }
    });
    let opts = RunOptions {
        outputs: OutputOptions { dir: Some(dir.to_path_buf()), ..OutputOptions::default() },
        sinks,
        ..RunOptions::default()
    };
    let (stats, _) = run::drive(&cfg, sc.layout().clone(), &mut events, opts).unwrap();
    let got: Vec<SinkEvent> = rx.try_iter().collect();
    assert_eq!(stats.sinks.len(), 1);
    assert_eq!(stats.sinks[0].lost(), 0, "{:?}", stats.sinks);

    let scans: Vec<_> = got
        .iter()
        .filter_map(|e| match e {
            SinkEvent::Scan(s) => Some(s.clone()),
            SinkEvent::ImuPose(_) => None,
        })
        .collect();
    assert_eq!(scans.len() as u64, stats.scans);
    assert!(scans.windows(2).all(|w| w[1].index == w[0].index + 1));
    // The tracked scans' poses are the trajectory's, to the TUM file's printed precision.
    let tum = read_trajectory(&dir.join("trajectory.tum"), Format::Tum, None).unwrap();
    let stamps = tum.stamps.as_ref().unwrap();
    let tracked: Vec<_> = scans.iter().filter(|s| s.pose.status != LiveStatus::Initialising).collect();
    assert_eq!(tracked.len(), tum.poses.len());
    assert!(tracked.len() >= 45, "{} tracked scans", tracked.len());
    for (s, (t, p)) in tracked.iter().zip(stamps.iter().zip(&tum.poses)) {
        assert!((s.pose.t_ns as f64 * 1e-9 - t).abs() < 1e-6);
        for k in 0..3 {
            assert!((s.pose.position[k] - p.t[k]).abs() < 1e-6, "{:?} vs {:?}", s.pose.position, p.t);
        }
        let cov = s.pose.pose_covariance;
        assert!((0..6).all(|i| cov[i][i] > 0.0 && cov[i][i].is_finite()));
        assert!(s.pose.status.is_tracking());
        // The scan's points: as many as the map received, near the sensor (the handheld walk
        // stays in a room of a few metres).
        if let Some(c) = &s.cloud {
            assert_eq!(c.len(), s.points[1] as usize);
            let p = s.pose.position;
            assert!(c.iter().all(|q| {
                let d2: f64 = (0..3).map(|k| (f64::from(q[k]) - p[k]).powi(2)).sum();
                d2 < 100.0 * 100.0
            }));
        }
    }
    assert!(tracked.iter().filter(|s| s.cloud.as_ref().is_some_and(|c| !c.is_empty())).count() >= 40);
    // The map every 2 s of data: 6 s with 1 s of initialisation gives 3.
    let maps: Vec<usize> = scans.iter().filter_map(|s| s.map.as_ref().map(|m| m.len())).collect();
    assert!((2..=3).contains(&maps.len()), "{maps:?}");
    assert!(maps.windows(2).all(|w| w[1] >= w[0]) && maps[0] > 1000, "{maps:?}");

    // The IMU-rate pose: every IMU sample after the first tracked scan (200 Hz), between the
    // scans, in time order, continuous with the next scan's pose.
    let mut last_t = 0u64;
    let mut imu_poses = 0usize;
    let mut worst_jump = 0.0f64;
    let mut prev_pose: Option<[f64; 3]> = None;
    for e in &got {
        let (t, p) = match e {
            SinkEvent::Scan(s) if s.pose.status.is_tracking() => (s.pose.t_ns, s.pose.position),
            SinkEvent::Scan(_) => continue,
            SinkEvent::ImuPose(p) => {
                imu_poses += 1;
                (p.t_ns, p.position)
            }
        };
        if let Some(q) = prev_pose {
            let d = (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f64>().sqrt();
            worst_jump = worst_jump.max(d);
        }
        prev_pose = Some(p);
        if let SinkEvent::ImuPose(_) = e {
            assert!(t > last_t, "an IMU pose at {t} after {last_t}");
        }
        last_t = last_t.max(t);
    }
    let span_s = (tracked.last().unwrap().pose.t_ns - tracked[0].pose.t_ns) as f64 * 1e-9;
    let rate = imu_poses as f64 / span_s;
    assert!((180.0..=210.0).contains(&rate), "{imu_poses} IMU poses over {span_s:.2} s: {rate:.0} Hz");
    // A walking pace: no step between consecutive poses of more than a few centimetres.
    assert!(worst_jump < 0.05, "a {worst_jump:.3} m step between consecutive poses");
}

/// A stop flag (what SIGINT sets) ends the run as if the source had ended: every output written.
#[test]
fn the_stop_flag_ends_the_run_with_everything_written() {
    let opt = handheld(8.0);
    let sc = sim::scenario(&opt).unwrap();
    let cfg = sim::scenario_config(&sc, sim::preset_of(opt.sensor), None);
    let dir = common::scratch("run-loop", "stop");
    let stop = Arc::new(AtomicBool::new(false));
    let flag = Arc::clone(&stop);
    let mut scans = 0;
    let mut events = sc.events().map(move |ev| match ev {
        SimEvent::Imu(s) => Event::Imu(s),
        SimEvent::Scan(s) => {
            scans += 1;
            if scans == 40 {
                flag.store(true, Ordering::Relaxed);
            }
            Event::Scan { scan: OwnedScan { start_ns: s.start_ns, points: s.points }, arrival_ns: 0 }
        }
    });
    let opts = RunOptions {
        outputs: OutputOptions { dir: Some(dir.to_path_buf()), map: true, ..OutputOptions::default() },
        stop: Some(stop),
        ..RunOptions::default()
    };
    let ((stats, fin), warnings) =
        loglio_host::diag::capture(|| run::drive(&cfg, sc.layout().clone(), &mut events, opts).unwrap());
    assert_eq!(stats.scans, 40);
    assert_eq!(warnings, ["warning: stopped by a signal; writing what was estimated"]);
    assert!(fin.map_points > 1000);
    let tum = std::fs::read_to_string(dir.join("trajectory.tum")).unwrap();
    assert_eq!(poses(&tum), 30, "40 scans less the 10 of the initialisation");
    assert!(dir.join("map.ply").exists());
}

/// `loglio sim --realtime`: the files are whole lines up to the last scan while the run goes
/// on, and SIGINT ends it with every output and the summary (exit 0).
#[test]
fn sigint_ends_a_realtime_sim_with_every_output_and_the_files_follow_the_run() {
    let dir = common::scratch("run-loop", "sigint");
    let out = dir.to_str().unwrap().to_string();
    let child = common::loglio_command(&[
        "sim",
        "--scenario",
        "handheld",
        "--sensor",
        "os1-16",
        "--seconds",
        "60",
        "--realtime",
        "--out",
        &out,
    ])
    .stdout(std::process::Stdio::piped())
    .stderr(std::process::Stdio::piped())
    .spawn()
    .unwrap();
    // Wait until the trajectory has 25 poses (about 2.5 s of real time after the initialisation;
    // longer under an emulator), reading it as a consumer would.
    let tum = dir.join("trajectory.tum");
    let t0 = Instant::now();
    let mut lines = 0;
    while t0.elapsed() < Duration::from_secs(120) {
        std::thread::sleep(Duration::from_millis(200));
        let text = std::fs::read_to_string(&tum).unwrap_or_default();
        // Flushed per scan: never a partial line.
        assert!(text.is_empty() || text.ends_with('\n'), "a partial line: {text:?}");
        assert!(text.lines().all(|l| l.starts_with('#') || l.split_whitespace().count() == 8), "{text}");
        lines = poses(&text);
        if lines >= 25 {
            break;
        }
    }
    assert!(lines >= 25, "only {lines} poses after {:?}", t0.elapsed());
    let status = std::process::Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap();
    assert!(status.success());
    let out = child.wait_with_output().unwrap();
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(stderr.contains("warning: stopped by a signal; writing what was estimated"), "{stderr}");
    assert!(stdout.contains("ATE against ground truth"), "{stdout}");
    let text = std::fs::read_to_string(&tum).unwrap();
    assert!(poses(&text) >= lines && poses(&text) < 590, "{} poses", poses(&text));
    for f in ["scans.csv", "map.ply", "map.pcd", "groundtruth.tum", "eval.json"] {
        assert!(dir.join(f).exists(), "{f} missing");
    }
}
