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
//! (`val` if there is none) is held out, composited on white. The scene box is the one
//! the layout states, else the visual hull of the training silhouettes grown by 5 %
//! ([`Dataset::scene_box`]); `--aabb H` sets the cube ±H instead.
//!
//! **Model.** `--model dvr`, `dvr-joint` or `idr` ([`SurfaceKind`]; `--render-inputs`
//! IDR's ablations), `--encoding hash` instant-NGP's hash grid under the networks: the
//! library's [`SurfaceModel`]. **One step** on `--rays` pixels drawn as 2 × 2 patches is
//! [`SurfaceModel::loss`]: the rays marched through the scene box (sphere tracing for
//! IDR), the hit points made differentiable, L1 photometric and DVR's image-gradient loss
//! inside the mask; for `dvr`/`dvr-joint` freespace and occupancy BCE at the most-occupied
//! of 64 samples of the rays that should miss or should have hit, and normal smoothness;
//! for `idr` IDR's mask loss (weight 100, α doubling over the run) and the eikonal loss.
//! The DVR geometry starts as a ball of radius 0.5; Adam with a log-linear decay from
//! `--lr` to a tenth.
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
//! `eval_views`, `data`, `scene_box`; with cameras moved or refined also `pose_rotation_error_deg`,
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
use neural_fields::camera::{pose_error, reprojection_error, PoseParam, Similarity};
use neural_fields::data::{
    comparison_strip, load, load_eval, psnr, write_png, Background, Dataset, LoadConfig, RayBatch,
    RaySampler, View,
};
use neural_fields::dvr::{
    surface_model, SurfaceEncoding, SurfaceKind, SurfaceModel, SurfaceModelConfig,
};
use neural_fields::encoding::CoarseToFine;
use neural_fields::field::{ImplicitSurface, Inside, SignedDistance, Sphere};
use neural_fields::glam::{DAffine3, DVec3};
use neural_fields::mesh::Mesh;
use neural_fields::nn::{adam, build_seeded, Budget, Clock, FiniteGuard};
use neural_fields::numerics::bce_with_logits;
use neural_fields::occupancy::{chamfer_icp, iou, mesh_metrics, mise, MiseConfig};
use neural_fields::rng::SplitMix64;
use neural_fields::texture::{vertex_colors, TextureField, TextureInput};
use neural_fields::volume::{log_linear_schedule, render_image, ImageConfig};
use neural_fields::{Error, Result};
use std::path::{Path, PathBuf};

mod cameras;
#[cfg(test)]
mod tests;

use cameras::*;

#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Rays per chunk when rendering whole views.
const CHUNK: usize = 8192;
/// Rays per pixel side when rendering held-out views (2 × 2 per pixel).
const SUPERSAMPLE: usize = 2;

/// The model.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Model {
    /// An occupancy network and a texture field (Texture Fields' decoder): one colour
    /// per surface point, whatever the view.
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

/// Stops on a NaN or infinity in a weight that `guard` watches, naming it and the step.
fn check_weights(guard: &FiniteGuard, step: usize) -> Result<()> {
    let zero = Tensor::zeros((), DType::F32, &Device::Cpu)?;
    guard.check(step, &zero, Some(&zero.backward()?))
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
    /// Read image and mask files outside the dataset folder (absolute paths, `../`,
    /// symlinks to elsewhere), which loading refuses by default.
    #[arg(long)]
    pub allow_outside_paths: bool,
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
    /// Half-side of the scene cube. Without it: the box the layout states, else the
    /// visual hull of the training silhouettes grown by 5 % (`Dataset::scene_box`).
    #[arg(long)]
    pub aabb: Option<f64>,
    #[arg(long, default_value_t = 500)]
    pub eval_every: usize,
    /// Held-out views of the periodic evaluations.
    #[arg(long, default_value_t = 4)]
    pub eval_views: usize,
    /// Held-out views written as pictures.
    #[arg(long, default_value_t = 4)]
    pub pictures: usize,
    /// The learning rate, in [0, 0.1] (default 1e-3, or 1e-2 for the DVR models on hash
    /// grids).
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
        if self.aabb.is_some_and(|h| !(h > 0.0 && h.is_finite())) {
            return Err("--aabb must be positive".into());
        }
        // A rate of 0 freezes what it drives (`--pose-lr 0`: the poses); above 0.1 Adam
        // collapses these networks within a few steps (a dead run).
        let rate = |v: f64| (0.0..=0.1).contains(&v);
        if !rate(self.pose_lr) || self.lr.is_some_and(|lr| !rate(lr)) {
            return Err("--lr and --pose-lr must be in [0, 0.1]".into());
        }
        Ok(self)
    }
}

