//! The `loglio` command.

use clap::Parser;

/// LiDAR-inertial odometry for spinning LiDARs (LOG-LIO).
#[derive(Debug, Parser)]
#[command(name = "loglio", version, about)]
struct Cli {}

fn main() -> anyhow::Result<()> {
    let _cli = Cli::parse();
    Ok(())
}
