//! Views, datasets, the loading options and the loader entry point, which detects the
//! layout and hands the folder to that layout's reader (Blender, nerfstudio, IDR/DTU).

use super::image::{Header, Image};
use super::layout::{confine, Bounds, DatasetLayout, FrameSpec, IntrinsicsSpec, Split};
use super::{blender, dtu, nerfstudio};
use crate::camera::{Camera, Intrinsics};
use crate::error::check_dtype;
use crate::error::{Error, Result};
use candle_core::{DType, Device, Tensor};
use glam::DAffine3;
use rayon::prelude::*;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// One calibrated picture: a camera, its image and an optional mask.
///
/// The mask of a view is its mask file where the layout has one (DTU's `mask/`,
/// nerfstudio's `mask_path`), else the image's alpha channel, else none.
#[derive(Clone, Debug)]
pub struct View {
    camera: Camera,
    // Shared: frames that name one file hold one decoded copy.
    image: Arc<Image>,
    mask: Option<Arc<Image>>,
    name: String,
}

impl View {
    /// A view from a camera, an RGB or RGBA image of the camera's size, and an optional
    /// one-channel mask of the same size; `name` is what error messages and writers call it
    /// (for loaded views, the image file's path).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `image` if it has 1 channel or its size is not the
    /// camera's, and `mask` unless it has 1 channel and the camera's size.
    pub fn new(camera: Camera, image: Image, mask: Option<Image>, name: String) -> Result<Self> {
        Self::shared(camera, Arc::new(image), mask.map(Arc::new), name)
    }

    /// [`View::new`] with an image and mask that other views may share.
    pub(crate) fn shared(
        camera: Camera,
        image: Arc<Image>,
        mask: Option<Arc<Image>>,
        name: String,
    ) -> Result<Self> {
        let k = camera.intrinsics();
        let (w, h, c) = image.size();
        if c == 1 || (w, h) != (k.width, k.height) {
            return Err(Error::invalid(
                "image",
                format!(
                    "an RGB or RGBA image of the camera's size {} × {}",
                    k.width, k.height
                ),
                format!("{w} × {h} with {c} channels"),
            ));
        }
        if let Some(m) = &mask {
            let (mw, mh, mc) = m.size();
            if mc != 1 || (mw, mh) != (k.width, k.height) {
                return Err(Error::invalid(
                    "mask",
                    format!("a one-channel mask of size {} × {}", k.width, k.height),
                    format!("{mw} × {mh} with {mc} channels"),
                ));
            }
        }
        Ok(Self {
            camera,
            image,
            mask,
            name,
        })
    }

    /// The camera.
    #[must_use]
    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// The image (RGB, or RGBA with straight alpha).
    #[must_use]
    pub fn image(&self) -> &Image {
        &self.image
    }

    /// The mask file's image (one channel), if the view has one.
    #[must_use]
    pub(crate) fn mask_image(&self) -> Option<&Image> {
        self.mask.as_deref()
    }

    /// The name: for loaded views, the path of the image file.
    #[must_use]
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Whether the view has a mask (a mask file or an alpha channel).
    pub(crate) fn has_mask(&self) -> bool {
        self.mask.is_some() || self.image.size().2 == 4
    }

    /// Colour of pixel `(u, v)` composited on `background`: `c·a + b·(1 − a)` with the
    /// straight colour `c` and alpha `a` (1 without an alpha channel), all `byte / 255`.
    pub(crate) fn color(&self, u: usize, v: usize, background: [f64; 3]) -> [f64; 3] {
        // Every caller (the samplers, `rgb`) passes (u, v) inside the image.
        let p = self.image.pixel(u, v).expect("pixel inside the image"); // invariant
        let a = if p.len() == 4 {
            f64::from(p[3]) / 255.0
        } else {
            1.0
        };
        std::array::from_fn(|c| f64::from(p[c]) / 255.0 * a + background[c] * (1.0 - a))
    }

    /// The mask value of pixel `(u, v)` in `[0, 1]` (see the type's docs), if any.
    pub(crate) fn mask_value(&self, u: usize, v: usize) -> Option<f64> {
        match &self.mask {
            Some(m) => Some(f64::from(m.pixel(u, v)?[0]) / 255.0),
            None if self.image.size().2 == 4 => Some(f64::from(self.image.pixel(u, v)?[3]) / 255.0),
            None => None,
        }
    }

