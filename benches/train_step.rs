//! Seconds per training step of the models in `benches/torch/train_step.py`, the PyTorch
//! twin: the same model, batch, loss and optimiser, so that the two can be run alternately
//! on the same cores (`benches/compare_torch.sh`).
//!
//! ```text
//! cargo bench --bench train_step -- --model nerf --steps 20 [--reference] [--composed] [--phases] [--device cuda]
//! ```
//!
//! * `nerf`: 1024 rays × 64 jittered stratified samples in [2, 6], NeRF's frequency
//!   encodings (L = 10 positions, L = 4 directions, input included), a 4 × 64 ReLU trunk
//!   with a 64-wide feature, a 64-wide view-dependent colour head, trunc-exp density
//!   (shift −3), compositing, MSE, Adam (lr 1e-3): [`neural_fields::volume::Nerf::color_loss`],
//!   the whole loss as one fused op; `--composed` forms it from `Nerf::radiance`, the
//!   fused compositing op and candle's MSE, as before that op existed.
//! * `nerf_hash`: the same rays, samples, loss and optimiser with the NeRF example's
//!   `--encoding hash` model: instant-NGP's hash grid ([`HashGridConfig::default`] over
//!   `[−2, 2]³`, which holds every sample) on a 1 × 64 trunk, the same colour head;
//!   [`neural_fields::volume::Nerf::color_loss`] composes it from the hash-grid op, the
//!   networks and the compositing op.
//! * `occupancy`: 2¹⁶ points, a 4 × 64 ReLU occupancy MLP on raw coordinates, binary
//!   cross-entropy with logits, Adam (lr 1e-3).
//! * `dvr`: 2048 rays into the box `[−0.55, 0.55]³` from a sphere of radius 1.5, an SDF
//!   network (4 × 64 softplus β = 100, frequency encoding L = 4, IDR's geometric
//!   initialisation to a sphere of radius 0.35), DVR's march (64 samples, both ends, then
//!   8 secant steps; detached), the implicit surface depth `t̂` at the hits, L1 depth loss
//!   towards the depth of a sphere of radius 0.3, Adam (lr 1e-3).
//! * `hash_grid`: the encoding alone: 2¹⁸ points uniform in `[−1, 1]³` through
//!   instant-NGP's hash grid ([`HashGridConfig::default`]: 16 levels × 2 features,
//!   tables of 2¹⁵ rows, resolutions 16 to 2048), loss `mean((γ(x)·c)²)` for a fixed
//!   `c`, Adam (lr 1e-3) on the table. `--reference` runs the reference path (candle's
//!   gathers) instead of the fused op.
//! * `onet_points`, `onet_voxels`, `onet_image`: the training step of
//!   `examples/shape_prior` (the conditional occupancy network) at its batch: B = 16
//!   shapes × 1024 query points uniform in `[−0.55, 0.55]³`, labelled inside a sphere of
//!   radius 0.3 about a per-shape centre in `[−0.15, 0.15]³`; code size 128; ONet's CBN
//!   decoder ([`neural_fields::occupancy::onet_decoder`]: width 128, 5 conditional-batch-
//!   norm ResNet blocks, batch statistics over all B·1024 points, one code per shape) on
//!   the code of the shape's input: `points`, a fixed cloud `[16, 300, 3]` (uniform in
//!   `[−0.5, 0.5]³`, a feature of ones per point) through the PointNet encoder (3 × 128
//!   ReLU layers, max-pool, the 128-wide mean head; the log-variance head is computed and
//!   unused, as in the example); `voxels`, the shapes' spheres on a 32³ 0/1 grid through
//!   the 3-D CNN (3³ convolutions, 16 → 32 → 64 → 128 → 256 channels, 32³ → 2³, a
//!   2048 → 128 linear map); `image`, fixed uniform images `[16, 3, 64, 64]` through the
//!   ResNet-18-layout encoder at width 32 (batch norm with batch statistics); loss ONet's
//!   BCE with logits summed over the points and averaged over the shapes
//!   ([`neural_fields::occupancy::reconstruction_loss`]), Adam (lr 1e-3) on every
//!   variable. The inputs are built once, so the example's host-side batch assembly is
//!   not timed; the example runs with mimalloc, the bench (as for every model here) with
//!   the system allocator. These need the `occupancy` feature (a default one).
//!
//! The optimiser is the crate's [`neural_fields::nn::Adam`] (weight decay 0), whose
//! update runs as two fused passes per variable wherever the kernels run (the twin uses
//! `torch.optim.Adam` at its defaults). `--reference` runs the MLPs through candle's ops
//! instead of the fused MLP op (and the ONet decoder's conditional batch norm through
//! candle's ops instead of its fused op);
//! `--phases` reports forward, backward and optimiser medians separately. `--device cuda`
//! (built with the `cuda` feature) runs on the first GPU, waiting for the device at the
//! end of every timed phase; there `NEURAL_FIELDS_CUDA_KERNELS=0` measures the candle-op
//! fallback instead of the crate's CUDA kernels. The output is one JSON line per run, with
//! `params`, the number of trainable values (variables other than batch norms' running
//! statistics). The global allocator is the system's (glibc's malloc on Linux), as a
//! user's program has by default.

