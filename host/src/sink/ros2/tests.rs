use rustdds::CDRSerializerAdapter;
use rustdds::no_key::SerializerAdapter;

use super::msg::*;
use super::*;
use crate::sink::LiveStatus;

/// What goes on the wire: the 4-byte encapsulation header, then the CDR body.
fn wire<T: serde::Serialize>(m: &T) -> Vec<u8> {
    let mut v = <CDRSerializerAdapter<T> as SerializerAdapter<T>>::output_encoding().to_bytes().to_vec();
    v.extend_from_slice(&[0, 0]);
    v.extend_from_slice(&<CDRSerializerAdapter<T> as SerializerAdapter<T>>::to_bytes(m).unwrap());
    v
}

fn le32(v: u32) -> [u8; 4] {
    v.to_le_bytes()
}

#[test]
fn tf_message_bytes_by_hand() {
    let m = TfMessage {
        transforms: vec![TransformStamped {
            header: Header { stamp: Time { sec: 1, nanosec: 2 }, frame_id: "odom".into() },
            child_frame_id: "base_link".into(),
            transform: Transform {
                translation: Vector3 { x: 1.0, y: 2.0, z: 3.0 },
                rotation: Quaternion { x: 0.0, y: 0.0, z: 0.0, w: 1.0 },
            },
        }],
    };
    let mut e = vec![0x00, 0x01, 0x00, 0x00]; // CDR little-endian, no options
    e.extend(le32(1)); // sequence length, @0 of the body
    e.extend(le32(1)); // stamp.sec @4
    e.extend(le32(2)); // stamp.nanosec @8
    e.extend(le32(5)); // "odom" with its terminator @12
    e.extend(b"odom\0"); // @16..21
    e.extend([0; 3]); // to 4 @24
    e.extend(le32(10)); // "base_link\0" @24
    e.extend(b"base_link\0"); // @28..38
    e.extend([0; 2]); // doubles align to 8 @40
    for v in [1.0f64, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0] {
        e.extend(v.to_le_bytes());
    }
    assert_eq!(wire(&m), e);
    assert_eq!(e.len(), 4 + 96);
}

