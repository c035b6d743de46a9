//! The procedural shape collection: five parametric shape families built by CSG from the
//! analytic fields, their samples (occupancy labels, surface points with normals, voxels),
//! the split, and the folder format with its writer and hostile-input-proof loader. The
//! families, the sampling and the format are documented in the [`data`](super) module's
//! docs, section "Procedural shape collection", and in `docs/shape_collection.md`.

use super::image::Image;
use super::layout::{confine, in_range, pose_from_rows, read_capped, Split, MAX_CAMERA_VALUE};
use super::output::{encode_png, write_atomic};
use crate::camera::{Camera, Convention, Intrinsics};
use crate::error::{check_dtype, Error, Result};
use crate::field::{Capsule, Csg, CsgOp, Cylinder, RoundedBox, SignedDistance, Sphere, Torus};
use crate::limits::check_bytes;
use crate::rng::SplitMix64;
use candle_core::{DType, Device, Tensor};
use rayon::prelude::*;
use serde_json::{json, Map, Value};
use std::f64::consts::TAU;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The `format` string of `manifest.json`.
const FORMAT: &str = "neural-fields shape collection";
/// The `format` metadata of each shape file.
const SHAPE_FORMAT: &str = "neural-fields shape";
/// The format version this code writes and reads.
const FORMAT_VERSION: u64 = 1;
/// The largest `manifest.json` and `cameras.json` the loader reads.
const MAX_JSON_BYTES: u64 = 64 << 20;
/// The largest safetensors header the loader reads.
const MAX_HEADER_BYTES: u64 = 64 << 10;
/// The most shapes a collection may hold.
const MAX_SHAPES: usize = 1 << 20;
/// Points evaluated per tensor batch (bounds the memory of one evaluation).
const CHUNK: usize = 1 << 15;
/// Newton steps that move a candidate onto the surface.
const NEWTON_STEPS: usize = 6;
/// The half-width of the band around the surface from which surface points are
/// projected.
const SURFACE_BAND: f32 = 0.015;
/// The smallest cosine between a kept surface point's normal and the gradient where its
/// projection started.
const SAME_FACE: f32 = 0.9;
/// The step along the surface at which a surface point's normal is probed.
const TANGENT_STEP: f32 = 1e-3;
/// The smallest cosine between a surface point's normal and the normals a tangent step
/// to either side.
const STABLE_NORMAL: f32 = 0.98;
/// The largest `|d|` of a kept surface point.
const SURFACE_TOLERANCE: f32 = 1e-4;

/// A category of procedural shapes, each a parametric family (see the
/// [module docs] for the parts of each).
///
/// [module docs]: crate::data#procedural-shape-collection
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum ShapeCategory {
    /// Seat, legs or pedestal, optional back and armrests.
    Chair,
    /// Top with 1, 3 or 4 legs, optional apron and shelf.
    Table,
    /// Base, stem or bent arm, shade (tube, cone-like stack or globe).
    Lamp,
    /// Hollow cylinder with a torus or D-shaped handle.
    Mug,
    /// Fuselage, wings, tail and fin, 0–4 engines.
    Airplane,
}

impl ShapeCategory {
    /// Every category, in the order of the default collection.
    pub const ALL: [ShapeCategory; 5] = [
        ShapeCategory::Chair,
        ShapeCategory::Table,
        ShapeCategory::Lamp,
        ShapeCategory::Mug,
        ShapeCategory::Airplane,
    ];

    /// The name in files: `chair`, `table`, `lamp`, `mug`, `airplane`.
    fn name(self) -> &'static str {
        match self {
            ShapeCategory::Chair => "chair",
            ShapeCategory::Table => "table",
            ShapeCategory::Lamp => "lamp",
            ShapeCategory::Mug => "mug",
            ShapeCategory::Airplane => "airplane",
        }
    }

    fn parse(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|c| c.name() == name)
    }

    /// A fixed code per category, mixed into the shapes' seeds (so that a shape's seed
    /// does not depend on the order of the categories in a configuration).
    fn code(self) -> u64 {
        match self {
            ShapeCategory::Chair => 1,
            ShapeCategory::Table => 2,
            ShapeCategory::Lamp => 3,
            ShapeCategory::Mug => 4,
            ShapeCategory::Airplane => 5,
        }
    }
}

impl std::fmt::Display for ShapeCategory {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// What [`write_shape_collection`] generates.
#[derive(Clone, Debug, PartialEq)]
pub struct ShapeCollectionConfig {
    /// The collection's seed: shapes, samples and split follow from it.
    pub seed: u64,
    /// The categories, each at most once, in the order shapes are numbered.
    pub categories: Vec<ShapeCategory>,
    /// Shapes per category (≥ 1).
    pub shapes_per_category: usize,
    /// Uniform points per shape in the padded cube.
    pub uniform_points: usize,
    /// Near-surface points per shape and per σ of `near_sigmas`.
    pub near_points: usize,
    /// The standard deviations of the near-surface noise (each in `(0, 1]`).
    pub near_sigmas: Vec<f64>,
    /// Surface points (with normals) per shape; ≥ 1 when `near_points > 0`.
    pub surface_points: usize,
    /// Voxels per side `R` of the grid over `[−0.5, 0.5]³` (≥ 1).
    pub voxel_resolution: usize,
    /// The padding of the cube the uniform points fill: `[−(1 + p)/2, (1 + p)/2]³`, in
    /// `[0, 1]`.
    pub padding: f64,
    /// The fraction of each category's shapes in the validation split.
    pub val_fraction: f64,
    /// The fraction of each category's shapes in the test split (`val + test ≤ 1`).
    pub test_fraction: f64,
}

impl Default for ShapeCollectionConfig {
    /// Seed 0, the five categories × 20 shapes, 10 000 uniform points, 5 000 near-surface
    /// points at σ = 0.01 and 5 000 at σ = 0.05, 10 000 surface points, 32³ voxels,
    /// padding 0.1, 10 % val and 20 % test.
    fn default() -> Self {
        Self {
            seed: 0,
            categories: ShapeCategory::ALL.to_vec(),
            shapes_per_category: 20,
            uniform_points: 10_000,
            near_points: 5_000,
            near_sigmas: vec![0.01, 0.05],
            surface_points: 10_000,
            voxel_resolution: 32,
            padding: 0.1,
            val_fraction: 0.1,
            test_fraction: 0.2,
        }
    }
}

impl ShapeCollectionConfig {
    /// Checks every field; errors name the field as `config.<field>`.
    fn validate(&self) -> Result<()> {
        if self.categories.is_empty() {
            return Err(Error::invalid(
                "config.categories",
                "at least one category",
                "none",
            ));
        }
        for (i, c) in self.categories.iter().enumerate() {
            if self.categories[..i].contains(c) {
                return Err(Error::invalid(
                    "config.categories",
                    "each category at most once",
                    format!("{c} twice"),
                ));
            }
        }
        if self.shapes_per_category == 0 {
            return Err(Error::invalid(
                "config.shapes_per_category",
                "at least 1",
                "0",
            ));
        }
        let total = self.categories.len().checked_mul(self.shapes_per_category);
        if total.is_none_or(|t| t > MAX_SHAPES) {
            return Err(Error::invalid(
                "config.shapes_per_category",
                format!("at most {MAX_SHAPES} shapes in all"),
                format!(
                    "{} categories × {}",
                    self.categories.len(),
                    self.shapes_per_category
                ),
            ));
        }
        check_bytes("config.uniform_points", &[self.uniform_points, 3], 4)?;
        check_bytes(
            "config.near_points",
            &[self.near_points, self.near_sigmas.len(), 3],
            4,
        )?;
        check_bytes("config.surface_points", &[self.surface_points, 6], 4)?;
        if self.voxel_resolution == 0 {
            return Err(Error::invalid("config.voxel_resolution", "at least 1", "0"));
        }
        let r = self.voxel_resolution;
        check_bytes("config.voxel_resolution", &[r, r, r, 16], 1)?;
        if self.near_points > 0 {
            if self.near_sigmas.is_empty() {
                return Err(Error::invalid(
                    "config.near_sigmas",
                    "at least one σ when near_points > 0",
                    "none",
                ));
            }
            if self.surface_points == 0 {
                return Err(Error::invalid(
                    "config.surface_points",
                    "at least 1 when near_points > 0 (near points are drawn from the surface points)",
                    "0",
                ));
            }
        }
        for &s in &self.near_sigmas {
            if !(s > 0.0 && s <= 1.0) {
                return Err(Error::invalid(
                    "config.near_sigmas",
                    "standard deviations in (0, 1]",
                    format!("{s}"),
                ));
            }
        }
        if !(0.0..=1.0).contains(&self.padding) {
            return Err(Error::invalid(
                "config.padding",
                "a padding in [0, 1]",
                format!("{}", self.padding),
            ));
        }
        for (arg, f) in [
            ("config.val_fraction", self.val_fraction),
            ("config.test_fraction", self.test_fraction),
        ] {
            if !(0.0..=1.0).contains(&f) {
                return Err(Error::invalid(arg, "a fraction in [0, 1]", format!("{f}")));
            }
        }
        if self.val_fraction + self.test_fraction > 1.0 {
            return Err(Error::invalid(
                "config.test_fraction",
                "val_fraction + test_fraction ≤ 1",
                format!("{} + {}", self.val_fraction, self.test_fraction),
            ));
        }
        Ok(())
    }

    /// The bytes of one shape's arrays: `[(name, dtype, shape)]` in file order.
    fn arrays(&self) -> Vec<(&'static str, &'static str, Vec<usize>)> {
        let near = self.near_points * self.near_sigmas.len();
        let (nu, ns, r) = (
            self.uniform_points,
            self.surface_points,
            self.voxel_resolution,
        );
        vec![
            ("near_points", "F32", vec![near, 3]),
            ("surface_normals", "F32", vec![ns, 3]),
            ("surface_points", "F32", vec![ns, 3]),
            ("uniform_points", "F32", vec![nu, 3]),
            ("near_occupancy", "U8", vec![near]),
            ("uniform_occupancy", "U8", vec![nu]),
            ("voxels", "U8", vec![r, r, r]),
        ]
    }

    /// The bytes of one shape's arrays (the data section of its file).
    fn shape_bytes(&self) -> Option<u64> {
        self.arrays()
            .iter()
            .try_fold(0u64, |acc, (_, dtype, shape)| {
                let size = if *dtype == "F32" { 4 } else { 1 };
                let n = shape
                    .iter()
                    .try_fold(size, |a: u64, &d| a.checked_mul(d as u64))?;
                acc.checked_add(n)
            })
    }
}

/// What [`load_shape_collection`] reads, and the limits it reads under.
#[derive(Clone, Debug, PartialEq)]
pub struct ShapeLoadConfig {
    /// The shapes of this split ([`Split::All`]: every shape).
    pub split: Split,
    /// Whether to read the shapes' rendered views (where a shape has them).
    pub views: bool,
    /// The most bytes of arrays and decoded images one load may hold, checked before
    /// reading (arrays, from the manifest's counts) and before decoding (images, from
    /// their headers).
    pub max_bytes: u64,
    /// The most pixels of one view's image.
    pub max_image_pixels: u64,
    /// The most views of one shape.
    pub max_views: usize,
}

impl Default for ShapeLoadConfig {
    /// Every shape with its views, at most 4 GiB, images of at most 2²⁴ pixels, at most
    /// 1024 views per shape.
    fn default() -> Self {
        Self {
            split: Split::All,
            views: true,
            max_bytes: 4 << 30,
            max_image_pixels: 1 << 24,
            max_views: 1024,
        }
    }
}

/// One shape of a collection, as the manifest lists it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ShapeInfo {
    /// The shape's number in the collection (category-major).
    pub index: usize,
    /// Its category.
    pub category: ShapeCategory,
    /// Its split: [`Split::Train`], [`Split::Val`] or [`Split::Test`].
    pub split: Split,
    /// Its seed: `generate_shape(category, seed, …)` rebuilds its tree.
    pub seed: u64,
}