use candle_core::{DType, Device, Tensor};
use candle_nn::{Optimizer, VarMap};
use neural_fields::camera::Rays;
use neural_fields::camera::{ray_aabb, ray_sphere};
use neural_fields::dvr::{depth_loss, implicit_surface, march, ImplicitConfig, MarchConfig};
use neural_fields::encoding::{
    hash_grid, Encoding, FrequencyEncoding, HashGridConfig, PointEncoding,
};
use neural_fields::field::Field;
use neural_fields::nn::{adam, build_seeded, mlp, MlpConfig};
use neural_fields::volume::{composite, stratified, CompositeConfig, Jitter};
use neural_fields::volume::{nerf, NerfConfig};
use std::time::Instant;

struct Args {
    model: String,
    steps: usize,
    warmup: usize,
    reference: bool,
    phases: bool,
    composed: bool,
    device: String,
}

fn parse() -> Args {
    let mut a = Args {
        model: "nerf".into(),
        steps: 20,
        warmup: 3,
        reference: false,
        phases: false,
        composed: false,
        device: "cpu".into(),
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        match flag.as_str() {
            "--model" => a.model = it.next().expect("--model NAME"),
            "--steps" => a.steps = it.next().and_then(|s| s.parse().ok()).expect("--steps N"),
            "--warmup" => a.warmup = it.next().and_then(|s| s.parse().ok()).expect("--warmup N"),
            "--reference" => a.reference = true,
            "--composed" => a.composed = true,
            "--phases" => a.phases = true,
            "--device" => a.device = it.next().expect("--device cpu|cuda"),
            "--bench" => {}
            other => panic!("unknown flag {other}"),
        }
    }
    a
}

/// A deterministic pseudo-random tensor in [lo, hi), on `dev`.
fn uniform(shape: &[usize], lo: f32, hi: f32, seed: u64, dev: &Device) -> Tensor {
    let n: usize = shape.iter().product();
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let v: Vec<f32> = (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            lo + (hi - lo) * ((s >> 40) as f32 / (1u64 << 24) as f32)
        })
        .collect();
    Tensor::from_vec(v, shape, &Device::Cpu)
        .and_then(|t| t.to_device(dev))
        .expect("shape matches, device open")
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

type Step<'a> = Box<dyn FnMut(usize) -> neural_fields::Result<Tensor> + 'a>;

