//! 3-D reconstruction from multi-view images: shape and colour of an object from its RGBA
//! (or image + mask) views, by surface rendering with implicit gradients (DVR, IDR), with
//! optional camera refinement (IDR's, BARF's, or a Levenberg–Marquardt registration).
//!
//! ```text
//! cargo run --release --example dvr_multiview                          # the committed dataset, DVR, 15 minutes
//! cargo run --release --example dvr_multiview -- --model idr --minutes 15 --out out/idr
//! cargo run --release --example dvr_multiview -- --perturb 3,0.03 --refine-poses on --pose-solver lm
//! cargo run --release --example dvr_multiview -- --help                # every flag and its default
//! ```
//!
//! **Data.** `--data DIR` is any dataset [`neural_fields::data::load`] reads whose views
//! have masks (default `examples/data/wuson`). The `train` split trains; the `test` split
//! (`val` if there is none) is held out, composited on white.
//!
//! **One step** on `--rays` pixels drawn as 2 × 2 patches: march the rays through the
//! scene box (sphere tracing for IDR), detached; [`implicit_surface`] makes the hit points
//! differentiable; losses: L1 photometric and DVR's image-gradient loss inside the mask;
//! for `--model dvr`/`dvr-joint` freespace and occupancy BCE at the most-occupied of 64
//! samples of the rays that should miss or should have hit, and normal smoothness; for
//! `--model idr` IDR's mask loss (weight 100, α doubling over the run) and the eikonal
//! loss. `--encoding hash` puts instant-NGP's hash grid under the networks. The geometry
//! starts as a ball of radius 0.5; Adam with a log-linear decay from `--lr` to a tenth.
//!
//! **Cameras.** `--perturb DEGREES,FRACTION` moves every training camera first;
//! `--refine-poses on` learns a [`PoseParam`] per view through the rays
//! ([`pose_rays`], Adam at `--pose-lr`), optionally under BARF's coarse-to-fine window
//! (`--coarse-to-fine START,END`). `--pose-solver lm` registers the cameras to the scene
//! held fixed ([`register_poses`], `--lm-iterations` renders each) after the last step,
//! and from `--lm-start` every `--lm-every` steps. A run with refined cameras is
//! evaluated after aligning the learnt frame to the dataset's ([`align_cameras`] on the
//! extracted surface; the poses after [`align_similarity`] of the centres, as BARF), and
//! each held-out camera is refined against its image first (`--test-pose-steps` Adam
//! steps, or the registration with `lm`).
//!
//! **Outputs** in `--out DIR` (default `target/dvr_multiview`): `metrics.json` (held-out
//! `mask_iou`, `psnr_masked`, `psnr_interior`, `chamfer_l1` and `chamfer_l1_icp` against
//! the source mesh (`--mesh`, or the one `scene.json` names; `null` without),
//! `train_seconds`, `steps`, `model`, `encoding`, `render_inputs`, `eval_split`,
//! `eval_views`, `data`; with cameras moved or refined also `pose_rotation_error_deg`,
//! `pose_centre_error_fraction` ([`pose_error`]: `before`, `after`, `after_aligned`),
//! `pose_reprojection_px` ([`reprojection_error`]), `pose_solver`, and with refinement
//! `unaligned`, `aligned`, `alignment`, `alignment_centres`, `chamfer_l1_centres`,
//! `test_pose_steps`); `curve.csv` (`step,train_seconds,mask_iou,psnr_masked` every
//! `--eval-every` steps on `--eval-views` views); `view_{i}.png` and `normals_{i}.png`
//! for `--pictures` views; `mesh.ply` (MISE, vertex colours); `weights.safetensors`
//! (`--resume FILE` continues from it, `--steps 0` evaluates); `poses.json` (refined
//! cameras; `--resume-poses FILE` starts from it). A NaN or infinity stops the run with an
//! error naming the step and the tensor. Runs and what they measured: docs/benchmarks.md.

use candle_core::{DType, Device, Tensor};
use candle_nn::{Optimizer, VarMap};
use clap::{Parser, ValueEnum};
use neural_fields::camera::{
    align_cameras, align_similarity, pose_error, pose_rays, ray_aabb, register_poses,
    reprojection_error, Camera, Intersection, PixelFilter, PoseParam, Rays, RegistrationConfig,
    Similarity,
};
use neural_fields::data::load_eval;
use neural_fields::data::{
    comparison_strip, load, psnr, write_png, Background, Dataset, LoadConfig, RayBatch, RaySampler,
};
use neural_fields::dvr::{
    eikonal_loss, idr_mask_loss, implicit_surface, march, most_inside_along_rays,
    normal_smoothness_loss, photometric_loss, sphere_trace, AlphaSchedule, Hits, ImplicitConfig,
    MarchConfig, Photometric, SphereTraceConfig,
};
use neural_fields::encoding::{
    hash_grid, CoarseToFine, FrequencyEncoding, HashGridConfig, PointEncoding,
};
use neural_fields::field::{ImplicitSurface, SignedDistance, Sphere};
use neural_fields::glam::{DAffine3, DMat3, DMat4, DVec3};
use neural_fields::mesh::Mesh;
use neural_fields::nn::{adam, build_seeded, mlp, Budget, Clock, FiniteGuard, Mlp, MlpConfig};
use neural_fields::numerics::bce_with_logits;
use neural_fields::occupancy::{chamfer_icp, mesh_metrics, mise, MiseConfig};
use neural_fields::rng::SplitMix64;
use neural_fields::texture::{image_gradient_loss, vertex_colors, TextureField, TextureInput};
use neural_fields::texture::{
    joint_decoder, rendering_net, texture_decoder, JointDecoder, RenderingNet, RenderingNetConfig,
    TextureDecoder, TextureDecoderConfig,
};
use neural_fields::volume::log_linear_schedule;
use neural_fields::{Error, Result};
use std::path::{Path, PathBuf};

#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// log₂ of the rows of each hash-grid level (`--encoding hash`).
const HASH_LOG2: u32 = 15;
/// Rays per chunk when rendering whole views.
const CHUNK: usize = 8192;
/// Rays per pixel side when rendering held-out views (2 × 2 per pixel).
const SUPERSAMPLE: usize = 2;

/// The model.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Model {
    /// An occupancy network and a texture field (Texture Fields' decoder).
    Dvr,
    /// DVR's joint decoder: one trunk for occupancy and colour.
    DvrJoint,
    /// IDR: an SDF network with a feature output and IDR's rendering network.
    Idr,
}

/// IDR's rendering-network inputs besides the point and the feature.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum RenderInputs {
    /// The view direction and the normal (IDR).
    Full,
    /// The normal, no view direction (IDR's `no_view_dir` ablation).
    NoView,
    /// The view direction, no normal (IDR's `no_normal` ablation).
    NoNormal,
}

/// How `--refine-poses on` moves the training poses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum PoseSolver {
    /// Adam on each pose, every step, beside the network (IDR).
    Adam,
    /// Adam until a Levenberg–Marquardt registration of every camera to the scene held
    /// fixed takes over; the held-out cameras are registered the same way.
    Lm,
}

/// The position encoding of the networks.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum PositionEncoding {
    /// A frequency encoding.
    Pe,
    /// instant-NGP's multiresolution hash grid over the scene box.
    Hash,
}

impl PositionEncoding {
    /// The encoding of 3-D points: `Pe` the frequency encoding with `frequencies` octaves;
    /// `Hash` [`HashGridConfig::default`] (2^[`HASH_LOG2`] rows per level) over the box
    /// `[lo, hi]` at resolutions 16 to `finest`, its table in `vb.pp("grid")`.
    fn build(
        self,
        frequencies: usize,
        (lo, hi): ([f64; 3], [f64; 3]),
        finest: f64,
        vb: &candle_nn::VarBuilder,
    ) -> Result<PointEncoding> {
        Ok(match self {
            Self::Pe => PointEncoding::Frequency(FrequencyEncoding::new(3, frequencies)?),
            Self::Hash => {
                let config = HashGridConfig {
                    lo: lo.to_vec(),
                    hi: hi.to_vec(),
                    log2_table_size: HASH_LOG2,
                    finest_resolution: finest,
                    ..HashGridConfig::default()
                };
                PointEncoding::HashGrid(hash_grid(&config, vb.pp("grid"))?)
            }
        })
    }
}

/// Rows `idx` of `t`.
fn rows(t: &Tensor, idx: &[u32]) -> Result<Tensor> {
    Ok(t.index_select(&Tensor::from_slice(idx, idx.len(), t.device())?, 0)?)
}

/// Rays `idx` of `rays` and their range on each.
fn select(rays: &Rays, range: &Intersection, idx: &[u32]) -> Result<(Rays, Intersection)> {
    let picked = Rays::new(rows(rays.origins(), idx)?, rows(rays.directions(), idx)?)?;
    let range = Intersection {
        near: rows(&range.near, idx)?,
        far: rows(&range.far, idx)?,
        hit: rows(&range.hit, idx)?,
    };
    Ok((picked, range))
}

/// Writes `bytes` to `path`.
fn write(path: &Path, bytes: impl AsRef<[u8]>) -> Result<()> {
    std::fs::write(path, bytes).map_err(|source| Error::Io {
        path: path.display().to_string(),
        source,
    })
}

/// `value` as pretty JSON in `path`.
fn write_json(path: &Path, value: &serde_json::Value) -> Result<()> {
    write(path, serde_json::to_string_pretty(value).expect("JSON")) // invariant: a Value
}

/// Stops on a NaN or infinity in a weight of `varmap`, naming it and the step.
fn check_weights(varmap: &VarMap, step: usize) -> Result<()> {
    let vars = varmap.data().lock().expect("an unpoisoned VarMap"); // invariant: not shared
    for (name, var) in vars.iter() {
        let sum = var.as_tensor().abs()?.sum_all()?.to_dtype(DType::F64)?;
        if !sum.to_scalar::<f64>()?.is_finite() {
            return Err(Error::InvalidArgument {
                arg: "training",
                expected: "finite losses, gradients and weights".into(),
                got: format!("a NaN or infinity in the weight {name} at step {step}"),
            });
        }
    }
    Ok(())
}

