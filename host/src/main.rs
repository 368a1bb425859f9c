//! The `loglio` command.

use clap::{Parser, Subcommand};

/// LiDAR-inertial odometry for spinning LiDARs (LOG-LIO).
#[derive(Debug, Parser)]
#[command(name = "loglio", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Ring FALS normals of a real capture (the bundled Ouster OS-1-32 frame by default): valid
    /// normals, time per scan, agreement with kNN-PCA on planar points.
    Normals(loglio_host::normals::NormalsArgs),
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Normals(args) => loglio_host::normals::run(&args),
    }
}
