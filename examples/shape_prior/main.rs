//! Learn 3-D reconstruction across a collection of shapes: a conditional occupancy
//! network (an encoder of the input → a code `c` → ONet's CBN decoder) trained on the
//! crate's procedural shape collection, scored on shapes it never saw against the mean
//! shape and retrieval baselines.
//!
//! ```text
//! cargo run --release --example shape_prior -- --input image|points|voxels|latent \
//!     [--data DIR] [--shapes-per-category N] [--minutes M | --steps N] [--out DIR] [--seed S]
//! ```
//!
//! **Data.** `--data DIR` reads a collection written by `data::write_shape_collection`
//! (views are rendered into it when `--input image` finds none); without it the example
//! generates one into `OUT/collection` from `--seed` (five categories × `--shapes-per-
//! category`, default 500: 2 075 train, 100 val and 325 test shapes; 4 096 uniform and 2 ×
//! 2 048 near-surface labelled points, 2 048 surface points with normals and a 32³ grid
//! per shape) and reuses it when it is there.
//!
//! **Inputs** (ONet's three experiments): `image`, one of `--views` renderings of the shape
//! (64 × 64, the crate's ray march of the analytic SDF, grey Lambertian shading from a
//! random light, random viewpoint; view 0 at test time) through the ResNet-18-layout
//! encoder; `points`, 300 surface points with Gaussian noise σ = 0.05 through the
//! PointNet encoder; `voxels`, the 32³ occupancy grid through the 3-D CNN encoder.
//! `latent` is ONet's variational (generative) model: no observation; the encoder
//! `q(z | points, labels)` (PointNet with mean and log-variance heads) reads 1 024 of the
//! shape's own labelled uniform points, training draws `z` from it (reparameterised) and
//! adds `KL(q ‖ N(0, I))` per shape to the loss, test shapes are decoded from the
//! posterior mean, and new shapes from codes drawn from `N(0, I)`.
//!
//! **Model and training.** Code size 128, ONet's decoder (5 conditional-batch-norm ResNet
//! blocks, width 128 rather than 256 for two cores). Each step takes `--batch` training
//! shapes (default 16) with 1 024 of their uniform points each (ONet samples uniform points
//! only), the stable BCE summed over the points, Adam 1e-3 (2e-4 for the last 30 % of the
//! budget). The run stops with an error naming the step at a NaN or infinity.
//!
//! **Evaluation** (test split): IoU on each shape's uniform points at ONet's threshold
//! (occupancy probability 0.2), and from the MISE mesh (32³ → 64³) 4 096 surface samples
//! against the shape's stored surface points: Chamfer-L1 (unscaled), normal consistency
//! and F-score at 0.01; means over the test shapes. **Baselines**, scored the same way:
//! `mean_shape`, the training voxels' mean occupancy ≥ ½ (one shape for every input);
//! `retrieval`, the training shape whose code from the trained encoder is nearest (L2);
//! `retrieval_fixed_feature`, the training shape nearest by a feature nobody trained (the
//! image at 16 × 16 grey, the voxel grid itself, the input cloud's 16³ occupancy, or for
//! `latent` the 16³ occupancy of its inside-labelled points).
//!
//! **Output** (`--out`, default `target/shape_prior`): `metrics.json` (`iou`,
//! `chamfer_l1`, `normal_consistency`, `fscore`, and `baselines.{mean_shape, retrieval,
//! retrieval_fixed_feature}` with the same keys; `input`, shape counts, steps, seconds),
//! `curve.csv` (IoU on 32 test shapes against training seconds, every 60 s of training)
//! and `test_NN.png`: input | reconstruction | truth for four test shapes; for `latent`
//! also `kl` (the test posteriors' mean KL) in metrics.json and `samples.png` (eight
//! shapes decoded from the prior). Uses mimalloc
//! (see `examples/tiny_nerf.rs`).

#[cfg(test)]
mod tests;
mod views;

use candle_core::{DType, Device, Tensor};
use candle_nn::{Optimizer, VarMap};
use clap::{Parser, ValueEnum};
use neural_fields::data::{
    load_shape_collection, write_png, write_shape_collection, write_shape_views, ShapeCollection,
    ShapeCollectionConfig, ShapeLoadConfig, ShapeSample, Split,
};
use neural_fields::field::{Conditioned, ImplicitSurface, Inside, SignedDistance};
use neural_fields::mesh::Mesh;
use neural_fields::nn::{adam, build_seeded, Budget, Clock, FiniteGuard};
use neural_fields::occupancy::{
    iou, kl_standard_normal, logit_threshold, marching_cubes, mise, onet_decoder, pointnet_encoder,
    reconstruction_loss, reparameterize, resnet_encoder, surface_metrics, voxel_encoder, Grid,
    MiseConfig, NormMode, OnetConfig, OnetDecoder, PointNetConfig, PointNetEncoder, ResnetEncoder,
    ResnetEncoderConfig, SurfaceMetrics, VoxelEncoder, VoxelEncoderConfig,
};
use neural_fields::rng::SplitMix64;
use neural_fields::{Error, Result};
use std::path::{Path, PathBuf};