/// The name of a flag's value, as on the command line and in `metrics.json`.
fn name(value: impl ValueEnum) -> String {
    let v = value.to_possible_value().expect("no skipped variants"); // invariant
    v.get_name().to_string()
}

/// The command line (`--help` lists it with the defaults).
#[derive(Clone, Debug, Parser)]
#[command(about = "3-D reconstruction from masked views by DVR or IDR")]
pub struct Args {
    /// The dataset's folder.
    #[arg(long, default_value = "examples/data/wuson")]
    pub data: PathBuf,
    /// Training budget in minutes of training (15 when neither this nor --steps is given).
    #[arg(long)]
    pub minutes: Option<f64>,
    /// Training budget in steps.
    #[arg(long)]
    pub steps: Option<usize>,
    /// The output folder.
    #[arg(long, default_value = "target/dvr_multiview")]
    pub out: PathBuf,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[arg(long, value_enum, default_value_t = Model::Dvr)]
    pub model: Model,
    /// Divides the images' resolution.
    #[arg(long, default_value_t = 1)]
    pub downscale: usize,
    /// Rays per step (at least 4).
    #[arg(long, default_value_t = 1024)]
    pub rays: usize,
    /// Half the side of the scene box for layouts that state no bounds.
    #[arg(long, default_value_t = 1.1)]
    pub aabb: f64,
    #[arg(long, default_value_t = 500)]
    pub eval_every: usize,
    /// Held-out views of the periodic evaluations.
    #[arg(long, default_value_t = 4)]
    pub eval_views: usize,
    /// Held-out views written as pictures.
    #[arg(long, default_value_t = 4)]
    pub pictures: usize,
    /// The learning rate (default 1e-3, or 1e-2 for the DVR models on hash grids).
    #[arg(long)]
    pub lr: Option<f64>,
    #[arg(long, value_enum, default_value_t = PositionEncoding::Pe)]
    pub encoding: PositionEncoding,
    #[arg(long, value_enum, default_value_t = RenderInputs::Full)]
    pub render_inputs: RenderInputs,
    /// The source mesh in the dataset's frame (default: the one scene.json names).
    #[arg(long)]
    pub mesh: Option<PathBuf>,
    /// MISE's starting resolution (refined twice).
    #[arg(long, default_value_t = 32)]
    pub mise_resolution: usize,
    /// Perturb the training cameras: DEGREES,FRACTION (of the distance to the origin).
    #[arg(long, value_parser = perturbation)]
    pub perturb: Option<(f64, f64)>,
    /// `on` learns the training poses.
    #[arg(long, default_value = "off", action = clap::ArgAction::Set,
          value_parser = on_off)]
    pub refine_poses: bool,
    #[arg(long, default_value_t = 1e-3)]
    pub pose_lr: f64,
    /// BARF's coarse-to-fine window: START,END fractions of the budget.
    #[arg(long, value_parser = window_span)]
    pub coarse_to_fine: Option<(f64, f64)>,
    /// Test-time refinement steps per held-out camera (0: none).
    #[arg(long, default_value_t = 100)]
    pub test_pose_steps: usize,
    /// Refined training poses to start from (a run's poses.json).
    #[arg(long)]
    pub resume_poses: Option<PathBuf>,
    /// Weights to start from (a run's weights.safetensors).
    #[arg(long)]
    pub resume: Option<PathBuf>,
    #[arg(long, value_enum, default_value_t = PoseSolver::Adam)]
    pub pose_solver: PoseSolver,
    /// With `lm`: a registration every this many steps after the first.
    #[arg(long)]
    pub lm_every: Option<usize>,
    /// With `lm`: renders per registration.
    #[arg(long, default_value_t = 2)]
    pub lm_iterations: usize,
    /// With `lm`: the fraction of the budget of the first registration (1: only the last).
    #[arg(long, default_value_t = 1.0)]
    pub lm_start: f64,
}

impl Default for Args {
    fn default() -> Self {
        Args::parse_from(["dvr_multiview"])
    }
}

/// Two finite numbers `A,B`.
fn pair(value: &str) -> Option<(f64, f64)> {
    let (a, b) = value.split_once(',')?;
    let (a, b) = (a.trim().parse::<f64>().ok()?, b.trim().parse::<f64>().ok()?);
    (a.is_finite() && b.is_finite()).then_some((a, b))
}

/// `--perturb DEGREES,FRACTION`, both ≥ 0.
fn perturbation(value: &str) -> std::result::Result<(f64, f64), String> {
    pair(value)
        .filter(|&(d, f)| d >= 0.0 && f >= 0.0)
        .ok_or_else(|| format!("DEGREES,FRACTION ≥ 0 like 3,0.03, not {value}"))
}

/// `--coarse-to-fine START,END`: 0 ≤ START < 1, START < END (END > 1 leaves the windows
/// still opening when training ends).
fn window_span(value: &str) -> std::result::Result<(f64, f64), String> {
    pair(value)
        .filter(|&(s, e)| 0.0 <= s && s < e && s < 1.0)
        .ok_or_else(|| format!("START,END with 0 ≤ START < 1 and START < END, not {value}"))
}

/// `on` or `off`.
fn on_off(value: &str) -> std::result::Result<bool, String> {
    match value {
        "on" => Ok(true),
        "off" => Ok(false),
        other => Err(format!("on or off, not {other}")),
    }
}

/// Opens each coarse-to-fine window to `bands · clamp((progress − START)/(END − START), 0,
/// 1)`; without `--coarse-to-fine` there are none.
fn open_windows(windows: &[CoarseToFine], progress: f64, span: Option<(f64, f64)>) -> Result<()> {
    let open = span.map_or(1.0, |(s, e)| ((progress - s) / (e - s)).clamp(0.0, 1.0));
    for w in windows {
        w.set_alpha(open * w.bands() as f64)?;
    }
    Ok(())
}

impl Args {
    /// The checks that span flags, and the default budget.
    fn check(mut self) -> std::result::Result<Self, String> {
        if self.minutes.is_some() && self.steps.is_some() {
            return Err("give --minutes or --steps, not both".into());
        }
        if self.minutes.is_none() && self.steps.is_none() {
            self.minutes = Some(15.0);
        }
        if self.minutes.is_some_and(|m| !(m > 0.0 && m.is_finite())) {
            return Err("--minutes must be positive".into());
        }
        if self.lm_every == Some(0)
            || self.lm_iterations == 0
            || !(0.0..=1.0).contains(&self.lm_start)
        {
            return Err(
                "--lm-every and --lm-iterations must be positive, --lm-start in [0, 1]".into(),
            );
        }
        if self.rays < 4 || self.eval_every == 0 || self.eval_views == 0 || self.mise_resolution < 2
        {
            return Err(
                "--rays must be at least 4, --eval-every and --eval-views positive, \
                        --mise-resolution at least 2"
                    .into(),
            );
        }
        if !(self.aabb > 0.0 && self.aabb.is_finite()) {
            return Err("--aabb must be positive".into());
        }
        // A rate of 0 freezes what it drives (`--pose-lr 0`: the poses).
        let rate = |v: f64| v >= 0.0 && v.is_finite();
        if !rate(self.pose_lr) || self.lr.is_some_and(|lr| !rate(lr)) {
            return Err("--lr and --pose-lr must be finite and ≥ 0".into());
        }
        Ok(self)
    }
}
/// IDR's rendering-network defaults with the inputs `inputs`.
fn render_config(inputs: RenderInputs) -> RenderingNetConfig {
    let idr = RenderingNetConfig::default();
    match inputs {
        RenderInputs::Full => idr,
        RenderInputs::NoView => RenderingNetConfig {
            view_frequencies: None,
            ..idr
        },
        RenderInputs::NoNormal => RenderingNetConfig {
            use_normals: false,
            ..idr
        },
    }
}

/// The model (see [`Model`]). One per run, so the variants' sizes do not matter.
#[allow(clippy::large_enum_variant)]
enum Net {
    Dvr {
        geometry: Mlp,
        texture: TextureDecoder,
    },
    Joint(JointDecoder),
    Idr {
        geometry: Mlp,
        render: RenderingNet,
    },
}

/// Per-ray colours at the surface points, and (IDR) the SDF's gradient there.
struct Shaded {
    rgb: Tensor,
    gradient: Option<Tensor>,
}

impl Net {
    fn surface(&self) -> &dyn ImplicitSurface {
        match self {
            Net::Joint(net) => net,
            Net::Dvr { geometry, .. } | Net::Idr { geometry, .. } => geometry,
        }
    }

    /// The first surface point on each ray, detached.
    fn find_surface(&self, rays: &Rays, range: &Intersection) -> Result<Hits> {
        let config = MarchConfig {
            steps: 64,
            secant_steps: 8,
            ..MarchConfig::default()
        };
        match self {
            Net::Joint(_) | Net::Dvr { .. } => march(self.surface(), rays, range, &config),
            Net::Idr { geometry, .. } => sphere_trace(
                geometry,
                rays,
                range,
                &SphereTraceConfig {
                    fallback: config,
                    ..SphereTraceConfig::default()
                },
            ),
        }
    }

    /// The colour at `points: [H, 3]` seen along `dirs: [H, 3]`.
    fn shade(&self, points: &Tensor, dirs: &Tensor) -> Result<Shaded> {
        match self {
            Net::Joint(net) => Ok(Shaded {
                rgb: net.rgb(&TextureInput::new(points))?,
                gradient: None,
            }),
            Net::Dvr { texture, .. } => Ok(Shaded {
                rgb: texture.rgb(&TextureInput::new(points))?,
                gradient: None,
            }),
            Net::Idr { geometry, render } => {
                let (y, jac) = geometry.forward_with_jacobian(points, None)?;
                let k = y.dim(1)?;
                let normal = jac.narrow(2, 0, 1)?.squeeze(2)?;
                let feature = y.narrow(1, 1, k - 1)?;
                let input = TextureInput {
                    normals: Some(&normal),
                    view_dirs: Some(dirs),
                    features: Some(&feature),
                    ..TextureInput::new(points)
                };
                Ok(Shaded {
                    rgb: render.rgb(&input)?,
                    gradient: Some(normal),
                })
            }
        }
    }
}

