//! The model's building blocks against references: minGRU and minLSTM parallel scans equal
//! their step-by-step recurrences (outputs and gradients, windows of 1, 2, 17 and 256, with
//! and without a carried state); GRU and LSTM match steps computed by hand; the encoder's
//! pool-then-project rewrite equals the plain encoder; minLSTM's normalised gates keep finite
//! values and gradients when both gates are closed.

use burn::backend::{Autodiff, NdArray};
use burn::module::Param;
use burn::nn::Linear;
use burn::tensor::{Distribution, Tensor, TensorData};
use minflow::model::minrnn::{normalized_gates, MinGru, MinLstm};
use minflow::model::paper::encoder::{Encoder, LastActivation, Pooling};
use minflow::model::rnn::{Gru, Lstm};

type B = Autodiff<NdArray<f32>>;

fn max_diff<const D: usize>(a: Tensor<B, D>, b: Tensor<B, D>) -> f32 {
    let a: Vec<f32> = a.into_data().to_vec().unwrap();
    let b: Vec<f32> = b.into_data().to_vec().unwrap();
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// Runs `step` over the window and stacks the outputs.
fn stepped<F>(x: Tensor<B, 3>, h0: Option<Tensor<B, 2>>, step: F) -> (Tensor<B, 3>, Tensor<B, 2>)
where
    F: Fn(Tensor<B, 2>, Option<Tensor<B, 2>>) -> (Tensor<B, 2>, Tensor<B, 2>),
{
    let [b, t, d] = x.dims();
    let mut h = h0;
    let mut outs = Vec::new();
    for k in 0..t {
        let (o, next) = step(x.clone().narrow(1, k, 1).reshape([b, d]), h);
        outs.push(o);
        h = Some(next);
    }
    (Tensor::stack(outs, 1), h.unwrap())
}

/// `log_scan`: the log-space parallel scan (what CUDA trains with); else `forward`, which on
/// this CPU backend is the fused linear-space pass.
fn check_scan(kind: &str, t: usize, with_state: bool, log_scan: bool) {
    let device = Default::default();
    let (b, d, h) = (3, 5, 7);
    let x =
        Tensor::<B, 3>::random([b, t, d], Distribution::Normal(0.0, 1.5), &device).require_grad();
    let h0 = with_state
        .then(|| Tensor::<B, 2>::random([b, h], Distribution::Uniform(0.1, 2.0), &device));
    let weights = Tensor::<B, 3>::random([b, t, d], Distribution::Normal(0.0, 1.0), &device);
    let (par, seq, gp, gs, gw_par, gw_seq) = match kind {
        "mingru" => {
            let m = MinGru::<B>::new(d, h, d, &device);
            let (p, _) = if log_scan {
                m.forward_log_scan(x.clone(), h0.clone())
            } else {
                m.forward(x.clone(), h0.clone())
            };
            let (s, _) = stepped(x.clone(), h0.clone(), |xk, hk| m.step(xk, hk));
            let gp = (p.clone() * weights.clone()).sum().backward();
            let gs = (s.clone() * weights.clone()).sum().backward();
            let w = &m.to_hidden_and_gate.weight;
            (
                p,
                s,
                x.grad(&gp).unwrap(),
                x.grad(&gs).unwrap(),
                w.grad(&gp).unwrap(),
                w.grad(&gs).unwrap(),
            )
        }
        _ => {
            let m = MinLstm::<B>::new(d, h, d, &device);
            let (p, _) = if log_scan {
                m.forward_log_scan(x.clone(), h0.clone())
            } else {
                m.forward(x.clone(), h0.clone())
            };
            let (s, _) = stepped(x.clone(), h0.clone(), |xk, hk| m.step(xk, hk));
            let gp = (p.clone() * weights.clone()).sum().backward();
            let gs = (s.clone() * weights.clone()).sum().backward();
            let w = &m.to_hidden_and_gates.weight;
            (
                p,
                s,
                x.grad(&gp).unwrap(),
                x.grad(&gs).unwrap(),
                w.grad(&gp).unwrap(),
                w.grad(&gs).unwrap(),
            )
        }
    };
    let out = max_diff(par, seq);
    assert!(
        out <= 1e-5,
        "{kind} T={t} state={with_state} log={log_scan}: outputs differ by {out}"
    );
    let dx = max_diff(Tensor::<B, 3>::from_inner(gp), Tensor::from_inner(gs));
    assert!(
        dx <= 1e-5,
        "{kind} T={t} log={log_scan}: input gradients differ by {dx}"
    );
    let dw = max_diff(
        Tensor::<B, 2>::from_inner(gw_par),
        Tensor::from_inner(gw_seq),
    );
    // Weight gradients sum over B x T terms; compare relative to their size.
    assert!(
        dw <= 1e-5 * (t as f32).max(1.0),
        "{kind} T={t} log={log_scan}: weight gradients differ by {dw}"
    );
}

#[test]
fn mingru_parallel_scan_equals_recurrence() {
    for t in [1, 2, 17, 256] {
        for log_scan in [true, false] {
            check_scan("mingru", t, false, log_scan);
            check_scan("mingru", t, true, log_scan);
        }
    }
}

#[test]
fn minlstm_parallel_scan_equals_recurrence() {
    for t in [1, 2, 17, 256] {
        for log_scan in [true, false] {
            check_scan("minlstm", t, false, log_scan);
            check_scan("minlstm", t, true, log_scan);
        }
    }
}

/// `f' = f / (f + i)` against f64 over pre-activations from -90 to 30, where both sigmoids
/// underflow in f32 at the low end; its gradient `d f' / d a = f' (1 - f') (1 - f)` stays finite.
#[test]
fn minlstm_normalized_gates_are_finite_when_both_gates_close() {
    let device = Default::default();
    let pairs: Vec<(f32, f32)> = (-9..=3)
        .flat_map(|p| [-20.0f32, -3.0, 0.0, 2.5].map(|d| (p as f32 * 10.0, p as f32 * 10.0 + d)))
        .collect();
    let a: Vec<f32> = pairs.iter().map(|p| p.0).collect();
    let b: Vec<f32> = pairs.iter().map(|p| p.1).collect();
    let at = Tensor::<B, 1>::from_floats(a.as_slice(), &device).require_grad();
    let bt = Tensor::<B, 1>::from_floats(b.as_slice(), &device).require_grad();
    let (f, i) = normalized_gates(at.clone(), bt.clone());
    let grads = f.clone().sum().backward();
    let ga: Vec<f32> = at.grad(&grads).unwrap().into_data().to_vec().unwrap();
    let f: Vec<f32> = f.into_data().to_vec().unwrap();
    let i: Vec<f32> = i.into_data().to_vec().unwrap();
    let log_sigmoid = |x: f64| -(1.0 + (-x).exp()).ln();
    for (k, &(a, b)) in pairs.iter().enumerate() {
        let (a, b) = (f64::from(a), f64::from(b));
        // f' = 1 / (1 + exp(log i - log f)), exact in f64 for these ranges.
        let want = 1.0 / (1.0 + (log_sigmoid(b) - log_sigmoid(a)).exp());
        let want_grad = want * (1.0 - want) * (1.0 - 1.0 / (1.0 + (-a).exp()));
        assert!(
            (f64::from(f[k]) - want).abs() < 1e-6 && (f64::from(i[k]) - (1.0 - want)).abs() < 1e-6,
            "a {a} b {b}: f' {} i' {}, want {want}",
            f[k],
            i[k]
        );
        assert!(
            ga[k].is_finite() && (f64::from(ga[k]) - want_grad).abs() < 1e-6,
            "a {a} b {b}: df'/da {} want {want_grad}",
            ga[k]
        );
    }
}

fn set(linear: &mut Linear<B>, weight: &[f32], rows: usize, cols: usize, bias: Option<&[f32]>) {
    let device = Default::default();
    linear.weight = Param::from_tensor(Tensor::from_data(
        TensorData::new(weight.to_vec(), [rows, cols]),
        &device,
    ));
    linear.bias = bias.map(|b| {
        Param::from_tensor(Tensor::from_data(
            TensorData::new(b.to_vec(), [b.len()]),
            &device,
        ))
    });
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// GRU with width 1, input 1: weights chosen by hand, one step from h = 0.5 at x = 2.
#[test]
fn gru_matches_a_step_by_hand() {
    let device = Default::default();
    let mut gru = Gru::<B>::new(1, 1, &device);
    // x -> [z, r, h~]: W = [0.5, -1.0, 0.25], b = [0.1, 0.2, -0.3]
    set(
        &mut gru.input,
        &[0.5, -1.0, 0.25],
        1,
        3,
        Some(&[0.1, 0.2, -0.3]),
    );
    // h -> [z, r]: U = [0.3, 0.7]; r h -> h~: U_h = 2.0
    set(&mut gru.recurrent_gates, &[0.3, 0.7], 1, 2, None);
    set(&mut gru.recurrent_candidate, &[2.0], 1, 1, None);
    let (x, h) = (2.0f64, 0.5f64);
    let z = sigmoid(0.5 * x + 0.1 + 0.3 * h); // sigmoid(1.25)
    let r = sigmoid(-x + 0.2 + 0.7 * h); // sigmoid(-1.45)
    let cand = (0.25 * x - 0.3 + 2.0 * r * h).tanh();
    let expected = (1.0 - z) * h + z * cand;
    let got = gru.step(
        Tensor::from_data([[x as f32]], &device),
        Some(Tensor::from_data([[h as f32]], &device)),
    );
    let got: Vec<f32> = got.into_data().to_vec().unwrap();
    assert!(
        (got[0] as f64 - expected).abs() < 1e-6,
        "{got:?} vs {expected}"
    );
}

/// LSTM with width 1, input 1: one step from (h, c) = (0.5, -0.25) at x = 1.5.
#[test]
fn lstm_matches_a_step_by_hand() {
    let device = Default::default();
    let mut lstm = Lstm::<B>::new(1, 1, &device);
    // x -> [i, f, o, c~]
    set(
        &mut lstm.input,
        &[0.4, -0.6, 1.0, 0.8],
        1,
        4,
        Some(&[0.0, 1.0, -0.5, 0.1]),
    );
    set(&mut lstm.recurrent, &[0.2, 0.3, -0.4, 0.5], 1, 4, None);
    let (x, h, c) = (1.5f64, 0.5f64, -0.25f64);
    let i = sigmoid(0.4 * x + 0.2 * h);
    let f = sigmoid(-0.6 * x + 1.0 + 0.3 * h);
    let o = sigmoid(1.0 * x - 0.5 - 0.4 * h);
    let cand = (0.8 * x + 0.1 + 0.5 * h).tanh();
    let c_next = f * c + i * cand;
    let h_next = o * c_next.tanh();
    let state = minflow::model::rnn::LstmState {
        h: Tensor::from_data([[h as f32]], &device),
        c: Tensor::from_data([[c as f32]], &device),
    };
    let out = lstm.step(Tensor::from_data([[x as f32]], &device), Some(state));
    let got_h: Vec<f32> = out.h.into_data().to_vec().unwrap();
    let got_c: Vec<f32> = out.c.into_data().to_vec().unwrap();
    assert!((got_h[0] as f64 - h_next).abs() < 1e-6 && (got_c[0] as f64 - c_next).abs() < 1e-6);
}

/// With no final activation and mean pooling, projecting after pooling equals the plain
/// encoder (the ~200x cheaper path), outputs and the gradients of input and both layers'
/// weights and biases (on this CPU backend the first layer, ELU and the mean are one fused
/// op with its own backward).
#[test]
fn pool_then_project_equals_plain_encoder() {
    let device = Default::default();
    let enc = Encoder::<B>::new(5, 32, 48, LastActivation::None, Pooling::Mean, &device);
    assert!(enc.project_after_pool);
    let x = Tensor::<B, 3>::random([4, 300, 5], Distribution::Uniform(-1.0, 1.0), &device)
        .require_grad();
    let (fused, plain) = (enc.forward(x.clone()), enc.forward_unfused(x.clone()));
    assert_same_function(&x, fused, plain, &[&enc.first, &enc.second], 1e-5);
    let elu = Encoder::<B>::new(5, 32, 48, LastActivation::Elu, Pooling::Mean, &device);
    assert!(!elu.project_after_pool);
}

/// The fused ELU (one pass forward, output-only backward) equals burn's composed ELU, values
/// and gradients, on both the autodiff and the plain CPU backend.
#[test]
fn fused_elu_equals_composed_elu() {
    let device = Default::default();
    let x = Tensor::<B, 3>::random([3, 50, 7], Distribution::Uniform(-4.0, 4.0), &device)
        .require_grad();
    let w = Tensor::<B, 3>::random([3, 50, 7], Distribution::Normal(0.0, 1.0), &device);
    let fused = minflow::ops::elu(x.clone());
    let composed = burn::tensor::activation::elu(x.clone(), 1.0);
    assert!(max_diff(fused.clone(), composed.clone()) <= 1e-6);
    let gf = x.grad(&(fused * w.clone()).sum().backward()).unwrap();
    let gc = x.grad(&(composed * w).sum().backward()).unwrap();
    let d = max_diff(Tensor::<B, 3>::from_inner(gf), Tensor::from_inner(gc));
    assert!(d <= 1e-6, "gradients differ by {d}");
    let plain =
        Tensor::<NdArray<f32>, 2>::random([64, 9], Distribution::Uniform(-3.0, 3.0), &device);
    let a: Vec<f32> = minflow::ops::elu(plain.clone())
        .into_data()
        .to_vec()
        .unwrap();
    let b: Vec<f32> = burn::tensor::activation::elu(plain, 1.0)
        .into_data()
        .to_vec()
        .unwrap();
    assert!(a.iter().zip(&b).all(|(p, q)| (p - q).abs() <= 1e-6));
}

/// The fused dense layer (gemm, bias and ELU in one pass, one autodiff node) equals burn's
/// `Linear` + ELU in outputs and in the gradients of input, weight and bias: 3-D input
/// (rows from two leading dims), with and without bias, with and without ELU, on a size
/// that takes the multi-threaded gemm path and on a one-row step (the streamed path).
#[test]
fn fused_linear_equals_burns_linear() {
    use burn::nn::LinearConfig;
    let device = Default::default();
    for (rows, d_in, d_out) in [(2 * 300, 40, 70), (1, 33, 21)] {
        for bias in [true, false] {
            for with_elu in [true, false] {
                let l: Linear<B> = LinearConfig::new(d_in, d_out).with_bias(bias).init(&device);
                let lead = if rows == 1 { 1 } else { 2 };
                let x = Tensor::<B, 3>::random(
                    [lead, rows / lead, d_in],
                    Distribution::Uniform(-2.0, 2.0),
                    &device,
                )
                .require_grad();
                let w = Tensor::<B, 3>::random(
                    [lead, rows / lead, d_out],
                    Distribution::Normal(0.0, 1.0),
                    &device,
                );
                let (fused, plain) = if with_elu {
                    (
                        minflow::ops::linear_elu(&l, x.clone()),
                        burn::tensor::activation::elu(l.forward(x.clone()), 1.0),
                    )
                } else {
                    (minflow::ops::linear(&l, x.clone()), l.forward(x.clone()))
                };
                let d = max_diff(fused.clone(), plain.clone());
                assert!(
                    d <= 1e-5,
                    "outputs differ by {d} ({rows}, bias {bias}, elu {with_elu})"
                );
                let gf = (fused * w.clone()).sum().backward();
                let gp = (plain * w).sum().backward();
                let (xf, xp) = (x.grad(&gf).unwrap(), x.grad(&gp).unwrap());
                let d = max_diff(Tensor::<B, 3>::from_inner(xf), Tensor::from_inner(xp));
                assert!(d <= 1e-4, "input gradients differ by {d}");
                let wf = l.weight.val().grad(&gf).unwrap();
                let wp = l.weight.val().grad(&gp).unwrap();
                let d = max_diff(Tensor::<B, 2>::from_inner(wf), Tensor::from_inner(wp));
                assert!(d <= 1e-3, "weight gradients differ by {d}");
                if let Some(b) = &l.bias {
                    let bf = b.val().grad(&gf).unwrap();
                    let bp = b.val().grad(&gp).unwrap();
                    let d = max_diff(Tensor::<B, 1>::from_inner(bf), Tensor::from_inner(bp));
                    assert!(d <= 1e-3, "bias gradients differ by {d}");
                }
            }
        }
    }
}

/// The dense layer + ELU + mean over particles as one autodiff node (the GPU path of the
/// paper's encoder) equals the composed layer, ELU and `mean_dim`, in values and in the
/// gradients of input, weight and bias.
#[test]
fn linear_elu_mean_node_equals_composed() {
    use minflow::ops::{elu, linear_elu_mean_pool};
    let device = Default::default();
    let layer = burn::nn::LinearConfig::new(16, 24).init::<B>(&device);
    let x = Tensor::<B, 3>::random([3, 200, 16], Distribution::Uniform(-1.0, 1.0), &device)
        .require_grad();
    let fused = linear_elu_mean_pool(&layer, x.clone());
    let plain = elu(layer.forward(x.clone())).mean_dim(1).reshape([3, 24]);
    assert_same_function(&x, fused, plain, &[&layer], 1e-6);
}

/// `fused` and `plain`, two computations of `[M, W]` from `x`, agree in values (within
/// `tol`) and in the gradients of a random projection of them with respect to `x` (`tol`)
/// and to each layer's weight and bias (1e-4: sums over hundreds of particles in different
/// orders round to ~1e-5 of their size in f32).
fn assert_same_function(
    x: &Tensor<B, 3>,
    fused: Tensor<B, 2>,
    plain: Tensor<B, 2>,
    layers: &[&Linear<B>],
    tol: f32,
) {
    let d = max_diff(fused.clone(), plain.clone());
    assert!(d <= tol, "values differ by {d}");
    let w = Tensor::<B, 2>::random(fused.dims(), Distribution::Normal(0.0, 1.0), &x.device());
    let (gf, gp) = (
        (fused * w.clone()).sum().backward(),
        (plain * w).sum().backward(),
    );
    let d = max_diff(
        Tensor::<B, 3>::from_inner(x.grad(&gf).unwrap()),
        Tensor::from_inner(x.grad(&gp).unwrap()),
    );
    assert!(d <= tol, "input gradients differ by {d}");
    for l in layers {
        let (a, b) = (
            l.weight.val().grad(&gf).unwrap(),
            l.weight.val().grad(&gp).unwrap(),
        );
        let d = max_diff(Tensor::<B, 2>::from_inner(a), Tensor::from_inner(b));
        assert!(d <= 1e-4, "weight gradients differ by {d}");
        let bias = l.bias.as_ref().unwrap().val();
        let (a, b) = (bias.grad(&gf).unwrap(), bias.grad(&gp).unwrap());
        let d = max_diff(Tensor::<B, 1>::from_inner(a), Tensor::from_inner(b));
        assert!(d <= 1e-4, "bias gradients differ by {d}");
    }
}
