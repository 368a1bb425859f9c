//! MAVLink 2 live output: `HEARTBEAT` at 1 Hz and `ODOMETRY` for every scan plus the
//! IMU-propagated pose at a chosen rate, to an autopilot's external-vision input (PX4 EKF2,
//! ArduPilot EKF3) over UDP or a serial port.
//!
//! The encoder is hand-written for exactly these two messages (field order, CRC_EXTRA and enum
//! values from MAVLink's `common.xml` / `minimal.xml`), so no generated dialect is compiled.
//!
//! Frames: loglio's world is z up with x along the start's heading and its body is the IMU's,
//! ROS FLU. Both are turned 180° about x into FRD. `frame_id` is `MAV_FRAME_LOCAL_FRD`, not
//! `LOCAL_NED`: the world's x is the start's heading, not north, which is what LOCAL_FRD means
//! ("arbitrary heading reference"); PX4 maps LOCAL_FRD to its vision odometry, and ArduPilot's
//! `handle_odometry` accepts only `LOCAL_FRD` with `BODY_FRD`.
//!
//! `time_usec` is the pose's time on the LiDAR's clock (the autopilots estimate the offset to
//! their own). The heartbeat goes out with the events, once a wall-clock second: when the
//! odometry stops, so does the component's heartbeat, which a ground station shows.

use std::io::{self, Write};
use std::net::{SocketAddr, ToSocketAddrs, UdpSocket};
use std::time::{Duration, Instant};

use super::{LiveStatus, PoseSample, Sink, SinkError, SinkEvent, Wants};

/// MAVLink 2 start-of-frame marker.
pub const STX: u8 = 0xFD;
/// Header bytes (STX to the 24-bit message id).
pub const HEADER_LEN: usize = 10;
/// The longest unsigned frame: header, 255 payload bytes, CRC.
pub const MAX_FRAME_LEN: usize = HEADER_LEN + 255 + 2;

/// `HEARTBEAT` message id and CRC_EXTRA (minimal.xml).
pub const HEARTBEAT_ID: u32 = 0;
const HEARTBEAT_CRC_EXTRA: u8 = 50;
/// `ODOMETRY` message id and CRC_EXTRA (common.xml).
pub const ODOMETRY_ID: u32 = 331;
const ODOMETRY_CRC_EXTRA: u8 = 91;
/// `ODOMETRY` payload length with its three extension fields, before truncation.
pub const ODOMETRY_LEN: usize = 233;
const HEARTBEAT_LEN: usize = 9;

/// `MAV_TYPE_ONBOARD_CONTROLLER`.
pub const MAV_TYPE_ONBOARD_CONTROLLER: u8 = 18;
/// `MAV_AUTOPILOT_INVALID` (not a flight controller).
pub const MAV_AUTOPILOT_INVALID: u8 = 8;
/// `MAV_FRAME_LOCAL_FRD`.
pub const MAV_FRAME_LOCAL_FRD: u8 = 20;
/// `MAV_FRAME_BODY_FRD`.
pub const MAV_FRAME_BODY_FRD: u8 = 12;
/// `MAV_ESTIMATOR_TYPE_LIDAR`.
pub const MAV_ESTIMATOR_TYPE_LIDAR: u8 = 7;
/// `MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY`, the default component id.
pub const MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY: u8 = 197;

/// `MAV_STATE` values used in the heartbeat.
pub mod mav_state {
    /// Booting up (loglio: waiting for the IMU initialisation).
    pub const BOOT: u8 = 1;
    /// Active (tracking, possibly degraded).
    pub const ACTIVE: u8 = 4;
    /// Non-normal mode, can still navigate (IMU only, or lost and re-initialising).
    pub const CRITICAL: u8 = 5;
}

/// Why a frame could not be encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EncodeError {
    /// The payload is longer than MAVLink's 255 bytes.
    PayloadTooLong,
    /// The message id does not fit in 24 bits.
    BadMessageId,
    /// The output buffer is too small for the frame.
    BufferTooSmall,
}

impl std::fmt::Display for EncodeError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            EncodeError::PayloadTooLong => "payload longer than 255 bytes",
            EncodeError::BadMessageId => "message id beyond 24 bits",
            EncodeError::BufferTooSmall => "output buffer too small",
        })
    }
}

/// One byte into a CRC-16/MCRF4XX (MAVLink's X.25 variant: reflected 0x1021, init 0xFFFF).
pub fn crc_accumulate(b: u8, crc: u16) -> u16 {
    let mut tmp = b ^ (crc & 0xFF) as u8;
    tmp ^= tmp << 4;
    let t = u16::from(tmp);
    (crc >> 8) ^ (t << 8) ^ (t << 3) ^ (t >> 4)
}

/// CRC-16/MCRF4XX of `data` from the initial value 0xFFFF.
pub fn crc16(data: &[u8]) -> u16 {
    data.iter().fold(0xFFFF, |c, &b| crc_accumulate(b, c))
}