#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Code size, query points per shape and step, cloud size and noise, image size.
const CODE: usize = 128;
const QUERIES: usize = 1024;
const CLOUD: usize = 300;
const CLOUD_NOISE: f64 = 0.05;
const IMAGE: usize = 64;
/// ONet's occupancy threshold, the F-score's distance, surface samples per mesh.
const THRESHOLD: f64 = 0.2;
const F_THRESHOLD: f64 = 0.01;
const SURFACE_SAMPLES: usize = 4096;
/// Test shapes on the training curve, and its period in training seconds.
const CURVE_SHAPES: usize = 32;
const CURVE_EVERY: f64 = 60.0;

/// Learn 3-D reconstruction across the procedural shape collection and score it on
/// unseen shapes against the mean-shape and retrieval baselines.
#[derive(Parser, Clone, Debug)]
struct Args {
    /// What the network sees of a shape.
    #[arg(long, value_enum, default_value_t = Input::Points)]
    input: Input,
    /// An existing collection (else one is generated into OUT/collection).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Shapes per category of a generated collection.
    #[arg(long, default_value_t = 500)]
    shapes_per_category: usize,
    /// Rendered views per shape (image input), written into the collection once.
    #[arg(long, default_value_t = 2)]
    views: usize,
    /// Minutes of training, evaluation not counted (default 30 without --steps).
    #[arg(long, conflicts_with = "steps")]
    minutes: Option<f64>,
    /// Training steps instead of minutes.
    #[arg(long)]
    steps: Option<usize>,
    /// Training shapes per step.
    #[arg(long, default_value_t = 16)]
    batch: usize,
    /// Score only the first N test shapes (all by default).
    #[arg(long)]
    test_shapes: Option<usize>,
    /// The split scored as "test": `test`, or `val` to tune settings without looking at
    /// the test shapes.
    #[arg(long, value_enum, default_value_t = EvalSplit::Test)]
    eval_split: EvalSplit,
    /// Fraction of each shape's training points drawn from its near-surface samples (the
    /// rest uniform in the cube).
    #[arg(long, default_value_t = 0.0)]
    near_fraction: f64,
    /// Output folder.
    #[arg(long, default_value = "target/shape_prior")]
    out: PathBuf,
    /// Seed of the generated collection, the initialisation and the batches.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum EvalSplit {
    Test,
    Val,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Input {
    Image,
    Points,
    Voxels,
    /// The variational ONet: no observation; the shape's own labelled points through the
    /// variational encoder `q(z | points, labels)`, KL to `N(0, I)`.
    Latent,
}

impl Input {
    fn name(self) -> &'static str {
        match self {
            Input::Image => "image",
            Input::Points => "points",
            Input::Voxels => "voxels",
            Input::Latent => "latent",
        }
    }
}

/// An error naming the `--data` collection and what it lacks.
fn bad_data(expected: &str, got: String) -> Error {
    Error::InvalidArgument {
        arg: "data",
        expected: expected.into(),
        got,
    }
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> Error + '_ {
    move |source| Error::Io {
        path: path.display().to_string(),
        source,
    }
}

/// The collection: `--data`, or the one generated (once) into `OUT/collection`; views
/// rendered into it where the image input needs them.
fn collection(args: &Args, dev: &Device) -> Result<ShapeCollection> {
    let dir = match &args.data {
        Some(d) => d.clone(),
        None => {
            let dir = args.out.join("collection");
            if !dir.join("manifest.json").exists() {
                let config = ShapeCollectionConfig {
                    seed: args.seed,
                    shapes_per_category: args.shapes_per_category,
                    uniform_points: 4096,
                    near_points: 2048,
                    surface_points: 2048,
                    val_fraction: 0.04,
                    test_fraction: 0.13,
                    ..ShapeCollectionConfig::default()
                };
                println!("generating the collection into {}", dir.display());
                write_shape_collection(&dir, &config)?;
            }
            dir
        }
    };
    let load = ShapeLoadConfig {
        views: args.input == Input::Image,
        ..ShapeLoadConfig::default()
    };
    let mut c = load_shape_collection(&dir, &load)?;
    if args.input == Input::Image && c.shapes.iter().any(|s| s.views.is_empty()) {
        println!("rendering {} views per shape", args.views);
        for s in &c.shapes {
            if !s.views.is_empty() {
                continue;
            }
            let shape = neural_fields::data::generate_shape(
                s.info.category,
                s.info.seed,
                &Device::Cpu,
                DType::F32,
            )?;
            let sdf = shape.sdf();
            let mut rng = SplitMix64::new(s.info.seed ^ 0x5eed);
            let mut v = Vec::with_capacity(args.views);
            for _ in 0..args.views {
                let cam = views::random_camera(&mut rng, IMAGE)?;
                let light = views::random_light(&mut rng, &cam);
                v.push((cam, views::shade(&sdf, &cam, light, dev)?));
            }
            write_shape_views(&dir, s.info.index, &v)?;
        }
        c = load_shape_collection(&dir, &load)?;
    }
    Ok(c)
}

