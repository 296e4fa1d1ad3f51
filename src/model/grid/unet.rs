//! The U-Net of the grid architecture (Ronneberger et al. 2015, as NeuralMPM uses it on its
//! grid: Rochman-Sharabi et al. 2024, arXiv 2408.15753, section 3): `levels` resolutions,
//! two 3x3 convolutions + SiLU per level on the way down (2x2 average pooling between
//! levels) and on the way up (nearest 2x upsampling, concatenated with the skip of the same
//! level), then a 1x1 convolution to the output channels. Widths double per level up to 4x
//! the first. burn's `Conv2d`; nothing custom.

use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::PaddingConfig2d;
use burn::tensor::activation::silu;
use burn::tensor::backend::Backend;
use burn::tensor::module::avg_pool2d;
use burn::tensor::Tensor;

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

    fn forward(&self, x: Tensor<B, 4>) -> Tensor<B, 4> {
        silu(self.b.forward(silu(self.a.forward(x))))
    }
}

/// The network; see the module doc.
#[derive(Module, Debug)]
pub struct UNet<B: Backend> {
    down: Vec<ConvBlock<B>>,
    up: Vec<ConvBlock<B>>,
    head: Conv2d<B>,
}

impl<B: Backend> UNet<B> {
    /// # Shapes
    /// - `x`: `[B, C_in, n, n]` -> `[B, C_out, n, n]`
    pub fn forward(&self, x: Tensor<B, 4>) -> Tensor<B, 4> {
        let mut skips = Vec::with_capacity(self.down.len());
        let mut x = x;
        for (l, block) in self.down.iter().enumerate() {
            if l > 0 {
                x = avg_pool2d(x, [2, 2], [2, 2], [0, 0], true, false);
            }
            x = block.forward(x);
            skips.push(x.clone());
        }
        skips.pop();
        for block in self.up.iter().rev() {
            let skip = skips.pop().expect("one skip per upper level");
            x = block.forward(Tensor::cat(vec![upsample(x), skip], 1));
        }
        self.head.forward(x)
    }
}

/// Nearest-neighbour 2x upsampling by broadcasting (`[B, C, h, w]` -> `[B, C, 2h, 2w]`), in
/// plain tensor operations so every backend differentiates it.
fn upsample<B: Backend>(x: Tensor<B, 4>) -> Tensor<B, 4> {
    let [b, c, h, w] = x.dims();
    x.reshape([b, c, h, 1, w, 1])
        .expand([b, c, h, 2, w, 2])
        .reshape([b, c, 2 * h, 2 * w])
}