/// Builds the model of `args.model` in `varmap`; with `--encoding hash`, the DVR models'
/// networks read points through hash grids over the scene box `aabb` (finest resolution
/// `finest`) on 2 × 64 trunks. With `--coarse-to-fine`, every position encoding is
/// windowed, and the windows are returned for the training loop to open.
fn build(
    args: &Args,
    aabb: [f64; 6],
    finest: f64,
    varmap: &VarMap,
    device: &Device,
    dtype: DType,
) -> Result<(Net, Vec<CoarseToFine>)> {
    let (lo, hi) = ([aabb[0], aabb[1], aabb[2]], [aabb[3], aabb[4], aabb[5]]);
    let windows = std::cell::RefCell::new(Vec::new());
    let window = |encoding: PointEncoding| -> Result<PointEncoding> {
        if args.coarse_to_fine.is_none() {
            return Ok(encoding);
        }
        let c = CoarseToFine::new(encoding)?;
        windows.borrow_mut().push(c.clone());
        Ok(PointEncoding::CoarseToFine(c))
    };
    let encode = |frequencies: usize, vb: &candle_nn::VarBuilder| {
        window(args.encoding.build(frequencies, (lo, hi), finest, vb)?)
    };
    // The occupancy network: PE(L = 4) on 5 × 128 with a skip, or a hash grid on 2 × 64.
    let shape = |vb: &candle_nn::VarBuilder| -> Result<MlpConfig> {
        let encoding = encode(4, vb)?;
        Ok(match args.encoding {
            PositionEncoding::Pe => MlpConfig {
                hidden: 128,
                depth: 5,
                skips: vec![3],
                encoding,
                ..MlpConfig::default()
            },
            PositionEncoding::Hash => MlpConfig {
                hidden: 64,
                depth: 2,
                encoding,
                ..MlpConfig::default()
            },
        })
    };
    let net = match args.model {
        Model::DvrJoint => Net::Joint(build_seeded(varmap, dtype, device, args.seed, |vb| {
            let vb = vb.pp("decoder");
            joint_decoder(&shape(&vb)?, vb)
        })?),
        Model::Dvr => {
            let geometry = build_seeded(varmap, dtype, device, args.seed, |vb| {
                let vb = vb.pp("geometry");
                mlp(&shape(&vb)?, vb)
            })?;
            let texture = build_seeded(varmap, dtype, device, args.seed + 1, |vb| {
                let vb = vb.pp("texture");
                let texture_config = TextureDecoderConfig {
                    encoding: encode(8, &vb)?,
                    ..TextureDecoderConfig::default()
                };
                texture_decoder(&texture_config, vb)
            })?;
            Net::Dvr { geometry, texture }
        }
        Model::Idr => {
            const FEATURES: usize = 32;
            let config = MlpConfig {
                hidden: 128,
                depth: 5,
                skips: vec![3],
                out_dim: 1 + FEATURES,
                // IDR's 6 frequencies: the SDF's geometric initialisation keeps the
                // higher ones at zero, where an occupancy network with them grows floaters.
                encoding: window(PointEncoding::Frequency(FrequencyEncoding::new(3, 6)?))?,
                ..MlpConfig::sdf(0.5)
            };
            let geometry = build_seeded(varmap, dtype, device, args.seed, |vb| {
                mlp(&config, vb.pp("geometry"))
            })?;
            // The rendering net reads the raw point (IDR), or with --encoding hash the
            // point through a hash grid (the SDF keeps its frequencies: its geometric
            // initialisation needs the point itself).
            let render = build_seeded(varmap, dtype, device, args.seed + 1, |vb| {
                let vb = vb.pp("render");
                let render_config = RenderingNetConfig {
                    feature_dim: FEATURES,
                    hidden: 64,
                    depth: 3,
                    point_encoding: match args.encoding {
                        PositionEncoding::Pe => PointEncoding::Identity,
                        PositionEncoding::Hash => encode(0, &vb)?,
                    },
                    ..render_config(args.render_inputs)
                };
                rendering_net(&render_config, vb)
            })?;
            Net::Idr { geometry, render }
        }
    };
    Ok((net, windows.into_inner()))
}

/// Checks that every view of `data` has a mask and that some mask covers a pixel.
///
/// # Errors
/// Naming `data`: a view without a mask (naming it), or masks that are all empty.
fn check_masks(data: &Dataset) -> Result<()> {
    let mut covered = 0.0;
    for v in data.views() {
        let m = v
            .mask(&Device::Cpu, DType::F32)?
            .ok_or_else(|| no_mask(v.name()))?;
        let inside = m.ge(0.5)?.to_dtype(DType::F32)?.sum_all()?;
        covered += f64::from(inside.to_scalar::<f32>()?);
    }
    if covered == 0.0 {
        return Err(Error::InvalidArgument {
            arg: "data",
            expected: "masks that cover the object in some training view".into(),
            got: format!("{} views whose masks are all empty", data.views().len()),
        });
    }
    Ok(())
}

/// The error for a dataset whose view `name` has no mask.
fn no_mask(name: &str) -> Error {
    Error::InvalidArgument {
        arg: "data",
        expected: "views with masks (alpha or mask files)".into(),
        got: format!("{name} without one"),
    }
}

fn zero(device: &Device, dtype: DType) -> Result<Tensor> {
    Ok(Tensor::zeros((), dtype, device)?)
}

/// The loss of one batch (see the module docs); `progress ∈ [0, 1)` drives IDR's α.
fn step_loss(
    net: &Net,
    rays: &Rays,
    colors: &Tensor,
    mask: &[bool],
    aabb: [f64; 6],
    progress: f64,
    seed: u64,
) -> Result<(Tensor, Tensor)> {
    let (device, dtype) = (colors.device().clone(), colors.dtype());
    let n = rays.len();
    let [x0, y0, z0, x1, y1, z1] = aabb;
    let range = ray_aabb(rays, [x0, y0, z0], [x1, y1, z1])?;
    let in_box: Vec<bool> = {
        let (near, far) = (range.near.to_vec1::<f32>()?, range.far.to_vec1::<f32>()?);
        let hit = range.hit.to_vec1::<u8>()?;
        (0..n).map(|i| hit[i] != 0 && far[i] > near[i]).collect()
    };
    let hits = net.find_surface(rays, &range)?;
    let surf = implicit_surface(net.surface(), rays, &hits, &ImplicitConfig::default())?;
    let hit_rays = surf.indices.to_vec1::<u32>()?;
    let dirs = rays.directions().index_select(&surf.indices, 0)?;
    let shaded = net.shade(&surf.points, &dirs)?;
    // Photometric: rays that hit inside the mask.
    let on: Vec<u32> = hit_rays
        .iter()
        .enumerate()
        .filter(|(_, &r)| mask[r as usize])
        .map(|(k, _)| k as u32)
        .collect();
    let mut photo = zero(&device, dtype)?;
    if !on.is_empty() {
        let on_rays: Vec<u32> = on.iter().map(|&k| hit_rays[k as usize]).collect();
        photo = photometric_loss(
            &rows(&shaded.rgb, &on)?,
            &rows(colors, &on_rays)?,
            None,
            Photometric::L1,
        )?;
    }
    // DVR's normalisation: every term is a sum over its rays divided by the batch size,
    // so a term over few rays (the mask covers a tenth of the committed views) does not
    // outweigh the others per ray.
    let share = |count: usize| count as f64 / n as f64;
    let photo_scale = share(on.len());
    let mut loss = (&photo * photo_scale)?;
    // DVR's image-gradient loss on the patches that hit inside the mask.
    if !hit_rays.is_empty() {
        let full =
            Tensor::zeros((n, 3), dtype, &device)?.index_add(&surf.indices, &shaded.rgb, 0)?;
        let mut valid = vec![0u8; n];
        for &r in &hit_rays {
            valid[r as usize] = u8::from(mask[r as usize]);
        }
        let valid = Tensor::from_vec(valid, n, &device)?;
        let gradient = image_gradient_loss(&full, colors, Some(&valid), 2)?;
        loss = (loss + (gradient * photo_scale)?)?;
    }
    let surface_hit: Vec<bool> = hits.status.iter().map(|s| s.has_surface()).collect();
    match net {
        Net::Joint(_) | Net::Dvr { .. } => {
            let decoder = net.surface();
            // DVR's freespace and occupancy losses, each at the most-occupied of 64 samples
            // on the ray (where DVR takes the hit or one random point): a background ray
            // pushes its most-occupied point out, which removes every floater on it, and
            // a mask ray that found no surface pushes its most-occupied point in.
            let (mut free, mut missed) = (Vec::new(), Vec::new());
            for r in 0..n {
                match (mask[r], surface_hit[r]) {
                    (false, _) if in_box[r] => free.push(r as u32),
                    (true, false) if in_box[r] => missed.push(r as u32),
                    _ => {}
                }
            }
            for (which, target) in [(&free, 0.0), (&missed, 1.0)] {
                if which.is_empty() {
                    continue;
                }
                let (sub, sub_range) = select(rays, &range, which)?;
                let logits = most_inside_along_rays(decoder, &sub, &sub_range, 64)?;
                let y = Tensor::full(target, which.len(), &device)?.to_dtype(dtype)?;
                let bce = bce_with_logits(&logits, &y)?.mean_all()?;
                loss = (loss + (bce * share(which.len()))?)?;
            }
            if !hit_rays.is_empty() {
                let smooth =
                    normal_smoothness_loss(decoder, &surf.points.detach(), 1e-3, seed ^ 2)?;
                loss = (loss + (smooth * (0.05 * share(hit_rays.len())))?)?;
            }
        }
        Net::Idr { geometry, .. } => {
            // Mask loss on the rays outside hit ∧ mask.
            let outside: Vec<u32> = (0..n)
                .filter(|&r| in_box[r] && !(surface_hit[r] && mask[r]))
                .map(|r| r as u32)
                .collect();
            if !outside.is_empty() {
                let (sub, sub_range) = select(rays, &range, &outside)?;
                let values = most_inside_along_rays(geometry, &sub, &sub_range, 64)?;
                let target: Vec<f32> = outside
                    .iter()
                    .map(|&r| f32::from(u8::from(mask[r as usize])))
                    .collect();
                let target = Tensor::from_vec(target, outside.len(), &device)?.to_dtype(dtype)?;
                let alpha = AlphaSchedule::default().alpha_at((progress * 2000.0) as usize);
                let m = idr_mask_loss(&values, &target, geometry.inside(), alpha, n)?;
                loss = (loss + (m * 100.0)?)?;
            }
            // Eikonal at random points of the box and at the surface points.
            let mut rng = SplitMix64::new(seed ^ 3);
            let p = rng.uniform_tensor(
                &[n / 2, 3],
                x0.min(y0).min(z0),
                x1.max(y1).max(z1),
                dtype,
                &device,
            )?;
            let (_, g) = geometry.value_and_grad(&p)?;
            let mut grads = vec![g];
            if let Some(g) = shaded.gradient {
                grads.push(g);
            }
            let eik = eikonal_loss(&Tensor::cat(&grads, 0)?)?;
            loss = (loss + (eik * 0.1)?)?;
        }
    }
    Ok((loss, photo))
}

