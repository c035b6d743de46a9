//! 3-D reconstruction from multi-view images: shape and colour of an object from its RGBA
//! (or image + mask) views, by surface rendering with implicit gradients (DVR, IDR).
//!
//! ```text
//! cargo run --release --example dvr_multiview                          # the committed dataset, DVR, 15 minutes
//! cargo run --release --example dvr_multiview -- --model idr --minutes 15 --out out/idr
//! cargo run --release --example dvr_multiview -- --data DIR --steps 2000 --seed 3
//! ```
//!
//! **Data.** `--data DIR` is any dataset [`neural_fields::data::load`] reads whose views
//! have masks (an alpha channel or mask files; default `examples/data/wuson`). The `train`
//! split trains; the `test` split (the `val` split if there is none) is held out, its
//! images composited on white. `--downscale K` divides the resolution by K.
//!
//! **One step** (DVR's, on `--rays` pixels drawn as 2 × 2 patches across the views):
//! 1. march the rays through the scene box (64 samples + 8 secant steps; sphere tracing
//!    for the IDR model), detached;
//! 2. [`implicit_surface`] makes the hit points `p̂` differentiable w.r.t. the network;
//! 3. the colour at `p̂`; losses:
//!    - L1 photometric on rays that hit inside the mask, and DVR's image-gradient loss on
//!      the patches that lie wholly there ([`image_gradient_loss`], weight 1);
//!    - `--model dvr` ([`JointDecoder`]: one trunk, occupancy logit + colour): freespace
//!      BCE at the (detached) hit of rays outside the mask or at a random point of those
//!      that hit nothing, occupancy BCE at a random point of mask rays that hit nothing,
//!      normal smoothness (weight 0.05) at the surface points;
//!    - `--model idr` (an SDF [`Mlp`] with geometric initialisation and a feature output,
//!      and IDR's [`RenderingNet`] reading the point, the view direction, the normal
//!      `∇f(p̂)` and the feature, so the colour reaches the geometry through the normal):
//!      IDR's mask loss on rays outside `hit ∧ mask` at the most-inside of 64 samples
//!      (weight 100, α from 50 doubling at IDR's epochs 250…1250 of 2000, mapped to the
//!      run's progress) and the eikonal loss (weight 0.1) at random points and at the
//!      surface points. `--render-inputs no-view` or `no-normal` drops the view direction
//!      or the normal from the rendering network's input (IDR's two ablation modes).
//!
//! `--encoding hash` gives the DVR models' networks instant-NGP's multiresolution hash grid
//! over the scene box (16 levels of 2 features, 2¹⁵ rows per level, resolutions 16 to five
//! cells per pixel of the images' larger side; one grid for the occupancy network, one for
//! the texture field) on 2 × 64 trunks, with `--lr` 1e-2 by default. For IDR it gives the
//! rendering network a hash grid on the surface point and keeps the SDF's frequency
//! encoding (its geometric initialisation needs the point itself in the input) and the
//! learning rate of 1e-3.
//!
//! The geometry starts as a ball of radius 0.5 (DVR: 150 steps fitting its occupancy;
//! IDR: the geometric initialisation), so that rays find a surface from the first step.
//! Adam, learning rate decaying log-linearly from `--lr` (1e-3) to a tenth of it.
//!
//! **Evaluation** renders each held-out pixel with 2 × 2 rays on a sub-pixel grid and
//! averages them (misses count as the white background): the images were rendered by
//! integrating over each pixel, so their object edges are antialiased, which one surface
//! point per pixel cannot reproduce. A pixel is predicted inside the object when at least
//! half of its rays hit.
//!
//! **Output** in `--out DIR` (default `out/dvr_multiview`):
//! - `metrics.json`: on the held-out views, `mask_iou` (predicted coverage ≥ ½ against the
//!   mask ≥ ½, pooled over the views), `psnr_masked` (PSNR of the prediction on white, inside the
//!   true mask, pooled), `chamfer_l1` (of the extracted mesh to the source mesh, both in the
//!   source mesh's unit cube; `null` when the source mesh is not known), `psnr_interior`
//!   (the same on the fully covered pixels, mask = 1: without the antialiased edge, which
//!   one surface point per pixel cannot reproduce), `train_seconds`,
//!   `steps`, `model`, `eval_split`, `eval_views`, `data`;
//! - `curve.csv`: `step,train_seconds,mask_iou,psnr_masked` every `--eval-every` steps
//!   (on the first `--eval-views` held-out views);
//! - `view_{i}.png` (truth | prediction | error) and `normals_{i}.png` for the first
//!   `--pictures` held-out views;
//! - `mesh.ply`: the surface extracted by MISE (32³ refined twice, 128³ at the surface),
//!   with the texture's colours at its vertices (MeshLab and Blender show them);
//! - `weights.safetensors`, which `--resume FILE` loads (the same `--model`) to continue
//!   training, or with `--steps 0` to evaluate.
//!
//! **Camera refinement** (IDR's): `--perturb DEGREES,FRACTION` first moves every training
//! camera (a rotation by DEGREES about a random axis, its centre shifted by FRACTION of its
//! distance to the origin; seeded), and `--refine-poses on` learns one
//! [`PoseParam`] per training view (unit quaternion and centre) through the rays, with its
//! own Adam at `--pose-lr` (1e-3, decaying like the network's). `--coarse-to-fine
//! START,END` puts every position encoding under BARF's window ([`CoarseToFine`]): only
//! the raw point (frequency encodings) or the coarsest level (hash grids) at first, the
//! finer bands fading in from the fraction START of the training budget to END (BARF's
//! schedule is `0.1,0.5`), so that the poses move while the fields are still smooth.
//!
//! Jointly refined cameras are determined only up to a similarity of the whole scene, so
//! a run that refines poses is evaluated as BARF's are: the similarity that best maps the
//! refined training-camera centres onto the true ones ([`align_similarity`]) moves the
//! held-out cameras into the learnt frame for the held-out metrics (and `curve.csv`), and
//! the extracted mesh out of it for the Chamfer distance and `mesh.ply`. `metrics.json`
//! then also holds `unaligned` (`mask_iou`, `psnr_masked`, `psnr_interior`, `chamfer_l1`
//! without the alignment), `alignment` (`scale`, `rotation_wxyz`, `translation`),
//! `pose_rotation_error_deg` and `pose_centre_error_fraction` (`before` and `after`
//! training and `after_aligned`, means over the training views against the unperturbed
//! poses), and `poses.json` the refined cameras (`views`: `name`, `cam_to_world` in the
//! learnt frame and `cam_to_world_aligned`, 4 × 4 rows). With `--perturb` alone the
//! pose errors are reported and nothing is aligned. After the alignment, each held-out
//! camera is refined against its own image with the network fixed (BARF's test-time
//! refinement, `--test-pose-steps` Adam steps of 256 rays at `--pose-lr`, default 100; 0
//! skips it), so that the held-out metrics measure the scene rather than the alignment;
//! `aligned` in `metrics.json` holds them before that refinement. `--resume-poses FILE`
//! starts the training poses from a run's `poses.json` (with `--resume` and `--steps 0`:
//! evaluate a finished run again). Every run also reports `chamfer_l1_icp`: Chamfer-L1
//! after a similarity ICP of the mesh onto the source mesh, the shape's error apart from
//! its placement (one-sided, so it can exceed `chamfer_l1` for a well-placed mesh).
//!
//! The source mesh is `--mesh FILE` (in the dataset's world frame), or the mesh that the
//! dataset's `scene.json` names (`mesh`, with its `normalisation.matrix`, as the committed
//! dataset's render script writes it) when that file exists.
//!
//! A NaN or infinity in the loss, a gradient or a weight stops the run with an error naming
//! the step and the tensor.

