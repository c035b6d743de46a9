//! Volume compositing: fused CPU op against the candle-op reference path, forward +
//! backward, 4096 rays × 192 samples with RGB, f32.
//!
//! Run: `cargo bench --bench volume -- --warm-up-time 1 --measurement-time 5`.

use candle_core::{CpuStorage, CustomOp3, DType, Device, Layout, Shape, Tensor, Var};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use neural_fields::volume::{composite, CompositeConfig, Intervals};
use std::hint::black_box;

const RAYS: usize = 4096;
const SAMPLES: usize = 192;

struct Inputs {
    sigmas: Var,
    colors: Var,
    /// Constant intervals `[k·δ, (k + 1)·δ]` (built once, outside the timed loop).
    intervals: Intervals,
    /// δ as a tensor, the null op's geometry input.
    deltas: Tensor,
}

fn inputs() -> Inputs {
    let dev = Device::Cpu;
    // Densities with moderate optical thickness (most rays keep some transmittance),
    // deterministic so that both paths see the same data.
    let n = RAYS * SAMPLES;
    let sig: Vec<f32> = (0..n).map(|i| ((i * 7919) % 1000) as f32 * 0.004).collect();
    let col: Vec<f32> = (0..n * 3)
        .map(|i| ((i * 104_729) % 1000) as f32 * 0.001)
        .collect();
    let delta = 4.0 / SAMPLES as f32;
    let deltas = Tensor::full(delta, (RAYS, SAMPLES), &dev).unwrap();
    let edges = |k0: f32| {
        (Tensor::arange(k0, k0 + SAMPLES as f32, &dev).unwrap() * f64::from(delta))
            .unwrap()
            .unsqueeze(0)
            .unwrap()
            .broadcast_as((RAYS, SAMPLES))
            .unwrap()
            .contiguous()
            .unwrap()
    };
    let intervals = Intervals::new(
        edges(0.0),
        edges(1.0),
        neural_fields::volume::Layout::Batched,
    )
    .unwrap();
    Inputs {
        sigmas: Var::from_tensor(&Tensor::from_vec(sig, (RAYS, SAMPLES), &dev).unwrap()).unwrap(),
        colors: Var::from_tensor(&Tensor::from_vec(col, (RAYS, SAMPLES, 3), &dev).unwrap())
            .unwrap(),
        intervals,
        deltas,
    }
}

/// One forward + backward step of `composite` on constant intervals with unit
/// directions (`rays: None`): the fused CPU kernel, or the candle-op reference path
/// with `force_reference`.
fn step(force_reference: bool, x: &Inputs) {
    let config = CompositeConfig {
        force_reference,
        ..CompositeConfig::default()
    };
    let out = composite(
        x.sigmas.as_tensor(),
        x.colors.as_tensor(),
        &x.intervals,
        None,
        &config,
    )
    .unwrap();
    let loss = ((out.color.sum_all().unwrap() + out.depth.sum_all().unwrap()).unwrap()
        + out.opacity.sum_all().unwrap())
    .unwrap();
    let grads = loss.backward().unwrap();
    black_box(grads.get(x.sigmas.as_tensor()).unwrap());
    black_box(grads.get(x.colors.as_tensor()).unwrap());
}

/// An op with the fused op's inputs, output and gradient shapes that computes nothing:
/// forward allocates the `[R, C + 2]` output, backward allocates zero gradients for
/// the densities and colours. Through the same narrow/sum/`backward()` step as the real
/// op, it measures what candle's graph walk, gradient accumulation and allocations
/// cost around any compositing kernel: the floor of the `fused` row.
struct NullComposite {
    rays: usize,
    width: usize,
}

impl CustomOp3 for NullComposite {
    fn name(&self) -> &'static str {
        "null-composite"
    }

    fn cpu_fwd(
        &self,
        _: &CpuStorage,
        _: &Layout,
        _: &CpuStorage,
        _: &Layout,
        _: &CpuStorage,
        _: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        Ok((
            CpuStorage::F32(vec![0.0; self.rays * self.width]),
            Shape::from((self.rays, self.width)),
        ))
    }

    fn bwd(
        &self,
        sig: &Tensor,
        _geo: &Tensor,
        vals: &Tensor,
        _res: &Tensor,
        _grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let zeros =
            |t: &Tensor| Tensor::from_vec(vec![0f32; t.elem_count()], t.shape(), t.device());
        Ok((Some(zeros(sig)?), None, Some(zeros(vals)?)))
    }
}

fn null_step(x: &Inputs) {
    let op = NullComposite {
        rays: RAYS,
        width: 5,
    };
    let out = x
        .sigmas
        .as_tensor()
        .apply_op3(&x.deltas, x.colors.as_tensor(), op)
        .unwrap();
    let color = out.narrow(1, 0, 3).unwrap();
    let depth = out.narrow(1, 3, 1).unwrap().squeeze(1).unwrap();
    let opacity = out.narrow(1, 4, 1).unwrap().squeeze(1).unwrap();
    let loss = ((color.sum_all().unwrap() + depth.sum_all().unwrap()).unwrap()
        + opacity.sum_all().unwrap())
    .unwrap();
    let grads = loss.backward().unwrap();
    black_box(grads.get(x.sigmas.as_tensor()).unwrap());
    black_box(grads.get(x.colors.as_tensor()).unwrap());
}

fn bench(c: &mut Criterion) {
    let x = inputs();
    let mut g = c.benchmark_group("composite_4096x192_rgb_f32_fwd_bwd");
    g.throughput(Throughput::Elements((RAYS * SAMPLES) as u64));
    g.sample_size(10);
    g.bench_function("fused", |b| b.iter(|| step(false, &x)));
    g.bench_function("reference", |b| b.iter(|| step(true, &x)));
    // What candle's backprop itself spends on the two gradients of any compositing op:
    // `GradStore::or_insert` makes zeros the size of each input, then adds the op's
    // gradient into them. A floor no op can go under through `backward()`.
    g.bench_function("candle_autograd_floor_null_op", |b| {
        b.iter(|| null_step(&x))
    });
    g.bench_function("candle_grad_accumulation_floor", |b| {
        b.iter(|| {
            for v in [&x.sigmas, &x.colors] {
                let acc = v.as_tensor().zeros_like().unwrap();
                black_box(acc.add(v.as_tensor()).unwrap());
            }
        })
    });
    g.finish();
    let _ = DType::F32;
}

criterion_group!(benches, bench);
criterion_main!(benches);