/// Builds the model of `args` in `varmap` (CPU, f32, initialised from `--seed`) over the
/// scene box `aabb`, hash grids up to the resolution `finest`.
fn build(args: &Args, aabb: [f64; 6], finest: f64, varmap: &VarMap) -> Result<SurfaceModel> {
    use neural_fields::dvr::RenderInputs as Inputs;
    let config = SurfaceModelConfig {
        kind: match args.model {
            Model::Dvr => SurfaceKind::Dvr,
            Model::DvrJoint => SurfaceKind::DvrJoint,
            Model::Idr => SurfaceKind::Idr,
        },
        encoding: match args.encoding {
            PositionEncoding::Pe => SurfaceEncoding::Frequency,
            PositionEncoding::Hash => SurfaceEncoding::HashGrid {
                finest_resolution: finest,
            },
        },
        render_inputs: match args.render_inputs {
            RenderInputs::Full => Inputs::Full,
            RenderInputs::NoView => Inputs::NoView,
            RenderInputs::NoNormal => Inputs::NoNormal,
        },
        scene_box: aabb,
        coarse_to_fine: args.coarse_to_fine.is_some(),
        patch: 2,
    };
    build_seeded(varmap, DType::F32, &Device::Cpu, args.seed, |vb| {
        surface_model(&config, vb)
    })
}

/// An error naming `data`: it was expected to hold `expected`, and holds `got`.
fn data_error(expected: &str, got: String) -> Error {
    let expected = expected.to_string();
    Error::InvalidArgument {
        arg: "data",
        expected,
        got,
    }
}

/// The mask of `view` (CPU, f32); an error naming `data` and the view when it has none.
fn mask_of(view: &View) -> Result<Tensor> {
    let missing = format!("{} without one", view.name());
    let no = || data_error("views with masks (alpha or mask files)", missing);
    view.mask(&Device::Cpu, DType::F32)?.ok_or_else(no)
}