/// Frames MAVLink 2 messages for one system and component, counting the sequence.
#[derive(Clone, Copy, Debug)]
pub struct Encoder {
    /// System id.
    pub sysid: u8,
    /// Component id.
    pub compid: u8,
    seq: u8,
}

impl Encoder {
    /// An encoder whose first frame has sequence 0.
    pub fn new(sysid: u8, compid: u8) -> Encoder {
        Encoder { sysid, compid, seq: 0 }
    }

    /// Writes one unsigned MAVLink 2 frame of `payload` into `out` and returns its length.
    /// Trailing zero bytes of the payload are left out (MAVLink 2 truncation; the first byte
    /// always stays). The sequence advances only on success.
    pub fn frame(
        &mut self,
        msgid: u32,
        crc_extra: u8,
        payload: &[u8],
        out: &mut [u8],
    ) -> Result<usize, EncodeError> {
        if payload.len() > 255 {
            return Err(EncodeError::PayloadTooLong);
        }
        if msgid > 0xFF_FFFF {
            return Err(EncodeError::BadMessageId);
        }
        let len = payload.iter().rposition(|&b| b != 0).map_or(1, |i| i + 1).min(payload.len());
        let total = HEADER_LEN + len + 2;
        let out = out.get_mut(..total).ok_or(EncodeError::BufferTooSmall)?;
        let id = msgid.to_le_bytes();
        out[..HEADER_LEN].copy_from_slice(&[
            STX,
            len as u8,
            0,
            0,
            self.seq,
            self.sysid,
            self.compid,
            id[0],
            id[1],
            id[2],
        ]);
        out[HEADER_LEN..HEADER_LEN + len].copy_from_slice(&payload[..len]);
        let crc = crc_accumulate(crc_extra, crc16(&out[1..HEADER_LEN + len]));
        out[HEADER_LEN + len..].copy_from_slice(&crc.to_le_bytes());
        self.seq = self.seq.wrapping_add(1);
        Ok(total)
    }
}

/// Little-endian writer over a fixed payload buffer (the lengths are the messages' own, so it
/// cannot run out; a wrong length would show in the layout tests).
struct Put<'a> {
    buf: &'a mut [u8],
    at: usize,
}

impl Put<'_> {
    fn bytes(&mut self, b: &[u8]) {
        if let Some(d) = self.buf.get_mut(self.at..self.at + b.len()) {
            d.copy_from_slice(b);
        }
        self.at += b.len();
    }
    fn f32s(&mut self, v: &[f32]) {
        for x in v {
            self.bytes(&x.to_le_bytes());
        }
    }
}

/// The `HEARTBEAT` payload of a component with `system_status` (a `MAV_STATE`).
pub fn heartbeat_payload(system_status: u8) -> [u8; HEARTBEAT_LEN] {
    // custom_mode u32, type, autopilot, base_mode, system_status, mavlink_version (3).
    let mut p = [0u8; HEARTBEAT_LEN];
    p[4] = MAV_TYPE_ONBOARD_CONTROLLER;
    p[5] = MAV_AUTOPILOT_INVALID;
    p[7] = system_status;
    p[8] = 3;
    p
}

/// The heartbeat's `MAV_STATE` of an odometry status.
pub fn system_status(s: LiveStatus) -> u8 {
    match s {
        LiveStatus::Initialising => mav_state::BOOT,
        LiveStatus::Ok | LiveStatus::Degraded { .. } | LiveStatus::Bridged { .. } => mav_state::ACTIVE,
        LiveStatus::ImuOnly | LiveStatus::Lost => mav_state::CRITICAL,
    }
}

/// MAVLink's `quality` (percent): -1 lost (the spec's "failed"), 0 initialising ("unknown"),
/// else [`LiveStatus::quality`] (100 ok, 50 degraded, 20 IMU only).
pub fn quality(s: LiveStatus) -> i8 {
    match s {
        LiveStatus::Lost => -1,
        s => i8::try_from(s.quality().min(100)).unwrap_or(100),
    }
}

/// One `ODOMETRY` message in MAVLink's conventions (FRD world and body).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Odometry {
    /// Pose time, µs (the LiDAR's clock).
    pub time_usec: u64,
    /// Position in LOCAL_FRD, m.
    pub position: [f32; 3],
    /// LOCAL_FRD from BODY_FRD rotation (w, x, y, z).
    pub q: [f32; 4],
    /// Velocity in BODY_FRD, m/s.
    pub velocity: [f32; 3],
    /// Body rates (roll, pitch, yaw speed), rad/s.
    pub rates: [f32; 3],
    /// Pose covariance, upper-right triangle row-major (x, y, z, roll, pitch, yaw).
    pub pose_covariance: [f32; 21],
    /// Velocity covariance, upper-right triangle row-major (vx, vy, vz, roll/pitch/yaw rate).
    pub velocity_covariance: [f32; 21],
    /// Resets so far (wrapping).
    pub reset_counter: u8,
    /// Quality, see [`quality`].
    pub quality: i8,
}