/// The scene along `rays`, without graph: colour on white `[N, 3]`, the surface's depth
/// `[N]` (the ray parameter), coverage `[N]` (1 where a ray hits) and outward normals
/// `[N, 3]` (0 where nothing is hit).
fn shade_rays(net: &Net, rays: &Rays, aabb: [f64; 6]) -> Result<[Tensor; 4]> {
    let (n, dtype) = (rays.len(), rays.origins().dtype());
    let device = rays.origins().device();
    let [x0, y0, z0, x1, y1, z1] = aabb;
    let hits = net.find_surface(rays, &ray_aabb(rays, [x0, y0, z0], [x1, y1, z1])?)?;
    let hit_rays: Vec<u32> = (0u32..)
        .zip(&hits.status)
        .filter(|(_, s)| s.has_surface())
        .map(|(i, _)| i)
        .collect();
    let coverage = hits.mask.to_dtype(dtype)?;
    let mut rgb = Tensor::ones((n, 3), dtype, device)?;
    let mut normals = Tensor::zeros((n, 3), dtype, device)?;
    if !hit_rays.is_empty() {
        let idx = Tensor::from_vec(hit_rays.clone(), hit_rays.len(), device)?;
        let points = hits.points.index_select(&idx, 0)?;
        let shading = net.shade(&points, &rays.directions().index_select(&idx, 0)?)?;
        // IDR's shading has already formed the SDF's gradient; DVR's has not.
        let g = match shading.gradient {
            Some(g) => g,
            None => net.surface().value_and_grad(&points)?.1,
        }
        .detach();
        let length = g
            .sqr()?
            .sum_keepdim(1)?
            .sqrt()?
            .clamp(1e-12, f64::INFINITY)?;
        // Outward normals: towards decreasing occupancy, increasing distance.
        let unit = (g.broadcast_div(&length)? * -net.surface().inside().sign())?;
        let on_white = rgb
            .zeros_like()?
            .index_add(&idx, &shading.rgb.detach(), 0)?;
        let covered = coverage.unsqueeze(1)?.broadcast_as((n, 3))?.ne(0.0)?;
        rgb = covered.where_cond(&on_white, &rgb)?;
        normals = normals.index_add(&idx, &unit, 0)?;
    }
    Ok([rgb, hits.depth, coverage, normals])
}

/// View `v` of `data` rendered whole without graph, `k × k` rays per pixel on a sub-pixel
/// grid averaged (the images integrate over each pixel too): colour on white
/// `[H, W, 3]`, the covered fraction `[H, W]` and normals `[H, W, 3]`.
fn render_view(
    net: &Net,
    data: &Dataset,
    v: usize,
    aabb: [f64; 6],
    k: usize,
) -> Result<[Tensor; 3]> {
    let cam = data.views()[v].camera();
    let (w, h) = (cam.intrinsics().width, cam.intrinsics().height);
    let grid = cam.subpixel_grid(k, PixelFilter::Box, &Device::Cpu, DType::F32)?;
    let all = cam.rays_for_pixels(&grid)?;
    let mut parts: [Vec<Tensor>; 3] = Default::default();
    for start in (0..all.len()).step_by(CHUNK) {
        let rays = all.narrow(start, CHUNK.min(all.len() - start))?;
        let [rgb, _, coverage, normals] = shade_rays(net, &rays, aabb)?;
        for (p, t) in parts.iter_mut().zip([rgb, coverage.unsqueeze(1)?, normals]) {
            p.push(t);
        }
    }
    let mean = |p: &[Tensor]| -> Result<Tensor> {
        let c = p[0].dim(1)?;
        Ok(Tensor::cat(p, 0)?
            .reshape((h * w, k * k, c))?
            .mean(1)?
            .reshape((h, w, c))?)
    };
    Ok([
        mean(&parts[0])?,
        mean(&parts[1])?.squeeze(2)?,
        mean(&parts[2])?,
    ])
}

/// What [`evaluate`] measures on held-out views: mask IoU (coverage ≥ ½ against the mask
/// ≥ ½) and PSNR inside the mask and on the fully covered pixels (mask = 1, without the
/// antialiased edge), each pooled over the views; per view `[truth, colour, normals]`.
struct Evaluation {
    iou: f64,
    psnr_masked: f64,
    psnr_interior: f64,
    renders: Vec<[Tensor; 3]>,
}

/// Squared error and sample count of predictions on masked pixels, pooled over views.
#[derive(Default)]
struct Pooled {
    se: f64,
    count: f64,
}

impl Pooled {
    fn add(&mut self, pred: &Tensor, truth: &Tensor, mask: &Tensor) -> Result<()> {
        let pixels = f64::from(mask.sum_all()?.to_scalar::<f32>()?);
        if pixels > 0.0 {
            let p = psnr(pred, truth, Some(mask))?;
            self.se += 10f64.powf(-p / 10.0) * pixels * 3.0;
            self.count += pixels * 3.0;
        }
        Ok(())
    }

    fn psnr(&self) -> f64 {
        match self.count > 0.0 {
            true => -10.0 * (self.se / self.count).log10(),
            false => f64::NAN,
        }
    }
}

/// The metrics of [`Evaluation`] over the first `n` views of `eval`.
fn evaluate(net: &Net, eval: &Dataset, n: usize, aabb: [f64; 6]) -> Result<Evaluation> {
    let (mut inter, mut union) = (0.0, 0.0);
    let (mut masked, mut interior) = (Pooled::default(), Pooled::default());
    let mut renders = Vec::new();
    for (v, view) in eval.views().iter().enumerate().take(n) {
        let truth = view.rgb([1.0; 3], &Device::Cpu, DType::F32)?;
        let mask = view
            .mask(&Device::Cpu, DType::F32)?
            .ok_or_else(|| no_mask(view.name()))?;
        let true_mask = mask.ge(0.5)?.to_dtype(DType::F32)?;
        let [color, coverage, normals] = render_view(net, eval, v, aabb, SUPERSAMPLE)?;
        let hit = coverage.ge(0.5)?.to_dtype(DType::F32)?;
        let sum = |t: Tensor| -> Result<f64> { Ok(f64::from(t.sum_all()?.to_scalar::<f32>()?)) };
        inter += sum((&hit * &true_mask)?)?;
        union += sum((&hit + &true_mask)?.clamp(0.0, 1.0)?)?;
        masked.add(&color, &truth, &true_mask)?;
        interior.add(&color, &truth, &mask.ge(1.0)?.to_dtype(DType::F32)?)?;
        renders.push([truth, color, normals]);
    }
    Ok(Evaluation {
        iou: if union > 0.0 { inter / union } else { 1.0 },
        psnr_masked: masked.psnr(),
        psnr_interior: interior.psnr(),
        renders,
    })
}

/// The source mesh in the dataset's world frame: `--mesh`, or `scene.json`'s `mesh` with
/// its `normalisation.matrix` (as the committed dataset's render script writes them);
/// `None` when neither is there.
fn source_mesh(args: &Args) -> Result<Option<Mesh>> {
    if let Some(path) = &args.mesh {
        return Ok(Some(Mesh::load(path)?));
    }
    let scene = args.data.join("scene.json");
    let Ok(text) = std::fs::read_to_string(&scene) else {
        return Ok(None);
    };
    let bad = |what: &str| Error::Format {
        path: scene.display().to_string(),
        field: what.to_string(),
        expected: "the render script's scene description".into(),
        got: "something else".into(),
    };
    let json: serde_json::Value = serde_json::from_str(&text).map_err(|_| bad("(JSON)"))?;
    let Some(path) = json["mesh"].as_str() else {
        return Ok(None);
    };
    if !Path::new(path).is_file() {
        println!("source mesh {path} not found: no Chamfer distance");
        return Ok(None);
    }
    let m: Vec<Vec<f64>> = serde_json::from_value(json["normalisation"]["matrix"].clone())
        .map_err(|_| bad("normalisation.matrix"))?;
    if m.len() < 3 || m.iter().take(3).any(|r| r.len() != 4) {
        return Err(bad("normalisation.matrix"));
    }
    let mut mesh = Mesh::load(path)?;
    for v in &mut mesh.vertices {
        let p = *v;
        *v = std::array::from_fn(|r| m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3]);
    }
    mesh.normals = None;
    Ok(Some(mesh))
}

/// The surface by MISE (`resolution0`, refined twice) with the texture's vertex colours.
fn extract_mesh(net: &Net, aabb: [f64; 6], resolution0: usize) -> Result<Mesh> {
    let (device, dtype) = (Device::Cpu, DType::F32);
    let config = MiseConfig {
        resolution0,
        upsampling_steps: 2,
        min: [aabb[0], aabb[1], aabb[2]],
        max: [aabb[3], aabb[4], aabb[5]],
        device: device.clone(),
        dtype,
        ..MiseConfig::new(32, 2, &Device::Cpu, DType::F32)
    };
    let mut mesh = mise(net.surface(), &config)?.mesh;
    if mesh.faces.is_empty() {
        return Ok(mesh);
    }
    let colors = vertex_colors(&mesh, 16_384, &device, dtype, |p| {
        // View the surface head-on: along the inward normal.
        let g = net.surface().value_and_grad(p)?.1.detach();
        Ok(net
            .shade(p, &(g * net.surface().inside().sign())?)?
            .rgb
            .detach())
    })?;
    mesh.colors = Some(colors);
    mesh.validate()?;
    Ok(mesh)
}

