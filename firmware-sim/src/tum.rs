//! Ground truth in the TUM trajectory format: one pose per line,
//! `t x y z qx qy qz qw` (t in seconds, Unix time, printed exactly from integer nanoseconds;
//! position in metres; orientation as a unit quaternion, world z up).

use std::fmt::Write as _;

use nalgebra::Isometry3;

/// One TUM line for a pose at `t_ns`.
pub fn line(t_ns: u64, pose: &Isometry3<f64>) -> String {
    let p = pose.translation.vector;
    let q = pose.rotation.coords; // [i, j, k, w]
    let mut s = String::with_capacity(120);
    let _ = write!(
        s,
        "{}.{:09} {:.9} {:.9} {:.9} {:.12} {:.12} {:.12} {:.12}",
        t_ns / 1_000_000_000,
        t_ns % 1_000_000_000,
        p.x,
        p.y,
        p.z,
        q[0],
        q[1],
        q[2],
        q[3]
    );
    s
}

/// A TUM file (with a comment header) of poses at the given times.
pub fn trajectory(times_ns: impl IntoIterator<Item = u64>, pose: impl Fn(u64) -> Isometry3<f64>) -> String {
    let mut s = String::from("# timestamp tx ty tz qx qy qz qw\n");
    for t in times_ns {
        s.push_str(&line(t, &pose(t)));
        s.push('\n');
    }
    s
}

/// Parses a TUM line into (t_ns, pose); `None` for comments or malformed lines.
pub fn parse_line(l: &str) -> Option<(u64, Isometry3<f64>)> {
    let l = l.trim();
    if l.is_empty() || l.starts_with('#') {
        return None;
    }
    let mut it = l.split_whitespace();
    let t = it.next()?;
    let (sec, frac) = t.split_once('.').unwrap_or((t, "0"));
    let frac = format!("{frac:0<9}");
    let t_ns = sec.parse::<u64>().ok()? * 1_000_000_000 + frac.get(..9)?.parse::<u64>().ok()?;
    let v: Vec<f64> = it.map(|x| x.parse().ok()).collect::<Option<_>>()?;
    if v.len() != 7 {
        return None;
    }
    let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(v[6], v[3], v[4], v[5]));
    Some((t_ns, Isometry3::from_parts(nalgebra::Translation3::new(v[0], v[1], v[2]), q)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip() {
        let p =
            Isometry3::new(nalgebra::Vector3::new(1.5, -2.25, 3.0), nalgebra::Vector3::new(0.1, -0.2, 0.3));
        let l = line(1_714_565_400_000_000_123, &p);
        assert!(l.starts_with("1714565400.000000123 1.500000000 -2.250000000 3.000000000 "), "{l}");
        let (t, q) = parse_line(&l).unwrap();
        assert_eq!(t, 1_714_565_400_000_000_123);
        assert!((q.translation.vector - p.translation.vector).norm() < 1e-9);
        assert!(q.rotation.angle_to(&p.rotation) < 1e-11);
        assert!(parse_line("# c").is_none() && parse_line("1 2 3").is_none());
    }
}
