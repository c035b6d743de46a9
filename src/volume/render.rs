//! Whole images from any per-ray renderer: one chunked, supersampled loop over a camera's
//! pixels.

use crate::camera::{Camera, PixelFilter, Rays};
use crate::error::{check_float, Error, Result};
use candle_core::{DType, Device, Tensor};

/// How [`render_image`] covers a camera's pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageConfig {
    /// Rays per pixel side `k`: each pixel is the mean of `k × k` rays through the
    /// quadrature points of `filter` ([`Camera::subpixel_grid`]), 1 to 64. Default 1.
    pub supersample: usize,
    /// The pixel filter the sub-pixel rays sample. With the default
    /// [`PixelFilter::Box`] and `supersample = 1`: one ray through each pixel centre.
    pub filter: PixelFilter,
    /// Rays per call of the renderer (rounded down to whole pixels, at least one pixel):
    /// bounds the memory of one forward pass. Default 4096.
    pub chunk: usize,
}

impl Default for ImageConfig {
    fn default() -> Self {
        ImageConfig {
            supersample: 1,
            filter: PixelFilter::Box,
            chunk: 4096,
        }
    }
}

/// Renders a whole image of `camera` in chunks of rays, `k × k` rays per pixel averaged.
///
/// The rays are those of [`Camera::subpixel_grid`]`(k, config.filter, device, dtype)`
/// through [`Camera::rays_for_pixels`] (`k = config.supersample`), pixel-major, in
/// chunks of at most `config.chunk` rays that hold whole pixels (`⌊chunk / k²⌋·k²`,
/// at least `k²`), each ray carrying the cone radius of its sub-pixel (the pixel's
/// divided by `k`). `render` maps each chunk of `n` rays to `N` per-ray outputs, each
/// `[n]` or `[n, C]` (float, any `C`): colour, depth, opacity, normals, masks. Output
/// `j` of pixel `(u, v)` is the mean of `render`'s output `j` over that pixel's `k²`
/// rays (the filter's quadrature, [`Camera::subpixel_grid`]):
///
/// ```text
/// image_j[v, u] = (1/k²) Σ_{s < k²} render(rays)_j[(v·W + u)·k² + s]
/// ```
///
/// Returns the `N` images, `[H, W]` or `[H, W, C]` (the shape of each output without
/// its ray axis), in each output's dtype and on its device. Every chunk's outputs are
/// detached before the next call, so no graph is kept: an evaluation renderer, not
/// differentiable. A quantity that is not linear in the rays (a depth normalised by the
/// opacity, a depth masked where the opacity is low) is best formed per ray inside
/// `render`, or from the averaged images after.
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use neural_fields::camera::{ray_sphere, Camera, Convention, Intrinsics};
/// use neural_fields::glam::DVec3;
/// use neural_fields::volume::{render_image, ImageConfig};
///
/// let k = Intrinsics::from_fov_y(8, 6, 0.8)?;
/// let cam = Camera::look_at(k, DVec3::new(0.0, 0.0, 3.0), DVec3::ZERO, DVec3::Y, Convention::OpenGl)?;
/// let config = ImageConfig { supersample: 2, chunk: 16, ..ImageConfig::default() };
/// // Per ray: whether it hits the unit sphere, and the distance to it.
/// let [coverage, near] = render_image(&cam, &config, &Device::Cpu, DType::F32, |rays| {
///     let hit = ray_sphere(rays, [0.0; 3], 1.0)?;
///     Ok([hit.hit.to_dtype(DType::F32)?, hit.near])
/// })?;
/// assert_eq!(coverage.dims(), &[6, 8]);
/// assert_eq!(coverage.to_vec2::<f32>()?[3][4], 1.0); // the centre of the image
/// assert_eq!(near.dims(), &[6, 8]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `config.supersample` unless in `1..=64`,
/// `config.chunk` when 0, `dtype` unless f32 or f64, `filter` for a Blackman–Harris
/// half width outside `(0, 64]`; naming `camera` when its `width · height · supersample²`
/// rays (8 values of `dtype` each) pass the allocation limit of 2³³ bytes (8 GiB), checked
/// before anything is allocated; naming `render` when an output is not float, or not `[n]`
/// or `[n, C]` for its chunk of `n` rays; whatever `render` returns.
pub fn render_image<const N: usize, F>(
    camera: &Camera,
    config: &ImageConfig,
    device: &Device,
    dtype: DType,
    mut render: F,
) -> Result<[Tensor; N]>
where
    F: FnMut(&Rays) -> Result<[Tensor; N]>,
{
    let k = config.supersample;
    if !(1..=64).contains(&k) {
        return Err(Error::invalid(
            "config.supersample",
            "1 to 64 rays per pixel side",
            k.to_string(),
        ));
    }
    if config.chunk == 0 {
        return Err(Error::invalid("config.chunk", "at least 1 ray", "0"));
    }
    config.filter.validate()?;
    let (w, h) = (camera.intrinsics().width, camera.intrinsics().height);
    let per_pixel = k * k;
    // Per ray: its sub-pixel position, origin and direction (8 values of `dtype`).
    crate::limits::check_bytes("camera", &[w, h, per_pixel, 8], dtype.size_in_bytes())?;
    let pixels = camera.subpixel_grid(k, config.filter, device, dtype)?;
    let n = pixels.dim(0)?;
    let chunk = (config.chunk / per_pixel).max(1) * per_pixel;
    let mut parts: Vec<Vec<Tensor>> = vec![Vec::new(); N];
    for start in (0..n).step_by(chunk) {
        let len = chunk.min(n - start);
        let mut rays = camera.rays_for_pixels(&pixels.narrow(0, start, len)?)?;
        if let (true, Some(r)) = (k > 1, rays.radii()) {
            // Each sub-pixel ray's cone covers 1/k of the pixel's width.
            let r = (r / k as f64)?;
            rays = rays.with_radii(r)?;
        }
        let outputs = render(&rays)?;
        for (j, out) in outputs.into_iter().enumerate() {
            parts[j].push(pixel_means(&out.detach(), len, per_pixel, j)?);
        }
    }
    let images = parts
        .into_iter()
        .map(|p| -> Result<Tensor> {
            let all = Tensor::cat(&p, 0)?;
            let mut shape = vec![h, w];
            shape.extend_from_slice(&all.dims()[1..]);
            Ok(all.reshape(shape)?)
        })
        .collect::<Result<Vec<Tensor>>>()?;
    images.try_into().map_err(|v: Vec<Tensor>| {
        Error::invalid(
            "render",
            format!("{N} outputs"),
            format!("{} images", v.len()),
        )
    })
}

/// The mean over each run of `per_pixel` rows of one output `[n]` or `[n, C]` of a chunk
/// of `n` rays: `[n / per_pixel]` or `[n / per_pixel, C]`. Errors name `render` (output
/// `j`).
fn pixel_means(out: &Tensor, n: usize, per_pixel: usize, j: usize) -> Result<Tensor> {
    check_float(out, "render")?;
    let dims = out.dims();
    let ok = match dims {
        [m] | [m, _] => *m == n,
        _ => false,
    };
    if !ok {
        return Err(Error::invalid(
            "render",
            format!("outputs [{n}] or [{n}, C] for a chunk of {n} rays"),
            format!("shape {dims:?} for output {j}"),
        ));
    }
    let c = dims.get(1).copied().unwrap_or(1);
    let px = n / per_pixel;
    let means = out.reshape((px, per_pixel, c))?.mean(1)?;
    Ok(if dims.len() == 1 {
        means.squeeze(1)?
    } else {
        means
    })
}