/// Checks that every view of `data` has a mask and that some mask covers a pixel.
///
/// # Errors
/// Naming `data`: a view without a mask (naming it), or masks that are all empty.
fn check_masks(data: &Dataset) -> Result<()> {
    let mut covered = false;
    for v in data.views() {
        covered |= mask_of(v)?.ge(0.5)?.max_all()?.to_scalar::<u8>()? != 0;
    }
    match covered {
        true => Ok(()),
        false => Err(data_error(
            "masks that cover the object in some training view",
            format!("{} views whose masks are all empty", data.views().len()),
        )),
    }
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

/// The metrics of [`Evaluation`] over the first `n` views of `eval`, each view rendered
/// whole ([`render_image`], 2 × 2 rays per pixel).
fn evaluate(model: &SurfaceModel, eval: &Dataset, n: usize) -> Result<Evaluation> {
    let (cpu, f32) = (&Device::Cpu, DType::F32);
    let (supersample, chunk) = (SUPERSAMPLE, CHUNK);
    let image = ImageConfig {
        supersample,
        chunk,
        ..ImageConfig::default()
    };
    // Every view's pixels in one column (colour, truth, coverage, mask): pooled metrics.
    let (mut renders, mut pixels) = (Vec::new(), [(); 4].map(|_| Vec::new()));
    for view in eval.views().iter().take(n) {
        let truth = view.rgb([1.0; 3], cpu, f32)?;
        let [color, coverage, normals] = render_image(view.camera(), &image, cpu, f32, |rays| {
            let seen = model.shade(rays)?;
            Ok([seen.rgb, seen.coverage, seen.normals])
        })?;
        let mask = mask_of(view)?;
        for (column, t) in pixels.iter_mut().zip([&color, &truth, &coverage, &mask]) {
            column.push(t.reshape(((), 1, t.elem_count() / (t.dim(0)? * t.dim(1)?)))?);
        }
        renders.push([truth, color, normals]);
    }
    let [color, truth, coverage, mask] = pixels.map(|p| Tensor::cat(&p, 0));
    let (color, truth, coverage, mask) = (color?, truth?, coverage?.squeeze(2)?, mask?.squeeze(2)?);
    let inside = |t: &Tensor, at: f64| -> Result<Vec<bool>> {
        Ok(t.ge(at)?
            .flatten_all()?
            .to_vec1::<u8>()?
            .iter()
            .map(|&b| b != 0)
            .collect())
    };
    // PSNR on the pixels where `m ≥ at`, NaN where there are none.
    let psnr_on = |at: f64| -> Result<f64> {
        let m = mask.ge(at)?.to_dtype(f32)?;
        match inside(&mask, at)?.contains(&true) {
            true => psnr(&color, &truth, Some(&m)),
            false => Ok(f64::NAN),
        }
    };
    Ok(Evaluation {
        iou: iou(&inside(&coverage, 0.5)?, &inside(&mask, 0.5)?)?,
        psnr_masked: psnr_on(0.5)?,
        psnr_interior: psnr_on(1.0)?,
        renders,
    })
}

/// An error naming the file `path`, whose `field` is not `expected`.
fn format_error(path: &Path, field: &str, expected: &str) -> Error {
    let (path, field) = (path.display().to_string(), field.to_string());
    let (expected, got) = (expected.to_string(), "something else".to_string());
    Error::Format {
        path,
        field,
        expected,
        got,
    }
}

/// The source mesh in the dataset's world frame: `--mesh`, or `scene.json`'s `mesh` with
/// its `normalisation.matrix` and `object_radius` scale (as the render script writes
/// them); `None` when neither is there or the file is of a format the crate does not
/// read (the suite's Collada meshes). Read before training, so that a bad file stops the
/// run at once.
fn source_mesh(args: &Args) -> Result<Option<Mesh>> {
    if let Some(path) = &args.mesh {
        return Ok(Some(Mesh::load(path)?));
    }
    let scene = args.data.join("scene.json");
    let Ok(text) = std::fs::read_to_string(&scene) else {
        return Ok(None);
    };
    let bad = |what: &str| format_error(&scene, what, "the render script's scene description");
    let json: serde_json::Value = serde_json::from_str(&text).map_err(|_| bad("(JSON)"))?;
    let Some(path) = json["mesh"].as_str() else {
        return Ok(None);
    };
    if !Path::new(path).is_file() {
        println!("source mesh {path} not found: no Chamfer distance");
        return Ok(None);
    }
    let readable = Path::new(path)
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| ["ply", "obj", "stl", "off"].contains(&e.to_ascii_lowercase().as_str()));
    if !readable {
        println!("source mesh {path} is not a .ply, .obj, .stl or .off file: no Chamfer distance");
        return Ok(None);
    }
    let m: Vec<Vec<f64>> = serde_json::from_value(json["normalisation"]["matrix"].clone())
        .map_err(|_| bad("normalisation.matrix"))?;
    if m.len() < 3 || m.iter().take(3).any(|r| r.len() != 4) {
        return Err(bad("normalisation.matrix"));
    }
    // The render script scales the normalised mesh by `object_radius` when it states one.
    let radius = match json.get("object_radius") {
        None => 1.0,
        Some(r) => r
            .as_f64()
            .filter(|r| r.is_finite() && *r > 0.0)
            .ok_or_else(|| bad("object_radius"))?,
    };
    let mut mesh = Mesh::load(path)?;
    for v in &mut mesh.vertices {
        let p = *v;
        *v = std::array::from_fn(|r| {
            radius * (m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3])
        });
    }
    mesh.normals = None;
    Ok(Some(mesh))
}

/// The surface by MISE (`resolution0`, refined twice) with the texture's vertex colours.
fn extract_mesh(model: &SurfaceModel, aabb: [f64; 6], resolution0: usize) -> Result<Mesh> {
    let (device, dtype) = (Device::Cpu, DType::F32);
    let (min, max) = ([aabb[0], aabb[1], aabb[2]], [aabb[3], aabb[4], aabb[5]]);
    let config = MiseConfig {
        min,
        max,
        ..MiseConfig::new(resolution0, 2, &device, dtype)
    };
    let mut mesh = mise(model, &config)?.mesh;
    if mesh.faces.is_empty() {
        return Ok(mesh);
    }
    let colors = vertex_colors(&mesh, 16_384, &device, dtype, |p| {
        // View the surface head-on: along the inward normal.
        let inward = match model.inside() {
            Inside::Positive => 1.0,
            Inside::Negative => -1.0,
        };
        let dirs = (model.value_and_grad(p)?.1.detach() * inward)?;
        let view_dirs = Some(&dirs);
        Ok(model
            .rgb(&TextureInput {
                view_dirs,
                ..TextureInput::new(p)
            })?
            .detach())
    })?;
    mesh.colors = Some(colors);
    mesh.validate()?;
    Ok(mesh)
}

