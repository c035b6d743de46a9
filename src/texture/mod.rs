//! Texture fields: colour as a function of the surface point (Texture Fields, DVR, IDR).
//!
//! A [`TextureField`] maps surface points `[N, 3]` — with, depending on the field, their
//! normals, the viewing directions, a feature vector from the geometry network, a shape
//! code and an image code — to RGB `[N, 3]` in `[0, 1]`, differentiable w.r.t. its
//! parameters and every input it reads. The inputs travel together in a
//! [`TextureInput`], so a renderer hands the same value to any texture field and each
//! field takes what it needs (and names what it misses).
//!
//! The networks, built on [`crate::nn`]'s blocks:
//! * [`TextureDecoder`]: the Texture Fields decoder (Oechsle et al. 2019), conditioned on
//!   a shape code and an image code;
//! * [`RenderingNet`]: IDR's rendering network (point, encoded view direction, normal,
//!   geometry feature);
//! * [`JointDecoder`]: DVR's decoder, one trunk for the occupancy logit and the colour
//!   (an implicit surface and a texture field at once).
//!
//! In a DVR/IDR training step the points are [`crate::dvr::SurfacePoints::points`], so a
//! photometric loss ([`crate::dvr::photometric_loss`], plus [`image_gradient_loss`] on
//! patches) reaches the geometry through `p̂` — and, for IDR's network, through the normal.
//!
//! ```
//! use candle_core::{DType, Device, Tensor};
//! use candle_nn::VarMap;
//! use neural_fields::nn::build_seeded;
//! use neural_fields::texture::{rendering_net, RenderingNetConfig, TextureField, TextureInput};
//!
//! let dev = Device::Cpu;
//! let config = RenderingNetConfig { feature_dim: 8, ..RenderingNetConfig::default() };
//! let varmap = VarMap::new();
//! let net = build_seeded(&varmap, DType::F32, &dev, 0, |vb| rendering_net(&config, vb))?;
//! let points = Tensor::zeros((5, 3), DType::F32, &dev)?;
//! let normals = Tensor::ones((5, 3), DType::F32, &dev)?;
//! let dirs = Tensor::ones((5, 3), DType::F32, &dev)?;
//! let features = Tensor::zeros((5, 8), DType::F32, &dev)?;
//! let input = TextureInput {
//!     normals: Some(&normals),
//!     view_dirs: Some(&dirs),
//!     features: Some(&features),
//!     ..TextureInput::new(&points)
//! };
//! let rgb = net.rgb(&input)?;                                  // [5, 3] in [0, 1]
//! assert_eq!(rgb.dims(), &[5, 3]);
//! // A missing input is an error that names it.
//! let err = net.rgb(&TextureInput::new(&points)).unwrap_err().to_string();
//! assert!(err.starts_with("view_dirs"));
//! # Ok::<(), neural_fields::Error>(())
//! ```

mod input;
mod losses;
mod networks;

pub use input::{TextureField, TextureInput};
pub use losses::image_gradient_loss;
pub use networks::{
    joint_decoder, rendering_net, texture_decoder, JointDecoder, RenderingNet, RenderingNetConfig,
    TextureDecoder, TextureDecoderConfig,
};

/// Vertex colours for a mesh: `texture` evaluated at the mesh's vertices in chunks of
/// `chunk` points, without graph, as `[V][3]` in `[0, 1]` (for
/// [`Mesh::colors`](crate::mesh::Mesh::colors), whose PLY writer stores them as `uchar`
/// red/green/blue that MeshLab and Blender show).
///
/// `inputs` builds the texture's inputs for a chunk of vertices `[n, 3]` (in `dtype` on
/// `device`) and returns the colours `[n, 3]`; for example
/// `|p| net.rgb(&TextureInput::new(p))`, or, for a field that reads normals and view
/// directions, the geometry's normals at `p` and the view directions `−n` (the surface
/// seen head-on).
///
/// # Errors
/// `chunk` 0; a closure result that is not `[n, 3]` or has non-finite values (naming
/// `colors`); errors of the closure.
pub fn vertex_colors(
    mesh: &crate::mesh::Mesh,
    chunk: usize,
    device: &candle_core::Device,
    dtype: candle_core::DType,
    mut inputs: impl FnMut(&candle_core::Tensor) -> crate::Result<candle_core::Tensor>,
) -> crate::Result<Vec<[f64; 3]>> {
    use crate::error::{check_shape, Dim, Error};
    if chunk == 0 {
        return Err(Error::invalid("chunk", "at least 1", "0"));
    }
    crate::error::check_dtype(dtype)?;
    let mut colors = Vec::with_capacity(mesh.vertices.len());
    for part in mesh.vertices.chunks(chunk) {
        let p = crate::mesh::points_to_tensor(part, device, dtype)?;
        let c = inputs(&p)?.detach();
        check_shape(&c, "colors", &[Dim::Is(part.len()), Dim::Is(3)])?;
        let rows = c.to_dtype(candle_core::DType::F64)?.to_vec2::<f64>()?;
        for row in rows {
            if row.iter().any(|v| !v.is_finite()) {
                return Err(Error::invalid("colors", "finite values", "NaN or infinity"));
            }
            colors.push([
                row[0].clamp(0.0, 1.0),
                row[1].clamp(0.0, 1.0),
                row[2].clamp(0.0, 1.0),
            ]);
        }
    }
    Ok(colors)
}
