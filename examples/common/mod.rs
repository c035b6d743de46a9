//! Set-up shared by the examples: the seeded model and its optimiser.
//!
//! Helpers that only some examples need live in sibling files that those examples
//! include themselves (`#[path = "common/cameras.rs"] mod cameras;`): `cameras.rs`
//! (cameras looking at the origin).
#![allow(dead_code)] // each example uses a part

use candle_core::{DType, Device};
use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarBuilder, VarMap};
use neural_fields::encoding::{hash_grid, FrequencyEncoding, HashGridConfig, PointEncoding};
use neural_fields::nn::{build_seeded, mlp, Mlp, MlpConfig};

/// The position encoding chosen by `--encoding pe|hash`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PositionEncoding {
    /// A frequency encoding (the example's own number of frequencies).
    Pe,
    /// instant-NGP's multiresolution hash grid over the example's scene box.
    Hash,
}

impl PositionEncoding {
    /// The value of `--encoding`: `pe` or `hash`.
    pub fn parse(value: &str) -> Result<Self, String> {
        match value {
            "pe" => Ok(Self::Pe),
            "hash" => Ok(Self::Hash),
            other => Err(format!("--encoding: pe or hash, not {other}")),
        }
    }

    /// The name on the command line (and in `metrics.json`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Pe => "pe",
            Self::Hash => "hash",
        }
    }

    /// The encoding of 3-D points: `Pe` is the frequency encoding with `frequencies`
    /// octaves; `Hash` is [`HashGridConfig::default`] (16 levels of 2 features, 2^`log2`
    /// rows) over the box `[lo, hi]` at resolutions 16 to `finest`, its table built in
    /// `vb.pp("grid")`.
    pub fn build(
        self,
        frequencies: usize,
        lo: [f64; 3],
        hi: [f64; 3],
        log2: u32,
        finest: f64,
        vb: &VarBuilder,
    ) -> neural_fields::Result<PointEncoding> {
        Ok(match self {
            Self::Pe => PointEncoding::Frequency(FrequencyEncoding::new(3, frequencies)?),
            Self::Hash => PointEncoding::HashGrid(hash_grid(
                &HashGridConfig {
                    lo: lo.to_vec(),
                    hi: hi.to_vec(),
                    log2_table_size: log2,
                    finest_resolution: finest,
                    ..HashGridConfig::default()
                },
                vb.pp("grid"),
            )?),
        })
    }
}

/// The model of an example: an [`Mlp`] built from `config` with its weights drawn from
/// `seed` (so that every run is the same), and Adam at learning rate `lr` (AdamW without
/// weight decay) over its parameters.
pub fn seeded_mlp(
    config: &MlpConfig,
    seed: u64,
    lr: f64,
    device: &Device,
    dtype: DType,
) -> neural_fields::Result<(Mlp, AdamW)> {
    let varmap = VarMap::new();
    let net = build_seeded(&varmap, dtype, device, seed, |vb| mlp(config, vb))?;
    Ok((net, adam(&varmap, lr)?))
}

/// Adam (AdamW without weight decay) at learning rate `lr` over every variable of
/// `varmap`.
pub fn adam(varmap: &VarMap, lr: f64) -> neural_fields::Result<AdamW> {
    let params = ParamsAdamW {
        lr,
        weight_decay: 0.0,
        ..Default::default()
    };
    Ok(AdamW::new(varmap.all_vars(), params)?)
}

/// Rows `idx` of `t` (`idx` on the host).
pub fn rows(t: &candle_core::Tensor, idx: &[u32]) -> neural_fields::Result<candle_core::Tensor> {
    let i = candle_core::Tensor::from_slice(idx, idx.len(), t.device())?;
    Ok(t.index_select(&i, 0)?)
}

/// Rays `idx` of `rays` and their range on each.
pub fn select(
    rays: &neural_fields::camera::Rays,
    range: &neural_fields::camera::Intersection,
    idx: &[u32],
) -> neural_fields::Result<(
    neural_fields::camera::Rays,
    neural_fields::camera::Intersection,
)> {
    let picked = neural_fields::camera::Rays::new(
        rows(rays.origins(), idx)?,
        rows(rays.directions(), idx)?,
    )?;
    let range = neural_fields::camera::Intersection {
        near: rows(&range.near, idx)?,
        far: rows(&range.far, idx)?,
        hit: rows(&range.hit, idx)?,
    };
    Ok((picked, range))
}
