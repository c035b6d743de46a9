//! The MLP field on 2¹⁶ points, fused CPU op against the reference path of candle ops:
//! forward, forward + backward, and `value_and_grad` followed by a backward pass through
//! the value and the normals (forward-mode tangents, fused on the CPU), for widths 32, 64
//! and 128 (4 hidden ReLU layers, frequency encoding L = 6, f32).
//!
//! ```text
//! cargo bench --bench mlp
//! ```

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use neural_fields::encoding::{FrequencyEncoding, PointEncoding};
use neural_fields::field::{Field, ImplicitSurface};
use neural_fields::nn::{mlp, MlpConfig};
use neural_fields::rng::SplitMix64;

const N: usize = 1 << 16;

fn bench(c: &mut Criterion) {
    let dev = Device::Cpu;
    let points = SplitMix64::new(1)
        .uniform_tensor(&[N, 3], -1.0, 1.0, DType::F32, &dev)
        .expect("points");
    let mut g = c.benchmark_group("mlp_2^16_points");
    g.sample_size(10);
    g.throughput(Throughput::Elements(N as u64));
    for width in [32, 64, 128] {
        for reference in [false, true] {
            let varmap = VarMap::new();
            let vb = VarBuilder::from_varmap(&varmap, DType::F32, &dev);
            let config = MlpConfig {
                hidden: width,
                encoding: PointEncoding::Frequency(FrequencyEncoding::new(3, 6).expect("L")),
                force_reference: reference,
                ..MlpConfig::default()
            };
            let net = mlp(&config, vb).expect("mlp");
            let path = if reference { "reference" } else { "fused" };
            g.bench_function(format!("forward/w{width}/{path}"), |b| {
                b.iter(|| net.forward(&points).expect("forward"))
            });
            g.bench_function(format!("forward_backward/w{width}/{path}"), |b| {
                b.iter(|| {
                    let y = net.forward(&points).expect("forward");
                    y.sum_all().and_then(|l| l.backward()).expect("backward")
                })
            });
            if !reference {
                g.bench_function(format!("value_and_grad/w{width}"), |b| {
                    b.iter(|| {
                        let (f, n) = net.value_and_grad(&points).expect("value_and_grad");
                        let l: Tensor = (f.sum_all().expect("sum")
                            + n.sqr().expect("sq").sum_all().expect("sum"))
                        .expect("add");
                        l.backward().expect("backward")
                    })
                });
            }
        }
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
