//! The ROS messages loglio reads from bags, and writes for tests and for peer odometries, in
//! both wire encodings:
//!
//! - **ROS 1** serialisation: little-endian, packed, `uint32` lengths before strings and
//!   variable arrays, `time` as two `uint32`.
//! - **ROS 2 CDR** (OMG classic CDR as Fast-DDS/Cyclone write it): a 4-byte encapsulation header
//!   (`00 01` little-endian, `00 00` big-endian), every primitive aligned to its size counted
//!   from the end of that header, strings with a trailing NUL counted in their length,
//!   `builtin_interfaces/Time` as `int32 sec, uint32 nanosec`.
//!
//! Every decoder checks lengths before reading, so a short or corrupt message is an error, never
//! a panic.

use std::fmt;

/// Wire encoding of a serialised message.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    /// ROS 1.
    Ros1,
    /// ROS 2 CDR (with its encapsulation header).
    Cdr,
}

/// A message could not be decoded.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct MsgError(pub String);

impl fmt::Display for MsgError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for MsgError {}

fn short(what: &str, need: usize, have: usize) -> MsgError {
    MsgError(format!("message too short: {what} needs {need} more bytes, {have} left"))
}

/// A reader over one serialised message.
#[derive(Debug)]
pub(crate) struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
    /// Start of the CDR payload (alignment origin); `None` for ROS 1 (no alignment).
    origin: Option<usize>,
    big_endian: bool,
}

impl<'a> Reader<'a> {
    pub(crate) fn new(buf: &'a [u8], enc: Encoding) -> Result<Self, MsgError> {
        match enc {
            Encoding::Ros1 => Ok(Reader { buf, pos: 0, origin: None, big_endian: false }),
            Encoding::Cdr => {
                if buf.len() < 4 {
                    return Err(short("the CDR encapsulation header", 4, buf.len()));
                }
                let big_endian = match [buf[0], buf[1]] {
                    [0, 0] => true,
                    [0, 1] => false,
                    other => {
                        return Err(MsgError(format!(
                            "unsupported CDR encapsulation {:02x}{:02x} (only classic CDR, 0000/0001)",
                            other[0], other[1]
                        )));
                    }
                };
                Ok(Reader { buf, pos: 4, origin: Some(4), big_endian })
            }
        }
    }

