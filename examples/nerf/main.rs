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
//! rate decaying log-linearly to a tenth of `--lr` (default by encoding and scene, see
//! `--help`); `--encoding hash` (the default in an unbounded scene) puts instant-NGP's
//! hash grid over the scene box on a 1 × 64 trunk; `--encoding ipe` is mip-NeRF: each
//! interval is the conical frustum of its ray's pixel footprint, encoded by the integrated
//! positional encoding ([`Nerf::sample_inputs`]), so one model serves every resolution
//! (train it on `examples/multiscale.rs`'s data).
//!
//! **Samplers** (`--sampler`): `grid` (default in a bounded scene), an [`OccupancyGrid`]
//! (64³ cells) updated every 16 steps, marched at the box diagonal / 64 while more than a
//! quarter of it is occupied in the first tenth of the budget, else / 256, whose sampling
//! lets only the visible samples (transmittance ≥ 1e-4, under the density at the
//! intervals' cones with `--encoding ipe`) through to the whole network; `stratified`,
//! `--samples` jittered samples across
//! the scene box; `proposal`, two proposal networks placing `--proposal-samples`, then
//! `--samples` intervals ([`proposal_sample`], [`interlevel_loss`]), of which only the
//! visible ones with opacity ≥ `--alpha-threshold` (nerfacc's `alpha_thre`) go on.
//!
//! **Scenes** (`--scene`): `object` (default), inside the scene box (`--aabb H` for the
//! cube ±H; else the box the layout states, else the visual hull of the training
//! silhouettes grown by 5 %, else ±1.5: [`Dataset::scene_box`]); `unbounded`, content
//! at every distance (mip-NeRF 360): the training cameras' frame scaled into the unit
//! ball, every network on [`contract`] of it (the hash grid over the contracted ball's
//! cube ±2 unless `--encoding` says otherwise), and either the proposal sampler (the
//! default) spacing samples linearly to 1 and then in disparity to 1e6 ([`Spacing`]),
//! with the distortion loss in that spacing's `s`, or (`--sampler grid`) the occupancy
//! grid with 5 levels doubling the unit cube to ±16, marched with steps growing as
//! `t/256` (cone stepping) and updated from the field at the contracted cell points;
//! `--gradient-scaling on` (default) scales each sample's gradients by `min(1, t²)`
//! (Philip and Deschaintre's remedy for floaters in front of the cameras).
//!
//! **Rays**: `--eval-supersample K` renders `K × K` rays per held-out pixel
//! ([`render_image`]); `--jitter on` trains on random points of the pixels,
//! `--train-supersample K` on the mean of `K × K` rays per pixel, `--march-jitter on` on
//! shifted march lattices (the default with `--encoding hash` in an object scene);
//! `--pixel-filter cycles` makes all three sample Cycles' Blackman–Harris filter
//! ([`PixelFilter::CYCLES`]). **Regularisers**: `--coarse-to-fine START,END` opens the
//! encoding's octaves over that fraction of training ([`CoarseToFine`]),
//! `--view-dependence off` drops the view direction, `--regnerf on` adds RegNeRF's depth
//! smoothness on patches from unseen cameras and its annealed range.
//!
//! **Device**: `--device cuda` trains and evaluates on the first GPU (build with `--features cuda`).
//!
//! **Output** in `--out` (default `target/nerf`): `metrics.json` (`psnr`, `ssim`,
//! `train_seconds` without evaluations, `steps`, `samples_per_ray`, `sampler`, `scene`, `encoding`,
//! `device`, `scene_box`, `eval_split`, `eval_views`, `eval_supersample`, `pixel_filter`, `jitter`,
//! `train_supersample`, `march_jitter`, `adam_eps`, `empty_psnr` (the held-out PSNR of
//! the background alone), `stalled_until` (the last evaluation from step 1000 on whose
//! PSNR was within 5 dB of `empty_psnr` in an object scene, or null), `coarse_to_fine`, `view_dependence`,
//! `alpha_threshold`, `proposal_samples`, `gradient_scaling`, `data`, `psnr_per_scale`: per image size,
//! largest first, `width`, `height`, `views`, `psnr`, `ssim`; and `phase_seconds`: host
//! seconds of training by phase, `grid_update`, `batch`, `sampling`, `loss`, `backward`,
//! `check`, `update`); `curve.csv` (`step,train_seconds,psnr`
//! every `--eval-every` steps on `--eval-views` views, and at the end); `view_{i}.png`
//! (truth | prediction | error), `depth_{i}.png` (turbo, near blue; of the log depth in
//! an unbounded scene), `opacity_{i}.png` for `--pictures`
//! views; `weights.safetensors`, which `--resume` loads. A NaN or infinity in the loss, a
//! gradient or a weight stops the run naming the step and the tensor. Past runs and their
//! commands: docs/benchmarks.md. Uses mimalloc (see `examples/tiny_nerf.rs`).