/// The encoders of the four inputs.
enum Encoder {
    Image(ResnetEncoder),
    Points(PointNetEncoder),
    Voxels(VoxelEncoder),
    Latent(PointNetEncoder),
}

struct Model {
    encoder: Encoder,
    decoder: OnetDecoder,
}

/// One batch of inputs, built on the host from the stored arrays.
fn inputs(
    input: Input,
    shapes: &[&ShapeSample],
    rng: Option<&mut SplitMix64>,
    dev: &Device,
) -> Result<Tensor> {
    let b = shapes.len();
    // Training draws from `rng`; evaluation (none) from a fixed stream, with view 0.
    let training = rng.is_some();
    let mut fixed = SplitMix64::new(7);
    let rng = match rng {
        Some(r) => r,
        None => &mut fixed,
    };
    match input {
        Input::Image => {
            let mut data = Vec::with_capacity(b * 3 * IMAGE * IMAGE);
            for s in shapes {
                if s.views.is_empty() {
                    return Err(bad_data(
                        "rendered views for every shape",
                        format!("none for shape {}", s.info.index),
                    ));
                }
                let k = if training {
                    rng.below(s.views.len() as u64) as usize
                } else {
                    0
                };
                let img = &s.views[k].image;
                let (w, h, c) = img.size();
                if (w, h) != (IMAGE, IMAGE) {
                    return Err(bad_data("64 × 64 views", format!("{w} × {h}")));
                }
                for ch in 0..3 {
                    for i in 0..w * h {
                        data.push(f32::from(img.data()[i * c + ch]) / 255.0);
                    }
                }
            }
            Ok(Tensor::from_vec(data, (b, 3, IMAGE, IMAGE), dev)?)
        }
        Input::Points => {
            let mut data = Vec::with_capacity(b * CLOUD * 3);
            for s in shapes {
                let n = s.surface_points.len() / 3;
                for _ in 0..CLOUD {
                    let i = rng.below(n as u64) as usize;
                    for a in 0..3 {
                        data.push(
                            s.surface_points[3 * i + a] + (CLOUD_NOISE * rng.normal()) as f32,
                        );
                    }
                }
            }
            Ok(Tensor::from_vec(data, (b, CLOUD, 3), dev)?)
        }
        Input::Voxels => {
            let r = shapes
                .first()
                .map_or(0, |s| (s.voxels.len() as f64).cbrt().round() as usize);
            let data: Vec<f32> = shapes
                .iter()
                .flat_map(|s| s.voxels.iter().map(|&v| f32::from(v)))
                .collect();
            Ok(Tensor::from_vec(data, (b, r, r, r), dev)?)
        }
        Input::Latent => {
            // `QUERIES` labelled uniform points per shape: `[B, Q, 4]` (x, y, z, label).
            let (p, y) = queries(shapes, 0.0, rng, dev)?;
            Ok(Tensor::cat(&[p, y.unsqueeze(2)?], 2)?)
        }
    }
}

impl Model {
    /// The codes `[B, CODE]` and, for `latent`, `KL(q(z | x) ‖ N(0, I))` per shape `[B]`;
    /// with `sample = Some(seed)` the latent codes are drawn from the posterior
    /// (reparameterised), else they are its mean.
    fn encode(
        &self,
        x: &Tensor,
        train: bool,
        sample: Option<u64>,
    ) -> Result<(Tensor, Option<Tensor>)> {
        Ok(match &self.encoder {
            Encoder::Image(e) => (e.forward(x, train)?, None),
            Encoder::Points(e) => {
                let ones = Tensor::ones((x.dim(0)?, x.dim(1)?, 1), x.dtype(), x.device())?;
                (e.forward(x, &ones)?.0, None)
            }
            Encoder::Voxels(e) => (e.forward(x)?, None),
            Encoder::Latent(e) => {
                let points = x.narrow(2, 0, 3)?.contiguous()?;
                let labels = x.narrow(2, 3, 1)?.squeeze(2)?.contiguous()?;
                let (mean, logvar) = e.forward(&points, &labels)?;
                let kl = kl_standard_normal(&mean, &logvar)?;
                let z = match sample {
                    Some(seed) => reparameterize(&mean, &logvar, seed)?,
                    None => mean,
                };
                (z, Some(kl))
            }
        })
    }