/// FLU/z-up to FRD/z-down: 180° about x, i.e. the signs of y and z flip (its own inverse).
const FLIP: [f64; 6] = [1.0, -1.0, -1.0, 1.0, -1.0, -1.0];

/// The upper-right triangle (row-major, 21 values) of `c` with each entry's sign flipped as the
/// 180° turn about x requires; entries of index 3-5 given as `None` are unknown (NaN).
fn flip_triangle(c: impl Fn(usize, usize) -> Option<f64>) -> [f32; 21] {
    let mut out = [f32::NAN; 21];
    let mut k = 0;
    for (i, fi) in FLIP.iter().enumerate() {
        for (j, fj) in FLIP.iter().enumerate().skip(i) {
            out[k] = c(i, j).map_or(f32::NAN, |v| (fi * fj * v) as f32);
            k += 1;
        }
    }
    out
}

impl Odometry {
    /// The message of a pose: world and body turned from z-up/FLU to FRD. The pose covariance's
    /// rotation part is loglio's body-frame rotation error, which for small errors is the
    /// roll/pitch/yaw error MAVLink asks for. loglio has no covariance of the body rates: that
    /// part of the velocity covariance (and its cross terms) is NaN.
    pub fn of(p: &PoseSample) -> Odometry {
        let f3 = |v: [f64; 3]| [v[0] as f32, -v[1] as f32, -v[2] as f32];
        let [w, x, y, z] = p.q_wxyz;
        let n = (w * w + x * x + y * y + z * z).sqrt();
        let n = if n > 0.0 && n.is_finite() { n } else { 1.0 };
        Odometry {
            time_usec: p.t_ns / 1000,
            position: f3(p.position),
            // F q F with F = 180° about x: w and x stay, y and z change sign.
            q: [(w / n) as f32, (x / n) as f32, (-y / n) as f32, (-z / n) as f32],
            velocity: f3(p.velocity_body),
            rates: f3(p.angular_velocity_body),
            pose_covariance: flip_triangle(|i, j| Some(p.pose_covariance[i][j])),
            velocity_covariance: flip_triangle(|i, j| (j < 3).then(|| p.velocity_covariance[i][j])),
            reset_counter: (p.resets & 0xFF) as u8,
            quality: quality(p.status),
        }
    }

    /// The payload in wire order (fields sorted by size, then the extensions in order).
    pub fn payload(&self) -> [u8; ODOMETRY_LEN] {
        let mut buf = [0u8; ODOMETRY_LEN];
        let mut w = Put { buf: &mut buf, at: 0 };
        w.bytes(&self.time_usec.to_le_bytes());
        w.f32s(&self.position);
        w.f32s(&self.q);
        w.f32s(&self.velocity);
        w.f32s(&self.rates);
        w.f32s(&self.pose_covariance);
        w.f32s(&self.velocity_covariance);
        w.bytes(&[
            MAV_FRAME_LOCAL_FRD,
            MAV_FRAME_BODY_FRD,
            self.reset_counter,
            MAV_ESTIMATOR_TYPE_LIDAR,
            self.quality.to_le_bytes()[0],
        ]);
        debug_assert_eq!(w.at, ODOMETRY_LEN);
        buf
    }
}

/// Where the frames go, as given on the command line.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum MavlinkUrl {
    /// `udp:HOST:PORT` or `udpout:HOST:PORT`: datagrams to that address.
    Udp {
        /// Host name or address.
        host: String,
        /// Port.
        port: u16,
    },
    /// `serial:/dev/PATH:BAUD`.
    Serial {
        /// Device path.
        path: String,
        /// Baud rate.
        baud: u32,
    },
}

impl std::str::FromStr for MavlinkUrl {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let usage = "expected udp:HOST:PORT, udpout:HOST:PORT or serial:/dev/PATH:BAUD";
        let (scheme, rest) = s.split_once(':').ok_or_else(|| format!("'{s}': {usage}"))?;
        let (head, tail) = rest.rsplit_once(':').ok_or_else(|| format!("'{s}': {usage}"))?;
        match scheme {
            "udp" | "udpout" => {
                let host = head.trim_start_matches('[').trim_end_matches(']');
                let port: u16 = tail.parse().map_err(|_| format!("'{s}': bad port '{tail}'; {usage}"))?;
                if host.is_empty() || port == 0 {
                    return Err(format!("'{s}': {usage}"));
                }
                Ok(MavlinkUrl::Udp { host: host.to_string(), port })
            }
            "serial" => {
                let baud: u32 =
                    tail.parse().map_err(|_| format!("'{s}': bad baud rate '{tail}'; {usage}"))?;
                if head.is_empty() || baud == 0 {
                    return Err(format!("'{s}': {usage}"));
                }
                Ok(MavlinkUrl::Serial { path: head.to_string(), baud })
            }
            _ => Err(format!("'{s}': unknown scheme '{scheme}'; {usage}")),
        }
    }
}