/// Chamfer-L1 of `pred` to `gt` in `gt`'s unit cube (ONet's normalisation, 100 000
/// samples on each).
fn chamfer(pred: &Mesh, gt: &Mesh, seed: u64) -> Result<f64> {
    let (mut gt, mut pred) = (gt.clone(), pred.clone());
    let (centre, scale) = gt.normalize_unit_cube()?;
    for v in &mut pred.vertices {
        *v = std::array::from_fn(|c| (v[c] - centre[c]) * scale);
    }
    Ok(mesh_metrics(&pred, &gt, 100_000, 0.01, seed)?.chamfer_l1)
}

/// The masks of `batch` (every view of `data` has one).
fn batch_mask<'a>(batch: &'a RayBatch, data: &Dataset) -> Result<&'a Tensor> {
    let missing = format!("{} without one", data.views()[0].name());
    let no = || data_error("views with masks (alpha or mask files)", missing);
    batch.masks.as_ref().ok_or_else(no)
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
        allow_outside_paths: args.allow_outside_paths,
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
    // The poses' variables, with an optimiser and a guard of their own.
    let pose_map = VarMap::new();
    for (v, p) in poses.iter().enumerate() {
        let mut vars = pose_map.data().lock().expect("an unpoisoned VarMap"); // invariant
        vars.insert(format!("pose{v}.rotation"), p.rotation.clone());
        vars.insert(format!("pose{v}.translation"), p.translation.clone());
    }
    let mut pose_opt = pose_adam(pose_map.all_vars(), args.pose_lr)?;
    let pose_guard = FiniteGuard::new(&pose_map);
    let (eval, eval_split) = load_eval(&args.data, &config)?;
    let eval_split = format!("{eval_split:?}").to_lowercase();
    std::fs::create_dir_all(&args.out).map_err(|source| Error::Io {
        path: args.out.display().to_string(),
        source,
    })?;
    // The cube ±`--aabb` when given, else `Dataset::scene_box`: the box the layout
    // states, else the training silhouettes' hull + 5 % (else ±1.1, for views without
    // masks, which `run` refuses before).
    let aabb = match args.aabb {
        Some(h) => [-h, -h, -h, h, h, h],
        None => train.scene_box(1.1),
    };
    let gt = source_mesh(args)?;
    let mut varmap = VarMap::new();
    let net = build(args, aabb, train.hash_finest(), &varmap)?;
    let guard = FiniteGuard::new(&varmap);
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
    } else if args.model != Model::Idr {
        // Start from a ball at the box's centre, of radius 0.45 of its smallest half-side
        // (0.5 in the cube ±1.1), so that the first marches find a surface.
        let (lo, hi) = (
            Tensor::new(&aabb[..3], &device)?.to_dtype(dtype)?,
            Tensor::new(&aabb[3..], &device)?.to_dtype(dtype)?,
        );
        let centre = [0, 1, 2].map(|i| 0.5 * (aabb[i] + aabb[i + 3]));
        let half = (0..3)
            .map(|i| 0.5 * (aabb[i + 3] - aabb[i]))
            .fold(f64::INFINITY, f64::min);
        let ball = Sphere::new(centre, 0.5 / 1.1 * half, &device, dtype)?.occupancy(10.0);
        let mut rng = SplitMix64::new(args.seed ^ 0xBA11);
        for _ in 0..150 {
            let u = rng.uniform_tensor(&[4096, 3], 0.0, 1.0, dtype, &device)?;
            let p = u.broadcast_mul(&(&hi - &lo)?)?.broadcast_add(&lo)?;
            let y = ball.value(&p)?.gt(0.0)?.to_dtype(dtype)?;
            opt.backward_step(&bce_with_logits(&net.value(&p)?, &y)?.mean_all()?)?;
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
        open_windows(&net.windows, progress, args.coarse_to_fine)?;
        let batch = sampler.patches(args.rays / 4, 2)?;
        let rays = match poses.is_empty() {
            true => batch.rays.clone(),
            false => batch_rays(&poses, &train, &batch)?,
        };
        let seed = args.seed ^ (step as u64).wrapping_mul(0x9E37_79B9);
        let mask = batch_mask(&batch, &train)?;
        let terms = net.loss(&rays, &batch.colors, mask, progress, seed)?;
        let (loss, photo) = (terms.total, terms.photometric);
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
            register_training(&net, args, &train, (&poses, &true_poses), step)?;
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
                check_weights(&guard, step)?;
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
                let e = evaluate(&net, aligned.as_ref().unwrap_or(&eval), args.eval_views)?;
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
        register_training(&net, args, &train, (&poses, &true_poses), step)?;
    }
    let train_seconds = clock.train_seconds();
    bar.finish_and_clear();
    // The windows as the schedule leaves them (every band open unless END > 1).
    open_windows(&net.windows, 1.0, args.coarse_to_fine)?;
    check_weights(&guard, step)?;
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
            PoseSolver::Adam => {
                let (steps, lr) = (args.test_pose_steps, args.pose_lr);
                refine_eval_poses(&net, aligned, steps, lr, args.seed)?
            }
            PoseSolver::Lm => {
                let at = poses_of(aligned);
                let rounds = args.lm_iterations;
                aligned.with_poses(&register(&net, aligned, &at, rounds, &mut |_, _| {})?)?
            }
        }),
        _ => None,
    };
    let final_eval = registered
        .as_ref()
        .or(aligned_eval.as_ref())
        .unwrap_or(&eval);
    let all = evaluate(&net, final_eval, eval.views().len())?;
    let first = evaluate(&net, final_eval, args.eval_views)?;
    curve.push_str(&format!(
        "{step},{train_seconds:.3},{:.4},{:.4}\n",
        first.iou, first.psnr_masked
    ));
    for (i, [truth, color, normals]) in all.renders.iter().enumerate().take(args.pictures) {
        let png = |what: &str| args.out.join(format!("{what}_{i}.png"));
        write_png(&png("view"), &comparison_strip(truth, color)?)?;
        write_png(&png("normals"), &normals.affine(0.5, 0.5)?)?;
    }
    // The mesh in the dataset's frame; as extracted too when the frames differ.
    let (mesh, learnt_mesh) = match poses.is_empty() {
        true => (extracted, None),
        false => (
            mesh_to_dataset_frame(extracted.clone(), &frame),
            Some(extracted),
        ),
    };
    // Chamfer distances to the source mesh, where there are one and a surface.
    let gt_for = |m: &Mesh| gt.as_ref().filter(|_| !m.faces.is_empty());
    let chamfer_of = |m: &Mesh| gt_for(m).map(|gt| chamfer(m, gt, args.seed)).transpose();
    let chamfer_l1 = chamfer_of(&mesh)?;
    let icp = gt_for(&mesh).map(|gt| chamfer_icp(&mesh, gt, 100_000, args.seed));
    let chamfer_l1_icp = icp.transpose()?;
    if !mesh.faces.is_empty() {
        mesh.save(args.out.join("mesh.ply"))?;
    }
    varmap.save(args.out.join("weights.safetensors"))?;
    write(&args.out.join("curve.csv"), &curve)?;
    let (encoding, inputs) = (name(args.encoding), name(args.render_inputs));
    let mut metrics = serde_json::json!({
        "mask_iou": all.iou, "psnr_masked": all.psnr_masked, "psnr_interior": all.psnr_interior,
        "chamfer_l1": chamfer_l1, "chamfer_l1_icp": chamfer_l1_icp, "train_seconds": train_seconds,
        "steps": step, "model": model, "encoding": encoding, "render_inputs": inputs,
        "eval_split": eval_split, "eval_views": eval.views().len(), "data": args.data.display().to_string(),
        "scene_box": aabb,
    });
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
        let errors = |b, a, al| serde_json::json!({"before": b, "after": a, "after_aligned": al});
        metrics["pose_rotation_error_deg"] = errors(r0, r1, r2);
        metrics["pose_centre_error_fraction"] = errors(t0, t1, t2);
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
        metrics["aligned"] = eval_json(&evaluate(&net, aligned, eval.views().len())?);
        metrics["test_pose_steps"] = serde_json::json!(args.test_pose_steps);
    }
    if let Some(learnt) = &learnt_mesh {
        let mut unaligned = eval_json(&evaluate(&net, &eval, eval.views().len())?);
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