fn main() -> neural_fields::Result<()> {
    let args = parse();
    let dev = match args.device.as_str() {
        "cpu" => Device::Cpu,
        "cuda" => Device::new_cuda(0)?,
        other => panic!("unknown device {other}"),
    };
    let varmap = VarMap::new();
    let mut forward: Step = match args.model.as_str() {
        model @ ("nerf" | "nerf_hash") => {
            let hash = model == "nerf_hash";
            let net = build_seeded(&varmap, DType::F32, &dev, 0, |vb| {
                let config = NerfConfig {
                    force_reference: args.reference,
                    ..NerfConfig::default()
                };
                if !hash {
                    return nerf(&config, vb);
                }
                // The samples lie within radius 2 of the origin.
                let grid = HashGridConfig {
                    lo: vec![-2.0; 3],
                    hi: vec![2.0; 3],
                    force_reference: args.reference,
                    ..HashGridConfig::default()
                };
                let config = NerfConfig {
                    position_encoding: PointEncoding::HashGrid(hash_grid(&grid, vb.pp("grid"))?),
                    depth: 1,
                    skips: vec![],
                    ..config
                };
                nerf(&config, vb)
            })?;
            let rays_n = 1024;
            let target = uniform(&[rays_n, 3], 0.0, 1.0, 1, &dev);
            let aim = uniform(&[rays_n, 3], -0.5, 0.5, 2, &dev);
            let origins = uniform(&[rays_n, 3], -1.0, 1.0, 3, &dev);
            let norm = origins.sqr()?.sum_keepdim(1)?.sqrt()?;
            let origins = origins.broadcast_div(&norm)?.affine(4.0, 0.0)?;
            let dirs = (aim - &origins)?;
            let dirs = dirs.broadcast_div(&dirs.sqr()?.sum_keepdim(1)?.sqrt()?)?;
            let rays = Rays::new(origins, dirs)?;
            let near = Tensor::full(2f32, rays_n, &dev)?;
            let far = Tensor::full(6f32, rays_n, &dev)?;
            let composed = args.composed;
            Box::new(move |step| {
                let iv = stratified(&near, &far, 64, Jitter::PerSample, step as u64)?;
                if !composed {
                    return Ok(net
                        .color_loss(&rays, &iv, &target, &CompositeConfig::default())?
                        .loss);
                }
                let pos = iv.positions(&rays)?.reshape((rays_n * 64, 3))?;
                let d = rays
                    .directions()
                    .unsqueeze(1)?
                    .broadcast_as((rays_n, 64, 3))?
                    .reshape((rays_n * 64, 3))?;
                let (sigma, rgb) = net.radiance(&pos, &d)?;
                let out = composite(
                    &sigma.reshape((rays_n, 64))?,
                    &rgb.reshape((rays_n, 64, 3))?,
                    &iv,
                    Some(&rays),
                    &CompositeConfig::default(),
                )?;
                Ok((out.color - &target)?.sqr()?.mean_all()?)
            })
        }
        "occupancy" => {
            let config = MlpConfig {
                force_reference: args.reference,
                ..MlpConfig::default()
            };
            let net = build_seeded(&varmap, DType::F32, &dev, 0, |vb| mlp(&config, vb))?;
            let n = 1 << 16;
            let points = uniform(&[n, 3], -0.55, 0.55, 4, &dev);
            let labels = points.sqr()?.sum(1)?.le(0.16)?.to_dtype(DType::F32)?;
            Box::new(move |_| {
                let logits = net.forward(&points)?.squeeze(1)?;
                Ok(candle_nn::loss::binary_cross_entropy_with_logit(
                    &logits, &labels,
                )?)
            })
        }
        "dvr" => {
            let config = MlpConfig {
                encoding: PointEncoding::Frequency(FrequencyEncoding::new(3, 4)?),
                force_reference: args.reference,
                ..MlpConfig::sdf(0.35)
            };
            let net = build_seeded(&varmap, DType::F32, &dev, 0, |vb| mlp(&config, vb))?;
            let rays_n = 2048;
            let origins = uniform(&[rays_n, 3], -1.0, 1.0, 5, &dev);
            let norm = origins.sqr()?.sum_keepdim(1)?.sqrt()?;
            let origins = origins.broadcast_div(&norm)?.affine(1.5, 0.0)?;
            let aim = uniform(&[rays_n, 3], -0.15, 0.15, 6, &dev);
            let dirs = (aim - &origins)?;
            let dirs = dirs.broadcast_div(&dirs.sqr()?.sum_keepdim(1)?.sqrt()?)?;
            let rays = Rays::new(origins, dirs)?;
            let bounds = ray_aabb(&rays, [-0.55; 3], [0.55; 3])?;
            // The target: the depth of a sphere of radius 0.3 (every ray meets it).
            let truth = ray_sphere(&rays, [0.0; 3], 0.3)?.near;
            let march_config = MarchConfig {
                steps: 64,
                secant_steps: 8,
                ..MarchConfig::default()
            };
            Box::new(move |_| {
                let hits = march(&net, &rays, &bounds, &march_config)?;
                let surf = implicit_surface(&net, &rays, &hits, &ImplicitConfig::default())?;
                let target = truth.index_select(&surf.indices, 0)?;
                depth_loss(&surf.depth, &target, None)
            })
        }
        "hash_grid" => {
            let config = HashGridConfig {
                force_reference: args.reference,
                ..HashGridConfig::default()
            };
            let grid = build_seeded(&varmap, DType::F32, &dev, 0, |vb| hash_grid(&config, vb))?;
            let points = uniform(&[1 << 18, 3], -1.0, 1.0, 7, &dev);
            let c = uniform(&[grid.out_dim(), 1], -1.0, 1.0, 8, &dev);
            Box::new(move |_| {
                let y = grid.forward(&points)?;
                Ok(y.matmul(&c)?.sqr()?.mean_all()?)
            })
        }
        #[cfg(feature = "occupancy")]
        name @ ("onet_points" | "onet_voxels" | "onet_image") => {
            onet_step(name, &varmap, &dev, args.reference)?
        }
        other => panic!("unknown model {other}"),
    };
    let params: usize = varmap
        .data()
        .lock()
        .expect("variable map lock")
        .iter()
        .filter(|(name, _)| !name.contains("running_"))
        .map(|(_, v)| v.elem_count())
        .sum();
    let mut opt = adam(&varmap, 1e-3)?;
    let (mut total, mut fwd, mut bwd, mut upd) = (vec![], vec![], vec![], vec![]);
    let mut last = 0.0;
    for step in 0..args.warmup + args.steps {
        let t0 = Instant::now();
        let loss = forward(step)?;
        if args.phases {
            // Force the forward (on the CPU candle is eager; a GPU runs asynchronously).
            last = loss.to_scalar::<f32>()?;
        }
        let t1 = Instant::now();
        let grads = loss.backward()?;
        if args.phases {
            dev.synchronize()?;
        }
        let t2 = Instant::now();
        opt.step(&grads)?;
        dev.synchronize()?;
        let t3 = Instant::now();
        if !args.phases {
            last = loss.to_scalar::<f32>()?;
        }
        if step >= args.warmup {
            total.push((t3 - t0).as_secs_f64());
            fwd.push((t1 - t0).as_secs_f64());
            bwd.push((t2 - t1).as_secs_f64());
            upd.push((t3 - t2).as_secs_f64());
        }
    }
    println!(
        "{{\"impl\": \"candle-{}{}\", \"model\": \"{}\", \"steps\": {}, \"median_s\": {:.5}, \"forward_s\": {:.5}, \"backward_s\": {:.5}, \"update_s\": {:.5}, \"final_loss\": {:.6}, \"params\": {}}}",
        if args.reference {
            "reference"
        } else if args.composed {
            "composed"
        } else {
            "fused"
        },
        if args.device == "cpu" {
            String::new()
        } else if std::env::var("NEURAL_FIELDS_CUDA_KERNELS").is_ok_and(|v| v == "0") {
            format!("-{}-fallback", args.device)
        } else {
            format!("-{}", args.device)
        },
        args.model,
        args.steps,
        median(&mut total),
        median(&mut fwd),
        median(&mut bwd),
        median(&mut upd),
        last,
        params
    );
    Ok(())
}