/// One rendered view of a shape: the camera and its 8-bit RGB (or RGBA) image, `[H, W, C]`
/// row-major bytes of the camera's size.
#[derive(Clone, Debug)]
pub struct ShapeView {
    /// The camera.
    pub camera: Camera,
    /// The image.
    pub image: Image,
}

/// One loaded shape: host arrays exactly as stored (f32 points, u8 labels), row-major.
#[derive(Clone, Debug)]
pub struct ShapeSample {
    /// Index, category, split and seed.
    pub info: ShapeInfo,
    /// `[uniform_points, 3]` points in the padded cube.
    pub uniform_points: Vec<f32>,
    /// `[uniform_points]` occupancy (1 inside).
    pub uniform_occupancy: Vec<u8>,
    /// `[S·near_points, 3]` near-surface points, grouped by σ.
    pub near_points: Vec<f32>,
    /// `[S·near_points]` occupancy (1 inside).
    pub near_occupancy: Vec<u8>,
    /// `[surface_points, 3]` points on the surface.
    pub surface_points: Vec<f32>,
    /// `[surface_points, 3]` unit outward normals.
    pub surface_normals: Vec<f32>,
    /// `[R, R, R]` voxel occupancy, axes x, y, z (1 occupied).
    pub voxels: Vec<u8>,
    /// The rendered views, empty where the shape has none (or views were not asked for).
    pub views: Vec<ShapeView>,
}

/// A loaded collection: its configuration (from the manifest) and the shapes asked for.
#[derive(Clone, Debug)]
pub struct ShapeCollection {
    /// The configuration that generated it.
    pub config: ShapeCollectionConfig,
    /// The loaded shapes, in index order.
    pub shapes: Vec<ShapeSample>,
}

// ---------------------------------------------------------------------------------------
// Shapes as host-side trees of parts.

type Vec3 = [f64; 3];

/// A primitive with its parameters on the host.
#[derive(Clone, Debug)]
enum Part {
    Sphere {
        c: Vec3,
        r: f64,
    },
    RoundedBox {
        c: Vec3,
        h: Vec3,
        r: f64,
    },
    Capsule {
        a: Vec3,
        b: Vec3,
        r: f64,
    },
    Cylinder {
        a: Vec3,
        b: Vec3,
        r: f64,
    },
    /// Axis `z` (the ring lies in a plane `z = c.z`).
    Torus {
        c: Vec3,
        major: f64,
        minor: f64,
    },
}

#[derive(Clone, Debug)]
enum Node {
    Part(Part),
    /// The first operand with the second cut away.
    Difference(Box<Node>, Box<Node>),
    /// The smooth union of `first` and `rest` with blend width `k`, folded left to right
    /// (`smin(smin(first, rest₀), rest₁)…`).
    Blend {
        k: f64,
        first: Box<Node>,
        rest: Vec<Node>,
    },
}

fn add(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

fn scaled(a: Vec3, s: f64, t: Vec3) -> Vec3 {
    [a[0] * s + t[0], a[1] * s + t[1], a[2] * s + t[2]]
}

impl Part {
    /// The part's axis-aligned bounding box `(min, max)`.
    fn bounds(&self) -> (Vec3, Vec3) {
        let grow = |c: Vec3, e: Vec3| ([c[0] - e[0], c[1] - e[1], c[2] - e[2]], add(c, e));
        match *self {
            Part::Sphere { c, r } => grow(c, [r; 3]),
            Part::RoundedBox { c, h, .. } => grow(c, h),
            Part::Capsule { a, b, r } => segment_bounds(a, b, [r; 3]),
            Part::Cylinder { a, b, r } => {
                let d = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
                let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-300);
                let e = d.map(|x| r * (1.0 - (x / len).powi(2)).max(0.0).sqrt());
                segment_bounds(a, b, e)
            }
            Part::Torus { c, major, minor } => grow(c, [major + minor, major + minor, minor]),
        }
    }

    /// The part moved by `p ↦ s·p + t`.
    fn transformed(&self, s: f64, t: Vec3) -> Part {
        match *self {
            Part::Sphere { c, r } => Part::Sphere {
                c: scaled(c, s, t),
                r: r * s,
            },
            Part::RoundedBox { c, h, r } => Part::RoundedBox {
                c: scaled(c, s, t),
                h: h.map(|x| x * s),
                r: r * s,
            },
            Part::Capsule { a, b, r } => Part::Capsule {
                a: scaled(a, s, t),
                b: scaled(b, s, t),
                r: r * s,
            },
            Part::Cylinder { a, b, r } => Part::Cylinder {
                a: scaled(a, s, t),
                b: scaled(b, s, t),
                r: r * s,
            },
            Part::Torus { c, major, minor } => Part::Torus {
                c: scaled(c, s, t),
                major: major * s,
                minor: minor * s,
            },
        }
    }

    fn build(
        &self,
        device: &Device,
        dtype: DType,
    ) -> Result<Arc<dyn SignedDistance + Send + Sync>> {
        Ok(match *self {
            Part::Sphere { c, r } => Arc::new(Sphere::new(c, r, device, dtype)?),
            Part::RoundedBox { c, h, r } => Arc::new(RoundedBox::new(c, h, r, device, dtype)?),
            Part::Capsule { a, b, r } => Arc::new(Capsule::new(a, b, r, device, dtype)?),
            Part::Cylinder { a, b, r } => Arc::new(Cylinder::new(a, b, r, device, dtype)?),
            Part::Torus { c, major, minor } => {
                Arc::new(Torus::new(c, major, minor, device, dtype)?)
            }
        })
    }
}

fn segment_bounds(a: Vec3, b: Vec3, e: Vec3) -> (Vec3, Vec3) {
    (
        std::array::from_fn(|i| a[i].min(b[i]) - e[i]),
        std::array::from_fn(|i| a[i].max(b[i]) + e[i]),
    )
}

impl Node {
    /// A bounding box `B` of the node's shape such that, outside `B`, the node's distance
    /// is at least the distance to `B` (so nodes nest). Parts: their exact boxes (their
    /// SDFs are exact). A difference lies inside its first operand. A blend of operands
    /// `dᵢ` with width `k` stays above `minᵢ dᵢ − k`: `smin` is increasing in both
    /// arguments, so after `n` folds the deficit below the minimum obeys
    /// `Dₙ₊₁ ≤ Dₙ + (k − Dₙ)²/(4k) < k`; its box is the union of the operands' boxes
    /// widened by `k` on every side.
    fn bounds(&self) -> (Vec3, Vec3) {
        match self {
            Node::Part(p) => p.bounds(),
            Node::Difference(a, _) => a.bounds(),
            Node::Blend { k, first, rest } => {
                let (mut lo, mut hi) = first.bounds();
                for n in rest {
                    let (l, h) = n.bounds();
                    lo = std::array::from_fn(|i| lo[i].min(l[i]));
                    hi = std::array::from_fn(|i| hi[i].max(h[i]));
                }
                (lo.map(|x| x - k), hi.map(|x| x + k))
            }
        }
    }

    fn transformed(&self, s: f64, t: Vec3) -> Node {
        match self {
            Node::Part(p) => Node::Part(p.transformed(s, t)),
            Node::Difference(a, b) => {
                Node::Difference(Box::new(a.transformed(s, t)), Box::new(b.transformed(s, t)))
            }
            Node::Blend { k, first, rest } => Node::Blend {
                k: k * s,
                first: Box::new(first.transformed(s, t)),
                rest: rest.iter().map(|n| n.transformed(s, t)).collect(),
            },
        }
    }

    /// Centred at the origin with the longest side of its bounding box 1.
    fn normalised(&self) -> Node {
        let (lo, hi) = self.bounds();
        let side = (0..3).map(|i| hi[i] - lo[i]).fold(0.0, f64::max);
        let s = 1.0 / side;
        let t = std::array::from_fn(|i| -0.5 * (lo[i] + hi[i]) * s);
        self.transformed(s, t)
    }

    fn build(
        &self,
        device: &Device,
        dtype: DType,
    ) -> Result<Arc<dyn SignedDistance + Send + Sync>> {
        match self {
            Node::Part(p) => p.build(device, dtype),
            _ => Ok(Arc::new(self.build_csg(device, dtype)?)),
        }
    }

    fn build_csg(&self, device: &Device, dtype: DType) -> Result<Csg> {
        match self {
            // Every family's root is a blend or a difference; a lone part (or a blend of
            // one) is its union with itself.
            Node::Part(p) => {
                let a = p.build(device, dtype)?;
                Ok(Csg {
                    op: CsgOp::Union,
                    a: a.clone(),
                    b: a,
                })
            }
            Node::Difference(a, b) => Ok(Csg {
                op: CsgOp::Difference,
                a: a.build(device, dtype)?,
                b: b.build(device, dtype)?,
            }),
            Node::Blend { k, first, rest } => {
                let Some((last, init)) = rest.split_last() else {
                    return first.build_csg(device, dtype);
                };
                let a = if init.is_empty() {
                    first.build(device, dtype)?
                } else {
                    let head = Node::Blend {
                        k: *k,
                        first: first.clone(),
                        rest: init.to_vec(),
                    };
                    Arc::new(head.build_csg(device, dtype)?)
                };
                Ok(Csg {
                    op: CsgOp::SmoothUnion { k: *k },
                    a,
                    b: last.build(device, dtype)?,
                })
            }
        }
    }
}

fn sphere(c: Vec3, r: f64) -> Node {
    Node::Part(Part::Sphere { c, r })
}

/// A rounded box whose rounding radius is kept within `(0, 0.95·minᵢ hᵢ]`.
fn rbox(c: Vec3, h: Vec3, r: f64) -> Node {
    let smallest = h.iter().copied().fold(f64::INFINITY, f64::min);
    Node::Part(Part::RoundedBox {
        c,
        h,
        r: r.clamp(1e-3 * smallest, 0.95 * smallest),
    })
}

fn capsule(a: Vec3, b: Vec3, r: f64) -> Node {
    Node::Part(Part::Capsule { a, b, r })
}

fn cylinder(a: Vec3, b: Vec3, r: f64) -> Node {
    Node::Part(Part::Cylinder { a, b, r })
}

fn torus(c: Vec3, major: f64, minor: f64) -> Node {
    Node::Part(Part::Torus { c, major, minor })
}

fn difference(a: Node, b: Node) -> Node {
    Node::Difference(Box::new(a), Box::new(b))
}

/// The smooth union of `first` and `rest` with blend width `k`, left to right.
fn smooth(k: f64, first: Node, rest: Vec<Node>) -> Node {
    Node::Blend {
        k,
        first: Box::new(first),
        rest,
    }
}