use candle_core::{DType, Device, Tensor};
use candle_nn::{Optimizer, ParamsAdamW, VarBuilder, VarMap};
use clap::{Parser, ValueEnum};
use neural_fields::camera::{cameras_around, patch_rays, ray_aabb, Camera, PixelFilter, Rays};
use neural_fields::data::{
    colorize_depth, comparison_strip, load, load_eval, psnr, ssim, write_png, Background, Dataset,
    LoadConfig, RaySampler, Split,
};
use neural_fields::encoding::{
    hash_grid, CoarseToFine, FrequencyEncoding, HashGridConfig, PointEncoding,
};
use neural_fields::glam;
use neural_fields::nn::{build_seeded, mlp, Adam, Budget, Clock, FiniteGuard, Mlp, MlpConfig};
use neural_fields::numerics::trunc_exp;
use neural_fields::volume::{
    anneal_near_far, composite, contract, depth_smoothness, distortion_loss, interlevel_loss,
    log_linear_schedule, nerf, proposal_sample, render_image, render_weights, stratified,
    Composite, CompositeConfig, DensityFn, GridConfig, GridMarchConfig, ImageConfig, Intervals,
    Jitter, Layout, Nerf, NerfConfig, OccupancyGrid, ProposalConfig, Spacing, ANNEAL_MID_RATIO,
    ANNEAL_P_START, DEFAULT_TERMINATION_EPS,
};
use neural_fields::{Error, Result};
use std::path::{Path, PathBuf};

#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Rays per chunk when rendering whole views.
const CHUNK: usize = 4096;

mod flags;
mod render;

use flags::*;
use render::*;

/// Opens each window to `bands · clamp((progress − START)/(END − START), 0, 1)`, fully
/// without a span.
fn open_windows(windows: &[CoarseToFine], progress: f64, span: Option<(f64, f64)>) -> Result<()> {
    let open = span.map_or(1.0, |(s, e)| ((progress - s) / (e - s)).clamp(0.0, 1.0));
    for w in windows {
        w.set_alpha(open * w.bands() as f64)?;
    }
    Ok(())
}