    fn align(&mut self, n: usize) -> Result<(), MsgError> {
        if let Some(o) = self.origin {
            let rem = (self.pos - o) % n;
            if rem != 0 {
                self.take(n - rem, "alignment padding")?;
            }
        }
        Ok(())
    }

    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], MsgError> {
        let left = self.buf.len() - self.pos;
        if n > left {
            return Err(short(what, n, left));
        }
        let s = &self.buf[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn fixed<const N: usize>(&mut self, what: &str) -> Result<[u8; N], MsgError> {
        self.align(N)?;
        let s = self.take(N, what)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        if self.big_endian {
            a.reverse();
        }
        Ok(a)
    }

    pub(crate) fn u8(&mut self, what: &str) -> Result<u8, MsgError> {
        Ok(self.take(1, what)?[0])
    }

    pub(crate) fn u32(&mut self, what: &str) -> Result<u32, MsgError> {
        self.fixed::<4>(what).map(u32::from_le_bytes)
    }

    pub(crate) fn i32(&mut self, what: &str) -> Result<i32, MsgError> {
        self.fixed::<4>(what).map(i32::from_le_bytes)
    }

    pub(crate) fn f64(&mut self, what: &str) -> Result<f64, MsgError> {
        self.fixed::<8>(what).map(f64::from_le_bytes)
    }

    /// A `uint8[]` (length-prefixed).
    pub(crate) fn bytes(&mut self, what: &str) -> Result<&'a [u8], MsgError> {
        let n = self.u32(what)? as usize;
        self.take(n, what)
    }

    /// A `uint8[N]` (no length).
    pub(crate) fn array(&mut self, n: usize, what: &str) -> Result<&'a [u8], MsgError> {
        self.take(n, what)
    }

    pub(crate) fn string(&mut self, what: &str) -> Result<String, MsgError> {
        let raw = self.bytes(what)?;
        let raw = if self.origin.is_some() { raw.strip_suffix(&[0]).unwrap_or(raw) } else { raw };
        String::from_utf8(raw.to_vec()).map_err(|_| MsgError(format!("{what} is not UTF-8")))
    }

    /// `time` (ROS 1) or `builtin_interfaces/Time` (CDR) as nanoseconds since the epoch.
    pub(crate) fn time(&mut self, what: &str) -> Result<u64, MsgError> {
        let (sec, nsec) = if self.origin.is_some() {
            let s = self.i32(what)?;
            if s < 0 {
                return Err(MsgError(format!("{what}: negative time ({s} s)")));
            }
            (s as u64, self.u32(what)? as u64)
        } else {
            (self.u32(what)? as u64, self.u32(what)? as u64)
        };
        if nsec >= 1_000_000_000 {
            return Err(MsgError(format!("{what}: {nsec} ns is not below one second")));
        }
        Ok(sec * 1_000_000_000 + nsec)
    }

    /// `std_msgs/Header`: (stamp ns, frame_id).
    pub(crate) fn header(&mut self) -> Result<(u64, String), MsgError> {
        if self.origin.is_none() {
            self.u32("header.seq")?;
        }
        let t = self.time("header.stamp")?;
        let frame = self.string("header.frame_id")?;
        Ok((t, frame))
    }

    /// Number of elements of a sequence, checked against the bytes left (each element takes at
    /// least `min_elem` bytes), so a corrupt count cannot make the caller allocate gigabytes.
    pub(crate) fn count(&mut self, what: &str, min_elem: usize) -> Result<usize, MsgError> {
        let n = self.u32(what)? as usize;
        let left = self.buf.len() - self.pos;
        if n.saturating_mul(min_elem.max(1)) > left {
            return Err(MsgError(format!("{what}: {n} elements cannot fit in the {left} bytes left")));
        }
        Ok(n)
    }
}

/// A writer of one serialised message.
#[derive(Debug)]
pub(crate) struct Writer {
    buf: Vec<u8>,
    cdr: bool,
}

impl Writer {
    pub(crate) fn new(enc: Encoding) -> Self {
        match enc {
            Encoding::Ros1 => Writer { buf: Vec::new(), cdr: false },
            Encoding::Cdr => Writer { buf: vec![0, 1, 0, 0], cdr: true },
        }
    }

    fn align(&mut self, n: usize) {
        if self.cdr {
            while !(self.buf.len() - 4).is_multiple_of(n) {
                self.buf.push(0);
            }
        }
    }

    pub(crate) fn u8(&mut self, v: u8) {
        self.buf.push(v);
    }

