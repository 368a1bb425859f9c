use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::*;

fn pose(t_ns: u64) -> PoseSample {
    PoseSample::placeholder(t_ns, LiveStatus::Ok, 0)
}

fn scan(index: u64) -> SinkEvent {
    SinkEvent::Scan(Arc::new(ScanOutput {
        index,
        scan_start_ns: index * 100_000_000,
        pose: pose(index * 100_000_000 + 99_000_000),
        process_ms: 1.0,
        map_voxels: 0,
        points: [0, 0],
        cloud: None,
        map: None,
        arrival_ns: 0,
        ready_ns: 0,
    }))
}

/// A sink that blocks on a gate until the test opens it, recording what it handled.
struct Gated {
    gate: Arc<(Mutex<bool>, std::sync::Condvar)>,
    seen: Arc<Mutex<Vec<String>>>,
    fail_every: Option<u64>,
    n: u64,
}

impl Sink for Gated {
    fn name(&self) -> String {
        "gated test".into()
    }
    fn wants(&self) -> Wants {
        Wants { imu_pose: true, ..Wants::default() }
    }
    fn handle(&mut self, ev: &SinkEvent) -> Result<(), SinkError> {
        let (m, cv) = &*self.gate;
        let mut open = m.lock().unwrap();
        while !*open {
            open = cv.wait(open).unwrap();
        }
        drop(open);
        self.n += 1;
        self.seen.lock().unwrap().push(match ev {
            SinkEvent::Scan(s) => format!("scan {}", s.index),
            SinkEvent::ImuPose(p) => format!("pose {}", p.t_ns),
        });
        match self.fail_every {
            Some(k) if self.n.is_multiple_of(k) => Err(SinkError(format!("failure {}", self.n))),
            _ => Ok(()),
        }
    }
}

type Gate = Arc<(Mutex<bool>, std::sync::Condvar)>;

fn gated(fail_every: Option<u64>) -> (Box<Gated>, Gate, Arc<Mutex<Vec<String>>>) {
    let gate = Arc::new((Mutex::new(false), std::sync::Condvar::new()));
    let seen = Arc::new(Mutex::new(Vec::new()));
    (Box::new(Gated { gate: Arc::clone(&gate), seen: Arc::clone(&seen), fail_every, n: 0 }), gate, seen)
}

fn open(gate: &(Mutex<bool>, std::sync::Condvar)) {
    *gate.0.lock().unwrap() = true;
    gate.1.notify_all();
}

/// A stuck sink never holds the sender up: sending 1,000 events to a queue of 4 whose sink is
/// blocked returns at once, and every event that did not fit is counted, poses evicted before
/// scans. Once the sink is unblocked it gets the rest in order.
#[test]
fn a_blocked_sink_drops_and_counts_instead_of_waiting() {
    let (sink, gate, seen) = gated(None);
    let mut q = SinkQueue::start(sink, 4).unwrap();
    let t = Instant::now();
    // The sink thread takes the first event and blocks in it; then 4 fit in the queue.
    assert!(q.try_send(scan(0)));
    std::thread::sleep(Duration::from_millis(50));
    for i in 1..=3 {
        assert!(q.try_send(scan(i)));
    }
    assert!(q.try_send(SinkEvent::ImuPose(pose(1))));
    // Full: a scan evicts the waiting pose; the next scans are refused; poses are refused.
    assert!(q.try_send(scan(4)));
    for i in 5..500 {
        assert!(!q.try_send(scan(i)));
        assert!(!q.try_send(SinkEvent::ImuPose(pose(i))));
    }
    assert!(t.elapsed() < Duration::from_secs(2), "the sender waited");
    let st = q.stats();
    assert_eq!(st.queued, 6);
    assert_eq!(st.dropped_scans, 495);
    assert_eq!(st.dropped_poses, 1 + 495);
    open(&gate);
    let st = q.finish(Duration::from_secs(5));
    assert_eq!(st.handled, 5);
    assert_eq!(st.errors, 0);
    assert_eq!(*seen.lock().unwrap(), ["scan 0", "scan 1", "scan 2", "scan 3", "scan 4"]);
}

/// Errors are counted per event and the first is kept; the sink keeps receiving.
#[test]
fn errors_are_counted_and_the_sink_goes_on() {
    let (sink, gate, seen) = gated(Some(3));
    open(&gate);
    let mut sinks = Sinks::new(SinkOptions { queue: 64, ..SinkOptions::default() });
    sinks.add(sink).unwrap();
    for i in 0..10 {
        sinks.send(scan(i));
    }
    assert!(sinks.drain(Duration::from_secs(5)));
    let st = sinks.finish();
    assert_eq!(st.len(), 1);
    assert_eq!(st[0].handled, 10);
    assert_eq!(st[0].errors, 3);
    assert_eq!(st[0].first_error.as_deref(), Some("failure 3"));
    assert_eq!(st[0].lost(), 3);
    assert_eq!(seen.lock().unwrap().len(), 10);
    let lines = sinks_summary(&st);
    assert_eq!(lines.len(), 1);
    assert!(lines[0].starts_with("gated test: 7 events sent, 0 scans and 0 poses dropped"), "{}", lines[0]);
    assert_eq!(sinks_phrase(&st), "gated 3 lost");
}