/// The mean PSNR and SSIM of the renders `[truth, colour, …]` per image size, largest
/// first: a multiscale dataset's scales.
fn per_scale(renders: &[[Tensor; 4]]) -> Result<Vec<serde_json::Value>> {
    let mut sizes: Vec<(usize, usize)> = Vec::new();
    for [truth, ..] in renders {
        let (h, w, _) = truth.dims3()?;
        if !sizes.contains(&(w, h)) {
            sizes.push((w, h));
        }
    }
    sizes.sort_by_key(|&(w, h)| std::cmp::Reverse(w * h));
    sizes
        .into_iter()
        .map(|(w, h)| {
            let (mut p, mut s, mut n) = (0.0, 0.0, 0usize);
            for [truth, color, _, _] in renders {
                if truth.dims()[..2] == [h, w] {
                    p += psnr(color, truth, None)?;
                    s += ssim(color, truth, None)?;
                    n += 1;
                }
            }
            let n_f = n as f64;
            Ok(serde_json::json!({
                "width": w, "height": h, "views": n, "psnr": p / n_f, "ssim": s / n_f,
            }))
        })
        .collect()
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
    let mut config = match args.encoding() {
        Encoding::Pe => NerfConfig::default(),
        // Octaves 2⁰ … 2¹¹ (no π): the frequency encoding's band (2⁹π ≈ 2¹⁰·⁶) and one
        // more octave, which the cones' variances damp where a pixel is wider.
        Encoding::Ipe => NerfConfig {
            position_encoding: PointEncoding::Integrated {
                dim: 3,
                min_deg: 0,
                max_deg: 12,
            },
            ..NerfConfig::default()
        },
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

/// The fraction of the budget during which a mostly occupied grid is marched coarsely.
const COARSE_MARCH_UNTIL: f64 = 0.1;

/// The training march's step across a box of diagonal `diag`: `diag/64` while more than
/// a quarter of the grid is occupied in the first [`COARSE_MARCH_UNTIL`] of the budget
/// (`progress` in `[0, 1]`; the warm-up's nearly full grid), else `diag/256`. Keyed on
/// the occupied fraction alone, an object that fills a third of its box kept the coarse
/// step (1.7 cells) for the whole run.
fn march_step(diag: f64, occupied: f64, progress: f64) -> f64 {
    if occupied > 0.25 && progress < COARSE_MARCH_UNTIL {
        diag / 64.0
    } else {
        diag / 256.0
    }
}

/// Steps in a row with every training ray's opacity below [`DEAD_OPACITY`] that end a
/// run as dead.
const DEAD_STEPS: usize = 100;
const DEAD_OPACITY: f64 = 1e-3;

/// Steps after which, in an object scene, a held-out PSNR within [`STALL_DB`] of an
/// empty scene's is reported as a stalled run (a warning and metrics.json's
/// `stalled_until`). A stalled hash-grid run rendered the plate's silhouette in one
/// uniform colour for 15 000 steps, 3.1 dB above the empty scene; at step 1 000 the
/// healthy hash runs of the scene suite are 15.3 to 22.6 dB above it.
const STALL_STEPS: usize = 1000;
const STALL_DB: f64 = 5.0;

/// The warning of a run whose held-out PSNR at `step` is still within [`STALL_DB`] of an
/// empty scene's.
fn stall_warning(step: usize, psnr: f64, empty: f64, args: &Args) -> String {
    format!(
        "warning: after {step} steps the held-out PSNR ({psnr:.2} dB) is within {STALL_DB} dB \
         of an empty scene's ({empty:.2} dB): the field has not learned the scene; likely \
         causes: Adam's epsilon (--adam-eps {:e}; 1e-15 suits hash grids), the learning rate \
         (--lr {}), the scene box (--aabb {:?})",
        args.adam_eps(),
        args.learning_rate(),
        args.aabb
    )
}

/// Host seconds of the training steps by phase, summed over the run (evaluations
/// excluded). On a GPU the host runs ahead of the device until a read-back, so a phase's
/// time includes the device work that its read-backs waited for.
#[derive(Default)]
struct Phases {
    grid_update: f64,
    batch: f64,
    sampling: f64,
    loss: f64,
    backward: f64,
    check: f64,
    update: f64,
}

impl Phases {
    fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "grid_update": self.grid_update, "batch": self.batch, "sampling": self.sampling,
            "loss": self.loss, "backward": self.backward, "check": self.check,
            "update": self.update,
        })
    }
}

/// A stopwatch that adds the time since its last mark to a phase.
struct Lap(std::time::Instant);

impl Lap {
    fn start() -> Self {
        Lap(std::time::Instant::now())
    }