impl std::fmt::Display for MavlinkUrl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            MavlinkUrl::Udp { host, port } if host.contains(':') => write!(f, "udp:[{host}]:{port}"),
            MavlinkUrl::Udp { host, port } => write!(f, "udp:{host}:{port}"),
            MavlinkUrl::Serial { path, baud } => write!(f, "serial:{path}:{baud}"),
        }
    }
}

/// Why a serial link at `baud` (8N1: 10 bits a byte) cannot carry ODOMETRY at `rate_hz` (scans
/// at 10 Hz at least) plus the heartbeat; `None` when it can. A UART that cannot keep up
/// blocks each write until its timeout: errors and dropped poses, not a slower odometry.
pub fn serial_too_slow(baud: u32, rate_hz: f64) -> Option<String> {
    let frame = (HEADER_LEN + ODOMETRY_LEN + 2) as f64;
    let need = rate_hz.max(10.0) * frame + (HEADER_LEN + HEARTBEAT_LEN + 2) as f64;
    let have = f64::from(baud) / 10.0;
    (have < need).then(|| {
        format!(
            "{baud} baud carries about {:.0} ODOMETRY messages a second, not {rate_hz}; raise the baud rate \
             (e.g. 921600) or lower --mavlink-rate",
            (have / frame).floor()
        )
    })
}

/// The sink's options.
#[derive(Clone, Debug, PartialEq)]
pub struct MavlinkOptions {
    /// Where to send.
    pub url: MavlinkUrl,
    /// Rate of the IMU-propagated poses between scans, Hz (0: scans only).
    pub rate_hz: f64,
    /// System id.
    pub sysid: u8,
    /// Component id.
    pub compid: u8,
}

enum Transport {
    Udp(UdpSocket),
    Serial(Box<dyn serialport::SerialPort>),
}

impl Transport {
    fn open(url: &MavlinkUrl) -> Result<Transport, SinkError> {
        match url {
            MavlinkUrl::Udp { host, port } => {
                let addr: SocketAddr = (host.as_str(), *port)
                    .to_socket_addrs()
                    .map_err(|e| SinkError(format!("cannot resolve {host}: {e}")))?
                    .next()
                    .ok_or_else(|| SinkError(format!("{host} has no address")))?;
                let local: SocketAddr =
                    if addr.is_ipv4() { ([0, 0, 0, 0], 0).into() } else { ([0u16; 8], 0).into() };
                let s = UdpSocket::bind(local)?;
                // Connected, so the kernel reports an unreachable port (ICMP) on a later send;
                // non-blocking, so a full send buffer is an error, never a wait.
                s.connect(addr).map_err(|e| SinkError(format!("cannot reach {addr}: {e}")))?;
                s.set_nonblocking(true)?;
                Ok(Transport::Udp(s))
            }
            MavlinkUrl::Serial { path, baud } => {
                let p = crate::input::serial::open(path, *baud, Duration::from_millis(100))
                    .map_err(|e| SinkError(format!("cannot open {path}: {e}")))?;
                Ok(Transport::Serial(p))
            }
        }
    }

    fn send(&mut self, frame: &[u8]) -> io::Result<()> {
        match self {
            Transport::Udp(s) => s.send(frame).map(|_| ()),
            Transport::Serial(p) => p.write_all(frame),
        }
    }
}

/// The MAVLink output: a [`Sink`] that wants the high-rate pose.
pub struct MavlinkSink {
    opt: MavlinkOptions,
    out: Transport,
    enc: Encoder,
    buf: [u8; MAX_FRAME_LEN],
    status: LiveStatus,
    last_heartbeat: Option<Instant>,
    /// Time of the last ODOMETRY sent (keeps the IMU poses after the scan pose in time).
    last_sent_ns: Option<u64>,
    /// Time of the last tracking scan pose (the IMU poses extrapolate from it).
    last_scan_ns: Option<u64>,
    /// The latest interval between two scan poses, ns.
    scan_dt_ns: Option<u64>,
    /// When the latest scan's ODOMETRY was sent.
    pose_sent: Option<Instant>,
}

/// How far past the last scan pose IMU-propagated poses are sent, ns. Without scans (a LiDAR
/// unplugged) the IMU alone drifts within seconds, yet would still carry the last scan's
/// status and quality: the autopilot had better see the odometry stop.
pub const MAX_IMU_AHEAD_NS: u64 = 500_000_000;

impl std::fmt::Debug for MavlinkSink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MavlinkSink").field("opt", &self.opt).finish_non_exhaustive()
    }
}

