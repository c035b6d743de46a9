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
//! own Adam at `--pose-lr` (1e-3, decaying like the network's; with `--pose-solver lm`,
//! 5e-4 did better on the committed dataset, docs/benchmarks.md). `--coarse-to-fine
//! START,END` puts every position encoding under BARF's window ([`CoarseToFine`]): only
//! the raw point (frequency encodings) or the coarsest level (hash grids) at first, the
//! finer bands fading in from the fraction START of the training budget to END (BARF's
//! schedule is `0.1,0.5`), so that the poses move while the fields are still smooth.
//!
//! `--pose-solver lm` registers the cameras to the scene once it is nearly right
//! ([`register_poses`]): after the last step (and first at the fraction `--lm-start` of
//! the budget, then every `--lm-every` steps if given; the default 1 makes only the last,
//! which did best on the committed dataset: docs/benchmarks.md), the network is
//! held fixed and each training camera is aligned to the scene `--lm-iterations` times
//! (2). The scene is rendered from the camera (surface points and colours on the mask's
//! bounding box), and the pose moves until the true image, seen where those points
//! project, matches the render (colour and alpha, Huber's loss, coarse to fine over blurs
//! of 2, 1 and 0 pixels), by Levenberg–Marquardt steps on its 6 parameters. The cameras
//! stay where the registration puts them, in the scene's frame (taking out the similarity
//! common to their moves, as this example once did, moved them all away from the scene
//! they were registered to). Adam moves the poses until the first registration. A
//! Gauss–Newton step solves for the direction in which a camera's centre and rotation
//! compensate each other, which Adam's per-parameter steps on the ray loss crawl along;
//! but it needs a scene that is nearly right: early on, a scene carved by inconsistent
//! silhouettes draws the cameras away, and registrations alternated with training did not
//! settle (docs/benchmarks.md). The held-out cameras are registered the same way, instead
//! of by BARF's Adam steps.
//!
//! Jointly refined cameras are determined only up to a similarity of the whole scene, so
//! a run that refines poses is evaluated in the dataset's frame after an alignment. The
//! poses are compared as BARF compares them, after the similarity that best maps the
//! refined training-camera centres onto the true ones ([`align_similarity`]). The scene
//! is placed by what the cameras see: the similarity under which the refined and the true
//! training cameras project the extracted surface alike ([`align_cameras`] on up to 2 000
//! of its vertices), which does not let each camera's error along its weakest direction
//! (a centre shifted across the line of sight with the matching turn) move the scene. It
//! moves the held-out cameras into the learnt frame for the final held-out metrics, and
//! the extracted mesh out of it for the Chamfer distance and `mesh.ply`; the periodic
//! evaluations during training (`curve.csv` before its last row) use the centres' fit,
//! which needs no mesh. `metrics.json` then also holds `unaligned` (`mask_iou`,
//! `psnr_masked`, `psnr_interior`, `chamfer_l1` without the alignment), `alignment`
//! (the scene's: `scale`, `rotation_wxyz`, `translation`), `alignment_centres` (the
//! centres' fit, the same keys), `chamfer_l1_centres` (the mesh placed by the centres'
//! fit), `pose_solver`, `pose_rotation_error_deg` and `pose_centre_error_fraction`
//! (`before` and `after` training and `after_aligned`, means over the training views
//! against the unperturbed poses), `pose_reprojection_px` (`before`, `after`: the mean
//! distance in pixels between where the training cameras and the true ones see the
//! extracted surface, after the scene's alignment ([`reprojection_error`]); unlike the
//! two errors before it, it leaves out a camera's error along its weakest direction,
//! which its image barely shows), and `poses.json` the refined cameras (`views`: `name`,
//! `cam_to_world` in the learnt frame and `cam_to_world_aligned` moved with the scene,
//! 4 × 4 rows). With `--perturb` alone the pose errors are reported and nothing is
//! aligned. After the alignment, each held-out camera is refined against its own image
//! with the network fixed (BARF's test-time refinement: `--test-pose-steps` Adam steps of 256 rays at
//! `--pose-lr`, default 100, or with `--pose-solver lm` the registration above, whatever
//! the count; 0 skips either), so that the held-out metrics measure the scene rather than
//! the alignment; `aligned` in `metrics.json` holds them before that refinement. `--resume-poses FILE`
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
    align_cameras, align_similarity, ray_aabb, reprojection_error, retract_pose, Camera,
    Intersection, PixelFilter, PoseParam, Rays, Similarity,
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
use neural_fields::numerics::{bce_with_logits, damped_solve};
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
    /// How the poses are refined: Adam beside the network, or Levenberg–Marquardt.
    pub pose_solver: PoseSolver,
    /// Levenberg–Marquardt: after the first registration, another every this many steps
    /// (`None`: only the last).
    pub lm_every: Option<usize>,
    /// Renders (each followed by a coarse-to-fine alignment) per registration.
    pub lm_iterations: usize,
    /// The fraction of the budget at which the first registration is made (1: only the
    /// one after the last step).
    pub lm_start: f64,
}

