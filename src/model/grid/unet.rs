//! The U-Net of the grid architecture (Ronneberger et al. 2015, as NeuralMPM uses it on its
//! grid: Rochman-Sharabi et al. 2024, arXiv 2408.15753, section 3): `levels` resolutions,
//! two 3x3 convolutions + SiLU per level on the way down (2x2 average pooling between
//! levels) and on the way up (nearest 2x upsampling, concatenated with the skip of the same
//! level), then a 1x1 convolution to the output channels. Widths double per level up to 4x
//! the first. The weights are burn's `Conv2d`s. On a GPU they run as burn's convolution; on
//! the CPU, where burn-ndarray's direct convolution loop took 59 % of an inference step
//! (perf, `eval` of a grid model), as im2col + one matrix product through the CPU's gemm
//! kernels ([`FusedElu::linear_forward`]): the nine shifted copies of the zero-padded
//! input side by side (Chellapilla et al. 2006, "High Performance Convolutional Neural
//! Networks for Document Processing"), times the weight as a `[9 C_in, C_out]` matrix.

use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::PaddingConfig2d;
use burn::tensor::activation::silu;
use burn::tensor::backend::Backend;
use burn::tensor::{Tensor, TensorPrimitive};

use crate::model::FusedElu;

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
                ConvBlock::new(c_in, self.level_width(l), device)
            })
            .collect();
        let up = (0..levels - 1)
            .map(|l| {
                ConvBlock::new(
                    self.level_width(l + 1) + self.level_width(l),
                    self.level_width(l),
                    device,
                )
            })
            .collect();
        UNet {
            down,
            up,
            head: Conv2dConfig::new([self.level_width(0), self.channels_out], [1, 1]).init(device),
        }
    }
}

/// Two 3x3 convolutions (same padding), each followed by SiLU.
#[derive(Module, Debug)]
pub struct ConvBlock<B: Backend> {
    a: Conv2d<B>,
    b: Conv2d<B>,
}

impl<B: Backend> ConvBlock<B> {
    fn new(c_in: usize, c_out: usize, device: &B::Device) -> Self {
        let conv = |i, o| {
            Conv2dConfig::new([i, o], [3, 3])
                .with_padding(PaddingConfig2d::Same)
                .init(device)
        };
        Self {
            a: conv(c_in, c_out),
            b: conv(c_out, c_out),
        }
    }
}

impl<B: FusedElu> ConvBlock<B> {
    fn forward(&self, x: Tensor<B, 4>) -> Tensor<B, 4> {
        self.forward_parts(vec![x])
    }

    /// The block on the channel concatenation of `parts` (see [`conv_parts`]).
    fn forward_parts(&self, parts: Vec<Tensor<B, 4>>) -> Tensor<B, 4> {
        silu(conv(&self.b, silu(conv_parts(&self.a, parts))))
    }
}

/// `conv.forward` for a stride-1 convolution with a 1x1 or 3x3 kernel and same padding, on a
/// channels-last tensor: burn's convolution on backends without
/// [`FusedElu::SEQUENTIAL_SCAN`] (the GPU; its input is the permuted view), im2col + gemm on
/// the CPU (see the module doc).
///
/// # Shapes
/// - `x`: `[B, H, W, C_in]` -> `[B, H, W, C_out]`
pub fn conv<B: FusedElu>(conv: &Conv2d<B>, x: Tensor<B, 4>) -> Tensor<B, 4> {
    conv_parts(conv, vec![x])
}