impl MavlinkSink {
    /// Opens the transport (a UDP socket connected to the address, or the serial port).
    pub fn new(opt: MavlinkOptions) -> Result<MavlinkSink, SinkError> {
        let out = Transport::open(&opt.url)?;
        Ok(MavlinkSink {
            enc: Encoder::new(opt.sysid, opt.compid),
            opt,
            out,
            buf: [0; MAX_FRAME_LEN],
            status: LiveStatus::Initialising,
            last_heartbeat: None,
            last_sent_ns: None,
            last_scan_ns: None,
            scan_dt_ns: None,
            pose_sent: None,
        })
    }

    fn send(&mut self, msgid: u32, crc_extra: u8, payload: &[u8]) -> Result<(), SinkError> {
        let n = self
            .enc
            .frame(msgid, crc_extra, payload, &mut self.buf)
            .map_err(|e| SinkError(format!("cannot encode message {msgid}: {e}")))?;
        self.out.send(&self.buf[..n]).map_err(|e| SinkError(format!("send: {e}")))
    }

    /// The heartbeat when a second has passed since the last (wall time).
    fn heartbeat_if_due(&mut self) -> Result<(), SinkError> {
        let now = Instant::now();
        if self.last_heartbeat.is_some_and(|t| now.duration_since(t) < Duration::from_secs(1)) {
            return Ok(());
        }
        self.last_heartbeat = Some(now);
        self.send(HEARTBEAT_ID, HEARTBEAT_CRC_EXTRA, &heartbeat_payload(system_status(self.status)))
    }

    /// Whether an IMU pose at `t_ns` is due: at most [`MAX_IMU_AHEAD_NS`] past the last scan,
    /// a period (less a tenth, for IMU jitter) after the last ODOMETRY of either kind, and not
    /// within half a period of a time a scan is expected (the IMU that ends a scan arrives before
    /// the scan's pose). The scan's pose is better and
    /// follows at once: sent after an IMU pose of the same or a later time it would go back in
    /// time, and an autopilot keeps only poses newer than the last by its minimum interval
    /// (PX4's EKF2 drops the others), so the corrected pose would be the one lost.
    fn imu_due(&self, t_ns: u64) -> bool {
        if self.opt.rate_hz.is_nan() || self.opt.rate_hz <= 0.0 {
            return false;
        }
        let Some(scan) = self.last_scan_ns.filter(|&s| t_ns > s && t_ns - s <= MAX_IMU_AHEAD_NS) else {
            return false;
        };
        let period = (1e9 / self.opt.rate_hz) as u64;
        if self.last_sent_ns.is_some_and(|l| t_ns < l.saturating_add(period - period / 10)) {
            return false;
        }
        // Until two scans gave the interval, scan poses only.
        self.scan_dt_ns.is_some_and(|dt| {
            let phase = (t_ns - scan) % dt;
            phase >= period / 2 && phase + period / 2 <= dt
        })
    }
}

impl Sink for MavlinkSink {
    fn name(&self) -> String {
        format!("mavlink {}", self.opt.url)
    }

    fn wants(&self) -> Wants {
        Wants { imu_pose: self.opt.rate_hz > 0.0, ..Wants::default() }
    }

    fn handle(&mut self, ev: &SinkEvent) -> Result<(), SinkError> {
        let pose = match ev {
            SinkEvent::Scan(s) => {
                let t = s.pose.t_ns;
                if let Some(dt) =
                    self.last_scan_ns.and_then(|l| t.checked_sub(l)).filter(|&d| d > 0 && d <= 1_000_000_000)
                {
                    self.scan_dt_ns = Some(dt);
                }
                self.last_scan_ns = s.pose.status.is_tracking().then_some(t);
                Some(s.pose)
            }
            SinkEvent::ImuPose(p) if self.imu_due(p.t_ns) => Some(*p),
            SinkEvent::ImuPose(_) => None,
        };
        if let Some(p) = &pose {
            self.status = p.status;
        }
        let hb = self.heartbeat_if_due();
        // Before the initialisation the pose is a placeholder, no measurement: an autopilot
        // that fuses quality 0 (PX4's default EKF2_EV_QMIN) must not get it.
        let odo = match pose {
            Some(p) if p.status != LiveStatus::Initialising => {
                self.last_sent_ns = Some(self.last_sent_ns.map_or(p.t_ns, |l| l.max(p.t_ns)));
                self.send(ODOMETRY_ID, ODOMETRY_CRC_EXTRA, &Odometry::of(&p).payload()).map(|()| true)
            }
            _ => Ok(false),
        };
        if matches!(ev, SinkEvent::Scan(_)) {
            self.pose_sent = matches!(odo, Ok(true)).then(Instant::now);
        }
        hb.and(odo.map(|_| ()))
    }