/// Draws from a shape's stream.
struct Draw(SplitMix64);

impl Draw {
    /// Uniform in `[lo, hi)`.
    fn u(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.0.uniform()
    }
    /// Uniform in `0..n`.
    fn pick(&mut self, n: usize) -> usize {
        self.0.below(n as u64) as usize
    }
    /// True with probability `p`.
    fn coin(&mut self, p: f64) -> bool {
        self.0.uniform() < p
    }
}

fn chair(r: &mut Draw) -> Node {
    let k = r.u(0.006, 0.012);
    let w = r.u(0.45, 0.60);
    let depth = r.u(0.42, 0.58);
    let t = r.u(0.06, 0.11);
    let hs = r.u(0.38, 0.50); // the top of the seat
    let seat_mid = hs - t / 2.0;
    let seat = rbox(
        [0.0, seat_mid, 0.0],
        [w / 2.0, t / 2.0, depth / 2.0],
        r.u(0.005, 0.02),
    );
    let mut parts = Vec::new();
    if r.pick(4) == 0 {
        // A pedestal: a column on a disk or on a star of feet.
        let cr = r.u(0.04, 0.07);
        let base = r.u(0.04, 0.07);
        parts.push(cylinder([0.0, base * 0.5, 0.0], [0.0, seat_mid, 0.0], cr));
        if r.coin(0.5) {
            parts.push(cylinder([0.0, 0.0, 0.0], [0.0, base, 0.0], r.u(0.18, 0.28)));
        } else {
            let n = 4 + r.pick(2);
            let (len, fr, phase) = (r.u(0.2, 0.3), r.u(0.02, 0.035), r.u(0.0, TAU));
            for i in 0..n {
                let a = phase + TAU * i as f64 / n as f64;
                parts.push(capsule(
                    [0.0, fr, 0.0],
                    [len * a.cos(), fr, len * a.sin()],
                    fr,
                ));
            }
        }
    } else {
        let lr = r.u(0.025, 0.045);
        let inset = lr + r.u(0.005, 0.04);
        let kind = r.pick(3);
        let splay = if kind < 2 && r.coin(0.4) {
            r.u(0.01, 0.05)
        } else {
            0.0
        };
        let (x, z) = (w / 2.0 - inset, depth / 2.0 - inset);
        for (sx, sz) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
            let top = [sx * x, seat_mid, sz * z];
            let foot = [sx * (x + splay), 0.0, sz * (z + splay)];
            parts.push(match kind {
                0 => cylinder(foot, top, lr),
                1 => capsule([foot[0], lr, foot[2]], top, lr),
                _ => rbox(
                    [sx * x, seat_mid / 2.0, sz * z],
                    [lr, seat_mid / 2.0, lr],
                    lr * 0.3,
                ),
            });
        }
        if splay == 0.0 && r.coin(0.3) {
            let y = r.u(0.08, 0.2);
            for sx in [-1.0, 1.0] {
                parts.push(capsule([sx * x, y, -z], [sx * x, y, z], lr * 0.6));
            }
        }
    }
    if r.coin(0.85) {
        let hb = r.u(0.28, 0.5);
        let tb = r.u(0.045, 0.08);
        let bw = w * r.u(0.8, 1.0);
        let zb = -depth / 2.0 + tb / 2.0;
        if r.coin(0.6) {
            // A panel from the seat's bottom to hb above its top.
            parts.push(rbox(
                [0.0, hs + (hb - t) / 2.0, zb],
                [bw / 2.0, (hb + t) / 2.0, tb / 2.0],
                r.u(0.005, tb / 2.0),
            ));
        } else {
            let rail = r.u(0.08, 0.14);
            let rail_y = hs + hb - rail / 2.0;
            parts.push(rbox(
                [0.0, rail_y, zb],
                [bw / 2.0, rail / 2.0, tb / 2.0],
                r.u(0.005, tb / 2.0),
            ));
            let n = 2 + r.pick(3);
            let sr = r.u(0.02, 0.03);
            for i in 0..n {
                let x = -bw / 2.0 + sr + (bw - 2.0 * sr) * i as f64 / (n - 1) as f64;
                parts.push(capsule([x, seat_mid, zb], [x, rail_y, zb], sr));
            }
        }
        if r.coin(0.3) {
            let (ha, aw, at) = (r.u(0.18, 0.26), r.u(0.04, 0.07), r.u(0.025, 0.04));
            let post = r.u(0.012, 0.02);
            for sx in [-1.0, 1.0] {
                let x = sx * (w / 2.0 - aw / 2.0);
                parts.push(rbox(
                    [x, hs + ha, 0.0],
                    [aw / 2.0, at / 2.0, depth * 0.45],
                    at * 0.4,
                ));
                parts.push(capsule(
                    [x, seat_mid, depth * 0.37],
                    [x, hs + ha, depth * 0.37],
                    post,
                ));
            }
        }
    }
    smooth(k, seat, parts)
}

fn table(r: &mut Draw) -> Node {
    let k = r.u(0.006, 0.012);
    let ht = r.u(0.55, 0.8);
    let tt = r.u(0.05, 0.09);
    let round = r.coin(0.35);
    let (top, ax, az) = if round {
        let rad = r.u(0.35, 0.6);
        (cylinder([0.0, ht - tt, 0.0], [0.0, ht, 0.0], rad), rad, rad)
    } else {
        let w = r.u(0.8, 1.2);
        let d = w * r.u(0.5, 1.0);
        (
            rbox(
                [0.0, ht - tt / 2.0, 0.0],
                [w / 2.0, tt / 2.0, d / 2.0],
                r.u(0.005, 0.03),
            ),
            w / 2.0,
            d / 2.0,
        )
    };
    let under = ht - tt / 2.0;
    let mut parts = Vec::new();
    match [1, 3, 4][r.pick(3)] {
        1 => {
            let cr = r.u(0.05, 0.1);
            let by = r.u(0.03, 0.06);
            parts.push(cylinder([0.0, by / 2.0, 0.0], [0.0, under, 0.0], cr));
            let reach = ax.min(az) * r.u(0.45, 0.7);
            if r.coin(0.5) {
                parts.push(cylinder([0.0, 0.0, 0.0], [0.0, by, 0.0], reach));
            } else {
                let n = 3 + r.pick(2);
                let (fr, phase) = (r.u(0.025, 0.04), r.u(0.0, TAU));
                for i in 0..n {
                    let a = phase + TAU * i as f64 / n as f64;
                    parts.push(capsule(
                        [0.0, fr, 0.0],
                        [reach * a.cos(), fr, reach * a.sin()],
                        fr,
                    ));
                }
            }
        }
        3 => {
            let lr = r.u(0.025, 0.05);
            let (phase, rho, splay) = (r.u(0.0, TAU), r.u(0.55, 0.8), r.u(0.0, 0.2));
            let capsules = r.coin(0.5);
            for i in 0..3 {
                let a = phase + TAU * i as f64 / 3.0;
                let (x, z) = (rho * ax * a.cos(), rho * az * a.sin());
                let foot = [x * (1.0 + splay), 0.0, z * (1.0 + splay)];
                parts.push(if capsules {
                    capsule([foot[0], lr, foot[2]], [x, under, z], lr)
                } else {
                    cylinder(foot, [x, under, z], lr)
                });
            }
        }
        _ => {
            let lr = r.u(0.025, 0.05);
            let (x, z) = if round {
                let rho = 0.7 * ax * std::f64::consts::FRAC_1_SQRT_2;
                (rho, rho)
            } else {
                let inset = lr + r.u(0.02, 0.08);
                (ax - inset, az - inset)
            };
            let kind = r.pick(3);
            for (sx, sz) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
                let (lx, lz) = (sx * x, sz * z);
                parts.push(match kind {
                    0 => cylinder([lx, 0.0, lz], [lx, under, lz], lr),
                    1 => capsule([lx, lr, lz], [lx, under, lz], lr),
                    _ => rbox([lx, under / 2.0, lz], [lr, under / 2.0, lr], lr * 0.3),
                });
            }
            if !round && r.coin(0.4) {
                let (ah, at) = (r.u(0.05, 0.1), 0.02);
                let y = ht - tt - ah / 2.0 + 0.005;
                for s in [-1.0, 1.0] {
                    parts.push(rbox([0.0, y, s * z], [x, ah / 2.0, at / 2.0], 0.005));
                    parts.push(rbox([s * x, y, 0.0], [at / 2.0, ah / 2.0, z], 0.005));
                }
            }
            if r.coin(0.25) {
                parts.push(rbox(
                    [0.0, r.u(0.12, 0.25), 0.0],
                    [x + lr * 0.5, 0.015, z + lr * 0.5],
                    0.01,
                ));
            }
        }
    }
    smooth(k, top, parts)
}

fn lamp(r: &mut Draw) -> Node {
    let k = r.u(0.006, 0.012);
    let (tb, rb) = (r.u(0.05, 0.1), r.u(0.16, 0.28));
    let base = if r.coin(0.6) {
        cylinder([0.0, 0.0, 0.0], [0.0, tb, 0.0], rb)
    } else {
        rbox(
            [0.0, tb / 2.0, 0.0],
            [rb * 0.85, tb / 2.0, rb * 0.85],
            r.u(0.005, tb / 2.0),
        )
    };
    let (rs, hs) = (r.u(0.025, 0.045), r.u(0.35, 0.7));
    let mut parts = Vec::new();
    let top = if r.coin(0.65) {
        parts.push(capsule([0.0, tb / 2.0, 0.0], [0.0, hs, 0.0], rs));
        [0.0, hs, 0.0]
    } else {
        let elbow = [r.u(0.05, 0.25), hs * r.u(0.5, 0.7), 0.0];
        let top = [elbow[0] * r.u(-0.5, 0.5), hs, r.u(-0.1, 0.1)];
        parts.push(capsule([0.0, tb / 2.0, 0.0], elbow, rs));
        parts.push(capsule(elbow, top, rs));
        parts.push(sphere(elbow, rs * 1.4));
        top
    };
    let [tx, ty, tz] = top;
    match r.pick(3) {
        0 => {
            // An open tube: outer minus inner cylinder, spokes to a bulb.
            let (ro, h, wall) = (r.u(0.16, 0.28), r.u(0.18, 0.35), r.u(0.03, 0.05));
            let outer = cylinder([tx, ty - 0.6 * h, tz], [tx, ty + 0.4 * h, tz], ro);
            let inner = cylinder(
                [tx, ty - 0.6 * h - 0.05, tz],
                [tx, ty + 0.4 * h + 0.05, tz],
                ro - wall,
            );
            parts.push(difference(outer, inner));
            let (n, sr, phase) = (2 + r.pick(2), r.u(0.008, 0.014), r.u(0.0, TAU));
            for i in 0..n {
                let a = phase + TAU * i as f64 / n as f64;
                let rim = ro - wall / 2.0;
                parts.push(capsule(
                    top,
                    [tx + rim * a.cos(), ty, tz + rim * a.sin()],
                    sr,
                ));
            }
            parts.push(sphere(top, r.u(0.03, 0.06)));
        }
        1 => {
            // A cone-like stack of cylinders, blended.
            let n = 3 + r.pick(3);
            let (r0, h) = (r.u(0.18, 0.3), r.u(0.18, 0.35));
            let r1 = r0 * r.u(0.3, 0.6);
            let step = h / n as f64;
            let y0 = ty - 0.7 * h;
            let layers: Vec<Node> = (0..n)
                .map(|i| {
                    let rad = r0 + (r1 - r0) * i as f64 / (n - 1) as f64;
                    let y = y0 + step * i as f64;
                    cylinder([tx, y, tz], [tx, y + step * 1.2, tz], rad)
                })
                .collect();
            let mut layers = layers.into_iter();
            let first = layers.next().unwrap_or_else(|| sphere(top, r0)); // invariant: n ≥ 3
            let mut shade = smooth((step * 0.3).min(0.015), first, layers.collect());
            if r.coin(0.5) {
                shade = difference(
                    shade,
                    cylinder(
                        [tx, y0 - 0.05, tz],
                        [tx, y0 + h * r.u(0.3, 0.6), tz],
                        r0 * r.u(0.5, 0.8),
                    ),
                );
            }
            parts.push(shade);
        }
        _ => {
            let gr = r.u(0.12, 0.22);
            parts.push(sphere([tx, ty + 0.6 * gr, tz], gr));
        }
    }
    smooth(k, base, parts)
}

