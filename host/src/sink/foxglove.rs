//! Foxglove live output (`--foxglove HOST:PORT`): a Foxglove WebSocket server, so a person can
//! watch loglio run in Foxglove (Open connection, Foxglove WebSocket, `ws://HOST:PORT`).
//!
//! Hand-written Foxglove WebSocket protocol v1 (`foxglove.websocket.v1`: serverInfo, advertise,
//! subscribe/unsubscribe, binary messageData) over sync `tungstenite`, not the Foxglove SDK: the
//! SDK (0.30, `websocket` only, no TLS) pulls in about 60 more crates (tokio, prost, serde_with,
//! darling, schemars, jiff, ...): its build had not finished after 5 minutes on the 2-core build
//! machine, where `tungstenite` and its few crates take seconds. Messages are JSON of Foxglove's well-known schemas
//! (`foxglove.PoseInFrame`, `PosesInFrame`, `PointCloud`, `FrameTransforms`), which Foxglove
//! shows without setup; [`super::mcap`] records the same channels.
//!
//! A client that stops reading never slows the odometry or the other clients: each client has
//! its own thread and a bounded send buffer; what does not fit is dropped and counted (in
//! `/loglio/status` and one warning at the end).

use std::collections::{HashMap, VecDeque};
use std::io::ErrorKind;
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use tungstenite::Message;
use tungstenite::handshake::server::{ErrorResponse, Request, Response};

use super::{LiveStatus, PoseSample, ScanOutput, Sink, SinkError, SinkEvent, Wants};

/// The WebSocket subprotocol of Foxglove's protocol v1.
pub const SUBPROTOCOL: &str = "foxglove.websocket.v1";
/// The world frame of every message.
pub const WORLD_FRAME: &str = "odom";
/// The body (IMU) frame.
pub const BODY_FRAME: &str = "base_link";

/// The channels, in advertised order (channel id = index + 1).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Channel {
    /// Each scan's pose.
    Pose,
    /// The IMU-propagated pose between scans, decimated.
    PoseImu,
    /// The trajectory so far (bounded), about once a second.
    Path,
    /// The undistorted, downsampled scan in the world frame.
    Scan,
    /// The map, every `--map-every` s.
    Map,
    /// `odom` -> `base_link`.
    Tf,
    /// Status text, resets, timing, map size, drops.
    Status,
}

/// One channel's topic and schema.
#[derive(Debug)]
pub struct ChannelDef {
    /// Which.
    pub channel: Channel,
    /// Topic.
    pub topic: &'static str,
    /// Schema name (Foxglove recognises the `foxglove.*` ones).
    pub schema_name: &'static str,
}

/// Every channel.
pub const CHANNELS: [ChannelDef; 7] = [
    ChannelDef { channel: Channel::Pose, topic: "/loglio/pose", schema_name: "foxglove.PoseInFrame" },
    ChannelDef { channel: Channel::PoseImu, topic: "/loglio/pose_imu", schema_name: "foxglove.PoseInFrame" },
    ChannelDef { channel: Channel::Path, topic: "/loglio/path", schema_name: "foxglove.PosesInFrame" },
    ChannelDef { channel: Channel::Scan, topic: "/loglio/scan", schema_name: "foxglove.PointCloud" },
    ChannelDef { channel: Channel::Map, topic: "/loglio/map", schema_name: "foxglove.PointCloud" },
    ChannelDef { channel: Channel::Tf, topic: "/tf", schema_name: "foxglove.FrameTransforms" },
    ChannelDef { channel: Channel::Status, topic: "/loglio/status", schema_name: "loglio.Status" },
];

impl Channel {
    /// Index into [`CHANNELS`].
    pub fn index(self) -> usize {
        self as usize
    }