/// How `--refine-poses on` moves the training poses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PoseSolver {
    /// Adam on each pose's quaternion and centre, every step, beside the network (IDR).
    Adam,
    /// Adam as above until a Levenberg–Marquardt registration of every camera to the
    /// scene held fixed takes over ([`register_poses`]): after the last step, or now and
    /// then from a fraction of the budget on; the held-out cameras are registered the
    /// same way.
    Lm,
}

impl PoseSolver {
    fn parse(value: &str) -> std::result::Result<Self, String> {
        match value {
            "adam" => Ok(Self::Adam),
            "lm" => Ok(Self::Lm),
            other => Err(format!("--pose-solver: adam or lm, not {other}")),
        }
    }

    fn name(self) -> &'static str {
        match self {
            Self::Adam => "adam",
            Self::Lm => "lm",
        }
    }
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
            pose_solver: PoseSolver::Adam,
            lm_every: None,
            lm_iterations: 2,
            lm_start: 1.0,
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
[--encoding pe|hash] [--render-inputs full|no-view|no-normal] [--pose-solver adam|lm] \
[--lm-every N] [--lm-iterations N] [--lm-start FRACTION]";

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
            "--pose-solver" => a.pose_solver = PoseSolver::parse(value)?,
            "--lm-every" => a.lm_every = Some(int(flag, value)?),
            "--lm-iterations" => a.lm_iterations = int(flag, value)?,
            "--lm-start" => a.lm_start = num(flag, value)?,
            other => return Err(format!("unknown flag {other}\n{USAGE}")),
        }
        Ok(())
    })?;
    training::check_budget(&mut a.minutes, a.steps, 15.0)?;
    if a.lm_every == Some(0) || a.lm_iterations == 0 || !(0.0..=1.0).contains(&a.lm_start) {
        return Err("--lm-every and --lm-iterations must be positive, --lm-start in [0, 1]".into());
    }
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
    // A rate of 0 freezes what it drives (`--pose-lr 0`: the poses).
    let rate = |v: f64| v >= 0.0 && v.is_finite();
    if !rate(a.pose_lr) || a.lr.is_some_and(|lr| !rate(lr)) {
        return Err("--lr and --pose-lr must be finite and ≥ 0".into());
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

/// The cameras of `train`'s views (intrinsics, convention) at `poses`.
fn cameras_at(train: &Dataset, poses: &[DAffine3]) -> Result<Vec<Camera>> {
    train
        .views()
        .iter()
        .zip(poses)
        .map(|(v, pose)| {
            let cam = v.camera();
            Camera::new(*cam.intrinsics(), *pose, cam.convention())
        })
        .collect()
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

/// The similarity from the learnt frame to the dataset's under which the training cameras
/// (`refined`, learnt frame) and the true ones (`truth`) see the extracted surface `mesh`
/// alike ([`align_cameras`] on [`mesh_points`]), or `centres` (the fit of the camera
/// centres) for a run whose mesh is empty or that no camera sees (said on stderr).
fn view_alignment(
    train: &Dataset,
    refined: &[DAffine3],
    truth: &[DAffine3],
    mesh: &Mesh,
    centres: Similarity,
) -> Result<Similarity> {
    if mesh.vertices.is_empty() {
        return Ok(centres);
    }
    let points = mesh_points(mesh);
    match align_cameras(
        &cameras_at(train, refined)?,
        &cameras_at(train, truth)?,
        &points,
    ) {
        Ok(frame) => Ok(frame),
        Err(e) => {
            eprintln!("the scene is placed by the camera centres' fit: {e}");
            Ok(centres)
        }
    }
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

/// An image as bilinearly sampled planes: red, green, blue (on white) and alpha, `[0, 1]`.
#[derive(Clone)]
struct Planes {
    w: usize,
    h: usize,
    px: Vec<[f64; 4]>,
}

impl Planes {
    /// `view`'s image on white and its mask.
    fn of_view(view: &View) -> Result<Self> {
        let rgb = view
            .rgb([1.0; 3], &Device::Cpu, DType::F64)?
            .to_vec3::<f64>()?;
        let mask = view
            .mask(&Device::Cpu, DType::F64)?
            .ok_or_else(|| no_mask(view.name()))?
            .to_vec2::<f64>()?;
        let (h, w) = (mask.len(), mask.first().map_or(0, Vec::len));
        let mut px = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let c = &rgb[y][x];
                px.push([c[0], c[1], c[2], mask[y][x]]);
            }
        }
        Ok(Self { w, h, px })
    }

    /// Blurred by a Gaussian of `sigma` pixels (separable, truncated at 3σ, edges
    /// clamped); itself for `sigma = 0`.
    fn blurred(&self, sigma: f64) -> Self {
        if sigma <= 0.0 {
            return self.clone();
        }
        let r = (3.0 * sigma).ceil() as isize;
        let k: Vec<f64> = (-r..=r)
            .map(|i| (-0.5 * (i as f64 / sigma).powi(2)).exp())
            .collect();
        let total: f64 = k.iter().sum();
        let pass = |src: &[[f64; 4]], horizontal: bool| -> Vec<[f64; 4]> {
            let mut out = vec![[0.0; 4]; src.len()];
            for y in 0..self.h {
                for x in 0..self.w {
                    let mut acc = [0.0; 4];
                    for (j, &kj) in k.iter().enumerate() {
                        let o = j as isize - r;
                        let (sx, sy) = if horizontal {
                            ((x as isize + o).clamp(0, self.w as isize - 1) as usize, y)
                        } else {
                            (x, (y as isize + o).clamp(0, self.h as isize - 1) as usize)
                        };
                        let p = src[sy * self.w + sx];
                        for c in 0..4 {
                            acc[c] += kj * p[c];
                        }
                    }
                    out[y * self.w + x] = acc.map(|a| a / total);
                }
            }
            out
        };
        let px = pass(&pass(&self.px, true), false);
        Self { px, ..*self }
    }

    /// The bilinear interpolation at the continuous pixel coordinate `u` (pixel `(i, j)`
    /// has its centre at `(i + ½, j + ½)`; edges clamped) and its derivatives along x
    /// and y.
    fn sample(&self, u: DVec2) -> ([f64; 4], [[f64; 4]; 2]) {
        let fx = (u.x - 0.5).clamp(0.0, (self.w - 1) as f64);
        let fy = (u.y - 0.5).clamp(0.0, (self.h - 1) as f64);
        let (x0, y0) = (
            (fx.floor() as usize).min(self.w.saturating_sub(2)),
            (fy.floor() as usize).min(self.h.saturating_sub(2)),
        );
        let (x1, y1) = ((x0 + 1).min(self.w - 1), (y0 + 1).min(self.h - 1));
        let (tx, ty) = (fx - x0 as f64, fy - y0 as f64);
        let at = |x: usize, y: usize| self.px[y * self.w + x];
        let (a, b, c, d) = (at(x0, y0), at(x1, y0), at(x0, y1), at(x1, y1));
        let mut value = [0.0; 4];
        let mut grad = [[0.0; 4]; 2];
        for k in 0..4 {
            value[k] =
                (1.0 - ty) * ((1.0 - tx) * a[k] + tx * b[k]) + ty * ((1.0 - tx) * c[k] + tx * d[k]);
            grad[0][k] = (1.0 - ty) * (b[k] - a[k]) + ty * (d[k] - c[k]);
            grad[1][k] = (1.0 - tx) * (c[k] - a[k]) + tx * (d[k] - b[k]);
        }
        (value, grad)
    }
}

/// One camera's Gauss–Newton system `H = Σ w j jᵀ`, `g = Σ w j r` and its robust cost
/// `Σ ρ(r)` at the pose it was formed at.
#[derive(Clone, Copy)]
struct PoseSystem {
    h: [[f64; 6]; 6],
    g: [f64; 6],
    cost: f64,
}

impl PoseSystem {
    const ZERO: Self = Self {
        h: [[0.0; 6]; 6],
        g: [0.0; 6],
        cost: 0.0,
    };

    /// Adds residual `r` with Jacobian row `j` under Huber's loss of threshold `k`
    /// (iteratively reweighted: weight `min(1, k/|r|)`).
    fn add(&mut self, r: f64, j: &[f64; 6], k: f64) {
        let a = r.abs();
        let (w, rho) = if a <= k {
            (1.0, 0.5 * r * r)
        } else {
            (k / a, k * (a - 0.5 * k))
        };
        self.cost += rho;
        for p in 0..6 {
            self.g[p] += w * j[p] * r;
            for q in 0..=p {
                self.h[p][q] += w * j[p] * j[q];
            }
        }
    }
}

/// Huber threshold of the registration's residuals (per channel).
const HUBER: f64 = 0.1;

/// The pixels of the bounding box of `truth`'s mask (alpha > 0) grown by `margin`
/// pixels, as indices `y·w + x`; none for an empty mask.
fn box_pixels(truth: &Planes, margin: usize) -> Vec<usize> {
    let (w, h) = (truth.w, truth.h);
    let covered = |x: usize, y: usize| truth.px[y * w + x][3] > 0.0;
    let ys: Vec<usize> = (0..h).filter(|&y| (0..w).any(|x| covered(x, y))).collect();
    let xs: Vec<usize> = (0..w).filter(|&x| (0..h).any(|y| covered(x, y))).collect();
    let (Some(&y0), Some(&y1), Some(&x0), Some(&x1)) =
        (ys.first(), ys.last(), xs.first(), xs.last())
    else {
        return Vec::new();
    };
    let grow = |lo: usize, hi: usize, n: usize| lo.saturating_sub(margin)..(hi + margin + 1).min(n);
    grow(y0, y1, h)
        .flat_map(|y| grow(x0, x1, w).map(move |x| y * w + x))
        .collect()
}

/// A render for [`alignment_system`] from the surface points `hits` (pixel index, point,
/// colour) that `camera` sees on the pixels `pixels` of a `w × h` image: the planes
/// (colour on white, alpha 1 at hits) and, for every pixel of `pixels`, a 3-D point: its
/// hit, or for a miss the point on its ray at the camera-space depth of its nearest hit
/// (4-neighbour breadth-first within `pixels`), so that the background around the
/// silhouette moves with it. Pixels with no hit within reach get no point.
fn surface_render(
    camera: &Camera,
    (w, h): (usize, usize),
    pixels: &[usize],
    hits: &[(usize, DVec3, [f64; 3])],
) -> (Planes, Vec<(usize, DVec3)>) {
    let mut planes = Planes {
        w,
        h,
        px: vec![[1.0, 1.0, 1.0, 0.0]; w * h],
    };
    let mut depth: Vec<Option<f64>> = vec![None; w * h];
    let mut inside = vec![false; w * h];
    for &i in pixels {
        inside[i] = true;
    }
    for &(i, x, c) in hits {
        planes.px[i] = [c[0], c[1], c[2], 1.0];
        depth[i] = camera.project(x).map(|u| u.z);
    }
    let mut queue: std::collections::VecDeque<usize> = pixels
        .iter()
        .copied()
        .filter(|&i| depth[i].is_some())
        .collect();
    while let Some(i) = queue.pop_front() {
        let (x, y) = (i % w, i / w);
        let neighbours = [
            (x > 0).then(|| i - 1),
            (x + 1 < w).then(|| i + 1),
            (y > 0).then(|| i - w),
            (y + 1 < h).then(|| i + w),
        ];
        for j in neighbours.into_iter().flatten() {
            if inside[j] && depth[j].is_none() {
                depth[j] = depth[i];
                queue.push_back(j);
            }
        }
    }
    let points = pixels
        .iter()
        .filter_map(|&i| {
            let z = depth[i]?;
            let (o, d) = camera.ray(DVec2::new((i % w) as f64 + 0.5, (i / w) as f64 + 0.5));
            Some((i, o + z * d))
        })
        .collect();
    (planes, points)
}

/// The scene as `camera` sees it on the mask's bounding box of `truth` grown by `margin`
/// pixels ([`box_pixels`]): the network's first surface point and its colour on each
/// pixel's ray, made into a render by [`surface_render`].
fn render_points(
    net: &Net,
    camera: &Camera,
    truth: &Planes,
    aabb: [f64; 6],
    margin: usize,
) -> Result<(Planes, Vec<(usize, DVec3)>)> {
    let w = truth.w;
    let pixels = box_pixels(truth, margin);
    let n = pixels.len();
    let mut hits = Vec::new();
    if n > 0 {
        let centres: Vec<f32> = pixels
            .iter()
            .flat_map(|&i| [(i % w) as f32 + 0.5, (i / w) as f32 + 0.5])
            .collect();
        let all = camera.rays_for_pixels(&Tensor::from_vec(centres, (n, 2), &Device::Cpu)?)?;
        let [x0, y0, z0, x1, y1, z1] = aabb;
        for start in (0..n).step_by(CHUNK) {
            let len = CHUNK.min(n - start);
            let rays = all.narrow(start, len)?;
            let range = ray_aabb(&rays, [x0, y0, z0], [x1, y1, z1])?;
            let found = net.find_surface(&rays, &range)?;
            let hit_rays = found.surface_indices();
            if hit_rays.is_empty() {
                continue;
            }
            let idx = Tensor::from_vec(hit_rays.clone(), hit_rays.len(), &Device::Cpu)?;
            let p = found.points.index_select(&idx, 0)?;
            let dirs = rays.directions().index_select(&idx, 0)?;
            let rgb = net.shade(&p, &dirs)?.rgb.detach();
            let rgb = rgb.to_dtype(DType::F64)?.to_vec2::<f64>()?;
            let p = p.to_dtype(DType::F64)?.to_vec2::<f64>()?;
            for (k, &r) in hit_rays.iter().enumerate() {
                hits.push((
                    pixels[start + r as usize],
                    DVec3::new(p[k][0], p[k][1], p[k][2]),
                    [rgb[k][0], rgb[k][1], rgb[k][2]],
                ));
            }
        }
    }
    Ok(surface_render(camera, (truth.w, truth.h), &pixels, &hits))
}

/// The Gauss–Newton system of registering `pose` by direct image alignment: for each
/// rendered surface point `X` (seen at pixel `x` of the render), the residual is the true
/// image at the projection of `X` under `pose` minus the render at `x`, both blurred
/// alike (four channels: colour on white and alpha), and its Jacobian w.r.t. the pose
/// step of [`retract_pose`] the image gradient times the projection's derivative (central
/// differences of [`Camera::project`], 10⁻⁶ per parameter).
fn alignment_system(
    camera: &Camera,
    pose: &DAffine3,
    truth: &Planes,
    render: &Planes,
    points: &[(usize, DVec3)],
) -> Result<PoseSystem> {
    let at = |p: DAffine3| Camera::new(*camera.intrinsics(), p, camera.convention());
    let cam = at(*pose)?;
    const H: f64 = 1e-6;
    let mut moved = Vec::with_capacity(12);
    for k in 0..6 {
        for sign in [1.0, -1.0] {
            let mut step = [0.0; 6];
            step[k] = sign * H;
            moved.push(at(retract_pose(pose, step))?);
        }
    }
    let mut system = PoseSystem::ZERO;
    for &(i, x) in points {
        let Some(u) = cam.project(x) else { continue };
        let mut du = [[0.0; 6]; 2];
        let mut ok = true;
        for k in 0..6 {
            match (moved[2 * k].project(x), moved[2 * k + 1].project(x)) {
                (Some(a), Some(b)) => {
                    du[0][k] = (a.x - b.x) / (2.0 * H);
                    du[1][k] = (a.y - b.y) / (2.0 * H);
                }
                _ => ok = false,
            }
        }
        if !ok {
            continue;
        }
        let (value, grad) = truth.sample(u.truncate());
        let rendered = render.px[i];
        for c in 0..4 {
            let j: [f64; 6] =
                std::array::from_fn(|k| grad[0][c] * du[0][k] + grad[1][c] * du[1][k]);
            system.add(value[c] - rendered[c], &j, HUBER);
        }
    }
    Ok(system)
}

/// Blur levels (pixels) of the coarse-to-fine alignment, and Levenberg–Marquardt
/// iterations at each.
const ALIGN_LEVELS: [f64; 3] = [2.0, 1.0, 0.0];
const ALIGN_ITERATIONS: usize = 10;
/// The most one registration may move a camera: degrees, and fraction of its distance
/// to the origin.
const MAX_MOVE: (f64, f64) = (5.0, 0.05);
/// The standard deviation (pixels) of the images' pixel filter, [`PixelFilter::CYCLES`].
const RENDER_SIGMA: f64 = 0.4155;

/// `camera`'s pose aligned to its true image (`truth`: one blur per [`ALIGN_LEVELS`])
/// by Levenberg–Marquardt on [`alignment_system`] against the render `render` with its
/// points `points` ([`surface_render`]), coarse to fine; a step that raises the cost is
/// undone and the damping raised.
fn align_view(
    camera: &Camera,
    truth: &[Planes],
    render: &Planes,
    points: &[(usize, DVec3)],
) -> Result<DAffine3> {
    let mut pose = camera.cam_to_world();
    for (level, &sigma) in ALIGN_LEVELS.iter().enumerate() {
        // The render is point-sampled at the pixel centres, the images filtered over
        // each pixel: the render gets the filter's blur too (a Gaussian of Cycles'
        // Blackman–Harris window's σ).
        let blurred = render.blurred((sigma * sigma + RENDER_SIGMA * RENDER_SIGMA).sqrt());
        let truth = &truth[level];
        let mut system = alignment_system(camera, &pose, truth, &blurred, points)?;
        let mut lambda = 1e-3;
        for _ in 0..ALIGN_ITERATIONS {
            let Some(step) = damped_solve(&system.h, &system.g, lambda) else {
                break;
            };
            let trial = retract_pose(&pose, step);
            let next = alignment_system(camera, &trial, truth, &blurred, points)?;
            if next.cost < system.cost {
                (pose, system) = (trial, next);
                lambda = (lambda / 3.0).max(1e-9);
            } else {
                lambda *= 4.0;
            }
        }
        // A registration never raises the finest level's cost: if the camera's own pose
        // has a lower one than where the levels ended, it stays.
        if level + 1 == ALIGN_LEVELS.len() {
            let start = camera.cam_to_world();
            if alignment_system(camera, &start, truth, &blurred, points)?.cost < system.cost {
                pose = start;
            }
        }
    }
    Ok(pose)
}

/// Registers each camera of `data` to the scene by direct image alignment, the network
/// held fixed: `renders` times, the scene is rendered from the camera's current pose
/// (its surface points and colours, [`render_points`]), and the pose is moved so that the
/// true image, seen at those points' projections, matches the render
/// ([`alignment_system`]), by Levenberg–Marquardt ([`damped_solve`], [`retract_pose`];
/// a step that raises the cost is undone and the damping raised), coarse to fine over
/// blurs of 2, 1 and 0 pixels; a camera that would move by more than [`MAX_MOVE`] in one
/// round keeps its pose. Adam's per-parameter steps on the ray loss crawl along
/// the direction in which a camera's rotation and centre compensate each other; the
/// Gauss–Newton step solves for it. `report(render, poses)` sees the poses after each.
fn register_poses(
    net: &Net,
    data: &Dataset,
    poses: &[DAffine3],
    aabb: [f64; 6],
    renders: usize,
    report: &mut dyn FnMut(usize, &[DAffine3]),
) -> Result<Vec<DAffine3>> {
    let truths: Vec<Planes> = data
        .views()
        .iter()
        .map(Planes::of_view)
        .collect::<Result<_>>()?;
    let levels: Vec<Vec<Planes>> = truths
        .iter()
        .map(|t| ALIGN_LEVELS.iter().map(|&s| t.blurred(s)).collect())
        .collect();
    let mut current = poses.to_vec();
    for round in 0..renders {
        for (v, view) in data.views().iter().enumerate() {
            let camera = Camera::new(
                *view.camera().intrinsics(),
                current[v],
                view.camera().convention(),
            )?;
            let (render, points) = render_points(net, &camera, &truths[v], aabb, 4)?;
            if points.is_empty() {
                continue;
            }
            let aligned = align_view(&camera, &levels[v], &render, &points)?;
            // Registration corrects small errors; a camera it would move further than
            // MAX_MOVE (a scene that is not yet right can draw one anywhere) stays.
            let (turn, shift) = pose_errors(&[aligned], &[current[v]]);
            if turn <= MAX_MOVE.0 && shift <= MAX_MOVE.1 {
                current[v] = aligned;
            }
        }
        report(round, &current);
    }
    Ok(current)
}

/// One Levenberg–Marquardt registration of the training cameras (`poses`, learnt on
/// `train`) to the scene as it is at `step`; prints the mean pose errors against `truth`
/// after each iteration (before any alignment).
fn register_training(
    net: &Net,
    args: &Args,
    train: &Dataset,
    poses: &[PoseParam],
    truth: &[DAffine3],
    aabb: [f64; 6],
    step: usize,
) -> Result<()> {
    let current = poses
        .iter()
        .map(PoseParam::to_affine)
        .collect::<Result<Vec<_>>>()?;
    let refined = register_poses(
        net,
        train,
        &current,
        aabb,
        args.lm_iterations,
        &mut |it, p| {
            let (r, t) = pose_errors(p, truth);
            println!(
                "step {step}, registration {it}: poses {r:.3}° / {:.3} % (unaligned)",
                100.0 * t
            );
        },
    )?;
    // The cameras stay where the registration put them, in the scene's frame. (Taking
    // out their common similarity, to keep the frame of the cameras before the
    // registration, moved every camera away from the scene they were just registered to:
    // a placement error of the whole scene against its cameras.)
    let (r, t) = pose_errors(&refined, truth);
    println!(
        "step {step}: poses {r:.3}° / {:.3} % (unaligned) after the registration",
        100.0 * t
    );
    for (p, pose) in poses.iter().zip(&refined) {
        let fresh = PoseParam::from_affine(pose, p.translation.device(), p.translation.dtype())?;
        p.rotation.set(fresh.rotation.as_tensor())?;
        p.translation.set(fresh.translation.as_tensor())?;
    }
    Ok(())
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
    let mut registered_at = None;
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
        // Adam moves the poses until the first registration; from then on the
        // registrations do.
        if !poses.is_empty() && registered_at.is_none() {
            pose_opt.step(&grads)?;
        }
        step += 1;
        let registration_due = match registered_at {
            None => args.lm_start < 1.0 && progress >= args.lm_start,
            Some(at) => args.lm_every.is_some_and(|n| step >= at + n),
        };
        if !poses.is_empty() && args.pose_solver == PoseSolver::Lm && registration_due {
            register_training(&net, args, &train, &poses, &true_poses, aabb, step)?;
            registered_at = Some(step);
        }
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
    // The last registration, unless the last step just made one.
    if !poses.is_empty() && args.pose_solver == PoseSolver::Lm && registered_at != Some(step) {
        register_training(&net, args, &train, &poses, &true_poses, aabb, step)?;
    }
    let train_seconds = clock.train_seconds();
    clock.bar.finish_and_clear();
    // The windows as the schedule leaves them at the end of training (every band open
    // unless END > 1), also for a run that stopped early or a resumed one.
    training::open_windows(&windows, 1.0, args.coarse_to_fine)?;
    training::check_weights(&vars, step)?;
    // With refined poses the scene was learnt in a frame of its own: the held-out cameras
    // are moved into it (and the mesh out of it) by the alignment of the training cameras.
    // The poses are compared after the fit of their centres (BARF's protocol), the scene
    // after the fit of what the cameras see on its extracted surface (`align_cameras`).
    let extracted = extract_mesh(&net, aabb, args.mise_resolution)?;
    let (centres_frame, refined) = if poses.is_empty() {
        (Similarity::IDENTITY, start_poses.clone())
    } else {
        alignment(&poses, &true_poses)?
    };
    let frame = if poses.is_empty() {
        Similarity::IDENTITY
    } else {
        view_alignment(&train, &refined, &true_poses, &extracted, centres_frame)?
    };
    let aligned_eval = match poses.is_empty() {
        true => None,
        false => Some(in_learnt_frame(&eval, &frame)?),
    };
    let registered = match &aligned_eval {
        Some(aligned) if args.test_pose_steps > 0 => Some(match args.pose_solver {
            PoseSolver::Adam => refine_eval_poses(
                &net,
                aligned,
                aabb,
                (args.test_pose_steps, 256, args.pose_lr),
                args.seed,
            )?,
            PoseSolver::Lm => {
                let refined = register_poses(
                    &net,
                    aligned,
                    &poses_of(aligned),
                    aabb,
                    args.lm_iterations,
                    &mut |_, _| {},
                )?;
                with_poses(aligned, &refined)?
            }
        }),
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
        let aligned: Vec<DAffine3> = refined
            .iter()
            .map(|p| centres_frame.transform_pose(p))
            .collect();
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
        metrics["pose_solver"] = serde_json::json!(args.pose_solver.name());
        // Both on the extracted surface: the start poses see it placed where the refined
        // cameras put it (the start poses are in the dataset's frame).
        let points = mesh_points(learnt_mesh.as_ref().unwrap_or(&mesh));
        let moved: Vec<DVec3> = points.iter().map(|&y| frame.transform_point(y)).collect();
        let truth = cameras_at(&train, &true_poses)?;
        // `null` in metrics.json where no training camera sees the surface.
        let px = |cameras: &[Camera], points: &[DVec3], frame: &Similarity| {
            reprojection_error(cameras, &truth, points, frame)
                .map_err(|e| eprintln!("no reprojection error: {e}"))
                .ok()
        };
        let before = px(
            &cameras_at(&train, &start_poses)?,
            &moved,
            &Similarity::IDENTITY,
        );
        let after = px(&cameras_at(&train, &refined)?, &points, &frame);
        if let (Some(b), Some(a)) = (before, after) {
            println!("training cameras' reprojection error {b:.3} px → {a:.3} px");
        }
        metrics["pose_reprojection_px"] = serde_json::json!({"before": before, "after": after});
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
        let json_of = |f: &Similarity| {
            let q = f.rotation;
            serde_json::json!({
                "scale": f.scale,
                "rotation_wxyz": [q.w, q.x, q.y, q.z],
                "translation": f.translation.to_array(),
            })
        };
        metrics["alignment"] = json_of(&frame);
        metrics["alignment_centres"] = json_of(&centres_frame);
        metrics["chamfer_l1_centres"] = serde_json::json!(learnt_mesh
            .as_ref()
            .map(|m| chamfer_of(&mesh_to_dataset_frame(m.clone(), &centres_frame)))
            .transpose()?
            .flatten());
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
        // With the cameras registered by Levenberg–Marquardt (after the first step, two
        // steps later and after the last): finite poses that moved.
        let lm = Args {
            pose_solver: PoseSolver::Lm,
            lm_every: Some(2),
            lm_iterations: 1,
            lm_start: 0.0,
            ..shortened(out.join("lm"))
        };
        run(&lm).unwrap();
        let m: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(lm.out.join("metrics.json")).unwrap())
                .unwrap();
        let after = m["pose_rotation_error_deg"]["after"].as_f64().unwrap();
        assert!(after.is_finite() && (after - 3.0).abs() > 1e-6, "{m}");
        assert_eq!(m["pose_solver"], "lm");
        let reprojection = m["pose_reprojection_px"].as_object().unwrap();
        assert!(reprojection.contains_key("before") && reprojection.contains_key("after"));
        run(&shortened(out.clone())).unwrap();
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

    /// Regression: a registration took out the similarity common to the registered
    /// cameras' moves, which moved every camera off the scene it had just been registered
    /// to. The poses `register_training` leaves are the ones `register_poses` found (and
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
        let whole = Planes {
            w: n,
            h: n,
            px: vec![[1.0; 4]; n * n],
        };
        let views = (0..8)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / 8.0;
                let eye = DVec3::new(6.0 * a.cos(), 6.0 * a.sin(), 1.5);
                let cam =
                    Camera::look_at(k, eye, DVec3::ZERO, DVec3::Z, Convention::OpenGl).unwrap();
                let (render, _) = render_points(&net, &cam, &whole, aabb, 0).unwrap();
                let byte = |x: f64| (x.clamp(0.0, 1.0) * 255.0).round() as u8;
                let rgb = render
                    .px
                    .iter()
                    .flat_map(|p| [byte(p[0]), byte(p[1]), byte(p[2])]);
                let alpha = render.px.iter().map(|p| byte(p[3]));
                View::new(
                    cam,
                    Image::new(n, n, 3, rgb.collect()).unwrap(),
                    Some(Image::new(n, n, 1, alpha.collect()).unwrap()),
                    format!("v{i}"),
                )
                .unwrap()
            })
            .collect();
        let data = Dataset::new(views, Background::Color([1.0; 3]), None).unwrap();
        let truth = poses_of(&data);
        let train = perturb(&data, 3.0, 0.03, 7).unwrap();
        let start = poses_of(&train);
        let expected = register_poses(&net, &train, &start, aabb, 1, &mut |_, _| {}).unwrap();
        let (turn, shift) = pose_errors(&expected, &start);
        assert!(turn > 1e-3 && shift > 1e-4, "{turn}° / {shift}");
        let poses: Vec<PoseParam> = start
            .iter()
            .map(|p| PoseParam::from_affine(p, &Device::Cpu, DType::F32).unwrap())
            .collect();
        register_training(&net, &args, &train, &poses, &truth, aabb, 0).unwrap();
        for (p, e) in poses.iter().zip(&expected) {
            let got = p.to_affine().unwrap();
            let (turn, shift) = pose_errors(&[got], &[*e]);
            assert!(
                turn < 1e-4 && shift < 1e-6,
                "{turn}° / {shift} from the registration"
            );
        }
    }

    /// Bilinear sampling: exact at pixel centres, its derivative that of the
    /// interpolation (central differences inside a cell); blurring keeps a constant image.
    #[test]
    fn planes_sample_bilinearly_with_their_gradient() {
        let mut rng = SplitMix64::new(5);
        let (w, h) = (7, 5);
        let px: Vec<[f64; 4]> = (0..w * h)
            .map(|_| std::array::from_fn(|_| rng.uniform()))
            .collect();
        let planes = Planes {
            w,
            h,
            px: px.clone(),
        };
        assert_eq!(planes.sample(DVec2::new(3.5, 2.5)).0, px[2 * w + 3]);
        for _ in 0..50 {
            let u = DVec2::new(0.5 + rng.uniform() * 6.0, 0.5 + rng.uniform() * 4.0);
            let (_, grad) = planes.sample(u);
            let e = 1e-7;
            for (axis, step) in [DVec2::X, DVec2::Y].into_iter().enumerate() {
                let (a, _) = planes.sample(u + step * e);
                let (b, _) = planes.sample(u - step * e);
                for c in 0..4 {
                    let fd = (a[c] - b[c]) / (2.0 * e);
                    // Within a cell; a sample on a cell edge has one-sided slopes.
                    if ((u[axis] - 0.5).fract() - 0.5).abs() < 0.49 {
                        assert!(
                            (grad[axis][c] - fd).abs() < 1e-6,
                            "{} vs {fd}",
                            grad[axis][c]
                        );
                    }
                }
            }
        }
        let flat = Planes {
            w,
            h,
            px: vec![[0.25, 0.5, 0.75, 1.0]; w * h],
        };
        for p in flat.blurred(1.5).px {
            assert!(p
                .iter()
                .zip([0.25, 0.5, 0.75, 1.0])
                .all(|(a, b)| (a - b).abs() < 1e-12));
        }
        assert_eq!(planes.blurred(0.0).px, px);
    }

    /// Direct image alignment registers a camera to an analytic textured ball: from
    /// 2° and 2 % of the distance off, four renders bring both errors below a quarter
    /// (a ball is the hardest case: its points lie at nearly one depth, so the centre and
    /// the rotation compensate each other almost exactly).
    #[test]
    fn alignment_registers_a_camera_to_a_textured_ball() {
        let k = neural_fields::camera::Intrinsics::from_fov_y(64, 64, 0.6).unwrap();
        let convention = neural_fields::camera::Convention::OpenGl;
        let truth = Camera::look_at(
            k,
            DVec3::new(2.0, -2.0, 1.0),
            DVec3::ZERO,
            DVec3::Z,
            convention,
        )
        .unwrap();
        // The ball of radius 0.5 at the origin, coloured by its point.
        let hit = |o: DVec3, d: DVec3| -> Option<DVec3> {
            let (a, b, c) = (d.dot(d), 2.0 * o.dot(d), o.dot(o) - 0.25);
            let disc = b * b - 4.0 * a * c;
            (disc >= 0.0).then(|| o + d * ((-b - disc.sqrt()) / (2.0 * a)))
        };
        let color = |p: DVec3| {
            [
                0.5 + 0.4 * (7.0 * p.x).sin(),
                0.5 + 0.4 * (5.0 * p.y + 2.0 * p.z).cos(),
                0.5 + 0.3 * (9.0 * p.z).sin(),
            ]
        };
        // The true image, 4 × 4 rays per pixel averaged (a filtered image).
        let mut px = Vec::new();
        for y in 0..64 {
            for x in 0..64 {
                let mut acc = [0.0; 4];
                for s in 0..16 {
                    let u = DVec2::new(
                        x as f64 + (s % 4) as f64 / 4.0 + 0.125,
                        y as f64 + (s / 4) as f64 / 4.0 + 0.125,
                    );
                    let (o, d) = truth.ray(u);
                    let c = hit(o, d).map_or([1.0, 1.0, 1.0, 0.0], |p| {
                        let c = color(p);
                        [c[0], c[1], c[2], 1.0]
                    });
                    for i in 0..4 {
                        acc[i] += c[i] / 16.0;
                    }
                }
                px.push(acc);
            }
        }
        let image = Planes { w: 64, h: 64, px };
        let levels: Vec<Planes> = ALIGN_LEVELS.iter().map(|&s| image.blurred(s)).collect();
        let start = perturb(
            &Dataset::new(
                vec![View::new(
                    truth,
                    neural_fields::data::Image::new(64, 64, 3, vec![0; 64 * 64 * 3]).unwrap(),
                    None,
                    "v".into(),
                )
                .unwrap()],
                Background::default(),
                None,
            )
            .unwrap(),
            2.0,
            0.02,
            11,
        )
        .unwrap();
        let mut pose = start.views()[0].camera().cam_to_world();
        let before = pose_errors(&[pose], &[truth.cam_to_world()]);
        for _ in 0..4 {
            let camera = Camera::new(k, pose, convention).unwrap();
            let pixels = box_pixels(&image, 4);
            let hits: Vec<(usize, DVec3, [f64; 3])> = pixels
                .iter()
                .filter_map(|&i| {
                    let (o, d) =
                        camera.ray(DVec2::new((i % 64) as f64 + 0.5, (i / 64) as f64 + 0.5));
                    hit(o, d).map(|p| (i, p, color(p)))
                })
                .collect();
            let (render, points) = surface_render(&camera, (64, 64), &pixels, &hits);
            pose = align_view(&camera, &levels, &render, &points).unwrap();
        }
        let after = pose_errors(&[pose], &[truth.cam_to_world()]);
        assert!((before.0 - 2.0).abs() < 1e-6 && (before.1 - 0.02).abs() < 1e-9);
        assert!(
            after.0 < before.0 / 4.0 && after.1 < before.1 / 4.0,
            "{before:?} -> {after:?}"
        );
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
