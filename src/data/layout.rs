//! What every dataset layout shares: the splits, the stated scene bounds, layout
//! detection, the per-frame description a layout reader produces ([`FrameSpec`], turned
//! into views by the loader), and the checked readers of poses and files.

use crate::camera::{orthonormality, Convention};
use crate::error::{Error, Result};
use glam::{DAffine3, DMat3, DVec3};
use std::path::{Path, PathBuf};

/// The region a layout says the scene occupies, in the loaded (normalised) world frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Bounds {
    /// An axis-aligned box.
    Aabb {
        /// Minimum corner.
        min: [f64; 3],
        /// Maximum corner.
        max: [f64; 3],
    },
    /// A sphere (IDR/DTU: the unit sphere after `scale_mat`).
    Sphere {
        /// Centre.
        center: [f64; 3],
        /// Radius.
        radius: f64,
    },
}

/// The largest magnitude of a camera quantity a layout may state: focal lengths and
/// principal points in pixels, image sides, `scale`, `offset`, `aabb_scale` and camera
/// centres in scene units. Real captures stay orders of magnitude below it; beyond it a
/// value is a typo or a hostile file, and rays built from it lose all precision.
pub(crate) const MAX_CAMERA_VALUE: f64 = 1e6;
/// The smallest focal length, in pixels, and the smallest positive scale a layout may
/// state (`scale`, `aabb_scale`, a DTU `scale_mat`).
pub(crate) const MIN_FOCAL: f64 = 1e-3;
pub(crate) const MIN_SCALE: f64 = 1e-6;
/// Fields of view, in radians, lie in `[MIN_ANGLE, π − MIN_ANGLE]`: outside, the focal
/// length is above 10³ image widths or the directions at the image edge exceed 10³.
pub(crate) const MIN_ANGLE: f64 = 1e-3;

/// `x` if it is finite and in `[lo, hi]`, else an [`Error::Format`] naming `path` and
/// `field`, with `what` the quantity in words (“a focal length in pixels”).
pub(crate) fn in_range(
    x: f64,
    lo: f64,
    hi: f64,
    path: &Path,
    field: &str,
    what: &str,
) -> Result<f64> {
    if x.is_finite() && (lo..=hi).contains(&x) {
        Ok(x)
    } else {
        Err(Error::format(
            path,
            field,
            format!("{what} in [{lo:e}, {hi:e}]"),
            format!("{x:e}"),
        ))
    }
}

/// Which frames of a dataset to load.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Split {
    /// Training frames.
    #[default]
    Train,
    /// Validation frames.
    Val,
    /// Test frames.
    Test,
    /// Every frame: the three splits in the order train, val, test where the layout has
    /// split files, else all frames in file order.
    All,
}

impl Split {
    /// The split's name in file names: `train`, `val`, `test`, `all`.
    #[must_use]
    pub(crate) fn name(&self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
            Split::All => "all",
        }
    }

    /// For layouts without split files (nerfstudio's single `transforms.json`, IDR/DTU):
    /// whether frame `i` belongs to the split by the hold-out rule of LLFF and mip-NeRF,
    /// every 8th frame (`i % 8 == 0`) held out for validation and testing.
    pub(crate) fn holds(&self, i: usize) -> bool {
        match self {
            Split::Train => !i.is_multiple_of(8),
            Split::Val | Split::Test => i.is_multiple_of(8),
            Split::All => true,
        }
    }
}

/// A dataset layout on disk. [`load`](super::load) detects it from the files present
/// unless [`LoadConfig::layout`](super::LoadConfig::layout) names it:
/// `transforms_train.json` → Blender, `transforms.json` → nerfstudio, `cameras.npz` or
/// `cameras_sphere.npz` → IDR/DTU; a folder with none of them is an error naming it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum DatasetLayout {
    /// The Blender synthetic layout (NeRF): `transforms_{train,val,test}.json` with
    /// `camera_angle_x` and per-frame `file_path` / `transform_matrix` (OpenGL axes).
    Blender,
    /// The nerfstudio / instant-NGP layout: one `transforms.json` with pinhole intrinsics
    /// (`fl_x, fl_y, cx, cy, w, h`, global or per frame).
    Nerfstudio,
    /// The IDR/DTU layout: `image/`, optional `mask/`, and `cameras.npz` (or
    /// `cameras_sphere.npz`) with `world_mat_i` and `scale_mat_i`.
    Dtu,
}

