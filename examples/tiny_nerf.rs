//! A tiny NeRF: learn a radiance field from 16 views of an analytic scene, twice: with
//! stratified samples along every ray, and with the occupancy grid skipping empty space.
//!
//! ```text
//! cargo run --release --example tiny_nerf            # writes target/tiny_nerf/tiny_nerf.png
//! cargo run --release --example tiny_nerf -- --out DIR
//! ```
//!
//! The scene is a fuzzy ball (density σ(p) = 8·(1 − |p|²/r²)², r = 0.6) whose colour
//! varies in space, inside the unit sphere. Its 40 × 40 ground-truth views (cameras on a
//! sphere of radius 3, one view held out) are rendered with this crate's compositing at
//! 1024 samples per ray (error far below what training reaches). The model is the
//! NeRF recipe at small scale: a 4 × 64 ReLU MLP on a frequency encoding (L = 6) with
//! four outputs, density `trunc_exp(raw₀ − 1)` and colour `sigmoid(raw₁…₃)`; each step
//! renders 1024 random rays from 4 training views and minimises the mean squared colour
//! error with Adam.
//!
//! The two runs differ only in where the samples come from:
//! - **stratified**: 48 jittered samples per ray between the ray's entry and exit of the
//!   unit sphere ([`stratified`]), composited in the batched layout ([`composite`]);
//! - **grid**: an [`OccupancyGrid`] (32³ cells over [−1, 1]³) updated from the network's
//!   density every 8 steps; rays are marched with the same step length (2/48) and keep
//!   only intervals in occupied cells ([`OccupancyGrid::sample`]), composited in the
//!   packed layout (the same [`composite`]). After warm-up it evaluates a fraction of the
//!   samples.
//!
//! Prints the held-out PSNR against training time (held-out renders left out) for both,
//! and writes the held-out view as `reference | stratified | grid` to `OUT/tiny_nerf.png`
//! (`--out`, default `target/tiny_nerf`). Held-out views are rendered with
//! [`render_image`]. About 85 s on 2 cores (`docs/tiny_nerf.png` is its output).
//!
//! The example uses mimalloc as its global allocator. candle allocates fresh tensors for
//! every op of every step; with glibc's default malloc, blocks of this size go back to
//! the kernel when freed and fault back in on the next step, which made this example
//! about 3× slower (most of its time in the kernel). A training binary of your own should
//! do the same, or set `GLIBC_TUNABLES` as docs/benchmarks.md describes.

use candle_core::{DType, Device, Tensor};
use candle_nn::{Optimizer, VarMap};
use clap::Parser;
use neural_fields::camera::{ray_sphere, Camera, Convention, Intrinsics, Rays};
use neural_fields::data::{psnr, write_png};
use neural_fields::encoding::{FrequencyEncoding, PointEncoding};
use neural_fields::field::Field;
use neural_fields::glam::DVec3;
use neural_fields::nn::{adam, build_seeded, mlp, Activation, Mlp, MlpConfig};
use neural_fields::numerics::trunc_exp;
use neural_fields::rng::SplitMix64;
use neural_fields::volume::{
    composite, render_image, stratified, Composite, CompositeConfig, GridConfig, GridMarchConfig,
    ImageConfig, Jitter, OccupancyGrid,
};
use neural_fields::Result;
use std::path::PathBuf;
use std::time::Instant;

// candle allocates fresh tensors every step; see the module docs.
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// The command line.
#[derive(Parser, Debug)]
#[command(about = "A tiny NeRF, with stratified samples and with the occupancy grid")]
struct Args {
    /// Where the picture goes.
    #[arg(long, default_value = "target/tiny_nerf")]
    out: PathBuf,
}

const SIDE: usize = 40;
const VIEWS: usize = 17;
const HELD_OUT: usize = 0;
const RAYS_PER_VIEW: usize = 256;
const VIEWS_PER_STEP: usize = 4;
const SAMPLES: usize = 48;
const STEPS: usize = 300;
const EVAL_EVERY: usize = 50;
/// Grid updates every this many steps (grid run).
const GRID_EVERY: usize = 8;
const BALL_R: f64 = 0.6;
const BALL_D: f64 = 8.0;
/// The grid march's step in t: the unit sphere's diameter over `SAMPLES`, so that both
/// runs place samples equally densely.
const GRID_STEP: f64 = 2.0 / SAMPLES as f64;
/// Rays per chunk when rendering a whole view (bounds the memory of one forward pass).
const CHUNK: usize = 400;