    /// The whole image composited on `background` (see [`View::new`]'s mask rule for
    /// alpha): `[H, W, 3]` in `dtype` (f32 or f64) on `device`, values in `[0, 1]`.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `dtype` unless f32 or f64, `background` unless in
    /// `[0, 1]`.
    pub fn rgb(&self, background: [f64; 3], device: &Device, dtype: DType) -> Result<Tensor> {
        check_dtype(dtype)?;
        check_background(&Background::Color(background))?;
        let (w, h, _) = self.image.size();
        let mut data = Vec::with_capacity(3 * w * h);
        for v in 0..h {
            for u in 0..w {
                data.extend_from_slice(&self.color(u, v, background));
            }
        }
        Ok(Tensor::from_vec(data, (h, w, 3), device)?.to_dtype(dtype)?)
    }

    /// The mask as `[H, W]` values in `[0, 1]` in `dtype` on `device`; `None` if the view
    /// has none.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `dtype` unless f32 or f64.
    pub fn mask(&self, device: &Device, dtype: DType) -> Result<Option<Tensor>> {
        check_dtype(dtype)?;
        if !self.has_mask() {
            return Ok(None);
        }
        let (w, h, _) = self.image.size();
        let mut data = Vec::with_capacity(w * h);
        for v in 0..h {
            for u in 0..w {
                data.push(self.mask_value(u, v).unwrap_or(1.0));
            }
        }
        Ok(Some(
            Tensor::from_vec(data, (h, w), device)?.to_dtype(dtype)?,
        ))
    }
}

/// The colour behind transparent pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Background {
    /// One colour (RGB in `[0, 1]`) for training and evaluation.
    Color([f64; 3]),
    /// A uniform random colour per ray in every training batch (so the field cannot
    /// explain transparency by colour; nerfacc's recipe for the Blender scenes), white for
    /// evaluation ([`Background::eval_color`]). Batches carry the colour used, to composite the
    /// prediction on.
    Random,
}

impl Default for Background {
    /// White, the convention of the Blender synthetic scenes.
    fn default() -> Self {
        Background::Color([1.0; 3])
    }
}

impl Background {
    /// The colour used for evaluation.
    #[must_use]
    pub fn eval_color(&self) -> [f64; 3] {
        match self {
            Background::Color(c) => *c,
            Background::Random => [1.0; 3],
        }
    }
}

fn check_background(background: &Background) -> Result<()> {
    match background {
        Background::Color(c) if !c.iter().all(|x| (0.0..=1.0).contains(x)) => Err(Error::invalid(
            "background",
            "a colour in [0, 1]",
            format!("{c:?}"),
        )),
        _ => Ok(()),
    }
}

/// How to load a dataset ([`load`]).
#[derive(Clone, Debug, PartialEq)]
pub struct LoadConfig {
    /// The split to load (default train).
    pub split: Split,
    /// The layout; `None` detects it from the files present (see [`DatasetLayout`]).
    pub layout: Option<DatasetLayout>,
    /// The colour behind transparent pixels (default white).
    pub background: Background,
    /// Integer downscaling factor ≥ 1 (box filter; intrinsics scaled by `1/k`; default 1).
    pub downscale: usize,
    /// A subset of the split's frames by index in the split's order (sparse-view training:
    /// "these 3 views"); `None` loads all.
    pub frames: Option<Vec<usize>>,
    /// Whether image and mask paths may lead outside the dataset folder (default false).
    /// By default a path that, resolved (symlinks followed), lies outside the folder's
    /// canonical path — an absolute `file_path`, a `../` that climbs out, a symlink to
    /// elsewhere — is an [`Error::Format`] naming the file, the frame and the field: a
    /// downloaded dataset should not read the rest of the disk. Set it for datasets whose
    /// images are shared between folders by such paths. Either way only regular,
    /// non-empty files are opened (not directories, devices, FIFOs or `/proc` files).
    pub allow_outside_paths: bool,
    /// The most bytes of decoded images one load may hold (default 4 GiB, 2³² bytes),
    /// checked from the image headers before any pixel is decoded: the sum over the
    /// distinct files of the larger of the decoder's output (16-bit channels take 2 bytes)
    /// and the 8-bit image kept (3 or 4 bytes per pixel, 1 for a mask). A file that many
    /// frames name is decoded once and shared, so it counts once. Exceeding it is an
    /// [`Error::Format`] naming the largest file, with the bytes needed and the budget.
    pub max_decoded_bytes: u64,
    /// The most pixels of one image or mask (default 2²⁶, 8192 × 8192), checked from its
    /// header before decoding: a file whose header claims more (a 74-byte PNG can claim
    /// 32768 × 32768) is an [`Error::Format`] naming it. Besides, an image of more than
    /// 16 times the median pixel count of the frames loaded is refused (a stray or hostile
    /// file among the views).
    pub max_image_pixels: u64,
}

