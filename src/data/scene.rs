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
    /// `scale_mat`), or, for layouts that state none (Blender), the cube `[−half, half]³`.
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
            None => [-half, -half, -half, half, half, half],
        }
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
