//! The U-Net of the grid architecture (Ronneberger et al. 2015, as NeuralMPM uses it on its
//! grid: Rochman-Sharabi et al. 2024, arXiv 2408.15753, section 3): `levels` resolutions, two
//! 3x3 convolutions + SiLU per level on the way down (2x2 average pooling between levels) and
//! on the way up (nearest 2x upsampling, concatenated with the skip of the same level), then a
//! 1x1 convolution to the output channels. Widths double per level up to 4x the first.
//!
//! The weights are burn's `Conv2d`s; by default they run as im2col + one matrix product
//! ([`NetOps::linear_forward`]): the nine shifted copies of the zero-padded input side by side
//! (Chellapilla et al. 2006, "High Performance Convolutional Neural Networks for Document
//! Processing"), times the weight as a `[9 C_in, C_out]` matrix, im2col one kernel where the
//! backend has it ([`NetOps::NATIVE_CONV_OPS`]: the CPU and CUDA) and nine shifted slices
//! elsewhere. burn's own convolution made the U-Net 8x slower on a GPU (its gradients) and took
//! 59 % of a CPU inference step (burn-ndarray's direct loop; perf, `eval` of a grid model). For
//! inference the CPU runs the 3x3 convolutions by Winograd F(4x4, 3x3) instead
//! ([`NetOps::conv3x3_forward`]). [`ConvKernel`] picks one of three equal ways per model (tests
//! check them against each other): burn's convolution, im2col by a row gather (or the backend's
//! kernel), im2col by nine shifted slices.

use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::PaddingConfig2d;
use burn::tensor::backend::Backend;
use burn::tensor::{Tensor, TensorPrimitive};

use crate::ops::{pool2 as pool, silu, upsample2 as upsample, NetOps, PreparedWeights};

/// How the U-Net's convolutions are computed; the weights and the result are the same.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ConvKernel {
    /// `Gather` where the backend has single-kernel im2col / col2im
    /// ([`NetOps::NATIVE_CONV_OPS`]: the CPU and CUDA), `Shift` elsewhere (on an H100, `bench
    /// train --arch grid --stages`: a batch-16 U-Net forward + backward took 14 ms with
    /// `Shift`, 121 ms with `Burn`, whose convolution gradients dominate; on the CPU `Gather`
    /// beat `Shift`, 0.48 s to 0.65 s, and `Burn` took 14 s).
    #[default]
    Auto,
    /// burn's `Conv2d::forward` on the permuted (channels-first) view.
    Burn,
    /// im2col through [`NetOps::im2col`] where it is one kernel (else as one row gather,
    /// `select`, of a zero-padded copy), then one product through
    /// [`NetOps::linear_forward`]; the concatenation of the U-Net's parts is never built.
    Gather,
    /// im2col as the nine shifted slices of the zero-padded input concatenated along the
    /// channels, then one product through [`NetOps::linear_forward`] (no gather, so its
    /// gradient needs no scatter).
    Shift,
}

impl ConvKernel {
    /// Every kernel, for flags.
    pub const ALL: [ConvKernel; 4] = [Self::Auto, Self::Burn, Self::Gather, Self::Shift];

    /// The flag value.
    pub fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Burn => "burn",
            Self::Gather => "gather",
            Self::Shift => "shift",
        }
    }

    /// The kernel named `name`, if any.
    pub fn parse(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }

    /// What `Auto` means on backend `B`.
    pub fn resolve<B: NetOps>(self) -> Self {
        match self {
            Self::Auto if B::NATIVE_CONV_OPS => Self::Gather,
            Self::Auto => Self::Shift,
            k => k,
        }
    }
}

/// U-Net sizes.
#[derive(Config, Debug)]
pub struct UNetConfig {
    /// Input channels.
    pub channels_in: usize,
    /// Output channels.
    pub channels_out: usize,
    /// Width of the first level.
    #[config(default = 32)]
    pub width: usize,
    /// Resolutions (the grid size must be divisible by `2^(levels - 1)`).
    #[config(default = 4)]
    pub levels: usize,
    /// How the convolutions are computed.
    #[config(default = "ConvKernel::Auto")]
    pub conv: ConvKernel,
}

