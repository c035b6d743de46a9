//! The pointwise ResNet trunk shared by the decoders that add a conditioning code before
//! every block: the Texture Fields decoder, the Conv. ONet decoder and Occupancy Flow's
//! velocity field. It is built with or without those features; without any of them
//! nothing uses it.
#![cfg_attr(
    not(any(feature = "occupancy", feature = "texture", feature = "flow")),
    allow(dead_code)
)]

use crate::error::{Error, Result};
use candle_core::Tensor;
use candle_nn::{Init, Linear, Module, VarBuilder};

/// A linear layer `[out, in]` whose weight and bias start at zero.
fn zero_linear(input: usize, out: usize, vb: VarBuilder) -> Result<Linear> {
    let w = vb.get_with_hints((out, input), "weight", Init::Const(0.0))?;
    let b = vb.get_with_hints(out, "bias", Init::Const(0.0))?;
    Ok(Linear::new(w, Some(b)))
}

/// `x: [N, in] → [N, out]`:
///
/// ```text
/// h = W_p x + b_p,
/// for each block i:  h ← h + W_cᵢ c + b_cᵢ  (when there is a code);
///                    h ← h + W₁ᵢ relu(W₀ᵢ relu(h) + b₀ᵢ) + b₁ᵢ,
/// y = W_out relu(h) + b_out,
/// ```
///
/// with `W₁ᵢ` and the output layer zero at initialisation (every block starts as the
/// identity and the output at 0). Variables: `fc_p`, `block{i}.fc0`, `block{i}.fc1`,
/// `code{i}` (when `code_dim > 0`) and `fc_out`. Candle ops on any device, f32 or f64;
/// differentiable w.r.t. the parameters, `x` and the code.
#[derive(Clone, Debug)]
pub(crate) struct ResnetFc {
    fc_p: Linear,
    fc_code: Vec<Linear>,
    blocks: Vec<(Linear, Linear)>,
    fc_out: Linear,
}

impl ResnetFc {
    /// Builds the trunk; `hidden` and `blocks` name their config fields in errors.
    pub(crate) fn new(
        input: usize,
        hidden: usize,
        blocks: usize,
        code_dim: usize,
        out: usize,
        vb: &VarBuilder,
    ) -> Result<Self> {
        for (name, v) in [("config.hidden", hidden), ("config.blocks", blocks)] {
            if v == 0 {
                return Err(Error::invalid(name, "at least 1", "0"));
            }
        }
        let params = hidden.saturating_mul(hidden).saturating_mul(2);
        crate::limits::check_layers("config.blocks", blocks, params, vb.dtype().size_in_bytes())?;
        let mut trunk = Vec::with_capacity(blocks);
        let mut fc_code = Vec::new();
        for i in 0..blocks {
            let bvb = vb.pp(format!("block{i}"));
            trunk.push((
                candle_nn::linear(hidden, hidden, bvb.pp("fc0"))?,
                zero_linear(hidden, hidden, bvb.pp("fc1"))?,
            ));
            if code_dim > 0 {
                fc_code.push(candle_nn::linear(
                    code_dim,
                    hidden,
                    vb.pp(format!("code{i}")),
                )?);
            }
        }
        Ok(Self {
            fc_p: candle_nn::linear(input, hidden, vb.pp("fc_p"))?,
            fc_code,
            blocks: trunk,
            fc_out: zero_linear(hidden, out, vb.pp("fc_out"))?,
        })
    }

    /// `y = f(x, c)` as above; `code: [N or 1, code_dim]` (broadcast over the rows of `x`)
    /// is used when the trunk was built with a code and ignored otherwise.
    pub(crate) fn forward(&self, x: &Tensor, code: Option<&Tensor>) -> Result<Tensor> {
        let mut h = self.fc_p.forward(x)?;
        for (i, (fc0, fc1)) in self.blocks.iter().enumerate() {
            if let (Some(c), Some(fc)) = (code, self.fc_code.get(i)) {
                h = h.broadcast_add(&fc.forward(c)?)?;
            }
            let r = fc0.forward(&h.relu()?)?;
            h = (h + fc1.forward(&r.relu()?)?)?;
        }
        Ok(self.fc_out.forward(&h.relu()?)?)
    }
}