    /// Logits `[B, Q]` at `points: [B, Q, 3]`, one code per shape.
    fn logits(&self, codes: &Tensor, points: &Tensor) -> Result<Tensor> {
        self.decoder.logits(points, codes)
    }
}

/// `QUERIES` labelled points of each shape, a fraction `near` of them from its
/// near-surface samples and the rest uniform: `[B, Q, 3]`, `[B, Q]`.
fn queries(
    shapes: &[&ShapeSample],
    near: f64,
    rng: &mut SplitMix64,
    dev: &Device,
) -> Result<(Tensor, Tensor)> {
    let b = shapes.len();
    let (mut p, mut y) = (
        Vec::with_capacity(b * QUERIES * 3),
        Vec::with_capacity(b * QUERIES),
    );
    let n_near = (near * QUERIES as f64).round() as usize;
    for s in shapes {
        for k in 0..QUERIES {
            let (points, labels) = if k < n_near && !s.near_occupancy.is_empty() {
                (&s.near_points, &s.near_occupancy)
            } else {
                (&s.uniform_points, &s.uniform_occupancy)
            };
            let i = rng.below(labels.len() as u64) as usize;
            p.extend_from_slice(&points[3 * i..3 * i + 3]);
            y.push(f32::from(labels[i]));
        }
    }
    Ok((
        Tensor::from_vec(p, (b, QUERIES, 3), dev)?,
        Tensor::from_vec(y, (b, QUERIES), dev)?,
    ))
}

/// Scores of one reconstruction.
#[derive(Clone, Copy, Debug, Default)]
struct Score {
    iou: f64,
    chamfer: f64,
    normals: f64,
    fscore: f64,
}

impl Score {
    fn from(iou: f64, m: &SurfaceMetrics) -> Self {
        Self {
            iou,
            chamfer: m.chamfer_l1,
            normals: m.normal_consistency.unwrap_or(0.0),
            fscore: m.f_score,
        }
    }

    fn json(scores: &[Score]) -> String {
        let n = scores.len().max(1) as f64;
        let mean = |f: fn(&Score) -> f64| scores.iter().map(f).sum::<f64>() / n;
        format!(
            "{{\"iou\": {:.5}, \"chamfer_l1\": {:.6}, \"normal_consistency\": {:.5}, \"fscore\": {:.5}}}",
            mean(|s| s.iou),
            mean(|s| s.chamfer),
            mean(|s| s.normals),
            mean(|s| s.fscore)
        )
    }
}

/// The stored voxel of the cell holding point `p` (cells over `[−½, ½]³`, `z` fastest).
fn voxel_at(v: &[f32], r: usize, p: &[f32]) -> f32 {
    let c = |x: f32| ((x + 0.5) * r as f32).floor().clamp(0.0, r as f32 - 1.0) as usize;
    v[c(p[2]) + r * (c(p[1]) + r * c(p[0]))]
}

/// Stored voxels (`z` fastest) as a marching-cubes grid (`x` fastest) at the cell centres.
fn voxel_grid(v: &[f32], r: usize) -> Grid {
    let mut values = vec![0f32; r * r * r];
    for i in 0..r {
        for j in 0..r {
            for k in 0..r {
                values[i + r * (j + r * k)] = v[k + r * (j + r * i)];
            }
        }
    }
    let h = 0.5 / r as f64;
    Grid {
        values,
        dims: [r; 3],
        min: [-0.5 + h; 3],
        max: [0.5 - h; 3],
    }
}

fn points3(v: &[f32]) -> Vec<[f64; 3]> {
    v.chunks_exact(3)
        .map(|p| [f64::from(p[0]), f64::from(p[1]), f64::from(p[2])])
        .collect()
}

/// Surface metrics of `mesh` against the shape's stored surface (an empty mesh scores
/// as one point at the origin: far from every surface).
fn surface_score(mesh: &Mesh, truth: &ShapeSample, seed: u64) -> Result<SurfaceMetrics> {
    let (p, n) = if mesh.faces.is_empty() {
        (vec![[0.0; 3]], vec![[0.0, 1.0, 0.0]])
    } else {
        mesh.sample_surface(SURFACE_SAMPLES, seed)?
    };
    let gt = points3(&truth.surface_points);
    let gn = points3(&truth.surface_normals);
    surface_metrics(&p, Some(&n), &gt, Some(&gn), F_THRESHOLD)
}

fn labels(s: &ShapeSample) -> Vec<bool> {
    s.uniform_occupancy.iter().map(|&o| o != 0).collect()
}

fn mise_config(dev: &Device) -> Result<MiseConfig> {
    Ok(MiseConfig {
        level: Some(logit_threshold(THRESHOLD)?),
        ..MiseConfig::new(32, 1, dev, DType::F32)
    })
}

