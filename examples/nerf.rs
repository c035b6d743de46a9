//! NeRF on a real capture: train a radiance field on a dataset folder and evaluate it on the
//! held-out views.
//!
//! ```text
//! cargo run --release --example nerf                                  # the committed dataset, 10 minutes
//! cargo run --release --example nerf -- --data DIR --minutes 5 --out out/mine
//! cargo run --release --example nerf -- --steps 2000 --sampler stratified --seed 3
//! ```
//!
//! **Data.** `--data DIR` is any dataset [`neural_fields::data::load`] reads (Blender
//! synthetic, nerfstudio, IDR/DTU; default `examples/data/wuson`). Training uses the
//! `train` split with a random background colour per ray (so transparency is learnt as
//! transparency); evaluation uses the `test` split (the `val` split if there is none) on
//! white. `--downscale K` divides the images' resolution by K.
//!
//! **Model.** [`neural_fields::nn::Nerf`] with its defaults: frequency encodings (L = 10
//! for positions, 4 for directions), a 4 × 64 ReLU trunk, trunc-exp density, a 64-wide
//! view-dependent colour head. Adam, learning rate decaying log-linearly from `--lr` (1e-3)
//! to a tenth of it over the run (over the steps, or over the time budget). Larger rates
//! (5e-3) collapse the density to zero everywhere within 20 steps on the committed
//! dataset, where 90 % of the pixels are background, and it does not recover; 5e-4 learns
//! more slowly than 1e-3.
//!
//! `--encoding hash` replaces the frequency encoding of positions by instant-NGP's
//! multiresolution hash grid ([`neural_fields::encoding::HashGrid`]: 16 levels of 2
//! features over the scene box, resolutions 16 to `--hash-finest` (default: five cells
//! per pixel of the training images' larger side, 500 for the committed 100 × 100 views;
//! instant-NGP uses 2048 for 800 × 800), tables of 2^`--hash-log2` rows (default 2¹⁵)) on
//! a 1 × 64 trunk, with a default learning rate of 1e-2 (instant-NGP's).
//!
//! **Samplers** (`--sampler`):
//! - `grid` (default): an [`OccupancyGrid`] (64³ cells over the scene box) updated from the
//!   network's density every 16 steps; rays are marched at a fixed step through occupied
//!   cells only: the box diagonal / 64 while more than a quarter of the cells are occupied
//!   (early on, when the grid has not yet learnt where the scene is empty), then the
//!   diagonal / 256; the density is evaluated there without a graph,
//!   samples behind transmittance 1e-4 are dropped ([`visible_mask`],
//!   [`Intervals::retain`](neural_fields::volume::Intervals::retain)), and the full network runs, with its graph, on the rest.
//! - `stratified`: `--samples` (64) jittered samples per ray between the ray's entry and
//!   exit of the scene box.
//! - `proposal`: two proposal networks (2 × 32 ReLU on a frequency encoding, L = 6) place
//!   16 and then 8 samples (`--proposal-samples 16,8`), from which `--samples` intervals
//!   are drawn for the radiance field
//!   ([`proposal_sample`](neural_fields::volume::proposal_sample)); the proposals learn
//!   from the interlevel loss ([`interlevel_loss`](neural_fields::volume::interlevel_loss)),
//!   added to the photometric loss. The field's density at those intervals, without a
//!   graph, gives the interlevel loss its target weights; then only the samples that are
//!   visible (transmittance ≥ 1e-4) and not empty (opacity `1 − e^{−σδ}` ≥
//!   `--alpha-threshold`, default 1e-2; nerfacc's `alpha_thre`) go through the whole
//!   network, in training and evaluation alike. `--alpha-threshold 0` keeps every
//!   sample.
//!
//! The scene box is the layout's bounds (nerfstudio's `aabb_scale`, DTU's unit sphere) or,
//! for layouts that state none (Blender), the cube of half-side `--aabb` (default 1.5,
//! nerfacc's for the Blender scenes).
//!
//! **Evaluation** renders one ray through each held-out pixel's centre, or with
//! `--eval-supersample K` (1 to 8) the mean of `K × K` rays on a sub-pixel grid (a box
//! filter, as the images were rendered by integrating over each pixel). `--jitter on`
//! trains on rays through random points of their pixels instead of the centres
//! ([`RaySampler::with_pixel_filter`], instant-NGP's training rays); `--train-supersample K`
//! renders `K × K` rays per training pixel and compares their mean with the pixel
//! ([`RaySampler::pixel_footprints`]: box-filtered training, the model of such images,
//! with `--rays / K²` pixels per step). `--march-jitter on` shifts each training ray's
//! grid-march steps by a random fraction of a step
//! ([`GridMarchConfig::with_jitter`](neural_fields::volume::GridMarchConfig::with_jitter)),
//! so the field is not fitted at the same points along a ray every step.
//!
//! **The pixel filter.** `--pixel-filter cycles` makes all three (the evaluation's
//! `K × K` rays, `--jitter` and `--train-supersample`) sample the filter Blender's Cycles
//! renders with, a Blackman–Harris window of support ±1.5 px
//! ([`PixelFilter::CYCLES`](neural_fields::camera::PixelFilter::CYCLES)), instead of the
//! pixel's square (`box`, the default). On the committed dataset the true scene scores
//! 30 dB at pixel centres but 45 dB under that filter
//! (`examples/data/pixel_filter_ceiling.py`, docs/benchmarks.md): a field trained on
//! pixel centres learns the filter's blur, one trained through the filter can learn the
//! scene. Evaluate with `--eval-supersample 3` or more (the filter reaches into the
//! neighbouring pixels).
//!
//! **Coarse-to-fine.** `--coarse-to-fine START,END` puts the position encoding under a
//! window ([`CoarseToFine`]) that opens its octaves (or hash levels) from the fraction
//! START of training to END: BARF's schedule, which FreeNeRF uses as a frequency
//! regulariser for sparse views (`--frames`). Evaluations during training use the window
//! as it stands, the final one the window at the end of the schedule: fully open, unless
//! END > 1, which leaves a fraction `(1 − START)/(END − START)` of the bands open and so
//! caps the encoding's frequencies. `--view-dependence off` drops the view direction
//! from the colour head (a diffuse scene, or too few views to tell shading from shape).
//!
//! **Output** in `--out DIR` (default `out/nerf`):
//! - `metrics.json`: `psnr`, `ssim` (means over the held-out views), `train_seconds`
//!   (evaluation excluded), `steps`, `samples_per_ray` (mean over training), `sampler`,
//!   `encoding`,
//!   `eval_split`, `eval_views`, `eval_supersample`, `pixel_filter`, `jitter`,
//!   `train_supersample`,
//!   `march_jitter`, `coarse_to_fine` (`[START, END]` or null), `view_dependence`,
//!   `alpha_threshold`, `proposal_samples`, `data`;
//! - `curve.csv`: `step,train_seconds,psnr` every `--eval-every` steps (PSNR on the first
//!   `--eval-views` held-out views);
//! - `view_{i}.png` (truth | prediction | error), `depth_{i}.png`, `opacity_{i}.png` for
//!   the first `--pictures` held-out views;
//! - `weights.safetensors`, which `--resume FILE` loads to continue training.
//!
//! A NaN or infinity in the loss, a gradient or a weight stops the run with an error naming
//! the step and the tensor. The example uses mimalloc (see `examples/tiny_nerf.rs`).

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use candle_nn::{Optimizer, VarMap};
use common::PositionEncoding;
use neural_fields::camera::{cameras_around, ray_aabb, Camera, PixelFilter, Rays};
use neural_fields::data::{
    colorize_depth, comparison_strip, load, psnr, ssim, write_png, Background, Dataset, LoadConfig,
    RaySampler,
};
use neural_fields::encoding::{CoarseToFine, FrequencyEncoding, HashGridConfig, PointEncoding};
use neural_fields::nn::{build_seeded, mlp, nerf, Mlp, MlpConfig, Nerf, NerfConfig};
use neural_fields::volume::{
    anneal_near_far, composite, depth_smoothness, interlevel_loss, log_linear_schedule,
    proposal_sample, render_weights, stratified, trunc_exp, visible_mask, Composite,
    CompositeConfig, GridConfig, GridMarchConfig, Intervals, Jitter, Layout, OccupancyGrid,
    ProposalConfig, ANNEAL_MID_RATIO, ANNEAL_P_START, DEFAULT_TERMINATION_EPS,
};
use neural_fields::Result;
use std::path::PathBuf;