    pub(crate) fn u32(&mut self, v: u32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub(crate) fn i32(&mut self, v: i32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub(crate) fn f64(&mut self, v: f64) {
        self.align(8);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub(crate) fn bytes(&mut self, v: &[u8]) {
        self.u32(v.len() as u32);
        self.buf.extend_from_slice(v);
    }

    pub(crate) fn array(&mut self, v: &[u8]) {
        self.buf.extend_from_slice(v);
    }

    pub(crate) fn string(&mut self, s: &str) {
        if self.cdr {
            self.u32(s.len() as u32 + 1);
            self.buf.extend_from_slice(s.as_bytes());
            self.buf.push(0);
        } else {
            self.bytes(s.as_bytes());
        }
    }

    pub(crate) fn time(&mut self, ns: u64) {
        let (s, n) = ((ns / 1_000_000_000) as u32, (ns % 1_000_000_000) as u32);
        if self.cdr {
            self.i32(s as i32);
        } else {
            self.u32(s);
        }
        self.u32(n);
    }

    pub(crate) fn header(&mut self, seq: u32, stamp_ns: u64, frame_id: &str) {
        if !self.cdr {
            self.u32(seq);
        }
        self.time(stamp_ns);
        self.string(frame_id);
    }

    pub(crate) fn finish(self) -> Vec<u8> {
        self.buf
    }
}

/// `sensor_msgs/PointField` datatypes.
pub mod datatype {
    /// int8
    pub const INT8: u8 = 1;
    /// uint8
    pub const UINT8: u8 = 2;
    /// int16
    pub const INT16: u8 = 3;
    /// uint16
    pub const UINT16: u8 = 4;
    /// int32
    pub const INT32: u8 = 5;
    /// uint32
    pub const UINT32: u8 = 6;
    /// float32
    pub const FLOAT32: u8 = 7;
    /// float64
    pub const FLOAT64: u8 = 8;

    /// Size in bytes of a datatype, or `None` for an unknown code.
    pub fn size(dt: u8) -> Option<usize> {
        match dt {
            INT8 | UINT8 => Some(1),
            INT16 | UINT16 => Some(2),
            INT32 | UINT32 | FLOAT32 => Some(4),
            FLOAT64 => Some(8),
            _ => None,
        }
    }
}

/// `sensor_msgs/PointField`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PointField {
    /// Field name (`x`, `ring`, `time`, ...).
    pub name: String,
    /// Byte offset in the point.
    pub offset: u32,
    /// One of [`datatype`].
    pub datatype: u8,
    /// Number of elements.
    pub count: u32,
}

/// `sensor_msgs/PointCloud2`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PointCloud2 {
    /// Header stamp, ns.
    pub stamp_ns: u64,
    /// Header frame.
    pub frame_id: String,
    /// Rows (1 for unorganised clouds).
    pub height: u32,
    /// Points per row.
    pub width: u32,
    /// The field table.
    pub fields: Vec<PointField>,
    /// Byte order of `data`.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The points.
    pub data: Vec<u8>,
    /// No invalid points.
    pub is_dense: bool,
}

impl PointCloud2 {
    /// Decodes a serialised PointCloud2.
    pub fn decode(buf: &[u8], enc: Encoding) -> Result<Self, MsgError> {
        let mut r = Reader::new(buf, enc)?;
        let (stamp_ns, frame_id) = r.header()?;
        let height = r.u32("height")?;
        let width = r.u32("width")?;
        let n = r.count("fields", 13)?;
        let mut fields = Vec::with_capacity(n);
        for _ in 0..n {
            let name = r.string("field name")?;
            let offset = r.u32("field offset")?;
            let datatype = r.u8("field datatype")?;
            let count = r.u32("field count")?;
            fields.push(PointField { name, offset, datatype, count });
        }
        let is_bigendian = r.u8("is_bigendian")? != 0;
        let point_step = r.u32("point_step")?;
        let row_step = r.u32("row_step")?;
        let data = r.bytes("data")?.to_vec();
        let is_dense = r.u8("is_dense")? != 0;
        Ok(PointCloud2 {
            stamp_ns,
            frame_id,
            height,
            width,
            fields,
            is_bigendian,
            point_step,
            row_step,
            data,
            is_dense,
        })
    }

    /// Serialises the message.
    pub fn encode(&self, enc: Encoding) -> Vec<u8> {
        let mut w = Writer::new(enc);
        w.header(0, self.stamp_ns, &self.frame_id);
        w.u32(self.height);
        w.u32(self.width);
        w.u32(self.fields.len() as u32);
        for f in &self.fields {
            w.string(&f.name);
            w.u32(f.offset);
            w.u8(f.datatype);
            w.u32(f.count);
        }
        w.u8(self.is_bigendian as u8);
        w.u32(self.point_step);
        w.u32(self.row_step);
        w.bytes(&self.data);
        w.u8(self.is_dense as u8);
        w.finish()
    }
}

/// `sensor_msgs/Imu` (the covariances are read and ignored; written as zeros with the
/// orientation covariance's first element -1, "no orientation").
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Imu {
    /// Header stamp, ns.
    pub stamp_ns: u64,
    /// Orientation (x, y, z, w).
    pub orientation_xyzw: [f64; 4],
    /// Angular velocity, rad/s.
    pub angular_velocity: [f64; 3],
    /// Linear acceleration (specific force), m/s^2.
    pub linear_acceleration: [f64; 3],
}

impl Imu {
    /// Decodes a serialised Imu.
    pub fn decode(buf: &[u8], enc: Encoding) -> Result<Self, MsgError> {
        let mut r = Reader::new(buf, enc)?;
        let (stamp_ns, _) = r.header()?;
        let mut vals = [0.0f64; 37];
        for v in vals.iter_mut() {
            *v = r.f64("Imu fields")?;
        }
        Ok(Imu {
            stamp_ns,
            orientation_xyzw: [vals[0], vals[1], vals[2], vals[3]],
            angular_velocity: [vals[13], vals[14], vals[15]],
            linear_acceleration: [vals[25], vals[26], vals[27]],
        })
    }

