//! Ray batches: seeded random pixels and k×k patches across all views, and whole-image
//! chunks for evaluation.

use super::dataset::{Background, Dataset};
use crate::camera::{PixelFilter, Rays};
use crate::error::check_dtype;
use crate::error::{Error, Result};
use crate::rng::SplitMix64;
use candle_core::{DType, Device, Tensor};
use glam::DVec2;

/// The most rays one batch may hold (2²⁸): larger requests are refused before allocating.
const MAX_BATCH: usize = 1 << 28;

/// Rays with the pixels they image.
///
/// All tensors are on the caller's device; floats in the caller's dtype. `N` rays.
#[derive(Clone, Debug)]
pub struct RayBatch {
    /// The rays (origins at the camera centres, directions with camera-space depth 1, see
    /// [`crate::camera`]).
    pub rays: Rays,
    /// `[N, 3]` target colours in `[0, 1]`, composited on `backgrounds`.
    pub colors: Tensor,
    /// `[N, 3]` the background colour of each ray: composite the prediction on it
    /// (`c + (1 − opacity)·b`) to compare with `colors`.
    pub backgrounds: Tensor,
    /// `[N]` mask values in `[0, 1]` (mask file, else alpha), if every view has one.
    pub masks: Option<Tensor>,
    /// `[N]` u32: the index of each ray's view in the dataset.
    pub views: Tensor,
    /// `[N, 2]` u32: each ray's pixel `(u, v)` (column, row); the ray passes through the
    /// pixel's centre `(u + 0.5, v + 0.5)`, or through a uniformly random point of the
    /// pixel for a jittered sampler's [`RaySampler::pixels`]
    /// ([`RaySampler::with_pixel_filter`]).
    pub pixels: Tensor,
}

/// Builds the batch of the pixels `picks = [(view, u, v)]` with per-ray backgrounds; the
/// rays pass through `(u, v) + offsets[i]` (the pixel centres, `(½, ½)`, without offsets).
fn gather(
    dataset: &Dataset,
    picks: &[(usize, usize, usize)],
    offsets: Option<&[[f64; 2]]>,
    side: usize,
    backgrounds: &[[f64; 3]],
    device: &Device,
    dtype: DType,
) -> Result<RayBatch> {
    let n = picks.len();
    let mut radii = Vec::with_capacity(n);
    let masked = dataset.views().iter().all(|v| v.has_mask());
    let (mut o, mut d, mut c) = (
        Vec::with_capacity(3 * n),
        Vec::with_capacity(3 * n),
        Vec::with_capacity(3 * n),
    );
    let mut m = Vec::with_capacity(if masked { n } else { 0 });
    let (mut vi, mut px) = (Vec::with_capacity(n), Vec::with_capacity(2 * n));
    for (i, (&(view, u, v), bg)) in picks.iter().zip(backgrounds).enumerate() {
        let vw = &dataset.views()[view];
        let [du, dv] = offsets.and_then(|o| o.get(i)).copied().unwrap_or([0.5; 2]);
        let (origin, dir) = vw.camera().ray(DVec2::new(u as f64 + du, v as f64 + dv));
        o.extend_from_slice(&origin.to_array());
        d.extend_from_slice(&dir.to_array());
        radii.push(vw.camera().intrinsics().cone_radius() / side as f64);
        c.extend_from_slice(&vw.color(u, v, *bg));
        if masked {
            m.push(vw.mask_value(u, v).unwrap_or(1.0));
        }
        vi.push(view as u32);
        px.extend_from_slice(&[u as u32, v as u32]);
    }
    let float = |data: Vec<f64>, shape: &[usize]| -> Result<Tensor> {
        Ok(crate::narrow::from_host(data, shape, dtype, device)?)
    };
    let bgs: Vec<f64> = backgrounds.iter().flatten().copied().collect();
    Ok(RayBatch {
        rays: Rays::new(float(o, &[n, 3])?, float(d, &[n, 3])?)?.with_radii(float(radii, &[n])?)?,
        colors: float(c, &[n, 3])?,
        backgrounds: float(bgs, &[n, 3])?,
        masks: if masked { Some(float(m, &[n])?) } else { None },
        views: Tensor::from_vec(vi, n, device)?,
        pixels: Tensor::from_vec(px, (n, 2), device)?,
    })
}

/// Each view's pixel area `1/(fx·fy)` in units of the finest view's, rounded to the
/// nearest whole number in `1..=2²⁰` (all 1 when the views share their focal lengths).
fn pixel_weights(dataset: &Dataset) -> Vec<u64> {
    let area = |v: &super::dataset::View| {
        let k = v.camera().intrinsics();
        1.0 / (k.fx * k.fy)
    };
    let finest = dataset
        .views()
        .iter()
        .map(area)
        .fold(f64::INFINITY, f64::min);
    dataset
        .views()
        .iter()
        .map(|v| (area(v) / finest).round().clamp(1.0, f64::from(1u32 << 20)) as u64)
        .collect()
}