/// How many times the median image of a load an image may be, in pixels.
const MEDIAN_RATIO: u64 = 16;

impl Default for LoadConfig {
    fn default() -> Self {
        Self {
            split: Split::Train,
            layout: None,
            background: Background::default(),
            downscale: 1,
            frames: None,
            allow_outside_paths: false,
            max_decoded_bytes: 4 << 30,
            max_image_pixels: 1 << 26,
        }
    }
}

/// Calibrated views with a background rule and, where the layout gives them, scene bounds.
#[derive(Clone, Debug)]
pub struct Dataset {
    views: Vec<View>,
    background: Background,
    bounds: Option<Bounds>,
}

impl Dataset {
    /// A dataset from views (at least one), e.g. renders of an analytic scene to write with
    /// [`crate::data::write_blender`].
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `views` if empty, `background` unless its colour is
    /// in `[0, 1]`.
    pub fn new(views: Vec<View>, background: Background, bounds: Option<Bounds>) -> Result<Self> {
        if views.is_empty() {
            return Err(Error::invalid("views", "at least one view", "none"));
        }
        check_background(&background)?;
        Ok(Self {
            views,
            background,
            bounds,
        })
    }

    /// The views.
    #[must_use]
    pub fn views(&self) -> &[View] {
        &self.views
    }

    /// The background rule.
    #[must_use]
    pub fn background(&self) -> Background {
        self.background
    }

    /// The scene bounds the layout states (nerfstudio's `aabb_scale`, IDR/DTU's unit
    /// sphere); `None` for the Blender layout, which states none.
    #[must_use]
    pub fn bounds(&self) -> Option<Bounds> {
        self.bounds
    }

    /// The same dataset with its views' cameras moved to `poses` (camera-to-world, one per
    /// view, in order): intrinsics, conventions, images, masks, names, the background and
    /// the bounds kept. For cameras perturbed or refined, or moved into another frame
    /// ([`crate::camera::Similarity::apply`]).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `poses` unless there is one per view, each a
    /// finite rigid transform (as [`Camera::new`] requires).
    pub fn with_poses(&self, poses: &[DAffine3]) -> Result<Dataset> {
        if poses.len() != self.views.len() {
            return Err(Error::invalid(
                "poses",
                format!("{} poses (one per view)", self.views.len()),
                poses.len().to_string(),
            ));
        }
        let views = self
            .views
            .iter()
            .zip(poses)
            .enumerate()
            .map(|(i, (v, pose))| {
                let cam = v.camera();
                let moved = Camera::new(*cam.intrinsics(), *pose, cam.convention()).map_err(
                    |e| match e {
                        Error::InvalidArgument { expected, got, .. } => Error::InvalidArgument {
                            arg: "poses",
                            expected,
                            got: format!("pose {i}: {got}"),
                        },
                        other => other,
                    },
                )?;
                View::shared(
                    moved,
                    Arc::clone(&v.image),
                    v.mask.clone(),
                    v.name().to_string(),
                )
            })
            .collect::<Result<Vec<_>>>()?;
        Dataset::new(views, self.background, self.bounds)
    }
}

