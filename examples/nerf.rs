//! NeRF on a real capture: train a radiance field on a dataset folder and evaluate it on the
//! held-out views. `--help` lists every flag with its default.
//!
//! ```text
//! cargo run --release --example nerf                                  # the committed dataset, 10 minutes
//! cargo run --release --example nerf -- --data DIR --minutes 5 --out target/mine
//! cargo run --release --example nerf -- --steps 2000 --sampler stratified --seed 3
//! ```
//!
//! **Data**: any dataset [`neural_fields::data::load`] reads (Blender, nerfstudio,
//! IDR/DTU); training on the `train` split with a random background per ray, evaluation on
//! `test` (or `val`) on white. **Model**: [`Nerf`] with its defaults, Adam with a learning
//! rate decaying log-linearly to a tenth of `--lr`; `--encoding hash` puts instant-NGP's
//! hash grid over the scene box on a 1 × 64 trunk.
//!
//! **Samplers** (`--sampler`): `grid` (default), an [`OccupancyGrid`] (64³ cells) updated
//! every 16 steps, marched at the box diagonal / 64 while more than a quarter of it is
//! occupied, then / 256, whose sampling lets only the visible samples (transmittance ≥
//! 1e-4) through to the whole network; `stratified`, `--samples` jittered samples across
//! the scene box; `proposal`, two proposal networks placing `--proposal-samples`, then
//! `--samples` intervals ([`proposal_sample`], [`interlevel_loss`]), of which only the
//! visible ones with opacity ≥ `--alpha-threshold` (nerfacc's `alpha_thre`) go on.
//!
//! **Rays**: `--eval-supersample K` renders `K × K` rays per held-out pixel
//! ([`render_image`]); `--jitter on` trains on random points of the pixels,
//! `--train-supersample K` on the mean of `K × K` rays per pixel, `--march-jitter on` on
//! shifted march lattices; `--pixel-filter cycles` makes all three sample Cycles'
//! Blackman–Harris filter ([`PixelFilter::CYCLES`]). **Regularisers**: `--coarse-to-fine
//! START,END` opens the encoding's octaves over that fraction of training
//! ([`CoarseToFine`]), `--view-dependence off` drops the view direction, `--regnerf on`
//! adds RegNeRF's depth smoothness on patches from unseen cameras and its annealed range.
//!
//! **Output** in `--out` (default `target/nerf`): `metrics.json` (`psnr`, `ssim`,
//! `train_seconds` without evaluations, `steps`, `samples_per_ray`, `sampler`, `encoding`,
//! `eval_split`, `eval_views`, `eval_supersample`, `pixel_filter`, `jitter`,
//! `train_supersample`, `march_jitter`, `coarse_to_fine`, `view_dependence`,
//! `alpha_threshold`, `proposal_samples`, `data`); `curve.csv` (`step,train_seconds,psnr`
//! every `--eval-every` steps on `--eval-views` views, and at the end); `view_{i}.png`
//! (truth | prediction | error), `depth_{i}.png`, `opacity_{i}.png` for `--pictures`
//! views; `weights.safetensors`, which `--resume` loads. A NaN or infinity in the loss, a
//! gradient or a weight stops the run naming the step and the tensor. Past runs and their
//! commands: docs/benchmarks.md. Uses mimalloc (see `examples/tiny_nerf.rs`).

use candle_core::{DType, Device, Tensor};
use candle_nn::{Optimizer, VarBuilder, VarMap};
use clap::{Parser, ValueEnum};
use neural_fields::camera::{cameras_around, patch_rays, ray_aabb, Camera, PixelFilter, Rays};
use neural_fields::data::{
    colorize_depth, comparison_strip, load, load_eval, psnr, ssim, write_png, Background, Dataset,
    LoadConfig, RaySampler, Split,
};
use neural_fields::encoding::{
    hash_grid, CoarseToFine, FrequencyEncoding, HashGridConfig, PointEncoding,
};
use neural_fields::nn::{adam, build_seeded, mlp, Budget, Clock, FiniteGuard, Mlp, MlpConfig};
use neural_fields::numerics::trunc_exp;
use neural_fields::volume::{
    anneal_near_far, composite, depth_smoothness, interlevel_loss, log_linear_schedule, nerf,
    proposal_sample, render_image, render_weights, stratified, Composite, CompositeConfig,
    DensityFn, GridConfig, GridMarchConfig, ImageConfig, Jitter, Layout, Nerf, NerfConfig,
    OccupancyGrid, ProposalConfig, ANNEAL_MID_RATIO, ANNEAL_P_START,
};
use neural_fields::{Error, Result};
use std::path::{Path, PathBuf};