/// The shape's uniform points as a tensor `[N, 3]`.
fn uniform_points(s: &ShapeSample, dev: &Device) -> Result<Tensor> {
    Ok(Tensor::from_slice(
        &s.uniform_points,
        (s.uniform_occupancy.len(), 3),
        dev,
    )?)
}

/// IoU of `surface` (the decoder with one code) on the shape's uniform points, occupied
/// at probability ≥ `THRESHOLD`.
fn network_iou(surface: &dyn ImplicitSurface, s: &ShapeSample, dev: &Device) -> Result<f64> {
    let level = logit_threshold(THRESHOLD)? as f32;
    let pred: Vec<bool> = surface
        .value(&uniform_points(s, dev)?)?
        .to_vec1::<f32>()?
        .iter()
        .map(|&l| l >= level)
        .collect();
    iou(&pred, &labels(s))
}

/// The network's score on one test shape, given its code `[CODE]`.
fn network_score(model: &Model, code: &Tensor, s: &ShapeSample, dev: &Device) -> Result<Score> {
    let surface = Conditioned::new(&model.decoder, code.clone())?;
    let mesh = mise(&surface, &mise_config(dev)?)?.mesh;
    Ok(Score::from(
        network_iou(&surface, s, dev)?,
        &surface_score(&mesh, s, s.info.seed)?,
    ))
}

/// The codes of `shapes` (inference mode), in batches.
fn encode_all(
    model: &Model,
    input: Input,
    shapes: &[&ShapeSample],
    dev: &Device,
) -> Result<(Tensor, f64)> {
    let (mut out, mut kl_sum) = (Vec::new(), 0.0);
    for chunk in shapes.chunks(32) {
        let x = inputs(input, chunk, None, dev)?;
        let (codes, kl) = model.encode(&x, false, None)?;
        if let Some(kl) = kl {
            kl_sum += f64::from(kl.sum_all()?.to_scalar::<f32>()?);
        }
        out.push(codes.detach());
    }
    Ok((Tensor::cat(&out, 0)?, kl_sum))
}

/// IoU on `n` test shapes (the training curve).
fn curve_iou(model: &Model, input: Input, test: &[&ShapeSample], dev: &Device) -> Result<f64> {
    model.decoder.set_mode(NormMode::Eval);
    let shapes = &test[..test.len().min(CURVE_SHAPES)];
    let (codes, _) = encode_all(model, input, shapes, dev)?;
    let mut sum = 0.0;
    for (i, s) in shapes.iter().enumerate() {
        let surface = Conditioned::new(&model.decoder, codes.get(i)?)?;
        sum += network_iou(&surface, s, dev)?;
    }
    model.decoder.set_mode(NormMode::Train);
    Ok(sum / shapes.len().max(1) as f64)
}

/// A training shape as the prediction for a test shape: its analytic occupancy at the
/// test shape's points and its stored surface.
fn retrieved_score(found: &ShapeSample, s: &ShapeSample, dev: &Device) -> Result<Score> {
    let shape =
        neural_fields::data::generate_shape(found.info.category, found.info.seed, dev, DType::F32)?;
    let (d, _) = shape.distance_and_grad(&uniform_points(s, dev)?)?;
    let pred: Vec<bool> = d.to_vec1::<f32>()?.iter().map(|&v| v < 0.0).collect();
    let gt = points3(&found.surface_points);
    let gn = points3(&found.surface_normals);
    let m = surface_metrics(
        &gt,
        Some(&gn),
        &points3(&s.surface_points),
        Some(&points3(&s.surface_normals)),
        F_THRESHOLD,
    )?;
    Ok(Score::from(iou(&pred, &labels(s))?, &m))
}

/// For each row of `queries: [T, D]`, the index of the nearest row of `bank: [N, D]`
/// (L2), from `‖b‖² − 2 q·b` by one matrix product (the `‖q‖²` term does not change the
/// argmin).
fn nearest_rows(bank: &Tensor, queries: &Tensor) -> Result<Vec<usize>> {
    let b2 = bank.sqr()?.sum(1)?.unsqueeze(0)?;
    let d = b2.broadcast_sub(&(queries.matmul(&bank.t()?)? * 2.0)?)?;
    Ok(d.argmin(1)?
        .to_vec1::<u32>()?
        .into_iter()
        .map(|i| i as usize)
        .collect())
}

/// The fixed features `[N, D]` of `shapes` (see [`fixed_feature`]).
fn fixed_features(input: Input, shapes: &[&ShapeSample], dev: &Device) -> Result<Tensor> {
    let rows = shapes
        .iter()
        .map(|s| fixed_feature(input, s, dev))
        .collect::<Result<Vec<_>>>()?;
    Ok(Tensor::stack(&rows, 0)?)
}