/// The training step of `examples/shape_prior` for `model` (`onet_points`, `onet_voxels`
/// or `onet_image`; see the module docs): its encoder and decoder built as the example
/// builds them (variables `encoder.*`, `decoder.*`), with fixed synthetic shapes.
#[cfg(feature = "occupancy")]
fn onet_step(
    model: &str,
    varmap: &VarMap,
    dev: &Device,
    reference: bool,
) -> neural_fields::Result<Step<'static>> {
    use neural_fields::occupancy::{
        onet_decoder, pointnet_encoder, reconstruction_loss, resnet_encoder, voxel_encoder,
        NormMode, OnetConfig, PointNetConfig, PointNetEncoder, ResnetEncoder, ResnetEncoderConfig,
        VoxelEncoder, VoxelEncoderConfig,
    };
    /// Shapes per step, query points per shape, code size, cloud size, grid and image side.
    const B: usize = 16;
    const Q: usize = 1024;
    const CODE: usize = 128;
    const CLOUD: usize = 300;
    const GRID: usize = 32;
    const IMAGE: usize = 64;
    enum Encoder {
        Points(PointNetEncoder),
        Voxels(VoxelEncoder),
        Image(ResnetEncoder),
    }
    let (encoder, decoder) = build_seeded(varmap, DType::F32, dev, 0, |vb| {
        let evb = vb.pp("encoder");
        let encoder = match model {
            "onet_points" => Encoder::Points(pointnet_encoder(
                &PointNetConfig {
                    latent_dim: CODE,
                    ..PointNetConfig::default()
                },
                evb,
            )?),
            "onet_voxels" => Encoder::Voxels(voxel_encoder(
                &VoxelEncoderConfig {
                    c_dim: CODE,
                    force_reference: reference,
                    ..VoxelEncoderConfig::default()
                },
                evb,
            )?),
            "onet_image" => Encoder::Image(resnet_encoder(
                &ResnetEncoderConfig {
                    c_dim: CODE,
                    ..ResnetEncoderConfig::default()
                },
                evb,
            )?),
            other => panic!("unknown model {other}"),
        };
        let decoder = onet_decoder(
            &OnetConfig {
                hidden: 128,
                code_dim: CODE,
                force_reference: reference,
                ..OnetConfig::default()
            },
            vb.pp("decoder"),
        )?;
        Ok((encoder, decoder))
    })?;
    decoder.set_mode(NormMode::Train);
    // The shapes: spheres of radius 0.3 about per-shape centres; labelled query points.
    let centres = uniform(&[B, 3], -0.15, 0.15, 9, dev).unsqueeze(1)?; // [B, 1, 3]
    let inside = |p: &Tensor| -> neural_fields::Result<Tensor> {
        let d2 = p.broadcast_sub(&centres)?.sqr()?.sum(2)?;
        Ok(d2.le(0.09)?.to_dtype(DType::F32)?)
    };
    let points = uniform(&[B, Q, 3], -0.55, 0.55, 10, dev);
    let labels = inside(&points)?; // [B, Q]
    let input = match &encoder {
        Encoder::Points(_) => uniform(&[B, CLOUD, 3], -0.5, 0.5, 11, dev),
        Encoder::Voxels(_) => {
            // Cell centres over [−½, ½]³, voxel (i, j, k) at row (i·R + j)·R + k.
            let c = |i: usize| -0.5 + (i as f32 + 0.5) / GRID as f32;
            let v: Vec<f32> = (0..GRID * GRID * GRID)
                .flat_map(|o| [c(o / (GRID * GRID)), c((o / GRID) % GRID), c(o % GRID)])
                .collect();
            let cells = Tensor::from_vec(v, (1, GRID * GRID * GRID, 3), dev)?;
            inside(&cells)?.reshape((B, GRID, GRID, GRID))?
        }
        Encoder::Image(_) => uniform(&[B, 3, IMAGE, IMAGE], 0.0, 1.0, 12, dev),
    };
    Ok(Box::new(move |_| {
        // `Model::codes` and `Model::logits` of the example, in training mode.
        let codes = match &encoder {
            Encoder::Image(e) => e.forward(&input, true)?,
            Encoder::Points(e) => {
                let (b, k) = (input.dim(0)?, input.dim(1)?);
                let ones = Tensor::ones((b, k, 1), input.dtype(), input.device())?;
                e.forward(&input, &ones)?.0
            }
            Encoder::Voxels(e) => e.forward(&input)?,
        };
        let logits = decoder.logits(&points, &codes)?;
        reconstruction_loss(&logits, &labels)
    }))
}