fn check_count(n: usize, arg: &'static str) -> Result<()> {
    if n == 0 || n > MAX_BATCH {
        return Err(Error::invalid(
            arg,
            format!("between 1 and {MAX_BATCH} rays"),
            n.to_string(),
        ));
    }
    Ok(())
}

/// A seeded sampler of training rays across all views of a dataset.
///
/// Same seed, same batches, on every machine. Pixels are drawn uniformly over all pixels
/// of all views (views of different sizes weigh by their pixel count), with replacement.
///
/// ```
/// use neural_fields::camera::{Camera, Convention, Intrinsics};
/// use neural_fields::data::{Background, Dataset, Image, RaySampler, View};
/// use neural_fields::glam::DVec3;
/// use candle_core::{DType, Device};
///
/// let k = Intrinsics::from_fov_y(8, 6, 0.8)?;
/// let cam = Camera::look_at(k, DVec3::new(0.0, -3.0, 0.0), DVec3::ZERO, DVec3::Z, Convention::OpenGl)?;
/// let image = Image::new(8, 6, 3, vec![128; 8 * 6 * 3])?;
/// let data = Dataset::new(vec![View::new(cam, image, None, "grey".into())?], Background::default(), None)?;
///
/// let mut sampler = RaySampler::new(&data, 0, &Device::Cpu, DType::F32)?;
/// let batch = sampler.pixels(1024)?;
/// assert_eq!(batch.colors.dims(), &[1024, 3]);
/// let patches = sampler.patches(16, 4)?; // 16 patches of 4 × 4 pixels
/// assert_eq!(patches.rays.len(), 16 * 16);
/// # Ok::<(), neural_fields::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct RaySampler<'a> {
    dataset: &'a Dataset,
    rng: SplitMix64,
    device: Device,
    dtype: DType,
    /// `ends[i]`: `Σ_{j ≤ i} pixels_j · weights[j]`, the cumulative drawing mass.
    ends: Vec<u64>,
    /// Each view's pixel area in units of the finest view's ([`pixel_weights`]).
    weights: Vec<u64>,
    /// Whether [`RaySampler::pixels`] jitters each ray inside its pixel.
    jitter: bool,
    /// The distribution of jittered offsets and footprint strata.
    filter: PixelFilter,
}

impl<'a> RaySampler<'a> {
    /// A sampler drawing from `seed`, building batches in `dtype` (f32 or f64) on `device`.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `dtype` unless f32 or f64.
    pub fn new(dataset: &'a Dataset, seed: u64, device: &Device, dtype: DType) -> Result<Self> {
        check_dtype(dtype)?;
        let weights = pixel_weights(dataset);
        let mut total = 0u64;
        let ends = dataset
            .views()
            .iter()
            .zip(&weights)
            .map(|(v, &m)| {
                let (w, h, _) = v.image().size();
                total += (w * h) as u64 * m;
                total
            })
            .collect();
        Ok(Self {
            dataset,
            rng: SplitMix64::new(seed),
            device: device.clone(),
            dtype,
            ends,
            weights,
            jitter: false,
            filter: PixelFilter::Box,
        })
    }

    /// The sampler with the pixel filter that its jittered rays and
    /// [`RaySampler::pixel_footprints`] sample ([`PixelFilter::Box`] by default: uniform
    /// over the pixel), and sub-pixel jitter on or off (off by default).
    ///
    /// With `jitter`, [`RaySampler::pixels`] sends each ray through a random point of its
    /// pixel instead of the centre (instant-NGP's training rays), so that a field trained
    /// on images that integrate over each pixel (antialiased renders, real sensors) sees
    /// the whole pixel footprint; evaluate such a field with several rays per pixel
    /// ([`crate::camera::Camera::subpixel_grid`]). With [`PixelFilter::Box`] the point is
    /// uniform over the pixel; with [`PixelFilter::CYCLES`], a jittered ray passes through
    /// `centre + (q(U₁), q(U₂))` for the filter's quantile function `q`, so its offsets
    /// are distributed as Blender's Cycles distributes a pixel's samples, reaching into the
    /// neighbouring pixels. Footprints take the medians (or, jittered, random points) of
    /// the filter's `k × k` equal-mass strata. Patches keep their pixel centres. The
    /// pixel's colour is unchanged: the image is the filter's mean of what those rays see.
    /// Draws no random numbers itself; the offsets are drawn after the pixels and
    /// backgrounds, so a sampler without jitter draws the same batches as before.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `filter` unless a Blackman–Harris `half_width` is
    /// finite and in `(0, 64]`.
    pub fn with_pixel_filter(mut self, filter: PixelFilter, jitter: bool) -> Result<Self> {
        filter.validate()?;
        self.filter = filter;
        self.jitter = jitter;
        Ok(self)
    }