/// Loads the dataset in `dir` ([`DatasetLayout`]: Blender, nerfstudio or IDR/DTU).
///
/// Image headers are read first and checked against the memory budget of `config`; then
/// each distinct file is decoded once, in parallel, kept as bytes and shared by the
/// frames that name it. Image and mask paths must lie inside `dir` unless
/// [`LoadConfig::allow_outside_paths`]. Every camera is validated (finite, rigid, of the
/// image's size; focal lengths in [10⁻³, 10⁶] pixels, fields of view in
/// [10⁻³, π − 10⁻³] radians, principal points, image sides, `scale`, `offset`,
/// `aabb_scale` and camera centres of magnitude at most 10⁶). Poses within 1e-3 of a
/// rotation but not within 1e-6 (the rounding of some exporters) are orthonormalised;
/// others are errors.
///
/// ```
/// use neural_fields::data::{load, LoadConfig, Split};
/// let train = load("examples/data/wuson".as_ref(), &LoadConfig::default())?;
/// let test = load(
///     "examples/data/wuson".as_ref(),
///     &LoadConfig { split: Split::Test, ..LoadConfig::default() },
/// )?;
/// println!("{} training views, {} test views", train.views().len(), test.views().len());
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::Io`] naming a missing or unreadable file; [`Error::Format`] naming the file and
/// the field for malformed content (JSON without `frames`, a singular or non-rigid
/// `transform_matrix`, NaN in a pose, an unsupported camera model or lens distortion, an
/// image or mask of the wrong size, a truncated PNG, an empty split), and naming the file
/// that lists an image or mask, the frame and the field (`frames[3].file_path`) for a path
/// outside the dataset folder (unless [`LoadConfig::allow_outside_paths`]) or a file that
/// is not a regular, non-empty file; [`Error::Format`] naming an image whose header states
/// more than [`LoadConfig::max_image_pixels`] pixels or more than 16 times the median
/// image's, or the largest file when the images would decode to more than
/// [`LoadConfig::max_decoded_bytes`] (all checked before decoding);
/// [`Error::InvalidArgument`] naming `downscale` if 0 or larger than an image, `frames`
/// for an index outside the split.
pub fn load(dir: &Path, config: &LoadConfig) -> Result<Dataset> {
    if config.downscale == 0 {
        return Err(Error::invalid("downscale", "an integer ≥ 1", "0"));
    }
    check_background(&config.background)?;
    let layout = match config.layout {
        Some(l) => l,
        None => DatasetLayout::detect(dir)?,
    };
    let (frames, bounds) = match layout {
        DatasetLayout::Blender => blender::frames(dir, config.split)?,
        DatasetLayout::Nerfstudio => nerfstudio::frames(dir, config.split)?,
        DatasetLayout::Dtu => dtu::frames(dir, config.split)?,
    };
    let frames = select(frames, config.frames.as_deref())?;
    let root = dir.canonicalize().map_err(|source| Error::Io {
        path: dir.display().to_string(),
        source,
    })?;
    let frames = frames
        .into_iter()
        .map(|f| {
            let allow = config.allow_outside_paths;
            let image = confine(&root, &f.image, &f.listed_in, &f.image_field, allow)?;
            let mask = match &f.mask {
                Some(m) => Some(confine(&root, m, &f.listed_in, &f.mask_field, allow)?),
                None => None,
            };
            Ok(Located {
                frame: f,
                image: (image, false),
                mask: mask.map(|m| (m, true)),
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let views = load_views(frames, config)?;
    Dataset::new(views, config.background, bounds)
}

/// A decoded file: its canonical path and whether it is read as a mask (one channel).
type FileKey = (PathBuf, bool);

/// A frame with the keys of its image and mask files.
struct Located {
    frame: FrameSpec,
    image: FileKey,
    mask: Option<FileKey>,
}

/// The views of `frames`, within `config`'s memory budget: every file's header read
/// first (each file once), the sizes checked against the budget and against each other,
/// then each file decoded once (in parallel) and shared by the frames that name it.
fn load_views(frames: Vec<Located>, config: &LoadConfig) -> Result<Vec<View>> {
    let mut keys: Vec<FileKey> = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for f in &frames {
        for key in std::iter::once(&f.image).chain(&f.mask) {
            if seen.insert(key) {
                keys.push(key.clone());
            }
        }
    }
    let headers: HashMap<FileKey, Header> = keys
        .par_iter()
        .map(|k| {
            Ok((
                k.clone(),
                Image::header(&k.0, k.1, config.max_image_pixels)?,
            ))
        })
        .collect::<Result<_>>()?;
    let header = |k: &FileKey| headers[k]; // every key was read above
    for f in &frames {
        let mask = f.mask.as_ref().map(header);
        check_sizes(&f.frame, &header(&f.image), mask, config.downscale)?;
    }
    // An image far above the others' size is a bomb or a stray file, not a view.
    let mut pixels: Vec<(u64, &Path)> = frames
        .iter()
        .map(|f| {
            let h = header(&f.image);
            ((h.width * h.height) as u64, f.frame.image.as_path())
        })
        .collect();
    pixels.sort_unstable();
    let median = pixels[(pixels.len() - 1) / 2].0;
    if let Some(&(largest, path)) = pixels.last() {
        if largest > MEDIAN_RATIO * median {
            return Err(Error::format(
                path,
                "image size",
                format!("at most {MEDIAN_RATIO} × the median image of the split ({median} pixels)"),
                format!("{largest} pixels"),
            ));
        }
    }
    let mut need: u64 = 0;
    for k in &keys {
        need = need.saturating_add(header(k).decoded_bytes());
    }
    if need > config.max_decoded_bytes {
        let (big, h) = keys
            .iter()
            .map(|k| (k, header(k)))
            .max_by_key(|(_, h)| h.decoded_bytes())
            .expect("at least one frame"); // invariant: frames is never empty
        return Err(Error::format(
            &big.0,
            "decoded size",
            format!(
                "at most {} bytes of decoded images in one load (LoadConfig::max_decoded_bytes)",
                config.max_decoded_bytes
            ),
            format!(
                "{need} bytes for {} files, the largest this one ({} × {}, {} bytes)",
                keys.len(),
                h.width,
                h.height,
                h.decoded_bytes()
            ),
        ));
    }
    let decoded: HashMap<FileKey, Arc<Image>> = keys
        .into_par_iter()
        .map(|k| {
            let image = Image::decode(&k.0, k.1, &header(&k))?.downscale(config.downscale);
            Ok((k, Arc::new(image)))
        })
        .collect::<Result<_>>()?;
    frames
        .into_iter()
        .map(|f| {
            let image = Arc::clone(&decoded[&f.image]);
            let mask = f.mask.as_ref().map(|m| Arc::clone(&decoded[m]));
            let h = header(&f.image);
            make_view(f.frame, (h.width, h.height), image, mask, config.downscale)
        })
        .collect()
}

fn select(frames: Vec<FrameSpec>, subset: Option<&[usize]>) -> Result<Vec<FrameSpec>> {
    let Some(subset) = subset else {
        return Ok(frames);
    };
    if subset.is_empty() {
        return Err(Error::invalid("frames", "at least one index", "[]"));
    }
    let mut slots: Vec<Option<FrameSpec>> = frames.into_iter().map(Some).collect();
    let n = slots.len();
    subset
        .iter()
        .map(|&i| {
            slots.get_mut(i).and_then(Option::take).ok_or_else(|| {
                Error::invalid(
                    "frames",
                    format!("distinct indices below the split's {n} frames"),
                    format!("{subset:?}"),
                )
            })
        })
        .collect()
}

/// Checks a frame's sizes from the headers, before decoding: the image's against the
/// size the layout states, the mask's against the image's, `downscale` against both.
fn check_sizes(
    frame: &FrameSpec,
    image: &Header,
    mask: Option<Header>,
    downscale: usize,
) -> Result<()> {
    let (w, h) = (image.width, image.height);
    if let IntrinsicsSpec::Pinhole {
        size: Some((sw, sh)),
        ..
    } = frame.intrinsics
    {
        if (sw, sh) != (w, h) {
            return Err(Error::format(
                &frame.image,
                "image size",
                format!("{sw} × {sh} (w, h in {})", frame.source.display()),
                format!("{w} × {h}"),
            ));
        }
    }
    if let (Some(m), Some(path)) = (mask, &frame.mask) {
        if (m.width, m.height) != (w, h) {
            return Err(Error::format(
                path,
                "mask size",
                format!("{w} × {h}, the size of {}", frame.image.display()),
                format!("{} × {}", m.width, m.height),
            ));
        }
    }
    if downscale > w.min(h) {
        return Err(Error::invalid(
            "downscale",
            format!("at most the image's smaller side ({})", w.min(h)),
            downscale.to_string(),
        ));
    }
    Ok(())
}

/// The view of one frame from its decoded (and downscaled) image and mask: the camera
/// built from the layout's intrinsics at the original size, scaled by `1/downscale`, and
/// validated.
fn make_view(
    frame: FrameSpec,
    (w0, h0): (usize, usize),
    image: Arc<Image>,
    mask: Option<Arc<Image>>,
    downscale: usize,
) -> Result<View> {
    let s = downscale as f64;
    let (w, h, _) = image.size();
    // The intrinsics the layout states are for the size before downscaling.
    let (w0, h0) = (w0 as f64, h0 as f64);
    let (fx, fy, cx, cy) = match frame.intrinsics {
        IntrinsicsSpec::Fov { angle_x, angle_y } => {
            let fx = 0.5 * w0 / (0.5 * angle_x).tan();
            let fy = angle_y.map_or(fx, |a| 0.5 * h0 / (0.5 * a).tan());
            (fx, fy, 0.5 * w0, 0.5 * h0)
        }
        IntrinsicsSpec::Pinhole { fx, fy, cx, cy, .. } => {
            (fx, fy, cx.unwrap_or(0.5 * w0), cy.unwrap_or(0.5 * h0))
        }
    };
    let k = Intrinsics::new(fx / s, fy / s, cx / s, cy / s, w, h).map_err(|e| {
        Error::format(
            &frame.source,
            format!("{} intrinsics", frame.field),
            "valid pinhole intrinsics",
            e.to_string(),
        )
    })?;
    let camera = Camera::new(k, frame.cam_to_world, frame.convention).map_err(|e| {
        Error::format(
            &frame.source,
            &frame.field,
            "a rigid camera-to-world pose",
            e.to_string(),
        )
    })?;
    View::shared(camera, image, mask, frame.image.display().to_string())
}