fn mug(r: &mut Draw) -> Node {
    let k = r.u(0.006, 0.012);
    let (rad, h) = (r.u(0.25, 0.4), r.u(0.55, 0.95));
    let (wall, bottom) = (r.u(0.025, 0.05), r.u(0.03, 0.07));
    let body = cylinder([0.0, 0.0, 0.0], [0.0, h, 0.0], rad);
    let handle = if r.coin(0.65) {
        let (major, minor) = (h * r.u(0.2, 0.3), r.u(0.025, 0.045));
        let reach = major + minor + 0.03;
        let cy = (h * r.u(0.45, 0.55)).clamp(reach, (h - reach).max(reach));
        torus([rad + major * r.u(0.1, 0.45), cy, 0.0], major, minor)
    } else {
        let (e, hr) = (r.u(0.1, 0.18), r.u(0.02, 0.04));
        let (y1, y2) = (h * r.u(0.15, 0.3), h * r.u(0.7, 0.85));
        let x0 = rad - wall / 2.0;
        smooth(
            hr * 0.3,
            capsule([x0, y1, 0.0], [rad + e, y1, 0.0], hr),
            vec![
                capsule([rad + e, y1, 0.0], [rad + e, y2, 0.0], hr),
                capsule([rad + e, y2, 0.0], [x0, y2, 0.0], hr),
            ],
        )
    };
    let cavity = cylinder([0.0, bottom, 0.0], [0.0, h + 0.1, 0.0], rad - wall);
    difference(smooth(k, body, vec![handle]), cavity)
}

fn airplane(r: &mut Draw) -> Node {
    let k = r.u(0.006, 0.012);
    let len = 1.0;
    let rf = r.u(0.1, 0.15);
    let fuselage = capsule([-len / 2.0, 0.0, 0.0], [len / 2.0, 0.0, 0.0], rf);
    let mut parts = Vec::new();
    if r.coin(0.5) {
        parts.push(capsule(
            [-len / 2.0, 0.0, 0.0],
            [-len / 2.0 - r.u(0.05, 0.12), rf * 0.5, 0.0],
            rf * 0.6,
        ));
    }
    let (sh, c, tw) = (r.u(0.4, 0.6), r.u(0.16, 0.28), r.u(0.04, 0.07));
    let (xw, yw) = (len * r.u(-0.1, 0.1), rf * r.u(-0.6, 0.3));
    if r.coin(0.5) {
        parts.push(rbox([xw, yw, 0.0], [c / 2.0, tw / 2.0, sh], tw * 0.45));
    } else {
        parts.push(rbox(
            [xw, yw, 0.0],
            [c / 2.0, tw / 2.0, sh * 0.55],
            tw * 0.45,
        ));
        for s in [-1.0, 1.0] {
            parts.push(rbox(
                [xw - c * 0.2, yw, s * sh * 0.75],
                [c * 0.32, tw * 0.4, sh * 0.25],
                tw * 0.35,
            ));
        }
    }
    let (ct, st, tt) = (c * r.u(0.5, 0.8), sh * r.u(0.3, 0.45), tw * 0.8);
    let (cf, hf) = (ct * r.u(0.8, 1.2), r.u(0.1, 0.22));
    let xf = -len / 2.0 + cf / 2.0 + 0.01;
    parts.push(rbox(
        [xf, (rf + hf) / 2.0, 0.0],
        [cf / 2.0, (rf + hf) / 2.0, tt / 2.0],
        tt * 0.45,
    ));
    let yt = if r.coin(0.25) {
        rf + hf - tt / 2.0
    } else {
        rf * r.u(-0.2, 0.4)
    };
    parts.push(rbox(
        [-len / 2.0 + ct / 2.0 + 0.02, yt, 0.0],
        [ct / 2.0, tt / 2.0, st],
        tt * 0.45,
    ));
    let engines = [0, 2, 4][r.pick(3)];
    if engines > 0 {
        let (re, le) = (r.u(0.03, 0.05), r.u(0.12, 0.2));
        let ye = yw - tw / 2.0 - re * 0.8;
        let zs = if engines == 2 {
            vec![sh * r.u(0.25, 0.45)]
        } else {
            vec![sh * 0.3, sh * 0.62]
        };
        for z in zs {
            for s in [-1.0, 1.0] {
                let front = xw + c * 0.5;
                parts.push(capsule([front, ye, s * z], [front - le, ye, s * z], re));
            }
        }
    }
    smooth(k, fuselage, parts)
}

/// One procedural shape of `category`: the family's parts, proportions and part counts
/// drawn from [`SplitMix64`]`::new(seed)`, combined into a [`Csg`] tree (smooth unions
/// where parts join, differences for hollows; see the [module docs] for each family)
/// and normalised so that its bounding box is centred at the origin with longest side 1
/// (the shape lies inside `[−0.5, 0.5]³`, `+y` up).
///
/// The tree's [`SignedDistance::distance_and_grad`] takes points `[N, 3]` of `dtype` on
/// `device` and returns `d: [N]` (negative inside; a 1-Lipschitz bound on the distance,
/// exact away from joins and cuts) and `∇d: [N, 3]`. The same `(category, seed)` gives the
/// same shape on every call; the collection's manifest stores each shape's seed.
///
/// [module docs]: crate::data#procedural-shape-collection
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use neural_fields::data::{generate_shape, ShapeCategory};
/// use neural_fields::field::SignedDistance;
///
/// let mug = generate_shape(ShapeCategory::Mug, 7, &Device::Cpu, DType::F64)?;
/// // Far outside (d > 0, about the distance), and a corner of the cube (outside too).
/// let p = Tensor::new(&[[3.0f64, 0.0, 0.0], [0.5, 0.5, 0.5]], &Device::Cpu)?;
/// let (d, grad) = mug.distance_and_grad(&p)?;
/// let d = d.to_vec1::<f64>()?;
/// assert!(d[0] > 2.4 && d[0] < 3.0 && d[1] > 0.0);
/// assert_eq!(grad.dims(), &[2, 3]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `dtype` unless f32 or f64; candle's errors for a
/// device that cannot hold the parameters.
pub fn generate_shape(
    category: ShapeCategory,
    seed: u64,
    device: &Device,
    dtype: DType,
) -> Result<Csg> {
    check_dtype(dtype)?;
    let mut draw = Draw(SplitMix64::new(seed));
    let node = match category {
        ShapeCategory::Chair => chair(&mut draw),
        ShapeCategory::Table => table(&mut draw),
        ShapeCategory::Lamp => lamp(&mut draw),
        ShapeCategory::Mug => mug(&mut draw),
        ShapeCategory::Airplane => airplane(&mut draw),
    };
    node.normalised().build_csg(device, dtype)
}

// ---------------------------------------------------------------------------------------
// Sampling.

/// A seed derived from `seed` and two labels (one SplitMix64 step of their mix).
fn derive(seed: u64, a: u64, b: u64) -> u64 {
    SplitMix64::new(
        seed ^ a.wrapping_mul(0xA076_1D64_78BD_642F) ^ b.wrapping_mul(0xE703_7ED1_A0B4_28DB),
    )
    .next_u64()
}

/// `d` and `∇d` (flat `[N·3]`) of `shape` (built on the CPU in f32) at flat points `[N·3]`,
/// in batches of [`CHUNK`] points.
fn evaluate(shape: &Csg, points: &[f32]) -> Result<(Vec<f32>, Vec<f32>)> {
    let mut d = Vec::new();
    let mut g = Vec::new();
    for chunk in points.chunks(3 * CHUNK) {
        let t = Tensor::from_slice(chunk, (chunk.len() / 3, 3), &Device::Cpu)?;
        let (dist, grad) = shape.distance_and_grad(&t)?;
        d.extend(dist.to_dtype(DType::F32)?.to_vec1::<f32>()?);
        g.extend(grad.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?);
    }
    Ok((d, g))
}

/// The arrays of one shape, in memory.
struct Arrays {
    uniform_points: Vec<f32>,
    uniform_occupancy: Vec<u8>,
    near_points: Vec<f32>,
    near_occupancy: Vec<u8>,
    surface_points: Vec<f32>,
    surface_normals: Vec<f32>,
    voxels: Vec<u8>,
}

fn occupancy(d: &[f32]) -> Vec<u8> {
    d.iter().map(|&x| u8::from(x < 0.0)).collect()
}