#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Rays per chunk when rendering whole views.
const CHUNK: usize = 4096;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Sampler {
    Grid,
    Stratified,
    Proposal,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Encoding {
    Pe,
    Hash,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum BackgroundFlag {
    Random,
    White,
    Black,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Filter {
    Box,
    Cycles,
}

/// The command line (see the module docs).
#[derive(Parser, Debug, Clone)]
#[command(about = "Train a NeRF on a dataset folder and evaluate it on the held-out views")]
struct Args {
    /// Dataset folder (Blender synthetic, nerfstudio or IDR/DTU layout).
    #[arg(long, default_value = "examples/data/wuson")]
    data: PathBuf,
    /// Read image and mask files outside the dataset folder (absolute paths, `../`,
    /// symlinks to elsewhere), which loading refuses by default.
    #[arg(long)]
    allow_outside_paths: bool,
    /// Minutes of training (default 10 unless --steps is given).
    #[arg(long, conflicts_with = "steps")]
    minutes: Option<f64>,
    /// Optimiser steps.
    #[arg(long)]
    steps: Option<usize>,
    /// Output folder.
    #[arg(long, default_value = "target/nerf")]
    out: PathBuf,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[arg(long, value_enum, default_value = "grid")]
    sampler: Sampler,
    /// Divide the images' resolution by this.
    #[arg(long, default_value_t = 1)]
    downscale: usize,
    /// Rays per step.
    #[arg(long, default_value_t = 1024)]
    rays: usize,
    /// Samples per ray (stratified and proposal samplers).
    #[arg(long, default_value_t = 64)]
    samples: usize,
    /// Half-side of the scene box for layouts that state none.
    #[arg(long, default_value_t = 1.5)]
    aabb: f64,
    #[arg(long, default_value_t = 250)]
    eval_every: usize,
    /// Held-out views evaluated during training.
    #[arg(long, default_value_t = 4)]
    eval_views: usize,
    /// Rays per pixel side in evaluation, 1 to 8.
    #[arg(long, default_value_t = 1)]
    eval_supersample: usize,
    #[arg(long, value_parser = on_off, action = clap::ArgAction::Set, default_value = "off")]
    jitter: bool,
    /// Rays per pixel side in training, 1 to 8.
    #[arg(long, default_value_t = 1)]
    train_supersample: usize,
    #[arg(long, value_parser = on_off, action = clap::ArgAction::Set, default_value = "off")]
    march_jitter: bool,
    #[arg(long, value_enum, default_value = "box")]
    pixel_filter: Filter,
    /// Held-out views written as pictures.
    #[arg(long, default_value_t = 8)]
    pictures: usize,
    /// Weights to start from (a previous run's weights.safetensors).
    #[arg(long)]
    resume: Option<PathBuf>,
    /// Learning rate (default 1e-3, 1e-2 with --encoding hash).
    #[arg(long)]
    lr: Option<f64>,
    #[arg(long, value_enum, default_value = "pe")]
    encoding: Encoding,
    #[arg(long, default_value_t = HashGridConfig::default().log2_table_size)]
    hash_log2: u32,
    #[arg(long)]
    hash_finest: Option<f64>,
    #[arg(long, value_enum, default_value = "random")]
    background: BackgroundFlag,
    /// Training views, e.g. 0,17,34 (default: all).
    #[arg(long, value_delimiter = ',')]
    frames: Option<Vec<usize>>,
    #[arg(long, value_parser = on_off, action = clap::ArgAction::Set, default_value = "off")]
    regnerf: bool,
    #[arg(long, value_parser = regnerf_weight, default_value = "400,0.1")]
    regnerf_weight: [f64; 2],
    /// START,END: the fractions of training over which the encoding's window opens.
    #[arg(long, value_parser = window_span)]
    coarse_to_fine: Option<(f64, f64)>,
    #[arg(long, value_parser = on_off, action = clap::ArgAction::Set, default_value = "on")]
    view_dependence: bool,
    /// Proposal sampler: drop samples of lower opacity, in [0, 1).
    #[arg(long, default_value_t = 1e-2)]
    alpha_threshold: f64,
    /// Proposal sampler: samples per ray of the two proposal levels.
    #[arg(long, value_parser = two_counts, default_value = "16,8")]
    proposal_samples: [usize; 2],
}

impl Default for Args {
    /// The defaults of the command line.
    fn default() -> Self {
        Args::parse_from(["nerf"])
    }
}

fn on_off(value: &str) -> std::result::Result<bool, String> {
    match value {
        "on" => Ok(true),
        "off" => Ok(false),
        other => Err(format!("on or off, not {other}")),
    }
}

fn numbers<const N: usize>(value: &str) -> std::result::Result<[f64; N], String> {
    let parts: Vec<f64> = value
        .split(',')
        .map(|v| v.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|e| e.to_string())?;
    match <[f64; N]>::try_from(parts) {
        Ok(a) if a.iter().all(|x: &f64| x.is_finite()) => Ok(a),
        _ => Err(format!(
            "{N} finite numbers separated by commas, not {value}"
        )),
    }
}

/// `--regnerf-weight START,END`: two weights > 0 (the schedule is log-linear).
fn regnerf_weight(value: &str) -> std::result::Result<[f64; 2], String> {
    match numbers(value)? {
        [a, b] if a > 0.0 && b > 0.0 => Ok([a, b]),
        _ => Err(format!("two weights > 0 like 400,0.1, not {value}")),
    }
}

/// `--coarse-to-fine START,END` with 0 ≤ START < 1 and START < END.
fn window_span(value: &str) -> std::result::Result<(f64, f64), String> {
    match numbers(value)? {
        [s, e] if 0.0 <= s && s < e && s < 1.0 => Ok((s, e)),
        _ => Err(format!(
            "START,END with 0 ≤ START < 1 and START < END, not {value}"
        )),
    }
}

fn two_counts(value: &str) -> std::result::Result<[usize; 2], String> {
    let bad = || format!("two positive counts like 16,8, not {value}");
    let l: Vec<usize> = value
        .split(',')
        .map(|v| v.trim().parse())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| bad())?;
    match l[..] {
        [a, b] if a > 0 && b > 0 => Ok([a, b]),
        _ => Err(bad()),
    }
}

impl Args {
    /// The checks clap cannot state; the training budget.
    fn budget(&self) -> Result<Budget> {
        let bad = |expected: &str, got: String| Error::InvalidArgument {
            arg: "flags",
            expected: expected.into(),
            got,
        };
        let ss = |k: usize| (1..=8).contains(&k);
        if self.rays == 0 || self.samples == 0 || self.eval_every == 0 || self.eval_views == 0 {
            return Err(bad(
                "--rays, --samples, --eval-every, --eval-views > 0",
                format!("{self:?}"),
            ));
        }
        if !ss(self.eval_supersample)
            || !ss(self.train_supersample)
            || self.rays < self.train_supersample.pow(2)
        {
            return Err(bad(
                "--eval-supersample and --train-supersample in 1..=8, --rays ≥ the square of the latter",
                format!("{self:?}"),
            ));
        }
        if !(self.aabb > 0.0 && self.aabb.is_finite() && (0.0..1.0).contains(&self.alpha_threshold))
        {
            return Err(bad(
                "--aabb > 0, --alpha-threshold in [0, 1)",
                format!("{self:?}"),
            ));
        }
        Ok(match (self.steps, self.minutes) {
            (Some(n), _) => Budget::Steps(n),
            (None, m) => Budget::Minutes(m.unwrap_or(10.0)),
        })
    }

    fn pixel_filter(&self) -> PixelFilter {
        match self.pixel_filter {
            Filter::Box => PixelFilter::Box,
            Filter::Cycles => PixelFilter::CYCLES,
        }
    }
}

/// The renderer: the network, its sampler and the scene box.
#[derive(Clone, Copy)]
struct Renderer<'a> {
    net: &'a Nerf,
    grid: Option<&'a OccupancyGrid>,
    proposals: &'a [Mlp],
    /// RegNeRF's annealed near/far at this training step (stratified sampler).
    anneal: Option<usize>,
    aabb: [f64; 6],
    step_size: f64,
    args: &'a Args,
}

impl Renderer<'_> {
    /// Renders `rays` composited on `background: [R, 3]`; also returns the number of
    /// samples that went through the full network and the interlevel loss. `seed`:
    /// jitter (training) or none.
    fn render(
        &self,
        rays: &Rays,
        background: &Tensor,
        seed: Option<u64>,
    ) -> Result<(Composite, usize, Tensor)> {
        let config = CompositeConfig {
            background: Some(background.clone()),
            ..CompositeConfig::default()
        };
        let mut levels = Vec::new();
        let mut interlevel = Tensor::zeros((), rays.origins().dtype(), rays.origins().device())?;
        let [x0, y0, z0, x1, y1, z1] = self.aabb;
        let intervals = match self.grid {
            Some(grid) => {
                // Only the samples in occupied cells that are still visible (T ≥ 1e-4)
                // reach the whole network; training shifts each ray's step lattice.
                let march = GridMarchConfig {
                    step_size: self.step_size,
                    jitter: seed.filter(|_| self.args.march_jitter),
                    ..GridMarchConfig::default()
                };
                let mut density = |p: &Tensor| self.net.density(p);
                grid.sample(rays, &march, Some(&mut density))?.intervals
            }
            None if !self.proposals.is_empty() => {
                let hit = ray_aabb(rays, [x0, y0, z0], [x1, y1, z1])?;
                let mut coarse = |p: &Tensor| proposal_density(&self.proposals[0], p);
                let mut fine = |p: &Tensor| proposal_density(&self.proposals[1], p);
                let proposal = ProposalConfig {
                    samples: self.args.proposal_samples.to_vec(),
                    final_samples: self.args.samples,
                    alpha_threshold: self.args.alpha_threshold,
                    ..ProposalConfig::default()
                };
                // With --alpha-threshold > 0 the field's density (no graph) culls the
                // samples and gives the interlevel loss its target weights.
                let mut field = |p: &Tensor| self.net.density(p);
                let cull = (self.args.alpha_threshold > 0.0).then_some(&mut field as _);
                let mut proposals: [DensityFn; 2] = [&mut coarse, &mut fine];
                let out = proposal_sample(
                    rays,
                    &hit.near,
                    &hit.far,
                    &mut proposals,
                    &proposal,
                    seed,
                    cull,
                )?;
                match out.interlevel {
                    Some(loss) => interlevel = loss,
                    None => levels = out.levels,
                }
                out.intervals
            }
            None => {
                let hit = ray_aabb(rays, [x0, y0, z0], [x1, y1, z1])?;
                let jitter = if seed.is_some() {
                    Jitter::PerSample
                } else {
                    Jitter::None
                };
                let (near, far) = match self.anneal {
                    Some(step) => anneal_near_far(
                        &hit.near,
                        &hit.far,
                        step,
                        256,
                        ANNEAL_P_START,
                        ANNEAL_MID_RATIO,
                    )?,
                    None => (hit.near, hit.far),
                };
                stratified(&near, &far, self.args.samples, jitter, seed.unwrap_or(0))?
            }
        };
        let positions = intervals.positions(rays)?.reshape(((), 3))?;
        let dirs = intervals.directions(rays)?.reshape(((), 3))?;
        let n = positions.dim(0)?;
        let (sigma, rgb) = self.net.radiance(&positions, &dirs)?;
        let (sigma, rgb) = match &intervals.layout {
            Layout::Batched => {
                let (r, s) = intervals.starts.dims2()?;
                (sigma.reshape((r, s))?, rgb.reshape((r, s, 3))?)
            }
            Layout::Packed(_) => (sigma, rgb),
        };
        // The proposals learn from the interlevel loss against the field's weights.
        if !levels.is_empty() {
            let weights = render_weights(&sigma, &intervals, Some(rays), &config)?.weights;
            for level in &levels {
                interlevel = (interlevel + interlevel_loss(level, &intervals, &weights)?)?;
            }
        }
        let out = composite(&sigma, &rgb, &intervals, Some(rays), &config)?;
        Ok((out, n, interlevel))
    }

    /// View `v` of `data`, `k × k` rays per pixel through `filter`: colour `[H, W, 3]`,
    /// depth `[H, W]` (NaN where the opacity is below 0.5), opacity `[H, W]`.
    fn render_view(
        &self,
        data: &Dataset,
        v: usize,
        k: usize,
        filter: PixelFilter,
    ) -> Result<[Tensor; 3]> {
        let bg = data.background().eval_color().map(|c| c as f32);
        let bg = Tensor::new(&bg, &Device::Cpu)?.unsqueeze(0)?;
        let config = ImageConfig {
            supersample: k,
            filter,
            chunk: CHUNK,
        };
        let cam = data.views()[v].camera();
        let [color, depth, opacity] =
            render_image(cam, &config, &Device::Cpu, DType::F32, |rays| {
                let background = bg.broadcast_as((rays.len(), 3))?.contiguous()?;
                let (out, _, _) = self.render(rays, &background, None)?;
                let depth = out.normalized_depth(1e-6)?;
                Ok([out.color, depth, out.opacity])
            })?;
        let nan = Tensor::full(f32::NAN, depth.shape(), depth.device())?;
        Ok([color, opacity.ge(0.5)?.where_cond(&depth, &nan)?, opacity])
    }
}