/// Chamfer-L1 of `pred` to `gt` in `gt`'s unit cube (ONet's normalisation, 100 000
/// samples on each).
fn chamfer(pred: &Mesh, gt: &Mesh, seed: u64) -> Result<f64> {
    let mut gt = gt.clone();
    let (centre, scale) = gt.normalize_unit_cube()?;
    let mut pred = pred.clone();
    for v in &mut pred.vertices {
        *v = std::array::from_fn(|c| (v[c] - centre[c]) * scale);
    }
    Ok(mesh_metrics(&pred, &gt, 100_000, 0.01, seed)?.chamfer_l1)
}

/// The camera-to-world poses of `data`'s views.
fn poses_of(data: &Dataset) -> Vec<DAffine3> {
    data.views()
        .iter()
        .map(|v| v.camera().cam_to_world())
        .collect()
}

/// The cameras of `data`'s views (intrinsics, convention) at `poses`.
fn cameras_at(data: &Dataset, poses: &[DAffine3]) -> Result<Vec<Camera>> {
    Ok(data
        .with_poses(poses)?
        .views()
        .iter()
        .map(|v| *v.camera())
        .collect())
}

/// `data` with every camera rotated by `degrees` about a random axis through its centre
/// and its centre shifted by `fraction` of its distance to the origin (seeded).
fn perturb(data: &Dataset, degrees: f64, fraction: f64, seed: u64) -> Result<Dataset> {
    let mut rng = SplitMix64::new(seed);
    let mut unit = || {
        let v = DVec3::new(rng.normal(), rng.normal(), rng.normal());
        v / v.length().max(1e-12)
    };
    let moved: Vec<DAffine3> = poses_of(data)
        .iter()
        .map(|pose| {
            let rotation = DMat3::from_axis_angle(unit(), degrees.to_radians()) * pose.matrix3;
            let centre = pose.translation + unit() * fraction * pose.translation.length();
            DAffine3::from_mat3_translation(rotation, centre)
        })
        .collect();
    data.with_poses(&moved)
}

/// The refined poses, and the least-squares fit of their centres onto the true ones: the
/// map from the learnt frame to the dataset's that BARF compares poses after.
fn alignment(poses: &[PoseParam], truth: &[DAffine3]) -> Result<(Similarity, Vec<DAffine3>)> {
    let refined = poses
        .iter()
        .map(PoseParam::to_affine)
        .collect::<Result<Vec<_>>>()?;
    let centres = |p: &[DAffine3]| p.iter().map(|p| p.translation).collect::<Vec<_>>();
    Ok((
        align_similarity(&centres(&refined), &centres(truth))?,
        refined,
    ))
}

/// At most 2 000 of `mesh`'s vertices, evenly spread over its vertex list.
fn mesh_points(mesh: &Mesh) -> Vec<DVec3> {
    let every = mesh.vertices.len().div_ceil(2_000).max(1);
    mesh.vertices
        .iter()
        .step_by(every)
        .map(|&v| DVec3::from_array(v))
        .collect()
}

/// The map from the learnt frame to the dataset's under which the refined and the true
/// training cameras see the extracted surface alike ([`align_cameras`]), or `centres`
/// (said on stderr) when the mesh is empty or no camera sees it.
fn view_alignment(
    train: &Dataset,
    (refined, truth): (&[DAffine3], &[DAffine3]),
    mesh: &Mesh,
    centres: Similarity,
) -> Result<Similarity> {
    if mesh.vertices.is_empty() {
        return Ok(centres);
    }
    let (from, to) = (cameras_at(train, refined)?, cameras_at(train, truth)?);
    Ok(
        align_cameras(&from, &to, &mesh_points(mesh)).unwrap_or_else(|e| {
            eprintln!("the scene is placed by the camera centres' fit: {e}");
            centres
        }),
    )
}

/// `eval` with its cameras moved into the learnt frame by the inverse of `frame`.
fn in_learnt_frame(eval: &Dataset, frame: &Similarity) -> Result<Dataset> {
    let r = frame.rotation.inverse();
    let inverse = Similarity {
        scale: 1.0 / frame.scale,
        rotation: r,
        translation: -(r * frame.translation) / frame.scale,
    };
    eval.with_poses(
        &poses_of(eval)
            .iter()
            .map(|p| inverse.apply(*p))
            .collect::<Vec<_>>(),
    )
}

/// `mesh` (in the learnt frame) moved into the dataset's frame by `frame`.
fn mesh_to_dataset_frame(mut mesh: Mesh, frame: &Similarity) -> Mesh {
    for v in &mut mesh.vertices {
        *v = frame.apply(DVec3::from_array(*v)).to_array();
    }
    for n in mesh.normals.iter_mut().flatten() {
        *n = (frame.rotation * DVec3::from_array(*n)).to_array();
    }
    mesh
}

/// The rays of `batch` (drawn from `data`) cast from the learnable `poses`, through the
/// centres of the batch's pixels.
fn batch_rays(poses: &[PoseParam], data: &Dataset, batch: &RayBatch) -> Result<Rays> {
    let cameras: Vec<Camera> = data.views().iter().map(|v| *v.camera()).collect();
    let pixels = (batch.pixels.to_dtype(batch.colors.dtype())? + 0.5)?;
    pose_rays(poses, &cameras, &batch.views, &pixels)
}

/// The masks of `batch` as booleans (mask ≥ ½).
fn batch_mask(batch: &RayBatch, data: &Dataset) -> Result<Vec<bool>> {
    let m = batch
        .masks
        .as_ref()
        .ok_or_else(|| no_mask(data.views()[0].name()))?;
    Ok(m.to_vec1::<f32>()?.iter().map(|&m| m >= 0.5).collect())
}

/// BARF's test-time refinement: each camera of `eval` (already in the learnt frame) is
/// refined against its own image with the network fixed, `steps` Adam steps at `lr` on
/// 256 rays, with the training loss at the end of its schedule.
fn refine_eval_poses(
    net: &Net,
    eval: &Dataset,
    aabb: [f64; 6],
    steps: usize,
    lr: f64,
    seed: u64,
) -> Result<Dataset> {
    let (device, dtype) = (Device::Cpu, DType::F32);
    let mut refined = Vec::with_capacity(eval.views().len());
    for (v, view) in eval.views().iter().enumerate() {
        let one = Dataset::new(vec![view.clone()], eval.background(), eval.bounds())?;
        let pose = PoseParam::from_affine(&view.camera().cam_to_world(), &device, dtype)?;
        let params = candle_nn::ParamsAdamW {
            lr,
            weight_decay: 0.0,
            ..Default::default()
        };
        let mut opt = candle_nn::AdamW::new(
            vec![pose.rotation.clone(), pose.translation.clone()],
            params,
        )?;
        let mut sampler = RaySampler::new(&one, seed ^ v as u64, &device, dtype)?;
        for step in 0..steps {
            let batch = sampler.patches(64, 2)?;
            let rays = batch_rays(std::slice::from_ref(&pose), &one, &batch)?;
            let mask = batch_mask(&batch, &one)?;
            let (loss, _) = step_loss(
                net,
                &rays,
                &batch.colors,
                &mask,
                aabb,
                1.0,
                seed ^ step as u64,
            )?;
            opt.step(&loss.backward()?)?;
        }
        refined.push(pose.to_affine()?);
    }
    eval.with_poses(&refined)
}

/// `rounds` registrations of `data`'s cameras, from `poses`, to the scene the network
/// renders ([`register_poses`]); `report(round, poses)` sees the poses after each.
fn register(
    net: &Net,
    data: &Dataset,
    poses: &[DAffine3],
    (aabb, rounds): ([f64; 6], usize),
    report: &mut dyn FnMut(usize, &[DAffine3]),
) -> Result<Vec<DAffine3>> {
    let images = data
        .views()
        .iter()
        .map(|v| {
            let mask = v
                .mask(&Device::Cpu, DType::F32)?
                .ok_or_else(|| no_mask(v.name()))?;
            let rgb = v.rgb([1.0; 3], &Device::Cpu, DType::F32)?;
            Ok(Tensor::cat(&[rgb, mask.unsqueeze(2)?], 2)?)
        })
        .collect::<Result<Vec<_>>>()?;
    let mut cameras = cameras_at(data, poses)?;
    for round in 0..rounds {
        let render = |rays: &Rays| -> Result<(Tensor, Tensor, Tensor)> {
            let [rgb, depth, coverage, _] = shade_rays(net, rays, aabb)?;
            Ok((rgb, depth, coverage))
        };
        cameras = register_poses(&cameras, &images, render, &RegistrationConfig::default())?;
        report(
            round,
            &cameras.iter().map(Camera::cam_to_world).collect::<Vec<_>>(),
        );
    }
    Ok(cameras.iter().map(Camera::cam_to_world).collect())
}

/// Sets each pose of `poses` to the matching rigid transform of `to`.
fn set_poses(poses: &[PoseParam], to: &[DAffine3]) -> Result<()> {
    for (p, pose) in poses.iter().zip(to) {
        let fresh = PoseParam::from_affine(pose, p.translation.device(), p.translation.dtype())?;
        p.rotation.set(fresh.rotation.as_tensor())?;
        p.translation.set(fresh.translation.as_tensor())?;
    }
    Ok(())
}

/// One registration of the training cameras (`poses`, learnt on `train`) to the scene at
/// `step`, printing the pose errors against `truth` (unaligned). The cameras stay where
/// the registration puts them, in the scene's frame.
fn register_training(
    net: &Net,
    args: &Args,
    train: &Dataset,
    (poses, truth): (&[PoseParam], &[DAffine3]),
    aabb: [f64; 6],
    step: usize,
) -> Result<()> {
    let current = poses
        .iter()
        .map(PoseParam::to_affine)
        .collect::<Result<Vec<_>>>()?;
    let refined = register(
        net,
        train,
        &current,
        (aabb, args.lm_iterations),
        &mut |it, p| {
            if let Ok((r, t)) = pose_error(p, truth) {
                println!(
                    "step {step}, registration {it}: poses {r:.3}° / {:.3} % (unaligned)",
                    100.0 * t
                );
            }
        },
    )?;
    set_poses(poses, &refined)
}