#[path = "common/mod.rs"]
mod common;
#[path = "common/training.rs"]
pub mod training;

#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Rays per chunk when rendering whole views.
const CHUNK: usize = 4096;

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Sampler {
    Grid,
    Stratified,
    Proposal,
}

#[derive(Debug)]
pub struct Args {
    pub data: PathBuf,
    pub minutes: Option<f64>,
    pub steps: Option<usize>,
    pub out: PathBuf,
    pub seed: u64,
    pub sampler: Sampler,
    pub downscale: usize,
    pub rays: usize,
    pub samples: usize,
    pub aabb: f64,
    pub eval_every: usize,
    pub eval_views: usize,
    /// Rays per pixel side in evaluation (`k × k` averaged; 1: the pixel centre).
    pub eval_supersample: usize,
    /// Training rays through random points of their pixels instead of the centres.
    pub jitter: bool,
    /// Rays per pixel side in training: `k × k` rays per pixel, their mean compared with
    /// the pixel (`--rays` counts rays, so `--rays / k²` pixels per step).
    pub train_supersample: usize,
    /// Shift the grid march's step lattice at random per ray in training.
    pub march_jitter: bool,
    /// The filter that evaluation's `k × k` rays, jittered training rays and training
    /// footprints sample.
    pub pixel_filter: PixelFilter,
    pub pictures: usize,
    pub resume: Option<PathBuf>,
    pub lr: Option<f64>,
    pub encoding: PositionEncoding,
    /// `--encoding hash`: log₂ of each level's table rows and the finest resolution.
    pub hash_log2: u32,
    /// `None`: five cells per pixel of the training images' larger side.
    pub hash_finest: Option<f64>,
    pub background: Background,
    pub frames: Option<Vec<usize>>,
    pub regnerf: bool,
    /// RegNeRF's depth-smoothness weight, log-linear from the first to the second value
    /// over the first 512 steps (RegNeRF's 400 → 0.1 by default).
    pub regnerf_weight: [f64; 2],
    /// The fractions of training over which the position encoding's window opens.
    pub coarse_to_fine: Option<(f64, f64)>,
    /// Whether the colour depends on the view direction.
    pub view_dependence: bool,
    /// Proposal sampler: drop final samples whose opacity `1 − e^{−σδ}` is below this
    /// (0: keep all; default 1e-2).
    pub alpha_threshold: f64,
    /// Proposal sampler: samples per ray of each proposal level.
    pub proposal_samples: Vec<usize>,
}