    /// Serialises the message.
    pub fn encode(&self, frame_id: &str, enc: Encoding) -> Vec<u8> {
        let mut w = Writer::new(enc);
        w.header(0, self.stamp_ns, frame_id);
        let cov = |w: &mut Writer, first: f64| {
            w.f64(first);
            for _ in 0..8 {
                w.f64(0.0);
            }
        };
        for v in self.orientation_xyzw {
            w.f64(v);
        }
        cov(&mut w, -1.0);
        for v in self.angular_velocity {
            w.f64(v);
        }
        cov(&mut w, 0.0);
        for v in self.linear_acceleration {
            w.f64(v);
        }
        cov(&mut w, 0.0);
        w.finish()
    }
}

/// Bytes of a Velodyne data packet.
pub const VELODYNE_PACKET_BYTES: usize = 1206;

/// `velodyne_msgs/VelodyneScan`: the packets of one revolution.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct VelodyneScan {
    /// Header stamp, ns.
    pub stamp_ns: u64,
    /// (packet stamp ns, 1206 payload bytes).
    pub packets: Vec<(u64, Vec<u8>)>,
}

impl VelodyneScan {
    /// Decodes a serialised VelodyneScan.
    pub fn decode(buf: &[u8], enc: Encoding) -> Result<Self, MsgError> {
        let mut r = Reader::new(buf, enc)?;
        let (stamp_ns, _) = r.header()?;
        let n = r.count("packets", 8 + VELODYNE_PACKET_BYTES)?;
        let mut packets = Vec::with_capacity(n);
        for _ in 0..n {
            let t = r.time("packet stamp")?;
            packets.push((t, r.array(VELODYNE_PACKET_BYTES, "packet data")?.to_vec()));
        }
        Ok(VelodyneScan { stamp_ns, packets })
    }

    /// Serialises the message.
    pub fn encode(&self, enc: Encoding) -> Vec<u8> {
        let mut w = Writer::new(enc);
        w.header(0, self.stamp_ns, "velodyne");
        w.u32(self.packets.len() as u32);
        for (t, p) in &self.packets {
            w.time(*t);
            let mut data = p.clone();
            data.resize(VELODYNE_PACKET_BYTES, 0);
            w.array(&data);
        }
        w.finish()
    }
}

/// `ouster_ros/PacketMsg` (ROS 1) / `ouster_sensor_msgs/msg/PacketMsg` (ROS 2): `uint8[] buf`.
pub fn decode_packet_msg(buf: &[u8], enc: Encoding) -> Result<Vec<u8>, MsgError> {
    Reader::new(buf, enc)?.bytes("buf").map(<[u8]>::to_vec)
}

/// Serialises a PacketMsg.
pub fn encode_packet_msg(payload: &[u8], enc: Encoding) -> Vec<u8> {
    let mut w = Writer::new(enc);
    w.bytes(payload);
    w.finish()
}

/// `std_msgs/String`.
pub fn decode_string(buf: &[u8], enc: Encoding) -> Result<String, MsgError> {
    Reader::new(buf, enc)?.string("data")
}