/// The learnt-frame poses of `path` (a run's `poses.json`), one per view of `data`, by
/// name.
///
/// # Errors
/// [`Error::Format`] naming `path` when it is not such a file or lacks a view of `data`.
fn read_poses(path: &Path, data: &Dataset) -> Result<Vec<DAffine3>> {
    let bad = |field: &str| Error::Format {
        path: path.display().to_string(),
        field: field.to_string(),
        expected: "dvr_multiview's poses.json (views: name, cam_to_world 4 × 4)".into(),
        got: "something else".into(),
    };
    let text = std::fs::read_to_string(path).map_err(|_| bad("(file)"))?;
    let json: serde_json::Value = serde_json::from_str(&text).map_err(|_| bad("(JSON)"))?;
    let views = json["views"].as_array().ok_or_else(|| bad("views"))?;
    data.views()
        .iter()
        .map(|v| {
            let entry = views
                .iter()
                .find(|e| e["name"] == v.name())
                .ok_or_else(|| bad(&format!("views[name = {}]", v.name())))?;
            let m: Vec<Vec<f64>> = serde_json::from_value(entry["cam_to_world"].clone())
                .map_err(|_| bad("cam_to_world"))?;
            if m.len() != 4 || m.iter().any(|r| r.len() != 4) {
                return Err(bad("cam_to_world"));
            }
            let col = |c: usize| DVec3::new(m[0][c], m[1][c], m[2][c]);
            Ok(DAffine3::from_cols(col(0), col(1), col(2), col(3)))
        })
        .collect()
}

/// Writes the refined training cameras to `path`: each view's name and camera-to-world
/// matrix (4 × 4, rows) in the learnt frame and moved by `frame` into the dataset's.
fn write_poses(
    path: &Path,
    data: &Dataset,
    refined: &[DAffine3],
    frame: &Similarity,
) -> Result<()> {
    let rows = |p: &DAffine3| {
        (0..4)
            .map(|r| DMat4::from(*p).row(r).to_array())
            .collect::<Vec<_>>()
    };
    let views: Vec<serde_json::Value> = data
        .views()
        .iter()
        .zip(refined)
        .map(|(v, p)| {
            serde_json::json!({
                "name": v.name(),
                "cam_to_world": rows(p),
                "cam_to_world_aligned": rows(&frame.apply(*p)),
            })
        })
        .collect();
    write_json(path, &serde_json::json!({ "views": views }))
}

/// What a run measured on the held-out views.
pub struct Summary {
    pub mask_iou: f64,
    pub psnr_masked: f64,
    pub chamfer_l1: Option<f64>,
}

/// The mask IoU and PSNRs of `e` as JSON.
fn eval_json(e: &Evaluation) -> serde_json::Value {
    serde_json::json!({"mask_iou": e.iou, "psnr_masked": e.psnr_masked, "psnr_interior": e.psnr_interior})
}

/// `f` as JSON: `scale`, `rotation_wxyz`, `translation`.
fn similarity_json(f: &Similarity) -> serde_json::Value {
    let q = f.rotation;
    serde_json::json!({"scale": f.scale, "rotation_wxyz": [q.w, q.x, q.y, q.z], "translation": f.translation.to_array()})
}