const USAGE: &str = "usage: nerf [--data DIR] [--minutes M | --steps N] [--out DIR] [--seed S] \
[--sampler grid|stratified|proposal] [--downscale K] [--rays N] [--samples N] [--aabb R] \
[--eval-every N] [--eval-views N] [--pictures N] [--resume FILE] [--lr LR] [--background random|white|black] [--frames I,J,K] [--regnerf on|off] \
[--encoding pe|hash] [--hash-log2 T] [--hash-finest N] [--eval-supersample K] [--jitter on|off] \
[--train-supersample K] [--march-jitter on|off] [--pixel-filter box|cycles] [--regnerf-weight START,END] \
[--coarse-to-fine START,END] [--view-dependence on|off] [--alpha-threshold A] [--proposal-samples N,M]";

impl Default for Args {
    /// The defaults of the command line.
    fn default() -> Self {
        Self {
            data: PathBuf::from("examples/data/wuson"),
            minutes: None,
            steps: None,
            out: PathBuf::from("out/nerf"),
            seed: 0,
            sampler: Sampler::Grid,
            downscale: 1,
            rays: 1024,
            samples: 64,
            aabb: 1.5,
            eval_every: 250,
            eval_views: 4,
            eval_supersample: 1,
            jitter: false,
            train_supersample: 1,
            march_jitter: false,
            pixel_filter: PixelFilter::Box,
            pictures: 8,
            resume: None,
            lr: None,
            encoding: PositionEncoding::Pe,
            hash_log2: HashGridConfig::default().log2_table_size,
            hash_finest: None,
            background: Background::Random,
            frames: None,
            regnerf: false,
            regnerf_weight: [400.0, 0.1],
            coarse_to_fine: None,
            view_dependence: true,
            alpha_threshold: 1e-2,
            proposal_samples: vec![16, 8],
        }
    }
}

