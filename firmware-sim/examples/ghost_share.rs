//! The share of a map's points that lie where the traffic scenario's actors drove (their swept
//! volumes over the whole run): points left in the map by moving objects ("ghost trails").
//!
//! ```text
//! loglio sim --scenario traffic --seed 1 --out out/traffic
//! cargo run --release -p loglio-firmware-sim --example ghost_share -- out/traffic 1
//! ```
//!
//! The map (`map.ply`, binary float properties, x y z first) is in the odometry's world frame; it
//! is put in the simulator's world with the first poses of `trajectory.tum` and
//! `groundtruth.tum` (the odometry drifts millimetres, the boxes are metres). Points less than
//! 0.3 m above the ground are not counted (boxes stand on the ground's height at their centre, so
//! the road under a path would be "inside" on slopes).

use std::collections::HashMap;
use std::path::Path;

use anyhow::{Context, bail};
use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::scenario::{Scenario, ScenarioKind};
use loglio_firmware_sim::tum;
use nalgebra::{Isometry3, Point3};

/// An actor's path segment: actor index, start and end time (seconds).
type Segment = (usize, f64, f64);

fn first_pose(path: &Path) -> anyhow::Result<Isometry3<f64>> {
    let text = std::fs::read_to_string(path).with_context(|| path.display().to_string())?;
    text.lines()
        .find_map(|l| tum::parse_line(l).map(|(_, p)| p))
        .with_context(|| format!("no pose in {}", path.display()))
}

fn read_ply(path: &Path) -> anyhow::Result<Vec<[f32; 3]>> {
    let bytes = std::fs::read(path).with_context(|| path.display().to_string())?;
    let end = bytes.windows(11).position(|w| w == b"end_header\n").context("no PLY header")? + 11;
    let header = std::str::from_utf8(&bytes[..end])?;
    if !header.contains("format binary_little_endian") {
        bail!("only binary little-endian PLY");
    }
    let mut n = 0usize;
    let mut props = 0usize;
    for l in header.lines() {
        if let Some(v) = l.strip_prefix("element vertex ") {
            n = v.trim().parse()?;
        } else if l.starts_with("property float ") {
            props += 1;
        } else if l.starts_with("property ") {
            bail!("only float properties: {l}");
        }
    }
    let stride = props * 4;
    let body = &bytes[end..];
    if props < 3 || body.len() < n * stride {
        bail!("short PLY body");
    }
    let f = |o: usize| f32::from_le_bytes([body[o], body[o + 1], body[o + 2], body[o + 3]]);
    Ok((0..n).map(|i| [f(i * stride), f(i * stride + 4), f(i * stride + 8)]).collect())
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let dir = Path::new(args.get(1).context("usage: ghost_share DIR [SEED]")?);
    let seed: u64 = args.get(2).map_or(Ok(1), |s| s.parse())?;
    let sc = Scenario::new(ScenarioKind::Traffic, SensorModel::Vlp32c, seed);
    let t_w_est =
        first_pose(&dir.join("groundtruth.tum"))? * first_pose(&dir.join("trajectory.tum"))?.inverse();
    let pts = read_ply(&dir.join("map.ply"))?;
    // A 2 m grid of the segments' swept bounds, so each point tests only the segments near it.
    let cell = 2.0;
    let key = |x: f64, y: f64| ((x / cell).floor() as i64, (y / cell).floor() as i64);
    let mut grid: HashMap<(i64, i64), Vec<Segment>> = HashMap::new();
    for (i, a) in sc.actors().list().iter().enumerate() {
        let r = {
            let s = a.kind.size();
            0.5 * libm::hypot(s[0], s[1])
        };
        for w in a.waypoints().windows(2) {
            let (lo, hi) = (
                [w[0].p[0].min(w[1].p[0]) - r, w[0].p[1].min(w[1].p[1]) - r],
                [w[0].p[0].max(w[1].p[0]) + r, w[0].p[1].max(w[1].p[1]) + r],
            );
            let (k0, k1) = (key(lo[0], lo[1]), key(hi[0], hi[1]));
            for gx in k0.0..=k1.0 {
                for gy in k0.1..=k1.1 {
                    grid.entry((gx, gy)).or_default().push((i, w[0].t, w[1].t));
                }
            }
        }
    }
    let (mut above, mut inside, mut standing) = (0usize, 0usize, 0usize);
    // Where the actors are at the end of the run (within 0.3 s of it), their points are the
    // objects as they stand, not trails.
    let end = sc.end_ns();
    let mut per_kind: HashMap<&str, usize> = HashMap::new();
    for p in &pts {
        let q = t_w_est * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        if q.z < sc.world().ground_height(q.x, q.y) + 0.3 {
            continue;
        }
        above += 1;
        let Some(list) = grid.get(&key(q.x, q.y)) else { continue };
        if let Some(&(i, _, _)) =
            list.iter().find(|(i, t0, t1)| sc.actors().list()[*i].swept_contains([q.x, q.y, q.z], *t0, *t1))
        {
            inside += 1;
            let p = [q.x, q.y, q.z];
            if (0..=3).any(|k| sc.inside_actor(p, end - k * 100_000_000).is_some()) {
                standing += 1;
            }
            *per_kind.entry(sc.actors().list()[i].kind.name()).or_default() += 1;
        }
    }
    println!(
        "{}: {} map points, {above} more than 0.3 m above the ground, {inside} of them in the actors' swept volumes ({:.3} %; {standing} of these where the actors stand in the last 0.3 s); by kind {per_kind:?}",
        dir.display(),
        pts.len(),
        100.0 * inside as f64 / above.max(1) as f64
    );
    Ok(())
}