/// The fixed feature of a shape's input (no training): the image at 16 × 16 grey, the
/// voxel grid, or the noisy cloud's 16³ occupancy.
fn fixed_feature(input: Input, s: &ShapeSample, dev: &Device) -> Result<Tensor> {
    let x = inputs(input, &[s], None, dev)?;
    Ok(match input {
        Input::Image => x
            .mean_keepdim(1)?
            .reshape((1, 16, IMAGE / 16, 16, IMAGE / 16))?
            .mean(4)?
            .mean(2)?
            .flatten_all()?,
        Input::Voxels => x.flatten_all()?,
        Input::Points | Input::Latent => {
            // Cells holding an input point (`latent`: an inside-labelled one).
            let width = x.dim(2)?;
            let mut h = vec![0f32; 16 * 16 * 16];
            for p in x.flatten_all()?.to_vec1::<f32>()?.chunks_exact(width) {
                if width == 4 && p[3] < 0.5 {
                    continue;
                }
                let c = |v: f32| (((v + 0.5) * 16.0).floor().clamp(0.0, 15.0)) as usize;
                h[c(p[0]) + 16 * (c(p[1]) + 16 * c(p[2]))] = 1.0;
            }
            Tensor::from_vec(h, 4096, dev)?
        }
    })
}

fn main() -> Result<()> {
    run(&Args::parse())
}