fn parse_args() -> std::result::Result<Args, String> {
    let mut a = Args::default();
    training::parse_flags(USAGE, |flag, value| {
        let (num, int) = (training::number, training::count);
        if training::take_run_flag(
            flag,
            value,
            &mut a.data,
            &mut a.minutes,
            &mut a.steps,
            &mut a.out,
            &mut a.seed,
        )? {
            return Ok(());
        }
        match flag {
            "--sampler" => {
                a.sampler = match value {
                    "grid" => Sampler::Grid,
                    "stratified" => Sampler::Stratified,
                    "proposal" => Sampler::Proposal,
                    other => {
                        return Err(format!(
                            "--sampler: grid, stratified or proposal, not {other}"
                        ))
                    }
                }
            }
            "--downscale" => a.downscale = int(flag, value)?,
            "--rays" => a.rays = int(flag, value)?,
            "--samples" => a.samples = int(flag, value)?,
            "--aabb" => a.aabb = num(flag, value)?,
            "--eval-every" => a.eval_every = int(flag, value)?,
            "--eval-views" => a.eval_views = int(flag, value)?,
            "--eval-supersample" => a.eval_supersample = int(flag, value)?,
            "--jitter" => a.jitter = training::on_off(flag, value)?,
            "--train-supersample" => a.train_supersample = int(flag, value)?,
            "--march-jitter" => a.march_jitter = training::on_off(flag, value)?,
            "--pixel-filter" => {
                a.pixel_filter = match value {
                    "box" => PixelFilter::Box,
                    "cycles" => PixelFilter::CYCLES,
                    other => return Err(format!("--pixel-filter: box or cycles, not {other}")),
                }
            }
            "--pictures" => a.pictures = int(flag, value)?,
            "--resume" => a.resume = Some(value.into()),
            "--lr" => a.lr = Some(num(flag, value)?),
            "--hash-log2" => {
                a.hash_log2 = u32::try_from(int(flag, value)?)
                    .map_err(|_| format!("--hash-log2: a small integer, not {value}"))?
            }
            "--hash-finest" => a.hash_finest = Some(num(flag, value)?),
            "--encoding" => a.encoding = PositionEncoding::parse(value)?,
            "--frames" => {
                let list: std::result::Result<Vec<usize>, _> = value
                    .split(',')
                    .map(|v| v.trim().parse::<usize>())
                    .collect();
                a.frames =
                    Some(list.map_err(|_| format!("--frames: indices like 0,16,33, not {value}"))?);
            }
            "--regnerf" => a.regnerf = training::on_off(flag, value)?,
            "--regnerf-weight" => a.regnerf_weight = regnerf_weight(value)?,
            "--coarse-to-fine" => a.coarse_to_fine = Some(training::window_span(flag, value)?),
            "--view-dependence" => a.view_dependence = training::on_off(flag, value)?,
            "--alpha-threshold" => a.alpha_threshold = num(flag, value)?,
            "--proposal-samples" => {
                let list: std::result::Result<Vec<usize>, _> = value
                    .split(',')
                    .map(|v| v.trim().parse::<usize>())
                    .collect();
                match list {
                    Ok(l) if l.len() == 2 && !l.contains(&0) => a.proposal_samples = l,
                    _ => {
                        return Err(format!(
                            "--proposal-samples: two positive counts like 64,32, not {value}"
                        ))
                    }
                }
            }
            "--background" => {
                a.background = match value {
                    "random" => Background::Random,
                    "white" => Background::Color([1.0; 3]),
                    "black" => Background::Color([0.0; 3]),
                    other => {
                        return Err(format!("--background: random, white or black, not {other}"))
                    }
                }
            }
            other => return Err(format!("unknown flag {other}\n{USAGE}")),
        }
        Ok(())
    })?;
    training::check_budget(&mut a.minutes, a.steps, 10.0)?;
    if a.rays == 0
        || a.samples == 0
        || a.eval_every == 0
        || a.eval_views == 0
        || !(1..=8).contains(&a.eval_supersample)
        || !(1..=8).contains(&a.train_supersample)
        || a.rays < a.train_supersample * a.train_supersample
    {
        return Err(
            "--rays, --samples, --eval-every and --eval-views must be positive, \
                    --eval-supersample and --train-supersample between 1 and 8, \
                    --rays at least the square of --train-supersample"
                .into(),
        );
    }
    if !(a.aabb > 0.0 && a.aabb.is_finite()) {
        return Err("--aabb must be positive".into());
    }
    if !(0.0..1.0).contains(&a.alpha_threshold) {
        return Err("--alpha-threshold must lie in [0, 1)".into());
    }
    Ok(a)
}

/// `--regnerf-weight START,END`: two finite weights > 0 (the schedule is log-linear).
pub fn regnerf_weight(value: &str) -> std::result::Result<[f64; 2], String> {
    match training::pair("--regnerf-weight", value, "400,0.1")? {
        [a, b] if a > 0.0 && b > 0.0 => Ok([a, b]),
        _ => Err(format!(
            "--regnerf-weight: two finite weights > 0 like 400,0.1, not {value}"
        )),
    }
}

/// The renderer: the network, its sampler and the scene box.
struct Renderer<'a> {
    net: &'a Nerf,
    grid: Option<&'a OccupancyGrid>,
    proposals: &'a [Mlp],
    /// RegNeRF's annealed near/far at this training step (stratified sampler).
    anneal: Option<usize>,
    aabb: [f64; 6],
    step_size: f64,
    samples: usize,
    /// Shift the grid march's steps at random in training (`--march-jitter`).
    march_jitter: bool,
    /// Proposal sampler: the opacity below which a final sample is skipped.
    alpha_threshold: f64,
    /// Proposal sampler: samples per ray of each level.
    proposal_samples: &'a [usize],
}