/// Serialises a `std_msgs/String`.
pub fn encode_string(s: &str, enc: Encoding) -> Vec<u8> {
    let mut w = Writer::new(enc);
    w.string(s);
    w.finish()
}

/// A ROS message type as a ROS 1 bag needs it: name, MD5 sum and full definition.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MessageType {
    /// `package/Name`.
    pub name: &'static str,
    /// The ROS 1 MD5 sum of the definition.
    pub md5sum: &'static str,
    /// The full definition, dependencies appended after `=====` lines (as `gendeps --cat` writes).
    pub definition: &'static str,
}

const SEP: &str = "================================================================================\n";

/// `sensor_msgs/PointCloud2`.
pub const POINTCLOUD2: MessageType = MessageType {
    name: "sensor_msgs/PointCloud2",
    md5sum: "1158d486dd51d683ce2f1be655c3c181",
    definition: concat!(
        "Header header\nuint32 height\nuint32 width\nPointField[] fields\nbool is_bigendian\nuint32 point_step\n",
        "uint32 row_step\nuint8[] data\nbool is_dense\n",
        "================================================================================\n",
        "MSG: std_msgs/Header\nuint32 seq\ntime stamp\nstring frame_id\n",
        "================================================================================\n",
        "MSG: sensor_msgs/PointField\nuint8 INT8    = 1\nuint8 UINT8   = 2\nuint8 INT16   = 3\nuint8 UINT16  = 4\n",
        "uint8 INT32   = 5\nuint8 UINT32  = 6\nuint8 FLOAT32 = 7\nuint8 FLOAT64 = 8\n",
        "string name\nuint32 offset\nuint8  datatype\nuint32 count\n"
    ),
};

/// `sensor_msgs/Imu`.
pub const IMU: MessageType = MessageType {
    name: "sensor_msgs/Imu",
    md5sum: "6a62c6daae103f4ff57a132d6f95cec2",
    definition: concat!(
        "Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n",
        "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n",
        "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance\n",
        "================================================================================\n",
        "MSG: std_msgs/Header\nuint32 seq\ntime stamp\nstring frame_id\n",
        "================================================================================\n",
        "MSG: geometry_msgs/Quaternion\nfloat64 x\nfloat64 y\nfloat64 z\nfloat64 w\n",
        "================================================================================\n",
        "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
    ),
};

/// `ouster_ros/PacketMsg`.
pub const OUSTER_PACKET: MessageType = MessageType {
    name: "ouster_ros/PacketMsg",
    md5sum: "4f7b5949e76f86d01e96b0e33ba9b5e3",
    definition: "uint8[] buf\n",
};

/// `velodyne_msgs/VelodyneScan`.
pub const VELODYNE_SCAN: MessageType = MessageType {
    name: "velodyne_msgs/VelodyneScan",
    md5sum: "50804fc9533a0e579e6322c04ae70566",
    definition: concat!(
        "Header           header\nVelodynePacket[] packets\n",
        "================================================================================\n",
        "MSG: std_msgs/Header\nuint32 seq\ntime stamp\nstring frame_id\n",
        "================================================================================\n",
        "MSG: velodyne_msgs/VelodynePacket\ntime stamp\nuint8[1206] data\n"
    ),
};

/// `std_msgs/String`.
pub const STRING: MessageType = MessageType {
    name: "std_msgs/String",
    md5sum: "992ce8a1687cec8c8bd883ec73ca41d1",
    definition: "string data\n",
};

/// `tf2_msgs/TFMessage` (`/tf`, `/tf_static`).
pub const TF_MESSAGE: MessageType = MessageType {
    name: "tf2_msgs/TFMessage",
    md5sum: "94810edda583a504dfda3829e70d7eec",
    definition: concat!(
        "geometry_msgs/TransformStamped[] transforms\n",
        "================================================================================\n",
        "MSG: geometry_msgs/TransformStamped\nHeader header\nstring child_frame_id\nTransform transform\n",
        "================================================================================\n",
        "MSG: std_msgs/Header\nuint32 seq\ntime stamp\nstring frame_id\n",
        "================================================================================\n",
        "MSG: geometry_msgs/Transform\nVector3 translation\nQuaternion rotation\n",
        "================================================================================\n",
        "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n",
        "================================================================================\n",
        "MSG: geometry_msgs/Quaternion\nfloat64 x\nfloat64 y\nfloat64 z\nfloat64 w\n"
    ),
};