    fn mark(&mut self, phase: &mut f64) {
        let now = std::time::Instant::now();
        *phase += (now - self.0).as_secs_f64();
        self.0 = now;
    }
}

/// The error of a run whose density collapsed: the steps, and the likely causes.
fn dead_run(since: usize, step: usize, args: &Args) -> Error {
    Error::InvalidArgument {
        arg: "training",
        expected: format!("some opacity on the training rays within {DEAD_STEPS} steps"),
        got: format!(
            "every ray's opacity below {DEAD_OPACITY} from step {since} to {step}: the density \
             collapsed to zero (a learning rate too high for this scene, --lr {}), or the \
             scene box misses the scene (--aabb {:?})",
            args.learning_rate(),
            args.aabb
        ),
    }
}

/// The `lo` and `hi` quantiles of the finite values of `x`, when they differ.
fn percentiles(x: &Tensor, lo: f64, hi: f64) -> Result<Option<(f64, f64)>> {
    let mut v: Vec<f64> = x
        .flatten_all()?
        .to_dtype(DType::F64)?
        .to_vec1::<f64>()?
        .into_iter()
        .filter(|v| v.is_finite())
        .collect();
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    Ok((!v.is_empty() && at(lo) < at(hi)).then(|| (at(lo), at(hi))))
}

