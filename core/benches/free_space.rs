//! Free-space image speed on one 32 x 1800 (VLP-32C) street scan (ground, walls, poles, a car;
//! 1 cm range noise, 2 % of the returns missing), single-threaded: the marks of every return
//! (`mark_returns`, each scan's whole point cloud), the fill (here with every return too) and
//! the verdict of every return against the filled image (the moving-point test's per-point
//! work).
//!
//! `cargo bench -p loglio-core --bench free_space`

use std::hint::black_box;
use std::time::Duration;

use criterion::{Criterion, criterion_group, criterion_main};
use loglio_core::free_space::{FreeSpaceConfig, FreeSpaceImage, Verdict};
use loglio_core::scan::ScanPoint;

#[path = "../../tests/synth.rs"]
mod synth;

fn bench(c: &mut Criterion) {
    let layout = synth::vlp32c_layout();
    let mut drop = synth::Rng::new(7 ^ 0xd0);
    let keep: Vec<bool> = (0..layout.pixels()).map(|_| drop.uniform() > 0.02).collect();
    let cols = layout.cols();
    let points: Vec<ScanPoint> =
        synth::render(&layout, &synth::street_scene(), 0.01, &mut synth::Rng::new(7), |r, c| {
            keep[r * cols + c]
        })
        .points;
    let mut img: Box<FreeSpaceImage<{ 32 * 1800 }>> = Box::new(FreeSpaceImage::new());
    assert!(img.set_layout(&layout, 360));
    let cfg = FreeSpaceConfig::DEFAULT;
    // Nearer by 1 m: some are seen through.
    let probes: Vec<[f32; 3]> = points.iter().map(|p| p.xyz.map(|v| v * 0.95)).collect();
    println!("free_space: {} points", points.len());

    let mut g = c.benchmark_group("free_space/32x1800");
    g.sample_size(40).measurement_time(Duration::from_secs(4)).warm_up_time(Duration::from_secs(1));
    g.bench_function("mark_returns", |b| b.iter(|| img.mark_returns(black_box(&points))));
    g.bench_function("fill", |b| b.iter(|| img.fill(black_box(&points))));
    img.fill(&points);
    g.bench_function("verdicts", |b| {
        b.iter(|| {
            let mut through = 0u32;
            for p in black_box(&probes) {
                through += u32::from(img.verdict(*p, &cfg) == Verdict::SeenThrough);
            }
            through
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
