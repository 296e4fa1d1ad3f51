//! The minGRU's and minLSTM's inference updates ([`crate::ops::mingru`]) on burn's CUDA backend
//! (feature `cuda`) as one cubecl kernel each, recorded as a custom operation of burn's
//! fusion layer (how one joins the fusion stream: see `cublas.rs`).
//!
//! Why: composed from burn's operations the minGRU's update of a 256-scene call (`[640,000,
//! 32]` states) was 13 kernels in cubecl's profile of one H100 call: two slices of the
//! pre-activations, two fused element-wise kernels and nine unfused ones (the two sigmoids
//! through `exp` and `log`, the blend), about 1.0 ms timed alone, each pass reading and
//! writing the whole state (docs/speed.md, "Closed-loop rollouts on the device"). Here the
//! update reads the pre-activations and the previous state once and writes the new state:
//! the CPU's one pass (`cpu/mingru.rs`), with the same formulas. Autodiff backends keep the
//! composed form (`NetOps::mingru_update`), so training is unchanged.

use burn::cubecl::cuda::CudaRuntime;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Shape, TensorMetadata};
use burn_cubecl::cubecl;
use burn_fusion::stream::{Operation, OperationStreams};
use burn_fusion::FusionRuntime;
use burn_ir::{CustomOpIr, HandleContainer, OperationIr, TensorIr};
use cubecl::prelude::*;

use super::conv::{contiguous, elementwise, Cuda, Inner, Runtime};
use crate::ops::OpsError;

/// `1 / (1 + e^-x)`.
#[cube]
fn sigmoid<F: Float>(x: F) -> F {
    F::new(1.0) / (F::new(1.0) + F::exp(F::new(0.0) - x))
}

/// `g(x)`: `x + 0.5` for `x >= 0`, `sigmoid(x)` otherwise (`ops::mingru::g`).
#[cube]
fn g<F: Float>(x: F) -> F {
    let mut y = x + F::new(0.5);
    if x < F::new(0.0) {
        y = sigmoid::<F>(x);
    }
    y
}

/// One state element per thread of the minGRU's or the minLSTM's update (Feng et al. 2024,
/// "Were RNNs All We Needed?"), `p` the previous state (`h`, read only when `carried`, else
/// 0); `h`, `out` `[M, H]` and `pre` contiguous:
/// - minGRU (`lstm` false): `pre` `[M, 2H]` (`h~`, then the gate), `out = p + z (g(h~) - p)`,
///   `z = sigmoid(gate)`, i.e. `(1 - z) p + z g(h~)`;
/// - minLSTM with normalised gates (`lstm`): `pre` `[M, 3H]` (`h~`, `a`, `b`), `out = (v p +
///   u g(h~)) / (u + v)` with `u = e^s + e^(s - a)`, `v = e^s + e^(s - b)`, `s = min(a, b,
///   0)`: `f' p + i' g(h~)`, `(f', i') = (f, i) / (f + i)`, `f = sigmoid(a)`, `i =
///   sigmoid(b)`, with no positive exponent (`cpu/mingru.rs`'s `lstm_update`).
#[cube(launch)]
fn update_kernel<F: Float>(
    pre: &Tensor<F>,
    h: &Tensor<F>,
    out: &mut Tensor<F>,
    hidden: u32,
    #[comptime] lstm: bool,
    #[comptime] carried: bool,
    #[define(F)] _dtype: StorageType,
) {
    if ABSOLUTE_POS >= out.len() {
        terminate!();
    }
    let hidden = hidden as usize;
    let row = ABSOLUTE_POS / hidden;
    let j = ABSOLUTE_POS % hidden;
    let mut p = F::new(0.0);
    if carried {
        p = h[ABSOLUTE_POS];
    }
    if lstm {
        let base = row * 3 * hidden + j;
        let (a, b) = (pre[base + hidden], pre[base + 2 * hidden]);
        let mut s = F::new(0.0);
        if a < s {
            s = a;
        }
        if b < s {
            s = b;
        }
        let e = F::exp(s);
        let u = e + F::exp(s - a);
        let v = e + F::exp(s - b);
        out[ABSOLUTE_POS] = (v * p + u * g::<F>(pre[base])) / (u + v);
    } else {
        let base = row * 2 * hidden + j;
        let tilde = g::<F>(pre[base]);
        let z = sigmoid::<F>(pre[base + hidden]);
        out[ABSOLUTE_POS] = p + z * (tilde - p);
    }
}