/// Samples every array of one shape (see the module docs), drawing from `rng`.
fn sample(shape: &Csg, config: &ShapeCollectionConfig, rng: &mut SplitMix64) -> Result<Arrays> {
    // Voxels: cell centres, occupied where the centre is within half a diagonal.
    let res = config.voxel_resolution;
    let cell = 1.0 / res as f64;
    let centre = |i: usize| (-0.5 + (i as f64 + 0.5) * cell) as f32;
    let mut centres = Vec::new();
    for ix in 0..res {
        for iy in 0..res {
            for iz in 0..res {
                centres.extend([centre(ix), centre(iy), centre(iz)]);
            }
        }
    }
    let (dc, _) = evaluate(shape, &centres)?;
    let half_diagonal = (0.5 * 3f64.sqrt() * cell) as f32;
    let voxels: Vec<u8> = dc.iter().map(|&d| u8::from(d < half_diagonal)).collect();
    let boundary: Vec<usize> = (0..dc.len())
        .filter(|&i| dc[i].abs() < half_diagonal)
        .collect();

    // Surface points: candidates drawn uniformly in the boundary cells, those within a
    // thin band around the surface projected onto d = 0 by Newton's steps.
    let want = config.surface_points;
    let mut surface_points = Vec::new();
    let mut surface_normals = Vec::new();
    let mut rounds = 0;
    // The fraction of candidates that become surface points, from the last round.
    let mut yield_rate = 0.3f64;
    while surface_points.len() < 3 * want {
        rounds += 1;
        if boundary.is_empty() || rounds > 64 {
            return Err(Error::invalid(
                "shape",
                format!("a surface on which {want} points can be found"),
                format!(
                    "{} points after {} rounds ({} boundary cells)",
                    surface_points.len() / 3,
                    rounds - 1,
                    boundary.len()
                ),
            ));
        }
        let missing = want - surface_points.len() / 3;
        let batch = ((missing as f64 * 1.3 / yield_rate.max(0.02)) as usize).clamp(256, 1 << 20);
        let mut candidates = Vec::new();
        for _ in 0..batch {
            let c = boundary[rng.below(boundary.len() as u64) as usize];
            let (ix, iy, iz) = (c / (res * res), (c / res) % res, c % res);
            for i in [ix, iy, iz] {
                candidates.push(centre(i) + ((rng.uniform() - 0.5) * cell) as f32);
            }
        }
        let (d0, g0) = evaluate(shape, &candidates)?;
        // The band's points (enough of them for this round), with d and ∇d where they are.
        let take = missing + missing / 4 + 16;
        let mut p = Vec::new();
        let mut d = Vec::new();
        let mut g = Vec::new();
        for (i, &di) in d0.iter().enumerate() {
            if di.abs() < SURFACE_BAND && d.len() < take {
                p.extend_from_slice(&candidates[3 * i..3 * i + 3]);
                d.push(di);
                g.extend_from_slice(&g0[3 * i..3 * i + 3]);
            }
        }
        let start_grad = g.clone();
        // Newton's steps p ← p − d·∇d/‖∇d‖², each point until it has converged.
        let mut active: Vec<usize> = (0..d.len())
            .filter(|&i| d[i].abs() >= SURFACE_TOLERANCE / 4.0)
            .collect();
        for _ in 0..NEWTON_STEPS {
            let mut moved = Vec::new();
            for &i in &active {
                let gi = &g[3 * i..3 * i + 3];
                let g2 = gi[0] * gi[0] + gi[1] * gi[1] + gi[2] * gi[2];
                if g2 > 1e-6 {
                    for a in 0..3 {
                        p[3 * i + a] -= d[i] * gi[a] / g2;
                    }
                    moved.extend_from_slice(&p[3 * i..3 * i + 3]);
                }
            }
            active.retain(|&i| {
                let gi = &g[3 * i..3 * i + 3];
                gi[0] * gi[0] + gi[1] * gi[1] + gi[2] * gi[2] > 1e-6
            });
            let (dm, gm) = evaluate(shape, &moved)?;
            for (j, &i) in active.iter().enumerate() {
                d[i] = dm[j];
                g[3 * i..3 * i + 3].copy_from_slice(&gm[3 * j..3 * j + 3]);
            }
            active.retain(|&i| d[i].abs() >= SURFACE_TOLERANCE / 4.0);
            if active.is_empty() {
                break;
            }
        }
        // Keep points on the surface whose normal is that of the face their projection
        // started from, and probe the normal a small step along the surface.
        let mut found = Vec::new();
        let mut normals = Vec::new();
        let mut probes = Vec::new();
        for (i, &di) in d.iter().enumerate() {
            let gi = &g[3 * i..3 * i + 3];
            let si = &start_grad[3 * i..3 * i + 3];
            let norm = (gi[0] * gi[0] + gi[1] * gi[1] + gi[2] * gi[2]).sqrt();
            let start = (si[0] * si[0] + si[1] * si[1] + si[2] * si[2]).sqrt();
            let cos = (gi[0] * si[0] + gi[1] * si[1] + gi[2] * si[2]) / (norm * start).max(1e-30);
            if di.abs() >= SURFACE_TOLERANCE || norm <= 0.5 || cos <= SAME_FACE {
                continue;
            }
            let n: Vec<f32> = gi.iter().map(|x| x / norm).collect();
            // A random direction in the tangent plane.
            let r: Vec<f32> = (0..3).map(|_| rng.normal() as f32).collect();
            let rn = r[0] * n[0] + r[1] * n[1] + r[2] * n[2];
            let t: Vec<f32> = (0..3).map(|a| r[a] - rn * n[a]).collect();
            let tl = (t[0] * t[0] + t[1] * t[1] + t[2] * t[2]).sqrt();
            if tl < 1e-3 {
                continue;
            }
            for side in [1.0, -1.0] {
                for a in 0..3 {
                    probes.push(p[3 * i + a] + side * TANGENT_STEP * t[a] / tl);
                }
            }
            found.extend_from_slice(&p[3 * i..3 * i + 3]);
            normals.extend(n);
        }
        // A point on a crease (where the normal jumps, and the gradient on the crease
        // itself is an average or one side's, by rounding) sees another normal a step to
        // one side, and is dropped.
        let (_, gp) = evaluate(shape, &probes)?;
        let before = surface_points.len();
        for (i, n) in normals.chunks(3).enumerate() {
            let stable = gp[6 * i..6 * i + 6].chunks(3).all(|q| {
                let ql = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt();
                q[0] * n[0] + q[1] * n[1] + q[2] * n[2] > STABLE_NORMAL * ql
            });
            if stable && surface_points.len() < 3 * want {
                surface_points.extend_from_slice(&found[3 * i..3 * i + 3]);
                surface_normals.extend_from_slice(n);
            }
        }
        yield_rate = (surface_points.len() - before) as f64 / 3.0 / batch as f64;
    }

    // Near-surface points: surface points plus Gaussian noise, one group per σ.
    let mut near_points = Vec::new();
    if config.near_points > 0 {
        for &sigma in &config.near_sigmas {
            for _ in 0..config.near_points {
                let j = rng.below(want as u64) as usize;
                for a in 0..3 {
                    near_points.push(surface_points[3 * j + a] + (sigma * rng.normal()) as f32);
                }
            }
        }
    }
    let (dn, _) = evaluate(shape, &near_points)?;

    // Uniform points in the padded cube.
    let half = 0.5 * (1.0 + config.padding);
    let mut uniform_points = Vec::new();
    for _ in 0..3 * config.uniform_points {
        uniform_points.push((-half + 2.0 * half * rng.uniform()) as f32);
    }
    let (du, _) = evaluate(shape, &uniform_points)?;

    Ok(Arrays {
        uniform_occupancy: occupancy(&du),
        uniform_points,
        near_occupancy: occupancy(&dn),
        near_points,
        surface_points,
        surface_normals,
        voxels,
    })
}

// ---------------------------------------------------------------------------------------
// Files.

fn io_error(path: &Path, source: std::io::Error) -> Error {
    Error::Io {
        path: path.display().to_string(),
        source,
    }
}

fn create_dir(path: &Path) -> Result<()> {
    std::fs::create_dir_all(path).map_err(|e| io_error(path, e))
}

fn to_json_text(value: &Value, path: &Path, pretty: bool) -> Result<String> {
    let text = if pretty {
        serde_json::to_string_pretty(value)
    } else {
        serde_json::to_string(value)
    };
    text.map_err(|e| io_error(path, std::io::Error::other(e)))
}

/// The safetensors bytes of `arrays` (name, dtype, shape, little-endian data), laid out
/// back to back in the given order, with `metadata` as the header's `__metadata__`.
fn encode_safetensors(
    path: &Path,
    metadata: Map<String, Value>,
    arrays: &[(&str, &str, Vec<usize>, Vec<u8>)],
) -> Result<Vec<u8>> {
    let mut header = Map::new();
    header.insert("__metadata__".into(), Value::Object(metadata));
    let mut offset = 0usize;
    for (name, dtype, shape, data) in arrays {
        header.insert(
            (*name).into(),
            json!({ "dtype": dtype, "shape": shape, "data_offsets": [offset, offset + data.len()] }),
        );
        offset += data.len();
    }
    let mut text = to_json_text(&Value::Object(header), path, false)?;
    while !text.len().is_multiple_of(8) {
        text.push(' ');
    }
    let mut out = Vec::new();
    out.extend_from_slice(&(text.len() as u64).to_le_bytes());
    out.extend_from_slice(text.as_bytes());
    for (_, _, _, data) in arrays {
        out.extend_from_slice(data);
    }
    Ok(out)
}

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// The shape's file, relative to the collection folder.
fn shape_file(index: usize) -> String {
    format!("shapes/{index:05}/shape.safetensors")
}

fn split_name(split: Split) -> &'static str {
    split.name()
}

/// The shapes of a collection in index order, with seeds and splits.
fn plan(config: &ShapeCollectionConfig) -> Vec<ShapeInfo> {
    let n = config.shapes_per_category;
    let n_test = ((n as f64) * config.test_fraction).round() as usize;
    let n_val = (((n as f64) * config.val_fraction).round() as usize).min(n - n_test.min(n));
    let mut infos = Vec::new();
    for (c, &category) in config.categories.iter().enumerate() {
        // A seeded Fisher–Yates permutation of the category's shapes.
        let mut order: Vec<usize> = (0..n).collect();
        let mut rng = SplitMix64::new(derive(config.seed, category.code(), u64::MAX));
        for i in (1..n).rev() {
            let j = rng.below(i as u64 + 1) as usize;
            order.swap(i, j);
        }
        let mut splits = vec![Split::Train; n];
        for (rank, &i) in order.iter().enumerate() {
            splits[i] = if rank < n_test {
                Split::Test
            } else if rank < n_test + n_val {
                Split::Val
            } else {
                Split::Train
            };
        }
        for (i, split) in splits.into_iter().enumerate() {
            infos.push(ShapeInfo {
                index: c * n + i,
                category,
                split,
                seed: derive(config.seed, category.code(), i as u64),
            });
        }
    }
    infos
}

/// Writes one shape's file.
fn write_shape(dir: &Path, config: &ShapeCollectionConfig, info: &ShapeInfo) -> Result<()> {
    let shape = generate_shape(info.category, info.seed, &Device::Cpu, DType::F32)?;
    let mut rng = SplitMix64::new(derive(info.seed, 0x5A, 0));
    let a = sample(&shape, config, &mut rng)?;
    let path = dir.join(shape_file(info.index));
    if let Some(parent) = path.parent() {
        create_dir(parent)?;
    }
    let mut metadata = Map::new();
    for (key, value) in [
        ("format", SHAPE_FORMAT.to_string()),
        ("format_version", FORMAT_VERSION.to_string()),
        ("index", info.index.to_string()),
        ("category", info.category.name().to_string()),
        ("seed", info.seed.to_string()),
    ] {
        metadata.insert(key.into(), Value::String(value));
    }
    let shapes = config.arrays();
    let data = [
        f32_bytes(&a.near_points),
        f32_bytes(&a.surface_normals),
        f32_bytes(&a.surface_points),
        f32_bytes(&a.uniform_points),
        a.near_occupancy,
        a.uniform_occupancy,
        a.voxels,
    ];
    let arrays: Vec<(&str, &str, Vec<usize>, Vec<u8>)> = shapes
        .into_iter()
        .zip(data)
        .map(|((name, dtype, shape), bytes)| (name, dtype, shape, bytes))
        .collect();
    let bytes = encode_safetensors(&path, metadata, &arrays)?;
    write_atomic(&path, &bytes)
}

fn manifest_json(config: &ShapeCollectionConfig, infos: &[ShapeInfo]) -> Value {
    let count = |s: Split| infos.iter().filter(|i| i.split == s).count();
    let shapes: Vec<Value> = infos
        .iter()
        .map(|i| {
            json!({
                "index": i.index,
                "category": i.category.name(),
                "split": split_name(i.split),
                "seed": i.seed,
                "file": shape_file(i.index),
            })
        })
        .collect();
    let categories: Vec<&str> = config.categories.iter().map(|c| c.name()).collect();
    json!({
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "seed": config.seed,
        "categories": categories,
        "shapes_per_category": config.shapes_per_category,
        "uniform_points": config.uniform_points,
        "near_points": config.near_points,
        "near_sigmas": config.near_sigmas,
        "surface_points": config.surface_points,
        "voxel_resolution": config.voxel_resolution,
        "padding": config.padding,
        "split_fractions": { "val": config.val_fraction, "test": config.test_fraction },
        "counts": {
            "train": count(Split::Train),
            "val": count(Split::Val),
            "test": count(Split::Test),
            "total": infos.len(),
        },
        "up": "+y",
        "voxel_rule": "a cell is occupied iff the signed distance at its centre is below half the cell diagonal",
        "shapes": shapes,
    })
}