use candle_core::{DType, Device, Tensor};
use candle_nn::{Optimizer, VarMap};
use common::PositionEncoding;
use neural_fields::camera::{
    align_similarity, ray_aabb, Camera, Intersection, PixelFilter, PoseParam, Rays, Similarity,
};
use neural_fields::data::{
    colorize_normals, comparison_strip, load, psnr, write_png, Background, Dataset, LoadConfig,
    RayBatch, RaySampler, View,
};
use neural_fields::dvr::{
    eikonal_loss, idr_mask_loss, implicit_surface, march, most_inside_along_rays,
    normal_smoothness_loss, photometric_loss, sphere_trace, AlphaSchedule, Hits, ImplicitConfig,
    MarchConfig, Photometric, SphereTraceConfig, SurfacePoints,
};
use neural_fields::encoding::{CoarseToFine, FrequencyEncoding, PointEncoding};
use neural_fields::field::{ImplicitSurface, SignedDistance, Sphere};
use neural_fields::glam::{DAffine3, DMat3, DMat4, DQuat, DVec2, DVec3};
use neural_fields::nn::{
    build_seeded, joint_decoder, mlp, rendering_net, texture_decoder, JointDecoder, Mlp, MlpConfig,
    RenderingNet, RenderingNetConfig, TextureDecoder, TextureDecoderConfig,
};
use neural_fields::numerics::bce_with_logits;
use neural_fields::occupancy::{mesh_metrics, mise, KdTree, Mesh, MiseConfig};
use neural_fields::rng::SplitMix64;
use neural_fields::texture::{image_gradient_loss, vertex_colors, TextureField, TextureInput};
use neural_fields::volume::log_linear_schedule;
use neural_fields::{Error, Result};
use std::path::{Path, PathBuf};

#[path = "common/mod.rs"]
mod common;
#[path = "common/training.rs"]
mod training;

#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// log₂ of the rows of each hash-grid level (`--encoding hash`).
const HASH_LOG2: u32 = 15;
/// Rays per chunk when rendering whole views.
const CHUNK: usize = 8192;
/// Rays per pixel side when rendering held-out views (2 × 2 per pixel).
const SUPERSAMPLE: usize = 2;

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Model {
    /// An occupancy network and a texture field (the Texture Fields decoder on
    /// frequency-encoded points).
    Dvr,
    /// DVR's joint decoder: one trunk for occupancy and colour.
    DvrJoint,
    /// IDR: an SDF network with a feature output and IDR's rendering network.
    Idr,
}

impl Model {
    /// The name on the command line.
    fn name(self) -> &'static str {
        match self {
            Model::Dvr => "dvr",
            Model::DvrJoint => "dvr-joint",
            Model::Idr => "idr",
        }
    }
}

#[derive(Debug)]
pub struct Args {
    pub data: PathBuf,
    pub minutes: Option<f64>,
    pub steps: Option<usize>,
    pub out: PathBuf,
    pub seed: u64,
    pub model: Model,
    pub downscale: usize,
    pub rays: usize,
    pub aabb: f64,
    pub eval_every: usize,
    pub eval_views: usize,
    pub pictures: usize,
    /// The learning rate (`None`: 1e-3, or 1e-2 for the DVR models on hash grids).
    pub lr: Option<f64>,
    pub encoding: PositionEncoding,
    /// IDR's rendering-network inputs beside the point and the feature: `full` (view
    /// direction and normal), `no-view` or `no-normal` (IDR's two ablation modes).
    pub render_inputs: RenderInputs,
    pub mesh: Option<PathBuf>,
    pub mise_resolution: usize,
    /// Perturb the training poses: (degrees, fraction of the camera's distance).
    pub perturb: Option<(f64, f64)>,
    pub refine_poses: bool,
    pub pose_lr: f64,
    /// BARF's coarse-to-fine window: the encodings' bands fade in from the start to the
    /// end of this span of the training (fractions of the budget).
    pub coarse_to_fine: Option<(f64, f64)>,
    /// BARF's test-time refinement of each held-out pose (steps per view; 0: none).
    pub test_pose_steps: usize,
    /// Refined training poses to start from (a run's `poses.json`).
    pub resume_poses: Option<PathBuf>,
    pub resume: Option<PathBuf>,
}

impl Default for Args {
    /// The defaults of the command line.
    fn default() -> Self {
        Self {
            data: PathBuf::from("examples/data/wuson"),
            minutes: None,
            steps: None,
            out: PathBuf::from("out/dvr_multiview"),
            seed: 0,
            model: Model::Dvr,
            downscale: 1,
            rays: 1024,
            aabb: 1.1,
            eval_every: 500,
            eval_views: 4,
            pictures: 4,
            lr: None,
            encoding: PositionEncoding::Pe,
            render_inputs: RenderInputs::Full,
            mesh: None,
            mise_resolution: 32,
            perturb: None,
            refine_poses: false,
            pose_lr: 1e-3,
            coarse_to_fine: None,
            test_pose_steps: 100,
            resume_poses: None,
            resume: None,
        }
    }
}