fn run(args: &Args) -> Result<()> {
    if !(0.0..=1.0).contains(&args.near_fraction) {
        return Err(Error::InvalidArgument {
            arg: "near-fraction",
            expected: "a fraction in [0, 1]".into(),
            got: args.near_fraction.to_string(),
        });
    }
    std::fs::create_dir_all(&args.out).map_err(io_err(&args.out))?;
    let dev = Device::Cpu;
    let data = collection(args, &dev)?;
    let split = |sp: Split| -> Vec<&ShapeSample> {
        data.shapes.iter().filter(|s| s.info.split == sp).collect()
    };
    let train = split(Split::Train);
    let mut test = split(match args.eval_split {
        EvalSplit::Test => Split::Test,
        EvalSplit::Val => Split::Val,
    });
    if let Some(n) = args.test_shapes {
        test.truncate(n);
    }
    if train.is_empty() || test.is_empty() {
        return Err(bad_data(
            "training and test shapes",
            "an empty split".into(),
        ));
    }
    println!(
        "{} training and {} test shapes; input {}",
        train.len(),
        test.len(),
        args.input.name()
    );

    let varmap = VarMap::new();
    let model = build_seeded(&varmap, DType::F32, &dev, args.seed, |vb| {
        let encoder = match args.input {
            Input::Image => Encoder::Image(resnet_encoder(
                &ResnetEncoderConfig {
                    c_dim: CODE,
                    ..ResnetEncoderConfig::default()
                },
                vb.pp("encoder"),
            )?),
            Input::Points | Input::Latent => {
                let e = pointnet_encoder(
                    &PointNetConfig {
                        latent_dim: CODE,
                        ..PointNetConfig::default()
                    },
                    vb.pp("encoder"),
                )?;
                match args.input {
                    Input::Points => Encoder::Points(e),
                    _ => Encoder::Latent(e),
                }
            }
            Input::Voxels => Encoder::Voxels(voxel_encoder(
                &VoxelEncoderConfig {
                    c_dim: CODE,
                    ..VoxelEncoderConfig::default()
                },
                vb.pp("encoder"),
            )?),
        };
        let decoder = onet_decoder(
            &OnetConfig {
                hidden: 128,
                code_dim: CODE,
                ..OnetConfig::default()
            },
            vb.pp("decoder"),
        )?;
        Ok(Model { encoder, decoder })
    })?;

    // Training.
    let mut opt = adam(&varmap, 1e-3)?;
    let guard = FiniteGuard::new(&varmap);
    let clock = Clock::start(match args.steps {
        Some(n) => Budget::Steps(n),
        None => Budget::Minutes(args.minutes.unwrap_or(30.0)),
    })?;
    let mut clock = clock;
    let mut rng = SplitMix64::new(args.seed ^ 0xba7c4);
    let mut curve = String::from("step,train_seconds,test_iou\n");
    let (mut step, mut next_eval, mut lowered) = (0usize, 0.0, false);
    model.decoder.set_mode(NormMode::Train);
    loop {
        let t = clock.train_seconds();
        let progress = clock.progress(step);
        if t >= next_eval || progress >= 1.0 {
            let i = clock.pause(|| curve_iou(&model, args.input, &test, &dev))?;
            curve.push_str(&format!("{step},{t:.1},{i:.5}\n"));
            println!(
                "step {step}, {t:.0} s: test IoU ({} shapes) {i:.4}",
                test.len().min(CURVE_SHAPES)
            );
            next_eval += CURVE_EVERY;
        }
        if progress >= 1.0 {
            break;
        }
        if !lowered && progress >= 0.7 {
            opt.set_learning_rate(2e-4);
            lowered = true;
        }
        let batch: Vec<&ShapeSample> = (0..args.batch.min(train.len()))
            .map(|_| train[rng.below(train.len() as u64) as usize])
            .collect();
        let x = inputs(args.input, &batch, Some(&mut rng), &dev)?;
        let (q, y) = queries(&batch, args.near_fraction, &mut rng, &dev)?;
        let (codes, kl) = model.encode(&x, true, Some(args.seed ^ ((step as u64) << 20)))?;
        let logits = model.logits(&codes, &q)?;
        let loss = match kl {
            // The variational ONet's bound: Σ BCE + KL per shape, averaged over shapes.
            Some(kl) => (reconstruction_loss(&logits, &y)? + kl.mean_all()?)?,
            None => reconstruction_loss(&logits, &y)?,
        };
        let grads = loss.backward()?;
        guard.check(step, &loss, (step % 50 == 0).then_some(&grads))?;
        opt.step(&grads)?;
        step += 1;
    }
    let seconds = clock.train_seconds();

    // Evaluation and baselines.
    model.decoder.set_mode(NormMode::Eval);
    let (test_codes, test_kl) = encode_all(&model, args.input, &test, &dev)?;
    let (train_codes, _) = encode_all(&model, args.input, &train, &dev)?;
    let by_code = nearest_rows(&train_codes, &test_codes)?;
    let by_feature = nearest_rows(
        &fixed_features(args.input, &train, &dev)?,
        &fixed_features(args.input, &test, &dev)?,
    )?;
    let mean_grid = {
        let r = (train[0].voxels.len() as f64).cbrt().round() as usize;
        let mut acc = vec![0f32; r * r * r];
        for s in &train {
            for (a, &v) in acc.iter_mut().zip(&s.voxels) {
                *a += f32::from(v);
            }
        }
        let n = train.len() as f32;
        (r, acc.into_iter().map(|a| a / n).collect::<Vec<f32>>())
    };
    let mean_mesh = marching_cubes(
        &voxel_grid(&mean_grid.1, mean_grid.0),
        0.5,
        Inside::Positive,
    )?;
    let (mut net, mut mean, mut retr, mut fixed) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for (i, s) in test.iter().enumerate() {
        let code = test_codes.get(i)?;
        net.push(network_score(&model, &code, s, &dev)?);
        let (r, v) = &mean_grid;
        let pred: Vec<bool> = s
            .uniform_points
            .chunks_exact(3)
            .map(|p| voxel_at(v, *r, p) >= 0.5)
            .collect();
        mean.push(Score::from(
            iou(&pred, &labels(s))?,
            &surface_score(&mean_mesh, s, s.info.seed)?,
        ));
        retr.push(retrieved_score(train[by_code[i]], s, &dev)?);
        fixed.push(retrieved_score(train[by_feature[i]], s, &dev)?);
        if i < 4 {
            picture(args, &model, &code, s, i, &dev)?;
        }
    }
    // The variational run: the test posteriors' mean KL, and shapes from the prior.
    let kl = if args.input == Input::Latent {
        samples(args, &model, &dev)?;
        format!("\n  \"kl\": {:.4},", test_kl / test.len() as f64)
    } else {
        String::new()
    };
    let json = format!(
        "{{\n  \"input\": \"{}\",{kl}\n  \"eval_split\": \"{}\",\n  \"near_fraction\": {},\n  \"train_shapes\": {},\n  \"test_shapes\": {},\n  \"steps\": {step},\n  \"train_seconds\": {seconds:.1},\n  \"iou\": {},\n  \"chamfer_l1\": {},\n  \"normal_consistency\": {},\n  \"fscore\": {},\n  \"baselines\": {{\n    \"mean_shape\": {},\n    \"retrieval\": {},\n    \"retrieval_fixed_feature\": {}\n  }}\n}}\n",
        args.input.name(),
        match args.eval_split {
            EvalSplit::Test => "test",
            EvalSplit::Val => "val",
        },
        args.near_fraction,
        train.len(),
        test.len(),
        mean_of(&net, |s| s.iou),
        mean_of(&net, |s| s.chamfer),
        mean_of(&net, |s| s.normals),
        mean_of(&net, |s| s.fscore),
        Score::json(&mean),
        Score::json(&retr),
        Score::json(&fixed),
    );
    let write = |name: &str, text: &str| -> Result<()> {
        let p = args.out.join(name);
        std::fs::write(&p, text).map_err(io_err(&p))
    };
    write("metrics.json", &json)?;
    write("curve.csv", &curve)?;
    println!(
        "{} input, {step} steps in {seconds:.0} s: test IoU {:.4} (mean shape {:.4}, retrieval {:.4}, fixed-feature retrieval {:.4}); wrote {}",
        args.input.name(),
        mean_of(&net, |s| s.iou),
        mean_of(&mean, |s| s.iou),
        mean_of(&retr, |s| s.iou),
        mean_of(&fixed, |s| s.iou),
        args.out.display()
    );
    Ok(())
}