impl UNetConfig {
    /// Width of level `l`: `width * 2^l`, at most `4 width`.
    pub fn level_width(&self, l: usize) -> usize {
        self.width << l.min(2)
    }

    /// A U-Net with fresh weights (burn's default initialisation).
    pub fn init<B: Backend>(&self, device: &B::Device) -> UNet<B> {
        let levels = self.levels.max(1);
        let down = (0..levels)
            .map(|l| {
                let c_in = if l == 0 {
                    self.channels_in
                } else {
                    self.level_width(l - 1)
                };
                ConvBlock::new(c_in, self.level_width(l), self.conv, device)
            })
            .collect();
        let up = (0..levels - 1)
            .map(|l| {
                ConvBlock::new(
                    self.level_width(l + 1) + self.level_width(l),
                    self.level_width(l),
                    self.conv,
                    device,
                )
            })
            .collect();
        UNet {
            down,
            up,
            head: Conv2dConfig::new([self.level_width(0), self.channels_out], [1, 1]).init(device),
            kernel: self.conv,
        }
    }
}

/// Two 3x3 convolutions (same padding), each followed by SiLU.
#[derive(Module, Debug)]
pub struct ConvBlock<B: Backend> {
    a: Conv2d<B>,
    b: Conv2d<B>,
    #[module(skip)]
    kernel: ConvKernel,
    /// The inference backend's prepared weights of `a` and `b` (the CPU's Winograd
    /// transform), owned here so they live and die with the weights.
    #[module(skip)]
    prepared: [PreparedWeights; 2],
}

impl<B: Backend> ConvBlock<B> {
    fn new(c_in: usize, c_out: usize, kernel: ConvKernel, device: &B::Device) -> Self {
        let conv = |i, o| {
            Conv2dConfig::new([i, o], [3, 3])
                .with_padding(PaddingConfig2d::Same)
                .init(device)
        };
        Self {
            a: conv(c_in, c_out),
            b: conv(c_out, c_out),
            kernel,
            prepared: Default::default(),
        }
    }
}

impl<B: Backend> ConvBlock<B> {
    /// This block with `extra` more input channels, appended after the existing ones, whose
    /// weights in the first convolution are zero (the block computes what it did).
    fn widen_input(self, extra: usize) -> Self {
        let weight = self.a.weight.val(); // [C_out, C_in, k, k]
        let [c_out, _, k, _] = weight.dims();
        let zeros = Tensor::zeros([c_out, extra, k, k], &weight.device());
        let weight = Tensor::cat(vec![weight, zeros], 1).detach();
        Self {
            a: Conv2d {
                weight: burn::module::Param::from_tensor(weight),
                ..self.a
            },
            ..self
        }
    }
}

impl<B: NetOps> ConvBlock<B> {
    fn forward(&self, x: Tensor<B, 4>) -> Tensor<B, 4> {
        self.forward_parts(vec![x])
    }

    /// The block on the channel concatenation of `parts` (see [`conv_parts`]).
    fn forward_parts(&self, parts: Vec<Tensor<B, 4>>) -> Tensor<B, 4> {
        let k = self.kernel;
        let a = conv_silu_parts_prepared(&self.a, parts, k, &self.prepared[0]);
        conv_silu_parts_prepared(&self.b, vec![a], k, &self.prepared[1])
    }
}

/// `conv.forward` for a stride-1 convolution with a 1x1 or 3x3 kernel and same padding, on a
/// channels-last tensor, computed as `kernel` says (see [`ConvKernel`]).
///
/// # Shapes
/// - `x`: `[B, H, W, C_in]` -> `[B, H, W, C_out]`
pub fn conv<B: NetOps>(conv: &Conv2d<B>, x: Tensor<B, 4>, kernel: ConvKernel) -> Tensor<B, 4> {
    conv_parts(conv, vec![x], kernel)
}

