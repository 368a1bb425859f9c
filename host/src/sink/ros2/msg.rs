//! The ROS 2 messages loglio publishes, as serde structs that mirror the `.msg` definitions
//! field by field: serde's order is the CDR order, so the bytes are what `rmw` expects.

use serde::ser::{Serialize, SerializeTuple, Serializer};

/// `builtin_interfaces/Time`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct Time {
    /// Seconds since the epoch.
    pub sec: i32,
    /// Nanoseconds within the second.
    pub nanosec: u32,
}

impl Time {
    /// From ns since the epoch (saturating at i32 seconds, as ROS's own `Time` is).
    pub fn from_ns(t_ns: u64) -> Time {
        let sec = i32::try_from(t_ns / 1_000_000_000).unwrap_or(i32::MAX);
        Time { sec, nanosec: (t_ns % 1_000_000_000) as u32 }
    }
}

/// `std_msgs/Header`.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Header {
    /// When.
    pub stamp: Time,
    /// The frame the data is in.
    pub frame_id: String,
}

/// `geometry_msgs/Point` and `geometry_msgs/Vector3` (the same layout).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct Vector3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

impl From<[f64; 3]> for Vector3 {
    fn from(v: [f64; 3]) -> Self {
        Vector3 { x: v[0], y: v[1], z: v[2] }
    }
}

/// `geometry_msgs/Quaternion` (x, y, z, w on the wire).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}

impl Quaternion {
    /// From (w, x, y, z).
    pub fn from_wxyz(q: [f64; 4]) -> Quaternion {
        Quaternion { x: q[1], y: q[2], z: q[3], w: q[0] }
    }
}

/// `geometry_msgs/Pose`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Pose {
    /// Position.
    pub position: Vector3,
    /// Orientation.
    pub orientation: Quaternion,
}

/// A row-major 6 x 6 covariance: `float64[36]`, a fixed array (no length on the wire; serde
/// derives arrays only up to 32).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Cov6(pub [f64; 36]);

impl Serialize for Cov6 {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut t = s.serialize_tuple(36)?;
        for v in &self.0 {
            t.serialize_element(v)?;
        }
        t.end()
    }
}

/// `geometry_msgs/PoseWithCovariance`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct PoseWithCovariance {
    /// The pose.
    pub pose: Pose,
    /// (x, y, z, rotation about x, y, z), row-major.
    pub covariance: Cov6,
}

/// `geometry_msgs/Twist`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Twist {
    /// Linear velocity, m/s.
    pub linear: Vector3,
    /// Angular velocity, rad/s.
    pub angular: Vector3,
}

/// `geometry_msgs/TwistWithCovariance`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct TwistWithCovariance {
    /// The twist.
    pub twist: Twist,
    /// (vx, vy, vz, wx, wy, wz), row-major.
    pub covariance: Cov6,
}

/// `nav_msgs/Odometry`.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Odometry {
    /// Stamp and the pose's frame (`odom`).
    pub header: Header,
    /// The twist's frame (`base_link`).
    pub child_frame_id: String,
    /// The pose in `header.frame_id`.
    pub pose: PoseWithCovariance,
    /// The velocity in `child_frame_id`.
    pub twist: TwistWithCovariance,
}

/// `geometry_msgs/Transform`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Transform {
    /// Translation.
    pub translation: Vector3,
    /// Rotation.
    pub rotation: Quaternion,
}

/// `geometry_msgs/TransformStamped`.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct TransformStamped {
    /// Stamp and the parent frame.
    pub header: Header,
    /// The child frame.
    pub child_frame_id: String,
    /// The child's pose in the parent.
    pub transform: Transform,
}

/// `tf2_msgs/TFMessage`.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct TfMessage {
    /// The transforms.
    pub transforms: Vec<TransformStamped>,
}

/// `sensor_msgs/PointField`.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct PointField {
    /// Field name.
    pub name: String,
    /// Byte offset in the point.
    pub offset: u32,
    /// `FLOAT32` is 7.
    pub datatype: u8,
    /// Elements in the field.
    pub count: u32,
}

/// `sensor_msgs/PointField.FLOAT32`.
pub const FLOAT32: u8 = 7;

/// A `uint8[]` written as one length and a block of bytes (not byte by byte).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ByteSeq(pub Vec<u8>);

impl Serialize for ByteSeq {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(&self.0)
    }
}

/// `sensor_msgs/PointCloud2`.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct PointCloud2 {
    /// Stamp and frame.
    pub header: Header,
    /// Rows (1: unordered).
    pub height: u32,
    /// Points in a row.
    pub width: u32,
    /// The layout of a point.
    pub fields: Vec<PointField>,
    /// Byte order of `data`.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The points.
    pub data: ByteSeq,
    /// No invalid (non-finite) points.
    pub is_dense: bool,
}

impl PointCloud2 {
    /// An unordered x, y, z float32 cloud (little-endian) of the finite points of `pts`.
    pub fn xyz<'a>(header: Header, pts: impl Iterator<Item = &'a [f32; 3]>) -> PointCloud2 {
        let mut data = Vec::new();
        let mut n = 0u32;
        for p in pts.filter(|p| p.iter().all(|v| v.is_finite())) {
            for v in p {
                data.extend_from_slice(&v.to_le_bytes());
            }
            n = n.saturating_add(1);
        }
        let field =
            |name: &str, offset| PointField { name: name.into(), offset, datatype: FLOAT32, count: 1 };
        PointCloud2 {
            header,
            height: 1,
            width: n,
            fields: vec![field("x", 0), field("y", 4), field("z", 8)],
            is_bigendian: false,
            point_step: 12,
            row_step: n.saturating_mul(12),
            data: ByteSeq(data),
            is_dense: true,
        }
    }
}