fn mean_of(v: &[Score], f: fn(&Score) -> f64) -> f64 {
    v.iter().map(f).sum::<f64>() / v.len().max(1) as f64
}

/// `samples.png`: eight shapes decoded from codes drawn from the prior `N(0, I)` (the
/// variational run), seen from one random camera and light, in two rows of four.
fn samples(args: &Args, model: &Model, dev: &Device) -> Result<()> {
    // z = 0 + exp(0)·ε with ε ~ N(0, I): draws from the prior.
    let zero = Tensor::zeros((8, CODE), DType::F32, dev)?;
    let z = reparameterize(&zero, &zero, args.seed ^ 0x5a3e)?;
    let mut rng = SplitMix64::new(args.seed ^ 0xca3);
    let cam = views::random_camera(&mut rng, IMAGE)?;
    let light = views::random_light(&mut rng, &cam);
    let mut rows = Vec::with_capacity(2);
    for r in 0..2 {
        let row = (0..4)
            .map(|c| {
                let surface = Conditioned::new(&model.decoder, z.get(4 * r + c)?)?;
                views::shade(&surface, &cam, light, dev)
            })
            .collect::<Result<Vec<_>>>()?;
        rows.push(Tensor::cat(&row, 1)?);
    }
    write_png(&args.out.join("samples.png"), &Tensor::cat(&rows, 0)?)
}

/// `test_NN.png`: the input, the network's surface and the true shape from one camera.
fn picture(
    args: &Args,
    model: &Model,
    code: &Tensor,
    s: &ShapeSample,
    i: usize,
    dev: &Device,
) -> Result<()> {
    let mut rng = SplitMix64::new(s.info.seed ^ 0x91c);
    let cam = match s.views.first() {
        Some(v) => v.camera,
        None => views::random_camera(&mut rng, IMAGE)?,
    };
    let light = views::random_light(&mut rng, &cam);
    let input = match args.input {
        Input::Image => inputs(Input::Image, &[s], None, dev)?
            .squeeze(0)?
            .permute((1, 2, 0))?,
        Input::Points => {
            let x = inputs(Input::Points, &[s], None, dev)?
                .flatten_all()?
                .to_vec1::<f32>()?;
            views::dots(&x, &cam)?
        }
        Input::Latent => {
            // The encoder's inside-labelled points.
            let x = inputs(Input::Latent, &[s], None, dev)?
                .flatten_all()?
                .to_vec1::<f32>()?;
            let inside: Vec<f32> = x
                .chunks_exact(4)
                .filter(|p| p[3] >= 0.5)
                .flat_map(|p| p[..3].to_vec())
                .collect();
            views::dots(&inside, &cam)?
        }
        Input::Voxels => {
            let r = (s.voxels.len() as f64).cbrt().round() as usize;
            let v: Vec<f32> = s.voxels.iter().map(|&v| f32::from(v)).collect();
            views::shade(&VoxelSurface(v, r), &cam, light, dev)?
        }
    };
    let recon = views::shade(
        &Conditioned::new(&model.decoder, code.clone())?,
        &cam,
        light,
        dev,
    )?;
    let truth =
        neural_fields::data::generate_shape(s.info.category, s.info.seed, dev, DType::F32)?.sdf();
    let truth = views::shade(&truth, &cam, light, dev)?;
    let strip = Tensor::cat(&[input, recon, truth], 1)?;
    write_png(&args.out.join(format!("test_{i:02}.png")), &strip)
}

/// Stored voxels (`z` fastest, resolution `r`) as a surface: the occupancy of the cell
/// holding a point, minus ½ (−½ outside the cube), inside positive.
struct VoxelSurface(Vec<f32>, usize);

impl ImplicitSurface for VoxelSurface {
    fn value(&self, points: &Tensor) -> Result<Tensor> {
        let v: Vec<f32> = points
            .to_dtype(DType::F32)?
            .flatten_all()?
            .to_vec1::<f32>()?
            .chunks_exact(3)
            .map(|p| {
                if p.iter().all(|x| (-0.5..=0.5).contains(x)) {
                    voxel_at(&self.0, self.1, p) - 0.5
                } else {
                    -0.5
                }
            })
            .collect();
        Ok(Tensor::from_vec(v, points.dim(0)?, points.device())?.to_dtype(points.dtype())?)
    }
    fn value_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        Ok((self.value(points)?, points.zeros_like()?))
    }
    fn inside(&self) -> Inside {
        Inside::Positive
    }
}