/// Generates the collection `config` describes and writes it to `dir` in the format of
/// the [module docs]: `manifest.json` and one `shapes/NNNNN/shape.safetensors` per
/// shape. Returns the shapes as the manifest lists them (index, category, split, seed).
///
/// Each shape is [`generate_shape`]`(category, seed, Cpu, F32)` with its seed derived from
/// `config.seed`, the category and its number in the category; its samples come from a
/// stream derived from its seed. Labels are `d(p) < 0` evaluated in f32 on the CPU (the
/// format fixes both, so the same configuration writes the same bytes); voxels are
/// occupied iff `d(centre) < √3/(2R)`. Shapes are generated in parallel (rayon), each
/// independent of the others. Files are written through a temporary name and renamed,
/// the manifest last, so a folder with a manifest is complete. Views are added afterwards
/// with [`write_shape_views`]; views left in `dir` by another collection are not removed,
/// and the loader refuses them (naming their `cameras.json`), so write a new collection
/// into a new folder.
///
/// [module docs]: crate::data#procedural-shape-collection
///
/// ```
/// use neural_fields::data::{write_shape_collection, ShapeCategory, ShapeCollectionConfig};
///
/// let dir = std::env::temp_dir().join(format!("nf-doc-write-shapes-{}", std::process::id()));
/// let config = ShapeCollectionConfig {
///     categories: vec![ShapeCategory::Chair, ShapeCategory::Mug],
///     shapes_per_category: 2,
///     uniform_points: 256,
///     near_points: 128,
///     surface_points: 128,
///     voxel_resolution: 8,
///     ..ShapeCollectionConfig::default()
/// };
/// let shapes = write_shape_collection(&dir, &config)?;
/// assert_eq!(shapes.len(), 4);
/// assert!(dir.join("manifest.json").is_file());
/// assert!(dir.join("shapes/00003/shape.safetensors").is_file());
/// # std::fs::remove_dir_all(&dir).ok();
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming the field (`config.shapes_per_category`, …) for an
/// empty or repeated category list, zero shapes, more than 2²⁰ shapes, point counts or a
/// voxel grid past the allocation limit, σ outside `(0, 1]`, padding outside `[0, 1]`,
/// fractions outside `[0, 1]` or summing past 1, or `near_points > 0` with no σ or no
/// surface points; [`Error::Io`] naming a file or folder that cannot be written.
pub fn write_shape_collection(
    dir: &Path,
    config: &ShapeCollectionConfig,
) -> Result<Vec<ShapeInfo>> {
    config.validate()?;
    create_dir(dir)?;
    let infos = plan(config);
    infos
        .par_iter()
        .try_for_each(|info| write_shape(dir, config, info))?;
    let path = dir.join("manifest.json");
    let text = to_json_text(&manifest_json(config, &infos), &path, true)?;
    write_atomic(&path, text.as_bytes())?;
    Ok(infos)
}

// ---------------------------------------------------------------------------------------
// Reading JSON with errors that name the file and the field.

fn kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "a list",
        Value::Object(_) => "an object",
    }
}

/// A JSON object of the file `path`, whose fields are named `prefix` + key in errors.
struct Obj<'a> {
    map: &'a Map<String, Value>,
    path: &'a Path,
    prefix: String,
}

impl<'a> Obj<'a> {
    fn new(value: &'a Value, path: &'a Path, field: &str) -> Result<Self> {
        match value {
            Value::Object(map) => Ok(Self {
                map,
                path,
                prefix: if field.is_empty() {
                    String::new()
                } else {
                    format!("{field}.")
                },
            }),
            other => Err(Error::format(
                path,
                if field.is_empty() { "top level" } else { field },
                "a JSON object",
                kind(other),
            )),
        }
    }

    fn name(&self, key: &str) -> String {
        format!("{}{key}", self.prefix)
    }

    fn get(&self, key: &str, what: &str) -> Result<&'a Value> {
        self.map.get(key).ok_or_else(|| {
            Error::format(self.path, self.name(key), what, format!("no `{key}` key"))
        })
    }

    fn u64(&self, key: &str, what: &str) -> Result<u64> {
        let v = self.get(key, what)?;
        v.as_u64()
            .ok_or_else(|| Error::format(self.path, self.name(key), what, v.to_string()))
    }

    fn usize(&self, key: &str, what: &str) -> Result<usize> {
        let n = self.u64(key, what)?;
        usize::try_from(n)
            .map_err(|_| Error::format(self.path, self.name(key), what, n.to_string()))
    }

    fn f64(&self, key: &str, what: &str) -> Result<f64> {
        let v = self.get(key, what)?;
        v.as_f64()
            .filter(|x| x.is_finite())
            .ok_or_else(|| Error::format(self.path, self.name(key), what, v.to_string()))
    }

    fn str(&self, key: &str, what: &str) -> Result<&'a str> {
        let v = self.get(key, what)?;
        v.as_str()
            .ok_or_else(|| Error::format(self.path, self.name(key), what, kind(v)))
    }

    fn list(&self, key: &str, what: &str) -> Result<&'a Vec<Value>> {
        let v = self.get(key, what)?;
        v.as_array()
            .ok_or_else(|| Error::format(self.path, self.name(key), what, kind(v)))
    }

    fn obj(&self, key: &str) -> Result<Obj<'a>> {
        Obj::new(self.get(key, "a JSON object")?, self.path, &self.name(key))
    }
}

fn read_json(path: &Path) -> Result<Value> {
    let bytes = read_capped(path, MAX_JSON_BYTES)?;
    serde_json::from_slice(&bytes)
        .map_err(|e| Error::format(path, "JSON", "valid JSON", e.to_string()))
}

fn parse_split(name: &str) -> Option<Split> {
    match name {
        "train" => Some(Split::Train),
        "val" => Some(Split::Val),
        "test" => Some(Split::Test),
        _ => None,
    }
}

/// A parsed, checked manifest: the configuration and the shapes with their files.
struct Manifest {
    path: PathBuf,
    root: PathBuf,
    config: ShapeCollectionConfig,
    shapes: Vec<(ShapeInfo, String)>,
}

fn read_manifest(dir: &Path) -> Result<Manifest> {
    let root = dir.canonicalize().map_err(|e| io_error(dir, e))?;
    let path = dir.join("manifest.json");
    let value = read_json(&path)?;
    let top = Obj::new(&value, &path, "")?;
    let format = top.str("format", &format!("\"{FORMAT}\""))?;
    if format != FORMAT {
        return Err(Error::format(
            &path,
            "format",
            format!("\"{FORMAT}\""),
            format!("\"{format}\""),
        ));
    }
    let version = top.get("format_version", "a format version")?;
    if version.as_u64() != Some(FORMAT_VERSION) {
        return Err(Error::format(
            &path,
            "format_version",
            format!("version {FORMAT_VERSION} (the version this library reads)"),
            version.to_string(),
        ));
    }
    let names = top.list("categories", "a list of category names")?;
    let mut categories = Vec::new();
    for (i, n) in names.iter().enumerate() {
        let category = n.as_str().and_then(ShapeCategory::parse).ok_or_else(|| {
            Error::format(
                &path,
                format!("categories[{i}]"),
                "chair, table, lamp, mug or airplane",
                n.to_string(),
            )
        })?;
        categories.push(category);
    }
    let sigmas = top.list("near_sigmas", "a list of standard deviations")?;
    let mut near_sigmas = Vec::new();
    for (i, s) in sigmas.iter().enumerate() {
        near_sigmas.push(s.as_f64().ok_or_else(|| {
            Error::format(
                &path,
                format!("near_sigmas[{i}]"),
                "a number",
                s.to_string(),
            )
        })?);
    }
    let fractions = top.obj("split_fractions")?;
    let count = "a count (a non-negative integer)";
    let config = ShapeCollectionConfig {
        seed: top.u64("seed", "a seed (an integer in [0, 2⁶⁴))")?,
        categories,
        shapes_per_category: top.usize("shapes_per_category", count)?,
        uniform_points: top.usize("uniform_points", count)?,
        near_points: top.usize("near_points", count)?,
        near_sigmas,
        surface_points: top.usize("surface_points", count)?,
        voxel_resolution: top.usize("voxel_resolution", count)?,
        padding: top.f64("padding", "a finite number")?,
        val_fraction: fractions.f64("val", "a finite number")?,
        test_fraction: fractions.f64("test", "a finite number")?,
    };
    if let Err(Error::InvalidArgument { arg, expected, got }) = config.validate() {
        let field = arg.trim_start_matches("config.").replace("_fraction", "");
        let field = match field.as_str() {
            "val" | "test" => format!("split_fractions.{field}"),
            _ => field,
        };
        return Err(Error::format(&path, field, expected, got));
    }
    let list = top.list("shapes", "a list of shapes")?;
    let total = config.categories.len() * config.shapes_per_category;
    if list.len() != total {
        return Err(Error::format(
            &path,
            "shapes",
            format!(
                "{total} shapes ({} categories × shapes_per_category {})",
                config.categories.len(),
                config.shapes_per_category
            ),
            format!("{} shapes", list.len()),
        ));
    }
    let mut shapes = Vec::new();
    for (i, item) in list.iter().enumerate() {
        let field = format!("shapes[{i}]");
        let o = Obj::new(item, &path, &field)?;
        let index = o.usize("index", "the shape's position in the list")?;
        if index != i {
            return Err(Error::format(
                &path,
                o.name("index"),
                format!("{i} (shapes are listed in index order)"),
                index.to_string(),
            ));
        }
        let want = config.categories[i / config.shapes_per_category];
        let category = o.str("category", want.name())?;
        if category != want.name() {
            return Err(Error::format(
                &path,
                o.name("category"),
                format!("{want} (shapes are numbered category by category)"),
                category.to_string(),
            ));
        }
        let split_text = o.str("split", "train, val or test")?;
        let split = parse_split(split_text).ok_or_else(|| {
            Error::format(
                &path,
                o.name("split"),
                "train, val or test",
                split_text.to_string(),
            )
        })?;
        let seed = o.u64("seed", "a seed (an integer in [0, 2⁶⁴))")?;
        let file = o.str("file", "a path relative to the collection folder")?;
        shapes.push((
            ShapeInfo {
                index,
                category: want,
                split,
                seed,
            },
            file.to_string(),
        ));
    }
    Ok(Manifest {
        path,
        root,
        config,
        shapes,
    })
}

// ---------------------------------------------------------------------------------------
// Reading shape files.

/// A shape file's `__metadata__` and its arrays' bytes, in the order asked for.
type Parsed<'b> = (Map<String, Value>, Vec<&'b [u8]>);