impl Renderer<'_> {
    /// Renders `rays` composited on `background: [R, 3]`; also returns the number of
    /// samples that went through the full network. `seed`: jitter (training) or none.
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
        let composite_config = &config;
        let mut levels = Vec::new();
        let mut interlevel = Tensor::zeros((), rays.origins().dtype(), rays.origins().device())?;
        let intervals = match self.grid {
            Some(grid) => {
                let march = GridMarchConfig::new(0.0, f64::INFINITY, self.step_size);
                // Training shifts each ray's step lattice at random (nerfacc's stratified
                // march), so the field is not fitted at the same points every step.
                let march = match seed {
                    Some(seed) if self.march_jitter => march.with_jitter(seed),
                    _ => march,
                };
                let iv = grid.sample(rays, &march)?.intervals;
                // Early termination: the density without a graph, then only the visible
                // samples through the whole network.
                let sigma = self.density(&iv, rays)?;
                self.skip(iv, &sigma, rays, 0.0)?
            }
            None if !self.proposals.is_empty() => {
                let [x0, y0, z0, x1, y1, z1] = self.aabb;
                let hit = ray_aabb(rays, [x0, y0, z0], [x1, y1, z1])?;
                let mut coarse = |p: &Tensor| proposal_density(&self.proposals[0], p);
                let mut fine = |p: &Tensor| proposal_density(&self.proposals[1], p);
                let config = ProposalConfig {
                    samples: self.proposal_samples.to_vec(),
                    final_samples: self.samples,
                    padding: 0.01,
                };
                let out = proposal_sample(
                    rays,
                    &hit.near,
                    &hit.far,
                    &mut [&mut coarse, &mut fine],
                    &config,
                    seed,
                )?;
                if self.alpha_threshold > 0.0 {
                    // Skip what the scene does not need: the field's density without a
                    // graph at every final sample gives the interlevel loss its (detached)
                    // target weights; then only samples that are visible (T ≥ 1e-4) and
                    // not empty (α ≥ the threshold) go through the whole network.
                    let iv = out.intervals;
                    let sigma = self.density(&iv, rays)?;
                    let weights =
                        render_weights(&sigma, &iv, Some(rays), composite_config)?.weights;
                    for level in &out.levels {
                        interlevel = (interlevel + interlevel_loss(level, &iv, &weights)?)?;
                    }
                    self.skip(iv, &sigma, rays, self.alpha_threshold)?
                } else {
                    levels = out.levels;
                    out.intervals
                }
            }
            None => {
                let [x0, y0, z0, x1, y1, z1] = self.aabb;
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
                stratified(&near, &far, self.samples, jitter, seed.unwrap_or(0))?
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

    /// The field's density at the samples of `iv` (either layout), without a graph.
    fn density(&self, iv: &Intervals, rays: &Rays) -> Result<Tensor> {
        let sigma = self
            .net
            .density(&iv.positions(rays)?.flatten_to(iv.starts.rank() - 1)?)?;
        Ok(sigma.reshape(iv.starts.shape())?.detach())
    }

    /// The samples of `iv` worth the whole network: visible (T ≥ 1e-4) and, for
    /// `alpha_threshold > 0`, not empty (opacity `1 − e^{−σδ}` ≥ the threshold).
    fn skip(
        &self,
        iv: Intervals,
        sigma: &Tensor,
        rays: &Rays,
        alpha_threshold: f64,
    ) -> Result<Intervals> {
        let mut mask = visible_mask(sigma, &iv, Some(rays), DEFAULT_TERMINATION_EPS)?;
        if alpha_threshold > 0.0 {
            let dt = (&iv.ends - &iv.starts)?;
            let alpha = (1.0 - (sigma * dt)?.neg()?.exp()?)?;
            mask = (mask * alpha.ge(alpha_threshold)?)?;
        }
        Ok(iv.retain(&mask)?.0)
    }

    /// Renders view `v` of `data` whole, in chunks, without keeping a graph, with
    /// `k × k` rays per pixel averaged (the quadrature of `filter`; `k = 1` with the box:
    /// one ray through the pixel centre): colour `[H, W, 3]`, depth `[H, W]` (NaN where
    /// the opacity is below 0.5), opacity `[H, W]`.
    fn render_view(
        &self,
        data: &Dataset,
        v: usize,
        k: usize,
        filter: PixelFilter,
    ) -> Result<(Tensor, Tensor, Tensor)> {
        let cam = data.views()[v].camera();
        let (w, h) = (cam.intrinsics().width, cam.intrinsics().height);
        let all =
            cam.rays_for_pixels(&cam.subpixel_grid(k, filter, &Device::Cpu, DType::F32)?)?;
        let n = all.len();
        let [r, g, b] = data.background().eval_color();
        let (mut colors, mut depths, mut opacities) = (Vec::new(), Vec::new(), Vec::new());
        // Whole pixels per chunk, so that each pixel's k² rays fall in one chunk.
        let chunk = (CHUNK / (k * k)).max(1) * k * k;
        let background = Tensor::new(&[[r as f32, g as f32, b as f32]], &Device::Cpu)?
            .broadcast_as((chunk.min(n), 3))?
            .contiguous()?;
        for start in (0..n).step_by(chunk) {
            let len = chunk.min(n - start);
            let background = background.narrow(0, 0, len)?;
            let (out, _, _) = self.render(&all.narrow(start, len)?, &background, None)?;
            let px = len / (k * k);
            let mean = |t: Tensor, c: usize| -> Result<Tensor> {
                Ok(t.detach().reshape((px, k * k, c))?.mean(1)?)
            };
            colors.push(mean(out.color.clone(), 3)?);
            depths.push(mean(out.normalized_depth(1e-6)?.unsqueeze(1)?, 1)?.squeeze(1)?);
            opacities.push(mean(out.opacity.unsqueeze(1)?, 1)?.squeeze(1)?);
        }
        let opacity = Tensor::cat(&opacities, 0)?;
        let depth = Tensor::cat(&depths, 0)?;
        let nan = Tensor::full(f32::NAN, depth.shape(), depth.device())?;
        let depth = opacity.ge(0.5)?.where_cond(&depth, &nan)?;
        Ok((
            Tensor::cat(&colors, 0)?.reshape((h, w, 3))?,
            depth.reshape((h, w))?,
            opacity.reshape((h, w))?,
        ))
    }
}

/// A proposal network: 2 × 32 ReLU on a frequency encoding (L = 6), density
/// `trunc_exp(raw − 1)`.
fn proposal_net(vb: candle_nn::VarBuilder) -> Result<Mlp> {
    mlp(
        &MlpConfig {
            hidden: 32,
            depth: 2,
            encoding: PointEncoding::Frequency(FrequencyEncoding::new(3, 6)?),
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
    let mut rng = neural_fields::rng::SplitMix64::new(seed);
    let (mut o, mut d) = (Vec::new(), Vec::new());
    for cam in &unseen {
        let k = cam.intrinsics();
        let u0 = rng.below((k.width.saturating_sub(K) + 1) as u64) as f64;
        let v0 = rng.below((k.height.saturating_sub(K) + 1) as u64) as f64;
        let pixels: Vec<f64> = (0..K * K)
            .flat_map(|p| [u0 + (p % K) as f64 + 0.5, v0 + (p / K) as f64 + 0.5])
            .collect();
        let pixels = Tensor::from_vec(pixels, (K * K, 2), &Device::Cpu)?.to_dtype(DType::F32)?;
        let patch = cam.rays_for_pixels(&pixels)?;
        o.push(patch.origins().clone());
        d.push(patch.directions().clone());
    }
    let n = PATCHES * K * K;
    let rays = Rays::new(Tensor::cat(&o, 0)?, Tensor::cat(&d, 0)?)?;
    let black = Tensor::zeros((n, 3), DType::F32, &Device::Cpu)?;
    let (out, _, _) = r.render(&rays, &black, Some(seed))?;
    let depth = out.normalized_depth(1e-6)?.reshape((PATCHES, K, K))?;
    // RegNeRF's DTU weighting: each pixel by its own opacity, detached, so that pixels of
    // empty space (whose normalised depth means nothing) do not smooth their neighbours.
    let opacity = out.opacity.detach().reshape((PATCHES, K, K))?;
    Ok(depth_smoothness(&depth, Some(&opacity))?.mean_all()?)
}

/// PSNR and SSIM of the first `n` views of `eval` (means), and the renders.
fn evaluate(
    r: &Renderer,
    eval: &Dataset,
    n: usize,
    k: usize,
    filter: PixelFilter,
) -> Result<(f64, f64, Vec<[Tensor; 4]>)> {
    let (mut p, mut s, mut renders) = (0.0, 0.0, Vec::new());
    let n = n.min(eval.len());
    for v in 0..n {
        let truth =
            eval.views()[v].rgb(eval.background().eval_color(), &Device::Cpu, DType::F32)?;
        let (color, depth, opacity) = r.render_view(eval, v, k, filter)?;
        p += psnr(&color, &truth, None)?;
        s += ssim(&color, &truth, None)?;
        renders.push([truth, color, depth, opacity]);
    }
    Ok((p / n as f64, s / n as f64, renders))
}

/// What a run measured: held-out means, and per held-out view `[truth, colour, depth,
/// opacity]`.
#[allow(dead_code)] // read by examples/sparse_views.rs, which includes this file
pub struct Summary {
    pub psnr: f64,
    pub renders: Vec<[Tensor; 4]>,
}

pub fn run(args: &Args) -> Result<Summary> {
    let (device, dtype) = (Device::Cpu, DType::F32);
    let train_config = LoadConfig {
        background: args.background,
        downscale: args.downscale,
        frames: args.frames.clone(),
        ..LoadConfig::default()
    };
    let train = load(&args.data, &train_config)?;
    let (eval, eval_split) = training::load_eval(
        &args.data,
        &LoadConfig {
            downscale: args.downscale,
            ..LoadConfig::default()
        },
    )?;
    training::create_dir(&args.out)?;
    let aabb = training::scene_box(&train, args.aabb);
    let diag =
        ((aabb[3] - aabb[0]).powi(2) + (aabb[4] - aabb[1]).powi(2) + (aabb[5] - aabb[2]).powi(2))
            .sqrt();

    let finest = args
        .hash_finest
        .unwrap_or_else(|| training::hash_finest(&train));
    let mut varmap = VarMap::new();
    let windows = std::cell::RefCell::new(Vec::new());
    let net = build_seeded(&varmap, dtype, &device, args.seed, |vb| {
        let mut config = nerf_config(args, aabb, finest, &vb)?;
        if !args.view_dependence {
            config.direction_encoding = None;
        }
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
    let lr = args.lr.unwrap_or(match args.encoding {
        PositionEncoding::Pe => 1e-3,
        PositionEncoding::Hash => 1e-2,
    });
    let (lr0, lr1) = (lr, lr / 10.0);
    let mut opt = common::adam(&varmap, lr0)?;
    let vars = training::named_vars(&varmap);
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
    let mut sampler = RaySampler::new(&train, args.seed, &device, dtype)?
        .with_pixel_filter(args.pixel_filter, args.jitter)?;
    let train_cameras: Vec<Camera> = train.views().iter().map(|v| *v.camera()).collect();
    let mut clock = training::Clock::start(args.steps, args.minutes);
    println!(
        "training on {} views of {} ({} {}), evaluating on {} {} views; sampler {:?}",
        train.len(),
        args.data.display(),
        train.views()[0].camera().intrinsics().width,
        train.views()[0].camera().intrinsics().height,
        eval.len(),
        eval_split,
        args.sampler
    );
    let mut curve = String::from("step,train_seconds,psnr\n");
    let mut samples_total = 0usize;
    let mut step = 0usize;
    loop {
        // --steps 0 evaluates (e.g. resumed weights) without training.
        let progress = clock.progress(step);
        if progress >= 1.0 {
            break;
        }
        opt.set_learning_rate(log_linear_schedule(
            (progress * 10_000.0) as usize,
            lr0,
            lr1,
            10_000,
        ));
        training::open_windows(&windows, progress, args.coarse_to_fine)?;
        if let Some(grid) = grid.as_mut() {
            grid.update(step, 16, &device, dtype, |p: &Tensor| {
                Ok(net.density(p)?.detach())
            })?;
        }
        let renderer = Renderer {
            net: &net,
            grid: grid.as_ref(),
            proposals: &proposals,
            anneal: args.regnerf.then_some(step),
            aabb,
            step_size: match &grid {
                Some(g) if g.occupied_fraction() > 0.25 => diag / 64.0,
                _ => diag / 256.0,
            },
            samples: args.samples,
            march_jitter: args.march_jitter,
            alpha_threshold: args.alpha_threshold,
            proposal_samples: &args.proposal_samples,
        };
        let k = args.train_supersample;
        let batch = if k > 1 {
            sampler.pixel_footprints(args.rays / (k * k), k)?
        } else {
            sampler.pixels(args.rays)?
        };
        let (out, n, interlevel) = renderer.render(
            &batch.rays,
            &batch.backgrounds,
            Some(args.seed ^ step as u64),
        )?;
        samples_total += n;
        // With k > 1, each pixel's k² rays averaged (a box filter) against the pixel's
        // colour, which every one of its rays carries.
        let (color, target) = if k > 1 {
            let px = batch.len() / (k * k);
            (
                out.color.reshape((px, k * k, 3))?.mean(1)?,
                batch
                    .colors
                    .reshape((px, k * k, 3))?
                    .narrow(1, 0, 1)?
                    .squeeze(1)?,
            )
        } else {
            (out.color, batch.colors.clone())
        };
        let photometric = (color - target)?.sqr()?.mean_all()?;
        let mut loss = (&photometric + interlevel)?;
        if args.regnerf {
            let [w0, w1] = args.regnerf_weight;
            let weight = log_linear_schedule(step, w0, w1, 512);
            let smooth =
                regnerf_depth_smoothness(&renderer, &train_cameras, args.seed ^ step as u64)?;
            loss = (loss + (smooth * weight)?)?;
        }
        training::check_finite(&loss, step, "the loss")?;
        let grads = loss.backward()?;
        training::check_gradients(&grads, &vars, step)?;
        opt.step(&grads)?;
        step += 1;
        let mse = photometric.to_dtype(DType::F64)?.to_scalar::<f64>()?;
        clock.tick(step);
        if step.is_multiple_of(10) {
            clock.bar.set_message(format!(
                "step {step} loss {mse:.5} train PSNR {:.2} samples/ray {:.1}",
                -10.0 * mse.log10(),
                n as f64 / args.rays as f64
            ));
        }
        if step.is_multiple_of(args.eval_every) {
            let seconds = clock.train_seconds();
            let shown = args.eval_views.min(eval.len());
            let p = clock.off_clock(|| -> Result<f64> {
                training::check_weights(&vars, step)?;
                let (p, _, _) = evaluate(
                    &renderer,
                    &eval,
                    args.eval_views,
                    args.eval_supersample,
                    args.pixel_filter,
                )?;
                println!(
                    "step {step}: loss {mse:.5}, held-out PSNR {p:.2} dB ({shown} views), {:.1} samples/ray{}",
                    n as f64 / args.rays as f64,
                    grid.as_ref().map_or(String::new(), |g| format!(", {:.1} % of the grid occupied", 100.0 * g.occupied_fraction()))
                );
                Ok(p)
            })?;
            curve.push_str(&format!("{step},{seconds:.3},{p:.4}\n"));
        }
    }
    let train_seconds = clock.train_seconds();
    clock.bar.finish_and_clear();
    training::open_windows(&windows, 1.0, args.coarse_to_fine)?;
    training::check_weights(&vars, step)?;
    let renderer = Renderer {
        net: &net,
        grid: grid.as_ref(),
        proposals: &proposals,
        anneal: None,
        aabb,
        step_size: diag / 256.0,
        samples: args.samples,
        march_jitter: false,
        alpha_threshold: args.alpha_threshold,
        proposal_samples: &args.proposal_samples,
    };
    if let Some(g) = &grid {
        println!(
            "grid: {:.1} % of the cells occupied",
            100.0 * g.occupied_fraction()
        );
    }
    let (p, s, renders) = evaluate(
        &renderer,
        &eval,
        eval.len(),
        args.eval_supersample,
        args.pixel_filter,
    )?;
    curve.push_str(&format!("{step},{train_seconds:.3},{:.4}\n", {
        let n = args.eval_views.min(renders.len());
        let truth_pred: f64 = renders[..n]
            .iter()
            .map(|r| psnr(&r[1], &r[0], None))
            .sum::<Result<f64>>()?;
        truth_pred / n as f64
    }));
    for (i, [truth, color, depth, opacity]) in renders.iter().enumerate().take(args.pictures) {
        write_png(
            &args.out.join(format!("view_{i}.png")),
            &comparison_strip(truth, color)?,
        )?;
        let (depth_rgb, _) = colorize_depth(depth, None)?;
        write_png(&args.out.join(format!("depth_{i}.png")), &depth_rgb)?;
        write_png(&args.out.join(format!("opacity_{i}.png")), opacity)?;
    }
    varmap.save(args.out.join("weights.safetensors"))?;
    training::write_text(&args.out.join("curve.csv"), &curve)?;
    let metrics = serde_json::json!({
        "psnr": p,
        "ssim": s,
        "train_seconds": train_seconds,
        "steps": step,
        "samples_per_ray": samples_total as f64 / (step.max(1) * args.rays) as f64,
        "sampler": format!("{:?}", args.sampler).to_lowercase(),
        "encoding": args.encoding.name(),
        "eval_split": eval_split,
        "eval_views": eval.len(),
        "eval_supersample": args.eval_supersample,
        "pixel_filter": match args.pixel_filter {
            PixelFilter::Box => "box",
            _ => "cycles",
        },
        "jitter": args.jitter,
        "train_supersample": args.train_supersample,
        "march_jitter": args.march_jitter,
        "coarse_to_fine": args.coarse_to_fine.map(|(s, e)| [s, e]),
        "view_dependence": args.view_dependence,
        "alpha_threshold": args.alpha_threshold,
        "proposal_samples": args.proposal_samples,
        "data": args.data.display().to_string(),
    });
    training::write_json(&args.out.join("metrics.json"), &metrics)?;
    println!(
        "{step} steps in {train_seconds:.1} s: held-out PSNR {p:.2} dB, SSIM {s:.4} over {} {eval_split} views; wrote {}",
        eval.len(),
        args.out.display()
    );
    Ok(Summary { psnr: p, renders })
}

/// The radiance field for `args.encoding`: NeRF's defaults, or instant-NGP's recipe (a hash
/// grid over the scene box `aabb`, whose table is `grid.table` in the weights, on a
/// 1 × 64 trunk; the view-dependent head as NeRF's).
fn nerf_config(args: &Args, aabb: [f64; 6], finest: f64, vb: &VarBuilder) -> Result<NerfConfig> {
    Ok(match args.encoding {
        PositionEncoding::Pe => NerfConfig::default(),
        PositionEncoding::Hash => NerfConfig {
            position_encoding: args.encoding.build(
                10,
                [aabb[0], aabb[1], aabb[2]],
                [aabb[3], aabb[4], aabb[5]],
                args.hash_log2,
                finest,
                vb,
            )?,
            depth: 1,
            skips: vec![],
            ..NerfConfig::default()
        },
    })
}

fn main() -> std::process::ExitCode {
    let args = match parse_args() {
        Ok(a) => a,
        Err(msg) => {
            eprintln!("{msg}");
            return std::process::ExitCode::from(2);
        }
    };
    match run(&args) {
        Ok(_) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("nerf: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let metrics: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap())
                .unwrap();
        for key in ["psnr", "ssim", "train_seconds", "steps", "samples_per_ray"] {
            assert!(
                metrics[key].as_f64().is_some_and(f64::is_finite),
                "{key}: {metrics}"
            );
        }
        assert_eq!(metrics["steps"], 4);
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
        let metrics: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap())
                .unwrap();
        assert_eq!(metrics["alpha_threshold"], 0.0);
        assert_eq!(metrics["coarse_to_fine"], serde_json::json!([0.0, 2.0]));
        assert_eq!(metrics["view_dependence"], false);
        args.coarse_to_fine = None;
        args.view_dependence = true;
        // The hash-grid encoding, with box-filtered training rays and a jittered march.
        args.sampler = Sampler::Grid;
        args.encoding = PositionEncoding::Hash;
        args.train_supersample = 2;
        args.march_jitter = true;
        run(&args).unwrap();
        let metrics: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap())
                .unwrap();
        assert_eq!(metrics["encoding"], "hash");
        assert_eq!(metrics["train_supersample"], 2);
        assert_eq!(metrics["march_jitter"], true);
        // Cycles' pixel filter in training (jittered rays) and in a 3 × 3 evaluation.
        args.train_supersample = 1;
        args.jitter = true;
        args.pixel_filter = PixelFilter::CYCLES;
        args.eval_supersample = 3;
        run(&args).unwrap();
        let metrics: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap())
                .unwrap();
        assert_eq!(metrics["pixel_filter"], "cycles");
        assert!(metrics["psnr"].as_f64().is_some_and(f64::is_finite));
        let _ = std::fs::remove_dir_all(&out);
    }
}