/// Which of IDR's rendering-network inputs to read besides the point and the feature.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RenderInputs {
    /// The view direction and the normal (IDR).
    Full,
    /// The normal, no view direction (IDR's `no_view_dir` mode: no view-dependent colour).
    NoView,
    /// The view direction, no normal (IDR's `no_normal` mode).
    NoNormal,
}

impl RenderInputs {
    fn parse(value: &str) -> std::result::Result<Self, String> {
        match value {
            "full" => Ok(Self::Full),
            "no-view" => Ok(Self::NoView),
            "no-normal" => Ok(Self::NoNormal),
            other => Err(format!(
                "--render-inputs: full, no-view or no-normal, not {other}"
            )),
        }
    }

    fn name(self) -> &'static str {
        match self {
            Self::Full => "full",
            Self::NoView => "no-view",
            Self::NoNormal => "no-normal",
        }
    }

    /// IDR's rendering-network defaults with these inputs.
    fn config(self) -> RenderingNetConfig {
        let idr = RenderingNetConfig::default();
        match self {
            Self::Full => idr,
            Self::NoView => RenderingNetConfig {
                view_frequencies: None,
                ..idr
            },
            Self::NoNormal => RenderingNetConfig {
                use_normals: false,
                ..idr
            },
        }
    }
}