    fn pose_sent(&mut self) -> Option<Instant> {
        self.pose_sent.take()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(q_wxyz: [f64; 4]) -> PoseSample {
        let mut p = PoseSample::placeholder(1_234_567_891, LiveStatus::Ok, 3);
        p.q_wxyz = q_wxyz;
        p.position = [1.0, 2.0, 3.0];
        p.velocity_body = [0.5, 0.25, -0.125];
        p.angular_velocity_body = [0.1, 0.2, 0.3];
        for i in 0..6 {
            for j in 0..6 {
                p.pose_covariance[i][j] = (10 * i + j) as f64 + 1.0;
            }
        }
        for i in 0..3 {
            for j in 0..3 {
                p.velocity_covariance[i][j] = (10 * i + j) as f64 + 100.0;
            }
        }
        p
    }

    #[test]
    fn crc_of_the_check_string() {
        // CRC-16/MCRF4XX's catalogue check value.
        assert_eq!(crc16(b"123456789"), 0x6F91);
        assert_eq!(crc16(b""), 0xFFFF);
    }

    #[test]
    fn heartbeat_frame_bytes() {
        let mut e = Encoder::new(1, 197);
        let mut buf = [0u8; MAX_FRAME_LEN];
        let n = e
            .frame(HEARTBEAT_ID, HEARTBEAT_CRC_EXTRA, &heartbeat_payload(mav_state::ACTIVE), &mut buf)
            .unwrap();
        // custom_mode (4 zero bytes) is not trailing, so nothing is truncated.
        assert_eq!(n, 10 + 9 + 2);
        assert_eq!(&buf[..19], &[0xFD, 9, 0, 0, 0, 1, 197, 0, 0, 0, 0, 0, 0, 0, 18, 8, 0, 4, 3]);
        let crc = crc_accumulate(50, crc16(&buf[1..19]));
        assert_eq!(&buf[19..21], &crc.to_le_bytes());
        // The sequence counts.
        let n2 = e
            .frame(HEARTBEAT_ID, HEARTBEAT_CRC_EXTRA, &heartbeat_payload(mav_state::ACTIVE), &mut buf)
            .unwrap();
        assert_eq!((n2, buf[4]), (21, 1));
    }

    #[test]
    fn trailing_zeros_are_truncated_but_one_byte_stays() {
        let mut e = Encoder::new(7, 8);
        let mut buf = [0u8; MAX_FRAME_LEN];
        let n = e.frame(331, 91, &[5, 0, 6, 0, 0, 0], &mut buf).unwrap();
        assert_eq!((n, buf[1]), (10 + 3 + 2, 3));
        assert_eq!(&buf[7..13], &[0x4B, 0x01, 0x00, 5, 0, 6]);
        let n = e.frame(0, 50, &[0; 9], &mut buf).unwrap();
        assert_eq!((n, buf[1], buf[10]), (10 + 1 + 2, 1, 0));
    }

    #[test]
    fn checked_lengths() {
        let mut e = Encoder::new(1, 1);
        let mut small = [0u8; 20];
        assert_eq!(e.frame(0, 50, &heartbeat_payload(4), &mut small), Err(EncodeError::BufferTooSmall));
        let mut buf = [0u8; MAX_FRAME_LEN];
        assert_eq!(e.frame(0, 50, &[1; 256], &mut buf), Err(EncodeError::PayloadTooLong));
        assert_eq!(e.frame(1 << 24, 50, &[1], &mut buf), Err(EncodeError::BadMessageId));
        // Failures leave the sequence alone.
        e.frame(0, 50, &[1], &mut buf).unwrap();
        assert_eq!(buf[4], 0);
    }

    #[test]
    fn odometry_layout() {
        let o = Odometry::of(&pose([1.0, 0.0, 0.0, 0.0]));
        let p = o.payload();
        let f = |at: usize| f32::from_le_bytes([p[at], p[at + 1], p[at + 2], p[at + 3]]);
        assert_eq!(u64::from_le_bytes(p[..8].try_into().unwrap()), 1_234_567);
        assert_eq!([f(8), f(12), f(16)], [1.0, -2.0, -3.0]);
        assert_eq!([f(20), f(24), f(28), f(32)], [1.0, 0.0, -0.0, -0.0]);
        assert_eq!([f(36), f(40), f(44)], [0.5, -0.25, 0.125]);
        assert_eq!([f(48), f(52), f(56)], [0.1, -0.2, -0.3]);
        // Pose covariance from 60: row 0 is (0,0)..(0,5), row 1 starts at (1,1).
        assert_eq!([f(60), f(64), f(80), f(84)], [1.0, -2.0, -6.0, 12.0]);
        // Velocity covariance from 144: (0,0), (0,1), then the unknown rate columns.
        assert_eq!([f(144), f(148)], [100.0, -101.0]);
        assert!(f(156).is_nan() && f(144 + 20 * 4).is_nan());
        assert_eq!(f(144 + 6 * 4), 111.0);
        assert_eq!(&p[228..], &[MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD, 3, MAV_ESTIMATOR_TYPE_LIDAR, 100]);
    }

    #[test]
    fn yaw_left_in_flu_is_yaw_right_in_frd() {
        let h = std::f64::consts::FRAC_PI_4;
        // 90° yaw left (about z up): in FRD about z down, i.e. yaw -90°.
        let o = Odometry::of(&pose([h.cos(), 0.0, 0.0, h.sin()]));
        let yaw = 2.0 * f64::from(o.q[3]).atan2(f64::from(o.q[0]));
        assert!((yaw + std::f64::consts::FRAC_PI_2).abs() < 1e-6, "{yaw}");
        // Nose up (pitch about FLU y, left) is pitch up in FRD too: about y right, positive.
        let a = 0.3f64;
        let o = Odometry::of(&pose([(a / 2.0).cos(), 0.0, -(a / 2.0).sin(), 0.0]));
        let pitch = 2.0 * f64::from(o.q[2]).atan2(f64::from(o.q[0]));
        assert!((pitch - a).abs() < 1e-6, "{pitch}");
        // Roll right (about x forward) stays roll right.
        let o = Odometry::of(&pose([(a / 2.0).cos(), (a / 2.0).sin(), 0.0, 0.0]));
        assert!((2.0 * f64::from(o.q[1]).atan2(f64::from(o.q[0])) - a).abs() < 1e-6);
    }

    #[test]
    fn frd_pose_maps_frd_body_vectors_like_flu() {
        // A body vector turned into the world agrees in both conventions: R' F v = F R v.
        let q = nalgebra::UnitQuaternion::from_euler_angles(0.3, -0.2, 1.1);
        let o = Odometry::of(&pose([q.w, q.i, q.j, q.k]));
        let q2 = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            f64::from(o.q[0]),
            f64::from(o.q[1]),
            f64::from(o.q[2]),
            f64::from(o.q[3]),
        ));
        let v = nalgebra::Vector3::new(0.7, -0.4, 0.2);
        let f = |v: nalgebra::Vector3<f64>| nalgebra::Vector3::new(v.x, -v.y, -v.z);
        assert!((q2 * f(v) - f(q * v)).norm() < 1e-6);
    }

    #[test]
    fn quality_and_state() {
        assert_eq!(quality(LiveStatus::Ok), 100);
        assert_eq!(quality(LiveStatus::Degraded { axes: 1 }), 50);
        assert_eq!(quality(LiveStatus::ImuOnly), 20);
        assert_eq!(quality(LiveStatus::Initialising), 0);
        assert_eq!(quality(LiveStatus::Lost), -1);
        assert_eq!(system_status(LiveStatus::Initialising), mav_state::BOOT);
        assert_eq!(system_status(LiveStatus::Ok), mav_state::ACTIVE);
        assert_eq!(system_status(LiveStatus::Lost), mav_state::CRITICAL);
        let mut p = pose([1.0, 0.0, 0.0, 0.0]);
        p.resets = 257;
        assert_eq!(Odometry::of(&p).reset_counter, 1);
    }

    #[test]
    fn serial_capacity() {
        assert!(serial_too_slow(921_600, 50.0).is_none());
        assert!(serial_too_slow(230_400, 50.0).is_none());
        let w = serial_too_slow(115_200, 50.0).unwrap();
        assert!(w.contains("about 47 ODOMETRY"), "{w}");
        assert!(serial_too_slow(57_600, 0.0).is_none());
        assert!(serial_too_slow(9_600, 0.0).is_some());
    }

    #[test]
    fn urls() {
        let u: MavlinkUrl = "udp:127.0.0.1:14550".parse().unwrap();
        assert_eq!(u, MavlinkUrl::Udp { host: "127.0.0.1".into(), port: 14550 });
        assert_eq!(u.to_string(), "udp:127.0.0.1:14550");
        assert_eq!("udpout:localhost:1".parse::<MavlinkUrl>().unwrap().to_string(), "udp:localhost:1");
        assert_eq!("udp:[::1]:5".parse::<MavlinkUrl>().unwrap().to_string(), "udp:[::1]:5");
        assert_eq!(
            "serial:/dev/ttyACM0:921600".parse::<MavlinkUrl>().unwrap(),
            MavlinkUrl::Serial { path: "/dev/ttyACM0".into(), baud: 921_600 }
        );
        for bad in [
            "",
            "udp",
            "udp:host",
            "udp::5",
            "udp:h:0",
            "udp:h:99999",
            "tcp:h:5",
            "serial:/dev/x:fast",
            "serial::5",
        ] {
            assert!(bad.parse::<MavlinkUrl>().is_err(), "{bad}");
        }
    }

    fn scan(t_ns: u64, status: LiveStatus) -> SinkEvent {
        let mut p = pose([1.0, 0.0, 0.0, 0.0]);
        (p.t_ns, p.status) = (t_ns, status);
        SinkEvent::Scan(std::sync::Arc::new(super::super::ScanOutput {
            index: 0,
            scan_start_ns: t_ns.saturating_sub(100_000_000),
            pose: p,
            process_ms: 1.0,
            map_voxels: 0,
            points: [0, 0],
            cloud: None,
            map: None,
            arrival_ns: 0,
            ready_ns: 0,
        }))
    }

    /// Sends `events` through a sink at 50 Hz to a local socket; the time_usec of each
    /// ODOMETRY received and the number of HEARTBEATs.
    fn through_sink(events: &[SinkEvent]) -> (Vec<u64>, usize) {
        let rx = UdpSocket::bind("127.0.0.1:0").unwrap();
        rx.set_read_timeout(Some(Duration::from_millis(200))).unwrap();
        let port = rx.local_addr().unwrap().port();
        let url = MavlinkUrl::Udp { host: "127.0.0.1".into(), port };
        let mut s = MavlinkSink::new(MavlinkOptions { url, rate_hz: 50.0, sysid: 1, compid: 197 }).unwrap();
        for ev in events {
            s.handle(ev).unwrap();
        }
        let (mut odo, mut hb) = (Vec::new(), 0);
        let mut buf = [0u8; 512];
        while let Ok(n) = rx.recv(&mut buf) {
            match u32::from_le_bytes([buf[7], buf[8], buf[9], 0]) {
                ODOMETRY_ID => {
                    let mut t = [0u8; 8];
                    t.copy_from_slice(&buf[10..18]);
                    odo.push(u64::from_le_bytes(t));
                }
                HEARTBEAT_ID => hb += 1,
                id => panic!("message {id} of {n} bytes"),
            }
        }
        (odo, hb)
    }

    fn imu(t_ns: u64) -> SinkEvent {
        let mut p = pose([1.0, 0.0, 0.0, 0.0]);
        p.t_ns = t_ns;
        SinkEvent::ImuPose(p)
    }

    #[test]
    fn decimation_and_order() {
        // IMU poses before any scan, two scans, then 1 s of 200 Hz IMU poses and a stale one.
        let mut ev: Vec<SinkEvent> = (1..10).map(|k| imu(k * 5_000_000)).collect();
        ev.push(scan(100_000_000, LiveStatus::Ok));
        ev.push(scan(200_000_000, LiveStatus::Ok));
        ev.extend((1..=200).map(|k| imu(200_000_000 + k * 5_000_000)));
        ev.push(imu(250_000_000));
        let (odo, hb) = through_sink(&ev);
        assert_eq!(hb, 1);
        assert_eq!(odo[..2], [100_000, 200_000]);
        // Then 50 Hz at most, forward in time, away from the expected scan times, and only for
        // the 0.5 s the IMU may run ahead of the last scan.
        let imu_t = &odo[2..];
        assert!(imu_t.windows(2).all(|w| w[1] >= w[0] + 18_000), "{odo:?}");
        assert!(
            imu_t
                .iter()
                .all(|t| *t > 200_000 && *t <= 700_000 && (t % 100_000).clamp(10_000, 90_000) == t % 100_000)
        );
        assert!((20..=25).contains(&imu_t.len()), "{odo:?}");

        // Scans every 100 ms, the IMU at 200 Hz up to one sample past each scan's end before
        // its pose (as the pipeline sends them): four IMU poses between scans, none at or
        // after the next scan's time, so the scan poses keep time moving forward.
        let mut ev = Vec::new();
        for k in 1..=5u64 {
            ev.push(scan(k * 100_000_000, LiveStatus::Ok));
            ev.extend((1..=21).map(|j| imu(k * 100_000_000 + j * 5_000_000)));
        }
        let (odo, _) = through_sink(&ev);
        let want: Vec<u64> = std::iter::once(100_000).chain((10..=29).map(|k| k * 20_000)).collect();
        assert_eq!(odo, want);
    }

    #[test]
    fn no_odometry_before_the_initialisation_nor_imu_poses_after_a_loss() {
        let ev = [
            scan(100_000_000, LiveStatus::Initialising),
            imu(120_000_000),
            scan(200_000_000, LiveStatus::Ok),
            imu(220_000_000),
            scan(300_000_000, LiveStatus::Ok),
            imu(320_000_000),
            scan(400_000_000, LiveStatus::Lost),
            imu(420_000_000),
            imu(440_000_000),
        ];
        let (odo, _) = through_sink(&ev);
        // The lost scan's pose goes out (quality -1 says so), the IMU poses after it do not.
        assert_eq!(odo, [200_000, 300_000, 320_000, 400_000]);
    }

    #[test]
    fn send_errors_are_errors_not_panics() {
        // A port with nothing listening: the kernel's ICMP reply fails a later send.
        let free = UdpSocket::bind("127.0.0.1:0").unwrap();
        let port = free.local_addr().unwrap().port();
        drop(free);
        let opt = MavlinkOptions {
            url: MavlinkUrl::Udp { host: "127.0.0.1".into(), port },
            rate_hz: 50.0,
            sysid: 1,
            compid: 197,
        };
        let mut s = MavlinkSink::new(opt).unwrap();
        let mut errors = 0;
        for k in 0..20u64 {
            if s.handle(&scan(k * 20_000_000, LiveStatus::Ok)).is_err() {
                errors += 1;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        assert!(errors > 0);
    }
}