/// The scene's density σ(p) = D·(1 − |p|²/r²)² inside the ball, 0 outside: `[N, 3]` →
/// `[N]`.
fn scene_sigma(p: &Tensor) -> Result<Tensor> {
    let u = p
        .sqr()?
        .sum(1)?
        .affine(-1.0 / (BALL_R * BALL_R), 1.0)?
        .relu()?;
    Ok((u.sqr()? * BALL_D)?)
}

/// The scene's colour c(p) = 0.5 + 0.45·sin(8p + φ) per channel, φ = (0, 2, 4):
/// `[N, 3]` → `[N, 3]`.
fn scene_rgb(p: &Tensor) -> Result<Tensor> {
    let phase = Tensor::new(&[0.0f64, 2.0, 4.0], p.device())?.to_dtype(p.dtype())?;
    Ok(((p * 8.0)?.broadcast_add(&phase)?.sin()? * 0.45)?.affine(1.0, 0.5)?)
}

/// The model's density `[N]` and colour `[N, 3]` at `points: [N, 3]`.
fn radiance(net: &Mlp, points: &Tensor) -> Result<(Tensor, Tensor)> {
    let raw = Field::forward(net, points)?;
    let sigma = trunc_exp(&raw.narrow(1, 0, 1)?.squeeze(1)?.affine(1.0, -1.0)?)?;
    let rgb = candle_nn::ops::sigmoid(&raw.narrow(1, 1, 3)?)?;
    Ok((sigma, rgb))
}

/// Renders `rays` with `n` samples per ray between the entry and exit of the unit sphere
/// (rays that miss it get the black background): stratified intervals (jittered with
/// `seed` when given), the density and colour of `field` at the midpoints, batched
/// compositing.
/// `n` rays through pixel centres drawn uniformly with replacement from `rng`, and their
/// linear pixel indices `v · width + u` as a `[n]` u32 tensor.
fn random_rays(
    camera: &Camera,
    n: usize,
    rng: &mut SplitMix64,
    device: &Device,
    dtype: DType,
) -> Result<(Rays, Tensor)> {
    let w = camera.intrinsics().width;
    let total = (w * camera.intrinsics().height) as u64;
    let idx: Vec<u32> = (0..n).map(|_| rng.below(total) as u32).collect();
    let pixels: Vec<f64> = idx
        .iter()
        .flat_map(|&i| [(i as usize % w) as f64 + 0.5, (i as usize / w) as f64 + 0.5])
        .collect();
    let pixels = Tensor::from_vec(pixels, (n, 2), device)?.to_dtype(dtype)?;
    Ok((
        camera.rays_for_pixels(&pixels)?,
        Tensor::from_vec(idx, n, device)?,
    ))
}

fn render_stratified(
    rays: &Rays,
    n: usize,
    seed: Option<u64>,
    field: impl Fn(&Tensor) -> Result<(Tensor, Tensor)>,
) -> Result<Composite> {
    let bounds = ray_sphere(rays, [0.0; 3], 1.0)?;
    let jitter = if seed.is_some() {
        Jitter::PerSample
    } else {
        Jitter::None
    };
    let iv = stratified(&bounds.near, &bounds.far, n, jitter, seed.unwrap_or(0))?;
    let r = rays.len();
    // Sample positions o + t·d at the midpoints: [R, n, 3] → [R·n, 3].
    let pos = iv.positions(rays)?.reshape((r * n, 3))?;
    let (sigma, rgb) = field(&pos)?;
    composite(
        &sigma.reshape((r, n))?,
        &rgb.reshape((r, n, 3))?,
        &iv,
        Some(rays),
        &CompositeConfig::default(),
    )
}

/// Renders `rays` through `grid`: a fixed-step march (2/48 in t) that keeps intervals in
/// occupied cells, the network at their midpoints, packed compositing. Also returns the
/// number of samples evaluated. (No density function: the fuzzy ball hides nothing
/// behind it, its transmittance never falls below 6e-3, so a density pass to drop
/// hidden samples would cost without saving.)
fn render_grid(rays: &Rays, grid: &OccupancyGrid, net: &Mlp) -> Result<(Composite, usize)> {
    let march = GridMarchConfig {
        step_size: GRID_STEP,
        ..GridMarchConfig::default()
    };
    let iv = grid.sample(rays, &march, None)?.intervals;
    let m = iv.starts.dims1()?;
    let (sigma, rgb) = radiance(net, &iv.positions(rays)?)?;
    let out = composite(&sigma, &rgb, &iv, Some(rays), &CompositeConfig::default())?;
    Ok((out, m))
}