/// A proposal network: 2 × 32 ReLU on a frequency encoding (L = 6), density
/// `trunc_exp(raw − 1)`.
fn proposal_net(vb: VarBuilder) -> Result<Mlp> {
    let encoding = PointEncoding::Frequency(FrequencyEncoding::new(3, 6)?);
    mlp(
        &MlpConfig {
            hidden: 32,
            depth: 2,
            encoding,
            ..MlpConfig::default()
        },
        vb,
    )
}

fn proposal_density(net: &Mlp, points: &Tensor) -> Result<Tensor> {
    let raw = neural_fields::field::Field::forward(net, points)?.squeeze(1)?;
    trunc_exp(&(raw - 1.0)?)
}

/// RegNeRF's regulariser: the mean depth smoothness of 16 patches of 8 × 8 pixels, each
/// rendered from a random camera around the training cameras ([`cameras_around`]),
/// weighted by the detached opacity as in RegNeRF's DTU configuration.
fn regnerf_depth_smoothness(r: &Renderer, cameras: &[Camera], seed: u64) -> Result<Tensor> {
    const PATCHES: usize = 16;
    const K: usize = 8;
    let unseen = cameras_around(cameras, PATCHES, seed)?;
    let rays = patch_rays(&unseen, K, seed, &Device::Cpu, DType::F32)?;
    let n = PATCHES * K * K;
    let black = Tensor::zeros((n, 3), DType::F32, &Device::Cpu)?;
    let (out, _, _) = r.render(&rays, &black, Some(seed))?;
    let depth = out.normalized_depth(1e-6)?.reshape((PATCHES, K, K))?;
    // Each pixel weighted by its own opacity, detached: pixels of empty space (whose
    // normalised depth means nothing) do not smooth their neighbours.
    let opacity = out.opacity.detach().reshape((PATCHES, K, K))?;
    Ok(depth_smoothness(&depth, Some(&opacity))?.mean_all()?)
}

