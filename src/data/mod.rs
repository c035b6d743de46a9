//! Datasets, ray batches, image metrics and pictures: the path from a capture on disk to a
//! training step and back to images a person can look at.
//!
//! # Loading
//! [`load`] reads a dataset folder in one of three layouts ([`DatasetLayout`], detected
//! from the files present):
//!
//! | layout | files | cameras |
//! |---|---|---|
//! | Blender synthetic (NeRF) | `transforms_{train,val,test}.json`, RGBA PNG frames | `camera_angle_x`, per-frame `transform_matrix` (camera-to-world, OpenGL axes) |
//! | nerfstudio / instant-NGP | `transforms.json` | `fl_x, fl_y, cx, cy, w, h` global or per frame; `camera_model`; no distortion; `scale`/`offset` applied to the camera centres; `aabb_scale` → [`Bounds`] |
//! | IDR/DTU | `image/`, `mask/`, `cameras.npz` | `world_mat_i = K·[R|t]`, `scale_mat_i` (the unit sphere) |
//!
//! [`LoadConfig`] picks the split, the background behind transparent pixels, an integer
//! downscale and a subset of frames (sparse views). Layouts without split files hold out
//! every 8th frame for validation and testing ([`Split`]). [`load_eval`] loads the
//! held-out views (test, else validation); [`Dataset::scene_box`] and
//! [`Dataset::hash_finest`] size a scene's box and a hash grid's finest level.
//!
//! # Batches
//! [`RaySampler`] draws seeded batches of random pixels ([`RaySampler::pixels`]) or
//! `k × k` patches ([`RaySampler::patches`]) across all views; whole images are a view's
//! camera's [`Camera::rays`](crate::camera::Camera::rays) (row-major, chunk by chunk with
//! [`Rays::narrow`](crate::camera::Rays::narrow)) and its [`View::rgb`] on
//! [`Background::eval_color`]. A [`RayBatch`] holds the [`Rays`](crate::camera::Rays)
//! with their target colours, backgrounds, masks, view and pixel indices, on the caller's
//! device and dtype.
//!
//! # Metrics and pictures
//! [`psnr`] and [`ssim`] (scikit-image's Gaussian SSIM, to 1e-4) with optional masks;
//! [`write_png`] for RGB, opacity and the colour maps [`colorize_depth`] and
//! [`comparison_strip`] (normals `n` show as the colours `(n + 1) / 2`,
//! `n.affine(0.5, 0.5)`); [`write_blender`] turns any [`Dataset`] (e.g. renders of an
//! analytic scene) into a Blender-layout dataset.
//!
//! ```
//! use candle_core::{DType, Device};
//! use neural_fields::data::{load, LoadConfig, RaySampler};
//!
//! let data = load("examples/data/wuson".as_ref(), &LoadConfig::default())?;
//! let mut sampler = RaySampler::new(&data, 0, &Device::Cpu, DType::F32)?;
//! let batch = sampler.pixels(4096)?;
//! // render batch.rays, composite on batch.backgrounds, compare with batch.colors …
//! # Ok::<(), neural_fields::Error>(())
//! ```

mod batch;
mod blender;
mod dataset;
mod dtu;
mod hull;
mod image;
mod layout;
mod metrics;
mod nerfstudio;
mod output;
mod scene;

pub use batch::{RayBatch, RaySampler};
pub use dataset::{load, Background, Dataset, LoadConfig, View};
pub use image::Image;
pub use layout::{Bounds, DatasetLayout, Split};
pub use metrics::{psnr, ssim};
pub use output::{colorize_depth, comparison_strip, write_blender, write_png};
pub use scene::load_eval;