/// The share of the grid's cells that are occupied, in percent.
fn occupied_percent(grid: &OccupancyGrid) -> f64 {
    let occupied = grid.occupied();
    100.0 * occupied.iter().filter(|&&o| o).count() as f64 / occupied.len() as f64
}

/// How samples are placed in a training run.
#[derive(Clone, Copy, PartialEq)]
enum Mode {
    Stratified,
    Grid,
}

/// Renders the held-out view in chunks: colour `[SIDE², 3]` and samples evaluated.
fn render_view(
    camera: &Camera,
    mode: Mode,
    net: &Mlp,
    grid: &OccupancyGrid,
) -> Result<(Tensor, usize)> {
    let config = ImageConfig {
        chunk: CHUNK,
        ..ImageConfig::default()
    };
    let mut evaluated = 0;
    let [color] = render_image(camera, &config, &Device::Cpu, DType::F32, |rays| {
        let (out, m) = match mode {
            Mode::Stratified => {
                let out = render_stratified(rays, SAMPLES, None, |p| radiance(net, p))?;
                (out, rays.len() * SAMPLES)
            }
            Mode::Grid => render_grid(rays, grid, net)?,
        };
        evaluated += m;
        Ok([out.color])
    })?;
    Ok((color.reshape((SIDE * SIDE, 3))?, evaluated))
}

/// One training run; returns the held-out rendering.
fn train(
    mode: Mode,
    cameras: &[Camera],
    images: &[Tensor],
    device: &Device,
    dtype: DType,
) -> Result<Tensor> {
    let config = MlpConfig {
        out_dim: 4,
        hidden: 64,
        depth: 4,
        activation: Activation::Relu,
        encoding: PointEncoding::Frequency(FrequencyEncoding::new(3, 6)?),
        ..MlpConfig::default()
    };
    let varmap = VarMap::new();
    let net = build_seeded(&varmap, dtype, device, 0, |vb| mlp(&config, vb))?;
    let mut opt = adam(&varmap, 5e-3)?;
    // The grid's default decay (0.8 per update) suits runs of thousands of steps; this
    // one is a few hundred, so the grid forgets faster and updates more often.
    let mut grid = OccupancyGrid::new(GridConfig {
        aabb: [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0],
        resolution: 32,
        levels: 1,
        decay: 0.6,
        ..GridConfig::default()
    })?;
    let mut rng = SplitMix64::new(7);
    let name = match mode {
        Mode::Stratified => "stratified",
        Mode::Grid => "grid",
    };
    let start = Instant::now();
    // Wall time spent rendering the held-out view, left out of the training time.
    let mut eval_secs = 0.0;
    let mut evaluated_total = 0usize;
    for step in 0..=STEPS {
        if mode == Mode::Grid {
            // The grid sees the network's density, detached (no graph is built).
            grid.update(step, GRID_EVERY, device, dtype, |p: &Tensor| {
                Ok(radiance(&net, p)?.0.detach())
            })?;
        }
        // A batch: RAYS_PER_VIEW random pixels of each of VIEWS_PER_STEP training views.
        let (mut os, mut ds, mut targets) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..VIEWS_PER_STEP {
            let v = 1 + rng.below((VIEWS - 1) as u64) as usize;
            let (rays, idx) = random_rays(&cameras[v], RAYS_PER_VIEW, &mut rng, device, dtype)?;
            os.push(rays.origins().clone());
            ds.push(rays.directions().clone());
            targets.push(images[v].index_select(&idx, 0)?);
        }
        let rays = Rays::new(Tensor::cat(&os, 0)?, Tensor::cat(&ds, 0)?)?;
        let target = Tensor::cat(&targets, 0)?;
        let (out, evaluated) = match mode {
            Mode::Stratified => (
                render_stratified(&rays, SAMPLES, Some(rng.next_u64()), |p| radiance(&net, p))?,
                rays.len() * SAMPLES,
            ),
            Mode::Grid => render_grid(&rays, &grid, &net)?,
        };
        evaluated_total += evaluated;
        let loss = (out.color - &target)?.sqr()?.mean_all()?;
        opt.backward_step(&loss)?;
        if step % EVAL_EVERY == 0 {
            let train_time = start.elapsed().as_secs_f64() - eval_secs;
            let clock = Instant::now();
            let (image, _) = render_view(&cameras[HELD_OUT], mode, &net, &grid)?;
            eval_secs += clock.elapsed().as_secs_f64();
            println!(
                "{name:>10} {step:>5} {:>10.5} {:>8.2} {:>9.1} {:>9.1} {:>8.1}",
                loss.to_dtype(DType::F64)?.to_scalar::<f64>()?,
                psnr(&image, &images[HELD_OUT], None)?,
                evaluated as f64 / rays.len() as f64,
                occupied_percent(&grid),
                train_time,
            );
        }
    }
    let (image, evaluated) = render_view(&cameras[HELD_OUT], mode, &net, &grid)?;
    println!(
        "{name}: held-out PSNR {:.2} dB after {STEPS} steps in {:.1} s of training; {:.1} \
         samples per ray evaluated in training on average, {:.1} to render the held-out view",
        psnr(&image, &images[HELD_OUT], None)?,
        start.elapsed().as_secs_f64() - eval_secs,
        evaluated_total as f64 / ((STEPS + 1) * VIEWS_PER_STEP * RAYS_PER_VIEW) as f64,
        evaluated as f64 / (SIDE * SIDE) as f64,
    );
    if mode == Mode::Grid {
        println!(
            "grid: {:.1} % of its cells occupied",
            occupied_percent(&grid)
        );
    }
    Ok(image)
}