/// PSNR and SSIM of the first `n` views of `eval` (means), and the renders
/// `[truth, colour, depth, opacity]`.
fn evaluate(r: &Renderer, eval: &Dataset, n: usize) -> Result<(f64, f64, Vec<[Tensor; 4]>)> {
    let (mut p, mut s, mut renders) = (0.0, 0.0, Vec::new());
    let n = n.min(eval.views().len());
    for v in 0..n {
        let truth =
            eval.views()[v].rgb(eval.background().eval_color(), &Device::Cpu, DType::F32)?;
        let [color, depth, opacity] =
            r.render_view(eval, v, r.args.eval_supersample, r.args.pixel_filter())?;
        p += psnr(&color, &truth, None)?;
        s += ssim(&color, &truth, None)?;
        renders.push([truth, color, depth, opacity]);
    }
    Ok((p / n as f64, s / n as f64, renders))
}

/// Opens each window to `bands · clamp((progress − START)/(END − START), 0, 1)`, fully
/// without a span.
fn open_windows(windows: &[CoarseToFine], progress: f64, span: Option<(f64, f64)>) -> Result<()> {
    let open = span.map_or(1.0, |(s, e)| ((progress - s) / (e - s)).clamp(0.0, 1.0));
    for w in windows {
        w.set_alpha(open * w.bands() as f64)?;
    }
    Ok(())
}