/// One `geometry_msgs/TransformStamped`: the child frame in the parent frame,
/// `p_parent = R * p_child + t`.
#[derive(Clone, Debug, PartialEq)]
pub struct Transform {
    /// The parent frame (`header.frame_id`).
    pub parent: String,
    /// The child frame.
    pub child: String,
    /// t, metres.
    pub translation: [f64; 3],
    /// R as x, y, z, w.
    pub rotation_xyzw: [f64; 4],
}

/// Decodes a `tf2_msgs/TFMessage`.
pub fn decode_tf(buf: &[u8], enc: Encoding) -> Result<Vec<Transform>, MsgError> {
    let mut r = Reader::new(buf, enc)?;
    // Each: a header (at least 12 bytes), a child frame (4) and 7 float64.
    let n = r.count("transforms", 12 + 4 + 56)?;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let (_, parent) = r.header()?;
        let child = r.string("child_frame_id")?;
        let mut v = [0.0; 7];
        for x in v.iter_mut() {
            *x = r.f64("transform")?;
        }
        out.push(Transform {
            parent,
            child,
            translation: [v[0], v[1], v[2]],
            rotation_xyzw: [v[3], v[4], v[5], v[6]],
        });
    }
    Ok(out)
}

/// Serialises a `tf2_msgs/TFMessage`.
pub fn encode_tf(transforms: &[Transform], enc: Encoding) -> Vec<u8> {
    let mut w = Writer::new(enc);
    w.u32(transforms.len() as u32);
    for t in transforms {
        w.header(0, 0, &t.parent);
        w.string(&t.child);
        for v in t.translation.iter().chain(&t.rotation_xyzw) {
            w.f64(*v);
        }
    }
    w.finish()
}

/// The ROS 2 definition text of a type for an MCAP schema (`ros2msg` encoding): the ROS 1
/// definition with ROS 2 names (`std_msgs/Header` without `seq`, `builtin_interfaces/Time`).
pub fn ros2_schema(t: &MessageType) -> String {
    t.definition
        .replace(
            "MSG: std_msgs/Header\nuint32 seq\ntime stamp\n",
            "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\n",
        )
        .replace("Header header", "std_msgs/Header header")
        .replace("Header           header", "std_msgs/Header header")
        .replace("time stamp", "builtin_interfaces/Time stamp")
        .replace("builtin_interfaces/builtin_interfaces/Time", "builtin_interfaces/Time")
        + &format!("{SEP}MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n")
}

