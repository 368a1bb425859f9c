//! The per-scan CSV: one row per scan with its times, point and association counts, filter
//! iterations, status and processing time. The odometry's driver fills a [`ScanRecord`] from the
//! core's per-scan result.

use std::fmt;
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};

use super::tum::format_stamp_ns;

/// The odometry's state after a scan.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ScanStatus {
    /// Waiting for the IMU initialisation (gravity, gyro bias).
    Initialising,
    /// Tracking normally.
    Ok,
    /// Tracking, with directions the scan cannot observe carried by the IMU.
    Degraded,
    /// Tracking again after a pause of the IMU or the LiDAR that the filter bridged.
    Bridged,
    /// The scan was not used; the pose comes from the IMU alone.
    ImuOnly,
    /// Lost, starting over.
    Reinitialising,
    /// The scans no longer agree with the map: the pose is not to be trusted.
    Lost,
}

impl ScanStatus {
    /// The CSV spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            ScanStatus::Initialising => "initialising",
            ScanStatus::Ok => "ok",
            ScanStatus::Degraded => "degraded",
            ScanStatus::Bridged => "bridged",
            ScanStatus::ImuOnly => "imu-only",
            ScanStatus::Reinitialising => "re-initialising",
            ScanStatus::Lost => "lost",
        }
    }
}

impl fmt::Display for ScanStatus {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// One row of the per-scan CSV (a plain host struct; `sink::files` fills it from the core's result).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScanRecord {
    /// Scan number, from 0.
    pub index: u64,
    /// Scan start, ns.
    pub start_ns: u64,
    /// Scan end (the pose's time), ns.
    pub end_ns: u64,
    /// Points received.
    pub points_in: u32,
    /// Points after the range gate and downsampling.
    pub points_used: u32,
    /// Points associated with a large (multi-voxel) surfel.
    pub large_surfel: u32,
    /// Points associated with a small (single-voxel) surfel.
    pub small_surfel: u32,
    /// Points associated by point-to-plane.
    pub point_to_plane: u32,
    /// Points with no accepted association.
    pub unmatched: u32,
    /// Iterated-update passes.
    pub iterations: u32,
    /// State after the scan.
    pub status: ScanStatus,
    /// Processing time of the scan, milliseconds.
    pub process_ms: f64,
    /// Voxels in the map after the scan.
    pub map_voxels: u64,
}

/// The CSV header line.
pub const SCAN_CSV_HEADER: &str = "index,start_s,end_s,points_in,points_used,large_surfel,small_surfel,point_to_plane,unmatched,iterations,status,process_ms,map_voxels";

/// Writes the per-scan CSV row by row.
#[derive(Debug)]
pub struct ScanCsvWriter<W: Write = BufWriter<File>> {
    w: W,
    path: Option<PathBuf>,
}

impl ScanCsvWriter<BufWriter<File>> {
    /// Creates (truncates) the file and writes the header.
    pub fn create(path: &Path) -> io::Result<Self> {
        let mut c = ScanCsvWriter::new(super::create(path)?)?;
        c.path = Some(path.to_path_buf());
        Ok(c)
    }
}

impl<W: Write> ScanCsvWriter<W> {
    /// Wraps a writer and writes the header.
    pub fn new(mut w: W) -> io::Result<Self> {
        writeln!(w, "{SCAN_CSV_HEADER}")?;
        Ok(ScanCsvWriter { w, path: None })
    }

    /// Appends one row.
    pub fn write(&mut self, r: &ScanRecord) -> io::Result<()> {
        writeln!(
            self.w,
            "{},{},{},{},{},{},{},{},{},{},{},{:.3},{}",
            r.index,
            format_stamp_ns(r.start_ns),
            format_stamp_ns(r.end_ns),
            r.points_in,
            r.points_used,
            r.large_surfel,
            r.small_surfel,
            r.point_to_plane,
            r.unmatched,
            r.iterations,
            r.status,
            r.process_ms,
            r.map_voxels
        )
        .map_err(|e| self.err(e))
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

    #[test]
    fn rows_follow_the_header() {
        let mut c = ScanCsvWriter::new(Vec::new()).unwrap();
        let r = ScanRecord {
            index: 7,
            start_ns: 1_000_000_000,
            end_ns: 1_100_000_001,
            points_in: 28800,
            points_used: 4100,
            large_surfel: 2500,
            small_surfel: 900,
            point_to_plane: 400,
            unmatched: 300,
            iterations: 3,
            status: ScanStatus::ImuOnly,
            process_ms: 4.25,
            map_voxels: 123456,
        };
        c.write(&r).unwrap();
        let text = String::from_utf8(c.finish().unwrap()).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], SCAN_CSV_HEADER);
        assert_eq!(lines[1], "7,1.000000000,1.100000001,28800,4100,2500,900,400,300,3,imu-only,4.250,123456");
        assert_eq!(lines[0].split(',').count(), lines[1].split(',').count());
    }
}
