//! DVR throughput: rays per second of the detached march with a 4×64 Mlp, and the cost
//! of the implicit step (forward only, and forward + backward) relative to one forward
//! pass of the field at the same points.
//!
//! `cargo bench --bench dvr` (results in docs/benchmarks.md, "DVR").

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use glam::DVec3;
use neural_fields::camera::{ray_sphere, Camera, Convention, Intrinsics, Rays};
use neural_fields::dvr::{implicit_surface, march, ImplicitConfig, MarchConfig};
use neural_fields::field::ImplicitSurface;
use neural_fields::nn::{build_seeded, mlp, Activation, Mlp, MlpConfig};
use std::time::Duration;

fn setup(side: usize) -> (VarMap, Mlp, Rays, neural_fields::camera::Intersection) {
    let dev = Device::Cpu;
    let varmap = VarMap::new();
    // ReLU with IDR's geometric initialisation (an approximate sphere of radius 0.5).
    let cfg = MlpConfig {
        hidden: 64,
        depth: 4,
        activation: Activation::Relu,
        ..MlpConfig::sdf(0.5)
    };
    let net = build_seeded(&varmap, DType::F32, &dev, 0, |vb| mlp(&cfg, vb)).unwrap();
    let k = Intrinsics::from_fov_y(side, side, 0.6).unwrap();
    let cam = Camera::look_at(
        k,
        DVec3::new(0.0, 0.0, 2.5),
        DVec3::ZERO,
        DVec3::Y,
        Convention::OpenGl,
    )
    .unwrap();
    let rays = cam.rays(&dev, DType::F32).unwrap();
    let bounds = ray_sphere(&rays, [0.0; 3], 1.0).unwrap();
    (varmap, net, rays, bounds)
}

fn bench(c: &mut Criterion) {
    let (_vm, net, rays, bounds) = setup(64); // 4096 rays
    let mut g = c.benchmark_group("dvr_march_4x64_mlp");
    g.measurement_time(Duration::from_secs(4)).sample_size(10);
    g.throughput(Throughput::Elements(rays.len() as u64));
    for steps in [16usize, 64, 128] {
        let cfg = MarchConfig {
            steps,
            secant_steps: 8,
            ..MarchConfig::default()
        };
        g.bench_with_input(BenchmarkId::new("steps+8_secant", steps), &cfg, |b, cfg| {
            b.iter(|| march(&net, &rays, &bounds, cfg).unwrap())
        });
    }
    g.finish();

    let cfg = MarchConfig {
        steps: 64,
        secant_steps: 8,
        ..MarchConfig::default()
    };
    let hits = march(&net, &rays, &bounds, &cfg).unwrap();
    let surface: Vec<u32> = (0u32..)
        .zip(&hits.status)
        .filter(|(_, s)| s.has_surface())
        .map(|(i, _)| i)
        .collect();
    let idx = Tensor::from_vec(surface.clone(), surface.len(), &Device::Cpu).unwrap();
    let points = hits.points.index_select(&idx, 0).unwrap();
    let mut g = c.benchmark_group("dvr_implicit_vs_forward");
    g.measurement_time(Duration::from_secs(3)).sample_size(20);
    g.throughput(Throughput::Elements(idx.dim(0).unwrap() as u64));
    g.bench_function("forward_value", |b| b.iter(|| net.value(&points).unwrap()));
    g.bench_function("value_and_grad", |b| {
        b.iter(|| net.value_and_grad(&points).unwrap())
    });
    let ic = ImplicitConfig::default();
    g.bench_function("implicit_surface", |b| {
        b.iter(|| implicit_surface(&net, &rays, &hits, &ic).unwrap())
    });
    g.bench_function("implicit_surface+backward", |b| {
        b.iter(|| {
            let s = implicit_surface(&net, &rays, &hits, &ic).unwrap();
            s.depth.sum_all().unwrap().backward().unwrap()
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