/// `[k^2 C_in, C_out]`: the weight of `conv` for channels `offset..offset + c` as the matrix
/// an im2col product needs (row `(ky k + kx) c + i` multiplies channel i at offset (ky, kx)).
fn im2col_weight<B: Backend>(conv: &Conv2d<B>, offset: usize, c: usize) -> Tensor<B, 2> {
    let weight = conv.weight.val(); // [C_out, C_in, k, k]
    let [c_out, _, k, _] = weight.dims();
    weight
        .narrow(1, offset, c)
        .permute([2, 3, 1, 0])
        .reshape([k * k * c, c_out])
}

/// `im2col(x, k) @ matrix + bias` through [`NetOps::im2col_linear`].
fn im2col_product<B: NetOps>(
    x: Tensor<B, 4>,
    matrix: Tensor<B, 2>,
    bias: Option<Tensor<B, 1>>,
    k: usize,
) -> Tensor<B, 2> {
    let y = B::im2col_linear(
        x.into_primitive().tensor(),
        matrix.into_primitive().tensor(),
        bias.map(|b| b.into_primitive().tensor()),
        k,
    );
    Tensor::from_primitive(TensorPrimitive::Float(y))
}

/// `rows @ matrix + bias` through [`NetOps::linear_forward`].
fn product<B: NetOps>(
    rows: Tensor<B, 2>,
    matrix: Tensor<B, 2>,
    bias: Option<Tensor<B, 1>>,
) -> Tensor<B, 2> {
    let y = B::linear_forward(
        rows.into_primitive().tensor(),
        matrix.into_primitive().tensor(),
        bias.map(|b| b.into_primitive().tensor()),
    );
    Tensor::from_primitive(TensorPrimitive::Float(y))
}

/// [`ConvKernel::Shift`]: the nine (or one) shifted slices of the zero-padded `x`
/// concatenated along the channels, times the weight matrix.
fn conv_shift<B: NetOps>(conv: &Conv2d<B>, x: Tensor<B, 4>) -> Tensor<B, 4> {
    let [b, h, w, c] = x.dims();
    let k = conv.weight.dims()[2];
    let c_out = conv.weight.dims()[0];
    let cols = if k == 1 {
        x
    } else {
        let x = crate::ops::pad_hw(x, k / 2);
        let shifted = (0..k * k)
            .map(|s| x.clone().narrow(1, s / k, h).narrow(2, s % k, w))
            .collect();
        Tensor::cat(shifted, 3)
    };
    let rows = cols.reshape([b * h * w, k * k * c]);
    let bias = conv.bias.as_ref().map(|p| p.val());
    product(rows, im2col_weight(conv, 0, c), bias).reshape([b, h, w, c_out])
}

/// `silu(conv_parts(conv, parts, kernel))`, the SiLU applied as the convolution writes its
/// output where the backend's inference kernel does that ([`NetOps::conv3x3_forward`]: the
/// CPU's Winograd output transform, which saves a pass over the output).
///
/// # Shapes
/// As [`conv_parts`].
pub fn conv_silu_parts<B: NetOps>(
    conv: &Conv2d<B>,
    parts: Vec<Tensor<B, 4>>,
    kernel: ConvKernel,
) -> Tensor<B, 4> {
    conv_silu_parts_prepared(conv, parts, kernel, &PreparedWeights::default())
}

/// [`conv_silu_parts`] with the backend's prepared weights of `conv` kept in `prepared`.
fn conv_silu_parts_prepared<B: NetOps>(
    conv: &Conv2d<B>,
    parts: Vec<Tensor<B, 4>>,
    kernel: ConvKernel,
    prepared: &PreparedWeights,
) -> Tensor<B, 4> {
    if kernel.resolve::<B>() == ConvKernel::Gather && B::NATIVE_CONV_OPS {
        if let Some(y) = conv3x3_forward(conv, &parts, true, prepared) {
            return y;
        }
    }
    silu(conv_parts_prepared(conv, parts, kernel, prepared))
}