/// [`conv`] of the channel concatenation of `parts` (the U-Net's `[upsampled, skip]`). On the
/// CPU the concatenation is never built: each part is multiplied by its slice of the weight
/// and the products are summed (burn-ndarray's concatenation along the last axis copies
/// element by element, as slowly as the convolution loop it replaces).
///
/// # Shapes
/// - `parts`: `[B, H, W, C_p]` each, `sum C_p = C_in` -> `[B, H, W, C_out]`
pub fn conv_parts<B: FusedElu>(conv: &Conv2d<B>, mut parts: Vec<Tensor<B, 4>>) -> Tensor<B, 4> {
    if !B::SEQUENTIAL_SCAN {
        let x = match parts.len() {
            1 => parts.pop().expect("one part"),
            _ => Tensor::cat(parts, 3),
        };
        return conv.forward(x.permute([0, 3, 1, 2])).permute([0, 2, 3, 1]);
    }
    let [b, h, w, _] = parts[0].dims();
    let device = parts[0].device();
    let weight = conv.weight.val(); // [C_out, C_in, k, k]
    let [c_out, _, k, _] = weight.dims();
    let index = (k > 1).then(|| im2col_index::<B>(b, h, w, k, &device));
    let mut bias = conv
        .bias
        .as_ref()
        .map(|p| p.val().into_primitive().tensor());
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
        // Row (ky k + kx) C + i multiplies channel i of this part at offset (ky, kx).
        let matrix = weight
            .clone()
            .narrow(1, offset, c)
            .permute([2, 3, 1, 0])
            .reshape([k * k * c, c_out]);
        offset += c;
        let y = B::linear_forward(
            cols.into_primitive().tensor(),
            matrix.into_primitive().tensor(),
            bias.take(),
        );
        let y = Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(y));
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
/// outside the grid. Built once per shape and thread.
fn im2col_index<B: Backend>(
    b: usize,
    h: usize,
    w: usize,
    k: usize,
    device: &B::Device,
) -> Tensor<B, 1, burn::tensor::Int> {
    use std::cell::RefCell;
    use std::collections::HashMap;
    thread_local! {
        static CACHE: RefCell<HashMap<[usize; 4], Vec<i64>>> = RefCell::new(HashMap::new());
    }
    let index = CACHE.with(|cache| {
        cache
            .borrow_mut()
            .entry([b, h, w, k])
            .or_insert_with(|| {
                let zero = (b * h * w) as i64;
                let half = (k / 2) as isize;
                let mut index = Vec::with_capacity(b * h * w * k * k);
                for bb in 0..b {
                    for y in 0..h as isize {
                        for x in 0..w as isize {
                            for s in 0..(k * k) as isize {
                                let (yy, xx) =
                                    (y + s / k as isize - half, x + s % k as isize - half);
                                index.push(
                                    if yy < 0 || xx < 0 || yy >= h as isize || xx >= w as isize {
                                        zero
                                    } else {
                                        ((bb * h) as isize * w as isize + yy * w as isize + xx)
                                            as i64
                                    },
                                );
                            }
                        }
                    }
                }
                index
            })
            .clone()
    });
    let n = index.len();
    Tensor::from_data(burn::tensor::TensorData::new(index, [n]), device)
}

/// The network; see the module doc.
#[derive(Module, Debug)]
pub struct UNet<B: Backend> {
    down: Vec<ConvBlock<B>>,
    up: Vec<ConvBlock<B>>,
    head: Conv2d<B>,
}

impl<B: FusedElu> UNet<B> {
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
        conv(&self.head, x)
    }
}

/// Nearest-neighbour 2x upsampling by broadcasting (`[B, h, w, C]` -> `[B, 2h, 2w, C]`), in
/// plain tensor operations so every backend differentiates it.
fn upsample<B: Backend>(x: Tensor<B, 4>) -> Tensor<B, 4> {
    let [b, h, w, c] = x.dims();
    x.reshape([b, h, 1, w, 1, c])
        .expand([b, h, 2, w, 2, c])
        .reshape([b, 2 * h, 2 * w, c])
}

/// 2x2 average pooling, stride 2 (`[B, h, w, C]` -> `[B, h/2, w/2, C]`).
fn pool<B: Backend>(x: Tensor<B, 4>) -> Tensor<B, 4> {
    let [b, h, w, c] = x.dims();
    x.reshape([b, h / 2, 2, w / 2, 2, c])
        .mean_dim(4)
        .mean_dim(2)
        .reshape([b, h / 2, w / 2, c])
}
