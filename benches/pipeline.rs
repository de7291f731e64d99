//! Criterion benchmarks of the pipeline stages on crate-rendered data (and DiLiGenT cat when
//! `../shared/data` is present), and of the streamed path against the in-memory one. Run: `cargo bench --bench pipeline`.
//!
//! Speed targets live here and in `photostereo bench`, not in timed tests.

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use photostereo::capture::lights::Lights;
use photostereo::eval::demo::synthesize;
use photostereo::integrate::{IntegrationOptions, Integrator, integrate_normals};
use photostereo::progress::Silent;
use photostereo::ps::solve::{Method, SolveOptions, solve};
use photostereo::synth::render::RenderOptions;
use photostereo::synth::scene::{Albedo, Scene};
use std::hint::black_box;

/// Per-pixel solve on a 512×512 sphere under 24 lights, per method (throughput in samples).
fn bench_solve(c: &mut Criterion) {
    let scene = Scene::sphere(512, 240.0, Albedo::Constant(0.6));
    let lights = Lights::fibonacci(24, 25.0).unwrap();
    let opts = RenderOptions {
        noise_sigma: 0.005,
        cast_shadows: false,
        ..RenderOptions::default()
    };
    let synth = synthesize(scene, lights, &opts).unwrap();
    let cap = &synth.capture;
    let mut g = c.benchmark_group("solve_512x512_24_lights");
    g.throughput(Throughput::Elements(
        (cap.mask.count() * cap.lights.len()) as u64,
    ));
    for method in [
        Method::LeastSquares,
        Method::Threshold,
        Method::ShadowWeighted,
        Method::Auto,
    ] {
        let o = SolveOptions {
            method,
            ..SolveOptions::default()
        };
        g.bench_function(method.name(), |b| {
            b.iter(|| black_box(solve(&cap.stack, 0, &cap.lights, &cap.mask, &o, &Silent).unwrap()))
        });
    }
    g.finish();
}

/// Integration of a sphere's normals at several sizes, per integrator (the slow bilateral
/// method only up to 512²).
fn bench_integrate(c: &mut Criterion) {
    let mut g = c.benchmark_group("integrate");
    g.sample_size(10);
    for size in [256usize, 512, 1024] {
        let hf = Scene::sphere(size, 0.45 * size as f64, Albedo::Constant(0.5)).height_field();
        g.throughput(Throughput::Elements((size * size) as u64));
        for integrator in Integrator::ALL {
            if integrator == Integrator::Bilateral && size > 512 {
                continue;
            }
            let options = IntegrationOptions {
                method: integrator,
                ..IntegrationOptions::default()
            };
            g.bench_with_input(BenchmarkId::new(integrator.name(), size), &size, |b, _| {
                b.iter(|| {
                    black_box(integrate_normals(&hf.normals, &hf.mask, &options, &Silent).unwrap())
                })
            });
        }
    }
    g.finish();
}

/// Loading DiLiGenT cat (96 16-bit PNGs), when the shared data are present.
fn bench_load_diligent(c: &mut Criterion) {
    let dir =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/diligent/catPNG");
    if !dir.is_dir() {
        eprintln!("skipping load_diligent_cat: {} is absent", dir.display());
        return;
    }
    let mut g = c.benchmark_group("diligent_cat");
    g.sample_size(10);
    g.bench_function("load", |b| {
        b.iter(|| {
            black_box(
                photostereo::capture::dataset::Capture::from_diligent(
                    &dir,
                    &Default::default(),
                    &Silent,
                )
                .unwrap(),
            )
        })
    });
    g.finish();
}

/// A 512² sphere under 24 lights as 16-bit PNGs: decoded whole and solved in memory, against
/// streamed in bands of 64 rows (`photostereo::run::stream`), load included in both; then the same
/// with the outputs written (Poisson integration), in memory against band by band.
fn bench_stream(c: &mut Criterion) {
    use photostereo::capture::dataset::CaptureFiles;
    use photostereo::capture::stack::{ColorMode, LoadOptions};
    use photostereo::integrate::{IntegrationOptions, Integrator};
    use photostereo::run::pipeline::{Config, reconstruct_and_write, reconstruct_normals};
    use photostereo::run::stream::{
        StreamOptions, reconstruct_and_write_streamed, reconstruct_streamed,
    };
    use photostereo::synth::render::render;
    use photostereo::synth::write::{ImageFormat, write_synthetic};
    let dir = tempfile::tempdir().unwrap();
    let scene = Scene::sphere(512, 240.0, Albedo::Constant(0.6));
    let lights = Lights::fibonacci(24, 25.0).unwrap();
    let opts = RenderOptions {
        noise_sigma: 0.005,
        ..RenderOptions::default()
    };
    let rendering = render(&scene, &lights, &opts).unwrap();
    let written = write_synthetic(&rendering, &lights, dir.path(), ImageFormat::Png16).unwrap();
    let images: Vec<_> = written
        .into_iter()
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("img_"))
        })
        .collect();
    let files = CaptureFiles::from_files(
        &images,
        &dir.path().join("lights.json"),
        Some(&dir.path().join("mask.png")),
    )
    .unwrap();
    let load = LoadOptions {
        color: ColorMode::Grey,
        ..LoadOptions::default()
    };
    let config = Config {
        integration: None,
        ..Config::default()
    };
    let mut g = c.benchmark_group("stream_512x512_24_png");
    g.sample_size(10);
    g.bench_function("in_memory", |b| {
        b.iter(|| {
            let capture = files.load(&load, &Silent).unwrap();
            black_box(reconstruct_normals(&capture, &config, &Silent).unwrap())
        })
    });
    let stream = StreamOptions {
        max_memory: 1 << 30,
        band_rows: Some(64),
    };
    g.bench_function("streamed_64_rows", |b| {
        b.iter(|| {
            black_box(reconstruct_streamed(&files, &load, &config, &stream, &Silent).unwrap())
        })
    });
    let written = Config {
        integration: Some(IntegrationOptions {
            method: Integrator::Poisson,
            ..IntegrationOptions::default()
        }),
        ..Config::default()
    };
    let out = dir.path().join("out");
    g.bench_function("in_memory_written", |b| {
        b.iter(|| {
            let capture = files.load(&load, &Silent).unwrap();
            black_box(
                reconstruct_and_write(&capture, &written, &out, 0.0, &Silent, |_| Ok(None))
                    .unwrap(),
            )
        })
    });
    g.bench_function("streamed_64_rows_written", |b| {
        b.iter(|| {
            black_box(
                reconstruct_and_write_streamed(&files, &load, &written, &stream, &out, &Silent)
                    .unwrap(),
            )
        })
    });
    g.finish();
}

criterion_group!(
    benches,
    bench_solve,
    bench_integrate,
    bench_load_diligent,
    bench_stream
);
criterion_main!(benches);
