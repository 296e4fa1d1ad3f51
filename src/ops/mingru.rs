//! The minGRU's activation `g` and its inference update (Feng et al. 2024, "Were RNNs All We
//! Needed?", minGRU): from the layer's pre-activations `[h~, gate]` and the previous hidden
//! state, `h = (1 - z) h_prev + z g(h~)` with `z = sigmoid(gate)` and `g(x) = x + 0.5` for
//! `x >= 0`, `sigmoid(x)` otherwise. Composed from burn's ops the update takes about ten
//! passes over the `[N, H]` state (two sigmoids through `exp` and `log`, a mask, the blend);
//! the CPU does it in one (`cpu/mingru.rs`; `perf` over `minflow eval` with
//! `models/all-grid-mingru-small`: 13 % of a step). Autodiff backends keep the composed form,
//! so training is unchanged. `model::minrnn` builds the minGRU on these.

use burn::tensor::activation::sigmoid;
use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Tensor, TensorPrimitive};

use super::NetOps;

/// `g(x)`: `x + 0.5` for `x >= 0`, `sigmoid(x)` otherwise (keeps the state positive).
pub fn g<B: Backend, const D: usize>(x: Tensor<B, D>) -> Tensor<B, D> {
    let pos = x.clone().greater_equal_elem(0.0);
    sigmoid(x.clone()).mask_where(pos, x + 0.5)
}

fn wrap<B: Backend>(x: FloatTensor<B>) -> Tensor<B, 2> {
    Tensor::from_primitive(TensorPrimitive::Float(x))
}

/// Composed minGRU update ([`NetOps::mingru_update`]'s default, in burn's ops).
///
/// # Shapes
/// - `hg`: `[M, 2H]` (`h~` in the first `H` columns, the gate's pre-activation after), `h`:
///   `[M, H]` -> `[M, H]`
pub(crate) fn composed_mingru_update<B: Backend>(
    hg: FloatTensor<B>,
    h: Option<FloatTensor<B>>,
) -> FloatTensor<B> {
    let hg = wrap::<B>(hg);
    let hidden = hg.dims()[1] / 2;
    let tilde = g(hg.clone().narrow(1, 0, hidden));
    let z = sigmoid(hg.narrow(1, hidden, hidden));
    let next = match h {
        Some(h) => (z.clone().neg() + 1.0) * wrap::<B>(h) + z * tilde,
        None => z * tilde,
    };
    next.into_primitive().tensor()
}

/// The minGRU update through [`NetOps::mingru_update`]: `hg` `[M, 2H]`, `h` `[M, H]` ->
/// `[M, H]`.
pub fn mingru_update<B: NetOps>(hg: Tensor<B, 2>, h: Option<Tensor<B, 2>>) -> Tensor<B, 2> {
    let out = B::mingru_update(
        hg.into_primitive().tensor(),
        h.map(|h| h.into_primitive().tensor()),
    );
    wrap::<B>(out)
}