/// [`NetOps::conv3x3_forward`] of `conv` (then SiLU when `silu`); None for another kernel
/// size or where the backend has no such kernel.
fn conv3x3_forward<B: NetOps>(
    conv: &Conv2d<B>,
    parts: &[Tensor<B, 4>],
    silu: bool,
    prepared: &PreparedWeights,
) -> Option<Tensor<B, 4>> {
    if conv.weight.dims()[2] != 3 {
        return None;
    }
    let inputs: Vec<_> = parts
        .iter()
        .map(|x| x.clone().into_primitive().tensor())
        .collect();
    let bias = conv
        .bias
        .as_ref()
        .map(|p| p.val().into_primitive().tensor());
    let weight = conv.weight.val().into_primitive().tensor();
    let y = B::conv3x3_forward(&inputs, &weight, bias.as_ref(), silu, prepared)?;
    Some(Tensor::from_primitive(TensorPrimitive::Float(y)))
}

/// [`conv`] of the channel concatenation of `parts` (the U-Net's `[upsampled, skip]`). With
/// [`ConvKernel::Gather`] the concatenation is never built: each part is multiplied by its
/// slice of the weight and the products are summed (burn-ndarray's concatenation along the
/// last axis copies element by element, as slowly as the convolution loop it replaces).
///
/// # Shapes
/// - `parts`: `[B, H, W, C_p]` each, `sum C_p = C_in` -> `[B, H, W, C_out]`
pub fn conv_parts<B: NetOps>(
    conv: &Conv2d<B>,
    parts: Vec<Tensor<B, 4>>,
    kernel: ConvKernel,
) -> Tensor<B, 4> {
    conv_parts_prepared(conv, parts, kernel, &PreparedWeights::default())
}

/// [`conv_parts`] with the backend's prepared weights of `conv` kept in `prepared`.
fn conv_parts_prepared<B: NetOps>(
    conv: &Conv2d<B>,
    mut parts: Vec<Tensor<B, 4>>,
    kernel: ConvKernel,
    prepared: &PreparedWeights,
) -> Tensor<B, 4> {
    let kernel = kernel.resolve::<B>();
    if kernel != ConvKernel::Gather {
        let x = match parts.len() {
            1 => parts.pop().expect("one part"),
            _ => Tensor::cat(parts, 3),
        };
        if kernel == ConvKernel::Shift {
            return conv_shift(conv, x);
        }
        return conv.forward(x.permute([0, 3, 1, 2])).permute([0, 2, 3, 1]);
    }
    let [b, h, w, _] = parts[0].dims();
    let device = parts[0].device();
    let [c_out, c_in, k, _] = conv.weight.dims();
    if B::NATIVE_CONV_OPS {
        return conv_parts_native(conv, parts, [b, h, w, c_out, c_in, k], prepared);
    }
    let index = (k > 1).then(|| im2col_index::<B>(b, h, w, k, &device));
    let mut bias = conv.bias.as_ref().map(|p| p.val());
    let mut offset = 0;
    let mut sum: Option<Tensor<B, 2>> = None;
    for x in parts {
        let c = x.dims()[3];
        let rows = x.reshape([b * h * w, c]);
        let cols = match &index {
            None => rows,
            Some(index) => Tensor::cat(vec![rows, Tensor::zeros([1, c], &device)], 0)
                .select(0, index.clone())
                .reshape([b * h * w, k * k * c]),
        };
        let y = product(cols, im2col_weight(conv, offset, c), bias.take());
        offset += c;
        sum = Some(match sum {
            Some(acc) => acc + y,
            None => y,
        });
    }
    sum.expect("at least one part").reshape([b, h, w, c_out])
}