/// Which cell's update an operation runs (`k`: pre-activation columns per state column).
#[derive(Clone, Copy, Debug)]
enum Cell {
    MinGru,
    MinLstm,
}

/// The recorded update: inputs `[pre]` or `[pre, h]`, output `[out]` of `[M, H]`.
#[derive(Debug)]
struct UpdateOp {
    desc: CustomOpIr,
    cell: Cell,
    hidden: usize,
}

impl Operation<Runtime> for UpdateOp {
    fn execute(&self, handles: &mut HandleContainer<<Runtime as FusionRuntime>::FusionHandle>) {
        let inputs = &self.desc.inputs;
        let pre = contiguous(handles.get_float_tensor::<Inner>(&inputs[0]));
        let carried = inputs.len() > 1;
        let h = match carried {
            true => contiguous(handles.get_float_tensor::<Inner>(&inputs[1])),
            false => pre.clone(),
        };
        let (client, dtype) = (pre.client.clone(), pre.dtype);
        let rows = pre.meta.shape()[0];
        let out = burn_cubecl::ops::numeric::empty_device_contiguous_dtype(
            client.clone(),
            pre.device.clone(),
            Shape::new([rows, self.hidden]),
            dtype,
        );
        let (count, dim) = elementwise(&client, rows * self.hidden);
        let hidden = (OpsError::fit_u32("state width", self.hidden))
            .unwrap_or_else(|e| e.raise("minGRU / minLSTM update kernel"));
        update_kernel::launch::<CudaRuntime>(
            &client,
            count,
            dim,
            pre.into_tensor_arg(),
            h.into_tensor_arg(),
            out.clone().into_tensor_arg(),
            hidden,
            matches!(self.cell, Cell::MinLstm),
            carried,
            dtype.into(),
        );
        handles.register_float_tensor::<Inner>(&self.desc.outputs[0].id, out);
    }
}

/// Records `cell`'s update of `pre` (`[M, k H]`) and `h` (`[M, H]`) -> `[M, H]`.
///
/// # Panics
/// `pre` is not `[M, k H]`, or `h` is not `[M, H]`.
fn record(cell: Cell, pre: FloatTensor<Cuda>, h: Option<FloatTensor<Cuda>>) -> FloatTensor<Cuda> {
    let k = match cell {
        Cell::MinGru => 2,
        Cell::MinLstm => 3,
    };
    let shape = pre.shape();
    assert!(
        shape.num_dims() == 2 && shape[1] % k == 0,
        "{cell:?} update: pre-activations {shape:?} are not [M, {k} H]"
    );
    let (rows, hidden) = (shape[0], shape[1] / k);
    if let Some(h) = &h {
        assert!(
            h.shape() == Shape::new([rows, hidden]),
            "{cell:?} update: state {:?} is not [{rows}, {hidden}]",
            h.shape()
        );
    }
    let client = pre.client.clone();
    let out = TensorIr::uninit(
        client.create_empty_handle(),
        Shape::new([rows, hidden]),
        pre.dtype(),
    );
    let inputs: Vec<FloatTensor<Cuda>> = std::iter::once(pre).chain(h).collect();
    let streams = OperationStreams::with_inputs(&inputs);
    let irs: Vec<TensorIr> = inputs.into_iter().map(|t| t.into_ir()).collect();
    let desc = CustomOpIr::new("minflow_minrnn_update", &irs, &[out]);
    let op = UpdateOp {
        desc: desc.clone(),
        cell,
        hidden,
    };
    client
        .register(streams, OperationIr::Custom(desc), op)
        .remove(0)
}

/// [`NetOps::mingru_update`](crate::ops::NetOps::mingru_update) on the GPU: `hg` `[M, 2H]`, `h`
/// `[M, H]` -> `[M, H]`, one kernel.
pub(crate) fn mingru_update(
    hg: FloatTensor<Cuda>,
    h: Option<FloatTensor<Cuda>>,
) -> FloatTensor<Cuda> {
    record(Cell::MinGru, hg, h)
}

/// [`NetOps::minlstm_update`](crate::ops::NetOps::minlstm_update) on the GPU: `hfi` `[M, 3H]`,
/// `h` `[M, H]` -> `[M, H]`, one kernel.
pub(crate) fn minlstm_update(
    hfi: FloatTensor<Cuda>,
    h: Option<FloatTensor<Cuda>>,
) -> FloatTensor<Cuda> {
    record(Cell::MinLstm, hfi, h)
}