impl DatasetLayout {
    /// The layout of the dataset in `dir`, from the files present: `transforms_train.json`
    /// → Blender, `transforms.json` → nerfstudio, `cameras.npz` or `cameras_sphere.npz` →
    /// IDR/DTU.
    ///
    /// # Errors
    /// [`Error::Io`] naming `dir` if it is not a directory; [`Error::Format`] naming `dir`
    /// if none of those files is there.
    pub(crate) fn detect(dir: &Path) -> Result<Self> {
        if !dir.is_dir() {
            return Err(Error::Io {
                path: dir.display().to_string(),
                source: std::io::Error::new(std::io::ErrorKind::NotFound, "not a directory"),
            });
        }
        if dir.join("transforms_train.json").is_file() {
            Ok(Self::Blender)
        } else if dir.join("transforms.json").is_file() {
            Ok(Self::Nerfstudio)
        } else if cameras_file(dir).is_some() {
            Ok(Self::Dtu)
        } else {
            Err(Error::format(
                dir,
                "layout",
                "transforms_train.json (Blender), transforms.json (nerfstudio) or cameras.npz (IDR/DTU)",
                "none of them",
            ))
        }
    }
}

/// The cameras file of an IDR/DTU dataset in `dir`: `cameras.npz` (IDR) or
/// `cameras_sphere.npz` (NeuS).
pub(crate) fn cameras_file(dir: &Path) -> Option<PathBuf> {
    ["cameras.npz", "cameras_sphere.npz"]
        .iter()
        .map(|n| dir.join(n))
        .find(|p| p.is_file())
}

/// The intrinsics a layout states for a frame, before the image's size is known.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum IntrinsicsSpec {
    /// Horizontal (and optionally vertical) field of view, principal point at the centre.
    Fov { angle_x: f64, angle_y: Option<f64> },
    /// Focal lengths and principal point in pixels, with the image size if stated.
    Pinhole {
        fx: f64,
        fy: f64,
        cx: Option<f64>,
        cy: Option<f64>,
        size: Option<(usize, usize)>,
    },
}

/// One frame as a layout describes it: where its files are and its camera.
#[derive(Clone, Debug)]
pub(crate) struct FrameSpec {
    pub image: PathBuf,
    pub mask: Option<PathBuf>,
    pub intrinsics: IntrinsicsSpec,
    pub cam_to_world: DAffine3,
    pub convention: Convention,
    /// The file the camera came from, and the field, for error messages.
    pub source: PathBuf,
    pub field: String,
    /// The file that names the image and mask files (the JSON, or the dataset folder for
    /// IDR/DTU's listings), and the fields that name them, for error messages.
    pub listed_in: PathBuf,
    pub image_field: String,
    pub mask_field: String,
}