    fn backgrounds(&mut self, n: usize) -> Vec<[f64; 3]> {
        match self.dataset.background() {
            Background::Color(c) => vec![c; n],
            Background::Random => (0..n)
                .map(|_| std::array::from_fn(|_| self.rng.uniform()))
                .collect(),
        }
    }

    /// `n` rays through pixel centres (or, jittered ([`RaySampler::with_pixel_filter`]), random
    /// points of the pixels) drawn over all pixels of all views, each pixel with probability
    /// proportional to its area: its solid angle at unit depth `1/(fx·fy)` in units of the
    /// finest view's, rounded to a whole number (at least 1). Where every view has the
    /// same focal lengths that is uniform over all pixels; in a multiscale dataset (each
    /// view also at ½, ¼, ⅛ resolution) a pixel at ½ resolution is drawn 4× as often as a
    /// full-resolution one, so every image weighs the same: mip-NeRF's loss weighting by
    /// pixel area, as importance sampling instead of a weighted mean.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `n` if 0 or above 2²⁸.
    pub fn pixels(&mut self, n: usize) -> Result<RayBatch> {
        check_count(n, "n")?;
        let picks = self.draw_pixels(n);
        let bgs = self.backgrounds(n);
        let filter = self.filter;
        let offsets: Option<Vec<[f64; 2]>> = self.jitter.then(|| {
            (0..n)
                .map(|_| {
                    let (a, b) = (self.rng.uniform(), self.rng.uniform());
                    [filter.corner_offset(a), filter.corner_offset(b)]
                })
                .collect()
        });
        gather(
            self.dataset,
            &picks,
            offsets.as_deref(),
            1,
            &bgs,
            &self.device,
            self.dtype,
        )
    }

    /// `n` pixels drawn as [`RaySampler::pixels`] draws them, each imaged by `k × k` rays
    /// on the sub-pixel grid of [`crate::camera::Camera::subpixel_grid`] for the sampler's
    /// pixel filter ([`RaySampler::with_pixel_filter`]; the box by default) (jittered,
    /// through a random point of each of the filter's `k × k`
    /// equal-mass strata: stratified sampling of the filter). Rays are pixel-major: rays
    /// `p·k² … (p + 1)·k² − 1` belong to pixel `p`, and every per-ray field (`colors`, `backgrounds`, `masks`, `views`,
    /// `pixels`) repeats the pixel's value over its `k²` rays. Average a prediction over each
    /// run of `k²` rays (`pred.reshape((n, k², 3))?.mean(1)`) to compare it with a pixel
    /// that integrates over its footprint (antialiased renders, real sensors): the
    /// box-filtered training that matches supersampled evaluation.
    ///
    /// ```
    /// # use neural_fields::camera::{Camera, Convention, Intrinsics};
    /// # use neural_fields::data::{Background, Dataset, Image, RaySampler, View};
    /// # use neural_fields::glam::DVec3;
    /// # use candle_core::{DType, Device};
    /// # let k = Intrinsics::from_fov_y(8, 6, 0.8)?;
    /// # let cam = Camera::look_at(k, DVec3::new(0.0, -3.0, 0.0), DVec3::ZERO, DVec3::Z, Convention::OpenGl)?;
    /// # let image = Image::new(8, 6, 3, vec![128; 8 * 6 * 3])?;
    /// # let data = Dataset::new(vec![View::new(cam, image, None, "grey".into())?], Background::default(), None)?;
    /// let mut sampler = RaySampler::new(&data, 0, &Device::Cpu, DType::F32)?;
    /// let batch = sampler.pixel_footprints(256, 2)?;     // 256 pixels × 4 rays
    /// assert_eq!(batch.rays.len(), 1024);
    /// let target = batch.colors.reshape((256, 4, 3))?.mean(1)?; // each pixel's colour
    /// assert_eq!(target.dims(), &[256, 3]);
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `k` unless between 1 and 64, and `n` if 0 or if
    /// `n · k²` is above 2²⁸.
    pub fn pixel_footprints(&mut self, n: usize, k: usize) -> Result<RayBatch> {
        if !(1..=64).contains(&k) {
            return Err(Error::invalid(
                "k",
                "1 to 64 rays per pixel side",
                k.to_string(),
            ));
        }
        check_count(n.saturating_mul(k * k), "n")?;
        let picks = self.draw_pixels(n);
        let bgs = self.backgrounds(n);
        let kk = k * k;
        let cell = 1.0 / k as f64;
        // The strata's medians, the same for every pixel (the filter's quantile is solved
        // once per stratum, not once per ray).
        let medians: Vec<f64> = (0..k)
            .map(|j| self.filter.corner_offset((j as f64 + 0.5) * cell))
            .collect();
        let mut offsets = Vec::with_capacity(n * kk);
        for _ in 0..n {
            for i in 0..k {
                for j in 0..k {
                    offsets.push(if self.jitter {
                        let (du, dv) = (self.rng.uniform(), self.rng.uniform());
                        [
                            self.filter.corner_offset((j as f64 + du) * cell),
                            self.filter.corner_offset((i as f64 + dv) * cell),
                        ]
                    } else {
                        [medians[j], medians[i]]
                    });
                }
            }
        }
        fn repeat<T: Copy>(v: &[T], k: usize) -> Vec<T> {
            v.iter().flat_map(|&x| std::iter::repeat_n(x, k)).collect()
        }
        let (picks, bgs) = (repeat(&picks, kk), repeat(&bgs, kk));
        gather(
            self.dataset,
            &picks,
            Some(&offsets),
            k,
            &bgs,
            &self.device,
            self.dtype,
        )
    }