fn run(args: &Args) -> Result<()> {
    let budget = args.budget()?;
    let (device, dtype) = (args.device()?, DType::F32);
    let background = match args.background {
        BackgroundFlag::Random => Background::Random,
        BackgroundFlag::White => Background::Color([1.0; 3]),
        BackgroundFlag::Black => Background::Color([0.0; 3]),
    };
    let train_config = LoadConfig {
        background,
        downscale: args.downscale,
        allow_outside_paths: args.allow_outside_paths,
        frames: args.frames.clone(),
        ..LoadConfig::default()
    };
    let train = load(&args.data, &train_config)?;
    if train.coverage() == Some(0.0) {
        return Err(Error::InvalidArgument {
            arg: "data",
            expected: "training views with some foreground (alpha or mask ≥ ½)".into(),
            got: format!(
                "{} views whose every pixel is transparent",
                train.views().len()
            ),
        });
    }
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
    // An unbounded scene: the networks live in the contracted frame of the training
    // cameras (radius < 2); the proposal sampler spaces samples to far away, the grid's
    // levels double the unit cube out to UNBOUNDED_GRID_LEVELS.
    let unbounded = (args.scene == Scene::Unbounded).then(|| {
        let cameras: Vec<Camera> = train.views().iter().map(|v| *v.camera()).collect();
        SceneFrame::from_cameras(&cameras)
    });
    let sampler_kind = args.sampler();
    let aabb = match (unbounded, args.aabb) {
        (Some(_), _) => [-2.0, -2.0, -2.0, 2.0, 2.0, 2.0],
        (None, Some(half)) => [-half, -half, -half, half, half, half],
        (None, None) => train.scene_box(1.5),
    };
    // The grid's finest level: the scene box, or in an unbounded scene the frame's unit
    // cube (the cameras' ball).
    let (grid_box, grid_levels) = match unbounded {
        Some(_) => ([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], UNBOUNDED_GRID_LEVELS),
        None => (aabb, 1),
    };
    let diag = (0..3)
        .map(|a| (grid_box[a + 3] - grid_box[a]).powi(2))
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
    let proposals = match sampler_kind {
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
    let lr0 = args.learning_rate();
    let mut opt = Adam::new(
        varmap.all_vars(),
        ParamsAdamW {
            lr: lr0,
            weight_decay: 0.0,
            eps: args.adam_eps(),
            ..ParamsAdamW::default()
        },
    )?;
    let guard = FiniteGuard::new(&varmap);
    let mut grid = match sampler_kind {
        Sampler::Grid => Some(OccupancyGrid::new(GridConfig {
            aabb: grid_box,
            levels: grid_levels,
            resolution: GRID_RESOLUTION,
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
        sampler_kind
    );
    let empty = empty_psnr(&eval, args.eval_views)?;
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
        unbounded,
        args,
        device: &device,
    };
    let mut curve = String::from("step,train_seconds,psnr\n");
    let (mut samples_total, mut step) = (0usize, 0usize);
    // The grid's occupied fraction as of its last update (no grid: nothing occupied).
    let mut occupied_now = 0.0;
    let mut dead_since = None;
    let mut stalled_until = None;
    let mut phases = Phases::default();
    loop {
        // --steps 0 evaluates (e.g. resumed weights) without training.
        let progress = clock.progress(step);
        if progress >= 1.0 {
            break;
        }
        let t = (progress * 10_000.0) as usize;
        opt.set_learning_rate(log_linear_schedule(t, lr0, lr0 / 10.0, 10_000));
        open_windows(&windows, progress, args.coarse_to_fine)?;
        let mut lap = Lap::start();
        if let Some(grid) = grid.as_mut() {
            let updated = grid.update(step, 16, &device, dtype, |p: &Tensor| {
                Ok(base.grid_density(p)?.detach())
            })?;
            if updated {
                occupied_now = occupied(grid);
            }
        }
        lap.mark(&mut phases.grid_update);
        let step_size = march_step(diag, occupied_now, progress);
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
        lap.mark(&mut phases.batch);
        let seed = args.seed ^ step as u64;
        let samples = r.samples(&batch.rays, Some(seed))?;
        lap.mark(&mut phases.sampling);
        // The photometric loss, the largest opacity of a training ray and the samples
        // evaluated: through `Nerf::color_loss` (fused where it can be) for one ray per
        // pixel in a bounded scene without proposals, else composited here.
        let (photometric, interlevel, peak, n) = if k == 1 && r.plain() {
            let n = samples.intervals.starts.elem_count();
            let config = CompositeConfig {
                background: Some(batch.backgrounds.clone()),
                ..CompositeConfig::default()
            };
            let out = net.color_loss(&samples.rays, &samples.intervals, &batch.colors, &config)?;
            (out.loss, None, out.opacity_max, n)
        } else {
            let (out, n, interlevel) = r.render_samples(samples, &batch.backgrounds)?;
            let peak = out
                .opacity
                .max_all()?
                .to_dtype(DType::F64)?
                .to_scalar::<f64>()?;
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
            (photometric, Some(interlevel), peak, n)
        };
        samples_total += n;
        // A dead run: no training ray has any opacity for DEAD_STEPS steps in a row.
        let since = *dead_since.get_or_insert(step);
        if peak >= DEAD_OPACITY {
            dead_since = None;
        } else if step + 1 - since >= DEAD_STEPS {
            return Err(dead_run(since, step, args));
        }
        let mut loss = match interlevel {
            Some(extra) => (&photometric + extra)?,
            None => photometric.clone(),
        };
        if args.regnerf {
            let weight =
                log_linear_schedule(step, args.regnerf_weight[0], args.regnerf_weight[1], 512);
            let smooth = regnerf_depth_smoothness(&r, &train_cameras, seed)?;
            loss = (loss + (smooth * weight)?)?;
        }
        lap.mark(&mut phases.loss);
        let grads = loss.backward()?;
        lap.mark(&mut phases.backward);
        guard.check(step, &loss, Some(&grads))?;
        lap.mark(&mut phases.check);
        opt.step(&grads)?;
        lap.mark(&mut phases.update);
        step += 1;
        // Read back only when shown (on a GPU each read-back waits for the device).
        let mse = || -> Result<f64> { Ok(photometric.to_dtype(DType::F64)?.to_scalar::<f64>()?) };
        bar.set_position(match budget {
            Budget::Steps(_) => step as u64,
            Budget::Minutes(_) => clock.train_seconds() as u64,
        });
        let per_ray = n as f64 / args.rays as f64;
        if step.is_multiple_of(10) {
            let mse = mse()?;
            let p = -10.0 * mse.log10();
            bar.set_message(format!(
                "step {step} loss {mse:.5} train PSNR {p:.2} samples/ray {per_ray:.1}"
            ));
        }
        if step.is_multiple_of(args.eval_every) {
            let seconds = clock.train_seconds();
            let mse = mse()?;
            let shown = args.eval_views.min(eval.views().len());
            let p = clock.pause(|| {
                bar.suspend(|| -> Result<f64> {
                    let (p, _, _) = evaluate(&r, &eval, args.eval_views)?;
                    let grid_note = grid.as_ref().map_or(String::new(), |g| {
                        format!(", {:.1} % of the grid occupied", 100.0 * occupied(g))
                    });
                    println!("step {step}: loss {mse:.5}, held-out PSNR {p:.2} dB ({shown} views), {per_ray:.1} samples/ray{grid_note}");
                    if args.scene == Scene::Object && step >= STALL_STEPS && p < empty + STALL_DB {
                        if stalled_until.is_none() {
                            eprintln!("{}", stall_warning(step, p, empty, args));
                        }
                        stalled_until = Some(step);
                    }
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
        // Unbounded: the log of the depth between its 2nd and 98th percentiles (it runs
        // from the ground at the cameras' feet to the sky).
        let (mapped, range) = match unbounded {
            Some(_) => {
                let log = depth.log()?;
                let range = percentiles(&log, 0.02, 0.98)?;
                (log, range)
            }
            None => (depth.clone(), None),
        };
        write_png(
            &args.out.join(format!("depth_{i}.png")),
            &colorize_depth(&mapped, range)?.0,
        )?;
        write_png(&args.out.join(format!("opacity_{i}.png")), opacity)?;
    }
    let per_scale = per_scale(&renders)?;
    varmap.save(args.out.join("weights.safetensors"))?;
    write(&args.out.join("curve.csv"), &curve)?;
    let metrics = serde_json::json!({
        "psnr": p,
        "ssim": s,
        "train_seconds": train_seconds,
        "steps": step,
        "samples_per_ray": samples_total as f64 / (step.max(1) * args.rays) as f64,
        "sampler": format!("{:?}", sampler_kind).to_lowercase(),
        "scene": format!("{:?}", args.scene).to_lowercase(),
        "encoding": format!("{:?}", args.encoding()).to_lowercase(),
        "device": format!("{:?}", args.device).to_lowercase(),
        "scene_box": aabb,
        "eval_split": eval_split,
        "eval_views": eval.views().len(),
        "eval_supersample": args.eval_supersample,
        "pixel_filter": format!("{:?}", args.pixel_filter).to_lowercase(),
        "jitter": args.jitter,
        "train_supersample": args.train_supersample,
        "march_jitter": args.march_jitter(),
        "adam_eps": args.adam_eps(),
        "empty_psnr": empty,
        "stalled_until": stalled_until,
        "coarse_to_fine": args.coarse_to_fine.map(|(s, e)| [s, e]),
        "view_dependence": args.view_dependence,
        "alpha_threshold": args.alpha_threshold,
        "proposal_samples": args.proposal_samples,
        "gradient_scaling": args.gradient_scaling,
        "data": args.data.display().to_string(),
        "psnr_per_scale": per_scale,
        "phase_seconds": phases.json(),
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
    println!("training host seconds by phase: {}", phases.json());
    if per_scale.len() > 1 {
        for scale in &per_scale {
            println!(
                "  {} × {}: PSNR {:.2} dB, SSIM {:.4} over {} views",
                scale["width"],
                scale["height"],
                scale["psnr"].as_f64().unwrap_or(f64::NAN),
                scale["ssim"].as_f64().unwrap_or(f64::NAN),
                scale["views"]
            );
        }
    }
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
mod tests;