/// A camera-to-world pose from the rows of a 3×4 or 4×4 matrix, checked: finite, last row
/// `[0, 0, 0, 1]`, rotation part within 1e-3 of orthonormal with determinant +1.
/// Orthonormalised (polar decomposition) where it deviates by more than 1e-6.
pub(crate) fn pose_from_rows(rows: &[[f64; 4]], path: &Path, field: &str) -> Result<DAffine3> {
    let bad = |expected: &str, got: String| Error::format(path, field, expected, got);
    if rows.len() != 3 && rows.len() != 4 {
        return Err(bad("a 3×4 or 4×4 matrix", format!("{} rows", rows.len())));
    }
    if rows.iter().flatten().any(|x| !x.is_finite()) {
        return Err(bad("finite entries", format!("{rows:?}")));
    }
    if rows.len() == 4 {
        let last = rows[3];
        let dev = (0..4)
            .map(|j| (last[j] - if j == 3 { 1.0 } else { 0.0 }).abs())
            .fold(0.0, f64::max);
        if dev > 1e-6 {
            return Err(bad("a last row [0, 0, 0, 1]", format!("{last:?}")));
        }
    }
    let col = |j: usize| DVec3::new(rows[0][j], rows[1][j], rows[2][j]);
    let mut r = DMat3::from_cols(col(0), col(1), col(2));
    let det = r.determinant();
    let dev = orthonormality(&r);
    if det.is_nan() || det <= 0.0 || dev > 1e-3 {
        return Err(bad(
            "a rigid transform (rotation part orthonormal within 1e-3, det +1)",
            format!("max |RᵀR − I| = {dev:.3e}, det R = {det:.6}"),
        ));
    }
    if dev > 1e-6 {
        // Polar decomposition by Newton's iteration R ← (R + R⁻ᵀ)/2, quadratically
        // convergent from this close.
        for _ in 0..8 {
            r = (r + r.inverse().transpose()) * 0.5;
        }
    }
    Ok(DAffine3::from_mat3_translation(r, col(3)))
}

/// Reads a whole file of at most `cap` bytes.
pub(crate) fn read_capped(path: &Path, cap: u64) -> Result<Vec<u8>> {
    use std::io::Read;
    let io = |source| Error::Io {
        path: path.display().to_string(),
        source,
    };
    let file = std::fs::File::open(path).map_err(io)?;
    let mut bytes = Vec::new();
    file.take(cap + 1).read_to_end(&mut bytes).map_err(io)?;
    if bytes.len() as u64 > cap {
        return Err(Error::format(
            path,
            "file size",
            format!("at most {cap} bytes"),
            "a larger file",
        ));
    }
    Ok(bytes)
}

/// The canonical path (symlinks resolved) of the file `path` that the field `field` of
/// `source` names, checked: a regular, non-empty file (not a directory, device, FIFO or
/// socket, nor a `/proc` pseudo-file, which reports a size of 0), and, unless
/// `allow_outside` is set, inside the dataset's canonical `root`. Checked from the
/// metadata, before the file is opened (opening a FIFO would block).
///
/// # Errors
/// [`Error::Io`] naming `path` if it does not exist or cannot be resolved;
/// [`Error::Format`] naming `source` and `field` (with `path`) for a path outside `root` or
/// a file that is not a regular, non-empty file.
pub(crate) fn confine(
    root: &Path,
    path: &Path,
    source: &Path,
    field: &str,
    allow_outside: bool,
) -> Result<PathBuf> {
    let canonical = path.canonicalize().map_err(|source| Error::Io {
        path: path.display().to_string(),
        source,
    })?;
    if !allow_outside && !canonical.starts_with(root) {
        return Err(Error::format(
            source,
            field,
            format!(
                "a file inside the dataset folder {} (LoadConfig::allow_outside_paths, \
                 --allow-outside-paths, to read others)",
                root.display()
            ),
            format!(
                "{}, which resolves to {}",
                path.display(),
                canonical.display()
            ),
        ));
    }
    let meta = std::fs::metadata(&canonical).map_err(|source| Error::Io {
        path: canonical.display().to_string(),
        source,
    })?;
    let got = if meta.is_dir() {
        Some("a directory")
    } else if !meta.is_file() {
        Some("a device, FIFO or socket")
    } else if meta.len() == 0 {
        Some("an empty file (or a pseudo-file of /proc or /sys)")
    } else {
        None
    };
    match got {
        Some(got) => Err(Error::format(
            source,
            field,
            "a regular, non-empty image file",
            format!("{}: {got}", path.display()),
        )),
        None => Ok(canonical),
    }
}
