//! The scan's voxel downsampling on one 32 x 1800 (VLP-32C) street scan (ground, walls, poles,
//! a car; 1 cm range noise, 2 % of the returns missing) in firing order, single-threaded, with the odometry's
//! 0.4 m voxels and its grid of 32,768 voxels: the binning (`bin`: every return's voxel, the
//! voxels' centroids and the return nearest each), the normals' sums (`add_normals`) and the
//! output in Morton order (`finish`). Each stage runs in its real state (after the previous
//! ones); only its own time counts.
//!
//! `cargo bench -p loglio-core --bench downsample`

use std::sync::Mutex;
use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group, criterion_main};
use loglio_core::downsample::{DownsampleConfig, VoxelDownsampler};
use loglio_core::scan::ScanPoint;

#[path = "../../tests/synth.rs"]
mod synth;

static GRID: Mutex<VoxelDownsampler<32768>> = Mutex::new(VoxelDownsampler::new());

fn bench(c: &mut Criterion) {
    let points: Vec<ScanPoint> = synth::vlp32c_street_in_firing_order();
    let normals: Vec<[f32; 3]> = points.iter().map(|p| [p.xyz[1], -p.xyz[0], 0.3]).collect();
    let cfg = DownsampleConfig { voxel: 0.4, ..DownsampleConfig::default() };
    let mut grid = GRID.lock().unwrap();
    let mut scratch = vec![0u32; points.len()];
    let (mut out, mut nout) = (points.clone(), normals.clone());
    grid.bin_with_scratch(&cfg, &points, &mut scratch).unwrap();
    grid.add_normals(&normals, &scratch);
    let stats = grid.finish(&cfg, &mut out, Some(&mut nout));
    println!("downsample: {} points, {} voxels", points.len(), stats.kept);

    let mut g = c.benchmark_group("downsample/32x1800");
    g.sample_size(40).measurement_time(Duration::from_secs(4)).warm_up_time(Duration::from_secs(1));
    for stage in ["bin", "add_normals", "finish"] {
        g.bench_function(stage, |b| {
            b.iter_custom(|iters| {
                let mut total = Duration::ZERO;
                for _ in 0..iters {
                    out.copy_from_slice(&points);
                    let t0 = Instant::now();
                    grid.bin_with_scratch(&cfg, std::hint::black_box(&out), &mut scratch).unwrap();
                    let t1 = Instant::now();
                    grid.add_normals(&normals, &scratch);
                    let t2 = Instant::now();
                    grid.finish(&cfg, &mut out, Some(&mut nout));
                    let t3 = Instant::now();
                    total += match stage {
                        "bin" => t1 - t0,
                        "add_normals" => t2 - t1,
                        _ => t3 - t2,
                    };
                }
                total
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
