//! What a training run sets up from a dataset: the held-out split to evaluate on, the
//! scene box, and the finest resolution a hash grid needs for the images' pixels.

use super::dataset::{load, Dataset, LoadConfig};
use super::layout::{Bounds, DatasetLayout, Split};
use crate::error::Result;
use std::path::Path;

/// Loads the held-out views of the dataset in `dir` with `config` (whose `split` is
/// replaced): the test split, or the validation split for a Blender layout that has no
/// `transforms_test.json`. Returns the dataset and the split loaded ([`Split::Test`] or
/// [`Split::Val`]). Layouts without split files (nerfstudio, IDR/DTU) hold the same
/// frames out for both (every 8th), and load as [`Split::Test`].
///
/// ```
/// use neural_fields::data::{load_eval, LoadConfig, Split};
/// let (test, split) = load_eval("examples/data/wuson".as_ref(), &LoadConfig::default())?;
/// assert_eq!(split, Split::Test);
/// assert!(!test.views().is_empty());
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// As [`load`]; a test split that exists but fails to load is an error, not a fallback.
pub fn load_eval(dir: &Path, config: &LoadConfig) -> Result<(Dataset, Split)> {
    let layout = match config.layout {
        Some(l) => l,
        None => DatasetLayout::detect(dir)?,
    };
    let split = if layout == DatasetLayout::Blender && !dir.join("transforms_test.json").is_file() {
        Split::Val
    } else {
        Split::Test
    };
    let config = LoadConfig {
        split,
        layout: Some(layout),
        ..config.clone()
    };
    Ok((load(dir, &config)?, split))
}

impl Dataset {
    /// The scene box `[x0, y0, z0, x1, y1, z1]`: the box the layout states (nerfstudio's
    /// `aabb_scale`), the box around the sphere it states (IDR/DTU's unit sphere after
    /// `scale_mat`); for layouts that state none (Blender), the box of the training
    /// silhouettes' visual hull grown by 5 % of its largest side on every side
    /// ([`Dataset::visual_hull`]`(0.05)`, when the views have alpha or masks with some
    /// foreground), else the cube `[−half, half]³`. Without stated bounds the call carves
    /// the hull (host f64, `O(48³ · views)`): call it once per dataset.
    ///
    /// ```
    /// use neural_fields::data::{load, LoadConfig};
    /// let train = load("examples/data/wuson".as_ref(), &LoadConfig::default())?;
    /// // A Blender layout states no bounds and its views have alpha: the hull + 5 %.
    /// assert_eq!(Some(train.scene_box(1.5)), train.visual_hull(0.05)?);
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    #[must_use]
    pub fn scene_box(&self, half: f64) -> [f64; 6] {
        match self.bounds() {
            Some(Bounds::Aabb { min, max }) => [min[0], min[1], min[2], max[0], max[1], max[2]],
            Some(Bounds::Sphere { center: c, radius }) => [
                c[0] - radius,
                c[1] - radius,
                c[2] - radius,
                c[0] + radius,
                c[1] + radius,
                c[2] + radius,
            ],
            None => {
                let cube = [-half, -half, -half, half, half, half];
                // The margin is valid, so the hull's only error cannot occur.
                self.visual_hull(0.05).ok().flatten().unwrap_or(cube)
            }
        }
    }

    /// The fraction of foreground pixels, `#{mask ≥ ½} / #pixels`, over the views that
    /// have a mask (a mask file or an alpha channel); `None` when no view has one. A
    /// training split whose coverage is 0 holds nothing to reconstruct: every pixel is
    /// background, and a field that renders nothing fits it perfectly (check it before
    /// training).
    ///
    /// ```
    /// use neural_fields::camera::{Camera, Convention, Intrinsics};
    /// use neural_fields::data::{Background, Dataset, Image, View};
    /// use neural_fields::glam::DAffine3;
    ///
    /// let cam = Camera::new(Intrinsics::new(2.0, 2.0, 1.0, 1.0, 2, 2)?, DAffine3::IDENTITY, Convention::OpenCv)?;
    /// // RGBA: one opaque pixel of four.
    /// let rgba = vec![9, 9, 9, 255, 9, 9, 9, 0, 9, 9, 9, 0, 9, 9, 9, 0];
    /// let view = View::new(cam, Image::new(2, 2, 4, rgba)?, None, "v".into())?;
    /// let data = Dataset::new(vec![view], Background::Color([1.0; 3]), None)?;
    /// assert_eq!(data.coverage(), Some(0.25));
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    #[must_use]
    pub fn coverage(&self) -> Option<f64> {
        let (mut inside, mut total) = (0usize, 0usize);
        for view in self.views().iter().filter(|v| v.has_mask()) {
            let (w, h, _) = view.image().size();
            for v in 0..h {
                for u in 0..w {
                    inside += usize::from(view.mask_value(u, v).is_some_and(|m| m >= 0.5));
                }
            }
            total += w * h;
        }
        (total > 0).then(|| inside as f64 / total as f64)
    }

    /// The finest resolution of a hash grid for these images: five cells per pixel of
    /// the largest image side (100 px → 500; instant-NGP's 2048 is for 800 px), at least
    /// 16 (the coarsest level of the default grid).
    #[must_use]
    pub fn hash_finest(&self) -> f64 {
        let side = self
            .views()
            .iter()
            .map(|v| {
                let k = v.camera().intrinsics();
                k.width.max(k.height)
            })
            .max()
            .unwrap_or(1);
        ((5 * side) as f64).max(16.0)
    }
}