/// [`ConvKernel::Gather`] on a backend with native im2col ([`NetOps::NATIVE_CONV_OPS`]):
/// a 3x3 kernel through [`NetOps::conv3x3_forward`] where the backend has it (the CPU's
/// inference: Winograd F(4x4, 3x3)); otherwise each part through [`NetOps::im2col_linear`]
/// (columns ordered as burn's weight `[C_out, C_in, k, k]` flattens, so the weight matrix
/// is a transposed view of it; in training the columns are recomputed), the products summed.
fn conv_parts_native<B: NetOps>(
    conv: &Conv2d<B>,
    parts: Vec<Tensor<B, 4>>,
    [b, h, w, c_out, c_in, k]: [usize; 6],
    prepared: &PreparedWeights,
) -> Tensor<B, 4> {
    if let Some(y) = conv3x3_forward(conv, &parts, false, prepared) {
        return y;
    }
    let weight = conv.weight.val().reshape([c_out, c_in * k * k]);
    let mut bias = conv.bias.as_ref().map(|p| p.val());
    let mut offset = 0;
    let mut sum: Option<Tensor<B, 2>> = None;
    for x in parts {
        let c = x.dims()[3];
        let matrix = weight
            .clone()
            .narrow(1, offset * k * k, c * k * k)
            .transpose();
        let y = match k {
            1 => product(x.reshape([b * h * w, c]), matrix, bias.take()),
            _ => im2col_product(x, matrix, bias.take(), k),
        };
        offset += c;
        sum = Some(match sum {
            Some(acc) => acc + y,
            None => y,
        });
    }
    sum.expect("at least one part").reshape([b, h, w, c_out])
}

/// The im2col gather of a `k x k` same-padding convolution over `[B, H, W]` positions: for
/// output row `(b H + y) W + x` and offset `s = ky k + kx`, entry `9 row + s` is the input row
/// `(b H + y + ky - k/2) W + x + kx - k/2`, or `B H W` (a zero row appended to the input)
/// outside the grid. Built per call, not cached: one integer per gathered row, a small
/// fraction of the gather of `C` channels it indexes (and only on backends without native
/// im2col, where `--conv gather` was asked for).
fn im2col_index<B: Backend>(
    b: usize,
    h: usize,
    w: usize,
    k: usize,
    device: &B::Device,
) -> Tensor<B, 1, burn::tensor::Int> {
    let zero = (b * h * w) as i64;
    let half = (k / 2) as isize;
    let mut index = Vec::with_capacity(b * h * w * k * k);
    for bb in 0..b {
        for y in 0..h as isize {
            for x in 0..w as isize {
                for s in 0..(k * k) as isize {
                    let (yy, xx) = (y + s / k as isize - half, x + s % k as isize - half);
                    index.push(
                        if yy < 0 || xx < 0 || yy >= h as isize || xx >= w as isize {
                            zero
                        } else {
                            ((bb * h) as isize * w as isize + yy * w as isize + xx) as i64
                        },
                    );
                }
            }
        }
    }
    let n = index.len();
    Tensor::from_data(burn::tensor::TensorData::new(index, [n]), device)
}

/// The network; see the module doc.
#[derive(Module, Debug)]
pub struct UNet<B: Backend> {
    down: Vec<ConvBlock<B>>,
    up: Vec<ConvBlock<B>>,
    /// The 1 x 1 output convolution (grown by `super::grow`).
    pub(super) head: Conv2d<B>,
    #[module(skip)]
    kernel: ConvKernel,
}

impl<B: Backend> UNet<B> {
    /// This U-Net with `extra` more input channels after the existing ones, their weights
    /// zero: the output is unchanged for any values in them (see
    /// [`super::GridModel::with_reference`]).
    pub fn widen_input(mut self, extra: usize) -> Self {
        if let Some(first) = self.down.first_mut() {
            *first = first.clone().widen_input(extra);
        }
        self
    }
}

impl<B: NetOps> UNet<B> {
    /// Channels last throughout (the grid as P2G leaves it), so the CPU's convolutions never
    /// copy a transposed layout.
    ///
    /// # Shapes
    /// - `x`: `[B, n, n, C_in]` -> `[B, n, n, C_out]`
    pub fn forward(&self, x: Tensor<B, 4>) -> Tensor<B, 4> {
        let mut skips = Vec::with_capacity(self.down.len());
        let mut x = x;
        for (l, block) in self.down.iter().enumerate() {
            if l > 0 {
                x = pool(x);
            }
            x = block.forward(x);
            skips.push(x.clone());
        }
        skips.pop();
        for block in self.up.iter().rev() {
            let skip = skips.pop().expect("one skip per upper level");
            x = block.forward_parts(vec![upsample(x), skip]);
        }
        conv(&self.head, x, self.kernel)
    }
}