/// A sink still stuck at the end is left behind after the timeout, its queue counted as
/// dropped: the run ends.
#[test]
fn a_stuck_sink_does_not_hold_the_end_of_the_run() {
    let (sink, _gate, _) = gated(None);
    let mut sinks = Sinks::new(SinkOptions { queue: 8, map_every_s: 5.0, finish_timeout_s: 0.2 });
    sinks.add(sink).unwrap();
    for i in 0..5 {
        sinks.send(scan(i));
    }
    let t = Instant::now();
    let st = sinks.finish();
    assert!(t.elapsed() < Duration::from_secs(3));
    assert_eq!(st[0].handled, 0);
    // One was taken by the blocked thread, four waited and are counted as dropped.
    assert_eq!(st[0].dropped_scans, 4);
}

/// The channel sink: events arrive in order; a dropped receiver is an error, not a panic.
#[test]
fn channel_sink_delivers_in_order_and_survives_a_gone_receiver() {
    let (sink, rx) = ChannelSink::new(Wants::default(), 16);
    let mut sinks = Sinks::new(SinkOptions::default());
    sinks.add(Box::new(sink)).unwrap();
    // Not wanted: high-rate poses are not even queued.
    sinks.send(SinkEvent::ImuPose(pose(7)));
    for i in 0..3 {
        sinks.send(scan(i));
    }
    let got: Vec<u64> = (0..3)
        .map(|_| match rx.recv_timeout(Duration::from_secs(5)).unwrap() {
            SinkEvent::Scan(s) => s.index,
            SinkEvent::ImuPose(_) => panic!("an unwanted pose"),
        })
        .collect();
    assert_eq!(got, [0, 1, 2]);
    assert!(matches!(rx.try_recv(), Err(mpsc::TryRecvError::Empty)));
    drop(rx);
    sinks.send(scan(3));
    let st = sinks.finish();
    assert_eq!(st[0].errors, 1);
    assert_eq!(st[0].first_error.as_deref(), Some("the receiver is gone"));
}

#[test]
fn status_names_and_quality() {
    assert_eq!(LiveStatus::Degraded { axes: 0b100001 }.to_string(), "degraded (x,yaw)");
    assert_eq!(LiveStatus::Lost.to_string(), "lost");
    assert_eq!(LiveStatus::Ok.quality(), 100);
    assert_eq!(LiveStatus::Lost.quality(), 0);
    assert!(!LiveStatus::Initialising.is_tracking());
}

/// The wire latency is the pose's send time less the scan's arrival on the run's clock, kept
/// beside the processing time; scans of unknown arrival (files) and failed sends are left out.
#[test]
fn wire_latency_is_measured_on_the_runs_clock() {
    let (sink, gate, _) = gated(Some(4));
    open(&gate);
    let mut sinks = Sinks::new(SinkOptions { queue: 64, ..SinkOptions::default() });
    // The origin 1 s ago; scans "arrived" 30 ms before now on that clock.
    let origin = Instant::now() - Duration::from_secs(1);
    sinks.set_origin(origin);
    sinks.add(sink).unwrap();
    for i in 0..5 {
        let SinkEvent::Scan(mut s) = scan(i) else { unreachable!() };
        let o = Arc::make_mut(&mut s);
        o.arrival_ns = if i == 2 { 0 } else { origin.elapsed().as_nanos() as u64 - 30_000_000 };
        o.process_ms = 20.0;
        sinks.send(SinkEvent::Scan(s));
    }
    let st = sinks.finish();
    // Scan 2 has no arrival; the 4th handled (scan 3) failed.
    assert_eq!(st[0].wire.scans, 3);
    let [med, p99] = st[0].wire.latency_ms().unwrap();
    assert!((30.0..1000.0).contains(&med) && p99 >= med, "{med} {p99}");
    assert_eq!(st[0].wire.process_ms(), Some([20.0, 20.0]));
    let line = &sinks_summary(&st)[0];
    assert!(line.contains("; pose latency from the scan's last packet: median "), "{line}");
    assert!(line.contains("(processing of the same 3 scans: median 20.0 ms, p99 20.0 ms)"), "{line}");
}

/// Without an origin (a file run) nothing is measured and the summary says nothing of it.
#[test]
fn no_origin_no_latency() {
    let (sink, gate, _) = gated(None);
    open(&gate);
    let mut sinks = Sinks::new(SinkOptions::default());
    sinks.add(sink).unwrap();
    let SinkEvent::Scan(mut s) = scan(0) else { unreachable!() };
    Arc::make_mut(&mut s).arrival_ns = 5;
    sinks.send(SinkEvent::Scan(s));
    let st = sinks.finish();
    assert_eq!(st[0].wire, WireLatency::default());
    assert!(!sinks_summary(&st)[0].contains("latency"));
}

/// Median and p99 by nearest rank; past the cap a uniform reservoir keeps the size bounded.
#[test]
fn wire_latency_quantiles_and_bound() {
    let mut w = WireLatency::default();
    assert_eq!(w.latency_ms(), None);
    assert_eq!(w.phrase(), None);
    for i in 1..=100u64 {
        w.record(i * 1_000_000, 500_000);
    }
    assert_eq!(w.latency_ms(), Some([50.0, 99.0]));
    assert_eq!(w.process_ms(), Some([0.5, 0.5]));
    for i in 0..(WireLatency::CAP as u64 * 3) {
        w.record(i % 1000 * 1000, 0);
    }
    assert_eq!(w.scans, 100 + WireLatency::CAP as u64 * 3);
    let [med, _] = w.latency_ms().unwrap();
    assert!((0.4..0.6).contains(&med), "{med}");
}