/// The ROS 2 name of a type (`sensor_msgs/msg/PointCloud2`).
pub fn ros2_name(t: &MessageType) -> String {
    let name = t.name.replace("ouster_ros/", "ouster_sensor_msgs/");
    match name.split_once('/') {
        Some((pkg, n)) => format!("{pkg}/msg/{n}"),
        None => name,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud() -> PointCloud2 {
        PointCloud2 {
            stamp_ns: 1_600_000_000_500_000_001,
            frame_id: "velodyne".into(),
            height: 1,
            width: 2,
            fields: vec![
                PointField { name: "x".into(), offset: 0, datatype: datatype::FLOAT32, count: 1 },
                PointField { name: "ring".into(), offset: 4, datatype: datatype::UINT16, count: 1 },
            ],
            is_bigendian: false,
            point_step: 6,
            row_step: 12,
            data: (0..12).collect(),
            is_dense: true,
        }
    }

    #[test]
    fn pointcloud2_round_trips_in_both_encodings() {
        for enc in [Encoding::Ros1, Encoding::Cdr] {
            let c = cloud();
            let bytes = c.encode(enc);
            assert_eq!(PointCloud2::decode(&bytes, enc).unwrap(), c, "{enc:?}");
            // Every truncation is an error, never a panic.
            for cut in 0..bytes.len() {
                assert!(PointCloud2::decode(&bytes[..cut], enc).is_err(), "{enc:?} cut {cut}");
            }
        }
        // ROS 1 layout: seq, sec, nsec, frame_id length and bytes, height, ...
        let b = cloud().encode(Encoding::Ros1);
        assert_eq!(&b[4..8], &1_600_000_000u32.to_le_bytes());
        assert_eq!(&b[8..12], &500_000_001u32.to_le_bytes());
        assert_eq!(&b[12..16], &8u32.to_le_bytes());
        assert_eq!(&b[16..24], b"velodyne");
        // CDR: header 00 01 00 00, sec, nanosec, frame_id with NUL counted.
        let c = cloud().encode(Encoding::Cdr);
        assert_eq!(&c[..4], &[0, 1, 0, 0]);
        assert_eq!(&c[12..16], &9u32.to_le_bytes());
        assert_eq!(&c[16..25], b"velodyne\0");
    }

    #[test]
    fn imu_round_trips_with_cdr_alignment() {
        let m = Imu {
            stamp_ns: 42_000_000_007,
            orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
            angular_velocity: [0.1, -0.2, 0.3],
            linear_acceleration: [0.5, 0.25, 9.81],
        };
        for enc in [Encoding::Ros1, Encoding::Cdr] {
            let b = m.encode("imu_link", enc);
            assert_eq!(Imu::decode(&b, enc).unwrap(), m);
        }
        // CDR: "imu_link\0" ends at payload offset 4+4+4+9 = 21, padded to 24 for the first f64.
        let b = m.encode("imu_link", Encoding::Cdr);
        assert_eq!(b.len(), 4 + 24 + 37 * 8);
        assert_eq!(
            Imu::decode(&b[..100], Encoding::Cdr).unwrap_err().0,
            "message too short: Imu fields needs 8 more bytes, 0 left"
        );
    }

    #[test]
    fn big_endian_cdr_and_bad_encapsulation() {
        let mut b = vec![0u8, 0, 0, 0];
        b.extend_from_slice(&5u32.to_be_bytes());
        b.extend_from_slice(b"abcd\0");
        assert_eq!(decode_string(&b, Encoding::Cdr).unwrap(), "abcd");
        assert_eq!(
            decode_string(&[0, 7, 0, 0], Encoding::Cdr).unwrap_err().0,
            "unsupported CDR encapsulation 0007 (only classic CDR, 0000/0001)"
        );
        // A huge sequence count is refused before allocating.
        let mut w = Writer::new(Encoding::Ros1);
        w.header(0, 0, "");
        w.u32(u32::MAX);
        assert!(VelodyneScan::decode(&w.finish(), Encoding::Ros1).unwrap_err().0.contains("cannot fit"));
    }

    #[test]
    fn velodyne_scan_and_packets_round_trip() {
        let s = VelodyneScan { stamp_ns: 7, packets: vec![(5, vec![1; 1206]), (6, vec![2; 1206])] };
        for enc in [Encoding::Ros1, Encoding::Cdr] {
            assert_eq!(VelodyneScan::decode(&s.encode(enc), enc).unwrap(), s);
            assert_eq!(decode_packet_msg(&encode_packet_msg(&[9, 8, 7], enc), enc).unwrap(), vec![9, 8, 7]);
            assert_eq!(decode_string(&encode_string("{}", enc), enc).unwrap(), "{}");
        }
    }

    #[test]
    fn ros2_names_and_schemas() {
        assert_eq!(ros2_name(&POINTCLOUD2), "sensor_msgs/msg/PointCloud2");
        assert_eq!(ros2_name(&OUSTER_PACKET), "ouster_sensor_msgs/msg/PacketMsg");
        let s = ros2_schema(&IMU);
        assert!(s.starts_with("std_msgs/Header header\n"));
        assert!(s.contains("MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"));
        assert!(s.ends_with("MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"));
        assert!(!s.contains("seq"));
    }
}