fn write(path: &Path, text: &str) -> Result<()> {
    std::fs::write(path, text).map_err(|source| Error::Io {
        path: path.display().to_string(),
        source,
    })
}

/// The radiance field for `args.encoding`: NeRF's defaults, or a hash grid over the scene
/// box `aabb` (its table `grid.table` in the weights) on a 1 × 64 trunk.
fn nerf_config(args: &Args, aabb: [f64; 6], finest: f64, vb: &VarBuilder) -> Result<NerfConfig> {
    let mut config = match args.encoding {
        Encoding::Pe => NerfConfig::default(),
        Encoding::Hash => {
            let hash = HashGridConfig {
                lo: aabb[..3].to_vec(),
                hi: aabb[3..].to_vec(),
                log2_table_size: args.hash_log2,
                finest_resolution: finest,
                ..HashGridConfig::default()
            };
            NerfConfig {
                position_encoding: PointEncoding::HashGrid(hash_grid(&hash, vb.pp("grid"))?),
                depth: 1,
                skips: vec![],
                ..NerfConfig::default()
            }
        }
    };
    if !args.view_dependence {
        config.direction_encoding = None;
    }
    Ok(config)
}

fn run(args: &Args) -> Result<()> {
    let (device, dtype) = (Device::Cpu, DType::F32);
    let budget = args.budget()?;
    let background = match args.background {
        BackgroundFlag::Random => Background::Random,
        BackgroundFlag::White => Background::Color([1.0; 3]),
        BackgroundFlag::Black => Background::Color([0.0; 3]),
    };
    let train_config = LoadConfig {
        background,
        downscale: args.downscale,
        frames: args.frames.clone(),
        allow_outside_paths: args.allow_outside_paths,
        ..LoadConfig::default()
    };
    let train = load(&args.data, &train_config)?;
    let eval_config = LoadConfig {
        downscale: args.downscale,
        allow_outside_paths: args.allow_outside_paths,
        ..LoadConfig::default()
    };
    let (eval, split) = load_eval(&args.data, &eval_config)?;
    let eval_split = if split == Split::Test { "test" } else { "val" };
    std::fs::create_dir_all(&args.out).map_err(|source| Error::Io {
        path: args.out.display().to_string(),
        source,
    })?;
    let aabb = train.scene_box(args.aabb);
    let diag = (0..3)
        .map(|a| (aabb[a + 3] - aabb[a]).powi(2))
        .sum::<f64>()
        .sqrt();
    let finest = args.hash_finest.unwrap_or_else(|| train.hash_finest());
    let mut varmap = VarMap::new();
    let windows = std::cell::RefCell::new(Vec::new());
    let net = build_seeded(&varmap, dtype, &device, args.seed, |vb| {
        let mut config = nerf_config(args, aabb, finest, &vb)?;
        windows.borrow_mut().clear();
        if args.coarse_to_fine.is_some() {
            let window = CoarseToFine::new(config.position_encoding)?;
            windows.borrow_mut().push(window.clone());
            config.position_encoding = PointEncoding::CoarseToFine(window);
        }
        nerf(&config, vb)
    })?;
    let windows = windows.into_inner();
    let proposals = match args.sampler {
        Sampler::Proposal => (0..2)
            .map(|l| {
                build_seeded(&varmap, dtype, &device, args.seed + 1 + l, |vb| {
                    proposal_net(vb.pp(format!("proposal{l}")))
                })
            })
            .collect::<Result<Vec<Mlp>>>()?,
        _ => Vec::new(),
    };
    if let Some(path) = &args.resume {
        varmap.load(path)?;
    }
    let lr0 = args.lr.unwrap_or(match args.encoding {
        Encoding::Pe => 1e-3,
        Encoding::Hash => 1e-2,
    });
    let mut opt = adam(&varmap, lr0)?;
    let guard = FiniteGuard::new(&varmap);
    let mut grid = match args.sampler {
        Sampler::Grid => Some(OccupancyGrid::new(GridConfig {
            aabb,
            resolution: 64,
            decay: 0.7,
            warmup_steps: 128,
            seed: args.seed,
            ..GridConfig::default()
        })?),
        Sampler::Stratified | Sampler::Proposal => None,
    };
    let occupied = |g: &OccupancyGrid| {
        g.occupied().iter().filter(|&&o| o).count() as f64 / g.occupied().len() as f64
    };
    let mut sampler = RaySampler::new(&train, args.seed, &device, dtype)?
        .with_pixel_filter(args.pixel_filter(), args.jitter)?;
    let train_cameras: Vec<Camera> = train.views().iter().map(|v| *v.camera()).collect();
    let k0 = train.views()[0].camera().intrinsics();
    println!(
        "training on {} views of {} ({} {}), evaluating on {} {eval_split} views; sampler {:?}",
        train.views().len(),
        args.data.display(),
        k0.width,
        k0.height,
        eval.views().len(),
        args.sampler
    );
    let mut clock = Clock::start(budget)?;
    let bar = indicatif::ProgressBar::new(match budget {
        Budget::Steps(n) => n as u64,
        Budget::Minutes(m) => (m * 60.0).ceil() as u64,
    });
    let base = Renderer {
        net: &net,
        grid: None,
        proposals: &proposals,
        anneal: None,
        aabb,
        step_size: diag / 256.0,
        args,
    };
    let mut curve = String::from("step,train_seconds,psnr\n");
    let (mut samples_total, mut step) = (0usize, 0usize);
    loop {
        // --steps 0 evaluates (e.g. resumed weights) without training.
        let progress = clock.progress(step);
        if progress >= 1.0 {
            break;
        }
        let t = (progress * 10_000.0) as usize;
        opt.set_learning_rate(log_linear_schedule(t, lr0, lr0 / 10.0, 10_000));
        open_windows(&windows, progress, args.coarse_to_fine)?;
        if let Some(grid) = grid.as_mut() {
            grid.update(step, 16, &device, dtype, |p: &Tensor| {
                Ok(net.density(p)?.detach())
            })?;
        }
        let step_size = match &grid {
            Some(g) if occupied(g) > 0.25 => diag / 64.0,
            _ => diag / 256.0,
        };
        let anneal = args.regnerf.then_some(step);
        let r = Renderer {
            grid: grid.as_ref(),
            anneal,
            step_size,
            ..base
        };
        let k = args.train_supersample;
        let batch = if k > 1 {
            sampler.pixel_footprints(args.rays / (k * k), k)?
        } else {
            sampler.pixels(args.rays)?
        };
        let seed = args.seed ^ step as u64;
        let (out, n, interlevel) = r.render(&batch.rays, &batch.backgrounds, Some(seed))?;
        samples_total += n;
        // With k > 1, each pixel's k² rays averaged (a box filter) against the pixel's
        // colour, which every one of its rays carries.
        let (color, target) = if k > 1 {
            let px = batch.rays.len() / (k * k);
            let target = batch
                .colors
                .reshape((px, k * k, 3))?
                .narrow(1, 0, 1)?
                .squeeze(1)?;
            (out.color.reshape((px, k * k, 3))?.mean(1)?, target)
        } else {
            (out.color, batch.colors.clone())
        };
        let photometric = (color - target)?.sqr()?.mean_all()?;
        let mut loss = (&photometric + interlevel)?;
        if args.regnerf {
            let weight =
                log_linear_schedule(step, args.regnerf_weight[0], args.regnerf_weight[1], 512);
            let smooth = regnerf_depth_smoothness(&r, &train_cameras, seed)?;
            loss = (loss + (smooth * weight)?)?;
        }
        let grads = loss.backward()?;
        guard.check(step, &loss, Some(&grads))?;
        opt.step(&grads)?;
        step += 1;
        let mse = photometric.to_dtype(DType::F64)?.to_scalar::<f64>()?;
        bar.set_position(match budget {
            Budget::Steps(_) => step as u64,
            Budget::Minutes(_) => clock.train_seconds() as u64,
        });
        let per_ray = n as f64 / args.rays as f64;
        if step.is_multiple_of(10) {
            let p = -10.0 * mse.log10();
            bar.set_message(format!(
                "step {step} loss {mse:.5} train PSNR {p:.2} samples/ray {per_ray:.1}"
            ));
        }
        if step.is_multiple_of(args.eval_every) {
            let seconds = clock.train_seconds();
            let shown = args.eval_views.min(eval.views().len());
            let p = clock.pause(|| {
                bar.suspend(|| -> Result<f64> {
                    let (p, _, _) = evaluate(&r, &eval, args.eval_views)?;
                    let grid_note = grid.as_ref().map_or(String::new(), |g| {
                        format!(", {:.1} % of the grid occupied", 100.0 * occupied(g))
                    });
                    println!("step {step}: loss {mse:.5}, held-out PSNR {p:.2} dB ({shown} views), {per_ray:.1} samples/ray{grid_note}");
                    Ok(p)
                })
            })?;
            curve.push_str(&format!("{step},{seconds:.3},{p:.4}\n"));
        }
    }
    let train_seconds = clock.train_seconds();
    bar.finish_and_clear();
    open_windows(&windows, 1.0, args.coarse_to_fine)?;
    // The weights as training left them (a zero loss's empty gradients).
    let zero = Tensor::zeros((), dtype, &device)?;
    guard.check(step, &zero, Some(&zero.backward()?))?;
    if let Some(g) = &grid {
        println!("grid: {:.1} % of the cells occupied", 100.0 * occupied(g));
    }
    let r = Renderer {
        grid: grid.as_ref(),
        ..base
    };
    let (p, s, renders) = evaluate(&r, &eval, eval.views().len())?;
    let shown = args.eval_views.min(renders.len());
    let mut first = 0.0;
    for [truth, color, _, _] in &renders[..shown] {
        first += psnr(color, truth, None)? / shown as f64;
    }
    curve.push_str(&format!("{step},{train_seconds:.3},{first:.4}\n"));
    for (i, [truth, color, depth, opacity]) in renders.iter().enumerate().take(args.pictures) {
        write_png(
            &args.out.join(format!("view_{i}.png")),
            &comparison_strip(truth, color)?,
        )?;
        write_png(
            &args.out.join(format!("depth_{i}.png")),
            &colorize_depth(depth, None)?.0,
        )?;
        write_png(&args.out.join(format!("opacity_{i}.png")), opacity)?;
    }
    varmap.save(args.out.join("weights.safetensors"))?;
    write(&args.out.join("curve.csv"), &curve)?;
    let metrics = serde_json::json!({
        "psnr": p,
        "ssim": s,
        "train_seconds": train_seconds,
        "steps": step,
        "samples_per_ray": samples_total as f64 / (step.max(1) * args.rays) as f64,
        "sampler": format!("{:?}", args.sampler).to_lowercase(),
        "encoding": format!("{:?}", args.encoding).to_lowercase(),
        "eval_split": eval_split,
        "eval_views": eval.views().len(),
        "eval_supersample": args.eval_supersample,
        "pixel_filter": format!("{:?}", args.pixel_filter).to_lowercase(),
        "jitter": args.jitter,
        "train_supersample": args.train_supersample,
        "march_jitter": args.march_jitter,
        "coarse_to_fine": args.coarse_to_fine.map(|(s, e)| [s, e]),
        "view_dependence": args.view_dependence,
        "alpha_threshold": args.alpha_threshold,
        "proposal_samples": args.proposal_samples,
        "data": args.data.display().to_string(),
    });
    write(
        &args.out.join("metrics.json"),
        &serde_json::to_string_pretty(&metrics).expect("JSON"),
    )?;
    println!(
        "{step} steps in {train_seconds:.1} s: held-out PSNR {p:.2} dB, SSIM {s:.4} over {} {eval_split} views; wrote {}",
        eval.views().len(),
        args.out.display()
    );
    Ok(())
}