pub fn run(args: &Args) -> Result<Summary> {
    let (device, dtype) = (Device::Cpu, DType::F32);
    let config = LoadConfig {
        background: Background::Color([1.0; 3]),
        downscale: args.downscale,
        ..LoadConfig::default()
    };
    let train = load(&args.data, &config)?;
    check_masks(&train)?;
    let true_poses = poses_of(&train);
    let train = match args.perturb {
        Some((degrees, fraction)) => perturb(&train, degrees, fraction, args.seed ^ 0x5EED)?,
        None => train,
    };
    let start_poses = poses_of(&train);
    // One learnable pose per training view, with its own optimiser (IDR's camera refinement).
    let poses = match args.refine_poses {
        true => start_poses
            .iter()
            .map(|p| PoseParam::from_affine(p, &device, dtype))
            .collect::<Result<Vec<_>>>()?,
        false => Vec::new(),
    };
    let mut pose_vars = Vec::new();
    for (v, p) in poses.iter().enumerate() {
        pose_vars.push((format!("pose{v}.rotation"), p.rotation.clone()));
        pose_vars.push((format!("pose{v}.translation"), p.translation.clone()));
    }
    let params = candle_nn::ParamsAdamW {
        lr: args.pose_lr,
        weight_decay: 0.0,
        ..Default::default()
    };
    let mut pose_opt =
        candle_nn::AdamW::new(pose_vars.iter().map(|(_, v)| v.clone()).collect(), params)?;
    let (eval, eval_split) = load_eval(&args.data, &config)?;
    let eval_split = format!("{eval_split:?}").to_lowercase();
    std::fs::create_dir_all(&args.out).map_err(|source| Error::Io {
        path: args.out.display().to_string(),
        source,
    })?;
    let aabb = train.scene_box(args.aabb);
    let mut varmap = VarMap::new();
    let (net, windows) = build(args, aabb, train.hash_finest(), &varmap, &device, dtype)?;
    let guard = FiniteGuard::new(&varmap);
    // The poses' variables, checked by a guard of their own.
    let pose_map = VarMap::new();
    pose_map
        .data()
        .lock()
        .expect("an unpoisoned VarMap") // invariant: not shared
        .extend(pose_vars.iter().cloned());
    let pose_guard = FiniteGuard::new(&pose_map);
    let lr0 = args.lr.unwrap_or(match (args.encoding, args.model) {
        (PositionEncoding::Hash, Model::Dvr | Model::DvrJoint) => 1e-2,
        _ => 1e-3,
    });
    let mut opt = adam(&varmap, lr0)?;
    if let Some(path) = &args.resume_poses {
        set_poses(&poses, &read_poses(path, &train)?)?;
    }
    if let Some(path) = &args.resume {
        varmap.load(path)?;
    } else if !matches!(net, Net::Idr { .. }) {
        // Start from a ball of radius 0.5 so that the first marches find a surface.
        let ball = Sphere::new([0.0; 3], 0.5, &device, dtype)?.occupancy(10.0);
        let mut rng = SplitMix64::new(args.seed ^ 0xBA11);
        for _ in 0..150 {
            let p = rng.uniform_tensor(&[4096, 3], aabb[0], aabb[3], dtype, &device)?;
            let y = ball.value(&p)?.gt(0.0)?.to_dtype(dtype)?;
            opt.backward_step(&bce_with_logits(&net.surface().value(&p)?, &y)?.mean_all()?)?;
        }
    }
    let mut sampler = RaySampler::new(&train, args.seed, &device, dtype)?;
    let mut clock = Clock::start(match args.steps {
        Some(n) => Budget::Steps(n),
        None => Budget::Minutes(args.minutes.unwrap_or(15.0)),
    })?;
    let bar = indicatif::ProgressBar::new(1000);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {percent}% {msg}")
            .expect("a valid template") // invariant: a literal
            .progress_chars("=> "),
    );
    let (model, lm) = (
        name(args.model),
        args.pose_solver == PoseSolver::Lm && !poses.is_empty(),
    );
    println!(
        "{model}: training on {} views of {}, evaluating on {} {eval_split} views",
        train.views().len(),
        args.data.display(),
        eval.views().len()
    );
    let mut curve = String::from("step,train_seconds,mask_iou,psnr_masked\n");
    let (mut step, mut registered_at) = (0usize, None);
    loop {
        let progress = clock.progress(step);
        if progress >= 1.0 {
            break;
        }
        let decay =
            |lr: f64| log_linear_schedule((progress * 10_000.0) as usize, lr, lr / 10.0, 10_000);
        opt.set_learning_rate(decay(lr0));
        pose_opt.set_learning_rate(decay(args.pose_lr));
        open_windows(&windows, progress, args.coarse_to_fine)?;
        let batch = sampler.patches(args.rays / 4, 2)?;
        let rays = match poses.is_empty() {
            true => batch.rays.clone(),
            false => batch_rays(&poses, &train, &batch)?,
        };
        let seed = args.seed ^ (step as u64).wrapping_mul(0x9E37_79B9);
        let mask = batch_mask(&batch, &train)?;
        let (loss, photo) = step_loss(&net, &rays, &batch.colors, &mask, aabb, progress, seed)?;
        let grads = loss.backward()?;
        guard.check(step, &loss, Some(&grads))?;
        pose_guard.check(step, &loss, Some(&grads))?;
        opt.step(&grads)?;
        // Adam moves the poses until the first registration; from then on the
        // registrations do.
        if !poses.is_empty() && registered_at.is_none() {
            pose_opt.step(&grads)?;
        }
        step += 1;
        let due = match registered_at {
            None => args.lm_start < 1.0 && progress >= args.lm_start,
            Some(at) => args.lm_every.is_some_and(|n| step >= at + n),
        };
        if lm && due {
            register_training(&net, args, &train, (&poses, &true_poses), aabb, step)?;
            registered_at = Some(step);
        }
        bar.set_position((1000.0 * clock.progress(step).min(1.0)) as u64);
        if step.is_multiple_of(10) {
            let l1 = photo.to_dtype(DType::F64)?.to_scalar::<f64>()?;
            bar.set_message(format!("step {step} photometric L1 {l1:.4}"));
        }
        if step.is_multiple_of(args.eval_every) {
            let seconds = clock.train_seconds();
            let (iou, p) = clock.pause(|| -> Result<(f64, f64)> {
                check_weights(&varmap, step)?;
                // The held-out cameras in the learnt frame by the fit of the centres.
                let (aligned, pose_note) = match poses.is_empty() {
                    true => (None, String::new()),
                    false => {
                        let (frame, refined) = alignment(&poses, &true_poses)?;
                        let moved: Vec<DAffine3> =
                            refined.iter().map(|p| frame.apply(*p)).collect();
                        let (r, t) = pose_error(&moved, &true_poses)?;
                        (
                            Some(in_learnt_frame(&eval, &frame)?),
                            format!(", poses (aligned) {r:.3}° / {:.3} %", 100.0 * t),
                        )
                    }
                };
                let e = evaluate(
                    &net,
                    aligned.as_ref().unwrap_or(&eval),
                    args.eval_views,
                    aabb,
                )?;
                println!(
                    "step {step}: held-out mask IoU {:.4}, masked PSNR {:.2} dB{pose_note}",
                    e.iou, e.psnr_masked
                );
                Ok((e.iou, e.psnr_masked))
            })?;
            curve.push_str(&format!("{step},{seconds:.3},{iou:.4},{p:.4}\n"));
        }
    }
    // The last registration, unless the last step just made one.
    if lm && registered_at != Some(step) {
        register_training(&net, args, &train, (&poses, &true_poses), aabb, step)?;
    }
    let train_seconds = clock.train_seconds();
    bar.finish_and_clear();
    // The windows as the schedule leaves them (every band open unless END > 1).
    open_windows(&windows, 1.0, args.coarse_to_fine)?;
    check_weights(&varmap, step)?;
    // With refined poses the scene was learnt in a frame of its own: the held-out cameras
    // are moved into it (and the mesh out of it) by the alignment of what the training
    // cameras see on the extracted surface; the poses are compared after the fit of their
    // centres (BARF's protocol).
    let extracted = extract_mesh(&net, aabb, args.mise_resolution)?;
    let (centres_frame, refined) = match poses.is_empty() {
        true => (Similarity::IDENTITY, start_poses.clone()),
        false => alignment(&poses, &true_poses)?,
    };
    let (frame, aligned_eval) = match poses.is_empty() {
        true => (Similarity::IDENTITY, None),
        false => {
            let f = view_alignment(&train, (&refined, &true_poses), &extracted, centres_frame)?;
            (f, Some(in_learnt_frame(&eval, &f)?))
        }
    };
    let registered = match &aligned_eval {
        Some(aligned) if args.test_pose_steps > 0 => Some(match args.pose_solver {
            PoseSolver::Adam => refine_eval_poses(
                &net,
                aligned,
                aabb,
                args.test_pose_steps,
                args.pose_lr,
                args.seed,
            )?,
            PoseSolver::Lm => {
                let rounds = (aabb, args.lm_iterations);
                aligned.with_poses(&register(
                    &net,
                    aligned,
                    &poses_of(aligned),
                    rounds,
                    &mut |_, _| {},
                )?)?
            }
        }),
        _ => None,
    };
    let final_eval = registered
        .as_ref()
        .or(aligned_eval.as_ref())
        .unwrap_or(&eval);
    let all = evaluate(&net, final_eval, eval.views().len(), aabb)?;
    let first = evaluate(&net, final_eval, args.eval_views, aabb)?;
    curve.push_str(&format!(
        "{step},{train_seconds:.3},{:.4},{:.4}\n",
        first.iou, first.psnr_masked
    ));
    for (i, [truth, color, normals]) in all.renders.iter().enumerate().take(args.pictures) {
        write_png(
            &args.out.join(format!("view_{i}.png")),
            &comparison_strip(truth, color)?,
        )?;
        write_png(
            &args.out.join(format!("normals_{i}.png")),
            &normals.affine(0.5, 0.5)?,
        )?;
    }
    // The mesh in the dataset's frame; as extracted too when the frames differ.
    let (mesh, learnt_mesh) = match poses.is_empty() {
        true => (extracted, None),
        false => (
            mesh_to_dataset_frame(extracted.clone(), &frame),
            Some(extracted),
        ),
    };
    let gt = source_mesh(args)?;
    let chamfer_of = |m: &Mesh| -> Result<Option<f64>> {
        match (&gt, m.faces.is_empty()) {
            (Some(gt), false) => Ok(Some(chamfer(m, gt, args.seed)?)),
            _ => Ok(None),
        }
    };
    let chamfer_l1 = chamfer_of(&mesh)?;
    let chamfer_l1_icp = match (&gt, mesh.faces.is_empty()) {
        (Some(gt), false) => Some(chamfer_icp(&mesh, gt, 100_000, args.seed)?),
        _ => None,
    };
    if !mesh.faces.is_empty() {
        mesh.save(args.out.join("mesh.ply"))?;
    }
    varmap.save(args.out.join("weights.safetensors"))?;
    write(&args.out.join("curve.csv"), &curve)?;
    let mut metrics = eval_json(&all);
    for (key, value) in [
        ("chamfer_l1", serde_json::json!(chamfer_l1)),
        ("chamfer_l1_icp", serde_json::json!(chamfer_l1_icp)),
        ("train_seconds", serde_json::json!(train_seconds)),
        ("steps", serde_json::json!(step)),
        ("model", serde_json::json!(model)),
        ("encoding", serde_json::json!(name(args.encoding))),
        ("render_inputs", serde_json::json!(name(args.render_inputs))),
        ("eval_split", serde_json::json!(eval_split)),
        ("eval_views", serde_json::json!(eval.views().len())),
        ("data", serde_json::json!(args.data.display().to_string())),
    ] {
        metrics[key] = value;
    }
    if args.perturb.is_some() || args.refine_poses {
        let moved: Vec<DAffine3> = refined.iter().map(|p| centres_frame.apply(*p)).collect();
        let (r0, t0) = pose_error(&start_poses, &true_poses)?;
        let (r1, t1) = pose_error(&refined, &true_poses)?;
        let (r2, t2) = pose_error(&moved, &true_poses)?;
        println!(
            "training poses: rotation error {r0:.3}° → {r1:.3}° ({r2:.3}° aligned), centre error \
             {:.3} % → {:.3} % ({:.3} % aligned) of the distance",
            100.0 * t0,
            100.0 * t1,
            100.0 * t2
        );
        metrics["pose_rotation_error_deg"] =
            serde_json::json!({"before": r0, "after": r1, "after_aligned": r2});
        metrics["pose_centre_error_fraction"] =
            serde_json::json!({"before": t0, "after": t1, "after_aligned": t2});
        metrics["pose_solver"] = serde_json::json!(name(args.pose_solver));
        // Both on the extracted surface: the start poses (in the dataset's frame) see it
        // placed where the refined cameras put it. `null` where no camera sees it.
        let points = mesh_points(learnt_mesh.as_ref().unwrap_or(&mesh));
        let moved_points: Vec<DVec3> = points.iter().map(|&y| frame.apply(y)).collect();
        let truth = cameras_at(&train, &true_poses)?;
        let px =
            |poses: &[DAffine3], points: &[DVec3], frame: &Similarity| -> Result<Option<f64>> {
                Ok(
                    reprojection_error(&cameras_at(&train, poses)?, &truth, points, frame)
                        .map_err(|e| eprintln!("no reprojection error: {e}"))
                        .ok(),
                )
            };
        let before = px(&start_poses, &moved_points, &Similarity::IDENTITY)?;
        let after = px(&refined, &points, &frame)?;
        if let (Some(b), Some(a)) = (before, after) {
            println!("training cameras' reprojection error {b:.3} px → {a:.3} px");
        }
        metrics["pose_reprojection_px"] = serde_json::json!({"before": before, "after": after});
    }
    if let (Some(aligned), Some(_)) = (&aligned_eval, &registered) {
        metrics["aligned"] = eval_json(&evaluate(&net, aligned, eval.views().len(), aabb)?);
        metrics["test_pose_steps"] = serde_json::json!(args.test_pose_steps);
    }
    if let Some(learnt) = &learnt_mesh {
        let mut unaligned = eval_json(&evaluate(&net, &eval, eval.views().len(), aabb)?);
        unaligned["chamfer_l1"] = serde_json::json!(chamfer_of(learnt)?);
        metrics["unaligned"] = unaligned;
        metrics["alignment"] = similarity_json(&frame);
        metrics["alignment_centres"] = similarity_json(&centres_frame);
        let by_centres = chamfer_of(&mesh_to_dataset_frame(learnt.clone(), &centres_frame))?;
        metrics["chamfer_l1_centres"] = serde_json::json!(by_centres);
        write_poses(&args.out.join("poses.json"), &train, &refined, &frame)?;
    }
    write_json(&args.out.join("metrics.json"), &metrics)?;
    println!(
        "{step} steps in {train_seconds:.1} s: held-out mask IoU {:.4}, masked PSNR {:.2} dB, \
         Chamfer-L1 {} over {} {eval_split} views; wrote {}",
        all.iou,
        all.psnr_masked,
        chamfer_l1.map_or("unknown".into(), |c| format!("{c:.5}")),
        eval.views().len(),
        args.out.display()
    );
    Ok(Summary {
        mask_iou: all.iou,
        psnr_masked: all.psnr_masked,
        chamfer_l1,
    })
}

