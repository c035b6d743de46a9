//! The nerf example's command line: its flags, their parsers and the checks clap cannot
//! state.

use super::*;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(super) enum Sampler {
    Grid,
    Stratified,
    Proposal,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(super) enum Encoding {
    Pe,
    Hash,
    /// mip-NeRF: the integrated encoding of each interval's conical frustum.
    Ipe,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(super) enum Scene {
    /// An object inside the scene box.
    Object,
    /// Content at every distance (a 360° capture): contraction, and the proposal
    /// sampler (disparity spacing, distortion loss) or the occupancy grid (cascaded
    /// levels, cone stepping).
    Unbounded,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(super) enum BackgroundFlag {
    Random,
    White,
    Black,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(super) enum DeviceFlag {
    Cpu,
    Cuda,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(super) enum Filter {
    Box,
    Cycles,
}

/// The command line (see the module docs).
#[derive(Parser, Debug, Clone)]
#[command(about = "Train a NeRF on a dataset folder and evaluate it on the held-out views")]
pub(super) struct Args {
    /// Dataset folder (Blender synthetic, nerfstudio or IDR/DTU layout).
    #[arg(long, default_value = "examples/data/wuson")]
    pub(super) data: PathBuf,
    /// Minutes of training (default 10 unless --steps is given).
    #[arg(long, conflicts_with = "steps")]
    pub(super) minutes: Option<f64>,
    /// Optimiser steps.
    #[arg(long)]
    pub(super) steps: Option<usize>,
    /// Output folder.
    #[arg(long, default_value = "target/nerf")]
    pub(super) out: PathBuf,
    #[arg(long, default_value_t = 0)]
    pub(super) seed: u64,
    /// Where to train and evaluate: `cpu`, or `cuda` (the first GPU; build with `--features cuda`).
    #[arg(long, value_enum, default_value = "cpu")]
    pub(super) device: DeviceFlag,
    /// The sampler: `grid` (the default for `--scene object`), `stratified` (bounded
    /// scenes only) or `proposal` (the default for `--scene unbounded`).
    #[arg(long, value_enum)]
    pub(super) sampler: Option<Sampler>,
    /// `object` (in the scene box) or `unbounded` (contracted space).
    #[arg(long, value_enum, default_value = "object")]
    pub(super) scene: Scene,
    /// Divide the images' resolution by this.
    #[arg(long, default_value_t = 1)]
    pub(super) downscale: usize,
    /// Rays per step.
    #[arg(long, default_value_t = 1024)]
    pub(super) rays: usize,
    /// Samples per ray (stratified and proposal samplers).
    #[arg(long, default_value_t = 64)]
    pub(super) samples: usize,
    /// Half-side of the scene cube. Without it: the box the layout states, else the
    /// visual hull of the training silhouettes grown by 5 % (`Dataset::scene_box`),
    /// else ±1.5.
    #[arg(long)]
    pub(super) aabb: Option<f64>,
    #[arg(long, default_value_t = 250)]
    pub(super) eval_every: usize,
    /// Held-out views evaluated during training.
    #[arg(long, default_value_t = 4)]
    pub(super) eval_views: usize,
    /// Rays per pixel side in evaluation, 1 to 8.
    #[arg(long, default_value_t = 1)]
    pub(super) eval_supersample: usize,
    #[arg(long, value_parser = on_off, action = clap::ArgAction::Set, default_value = "off")]
    pub(super) jitter: bool,
    /// Rays per pixel side in training, 1 to 8.
    #[arg(long, default_value_t = 1)]
    pub(super) train_supersample: usize,
    /// Shift each training ray's march lattice at random every step (default: on with
    /// `--encoding hash` in an object scene, off otherwise).
    #[arg(long, value_parser = on_off, action = clap::ArgAction::Set)]
    pub(super) march_jitter: Option<bool>,
    #[arg(long, value_enum, default_value = "box")]
    pub(super) pixel_filter: Filter,
    /// Held-out views written as pictures.
    #[arg(long, default_value_t = 8)]
    pub(super) pictures: usize,
    /// Weights to start from (a previous run's weights.safetensors).
    #[arg(long)]
    pub(super) resume: Option<PathBuf>,
    /// Learning rate, in (0, 0.1] (default 5e-3; 1e-2 with --encoding hash, 1e-3 with ipe
    /// and with pe in an unbounded scene).
    #[arg(long, value_parser = learning_rate)]
    pub(super) lr: Option<f64>,
    /// Adam's ε, in (0, 1e-4] (default 1e-15 with `--encoding hash` in an object scene,
    /// 1e-8 otherwise).
    #[arg(long, value_parser = adam_eps)]
    pub(super) adam_eps: Option<f64>,
    /// The position encoding: `pe` (the default for `--scene object`), `hash` (the
    /// default for `--scene unbounded`) or `ipe`.
    #[arg(long, value_enum)]
    pub(super) encoding: Option<Encoding>,
    #[arg(long, default_value_t = HashGridConfig::default().log2_table_size)]
    pub(super) hash_log2: u32,
    #[arg(long)]
    pub(super) hash_finest: Option<f64>,
    #[arg(long, value_enum, default_value = "random")]
    pub(super) background: BackgroundFlag,
    /// Training views, e.g. 0,17,34 (default: all).
    #[arg(long, value_delimiter = ',')]
    pub(super) frames: Option<Vec<usize>>,
    #[arg(long, value_parser = on_off, action = clap::ArgAction::Set, default_value = "off")]
    pub(super) regnerf: bool,
    #[arg(long, value_parser = regnerf_weight, default_value = "400,0.1")]
    pub(super) regnerf_weight: [f64; 2],
    /// START,END: the fractions of training over which the encoding's window opens.
    #[arg(long, value_parser = window_span)]
    pub(super) coarse_to_fine: Option<(f64, f64)>,
    #[arg(long, value_parser = on_off, action = clap::ArgAction::Set, default_value = "on")]
    pub(super) view_dependence: bool,
    /// Proposal sampler: drop samples of lower opacity, in [0, 1).
    #[arg(long, default_value_t = 1e-2)]
    pub(super) alpha_threshold: f64,
    /// Proposal sampler: samples per ray of the two proposal levels.
    #[arg(long, value_parser = two_counts, default_value = "16,8")]
    pub(super) proposal_samples: [usize; 2],
    /// Unbounded scenes: scale each sample's gradients by min(1, t²), t its distance
    /// from the camera in the frame whose unit ball holds the cameras (against floaters
    /// in front of the training cameras).
    #[arg(long, value_parser = on_off, action = clap::ArgAction::Set, default_value = "on")]
    pub(super) gradient_scaling: bool,
    /// Read image and mask files outside the dataset folder (absolute paths, `../`,
    /// symlinks to elsewhere), which loading refuses by default.
    #[arg(long)]
    pub(super) allow_outside_paths: bool,
}

impl Default for Args {
    /// The defaults of the command line.
    fn default() -> Self {
        Args::parse_from(["nerf"])
    }
}

/// `--lr`: Adam's learning rate, in (0, 0.1]: above it the density collapses to zero
/// within a few steps (a dead run), at 0 nothing trains.
pub(super) fn learning_rate(value: &str) -> std::result::Result<f64, String> {
    match value.parse::<f64>() {
        Ok(lr) if lr > 0.0 && lr <= 0.1 => Ok(lr),
        _ => Err(format!(
            "a learning rate in (0, 0.1] (Adam; 1e-3 for NeRF, 1e-2 for hash grids), not {value}"
        )),
    }
}

/// `--adam-eps`: Adam's ε, in (0, 1e-4] (above it ε, not the gradient's scale, sets the
/// step of every weight whose gradients are below about ε).
pub(super) fn adam_eps(value: &str) -> std::result::Result<f64, String> {
    match value.parse::<f64>() {
        Ok(eps) if eps > 0.0 && eps <= 1e-4 => Ok(eps),
        _ => Err(format!(
            "an epsilon in (0, 1e-4] (Adam's; e.g. 1e-8 or 1e-15), not {value}"
        )),
    }
}

pub(super) fn on_off(value: &str) -> std::result::Result<bool, String> {
    match value {
        "on" => Ok(true),
        "off" => Ok(false),
        other => Err(format!("on or off, not {other}")),
    }
}

pub(super) fn numbers<const N: usize>(value: &str) -> std::result::Result<[f64; N], String> {
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
pub(super) fn regnerf_weight(value: &str) -> std::result::Result<[f64; 2], String> {
    match numbers(value)? {
        [a, b] if a > 0.0 && b > 0.0 => Ok([a, b]),
        _ => Err(format!("two weights > 0 like 400,0.1, not {value}")),
    }
}

/// `--coarse-to-fine START,END` with 0 ≤ START < 1 and START < END.
pub(super) fn window_span(value: &str) -> std::result::Result<(f64, f64), String> {
    match numbers(value)? {
        [s, e] if 0.0 <= s && s < e && s < 1.0 => Ok((s, e)),
        _ => Err(format!(
            "START,END with 0 ≤ START < 1 and START < END, not {value}"
        )),
    }
}

pub(super) fn two_counts(value: &str) -> std::result::Result<[usize; 2], String> {
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
    pub(super) fn budget(&self) -> Result<Budget> {
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
        if self.scene == Scene::Unbounded && self.sampler == Some(Sampler::Stratified) {
            return Err(bad(
                "--sampler grid or proposal with --scene unbounded (stratified samples need a box)",
                format!("{self:?}"),
            ));
        }
        if !(self.aabb.is_none_or(|a| a > 0.0 && a.is_finite())
            && (0.0..1.0).contains(&self.alpha_threshold))
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

    /// The device of `--device`: the CPU, or the first GPU (`Device::new_cuda(0)`), whose
    /// error says what is missing (a build with `--features cuda`, or a GPU).
    pub(super) fn device(&self) -> Result<Device> {
        match self.device {
            DeviceFlag::Cpu => Ok(Device::Cpu),
            DeviceFlag::Cuda => Device::new_cuda(0).map_err(|e| Error::InvalidArgument {
                arg: "device",
                expected: if candle_core::utils::cuda_is_available() {
                    "a CUDA GPU (the first, Device::new_cuda(0))".into()
                } else {
                    "a build with CUDA support: build with `--features cuda` (cargo run \
                     --release --features cuda --example nerf -- --device cuda)"
                        .into()
                },
                got: e.to_string(),
            }),
        }
    }

    /// The encoding of `--encoding`, or the scene's default.
    pub(super) fn encoding(&self) -> Encoding {
        self.encoding.unwrap_or(match self.scene {
            Scene::Object => Encoding::Pe,
            Scene::Unbounded => Encoding::Hash,
        })
    }

    /// `--lr`, or the default of the scene and encoding: 1e-2 for the hash grid, 1e-3
    /// for mip-NeRF's and for the frequency encoding in an unbounded scene (at 5e-3 its
    /// density collapses there), 5e-3 for the frequency encoding in a bounded scene.
    pub(super) fn learning_rate(&self) -> f64 {
        self.lr.unwrap_or(match (self.encoding(), self.scene) {
            (Encoding::Hash, _) => 1e-2,
            (Encoding::Ipe, _) | (Encoding::Pe, Scene::Unbounded) => 1e-3,
            (Encoding::Pe, Scene::Object) => 5e-3,
        })
    }

    /// `--march-jitter`, or the default: on for the hash grid in an object scene, whose
    /// table otherwise fits the fixed points a pixel's march visits every step (chosen
    /// on the tuning set, docs/benchmarks.md), off for the frequency encodings and for
    /// the cascaded grid of an unbounded scene.
    pub(super) fn march_jitter(&self) -> bool {
        self.march_jitter.unwrap_or(self.hash_object())
    }

    /// Whether this is the hash grid in an object scene, the setting whose defaults for
    /// `--march-jitter` and `--adam-eps` were tuned apart from the others'.
    fn hash_object(&self) -> bool {
        self.encoding() == Encoding::Hash && self.scene == Scene::Object
    }

    /// `--adam-eps`, or the default: 1e-15 (instant-NGP's) for the hash grid in an
    /// object scene, whose table over a tight scene box can otherwise stall for thousands
    /// of steps at Adam's usual 1e-8 (docs/benchmarks.md, "Adam's ε and the hash grid");
    /// 1e-8 for the frequency encodings and in an unbounded scene, where 1e-15 lost on
    /// the report capture ("ε in an unbounded scene, probed").
    pub(super) fn adam_eps(&self) -> f64 {
        self.adam_eps
            .unwrap_or(if self.hash_object() { 1e-15 } else { 1e-8 })
    }

    /// The sampler of `--sampler`, or the scene's default.
    pub(super) fn sampler(&self) -> Sampler {
        self.sampler.unwrap_or(match self.scene {
            Scene::Object => Sampler::Grid,
            Scene::Unbounded => Sampler::Proposal,
        })
    }

    pub(super) fn pixel_filter(&self) -> PixelFilter {
        match self.pixel_filter {
            Filter::Box => PixelFilter::Box,
            Filter::Cycles => PixelFilter::CYCLES,
        }
    }
}