/// The arrays of one safetensors file, checked against `expected` (name, dtype, shape):
/// exactly those arrays, back to back from offset 0 to the end of the file, with
/// `__metadata__` returned.
fn parse_shape_file<'b>(
    path: &Path,
    bytes: &'b [u8],
    expected: &[(&'static str, &'static str, Vec<usize>)],
) -> Result<Parsed<'b>> {
    let bad = |field: &str, what: &str, got: String| Error::format(path, field, what, got);
    let Some((len_bytes, rest)) = bytes.split_first_chunk::<8>() else {
        return Err(bad(
            "header size",
            "an 8-byte header length",
            format!("a file of {} bytes (truncated)", bytes.len()),
        ));
    };
    let n = u64::from_le_bytes(*len_bytes);
    if n > MAX_HEADER_BYTES || n > rest.len() as u64 {
        return Err(bad(
            "header size",
            &format!("a header of at most {MAX_HEADER_BYTES} bytes within the file"),
            format!("{n} bytes in a file of {} bytes", bytes.len()),
        ));
    }
    let (header, data) = rest.split_at(n as usize);
    let header: Value = serde_json::from_slice(header)
        .map_err(|e| bad("header", "a JSON header", e.to_string()))?;
    let Value::Object(mut entries) = header else {
        return Err(bad("header", "a JSON object", kind(&header).to_string()));
    };
    let metadata = match entries.remove("__metadata__") {
        Some(Value::Object(m)) => m,
        Some(other) => return Err(bad("__metadata__", "an object", kind(&other).to_string())),
        None => return Err(bad("__metadata__", "the shape's metadata", "none".into())),
    };
    if let Some(extra) = entries
        .keys()
        .find(|k| !expected.iter().any(|(n, ..)| n == k))
    {
        return Err(bad(
            extra,
            "only the arrays of the format",
            format!("an unexpected array `{extra}`"),
        ));
    }
    let mut spans = Vec::new();
    for (name, dtype, shape) in expected {
        let entry = entries
            .get(*name)
            .ok_or_else(|| bad(name, "an array of the format", "no such array".into()))?;
        let o = Obj::new(entry, path, name)?;
        let got_dtype = o.str("dtype", dtype)?;
        if got_dtype != *dtype {
            return Err(bad(&o.name("dtype"), dtype, got_dtype.to_string()));
        }
        let dims = o.list("shape", "a list of dimensions")?;
        let got: Vec<Option<u64>> = dims.iter().map(Value::as_u64).collect();
        let want: Vec<Option<u64>> = shape.iter().map(|&d| Some(d as u64)).collect();
        if got != want {
            return Err(bad(
                &o.name("shape"),
                &format!("shape {shape:?} (from manifest.json)"),
                Value::Array(dims.clone()).to_string(),
            ));
        }
        let offsets = o.list("data_offsets", "[begin, end]")?;
        let (begin, end) = match offsets.as_slice() {
            [b, e] => (b.as_u64(), e.as_u64()),
            _ => (None, None),
        };
        let size: u64 = if *dtype == "F32" { 4 } else { 1 };
        let need = shape.iter().fold(size, |a, &d| a.saturating_mul(d as u64));
        match (begin, end) {
            (Some(b), Some(e)) if e >= b && e - b == need && e <= data.len() as u64 => {
                spans.push((b, e, *name));
            }
            _ => {
                return Err(bad(
                    &o.name("data_offsets"),
                    &format!(
                        "[begin, begin + {need}] within the {} data bytes of the file",
                        data.len()
                    ),
                    Value::Array(offsets.clone()).to_string(),
                ))
            }
        }
    }
    let mut sorted = spans.clone();
    sorted.sort_unstable();
    let mut at = 0u64;
    for &(b, e, name) in &sorted {
        if b != at {
            return Err(bad(
                &format!("{name}.data_offsets"),
                &format!("arrays back to back: begin {at}"),
                format!("begin {b}"),
            ));
        }
        at = e;
    }
    if at != data.len() as u64 {
        return Err(bad(
            "data",
            &format!("{at} bytes of arrays"),
            format!("{} bytes", data.len()),
        ));
    }
    let slices = spans
        .iter()
        .map(|&(b, e, _)| &data[b as usize..e as usize])
        .collect();
    Ok((metadata, slices))
}

fn f32s(path: &Path, name: &str, bytes: &[u8]) -> Result<Vec<f32>> {
    let v: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    if let Some(i) = v.iter().position(|x| !x.is_finite()) {
        return Err(Error::format(
            path,
            name,
            "finite values",
            format!("element {i} = {}", v[i]),
        ));
    }
    Ok(v)
}

fn labels(path: &Path, name: &str, bytes: &[u8]) -> Result<Vec<u8>> {
    if let Some(i) = bytes.iter().position(|&b| b > 1) {
        return Err(Error::format(
            path,
            name,
            "labels 0 or 1",
            format!("element {i} = {}", bytes[i]),
        ));
    }
    Ok(bytes.to_vec())
}

/// Reads and checks one shape's file against the manifest's configuration and entry.
fn read_shape(manifest: &Manifest, info: ShapeInfo, file: &str) -> Result<(ShapeSample, PathBuf)> {
    let field = format!("shapes[{}].file", info.index);
    let path = confine(
        &manifest.root,
        &manifest.root.join(file),
        &manifest.path,
        &field,
        false,
    )?;
    let data_bytes = manifest.config.shape_bytes().unwrap_or(u64::MAX);
    let bytes = read_capped(&path, data_bytes.saturating_add(8 + MAX_HEADER_BYTES))?;
    let expected = manifest.config.arrays();
    let (metadata, arrays) = parse_shape_file(&path, &bytes, &expected)?;
    let index = info.index.to_string();
    let version = FORMAT_VERSION.to_string();
    let seed = info.seed.to_string();
    for (key, want) in [
        ("format", SHAPE_FORMAT),
        ("format_version", version.as_str()),
        ("index", index.as_str()),
        ("category", info.category.name()),
        ("seed", seed.as_str()),
    ] {
        let got = metadata.get(key).and_then(Value::as_str);
        if got != Some(want) {
            return Err(Error::format(
                &path,
                format!("__metadata__.{key}"),
                format!("\"{want}\" (as manifest.json lists the shape)"),
                got.map_or_else(|| "none".to_string(), |g| format!("\"{g}\"")),
            ));
        }
    }
    let [near, normals, surface, uniform, near_occ, uniform_occ, voxels] = arrays[..] else {
        // invariant: parse_shape_file returns one slice per expected array (7).
        return Err(Error::format(
            &path,
            "arrays",
            "7 arrays",
            arrays.len().to_string(),
        ));
    };
    let sample = ShapeSample {
        info,
        uniform_points: f32s(&path, "uniform_points", uniform)?,
        uniform_occupancy: labels(&path, "uniform_occupancy", uniform_occ)?,
        near_points: f32s(&path, "near_points", near)?,
        near_occupancy: labels(&path, "near_occupancy", near_occ)?,
        surface_points: f32s(&path, "surface_points", surface)?,
        surface_normals: f32s(&path, "surface_normals", normals)?,
        voxels: labels(&path, "voxels", voxels)?,
        views: Vec::new(),
    };
    Ok((sample, path))
}

fn convention_name(c: Convention) -> &'static str {
    match c {
        Convention::OpenCv => "opencv",
        Convention::OpenGl => "opengl",
    }
}

/// Reads the views of the shape whose file is `shape_path`, adding their decoded bytes
/// to `used` and refusing to pass `config.max_bytes`.
fn read_views(
    manifest: &Manifest,
    info: &ShapeInfo,
    shape_path: &Path,
    config: &ShapeLoadConfig,
    used: &mut u64,
) -> Result<Vec<ShapeView>> {
    let Some(dir) = shape_path.parent().map(|p| p.join("views")) else {
        return Ok(Vec::new());
    };
    let path = dir.join("cameras.json");
    if !path.exists() && !path.is_symlink() {
        return Ok(Vec::new());
    }
    let path = confine(
        &manifest.root,
        &path,
        shape_path,
        "views/cameras.json",
        false,
    )?;
    let value = read_json(&path)?;
    let top = Obj::new(&value, &path, "")?;
    let version = top.get("format_version", "a format version")?;
    if version.as_u64() != Some(FORMAT_VERSION) {
        return Err(Error::format(
            &path,
            "format_version",
            format!("version {FORMAT_VERSION}"),
            version.to_string(),
        ));
    }
    for (key, want) in [
        ("shape_index", info.index as u64),
        ("shape_seed", info.seed),
    ] {
        let got = top.u64(key, "an integer")?;
        if got != want {
            return Err(Error::format(
                &path,
                key,
                format!("{want} (the shape's, in manifest.json: views of another collection?)"),
                got.to_string(),
            ));
        }
    }
    let list = top.list("views", "a list of views")?;
    if list.len() > config.max_views {
        return Err(Error::format(
            &path,
            "views",
            format!(
                "at most {} views (ShapeLoadConfig::max_views)",
                config.max_views
            ),
            format!("{} views", list.len()),
        ));
    }
    let mut specs = Vec::new();
    for (i, item) in list.iter().enumerate() {
        let o = Obj::new(item, &path, &format!("views[{i}]"))?;
        let side = |key: &str| -> Result<usize> {
            let v = o.u64(key, "a positive integer up to 1e6")?;
            if v == 0 || v > 1_000_000 {
                return Err(Error::format(
                    &path,
                    o.name(key),
                    "a positive integer up to 1e6",
                    v.to_string(),
                ));
            }
            Ok(v as usize)
        };
        let (width, height) = (side("width")?, side("height")?);
        let focal = |key: &str| -> Result<f64> {
            let v = o.f64(key, "a focal length in pixels")?;
            in_range(
                v,
                1e-3,
                MAX_CAMERA_VALUE,
                &path,
                &o.name(key),
                "a focal length in pixels",
            )
        };
        let centre = |key: &str| -> Result<f64> {
            let v = o.f64(key, "a principal point in pixels")?;
            in_range(
                v,
                -MAX_CAMERA_VALUE,
                MAX_CAMERA_VALUE,
                &path,
                &o.name(key),
                "a principal point in pixels",
            )
        };
        let intrinsics = Intrinsics::new(
            focal("fx")?,
            focal("fy")?,
            centre("cx")?,
            centre("cy")?,
            width,
            height,
        )
        .map_err(|e| Error::format(&path, o.name("width"), "valid intrinsics", e.to_string()))?;
        let convention = match o.str("convention", "opencv or opengl")? {
            "opencv" => Convention::OpenCv,
            "opengl" => Convention::OpenGl,
            other => {
                return Err(Error::format(
                    &path,
                    o.name("convention"),
                    "opencv or opengl",
                    other.to_string(),
                ))
            }
        };
        let rows_value = o.list("camera_to_world", "4 rows of 4 numbers")?;
        let mut rows = Vec::new();
        for (r, row) in rows_value.iter().enumerate() {
            let nums: Option<Vec<f64>> = row
                .as_array()
                .map(|a| a.iter().map(Value::as_f64).collect::<Option<Vec<f64>>>())
                .unwrap_or(None);
            match nums.as_deref() {
                Some(&[a, b, c, d]) => rows.push([a, b, c, d]),
                _ => {
                    return Err(Error::format(
                        &path,
                        format!("{}[{r}]", o.name("camera_to_world")),
                        "a row of 4 numbers",
                        row.to_string(),
                    ))
                }
            }
        }
        let pose = pose_from_rows(&rows, &path, &o.name("camera_to_world"))?;
        let camera = Camera::new(intrinsics, pose, convention).map_err(|e| {
            Error::format(
                &path,
                o.name("camera_to_world"),
                "a rigid pose",
                e.to_string(),
            )
        })?;
        for x in [pose.translation.x, pose.translation.y, pose.translation.z] {
            in_range(
                x,
                -MAX_CAMERA_VALUE,
                MAX_CAMERA_VALUE,
                &path,
                &o.name("camera_to_world"),
                "a camera centre",
            )?;
        }
        let file = o.str("file", "a PNG file relative to the views folder")?;
        let image_path = confine(
            &manifest.root,
            &dir.join(file),
            &path,
            &o.name("file"),
            false,
        )?;
        let header = Image::header(&image_path, false, config.max_image_pixels)?;
        if (header.width, header.height) != (width, height) {
            return Err(Error::format(
                &image_path,
                "image size",
                format!("{width} × {height} (the camera's, in {})", path.display()),
                format!("{} × {}", header.width, header.height),
            ));
        }
        *used = used.saturating_add(header.decoded_bytes());
        if *used > config.max_bytes {
            return Err(Error::format(
                &path,
                o.name("file"),
                format!(
                    "at most {} bytes of arrays and decoded images in one load (ShapeLoadConfig::max_bytes)",
                    config.max_bytes
                ),
                format!("{} bytes with this image", *used),
            ));
        }
        specs.push((camera, image_path, header));
    }
    specs
        .into_iter()
        .map(|(camera, image_path, header)| {
            Ok(ShapeView {
                camera,
                image: Image::decode(&image_path, false, &header)?,
            })
        })
        .collect()
}

