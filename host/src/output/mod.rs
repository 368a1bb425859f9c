//! What `loglio` writes: the trajectory (TUM), the map (PLY, PCD), a per-scan CSV, plots (PNG,
//! SVG) and a progress bar.
//!
//! Streaming writers ([`TumWriter`], [`ScanCsvWriter`]) buffer their output and can be flushed
//! at any time with `flush()`, so a Ctrl-C handler (wired by the odometry's driver) can flush
//! every open output before the process exits; `finish()` flushes and closes. The map and the
//! plots are written whole, from slices, at the end of a run (or on Ctrl-C).

mod map;
mod plot;
mod progress;
mod scan_csv;
mod tum;

pub use map::{MapPoint, PcdEncoding, write_pcd, write_pcd_file, write_ply, write_ply_file};
pub use plot::{PlotError, plot_error_over_time, plot_trajectory_top_view};
pub use progress::Progress;
pub use scan_csv::{SCAN_CSV_HEADER, ScanCsvWriter, ScanRecord, ScanStatus};
pub use tum::{TumWriter, format_stamp_ns};

use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

/// Creates a file for writing (and its parent directories), with the path in the error.
pub(crate) fn create(path: &Path) -> std::io::Result<BufWriter<File>> {
    if let Some(dir) = path.parent()
        && !dir.as_os_str().is_empty()
    {
        std::fs::create_dir_all(dir).map_err(|e| with_path(e, dir))?;
    }
    File::create(path).map(BufWriter::new).map_err(|e| with_path(e, path))
}

/// Adds the path to an I/O error's message.
pub(crate) fn with_path(e: std::io::Error, path: &Path) -> std::io::Error {
    std::io::Error::new(e.kind(), format!("{}: {e}", path.display()))
}
