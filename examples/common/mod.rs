//! Set-up shared by the examples: the seeded model and its optimiser.
//!
//! Helpers that only some examples need live in sibling files that those examples
//! include themselves (`#[path = "common/cameras.rs"] mod cameras;`): `cameras.rs`
//! (cameras looking at the origin).
#![allow(dead_code)] // each example uses a part

use candle_core::{DType, Device};
use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarMap};
use neural_fields::nn::{build_seeded, mlp, Mlp, MlpConfig};

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
