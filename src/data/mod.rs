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
//!
//! # Procedural shape collection
//! A procedural shape collection: categories of parametric shapes built from the crate's
//! analytic signed distances ([`crate::field`]) by CSG, with exact occupancy labels, surface
//! point clouds with normals, voxel grids, optional rendered views and a train / val / test
//! split, written to and read from one documented folder format. It stands in for ShapeNet
//! in the experiments of Occupancy Networks (learning a shape prior across a collection).
//!
//! ## Categories
//! Every shape is a [`Csg`] tree of [`RoundedBox`], [`Capsule`], [`Cylinder`], [`Sphere`]
//! and [`Torus`] parts. Parts join by smooth union ([`CsgOp::SmoothUnion`], blend width
//! `k` of 0.006–0.012 before normalisation), so that the gradient stays defined where they
//! meet; hollows are cut by [`CsgOp::Difference`]. The world's up axis is `+y`
//! (ShapeNet's). Proportions and part counts are drawn from a [`SplitMix64`] stream seeded
//! by the shape's seed ([`generate_shape`]):
//!
//! | [`ShapeCategory`] | parts (each proportion drawn uniformly from a range) |
//! |---|---|
//! | chair | rounded-box seat; four legs (cylinders, capsules — optionally splayed — or square rounded boxes, with optional side stretchers) or a pedestal (column on a disk or a star of 4–5 capsule feet); a back (85 %): a panel or a top rail on 2–4 capsule spindles; armrests on posts (30 % of chairs with a back) |
//! | table | a rectangular rounded-box top or a round cylinder top; 1 leg (a column on a disk or on 3–4 capsule feet), 3 legs on a circle (optionally splayed) or 4 legs (cylinders, capsules or square boxes) with an optional apron and lower shelf |
//! | lamp | a disk or square base; a straight stem or a bent arm (two capsules and a joint); a shade: an open tube (outer minus inner cylinder, with 2–3 spokes to a bulb), a rounded cone-like stack of 3–5 cylinders (optionally hollowed from below), or a globe |
//! | mug | a cylinder hollowed by a second cylinder (wall and bottom thickness drawn), with a torus handle or a D-shaped handle of three capsules |
//! | airplane | a capsule fuselage (with an optional raised tail cone); straight or two-part (cranked) rounded-box wings; a horizontal tail (low or T-tail) and a vertical fin; 0, 2 or 4 capsule engines under the wings |
//!
//! Each shape is then normalised (ONet's convention): its bounding box is centred at the
//! origin and scaled so that its longest side is 1, so the shape lies inside
//! `[−0.5, 0.5]³`. The box is conservative: the union of the parts' boxes, widened by the
//! blend width `k` around each blended group (a chain of smooth unions never falls more
//! than `k` below the smallest of its operands, so it bulges by less than `k`); the
//! shapes' extent along their longest axis is 0.9–1. Blend widths scale with the shape.
//! Over 200 shapes per category, the occupied fraction of the padded cube ranges from
//! 1.6 % (thin airplanes) to 21 % (lamps with a large base and shade).
//!
//! ## What is stored per shape
//! Everything is computed on the CPU in f32 (part of the format: the same seed gives the
//! same bytes), from the tree [`generate_shape`] builds with `Device::Cpu` and
//! `DType::F32`:
//! - **uniform points**: `uniform_points` points uniform in the padded cube
//!   `[−(1 + padding)/2, (1 + padding)/2]³` (ONet: padding 0.1) with their occupancy
//!   `d(p) < 0` (1 inside, 0 outside);
//! - **near-surface points**: for each σ of `near_sigmas` (ONet / Conv. ONet: 0.01 and
//!   0.05), `near_points` surface points (drawn with replacement from the point cloud
//!   below) plus `N(0, σ²)` noise per coordinate, with their occupancy `d(p) < 0`;
//!   group `s` holds rows `s·near_points ..< (s + 1)·near_points`;
//! - **surface point cloud**: `surface_points` points on the zero level set with unit
//!   outward normals `∇d/‖∇d‖`: candidates drawn uniformly inside the voxel cells the
//!   surface may cross (`|d(centre)| <` half the cell diagonal), those within 0.015 of the
//!   surface (so roughly uniform by area) moved by Newton's steps `p ← p − d·∇d/‖∇d‖²`
//!   (at most six), and kept where `|d| < 10⁻⁴`, `‖∇d‖ > 0.5`, the normal is within 25° of
//!   the gradient where the projection started, and the normals a step of 10⁻³ to either
//!   side along the surface agree with it (cosine > 0.98): points on a crease, where the
//!   normal is not defined, are dropped;
//! - **voxels**: `voxel_resolution³` cells over `[−0.5, 0.5]³`; cell `(i, j, k)` has its
//!   centre at `−0.5 + (i + ½, j + ½, k + ½)/R` and is occupied iff the centre's distance
//!   is below half the cell diagonal, `d(centre) < √3/(2R)`. Since `d` is 1-Lipschitz and
//!   never exceeds the true distance, every cell that meets the shape is occupied (the grid
//!   covers the shape; a few cells beside it may be occupied too);
//! - **views** (optional, added later by [`write_shape_views`]): RGB(A) PNG images with
//!   their cameras.
//!
//! The split is by shape and per category: a seeded permutation of each category's shapes
//! puts `round(n·test_fraction)` in test, `round(n·val_fraction)` in val and the rest in
//! train.
//!
//! ## On-disk format (version 1)
//! ```text
//! DIR/manifest.json                        the collection (written last)
//! DIR/shapes/00000/shape.safetensors       the arrays of shape 0
//! DIR/shapes/00000/views/cameras.json      optional rendered views of shape 0 …
//! DIR/shapes/00000/views/000.png           … one PNG per view
//! ```
//! `manifest.json` is an object with `format` (`"neural-fields shape collection"`),
//! `format_version` (1), `seed`, `categories` (names: `chair`, `table`, `lamp`, `mug`,
//! `airplane`), `shapes_per_category`, `uniform_points`, `near_points`, `near_sigmas`,
//! `surface_points`, `voxel_resolution`, `padding`, `split_fractions`
//! (`{"val": …, "test": …}`), `counts` (`{"train", "val", "test", "total"}`), `up`
//! (`"+y"`), `voxel_rule` (words) and `shapes`: one object per shape, in index order, with
//! `index`, `category`, `split` (`train`, `val`, `test`), `seed` (the shape's seed:
//! `generate_shape(category, seed, …)` rebuilds its tree) and `file` (relative to `DIR`).
//! Shapes are numbered category by category, in the order of `categories`.
//!
//! Each `shape.safetensors` is a [safetensors](https://github.com/huggingface/safetensors)
//! file (readable by `candle_core::safetensors::load`, or `safetensors.numpy.load_file` in
//! Python): an 8-byte little-endian header length, a JSON header padded with spaces to a
//! multiple of 8 bytes, then the raw little-endian arrays back to back, in this order:
//!
//! | name | dtype | shape |
//! |---|---|---|
//! | `near_points` | F32 | `[S·near_points, 3]` (S = number of σ) |
//! | `surface_normals` | F32 | `[surface_points, 3]` |
//! | `surface_points` | F32 | `[surface_points, 3]` |
//! | `uniform_points` | F32 | `[uniform_points, 3]` |
//! | `near_occupancy` | U8 | `[S·near_points]` |
//! | `uniform_occupancy` | U8 | `[uniform_points]` |
//! | `voxels` | U8 | `[R, R, R]` (axes x, y, z; 1 occupied) |
//!
//! The header's `__metadata__` holds strings: `format` (`"neural-fields shape"`),
//! `format_version` (`"1"`), `index`, `category` and `seed` (matching the manifest).
//!
//! `views/cameras.json` is an object with `format_version` (1), `shape_index`, `shape_seed`
//! (the loader refuses views left over from another collection) and `views`: one object
//! per view with `file` (relative to the `views/` folder), `width`, `height`, `fx`, `fy`,
//! `cx`, `cy` (pixels), `convention` (`"opencv"` or `"opengl"`, [`Convention`]) and
//! `camera_to_world` (4 rows of 4 numbers, a rigid transform).
//!
//! ## Loading
//! [`load_shape_collection`] reads a folder under the limits of [`ShapeLoadConfig`]: the
//! manifest's counts are checked against the memory budget before any shape file is read,
//! each file's size and every header entry (dtype, shape, offsets) are checked against the
//! manifest before any array is decoded, every path must resolve inside the folder, PNG
//! headers are checked against the budget before decoding, and anything malformed is an
//! [`Error::Format`] naming the file and the field.
//!
//! [`Csg`]: crate::field::Csg
//! [`RoundedBox`]: crate::field::RoundedBox
//! [`Capsule`]: crate::field::Capsule
//! [`Cylinder`]: crate::field::Cylinder
//! [`Sphere`]: crate::field::Sphere
//! [`Torus`]: crate::field::Torus
//! [`CsgOp::SmoothUnion`]: crate::field::CsgOp::SmoothUnion
//! [`CsgOp::Difference`]: crate::field::CsgOp::Difference
//! [`SplitMix64`]: crate::rng::SplitMix64
//! [`Convention`]: crate::camera::Convention
//! [`Error::Format`]: crate::Error::Format
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
mod shapes;

pub use batch::{RayBatch, RaySampler};
pub use dataset::{load, Background, Dataset, LoadConfig, View};
pub use image::Image;
pub use layout::{Bounds, DatasetLayout, Split};
pub use metrics::{psnr, ssim};
pub use output::{colorize_depth, comparison_strip, write_blender, write_png};
pub use scene::load_eval;
pub use shapes::{
    generate_shape, load_shape_collection, write_shape_collection, write_shape_views,
    ShapeCategory, ShapeCollection, ShapeCollectionConfig, ShapeInfo, ShapeLoadConfig, ShapeSample,
    ShapeView,
};
