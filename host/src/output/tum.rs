//! The trajectory in TUM format: `t tx ty tz qx qy qz qw` per line, the IMU frame in the world
//! frame at each scan-end time, in full precision (stamps to the nanosecond, values with the
//! shortest text that reads back to the same f64).

use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};

/// Formats nanoseconds as seconds with exactly nine decimals (no rounding through f64).
pub fn format_stamp_ns(t_ns: u64) -> String {
    format!("{}.{:09}", t_ns / 1_000_000_000, t_ns % 1_000_000_000)
}

/// Writes a TUM trajectory pose by pose.
#[derive(Debug)]
pub struct TumWriter<W: Write = BufWriter<File>> {
    w: W,
    path: Option<PathBuf>,
    poses: u64,
}

impl TumWriter<BufWriter<File>> {
    /// Creates (truncates) the file and writes a one-line comment header.
    pub fn create(path: &Path) -> io::Result<Self> {
        let mut t = TumWriter::new(super::create(path)?)?;
        t.path = Some(path.to_path_buf());
        Ok(t)
    }
}

impl<W: Write> TumWriter<W> {
    /// Wraps a writer and writes the comment header.
    pub fn new(mut w: W) -> io::Result<Self> {
        writeln!(
            w,
            "# loglio trajectory: IMU frame in the world frame at each scan end; t[s] tx ty tz[m] qx qy qz qw"
        )?;
        Ok(TumWriter { w, path: None, poses: 0 })
    }

    /// Appends one pose: time (ns), position (m) and unit quaternion (w, x, y, z).
    pub fn write(&mut self, t_ns: u64, p: [f64; 3], q_wxyz: [f64; 4]) -> io::Result<()> {
        let [w, x, y, z] = q_wxyz;
        writeln!(self.w, "{} {} {} {} {} {} {} {}", format_stamp_ns(t_ns), p[0], p[1], p[2], x, y, z, w)
            .map_err(|e| self.err(e))?;
        self.poses += 1;
        Ok(())
    }

    /// Poses written so far.
    pub fn poses(&self) -> u64 {
        self.poses
    }

    /// Pushes everything written so far to the file.
    pub fn flush(&mut self) -> io::Result<()> {
        self.w.flush().map_err(|e| self.err(e))
    }

    /// Flushes and returns the inner writer.
    pub fn finish(mut self) -> io::Result<W> {
        self.flush()?;
        Ok(self.w)
    }

    fn err(&self, e: io::Error) -> io::Error {
        match &self.path {
            Some(p) => super::with_path(e, p),
            None => e,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::parse_tum;

    #[test]
    fn writes_full_precision_that_reads_back() {
        let mut t = TumWriter::new(Vec::new()).unwrap();
        let q = [0.5f64.sqrt(), 0.0, 0.0, 0.5f64.sqrt()];
        t.write(1_700_000_000_123_456_789, [1.0 / 3.0, -2.5e-7, 123456.789], q).unwrap();
        t.write(1_700_000_000_223_456_789, [0.1, 0.2, 0.3], [1.0, 0.0, 0.0, 0.0]).unwrap();
        assert_eq!(t.poses(), 2);
        let text = String::from_utf8(t.finish().unwrap()).unwrap();
        let line = text.lines().nth(1).unwrap();
        assert_eq!(
            line,
            "1700000000.123456789 0.3333333333333333 -0.00000025 123456.789 0 0 0.7071067811865476 0.7071067811865476"
        );
        let back = parse_tum(&text, "t").unwrap();
        assert_eq!(back.poses[0].t.x, 1.0 / 3.0);
        assert_eq!(back.stamps.unwrap()[1], "1700000000.223456789".parse::<f64>().unwrap());
        assert_eq!(format_stamp_ns(5), "0.000000005");
    }
}