fn main() -> Result<()> {
    let args = Args::parse();
    let device = Device::Cpu;
    let dtype = DType::F32;
    std::fs::create_dir_all(&args.out).map_err(|source| neural_fields::Error::Io {
        path: args.out.display().to_string(),
        source,
    })?;
    let path = args.out.join("tiny_nerf.png");

    // Cameras on a sphere of radius 3 looking at the origin (a golden-angle spiral).
    let cameras = (0..VIEWS)
        .map(|i| {
            let z = 0.8 - 1.6 * (i as f64 + 0.5) / VIEWS as f64;
            let phi = i as f64 * 2.399_963;
            let rxy = (1.0 - z * z).sqrt();
            let eye = 3.0 * DVec3::new(rxy * phi.cos(), rxy * phi.sin(), z);
            let k = Intrinsics::from_fov_y(SIDE, SIDE, 0.55)?;
            Camera::look_at(k, eye, DVec3::ZERO, DVec3::Z, Convention::OpenGl)
        })
        .collect::<Result<Vec<_>>>()?;
    let t = Instant::now();
    let images = cameras
        .iter()
        .map(|cam| {
            let rays = cam.rays(&device, DType::F64)?;
            let field = |p: &Tensor| Ok((scene_sigma(p)?, scene_rgb(p)?));
            let img = render_stratified(&rays, 1024, None, field)?.color;
            Ok(img.to_dtype(dtype)?)
        })
        .collect::<Result<Vec<_>>>()?;
    println!(
        "{VIEWS} ground-truth views of {SIDE}x{SIDE} rendered in {:.1} s (view {HELD_OUT} held out)",
        t.elapsed().as_secs_f64()
    );
    println!(
        "{:>10} {:>5} {:>10} {:>8} {:>9} {:>9} {:>8}",
        "run", "step", "train mse", "PSNR/dB", "samples", "occupied%", "time/s"
    );
    let strat = train(Mode::Stratified, &cameras, &images, &device, dtype)?;
    let grid = train(Mode::Grid, &cameras, &images, &device, dtype)?;
    write_panels(&path, &[&images[HELD_OUT], &strat, &grid])?;
    println!(
        "wrote {} (held-out view: reference | stratified | grid)",
        path.display()
    );
    Ok(())
}

/// Writes `SIDE × SIDE` RGB images (`[SIDE², 3]` in [0, 1]) side by side, each pixel
/// scaled up 4×, to an 8-bit PNG.
fn write_panels(path: &std::path::Path, panels: &[&Tensor]) -> Result<()> {
    const UP: usize = 4;
    let images = panels
        .iter()
        .map(|t| {
            // [SIDE², 3] → [1, 3, SIDE, SIDE] for candle's nearest upsampling, and back.
            let chw = t
                .reshape((SIDE, SIDE, 3))?
                .permute((2, 0, 1))?
                .unsqueeze(0)?;
            let up = chw.upsample_nearest2d(SIDE * UP, SIDE * UP)?;
            Ok(up.squeeze(0)?.permute((1, 2, 0))?)
        })
        .collect::<Result<Vec<Tensor>>>()?;
    write_png(path, &Tensor::cat(&images, 1)?)
}
