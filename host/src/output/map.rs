//! The map as a point cloud: PLY (binary little-endian, normals optional) and PCD v0.7 (ASCII
//! or binary), readable by CloudCompare, PCL, Open3D and MeshLab.

use std::io::{self, Write};
use std::path::Path;

/// One map point in the world frame, with its normal when the map has one.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MapPoint {
    /// Position, metres.
    pub xyz: [f32; 3],
    /// Unit normal, if known. Written as (0, 0, 0) when normals are requested and this is `None`.
    pub normal: Option<[f32; 3]>,
}

impl MapPoint {
    fn normal_or_zero(&self) -> [f32; 3] {
        self.normal.unwrap_or([0.0; 3])
    }
}

/// Writes a binary little-endian PLY with `x y z` (float32) and, if `normals`, `nx ny nz`.
pub fn write_ply<W: Write>(mut w: W, points: &[MapPoint], normals: bool) -> io::Result<()> {
    write!(
        w,
        "ply\nformat binary_little_endian 1.0\ncomment loglio map (world frame, metres)\nelement vertex {}\n",
        points.len()
    )?;
    w.write_all(b"property float x\nproperty float y\nproperty float z\n")?;
    if normals {
        w.write_all(b"property float nx\nproperty float ny\nproperty float nz\n")?;
    }
    w.write_all(b"end_header\n")?;
    let mut rec = Vec::with_capacity(24);
    for p in points {
        rec.clear();
        for v in p.xyz {
            rec.extend_from_slice(&v.to_le_bytes());
        }
        if normals {
            for v in p.normal_or_zero() {
                rec.extend_from_slice(&v.to_le_bytes());
            }
        }
        w.write_all(&rec)?;
    }
    w.flush()
}

/// [`write_ply`] to a file.
pub fn write_ply_file(path: &Path, points: &[MapPoint], normals: bool) -> io::Result<()> {
    write_ply(super::create(path)?, points, normals).map_err(|e| super::with_path(e, path))
}

/// PCD data section encoding.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PcdEncoding {
    /// Text, one point per line.
    Ascii,
    /// Packed little-endian float32 records.
    Binary,
}

/// Writes a PCD v0.7 file with fields `x y z` and, if `normals`, `normal_x normal_y normal_z`.
pub fn write_pcd<W: Write>(
    mut w: W,
    points: &[MapPoint],
    normals: bool,
    encoding: PcdEncoding,
) -> io::Result<()> {
    let (fields, n) = if normals { ("x y z normal_x normal_y normal_z", 6) } else { ("x y z", 3) };
    let rep = |s: &str| vec![s; n].join(" ");
    write!(
        w,
        "# .PCD v0.7 - Point Cloud Data file format (loglio map, world frame, metres)\nVERSION 0.7\nFIELDS {fields}\nSIZE {}\nTYPE {}\nCOUNT {}\nWIDTH {}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {}\nDATA {}\n",
        rep("4"),
        rep("F"),
        rep("1"),
        points.len(),
        points.len(),
        if encoding == PcdEncoding::Ascii { "ascii" } else { "binary" }
    )?;
    match encoding {
        PcdEncoding::Ascii => {
            for p in points {
                let [x, y, z] = p.xyz;
                if normals {
                    let [a, b, c] = p.normal_or_zero();
                    writeln!(w, "{x} {y} {z} {a} {b} {c}")?;
                } else {
                    writeln!(w, "{x} {y} {z}")?;
                }
            }
        }
        PcdEncoding::Binary => {
            let mut rec = Vec::with_capacity(24);
            for p in points {
                rec.clear();
                for v in p.xyz {
                    rec.extend_from_slice(&v.to_le_bytes());
                }
                if normals {
                    for v in p.normal_or_zero() {
                        rec.extend_from_slice(&v.to_le_bytes());
                    }
                }
                w.write_all(&rec)?;
            }
        }
    }
    w.flush()
}

/// [`write_pcd`] to a file.
pub fn write_pcd_file(
    path: &Path,
    points: &[MapPoint],
    normals: bool,
    encoding: PcdEncoding,
) -> io::Result<()> {
    write_pcd(super::create(path)?, points, normals, encoding).map_err(|e| super::with_path(e, path))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud() -> Vec<MapPoint> {
        vec![
            MapPoint { xyz: [1.0, -2.5, 0.125], normal: Some([0.0, 0.0, 1.0]) },
            MapPoint { xyz: [1e-3, 3.25e4, -7.0], normal: None },
        ]
    }

    fn split_header(bytes: &[u8], end: &str) -> (String, Vec<u8>) {
        let pos = bytes.windows(end.len()).position(|w| w == end.as_bytes()).unwrap() + end.len();
        (String::from_utf8(bytes[..pos].to_vec()).unwrap(), bytes[pos..].to_vec())
    }

    fn floats(b: &[u8]) -> Vec<f32> {
        b.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect()
    }

    #[test]
    fn ply_binary_with_and_without_normals() {
        let mut out = Vec::new();
        write_ply(&mut out, &cloud(), true).unwrap();
        let (header, body) = split_header(&out, "end_header\n");
        assert!(header.starts_with("ply\nformat binary_little_endian 1.0\n"));
        assert!(header.contains("element vertex 2\n"));
        assert!(header.contains("property float nz\n"));
        assert_eq!(floats(&body), vec![1.0, -2.5, 0.125, 0.0, 0.0, 1.0, 1e-3, 3.25e4, -7.0, 0.0, 0.0, 0.0]);
        let mut out = Vec::new();
        write_ply(&mut out, &cloud(), false).unwrap();
        let (header, body) = split_header(&out, "end_header\n");
        assert!(!header.contains("nx"));
        assert_eq!(floats(&body), vec![1.0, -2.5, 0.125, 1e-3, 3.25e4, -7.0]);
    }

    #[test]
    fn pcd_ascii_and_binary() {
        let mut out = Vec::new();
        write_pcd(&mut out, &cloud(), false, PcdEncoding::Ascii).unwrap();
        let text = String::from_utf8(out).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(
            lines[1..11],
            [
                "VERSION 0.7",
                "FIELDS x y z",
                "SIZE 4 4 4",
                "TYPE F F F",
                "COUNT 1 1 1",
                "WIDTH 2",
                "HEIGHT 1",
                "VIEWPOINT 0 0 0 1 0 0 0",
                "POINTS 2",
                "DATA ascii"
            ]
        );
        assert_eq!(lines[11..], ["1 -2.5 0.125", "0.001 32500 -7"]);
        let mut out = Vec::new();
        write_pcd(&mut out, &cloud(), true, PcdEncoding::Binary).unwrap();
        let (header, body) = split_header(&out, "DATA binary\n");
        assert!(
            header.contains("FIELDS x y z normal_x normal_y normal_z\nSIZE 4 4 4 4 4 4\nTYPE F F F F F F\n")
        );
        assert_eq!(body.len(), 2 * 24);
        assert_eq!(floats(&body)[..6], [1.0, -2.5, 0.125, 0.0, 0.0, 1.0]);
    }
}