fn main() -> std::process::ExitCode {
    let args = match Args::parse().check() {
        Ok(a) => a,
        Err(msg) => {
            eprintln!("{msg}");
            return std::process::ExitCode::from(2);
        }
    };
    match run(&args) {
        Ok(_) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("dvr_multiview: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use neural_fields::data::View;

    fn read_json(path: &Path) -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
    }

    /// Each model (and encoding, and IDR's input ablations) for a few steps on the
    /// committed dataset at a quarter of its resolution: the whole pipeline runs and writes
    /// every output with the documented keys.
    #[test]
    fn a_shortened_run_of_each_model_writes_its_outputs() {
        for (model, encoding, render_inputs) in [
            (Model::Dvr, PositionEncoding::Pe, RenderInputs::Full),
            (Model::DvrJoint, PositionEncoding::Pe, RenderInputs::Full),
            (Model::Idr, PositionEncoding::Pe, RenderInputs::Full),
            (Model::Idr, PositionEncoding::Pe, RenderInputs::NoView),
            (Model::Idr, PositionEncoding::Pe, RenderInputs::NoNormal),
            (Model::Dvr, PositionEncoding::Hash, RenderInputs::Full),
            (Model::Idr, PositionEncoding::Hash, RenderInputs::Full),
        ] {
            let id = format!(
                "{model:?}-{encoding:?}-{render_inputs:?}-{}",
                std::process::id()
            );
            let out = std::env::temp_dir().join(format!("dvr-multiview-{id}"));
            let _ = std::fs::remove_dir_all(&out);
            let args = Args {
                steps: Some(4),
                out: out.clone(),
                seed: 1,
                model,
                encoding,
                render_inputs,
                downscale: 4,
                rays: 256,
                eval_every: 2,
                eval_views: 1,
                pictures: 1,
                mise_resolution: 8,
                ..Args::default()
            };
            let summary = run(&args).unwrap();
            assert!((0.0..=1.0).contains(&summary.mask_iou));
            let metrics = read_json(&out.join("metrics.json"));
            assert_eq!(metrics["encoding"], name(encoding));
            for key in [
                "mask_iou",
                "psnr_masked",
                "psnr_interior",
                "train_seconds",
                "steps",
            ] {
                let value = metrics[key].as_f64();
                assert!(value.is_some_and(f64::is_finite), "{key}: {metrics}");
            }
            assert!(metrics.get("chamfer_l1").is_some(), "{metrics}");
            assert!(metrics.get("chamfer_l1_icp").is_some(), "{metrics}");
            assert_eq!(metrics["steps"], 4);
            assert_eq!(metrics["render_inputs"], name(render_inputs));
            let curve = std::fs::read_to_string(out.join("curve.csv")).unwrap();
            assert_eq!(curve.lines().count(), 1 + 2 + 1);
            for file in ["view_0.png", "normals_0.png", "weights.safetensors"] {
                assert!(out.join(file).is_file(), "{file}");
            }
            let _ = std::fs::remove_dir_all(&out);
        }
    }

    /// The flags keep their names and defaults; the checks across flags refuse what they
    /// should.
    #[test]
    fn flags_parse_with_their_defaults() {
        let a = Args::default().check().unwrap();
        assert_eq!(
            (a.model, a.rays, a.minutes, a.pose_solver),
            (Model::Dvr, 1024, Some(15.0), PoseSolver::Adam)
        );
        let line = [
            "x",
            "--model",
            "dvr-joint",
            "--perturb",
            "3,0.03",
            "--refine-poses",
            "on",
            "--coarse-to-fine",
            "0.1,0.5",
            "--steps",
            "9",
        ];
        let a = Args::parse_from(line).check().unwrap();
        assert_eq!(
            (a.model, a.perturb, a.refine_poses, a.coarse_to_fine),
            (Model::DvrJoint, Some((3.0, 0.03)), true, Some((0.1, 0.5)))
        );
        assert!(Args::parse_from(["x", "--steps", "1", "--minutes", "2"])
            .check()
            .is_err());
        assert!(Args::try_parse_from(["x", "--perturb", "-1,0"]).is_err());
        assert!(Args::parse_from(["x", "--lm-start", "2"]).check().is_err());
    }

    /// The perturbation moves every camera by exactly the asked rotation and centre shift,
    /// and shortened runs with pose refinement (Adam, and Levenberg–Marquardt registrations
    /// after the first step, two steps later and after the last) report the pose errors
    /// before and after, evaluate in the learnt frame and write the poses.
    #[test]
    fn perturbed_poses_are_measured_and_refined() {
        let config = LoadConfig {
            downscale: 4,
            ..LoadConfig::default()
        };
        let data = load(Path::new("examples/data/wuson"), &config).unwrap();
        let truth = poses_of(&data);
        let moved = perturb(&data, 3.0, 0.03, 7).unwrap();
        let (r, t) = pose_error(&poses_of(&moved), &truth).unwrap();
        // The committed poses are Blender's float32 matrices: orthonormal to about 1e-7.
        assert!((r - 3.0).abs() < 1e-4, "{r}");
        assert!((t - 0.03).abs() < 1e-9, "{t}");
        let out = std::env::temp_dir().join(format!("dvr-multiview-poses-{}", std::process::id()));
        let shortened = |out: PathBuf| Args {
            steps: Some(3),
            out,
            downscale: 4,
            rays: 256,
            eval_every: 10,
            eval_views: 1,
            pictures: 0,
            mise_resolution: 8,
            perturb: Some((3.0, 0.03)),
            refine_poses: true,
            test_pose_steps: 2,
            ..Args::default()
        };
        let lm = Args {
            pose_solver: PoseSolver::Lm,
            lm_every: Some(2),
            lm_iterations: 1,
            lm_start: 0.0,
            ..shortened(out.join("lm"))
        };
        run(&lm).unwrap();
        let m = read_json(&lm.out.join("metrics.json"));
        let after = m["pose_rotation_error_deg"]["after"].as_f64().unwrap();
        assert!(after.is_finite() && (after - 3.0).abs() > 1e-6, "{m}");
        assert_eq!(m["pose_solver"], "lm");
        let reprojection = m["pose_reprojection_px"].as_object().unwrap();
        assert!(reprojection.contains_key("before") && reprojection.contains_key("after"));
        run(&shortened(out.clone())).unwrap();
        let metrics = read_json(&out.join("metrics.json"));
        let before = metrics["pose_rotation_error_deg"]["before"]
            .as_f64()
            .unwrap();
        let after = metrics["pose_rotation_error_deg"]["after"]
            .as_f64()
            .unwrap();
        assert!((before - 3.0).abs() < 1e-3, "{metrics}");
        assert!(after.is_finite() && after != before, "{metrics}");
        assert!(metrics["pose_rotation_error_deg"]["after_aligned"].is_f64());
        assert!(metrics["unaligned"]["mask_iou"].is_f64(), "{metrics}");
        assert!(metrics["aligned"]["mask_iou"].is_f64(), "{metrics}");
        assert_eq!(metrics["test_pose_steps"], 2);
        let scale = metrics["alignment"]["scale"].as_f64().unwrap();
        assert!((scale - 1.0).abs() < 0.1, "{metrics}");
        let poses = read_json(&out.join("poses.json"));
        let views = poses["views"].as_array().unwrap();
        assert_eq!(views.len(), data.views().len());
        assert_eq!(views[0]["name"], data.views()[0].name());
        let last_row = serde_json::json!([0.0, 0.0, 0.0, 1.0]);
        assert_eq!(views[0]["cam_to_world_aligned"][3], last_row);
        // The written poses read back.
        let back = read_poses(&out.join("poses.json"), &moved).unwrap();
        assert_eq!(back.len(), data.views().len());
        let _ = std::fs::remove_dir_all(&out);
    }

    /// Regression: a registration took out the similarity common to the registered
    /// cameras' moves, which moved every camera off the scene it had just been registered
    /// to. The poses `register_training` leaves are the ones the registration found (and
    /// the registration did move them).
    #[test]
    fn a_registration_moved_the_cameras_off_their_scene() {
        use neural_fields::camera::{Convention, Intrinsics};
        use neural_fields::data::Image;
        // The untrained network's own scene, rendered from eight cameras 6 units away:
        // views the network explains exactly at the true poses. The cameras are then
        // perturbed and registered to it.
        let args = Args {
            lm_iterations: 1,
            ..Args::default()
        };
        let aabb = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0];
        let varmap = VarMap::new();
        let (net, _) = build(&args, aabb, 16.0, &varmap, &Device::Cpu, DType::F32).unwrap();
        let n = 48;
        let k = Intrinsics::from_fov_y(n, n, 0.6).unwrap();
        let byte = |x: f32| (x.clamp(0.0, 1.0) * 255.0).round() as u8;
        let views = (0..8)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / 8.0;
                let eye = DVec3::new(6.0 * a.cos(), 6.0 * a.sin(), 1.5);
                let cam =
                    Camera::look_at(k, eye, DVec3::ZERO, DVec3::Z, Convention::OpenGl).unwrap();
                let rays = cam.rays(&Device::Cpu, DType::F32).unwrap();
                let [rgb, _, coverage, _] = shade_rays(&net, &rays, aabb).unwrap();
                let rgb = rgb.flatten_all().unwrap().to_vec1::<f32>().unwrap();
                let alpha = coverage.to_vec1::<f32>().unwrap();
                let image = Image::new(n, n, 3, rgb.into_iter().map(byte).collect()).unwrap();
                let mask = Image::new(n, n, 1, alpha.into_iter().map(byte).collect()).unwrap();
                View::new(cam, image, Some(mask), format!("v{i}")).unwrap()
            })
            .collect();
        let data = Dataset::new(views, Background::Color([1.0; 3]), None).unwrap();
        let truth = poses_of(&data);
        let train = perturb(&data, 3.0, 0.03, 7).unwrap();
        let start = poses_of(&train);
        let expected = register(&net, &train, &start, (aabb, 1), &mut |_, _| {}).unwrap();
        let (turn, shift) = pose_error(&expected, &start).unwrap();
        assert!(turn > 1e-3 && shift > 1e-4, "{turn}° / {shift}");
        let poses: Vec<PoseParam> = start
            .iter()
            .map(|p| PoseParam::from_affine(p, &Device::Cpu, DType::F32).unwrap())
            .collect();
        register_training(&net, &args, &train, (&poses, &truth), aabb, 0).unwrap();
        for (p, e) in poses.iter().zip(&expected) {
            let (turn, shift) = pose_error(&[p.to_affine().unwrap()], &[*e]).unwrap();
            assert!(
                turn < 1e-4 && shift < 1e-6,
                "{turn}° / {shift} from the registration"
            );
        }
    }

    /// A one-view dataset of a 4 × 4 image with `channels` channels of `value`.
    fn tiny_dataset(channels: usize, value: u8) -> Dataset {
        let k = neural_fields::camera::Intrinsics::from_fov_y(4, 4, 0.8).unwrap();
        let gl = neural_fields::camera::Convention::OpenGl;
        let cam = Camera::look_at(k, DVec3::new(0.0, 0.0, 3.0), DVec3::ZERO, DVec3::Y, gl).unwrap();
        let image = neural_fields::data::Image::new(4, 4, channels, vec![value; 16 * channels]);
        let view = View::new(cam, image.unwrap(), None, "tiny.png".into()).unwrap();
        Dataset::new(vec![view], Background::default(), None).unwrap()
    }

    #[test]
    fn views_without_masks_or_with_empty_masks_are_refused() {
        let e = check_masks(&tiny_dataset(3, 100)).unwrap_err().to_string();
        assert!(e.starts_with("data: expected views with masks"), "{e}");
        assert!(e.contains("tiny.png"), "{e}");
        let e = check_masks(&tiny_dataset(4, 0)).unwrap_err().to_string();
        assert!(
            e.starts_with("data: expected masks that cover the object"),
            "{e}"
        );
        assert!(check_masks(&tiny_dataset(4, 255)).is_ok());
    }
}