    /// `n` pixels `(view, u, v)` drawn over all pixels of all views in proportion to
    /// their area ([`RaySampler::pixels`]).
    fn draw_pixels(&mut self, n: usize) -> Vec<(usize, usize, usize)> {
        // invariant: a Dataset holds at least one view (Dataset::new), so `ends` is non-empty.
        let total = self.ends.last().copied().unwrap_or(0);
        (0..n)
            .map(|_| {
                let i = self.rng.below(total);
                let view = self.ends.partition_point(|&e| e <= i);
                let start = if view == 0 { 0 } else { self.ends[view - 1] };
                let w = self.dataset.views()[view].image().size().0 as u64;
                let local = (i - start) / self.weights[view];
                (view, (local % w) as usize, (local / w) as usize)
            })
            .collect()
    }

    /// `count` square patches of `k × k` adjacent pixels (RegNeRF's depth smoothness and
    /// DVR's image-gradient loss need neighbours). A patch's top-left pixel is drawn
    /// uniformly over all positions where the patch fits, across all views. Rays are ordered
    /// patch by patch, row-major inside a patch: ray `p·k² + i·k + j` is pixel `(u₀ + j,
    /// v₀ + i)` of patch `p`, so `colors.reshape((count, k, k, 3))` gives the patches. The
    /// background colour is drawn per patch under [`Background::Random`].
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `count` if 0, `k` if 0 or larger than every view,
    /// and `count` if `count · k²` is above 2²⁸.
    pub fn patches(&mut self, count: usize, k: usize) -> Result<RayBatch> {
        if count == 0 {
            return Err(Error::invalid("count", "at least one patch", "0"));
        }
        let n = count
            .checked_mul(k)
            .and_then(|x| x.checked_mul(k))
            .unwrap_or(usize::MAX);
        if k == 0 {
            return Err(Error::invalid("k", "a patch side ≥ 1", "0"));
        }
        check_count(n, "count")?;
        let mut total = 0u64;
        let ends: Vec<u64> = self
            .dataset
            .views()
            .iter()
            .map(|v| {
                let (w, h, _) = v.image().size();
                if w >= k && h >= k {
                    total += ((w - k + 1) * (h - k + 1)) as u64;
                }
                total
            })
            .collect();
        if total == 0 {
            return Err(Error::invalid(
                "k",
                "a patch side that fits in at least one view",
                k.to_string(),
            ));
        }
        let mut picks = Vec::with_capacity(n);
        let mut bgs = Vec::with_capacity(n);
        for _ in 0..count {
            let i = self.rng.below(total);
            let view = ends.partition_point(|&e| e <= i);
            let start = if view == 0 { 0 } else { ends[view - 1] };
            let span = (self.dataset.views()[view].image().size().0 - k + 1) as u64;
            let local = i - start;
            let (u0, v0) = ((local % span) as usize, (local / span) as usize);
            let bg = self.backgrounds(1)[0];
            for i in 0..k {
                for j in 0..k {
                    picks.push((view, u0 + j, v0 + i));
                    bgs.push(bg);
                }
            }
        }
        gather(
            self.dataset,
            &picks,
            None,
            1,
            &bgs,
            &self.device,
            self.dtype,
        )
    }
}