const USAGE: &str = "usage: dvr_multiview [--data DIR] [--minutes M | --steps N] [--out DIR] \
[--seed S] [--model dvr|dvr-joint|idr] [--downscale K] [--rays N] [--aabb R] [--eval-every N] \
[--eval-views N] [--pictures N] [--lr LR] [--mesh FILE] [--mise-resolution N] \
[--perturb DEGREES,FRACTION] [--refine-poses on|off] [--pose-lr LR] \
[--coarse-to-fine START,END] [--test-pose-steps N] [--resume FILE] [--resume-poses FILE] \
[--encoding pe|hash] [--render-inputs full|no-view|no-normal]";

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
            "--model" => {
                a.model = match value {
                    "dvr" => Model::Dvr,
                    "dvr-joint" => Model::DvrJoint,
                    "idr" => Model::Idr,
                    other => return Err(format!("--model: dvr, dvr-joint or idr, not {other}")),
                }
            }
            "--downscale" => a.downscale = int(flag, value)?,
            "--rays" => a.rays = int(flag, value)?,
            "--aabb" => a.aabb = num(flag, value)?,
            "--eval-every" => a.eval_every = int(flag, value)?,
            "--eval-views" => a.eval_views = int(flag, value)?,
            "--pictures" => a.pictures = int(flag, value)?,
            "--lr" => a.lr = Some(num(flag, value)?),
            "--encoding" => a.encoding = PositionEncoding::parse(value)?,
            "--render-inputs" => a.render_inputs = RenderInputs::parse(value)?,
            "--mesh" => a.mesh = Some(value.into()),
            "--mise-resolution" => a.mise_resolution = int(flag, value)?,
            "--perturb" => match training::pair(flag, value, "3,0.03")? {
                [d, f] if d >= 0.0 && f >= 0.0 => a.perturb = Some((d, f)),
                _ => return Err(format!("--perturb: DEGREES,FRACTION ≥ 0, not {value}")),
            },
            "--coarse-to-fine" => a.coarse_to_fine = Some(training::window_span(flag, value)?),
            "--refine-poses" => a.refine_poses = training::on_off(flag, value)?,
            "--pose-lr" => a.pose_lr = num(flag, value)?,
            "--resume" => a.resume = Some(value.into()),
            "--resume-poses" => a.resume_poses = Some(value.into()),
            "--test-pose-steps" => a.test_pose_steps = int(flag, value)?,
            other => return Err(format!("unknown flag {other}\n{USAGE}")),
        }
        Ok(())
    })?;
    training::check_budget(&mut a.minutes, a.steps, 15.0)?;
    if a.rays < 4 || a.eval_every == 0 || a.eval_views == 0 || a.mise_resolution < 2 {
        return Err(
            "--rays must be at least 4, --eval-every and --eval-views positive, \
             --mise-resolution at least 2"
                .into(),
        );
    }
    if !(a.aabb > 0.0 && a.aabb.is_finite()) {
        return Err("--aabb must be positive".into());
    }
    Ok(a)
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
                let input = TextureInput::new(points)
                    .normals(&normal)
                    .view_dirs(dirs)
                    .features(&feature);
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
        window(
            args.encoding
                .build(frequencies, lo, hi, HASH_LOG2, finest, vb)?,
        )
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
                    ..args.render_inputs.config()
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
    if let Some(v) = data.views().iter().find(|v| !v.has_mask()) {
        return Err(no_mask(v.name()));
    }
    let mut covered = 0.0;
    for v in data.views() {
        if let Some(m) = v.mask(&Device::Cpu, DType::F32)? {
            let inside = m.ge(0.5)?.to_dtype(DType::F32)?.sum_all()?;
            covered += f64::from(inside.to_scalar::<f32>()?);
        }
    }
    if covered == 0.0 {
        return Err(Error::InvalidArgument {
            arg: "data",
            expected: "masks that cover the object in some training view".into(),
            got: format!("{} views whose masks are all empty", data.len()),
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
    let surf: SurfacePoints =
        implicit_surface(net.surface(), rays, &hits, &ImplicitConfig::default())?;
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
            &common::rows(&shaded.rgb, &on)?,
            &common::rows(colors, &on_rays)?,
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
                let (sub, sub_range) = common::select(rays, &range, which)?;
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
                let (sub, sub_range) = common::select(rays, &range, &outside)?;
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

/// A held-out view rendered whole without graph, with `k × k` rays per pixel on a
/// regular sub-pixel grid averaged (the image's renderer integrated over the pixel too, so
/// that its object edges are antialiased): colour on white `[H, W, 3]`, the covered
/// fraction `[H, W]` of each pixel, normals `[H, W, 3]` (outward, averaged; 0 where
/// nothing is hit).
fn render_view(
    net: &Net,
    data: &Dataset,
    v: usize,
    aabb: [f64; 6],
    k: usize,
) -> Result<(Tensor, Tensor, Tensor)> {
    let cam = data.views()[v].camera();
    let (w, h) = (cam.intrinsics().width, cam.intrinsics().height);
    let [x0, y0, z0, x1, y1, z1] = aabb;
    let all =
        cam.rays_for_pixels(&cam.subpixel_grid(k, PixelFilter::Box, &Device::Cpu, DType::F32)?)?;
    let n = all.len();
    let (mut colors, mut masks, mut normals) = (Vec::new(), Vec::new(), Vec::new());
    for start in (0..n).step_by(CHUNK) {
        let len = CHUNK.min(n - start);
        let rays = all.narrow(start, len)?;
        let range = ray_aabb(&rays, [x0, y0, z0], [x1, y1, z1])?;
        let hits = net.find_surface(&rays, &range)?;
        let hit_rays = hits.surface_indices();
        let idx = Tensor::from_vec(hit_rays.clone(), hit_rays.len(), &Device::Cpu)?;
        let mut rgb = Tensor::ones((len, 3), DType::F32, &Device::Cpu)?;
        let mut nrm = Tensor::zeros((len, 3), DType::F32, &Device::Cpu)?;
        if !hit_rays.is_empty() {
            let points = hits.points.index_select(&idx, 0)?;
            let dirs = rays.directions().index_select(&idx, 0)?;
            let shading = net.shade(&points, &dirs)?;
            let shaded = shading.rgb.detach();
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
            let covered = hits
                .mask
                .to_dtype(DType::F32)?
                .unsqueeze(1)?
                .broadcast_as((len, 3))?;
            let on_white =
                Tensor::zeros((len, 3), DType::F32, &Device::Cpu)?.index_add(&idx, &shaded, 0)?;
            rgb = covered.ne(0.0)?.where_cond(&on_white, &rgb)?;
            nrm = nrm.index_add(&idx, &unit, 0)?;
        }
        colors.push(rgb);
        masks.push(hits.mask.to_dtype(DType::F32)?);
        normals.push(nrm);
    }
    let mean = |parts: Vec<Tensor>, c: usize| -> Result<Tensor> {
        Ok(Tensor::cat(&parts, 0)?
            .reshape((h * w, k * k, c))?
            .mean(1)?
            .reshape((h, w, c))?)
    };
    Ok((
        mean(colors, 3)?,
        mean(masks, 1)?.squeeze(2)?,
        mean(normals, 3)?,
    ))
}

/// What [`evaluate`] measures on held-out views.
struct Evaluation {
    /// Mask IoU of the predicted hits against the true masks (mask ≥ ½), pooled.
    iou: f64,
    /// PSNR inside the true masks (mask ≥ ½), pooled.
    psnr_masked: f64,
    /// PSNR on the fully covered pixels (mask = 1), pooled: without the object's
    /// antialiased edge, which one surface point per pixel cannot reproduce.
    psnr_interior: f64,
    /// Per view `[truth, colour, normals]`.
    renders: Vec<[Tensor; 3]>,
}

/// Squared error and sample count of `pred` against `truth` on the pixels of `mask`.
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
        if self.count > 0.0 {
            -10.0 * (self.se / self.count).log10()
        } else {
            f64::NAN
        }
    }
}

/// The metrics of [`Evaluation`] over the first `n` views of `eval`.
fn evaluate(net: &Net, eval: &Dataset, n: usize, aabb: [f64; 6]) -> Result<Evaluation> {
    let n = n.min(eval.len());
    let (mut inter, mut union) = (0.0, 0.0);
    let (mut masked, mut interior) = (Pooled::default(), Pooled::default());
    let mut renders = Vec::new();
    for v in 0..n {
        let view = &eval.views()[v];
        let truth = view.rgb([1.0; 3], &Device::Cpu, DType::F32)?;
        let mask = view
            .mask(&Device::Cpu, DType::F32)?
            .ok_or_else(|| no_mask(view.name()))?;
        let true_mask = mask.ge(0.5)?.to_dtype(DType::F32)?;
        let full = mask.ge(1.0)?.to_dtype(DType::F32)?;
        let (color, coverage, normals) = render_view(net, eval, v, aabb, SUPERSAMPLE)?;
        let hit = coverage.ge(0.5)?.to_dtype(DType::F32)?;
        let both = (&hit * &true_mask)?.sum_all()?.to_scalar::<f32>()?;
        let either = (&hit + &true_mask)?
            .clamp(0.0, 1.0)?
            .sum_all()?
            .to_scalar::<f32>()?;
        inter += f64::from(both);
        union += f64::from(either);
        masked.add(&color, &truth, &true_mask)?;
        interior.add(&color, &truth, &full)?;
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
/// its `normalisation.matrix`; `None` when neither is there.
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

/// The surface by MISE with vertex colours.
fn extract_mesh(net: &Net, aabb: [f64; 6], resolution0: usize) -> Result<Mesh> {
    let (device, dtype) = (Device::Cpu, DType::F32);
    let config = MiseConfig {
        min: [aabb[0], aabb[1], aabb[2]],
        max: [aabb[3], aabb[4], aabb[5]],
        ..MiseConfig::new(resolution0, 2, &device, dtype)
    };
    let mesh = mise(net.surface(), &config)?.mesh;
    if mesh.faces.is_empty() {
        return Ok(mesh);
    }
    let colors = vertex_colors(&mesh, 16_384, &device, dtype, |p| {
        // View the surface head-on: along the inward normal.
        let (_, g) = net.surface().value_and_grad(p)?;
        let g = g.detach();
        let dirs = (g * net.surface().inside().sign())?;
        Ok(net.shade(p, &dirs)?.rgb.detach())
    })?;
    mesh.with_colors(colors)
}

/// Chamfer-L1 of `pred` to `gt` in `gt`'s unit cube (ONet's normalisation, 100 000 samples
/// on each).
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

/// `data` with every camera moved: rotated by `degrees` about a random axis through its
/// centre and its centre shifted by `fraction` of its distance to the origin in a random
/// direction (seeded).
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
    with_poses(data, &moved)
}

/// `data` with its views' camera-to-world poses replaced by `poses` (intrinsics,
/// conventions, images, masks and names kept).
fn with_poses(data: &Dataset, poses: &[DAffine3]) -> Result<Dataset> {
    let views = data
        .views()
        .iter()
        .zip(poses)
        .map(|(v, pose)| {
            let cam = v.camera();
            View::new(
                Camera::new(*cam.intrinsics(), *pose, cam.convention())?,
                v.image().clone(),
                v.mask_image().cloned(),
                v.name().to_string(),
            )
        })
        .collect::<Result<Vec<_>>>()?;
    Dataset::new(views, data.background(), data.bounds())
}

/// The refined poses, and the similarity from the frame they and the scene were learnt in
/// to the dataset's frame: the least-squares fit of their centres onto the true ones
/// (jointly refined cameras are determined only up to such a map; BARF aligns the same
/// way before it measures).
fn alignment(poses: &[PoseParam], truth: &[DAffine3]) -> Result<(Similarity, Vec<DAffine3>)> {
    let refined = poses
        .iter()
        .map(PoseParam::to_affine)
        .collect::<Result<Vec<_>>>()?;
    let from: Vec<DVec3> = refined.iter().map(|p| p.translation).collect();
    let to: Vec<DVec3> = truth.iter().map(|p| p.translation).collect();
    Ok((align_similarity(&from, &to)?, refined))
}

/// `eval` with its (true) cameras moved into the learnt frame by the inverse of `frame`.
fn in_learnt_frame(eval: &Dataset, frame: &Similarity) -> Result<Dataset> {
    let inverse = frame.inverse();
    let poses: Vec<DAffine3> = poses_of(eval)
        .iter()
        .map(|p| inverse.transform_pose(p))
        .collect();
    with_poses(eval, &poses)
}

/// `mesh` (in the learnt frame) moved into the dataset's frame by `frame`.
fn mesh_to_dataset_frame(mut mesh: Mesh, frame: &Similarity) -> Mesh {
    for v in &mut mesh.vertices {
        *v = frame.transform_point(DVec3::from_array(*v)).to_array();
    }
    if let Some(normals) = &mut mesh.normals {
        for n in normals.iter_mut() {
            *n = (frame.rotation * DVec3::from_array(*n)).to_array();
        }
    }
    mesh
}

/// The rays of `batch` from the learnable poses: for each ray, the camera-space direction
/// of its pixel in its view of `data` (whose poses the batch was drawn with), turned by its
/// pose's rotation, from its pose's centre. Differentiable w.r.t. the poses.
fn pose_rays(poses: &[PoseParam], data: &Dataset, batch: &RayBatch) -> Result<Rays> {
    let views = batch.views.to_vec1::<u32>()?;
    let pixels = batch.pixels.to_vec2::<u32>()?;
    let mut d_cam = Vec::with_capacity(3 * views.len());
    for (&v, px) in views.iter().zip(&pixels) {
        let cam = data.views()[v as usize].camera();
        let (_, dir) = cam.ray(DVec2::new(f64::from(px[0]) + 0.5, f64::from(px[1]) + 0.5));
        d_cam.extend_from_slice(&(cam.cam_to_world().matrix3.transpose() * dir).to_array());
    }
    let dtype = batch.colors.dtype();
    let device = batch.colors.device();
    let d_cam = Tensor::from_vec(d_cam, (views.len(), 3, 1), device)?.to_dtype(dtype)?;
    let rotations = poses
        .iter()
        .map(PoseParam::rotation_matrix)
        .collect::<Result<Vec<_>>>()?;
    let centres: Vec<&Tensor> = poses.iter().map(|p| p.translation.as_tensor()).collect();
    let r = Tensor::stack(&rotations, 0)?.index_select(&batch.views, 0)?;
    let o = Tensor::stack(&centres, 0)?.index_select(&batch.views, 0)?;
    Rays::new(o, r.matmul(&d_cam)?.squeeze(2)?)
}

/// Mean rotation error (degrees) and mean centre error (fraction of the true camera's
/// distance to the origin) of `poses` against `truth`.
fn pose_errors(poses: &[DAffine3], truth: &[DAffine3]) -> (f64, f64) {
    let (mut rot, mut trans) = (0.0, 0.0);
    for (p, t) in poses.iter().zip(truth) {
        // The angle of the relative rotation from its quaternion, which stays accurate near
        // 0 where acos((tr R − 1)/2) does not.
        let q = DQuat::from_mat3(&(p.matrix3.transpose() * t.matrix3)).normalize();
        rot += (2.0 * q.xyz().length().atan2(q.w.abs())).to_degrees();
        trans += (p.translation - t.translation).length() / t.translation.length().max(1e-12);
    }
    let n = poses.len().max(1) as f64;
    (rot / n, trans / n)
}

/// BARF's test-time pose refinement: each view of `eval` (its camera already moved into the
/// learnt frame) gets a pose started at its camera and refined against its own image and
/// mask with the network held fixed, `steps` Adam steps at `lr` on `rays` rays drawn as
/// 2 × 2 patches, with the training loss at the end of its schedule. The held-out views
/// then measure the scene, not the registration of their cameras to it.
fn refine_eval_poses(
    net: &Net,
    eval: &Dataset,
    aabb: [f64; 6],
    (steps, rays, lr): (usize, usize, f64),
    seed: u64,
) -> Result<Dataset> {
    let (device, dtype) = (Device::Cpu, DType::F32);
    let mut refined = Vec::with_capacity(eval.len());
    for (v, view) in eval.views().iter().enumerate() {
        let one = Dataset::new(vec![view.clone()], eval.background(), eval.bounds())?;
        let pose = PoseParam::from_affine(&view.camera().cam_to_world(), &device, dtype)?;
        let mut opt = candle_nn::AdamW::new(
            vec![pose.rotation.clone(), pose.translation.clone()],
            candle_nn::ParamsAdamW {
                lr,
                weight_decay: 0.0,
                ..Default::default()
            },
        )?;
        let mut sampler = RaySampler::new(&one, seed ^ v as u64, &device, dtype)?;
        for step in 0..steps {
            let batch = sampler.patches(rays / 4, 2)?;
            let mask: Vec<bool> = match &batch.masks {
                Some(m) => m.to_vec1::<f32>()?.iter().map(|&m| m >= 0.5).collect(),
                None => return Err(no_mask(view.name())),
            };
            let r = pose_rays(std::slice::from_ref(&pose), &one, &batch)?;
            let (loss, _) =
                step_loss(net, &r, &batch.colors, &mask, aabb, 1.0, seed ^ step as u64)?;
            opt.step(&loss.backward()?)?;
        }
        refined.push(pose.to_affine()?);
    }
    with_poses(eval, &refined)
}

/// Chamfer-L1 (as [`chamfer`]) after moving `pred` onto `gt` by a similarity found by
/// iterative closest points (30 rounds of [`align_similarity`] from 20 000 points on
/// `pred` to their nearest of 20 000 points on `gt`): the shape's error apart from its
/// placement, which refined cameras fix only up to a similarity. Reported for every run,
/// so that runs with and without refined cameras compare alike.
fn chamfer_icp(pred: &Mesh, gt: &Mesh, seed: u64) -> Result<f64> {
    let (from, _) = pred.sample_surface(20_000, seed)?;
    let (to, _) = gt.sample_surface(20_000, seed ^ 1)?;
    let tree = KdTree::new(&to)?;
    let from: Vec<DVec3> = from.iter().map(|&p| DVec3::from_array(p)).collect();
    let mut frame = Similarity::IDENTITY;
    for _ in 0..30 {
        let targets: Vec<DVec3> = from
            .iter()
            .map(|&p| DVec3::from_array(to[tree.nearest(frame.transform_point(p).to_array()).0]))
            .collect();
        frame = align_similarity(&from, &targets)?;
    }
    chamfer(&mesh_to_dataset_frame(pred.clone(), &frame), gt, seed)
}

/// The learnt-frame poses of `path` (a run's `poses.json`), one per view of `data`, by name.
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
/// matrix (4 × 4, rows) in the learnt frame and, aligned, in the dataset's frame.
fn write_poses(
    path: &Path,
    data: &Dataset,
    refined: &[DAffine3],
    frame: &Similarity,
) -> Result<()> {
    let rows = |p: &DAffine3| {
        let m = DMat4::from(*p);
        (0..4).map(|r| m.row(r).to_array()).collect::<Vec<_>>()
    };
    let views: Vec<serde_json::Value> = data
        .views()
        .iter()
        .zip(refined)
        .map(|(v, p)| {
            serde_json::json!({
                "name": v.name(),
                "cam_to_world": rows(p),
                "cam_to_world_aligned": rows(&frame.transform_pose(p)),
            })
        })
        .collect();
    training::write_json(path, &serde_json::json!({ "views": views }))
}

/// What a run measured on the held-out views.
pub struct Summary {
    pub mask_iou: f64,
    pub psnr_masked: f64,
    pub chamfer_l1: Option<f64>,
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
    let poses = if args.refine_poses {
        start_poses
            .iter()
            .map(|p| PoseParam::from_affine(p, &device, dtype))
            .collect::<Result<Vec<_>>>()?
    } else {
        Vec::new()
    };
    let mut pose_vars = Vec::new();
    for (v, p) in poses.iter().enumerate() {
        pose_vars.push((format!("pose{v}.rotation"), p.rotation.clone()));
        pose_vars.push((format!("pose{v}.translation"), p.translation.clone()));
    }
    let mut pose_opt = candle_nn::AdamW::new(
        pose_vars.iter().map(|(_, v)| v.clone()).collect(),
        candle_nn::ParamsAdamW {
            lr: args.pose_lr,
            weight_decay: 0.0,
            ..Default::default()
        },
    )?;
    let (eval, eval_split) = training::load_eval(&args.data, &config)?;
    training::create_dir(&args.out)?;
    let aabb = training::scene_box(&train, args.aabb);
    let mut varmap = VarMap::new();
    let finest = training::hash_finest(&train);
    let (net, windows) = build(args, aabb, finest, &varmap, &device, dtype)?;
    let vars = training::named_vars(&varmap);
    let lr0 = args.lr.unwrap_or(match (args.encoding, args.model) {
        (PositionEncoding::Hash, Model::Dvr | Model::DvrJoint) => 1e-2,
        _ => 1e-3,
    });
    let mut opt = common::adam(&varmap, lr0)?;
    if let Some(path) = &args.resume_poses {
        for (p, pose) in poses.iter().zip(read_poses(path, &train)?) {
            let fresh = PoseParam::from_affine(&pose, &device, dtype)?;
            p.rotation.set(fresh.rotation.as_tensor())?;
            p.translation.set(fresh.translation.as_tensor())?;
        }
    }
    if let Some(path) = &args.resume {
        varmap.load(path)?;
    } else if !matches!(net, Net::Idr { .. }) {
        let decoder = net.surface();
        // Start from a ball of radius 0.5 so that the first marches find a surface.
        let ball = Sphere::new([0.0; 3], 0.5, &device, dtype)?.occupancy(10.0);
        let mut rng = SplitMix64::new(args.seed ^ 0xBA11);
        for _ in 0..150 {
            let p = rng.uniform_tensor(&[4096, 3], aabb[0], aabb[3], dtype, &device)?;
            let y = ball.value(&p)?.gt(0.0)?.to_dtype(dtype)?;
            opt.backward_step(&bce_with_logits(&decoder.value(&p)?, &y)?.mean_all()?)?;
        }
    }
    let mut sampler = RaySampler::new(&train, args.seed, &device, dtype)?;
    let mut clock = training::Clock::start(args.steps, args.minutes);
    println!(
        "{}: training on {} views of {}, evaluating on {} {eval_split} views",
        args.model.name(),
        train.len(),
        args.data.display(),
        eval.len()
    );
    let mut curve = String::from("step,train_seconds,mask_iou,psnr_masked\n");
    let mut step = 0usize;
    loop {
        let progress = clock.progress(step);
        if progress >= 1.0 {
            break;
        }
        let decay =
            |lr: f64| log_linear_schedule((progress * 10_000.0) as usize, lr, lr / 10.0, 10_000);
        opt.set_learning_rate(decay(lr0));
        pose_opt.set_learning_rate(decay(args.pose_lr));
        training::open_windows(&windows, progress, args.coarse_to_fine)?;
        let batch = sampler.patches(args.rays / 4, 2)?;
        let mask: Vec<bool> = batch
            .masks
            .as_ref()
            .expect("checked: every view has a mask") // invariant
            .to_vec1::<f32>()?
            .iter()
            .map(|&m| m >= 0.5)
            .collect();
        let rays = if poses.is_empty() {
            batch.rays.clone()
        } else {
            pose_rays(&poses, &train, &batch)?
        };
        let (loss, photo) = step_loss(
            &net,
            &rays,
            &batch.colors,
            &mask,
            aabb,
            progress,
            args.seed ^ (step as u64).wrapping_mul(0x9E37_79B9),
        )?;
        training::check_finite(&loss, step, "the loss")?;
        let grads = loss.backward()?;
        training::check_gradients(&grads, &vars, step)?;
        training::check_gradients(&grads, &pose_vars, step)?;
        opt.step(&grads)?;
        if !poses.is_empty() {
            pose_opt.step(&grads)?;
        }
        step += 1;
        clock.tick(step);
        if step.is_multiple_of(10) {
            let l1 = photo.to_dtype(DType::F64)?.to_scalar::<f64>()?;
            clock
                .bar
                .set_message(format!("step {step} photometric L1 {l1:.4}"));
        }
        if step.is_multiple_of(args.eval_every) {
            let seconds = clock.train_seconds();
            let (iou, p) = clock.off_clock(|| -> Result<(f64, f64)> {
                training::check_weights(&vars, step)?;
                let (aligned, pose_error) = if poses.is_empty() {
                    (None, String::new())
                } else {
                    let (frame, refined) = alignment(&poses, &true_poses)?;
                    let moved: Vec<DAffine3> =
                        refined.iter().map(|p| frame.transform_pose(p)).collect();
                    let (r, t) = pose_errors(&moved, &true_poses);
                    let error = format!(", poses (aligned) {r:.3}° / {:.3} %", 100.0 * t);
                    (Some(in_learnt_frame(&eval, &frame)?), error)
                };
                let e = evaluate(
                    &net,
                    aligned.as_ref().unwrap_or(&eval),
                    args.eval_views,
                    aabb,
                )?;
                println!(
                    "step {step}: held-out mask IoU {:.4}, masked PSNR {:.2} dB{pose_error}",
                    e.iou, e.psnr_masked
                );
                Ok((e.iou, e.psnr_masked))
            })?;
            curve.push_str(&format!("{step},{seconds:.3},{iou:.4},{p:.4}\n"));
        }
    }
    let train_seconds = clock.train_seconds();
    clock.bar.finish_and_clear();
    // The windows as the schedule leaves them at the end of training (every band open
    // unless END > 1), also for a run that stopped early or a resumed one.
    training::open_windows(&windows, 1.0, args.coarse_to_fine)?;
    training::check_weights(&vars, step)?;
    // With refined poses the scene was learnt in a frame of its own: the held-out cameras
    // are moved into it (and the mesh out of it) by the alignment of the training cameras.
    let (frame, refined) = if poses.is_empty() {
        (Similarity::IDENTITY, start_poses.clone())
    } else {
        alignment(&poses, &true_poses)?
    };
    let aligned_eval = match poses.is_empty() {
        true => None,
        false => Some(in_learnt_frame(&eval, &frame)?),
    };
    let registered = match &aligned_eval {
        Some(aligned) if args.test_pose_steps > 0 => Some(refine_eval_poses(
            &net,
            aligned,
            aabb,
            (args.test_pose_steps, 256, args.pose_lr),
            args.seed,
        )?),
        _ => None,
    };
    let final_eval = registered
        .as_ref()
        .or(aligned_eval.as_ref())
        .unwrap_or(&eval);
    let all = evaluate(&net, final_eval, eval.len(), aabb)?;
    let first = evaluate(&net, final_eval, args.eval_views, aabb)?;
    curve.push_str(&format!(
        "{step},{train_seconds:.3},{:.4},{:.4}\n",
        first.iou, first.psnr_masked
    ));
    let (iou, p) = (all.iou, all.psnr_masked);
    for (i, [truth, color, normals]) in all.renders.iter().enumerate().take(args.pictures) {
        write_png(
            &args.out.join(format!("view_{i}.png")),
            &comparison_strip(truth, color)?,
        )?;
        write_png(
            &args.out.join(format!("normals_{i}.png")),
            &colorize_normals(normals)?,
        )?;
    }
    // The mesh in the dataset's frame; as extracted too when the frames differ.
    let extracted = extract_mesh(&net, aabb, args.mise_resolution)?;
    let (mesh, learnt_mesh) = if poses.is_empty() {
        (extracted, None)
    } else {
        (
            mesh_to_dataset_frame(extracted.clone(), &frame),
            Some(extracted),
        )
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
        (Some(gt), false) => Some(chamfer_icp(&mesh, gt, args.seed)?),
        _ => None,
    };
    if !mesh.faces.is_empty() {
        mesh.save(args.out.join("mesh.ply"))?;
    }
    varmap.save(args.out.join("weights.safetensors"))?;
    training::write_text(&args.out.join("curve.csv"), &curve)?;
    let mut metrics = serde_json::json!({
        "mask_iou": iou,
        "psnr_masked": p,
        "psnr_interior": all.psnr_interior,
        "chamfer_l1": chamfer_l1,
        "chamfer_l1_icp": chamfer_l1_icp,
        "train_seconds": train_seconds,
        "steps": step,
        "model": args.model.name(),
        "encoding": args.encoding.name(),
        "render_inputs": args.render_inputs.name(),
        "eval_split": eval_split,
        "eval_views": eval.len(),
        "data": args.data.display().to_string(),
    });
    if args.perturb.is_some() || args.refine_poses {
        let (r0, t0) = pose_errors(&start_poses, &true_poses);
        let (r1, t1) = pose_errors(&refined, &true_poses);
        let aligned: Vec<DAffine3> = refined.iter().map(|p| frame.transform_pose(p)).collect();
        let (r2, t2) = pose_errors(&aligned, &true_poses);
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
    }
    if let (Some(aligned), Some(_)) = (&aligned_eval, &registered) {
        let e = evaluate(&net, aligned, eval.len(), aabb)?;
        metrics["aligned"] = serde_json::json!({
            "mask_iou": e.iou,
            "psnr_masked": e.psnr_masked,
            "psnr_interior": e.psnr_interior,
        });
        metrics["test_pose_steps"] = serde_json::json!(args.test_pose_steps);
    }
    if !poses.is_empty() {
        let raw = evaluate(&net, &eval, eval.len(), aabb)?;
        metrics["unaligned"] = serde_json::json!({
            "mask_iou": raw.iou,
            "psnr_masked": raw.psnr_masked,
            "psnr_interior": raw.psnr_interior,
            "chamfer_l1": learnt_mesh.as_ref().map(chamfer_of).transpose()?.flatten(),
        });
        let q = frame.rotation;
        metrics["alignment"] = serde_json::json!({
            "scale": frame.scale,
            "rotation_wxyz": [q.w, q.x, q.y, q.z],
            "translation": frame.translation.to_array(),
        });
        write_poses(&args.out.join("poses.json"), &train, &refined, &frame)?;
    }
    training::write_json(&args.out.join("metrics.json"), &metrics)?;
    println!(
        "{step} steps in {train_seconds:.1} s: held-out mask IoU {iou:.4}, masked PSNR {p:.2} dB, \
         Chamfer-L1 {} over {} {eval_split} views; wrote {}",
        chamfer_l1.map_or("unknown".into(), |c| format!("{c:.5}")),
        eval.len(),
        args.out.display()
    );
    Ok(Summary {
        mask_iou: iou,
        psnr_masked: p,
        chamfer_l1,
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
            eprintln!("dvr_multiview: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A few steps of each model on the committed dataset at a quarter of its resolution:
    /// the whole pipeline runs and writes every output with the documented keys.
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
            let out = std::env::temp_dir().join(format!(
                "dvr-multiview-{:?}-{:?}-{:?}-{}",
                model,
                encoding,
                render_inputs,
                std::process::id()
            ));
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
            assert_eq!(metrics_encoding(&out), encoding.name());
            assert!((0.0..=1.0).contains(&summary.mask_iou));
            let metrics: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap())
                    .unwrap();
            for key in [
                "mask_iou",
                "psnr_masked",
                "psnr_interior",
                "train_seconds",
                "steps",
            ] {
                assert!(
                    metrics[key].as_f64().is_some_and(f64::is_finite),
                    "{key}: {metrics}"
                );
            }
            assert!(metrics.get("chamfer_l1").is_some(), "{metrics}");
            assert!(metrics.get("chamfer_l1_icp").is_some(), "{metrics}");
            assert_eq!(metrics["steps"], 4);
            assert_eq!(metrics["render_inputs"], render_inputs.name());
            let curve = std::fs::read_to_string(out.join("curve.csv")).unwrap();
            assert_eq!(curve.lines().count(), 1 + 2 + 1);
            for file in ["view_0.png", "normals_0.png", "weights.safetensors"] {
                assert!(out.join(file).is_file(), "{file}");
            }
            let _ = std::fs::remove_dir_all(&out);
        }
    }

    fn metrics_encoding(out: &Path) -> String {
        let metrics: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap())
                .unwrap();
        metrics["encoding"].as_str().unwrap_or("none").to_string()
    }

    /// The perturbation moves every camera by exactly the asked rotation and centre shift,
    /// and a shortened run with pose refinement reports the pose errors before and after.
    #[test]
    fn perturbed_poses_are_measured_and_refined() {
        let data = load(
            Path::new("examples/data/wuson"),
            &LoadConfig {
                downscale: 4,
                ..LoadConfig::default()
            },
        )
        .unwrap();
        let truth = poses_of(&data);
        let moved = perturb(&data, 3.0, 0.03, 7).unwrap();
        let poses = poses_of(&moved);
        let (r, t) = pose_errors(&poses, &truth);
        // The committed poses are Blender's float32 matrices: orthonormal to about 1e-7.
        assert!((r - 3.0).abs() < 1e-4, "{r}");
        assert!((t - 0.03).abs() < 1e-9, "{t}");
        let (r0, t0) = pose_errors(&truth, &truth);
        assert!(r0 < 1e-5 && t0 == 0.0, "{r0} {t0}");
        // Rays from unmoved learnable poses are the dataset's rays.
        let params: Vec<PoseParam> = truth
            .iter()
            .map(|p| PoseParam::from_affine(p, &Device::Cpu, DType::F32).unwrap())
            .collect();
        let mut sampler = RaySampler::new(&data, 3, &Device::Cpu, DType::F32).unwrap();
        let batch = sampler.patches(8, 2).unwrap();
        let rays = pose_rays(&params, &data, &batch).unwrap();
        for (a, b) in [
            (rays.origins(), batch.rays.origins()),
            (rays.directions(), batch.rays.directions()),
        ] {
            let d = (a - b).unwrap().abs().unwrap().max_all().unwrap();
            assert!(d.to_scalar::<f32>().unwrap() < 1e-5);
        }
        let out = std::env::temp_dir().join(format!("dvr-multiview-poses-{}", std::process::id()));
        let args = Args {
            steps: Some(3),
            out: out.clone(),
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
        run(&args).unwrap();
        let metrics: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap())
                .unwrap();
        let before = metrics["pose_rotation_error_deg"]["before"]
            .as_f64()
            .unwrap();
        let after = metrics["pose_rotation_error_deg"]["after"]
            .as_f64()
            .unwrap();
        assert!((before - 3.0).abs() < 1e-3, "{metrics}");
        assert!(after.is_finite() && after != before, "{metrics}");
        // Refined poses: evaluated in the learnt frame, with the unaligned figures beside,
        // and written out per view.
        assert!(metrics["pose_rotation_error_deg"]["after_aligned"].is_f64());
        assert!(metrics["unaligned"]["mask_iou"].is_f64(), "{metrics}");
        assert!(metrics["aligned"]["mask_iou"].is_f64(), "{metrics}");
        assert_eq!(metrics["test_pose_steps"], 2);
        let scale = metrics["alignment"]["scale"].as_f64().unwrap();
        assert!((scale - 1.0).abs() < 0.1, "{metrics}");
        let poses: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("poses.json")).unwrap())
                .unwrap();
        let views = poses["views"].as_array().unwrap();
        assert_eq!(views.len(), data.len());
        assert_eq!(views[0]["name"], data.views()[0].name());
        assert_eq!(
            views[0]["cam_to_world_aligned"][3],
            serde_json::json!([0.0, 0.0, 0.0, 1.0])
        );
        let _ = std::fs::remove_dir_all(&out);
    }

    /// A one-view dataset of a 4 × 4 image with `channels` channels of `value`.
    fn tiny_dataset(channels: usize, value: u8) -> Dataset {
        let k = neural_fields::camera::Intrinsics::from_fov_y(4, 4, 0.8).unwrap();
        let cam = Camera::look_at(
            k,
            DVec3::new(0.0, 0.0, 3.0),
            DVec3::ZERO,
            DVec3::Y,
            neural_fields::camera::Convention::OpenGl,
        )
        .unwrap();
        let image =
            neural_fields::data::Image::new(4, 4, channels, vec![value; 16 * channels]).unwrap();
        let view = View::new(cam, image, None, "tiny.png".into()).unwrap();
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