    /// The JSON schema of the channel's messages.
    pub fn schema(self) -> Value {
        let def = &CHANNELS[self.index()];
        let time = json!({"type": "object", "properties": {
            "sec": {"type": "integer", "minimum": 0},
            "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}});
        let vec3 = json!({"type": "object", "properties": {
            "x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}}});
        let quat = json!({"type": "object", "properties": {
            "x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}, "w": {"type": "number"}}});
        let pose = json!({"type": "object", "properties": {"position": vec3, "orientation": quat}});
        let props = match self {
            Channel::Pose | Channel::PoseImu => {
                json!({"timestamp": time, "frame_id": {"type": "string"}, "pose": pose})
            }
            Channel::Path => json!({"timestamp": time, "frame_id": {"type": "string"},
                "poses": {"type": "array", "items": pose}}),
            Channel::Scan | Channel::Map => json!({"timestamp": time, "frame_id": {"type": "string"},
                "pose": pose, "point_stride": {"type": "integer", "minimum": 0},
                "fields": {"type": "array", "items": {"type": "object", "properties": {
                    "name": {"type": "string"}, "offset": {"type": "integer", "minimum": 0},
                    "type": {"type": "integer", "description": "foxglove.NumericType: 7 FLOAT32"}}}},
                "data": {"type": "string", "contentEncoding": "base64"}}),
            Channel::Tf => json!({"transforms": {"type": "array", "items": {"type": "object", "properties": {
                "timestamp": time, "parent_frame_id": {"type": "string"},
                "child_frame_id": {"type": "string"}, "translation": vec3, "rotation": quat}}}}),
            Channel::Status => json!({"timestamp": time, "scan": {"type": "integer"},
                "status": {"type": "string"}, "tracking": {"type": "boolean"},
                "quality": {"type": "integer"}, "resets": {"type": "integer"},
                "process_ms": {"type": "number"}, "map_voxels": {"type": "integer"},
                "points": {"type": "array", "items": {"type": "integer"}},
                "latency_ms": {"type": ["number", "null"]},
                "dropped": {"type": "integer", "description": "messages not sent to slow clients so far"}}),
        };
        json!({"title": def.schema_name, "type": "object", "properties": props})
    }
}

/// One encoded message: its channel, the data's time and the JSON bytes.
#[derive(Clone, Debug)]
pub struct Encoded {
    /// Channel.
    pub channel: Channel,
    /// The data's time, ns.
    pub t_ns: u64,
    /// JSON.
    pub data: Arc<Vec<u8>>,
}

/// Rates and bounds of the derived channels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EncoderOptions {
    /// Least time between two `/loglio/pose_imu` (and their `/tf`), ns (20 ms: 50 Hz).
    pub imu_every_ns: u64,
    /// Least time between two `/loglio/path`, ns.
    pub path_every_ns: u64,
    /// Most poses in a path: beyond, every second one is left out (the whole run stays, coarser).
    pub path_max: usize,
}

impl Default for EncoderOptions {
    fn default() -> Self {
        EncoderOptions { imu_every_ns: 20_000_000, path_every_ns: 1_000_000_000, path_max: 2000 }
    }
}

/// Turns sink events into the channels' JSON messages (shared by the server and the recorder).
#[derive(Debug, Default)]
pub struct Encoder {
    opt: EncoderOptions,
    imu_sent_ns: Option<u64>,
    path: Vec<(u64, [f64; 3], [f64; 4])>,
    path_resets: u32,
    path_sent_ns: Option<u64>,
}

fn stamp(t_ns: u64) -> Value {
    json!({"sec": t_ns / 1_000_000_000, "nsec": t_ns % 1_000_000_000})
}

fn pose_json(p: [f64; 3], q: [f64; 4]) -> Value {
    json!({"position": {"x": p[0], "y": p[1], "z": p[2]},
           "orientation": {"x": q[1], "y": q[2], "z": q[3], "w": q[0]}})
}

/// Standard base64 (RFC 4648, padded): how Foxglove's JSON carries `bytes` fields.
pub fn base64(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for c in bytes.chunks(3) {
        let b = [c[0], c.get(1).copied().unwrap_or(0), c.get(2).copied().unwrap_or(0)];
        let n = (u32::from(b[0]) << 16) | (u32::from(b[1]) << 8) | u32::from(b[2]);
        for k in 0..4 {
            if k <= c.len() {
                s.push(char::from(A[(n >> (18 - 6 * k)) as usize & 63]));
            } else {
                s.push('=');
            }
        }
    }
    s
}

fn cloud_json(t_ns: u64, points: impl ExactSizeIterator<Item = [f32; 3]>) -> Value {
    let mut data = Vec::with_capacity(points.len() * 12);
    for p in points {
        for c in p {
            data.extend_from_slice(&c.to_le_bytes());
        }
    }
    json!({"timestamp": stamp(t_ns), "frame_id": WORLD_FRAME,
        "pose": pose_json([0.0; 3], [1.0, 0.0, 0.0, 0.0]), "point_stride": 12,
        "fields": [{"name": "x", "offset": 0, "type": 7}, {"name": "y", "offset": 4, "type": 7},
                   {"name": "z", "offset": 8, "type": 7}],
        "data": base64(&data)})
}

fn tf_json(p: &PoseSample) -> Value {
    json!({"transforms": [{"timestamp": stamp(p.t_ns), "parent_frame_id": WORLD_FRAME,
        "child_frame_id": BODY_FRAME,
        "translation": {"x": p.position[0], "y": p.position[1], "z": p.position[2]},
        "rotation": {"x": p.q_wxyz[1], "y": p.q_wxyz[2], "z": p.q_wxyz[3], "w": p.q_wxyz[0]}}]})
}

fn pose_in_frame(p: &PoseSample) -> Value {
    json!({"timestamp": stamp(p.t_ns), "frame_id": WORLD_FRAME, "pose": pose_json(p.position, p.q_wxyz)})
}

impl Encoder {
    /// An encoder with `opt`.
    pub fn new(opt: EncoderOptions) -> Encoder {
        Encoder { opt, ..Encoder::default() }
    }

    /// The messages of `ev`; `dropped` (messages lost so far) goes into the status.
    pub fn encode(&mut self, ev: &SinkEvent, dropped: u64) -> Vec<Encoded> {
        self.encode_for(ev, dropped, |_| true)
    }

    /// The messages of `ev` on the channels `want` takes: the others are not serialised (no
    /// clouds encoded while nobody watches); the rates and the path advance all the same.
    pub fn encode_for(
        &mut self,
        ev: &SinkEvent,
        dropped: u64,
        want: impl Fn(Channel) -> bool,
    ) -> Vec<Encoded> {
        let mut out = Vec::new();
        let mut push = |channel: Channel, t_ns: u64, v: &dyn Fn() -> Value| {
            if want(channel) {
                // A `Value` always serialises (string keys only).
                let data = serde_json::to_vec(&v()).unwrap_or_default();
                out.push(Encoded { channel, t_ns, data: Arc::new(data) });
            }
        };
        match ev {
            SinkEvent::ImuPose(p) => {
                if !p.status.is_tracking() {
                    return out;
                }
                if self.imu_sent_ns.is_some_and(|t| p.t_ns < t.saturating_add(self.opt.imu_every_ns)) {
                    return out;
                }
                self.imu_sent_ns = Some(p.t_ns);
                push(Channel::PoseImu, p.t_ns, &|| pose_in_frame(p));
                push(Channel::Tf, p.t_ns, &|| tf_json(p));
            }
            SinkEvent::Scan(s) => self.encode_scan(s, dropped, &mut push),
        }
        out
    }

    fn encode_scan(
        &mut self,
        s: &ScanOutput,
        dropped: u64,
        push: &mut impl FnMut(Channel, u64, &dyn Fn() -> Value),
    ) {
        let p = &s.pose;
        let t = p.t_ns;
        // The trajectory file's poses: every scan after the initialisation.
        if p.status != LiveStatus::Initialising {
            push(Channel::Pose, t, &|| pose_in_frame(p));
            push(Channel::Tf, t, &|| tf_json(p));
            if p.resets != self.path_resets {
                // A new world frame: the old path means nothing in it.
                self.path.clear();
                self.path_resets = p.resets;
            }
            self.path.push((t, p.position, p.q_wxyz));
            if self.path.len() > self.opt.path_max.max(2) {
                let last = self.path.len() - 1;
                let mut k = 0;
                self.path.retain(|_| {
                    k += 1;
                    (k - 1) % 2 == 0 || k - 1 == last
                });
            }
            if self.path_sent_ns.is_none_or(|s| t >= s.saturating_add(self.opt.path_every_ns)) {
                self.path_sent_ns = Some(t);
                let path = &self.path;
                push(Channel::Path, t, &|| {
                    let poses: Vec<Value> = path.iter().map(|(_, p, q)| pose_json(*p, *q)).collect();
                    json!({"timestamp": stamp(t), "frame_id": WORLD_FRAME, "poses": poses})
                });
            }
        }
        if let Some(c) = &s.cloud {
            push(Channel::Scan, t, &|| cloud_json(t, c.iter().copied()));
        }
        if let Some(m) = &s.map {
            push(Channel::Map, t, &|| cloud_json(t, m.iter().map(|m| m.xyz)));
        }
        let latency_ms = (s.arrival_ns > 0 && s.ready_ns >= s.arrival_ns)
            .then(|| (s.ready_ns - s.arrival_ns) as f64 * 1e-6);
        push(Channel::Status, t, &|| {
            json!({"timestamp": stamp(t), "scan": s.index, "status": p.status.to_string(),
                "tracking": p.status.is_tracking(), "quality": p.status.quality(), "resets": p.resets,
                "process_ms": s.process_ms, "map_voxels": s.map_voxels, "points": s.points,
                "latency_ms": latency_ms, "dropped": dropped})
        });
    }
}

/// Most messages waiting for one client before new ones are dropped.
const CLIENT_MAX_MESSAGES: usize = 512;
/// Most bytes waiting for one client before new messages are dropped.
const CLIENT_MAX_BYTES: usize = 32 << 20;
/// How long a client's thread waits for the client's messages between two sends.
const READ_POLL: Duration = Duration::from_millis(2);
/// How long the end of the run gives the clients to take what is queued.
const CLOSE_GRACE: Duration = Duration::from_millis(1500);

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

#[derive(Default)]
struct ClientState {
    out: VecDeque<Message>,
    bytes: usize,
    /// (subscription id, channel index).
    subs: Vec<(u32, usize)>,
    closing: bool,
    done: bool,
}

#[derive(Default)]
struct ClientShared {
    st: Mutex<ClientState>,
    cv: Condvar,
}

struct Client {
    shared: Arc<ClientShared>,
    stream: Option<TcpStream>,
    thread: Option<JoinHandle<()>>,
}

#[derive(Default)]
struct ServerShared {
    clients: Mutex<Vec<Client>>,
    stop: AtomicBool,
    /// The last map and path, sent to a client when it subscribes (they come seldom).
    latched: Mutex<HashMap<usize, Encoded>>,
    connections: AtomicU64,
    sent: AtomicU64,
    dropped: AtomicU64,
}

impl ClientShared {
    /// Queues `msg` unless the buffer is full (then counts it as dropped).
    fn offer(&self, msg: Message, server: &ServerShared) {
        let len = msg.len();
        let mut st = lock(&self.st);
        if st.done || st.closing {
            return;
        }
        if st.out.len() >= CLIENT_MAX_MESSAGES || st.bytes + len > CLIENT_MAX_BYTES {
            server.dropped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        st.bytes += len;
        st.out.push_back(msg);
        drop(st);
        self.cv.notify_all();
    }
}

fn message_data(sub: u32, m: &Encoded) -> Message {
    let mut b = Vec::with_capacity(13 + m.data.len());
    b.push(1u8);
    b.extend_from_slice(&sub.to_le_bytes());
    b.extend_from_slice(&m.t_ns.to_le_bytes());
    b.extend_from_slice(&m.data);
    Message::Binary(b.into())
}

/// The serverInfo and advertise messages a client gets first.
fn hello() -> [Message; 2] {
    let info = json!({"op": "serverInfo", "name": "loglio", "capabilities": [],
        "supportedEncodings": [], "metadata": {}, "sessionId": format!("{}", std::process::id())});
    let channels: Vec<Value> = CHANNELS
        .iter()
        .enumerate()
        .map(|(i, c)| {
            json!({"id": i + 1, "topic": c.topic, "encoding": "json", "schemaName": c.schema_name,
                "schema": c.channel.schema().to_string(), "schemaEncoding": "jsonschema"})
        })
        .collect();
    let adv = json!({"op": "advertise", "channels": channels});
    [Message::Text(info.to_string().into()), Message::Text(adv.to_string().into())]
}

/// Applies a client's text message (subscribe, unsubscribe; anything else is ignored).
fn client_op(text: &str, shared: &ClientShared, server: &ServerShared) {
    let Ok(v) = serde_json::from_str::<Value>(text) else { return };
    match v.get("op").and_then(Value::as_str) {
        Some("subscribe") => {
            let subs = v.get("subscriptions").and_then(Value::as_array).cloned().unwrap_or_default();
            for s in subs {
                let id = s.get("id").and_then(Value::as_u64).and_then(|i| u32::try_from(i).ok());
                let ch = s.get("channelId").and_then(Value::as_u64).and_then(|c| usize::try_from(c).ok());
                let (Some(id), Some(ch)) = (id, ch) else { continue };
                if ch == 0 || ch > CHANNELS.len() {
                    continue;
                }
                let ch = ch - 1;
                {
                    let mut st = lock(&shared.st);
                    if st.subs.iter().any(|(i, _)| *i == id) {
                        continue;
                    }
                    st.subs.push((id, ch));
                }
                let latched = lock(&server.latched).get(&ch).cloned();
                if let Some(m) = latched {
                    shared.offer(message_data(id, &m), server);
                }
            }
        }
        Some("unsubscribe") => {
            let ids: Vec<u64> = v
                .get("subscriptionIds")
                .and_then(Value::as_array)
                .map(|a| a.iter().filter_map(Value::as_u64).collect())
                .unwrap_or_default();
            lock(&shared.st).subs.retain(|(i, _)| !ids.contains(&u64::from(*i)));
        }
        _ => {}
    }
}

fn is_timeout(e: &tungstenite::Error) -> bool {
    matches!(e, tungstenite::Error::Io(io) if matches!(io.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut))
}

/// The handshake's answer: the Foxglove subprotocol, or 400 to a client that does not offer it.
#[allow(clippy::result_large_err)] // tungstenite's callback type.
fn pick_subprotocol(req: &Request, mut resp: Response) -> Result<Response, ErrorResponse> {
    let offered = req
        .headers()
        .get_all("Sec-WebSocket-Protocol")
        .iter()
        .filter_map(|h| h.to_str().ok())
        .flat_map(|h| h.split(','))
        .any(|p| p.trim() == SUBPROTOCOL);
    if !offered {
        let mut e = ErrorResponse::new(Some(format!("subprotocol {SUBPROTOCOL} required")));
        *e.status_mut() = tungstenite::http::StatusCode::BAD_REQUEST;
        return Err(e);
    }
    resp.headers_mut()
        .insert("Sec-WebSocket-Protocol", tungstenite::http::HeaderValue::from_static(SUBPROTOCOL));
    Ok(resp)
}

/// One client: the handshake, then sending what is queued and reading its requests in turns.
/// A client that does not read blocks only this thread (its buffer then fills and drops).
fn serve(stream: TcpStream, shared: Arc<ClientShared>, server: Arc<ServerShared>) {
    let _ = stream.set_nodelay(true);
    let _ = stream.set_read_timeout(Some(Duration::from_secs(5)));
    let mut ws = match tungstenite::accept_hdr(stream, pick_subprotocol) {
        Ok(ws) => ws,
        Err(_) => {
            lock(&shared.st).done = true;
            return;
        }
    };
    let _ = ws.get_ref().set_read_timeout(Some(READ_POLL));
    let mut ok = hello().into_iter().all(|m| ws.send(m).is_ok());
    while ok {
        let (batch, closing) = {
            let mut st = lock(&shared.st);
            if st.out.is_empty() && !st.closing {
                st = shared
                    .cv
                    .wait_timeout(st, Duration::from_millis(10))
                    .unwrap_or_else(|p| p.into_inner())
                    .0;
            }
            st.bytes = 0;
            (std::mem::take(&mut st.out), st.closing)
        };
        let n = batch.len() as u64;
        for m in batch {
            if ws.write(m).is_err() {
                ok = false;
                break;
            }
        }
        if !ok || ws.flush().is_err() {
            break;
        }
        server.sent.fetch_add(n, Ordering::Relaxed);
        if closing && n == 0 {
            let _ = ws.close(None);
            let _ = ws.flush();
            break;
        }
        loop {
            match ws.read() {
                Ok(Message::Text(t)) => client_op(t.as_str(), &shared, &server),
                Ok(Message::Close(_)) => {
                    ok = false;
                    break;
                }
                Ok(_) => {}
                Err(e) if is_timeout(&e) => break,
                Err(_) => {
                    ok = false;
                    break;
                }
            }
        }
    }
    let mut st = lock(&shared.st);
    st.done = true;
    st.out.clear();
    drop(st);
    shared.cv.notify_all();
}

/// The Foxglove WebSocket server.
pub struct FoxgloveServer {
    addr: SocketAddr,
    shared: Arc<ServerShared>,
    accept: Option<JoinHandle<()>>,
}

impl FoxgloveServer {
    /// Listens on `addr` (`HOST:PORT`; port 0 picks one) and accepts clients on a thread.
    pub fn bind(addr: &str) -> Result<FoxgloveServer, SinkError> {
        let listener =
            TcpListener::bind(addr).map_err(|e| SinkError(format!("cannot listen on {addr}: {e}")))?;
        let addr = listener.local_addr()?;
        listener.set_nonblocking(true)?;
        let shared = Arc::new(ServerShared::default());
        let sh = Arc::clone(&shared);
        let accept = std::thread::Builder::new()
            .name("loglio-foxglove".into())
            .spawn(move || accept_loop(listener, sh))
            .map_err(|e| SinkError(format!("cannot start the server's thread: {e}")))?;
        Ok(FoxgloveServer { addr, shared, accept: Some(accept) })
    }

    /// The address it listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// Messages not sent to slow clients so far.
    pub fn dropped(&self) -> u64 {
        self.shared.dropped.load(Ordering::Relaxed)
    }

    /// Clients connected so far, and messages sent to them.
    pub fn counts(&self) -> (u64, u64) {
        (self.shared.connections.load(Ordering::Relaxed), self.shared.sent.load(Ordering::Relaxed))
    }

    /// Whether `channel` is worth encoding: a client subscribes to it, or it is kept for the
    /// clients to come (the map, the path).
    pub fn wants(&self, channel: Channel) -> bool {
        let ch = channel.index();
        matches!(channel, Channel::Map | Channel::Path)
            || lock(&self.shared.clients)
                .iter()
                .any(|c| lock(&c.shared.st).subs.iter().any(|(_, sc)| *sc == ch))
    }

    /// Offers `m` to every client subscribed to its channel (never waits).
    pub fn publish(&self, m: &Encoded) {
        let ch = m.channel.index();
        if matches!(m.channel, Channel::Map | Channel::Path) {
            lock(&self.shared.latched).insert(ch, m.clone());
        }
        let mut clients = lock(&self.shared.clients);
        clients.retain_mut(|c| {
            let done = lock(&c.shared.st).done;
            if done && let Some(t) = c.thread.take() {
                let _ = t.join();
            }
            !done
        });
        for c in clients.iter() {
            let subs: Vec<u32> =
                lock(&c.shared.st).subs.iter().filter(|(_, sc)| *sc == ch).map(|(id, _)| *id).collect();
            for id in subs {
                c.shared.offer(message_data(id, m), &self.shared);
            }
        }
    }

    /// Stops accepting, gives the clients [`CLOSE_GRACE`] to take what is queued, closes them.
    pub fn close(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.accept.take() {
            let _ = t.join();
        }
        let mut clients = std::mem::take(&mut *lock(&self.shared.clients));
        for c in &clients {
            lock(&c.shared.st).closing = true;
            c.shared.cv.notify_all();
        }
        let deadline = Instant::now() + CLOSE_GRACE;
        for c in &clients {
            let mut st = lock(&c.shared.st);
            while !st.done {
                let now = Instant::now();
                if now >= deadline {
                    break;
                }
                st = c.shared.cv.wait_timeout(st, deadline - now).unwrap_or_else(|p| p.into_inner()).0;
            }
        }
        for c in &mut clients {
            // Unblocks a thread stuck writing to a client that does not read.
            if let Some(s) = c.stream.take() {
                let _ = s.shutdown(Shutdown::Both);
            }
            if let Some(t) = c.thread.take() {
                let _ = t.join();
            }
        }
    }
}

impl std::fmt::Debug for FoxgloveServer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FoxgloveServer").field("addr", &self.addr).finish()
    }
}

impl Drop for FoxgloveServer {
    fn drop(&mut self) {
        self.close();
    }
}

fn accept_loop(listener: TcpListener, sh: Arc<ServerShared>) {
    while !sh.stop.load(Ordering::Relaxed) {
        match listener.accept() {
            Ok((stream, _)) => {
                if stream.set_nonblocking(false).is_err() {
                    continue;
                }
                let shared = Arc::new(ClientShared::default());
                let (s2, c2) = (Arc::clone(&sh), Arc::clone(&shared));
                let kept = stream.try_clone().ok();
                let thread = std::thread::Builder::new()
                    .name("loglio-foxglove-client".into())
                    .spawn(move || serve(stream, c2, s2))
                    .ok();
                if thread.is_some() {
                    sh.connections.fetch_add(1, Ordering::Relaxed);
                    lock(&sh.clients).push(Client { shared, stream: kept, thread });
                }
            }
            Err(e) if e.kind() == ErrorKind::WouldBlock => std::thread::sleep(Duration::from_millis(20)),
            Err(_) => std::thread::sleep(Duration::from_millis(100)),
        }
    }
}

/// The `--foxglove` sink.
#[derive(Debug)]
pub struct FoxgloveSink {
    server: FoxgloveServer,
    enc: Encoder,
}

impl FoxgloveSink {
    /// Starts the server on `addr` and says where on stderr.
    pub fn start(addr: &str) -> Result<FoxgloveSink, SinkError> {
        let server = FoxgloveServer::bind(addr)?;
        eprintln!(
            "foxglove: serving ws://{} (Foxglove: Open connection, Foxglove WebSocket)",
            server.local_addr()
        );
        Ok(FoxgloveSink { server, enc: Encoder::new(EncoderOptions::default()) })
    }
}

impl Sink for FoxgloveSink {
    fn name(&self) -> String {
        format!("foxglove {}", self.server.local_addr())
    }

    fn wants(&self) -> Wants {
        Wants { cloud: true, map: true, imu_pose: true }
    }

    fn handle(&mut self, ev: &SinkEvent) -> Result<(), SinkError> {
        let server = &self.server;
        for m in self.enc.encode_for(ev, server.dropped(), |c| server.wants(c)) {
            self.server.publish(&m);
        }
        Ok(())
    }

    fn finish(&mut self) -> Result<(), SinkError> {
        self.server.close();
        let dropped = self.server.dropped();
        let (clients, sent) = self.server.counts();
        if dropped > 0 {
            crate::diag::warn(format!(
                "{}: {dropped} messages dropped for slow clients (their send buffers were full); {sent} sent to {clients} clients",
                self.name()
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_matches_rfc4648_vectors() {
        let cases = [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ];
        for (i, o) in cases {
            assert_eq!(base64(i.as_bytes()), o);
        }
    }

    fn pose(t_ns: u64, status: LiveStatus) -> PoseSample {
        let mut p = PoseSample::placeholder(t_ns, status, 0);
        p.position = [1.0, 2.0, 3.0];
        p
    }

    #[test]
    fn imu_poses_are_decimated_and_paths_bounded() {
        let mut e = Encoder::new(EncoderOptions { imu_every_ns: 20_000_000, path_every_ns: 0, path_max: 10 });
        let n: usize = (0..100u64)
            .map(|k| e.encode(&SinkEvent::ImuPose(pose(k * 5_000_000, LiveStatus::Ok)), 0).len())
            .sum();
        // 0.5 s at 200 Hz -> 25 at 50 Hz, each a pose and a tf.
        assert_eq!(n, 50);
        let mut last_path = None;
        for k in 0..50u64 {
            let s = ScanOutput {
                index: k,
                scan_start_ns: 0,
                pose: pose(k * 100_000_000, LiveStatus::Ok),
                process_ms: 1.0,
                map_voxels: 3,
                points: [10, 5],
                cloud: Some(Arc::new(vec![[1.0, 2.0, 3.0]])),
                map: None,
                arrival_ns: 0,
                ready_ns: 0,
            };
            for m in e.encode(&SinkEvent::Scan(Arc::new(s)), 7) {
                if m.channel == Channel::Path {
                    last_path = Some(m);
                }
            }
        }
        let v: Value = serde_json::from_slice(&last_path.unwrap().data).unwrap();
        let poses = v["poses"].as_array().unwrap();
        assert!(poses.len() <= 10 && poses.len() >= 5, "{}", poses.len());
        assert_eq!(v["timestamp"]["sec"], 4);
        assert_eq!(v["timestamp"]["nsec"], 900_000_000);
    }

    #[test]
    fn initialising_scans_send_only_status() {
        let mut e = Encoder::default();
        let s = ScanOutput {
            index: 0,
            scan_start_ns: 0,
            pose: pose(5, LiveStatus::Initialising),
            process_ms: 1.0,
            map_voxels: 0,
            points: [0, 0],
            cloud: None,
            map: None,
            arrival_ns: 0,
            ready_ns: 0,
        };
        let m = e.encode(&SinkEvent::Scan(Arc::new(s)), 0);
        assert_eq!(m.len(), 1);
        assert_eq!(m[0].channel, Channel::Status);
        let v: Value = serde_json::from_slice(&m[0].data).unwrap();
        assert_eq!(v["status"], "initialising");
    }

    #[test]
    fn unwanted_channels_are_not_serialised() {
        let mut e = Encoder::default();
        let m = e.encode_for(&SinkEvent::ImuPose(pose(0, LiveStatus::Ok)), 0, |c| c == Channel::Tf);
        assert_eq!(m.len(), 1);
        assert_eq!(m[0].channel, Channel::Tf);
    }

    fn connect(
        addr: SocketAddr,
        subprotocol: Option<&str>,
    ) -> tungstenite::Result<tungstenite::WebSocket<TcpStream>> {
        use tungstenite::client::IntoClientRequest;
        let mut req = format!("ws://{addr}/").into_client_request()?;
        if let Some(p) = subprotocol {
            req.headers_mut()
                .insert("Sec-WebSocket-Protocol", tungstenite::http::HeaderValue::from_str(p).unwrap());
        }
        let stream = TcpStream::connect(addr)?;
        tungstenite::client(req, stream).map(|(ws, _)| ws).map_err(|e| match e {
            tungstenite::HandshakeError::Failure(e) => e,
            tungstenite::HandshakeError::Interrupted(_) => tungstenite::Error::ConnectionClosed,
        })
    }

    #[test]
    fn a_subscriber_gets_message_data_and_others_nothing() {
        let mut server = FoxgloveServer::bind("127.0.0.1:0").unwrap();
        let addr = server.local_addr();
        assert!(connect(addr, None).is_err(), "a client without the subprotocol is refused");
        let mut ws = connect(addr, Some("foxglove.websocket.v1")).unwrap();
        let text = |m: Message| serde_json::from_str::<Value>(m.to_text().unwrap()).unwrap();
        assert_eq!(text(ws.read().unwrap())["op"], "serverInfo");
        let adv = text(ws.read().unwrap());
        let chans = adv["channels"].as_array().unwrap();
        assert_eq!(chans.len(), CHANNELS.len());
        let status = chans.iter().find(|c| c["topic"] == "/loglio/status").unwrap();
        let sub = json!({"op": "subscribe", "subscriptions": [{"id": 42, "channelId": status["id"]}]});
        ws.send(Message::Text(sub.to_string().into())).unwrap();
        let deadline = Instant::now() + Duration::from_secs(5);
        while !server.wants(Channel::Status) {
            assert!(Instant::now() < deadline, "the subscription never arrived");
            std::thread::sleep(Duration::from_millis(5));
        }
        assert!(!server.wants(Channel::Scan));
        let data = Arc::new(b"{\"a\":1}".to_vec());
        server.publish(&Encoded { channel: Channel::Scan, t_ns: 1, data: Arc::clone(&data) });
        server.publish(&Encoded { channel: Channel::Status, t_ns: 1_234_567_890_123, data });
        let Message::Binary(b) = ws.read().unwrap() else { panic!("not binary") };
        assert_eq!(b[0], 1);
        assert_eq!(u32::from_le_bytes(b[1..5].try_into().unwrap()), 42);
        assert_eq!(u64::from_le_bytes(b[5..13].try_into().unwrap()), 1_234_567_890_123);
        assert_eq!(&b[13..], b"{\"a\":1}");
        server.close();
        assert!(matches!(ws.read(), Ok(Message::Close(_)) | Err(_)));
        assert_eq!(server.dropped(), 0);
    }

    #[test]
    fn a_port_in_use_is_an_error_not_a_panic() {
        let s = FoxgloveServer::bind("127.0.0.1:0").unwrap();
        let e = FoxgloveServer::bind(&s.local_addr().to_string()).err().unwrap();
        assert!(e.0.contains("cannot listen"), "{e}");
        assert!(FoxgloveServer::bind("not an address").is_err());
    }
}
