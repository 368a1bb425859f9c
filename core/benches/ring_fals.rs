//! Ring FALS speed: one 32 x 1800 (VLP-32C) and one 16 x 1024 (OS1-16-like) scan of a street
//! (ground, walls, poles, a car; 1 cm range noise, 2 % of the returns missing), single-threaded.
//! Each stage is timed on its own (`project`, `solve`, `smooth`, `write_points`), then the whole
//! `estimate`, and in the same run the classic baseline: kNN-PCA normals (k = 10, kiddo k-d
//! tree, build included) on the same points.
//!
//! `cargo bench -p loglio-core --bench ring_fals`

use std::hint::black_box;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group, criterion_main};
use loglio_core::range_image::RangeImageLayout;
use loglio_core::ring_fals::{PointNormal, RingFals, RingFals32x1800, RingFalsConfig, RingTable};
use loglio_core::scan::ScanPoint;

#[path = "../../tests/synth.rs"]
mod synth;

#[path = "../../host/src/machine.rs"]
mod machine;

#[path = "../../host/src/knn_pca.rs"]
#[allow(dead_code)]
mod knn_pca;

static FALS: Mutex<RingFals32x1800> = Mutex::new(RingFals::new());

fn scan(layout: &RangeImageLayout, seed: u64) -> Vec<ScanPoint> {
    let mut drop = synth::Rng::new(seed ^ 0xd0);
    let keep: Vec<bool> = (0..layout.pixels()).map(|_| drop.uniform() > 0.02).collect();
    let cols = layout.cols();
    synth::render(layout, &synth::street_scene(), 0.01, &mut synth::Rng::new(seed), |r, c| keep[r * cols + c])
        .points
}

fn bench_layout(c: &mut Criterion, name: &str, layout: &RangeImageLayout) {
    let points = scan(layout, 7);
    let mut table = RingTable::new();
    table.build(layout, &RingFalsConfig::DEFAULT).unwrap();
    let mut out = vec![PointNormal::INVALID; points.len()];
    let mut fals = FALS.lock().unwrap();
    let stats = fals.estimate(&table, &points, &mut out).unwrap();
    println!("{name}: {} points, {stats:?}", points.len());

    let mut g = c.benchmark_group(format!("ring_fals/{name}"));
    g.sample_size(40).measurement_time(Duration::from_secs(4)).warm_up_time(Duration::from_secs(1));

    // Every stage runs in its real state (after the previous stages); only its own time counts.
    for stage in ["project", "solve", "smooth", "write_points"] {
        g.bench_function(stage, |b| {
            b.iter_custom(|iters| {
                let mut total = Duration::ZERO;
                for _ in 0..iters {
                    let t0 = Instant::now();
                    fals.project(&table, black_box(&points)).unwrap();
                    let t1 = Instant::now();
                    fals.solve(&table);
                    let t2 = Instant::now();
                    fals.smooth(&table);
                    let t3 = Instant::now();
                    fals.write_points(&table, &points, &mut out);
                    let t4 = Instant::now();
                    total += match stage {
                        "project" => t1 - t0,
                        "solve" => t2 - t1,
                        "smooth" => t3 - t2,
                        _ => t4 - t3,
                    };
                }
                total
            })
        });
    }
    g.bench_function("estimate", |b| {
        b.iter(|| fals.estimate(&table, black_box(&points), &mut out).unwrap());
    });
    let xyz: Vec<[f32; 3]> = points.iter().map(|p| p.xyz).collect();
    g.sample_size(10).measurement_time(Duration::from_secs(8));
    g.bench_function("knn_pca_k10_baseline", |b| {
        b.iter(|| knn_pca::knn_pca_normals(black_box(&xyz), 10).unwrap());
    });
    g.finish();
}

fn benches(c: &mut Criterion) {
    println!("{}", machine::describe());
    bench_layout(c, "32x1800", &synth::vlp32c_layout());
    bench_layout(c, "16x1024", &synth::os1_16_layout());
}

criterion_group!(ring_fals, benches);
criterion_main!(ring_fals);