#[test]
fn point_cloud_bytes_by_hand() {
    let h = Header { stamp: Time { sec: 7, nanosec: 8 }, frame_id: "odom".into() };
    let pts = [[1.0f32, 2.0, 3.0], [f32::NAN, 0.0, 0.0]];
    let m = PointCloud2::xyz(h, pts.iter());
    assert_eq!((m.width, m.height, m.point_step, m.row_step, m.data.0.len()), (1, 1, 12, 12, 12));
    let b = wire(&m);
    let body = &b[4..];
    let u32_at = |o: usize| u32::from_le_bytes(body[o..o + 4].try_into().unwrap());
    assert_eq!(&b[..4], &[0, 1, 0, 0]);
    assert_eq!((u32_at(0), u32_at(4), u32_at(8)), (7, 8, 5));
    assert_eq!(&body[12..17], b"odom\0");
    assert_eq!((u32_at(20), u32_at(24), u32_at(28)), (1, 1, 3)); // height, width, 3 fields
    // Field x: name @32, offset @40, datatype (u8) @44, count aligned to 4 @48.
    assert_eq!((u32_at(32), &body[36..38], u32_at(40), body[44], u32_at(48)), (2, &b"x\0"[..], 0, 7, 1));
    assert_eq!((u32_at(52), &body[56..58], u32_at(60), body[64], u32_at(68)), (2, &b"y\0"[..], 4, 7, 1));
    assert_eq!((u32_at(72), &body[76..78], u32_at(80), body[84], u32_at(88)), (2, &b"z\0"[..], 8, 7, 1));
    assert_eq!(body[92], 0); // is_bigendian
    assert_eq!((u32_at(96), u32_at(100), u32_at(104)), (12, 12, 12)); // point_step, row_step, data length
    let xyz: Vec<f32> = body[108..120].chunks(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect();
    assert_eq!(xyz, [1.0, 2.0, 3.0]);
    assert_eq!(body[120], 1); // is_dense
    assert_eq!(body.len(), 121);
}

#[test]
fn odometry_layout_and_values() {
    let mut p = PoseSample::placeholder(1_700_000_000_123_456_789, LiveStatus::Ok, 0);
    p.position = [1.0, 2.0, 3.0];
    // 90 degrees about z.
    let h = std::f64::consts::FRAC_1_SQRT_2;
    p.q_wxyz = [h, 0.0, 0.0, h];
    p.velocity_body = [0.5, 0.0, 0.0];
    p.angular_velocity_body = [0.0, 0.0, 0.1];
    for i in 0..6 {
        p.pose_covariance[i][i] = (i + 1) as f64;
    }
    p.velocity_covariance = [[0.1, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.3]];
    let m = odometry(&p, "odom", "base_link");
    assert_eq!(m.header.stamp, Time { sec: 1_700_000_000, nanosec: 123_456_789 });
    assert_eq!((m.header.frame_id.as_str(), m.child_frame_id.as_str()), ("odom", "base_link"));
    assert_eq!(m.pose.pose.orientation, Quaternion { x: 0.0, y: 0.0, z: h, w: h });
    let c = m.pose.covariance.0;
    assert_eq!(&c[..3], &[1.0, 0.0, 0.0]);
    // Body rotation errors about x (var 4) and y (var 5) become the world's y and x.
    assert!((c[3 * 6 + 3] - 5.0).abs() < 1e-12 && (c[4 * 6 + 4] - 4.0).abs() < 1e-12);
    assert!((c[5 * 6 + 5] - 6.0).abs() < 1e-12);
    let t = m.twist.covariance.0;
    assert_eq!((t[0], t[7], t[14], t[21], t[35]), (0.1, 0.2, 0.3, GYRO_RATE_VARIANCE, GYRO_RATE_VARIANCE));
    assert_eq!(m.twist.twist.linear, Vector3 { x: 0.5, y: 0.0, z: 0.0 });
    // Header 4+4+4+5 -> 17, child "base_link" at 20 (+4+10 = 34), doubles from 40: pose 7,
    // covariance 36, twist 6, covariance 36.
    let b = wire(&m);
    assert_eq!(b.len(), 4 + 40 + 8 * (7 + 36 + 6 + 36));
    assert_eq!(f64::from_le_bytes(b[4 + 40..4 + 48].try_into().unwrap()), 1.0);
}

#[test]
fn stamps_and_names() {
    assert_eq!(Time::from_ns(0), Time { sec: 0, nanosec: 0 });
    assert_eq!(Time::from_ns(u64::MAX).sec, i32::MAX);
    assert_eq!(domain_from_env(None), Ok(0));
    assert_eq!(domain_from_env(Some(" 42 ")), Ok(42));
    assert!(domain_from_env(Some("300")).is_err() && domain_from_env(Some("x")).is_err());
    assert_eq!(check_namespace("/loglio").unwrap(), "/loglio");
    assert_eq!(check_namespace("/robot1/loglio/").unwrap(), "/robot1/loglio");
    assert_eq!(check_namespace("/").unwrap(), "");
    for bad in ["loglio", "/a b", "/1a", "//a", "/a-b"] {
        let e = check_namespace(bad).unwrap_err().0;
        assert!(e.starts_with("--ros2-namespace") && !e.contains('\n'), "{bad}: {e}");
    }
    assert!(check_frame("--ros2-frame-id", "odom").is_ok());
    assert!(check_frame("--ros2-frame-id", "").is_err() && check_frame("--ros2-frame-id", "/odom").is_err());
}

#[test]
fn tf_of_a_pose() {
    let mut p = PoseSample::placeholder(2_000_000_001, LiveStatus::Ok, 0);
    p.position = [4.0, 5.0, 6.0];
    let m = transform(&p, "map", "imu");
    let t = &m.transforms[0];
    assert_eq!((t.header.frame_id.as_str(), t.child_frame_id.as_str()), ("map", "imu"));
    assert_eq!(t.header.stamp, Time { sec: 2, nanosec: 1 });
    assert_eq!(t.transform.translation, Vector3 { x: 4.0, y: 5.0, z: 6.0 });
    assert_eq!(t.transform.rotation, Quaternion { x: 0.0, y: 0.0, z: 0.0, w: 1.0 });
}