fn main() -> std::process::ExitCode {
    match run(&Args::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("nerf: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn metrics(out: &Path) -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap()
    }

    /// A few steps on the committed dataset at a quarter of its resolution: the whole
    /// pipeline runs, writes every output with the documented keys, and resumes.
    #[test]
    fn a_shortened_run_trains_writes_its_outputs_and_resumes() {
        let out = std::env::temp_dir().join(format!("nerf-example-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&out);
        let mut args = Args {
            steps: Some(4),
            out: out.clone(),
            seed: 1,
            downscale: 4,
            rays: 128,
            samples: 16,
            eval_every: 2,
            eval_views: 1,
            pictures: 1,
            ..Args::default()
        };
        run(&args).unwrap();
        let m = metrics(&out);
        for key in ["psnr", "ssim", "train_seconds", "steps", "samples_per_ray"] {
            assert!(m[key].as_f64().is_some_and(f64::is_finite), "{key}: {m}");
        }
        assert_eq!(m["steps"], 4);
        let curve = std::fs::read_to_string(out.join("curve.csv")).unwrap();
        assert_eq!(curve.lines().next(), Some("step,train_seconds,psnr"));
        assert_eq!(curve.lines().count(), 1 + 2 + 1); // header, steps 2 and 4, final
        for file in [
            "view_0.png",
            "depth_0.png",
            "opacity_0.png",
            "weights.safetensors",
        ] {
            assert!(out.join(file).is_file(), "{file}");
        }
        // Resuming from the saved weights, with the stratified sampler.
        args.resume = Some(out.join("weights.safetensors"));
        args.sampler = Sampler::Stratified;
        args.steps = Some(2);
        run(&args).unwrap();
        // The proposal sampler from scratch (its networks are not in the saved weights),
        // skipping empty samples (the default) and keeping them all, under a window.
        args.resume = None;
        args.sampler = Sampler::Proposal;
        run(&args).unwrap();
        args.alpha_threshold = 0.0;
        args.coarse_to_fine = Some((0.0, 2.0));
        args.view_dependence = false;
        run(&args).unwrap();
        let m = metrics(&out);
        assert_eq!(m["alpha_threshold"], 0.0);
        assert_eq!(m["coarse_to_fine"], serde_json::json!([0.0, 2.0]));
        assert_eq!(m["view_dependence"], false);
        assert_eq!(m["proposal_samples"], serde_json::json!([16, 8]));
        args.coarse_to_fine = None;
        args.view_dependence = true;
        // The hash-grid encoding, with box-filtered training rays and a jittered march.
        args.sampler = Sampler::Grid;
        args.encoding = Encoding::Hash;
        args.train_supersample = 2;
        args.march_jitter = true;
        run(&args).unwrap();
        let m = metrics(&out);
        assert_eq!(m["encoding"], "hash");
        assert_eq!(m["sampler"], "grid");
        assert_eq!(m["train_supersample"], 2);
        assert_eq!(m["march_jitter"], true);
        // Cycles' pixel filter in training (jittered rays) and in a 3 × 3 evaluation.
        args.train_supersample = 1;
        args.jitter = true;
        args.pixel_filter = Filter::Cycles;
        args.eval_supersample = 3;
        run(&args).unwrap();
        let m = metrics(&out);
        assert_eq!(m["pixel_filter"], "cycles");
        assert!(m["psnr"].as_f64().is_some_and(f64::is_finite));
        let _ = std::fs::remove_dir_all(&out);
    }

    /// The command line keeps the flags, spellings and defaults of earlier versions.
    #[test]
    fn flags_parse_as_documented() {
        let a = Args::default();
        assert_eq!(a.out, PathBuf::from("target/nerf"));
        let counts = (a.rays, a.samples, a.eval_every, a.eval_views, a.pictures);
        assert_eq!(counts, (1024, 64, 250, 4, 8));
        assert_eq!((a.sampler, a.encoding), (Sampler::Grid, Encoding::Pe));
        assert_eq!(
            (a.regnerf_weight, a.proposal_samples),
            ([400.0, 0.1], [16, 8])
        );
        assert!(a.view_dependence && !a.jitter && !a.march_jitter && !a.regnerf);
        assert_eq!(a.budget().unwrap(), Budget::Minutes(10.0));
        let flags = "nerf --sampler proposal --frames 0,17,34 --jitter on --coarse-to-fine 0,3.5 \
            --pixel-filter cycles --background black --proposal-samples 32,16 --steps 7";
        let b = Args::parse_from(flags.split_whitespace());
        assert_eq!(
            (b.frames.clone(), b.proposal_samples),
            (Some(vec![0, 17, 34]), [32, 16])
        );
        assert_eq!(
            (b.coarse_to_fine, b.budget().unwrap()),
            (Some((0.0, 3.5)), Budget::Steps(7))
        );
        for bad in [
            "--steps 1 --minutes 2",
            "--jitter yes",
            "--coarse-to-fine 0.5,0.2",
        ] {
            let flags = std::iter::once("nerf").chain(bad.split_whitespace());
            assert!(Args::try_parse_from(flags).is_err(), "{bad}");
        }
        assert!(Args {
            rays: 0,
            ..Args::default()
        }
        .budget()
        .is_err());
    }
}