/// Reads the shape collection in `dir` (the format of the [module docs]): the
/// manifest, then the shapes of `config.split` with their arrays (f32 points, u8 labels,
/// exactly as stored) and, if `config.views`, their rendered views (8-bit images with
/// their cameras; shapes without a `views/cameras.json` have none).
///
/// Hostile folders are refused before anything large is allocated: the arrays' bytes
/// (`12·N_uniform + N_uniform + 13·S·N_near + 24·N_surface + R³` per shape, from the
/// manifest) times the shapes to load must fit `config.max_bytes`; each shape file must be
/// no larger than its arrays plus a 64 KiB header, and its header must list exactly the
/// format's arrays with the manifest's dtypes and shapes, back to back; points and normals
/// must be finite, labels 0 or 1; the metadata must match the manifest's entry; every
/// path must resolve inside `dir`; view images are checked against
/// `config.max_image_pixels`, their camera's size and the budget before decoding.
///
/// [module docs]: crate::data#procedural-shape-collection
///
/// ```
/// use neural_fields::data::{
///     load_shape_collection, write_shape_collection, ShapeCategory, ShapeCollectionConfig,
///     ShapeLoadConfig, Split,
/// };
///
/// let dir = std::env::temp_dir().join(format!("nf-doc-load-shapes-{}", std::process::id()));
/// let config = ShapeCollectionConfig {
///     categories: vec![ShapeCategory::Table],
///     shapes_per_category: 5,
///     uniform_points: 256,
///     near_points: 64,
///     surface_points: 64,
///     voxel_resolution: 8,
///     ..ShapeCollectionConfig::default()
/// };
/// write_shape_collection(&dir, &config)?;
/// let test = load_shape_collection(&dir, &ShapeLoadConfig { split: Split::Test, ..Default::default() })?;
/// assert_eq!(test.config, config);
/// assert_eq!(test.shapes.len(), 1); // 20 % of 5
/// let shape = &test.shapes[0];
/// assert_eq!(shape.uniform_points.len(), 3 * 256);
/// assert_eq!(shape.near_points.len(), 3 * 64 * 2); // σ = 0.01 and 0.05
/// assert_eq!(shape.voxels.len(), 8 * 8 * 8);
/// # std::fs::remove_dir_all(&dir).ok();
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::Io`] naming a folder or file that cannot be read; [`Error::Format`] naming the
/// file and the field for anything malformed: another `format_version`, counts past the
/// budget, a path outside `dir`, a truncated file, a header whose shapes or offsets differ
/// from the manifest's, non-finite points, labels other than 0 or 1, metadata of another
/// shape, views of another collection or images of the wrong size.
pub fn load_shape_collection(dir: &Path, config: &ShapeLoadConfig) -> Result<ShapeCollection> {
    let manifest = read_manifest(dir)?;
    let chosen: Vec<&(ShapeInfo, String)> = manifest
        .shapes
        .iter()
        .filter(|(info, _)| config.split == Split::All || info.split == config.split)
        .collect();
    let per_shape = manifest.config.shape_bytes();
    let total = per_shape.and_then(|b| b.checked_mul(chosen.len() as u64));
    let mut used = match total {
        Some(t) if t <= config.max_bytes => t,
        _ => {
            return Err(Error::format(
                &manifest.path,
                "shapes",
                format!(
                    "at most {} bytes of arrays in one load (ShapeLoadConfig::max_bytes)",
                    config.max_bytes
                ),
                format!(
                    "{} shapes of {} bytes",
                    chosen.len(),
                    per_shape.map_or_else(|| "more than 2⁶⁴".to_string(), |b| b.to_string())
                ),
            ))
        }
    };
    let mut shapes = Vec::new();
    for (info, file) in chosen {
        let (mut sample, path) = read_shape(&manifest, *info, file)?;
        if config.views {
            sample.views = read_views(&manifest, info, &path, config, &mut used)?;
        }
        shapes.push(sample);
    }
    Ok(ShapeCollection {
        config: manifest.config,
        shapes,
    })
}

/// Writes rendered views of shape `shape` of the collection in `dir`: each `(camera,
/// image)` becomes `views/NNN.png` beside the shape's file, and `views/cameras.json` lists
/// them with the cameras' intrinsics, convention and camera-to-world matrices (see the
/// [module docs]), replacing any views the shape had.
///
/// `image` is `[H, W, 3]` (RGB) or `[H, W, 4]` (RGBA, straight alpha) of the camera's size:
/// u8 bytes as they are, or f32 / f64 values in `[0, 1]` (clamped, then `round(255·v)`).
/// The PNGs are written first and `cameras.json` last, each through a temporary file.
///
/// [module docs]: crate::data#procedural-shape-collection
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use neural_fields::camera::{Camera, Convention, Intrinsics};
/// use neural_fields::data::{
///     load_shape_collection, write_shape_collection, write_shape_views, ShapeCategory,
///     ShapeCollectionConfig, ShapeLoadConfig,
/// };
/// use neural_fields::glam::DVec3;
///
/// let dir = std::env::temp_dir().join(format!("nf-doc-views-{}", std::process::id()));
/// let config = ShapeCollectionConfig {
///     categories: vec![ShapeCategory::Lamp],
///     shapes_per_category: 1,
///     uniform_points: 64,
///     near_points: 32,
///     surface_points: 32,
///     voxel_resolution: 4,
///     ..ShapeCollectionConfig::default()
/// };
/// write_shape_collection(&dir, &config)?;
/// let k = Intrinsics::from_fov_y(16, 16, 0.8)?;
/// let camera = Camera::look_at(k, DVec3::new(0.0, 0.5, 2.0), DVec3::ZERO, DVec3::Y, Convention::OpenCv)?;
/// let image = Tensor::full(0.5f32, (16, 16, 3), &Device::Cpu)?; // e.g. a DVR rendering
/// write_shape_views(&dir, 0, &[(camera, image)])?;
/// let loaded = load_shape_collection(&dir, &ShapeLoadConfig::default())?;
/// let view = &loaded.shapes[0].views[0];
/// assert_eq!(view.image.size(), (16, 16, 3));
/// assert_eq!(view.image.data()[0], 128);
/// # std::fs::remove_dir_all(&dir).ok();
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `shape` if the collection has no such shape, and
/// `views` if it is empty, an image is not `[H, W, 3 or 4]` of its camera's size, has
/// another dtype, or holds a NaN; the errors of reading the manifest
/// ([`load_shape_collection`]); [`Error::Io`] naming a file that cannot be written.
pub fn write_shape_views(dir: &Path, shape: usize, views: &[(Camera, Tensor)]) -> Result<()> {
    let manifest = read_manifest(dir)?;
    let Some((info, file)) = manifest.shapes.get(shape) else {
        return Err(Error::invalid(
            "shape",
            format!("a shape index below {}", manifest.shapes.len()),
            shape.to_string(),
        ));
    };
    if views.is_empty() {
        return Err(Error::invalid("views", "at least one view", "none"));
    }
    let mut images = Vec::new();
    for (i, (camera, image)) in views.iter().enumerate() {
        let k = camera.intrinsics();
        let dims = image.dims();
        if !matches!(dims, [h, w, 3 | 4] if *h == k.height && *w == k.width) {
            return Err(Error::invalid(
                "views",
                format!(
                    "view {i}: an image [{}, {}, 3 or 4] (the camera's size)",
                    k.height, k.width
                ),
                format!("shape {dims:?}"),
            ));
        }
        let img = match image.dtype() {
            DType::U8 => Image::new(
                k.width,
                k.height,
                dims[2],
                image.flatten_all()?.to_vec1::<u8>()?,
            )?,
            DType::F32 | DType::F64 => Image::from_tensor(image).map_err(|e| {
                Error::invalid(
                    "views",
                    format!("view {i}: an image without NaN"),
                    e.to_string(),
                )
            })?,
            other => {
                return Err(Error::invalid(
                    "views",
                    format!("view {i}: an image of dtype u8, f32 or f64"),
                    format!("{other:?}"),
                ))
            }
        };
        images.push(img);
    }
    let field = format!("shapes[{shape}].file");
    let shape_path = confine(
        &manifest.root,
        &manifest.root.join(file),
        &manifest.path,
        &field,
        false,
    )?;
    let Some(dir) = shape_path.parent().map(|p| p.join("views")) else {
        return Err(Error::format(
            &manifest.path,
            field,
            "a file in a folder",
            file.clone(),
        ));
    };
    create_dir(&dir)?;
    let mut list = Vec::new();
    for (i, ((camera, _), img)) in views.iter().zip(&images).enumerate() {
        let name = format!("{i:03}.png");
        let (w, h, c) = img.size();
        write_atomic(&dir.join(&name), &encode_png(w, h, c, img.data())?)?;
        let k = camera.intrinsics();
        let m = camera.cam_to_world();
        let rows: Vec<Value> = (0..3)
            .map(|r| {
                let row = m.matrix3.row(r);
                json!([row.x, row.y, row.z, m.translation[r]])
            })
            .chain(std::iter::once(json!([0.0, 0.0, 0.0, 1.0])))
            .collect();
        list.push(json!({
            "file": name,
            "width": k.width,
            "height": k.height,
            "fx": k.fx,
            "fy": k.fy,
            "cx": k.cx,
            "cy": k.cy,
            "convention": convention_name(camera.convention()),
            "camera_to_world": rows,
        }));
    }
    let path = dir.join("cameras.json");
    let value = json!({
        "format_version": FORMAT_VERSION,
        "shape_index": info.index,
        "shape_seed": info.seed,
        "views": list,
    });
    write_atomic(&path, to_json_text(&value, &path, true)?.as_bytes())
}
