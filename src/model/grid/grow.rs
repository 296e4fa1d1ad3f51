//! Growing a trained grid model into a larger one that predicts exactly what it did until it
//! is trained further (`train --init-from`): reference channels, temporal bundling, rest-shape
//! features, a grid velocity update. Also moving a model onto another network grid, which
//! keeps its weights but not its predictions ([`GridModel::with_grid`]). New inputs get zero weights, new outputs start at zero
//! (or, for bundling, as copies), so fine-tuning starts from the parent's predictions.

use burn::module::Param;
use burn::nn::conv::Conv2d;
use burn::nn::{Initializer, LinearConfig};
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;

use super::unet::UNet;
use super::{Deformation, GridModel, Update, REST_FEATURES};
use crate::ops::NetOps;

impl<B: NetOps> GridModel<B> {
    /// This model with [`super::GridConfig::reference`] on: the U-Net's first convolution
    /// gets two input channels (the displacement from the reference position) whose weights
    /// start at zero, so the result predicts exactly what `self` does until it is trained
    /// further (`train --init-from` a model without them). A model that has them is returned
    /// as is. Grow the reference before the rest shape (its channels come first).
    pub fn with_reference(self) -> Self {
        if self.reference {
            return self;
        }
        Self {
            unet: self.unet.widen_input(2),
            reference: true,
            ..self
        }
    }

    /// This model on an `n x n` network grid ([`super::GridConfig::grid`]). Every weight is
    /// the same: the U-Net is convolutional and the transfers take any grid, so a model
    /// trained on one grid runs (and is fine-tuned, `train --grid N --init-from`) on
    /// another. Its predictions change: the mass a cell holds, the reference channel
    /// `(x - X) n` and the wall masks all scale with `n`. At 40,000 particles the network grid
    /// 64 of a model trained on 32 gives a sixth of its avg20 (docs/grid.md, "The network's
    /// grid at scale").
    ///
    /// `n` must be a grid [`super::GridConfig`] accepts for the U-Net's levels (a multiple of
    /// `2^(levels - 1)`, at least 8); `train` checks its `--grid` before this runs.
    pub fn with_grid(self, n: usize) -> Self {
        Self { n, ..self }
    }

    /// This model clamping its predicted positions into the MPM box of the grid `g`
    /// ([`super::GridConfig::box_grid`]; 0: its network grid's): the same weights. `train
    /// --box-grid G --init-from` starts from this.
    pub fn with_box_grid(self, g: usize) -> Self {
        Self {
            box_grid: g,
            ..self
        }
    }

    /// This model taking `s` network substeps per frame ([`super::GridConfig::substeps`]):
    /// the same weights, its velocity change spread over the substeps. `train --substeps S
    /// --init-from` a trained single-frame model starts from this. A bundled model is
    /// returned as is (`train` refuses substeps with a bundle before this runs).
    pub fn with_substeps(self, s: usize) -> Self {
        if self.bundle != 1 || s == 0 {
            return self;
        }
        Self {
            substeps: s,
            ..self
        }
    }

    /// This model with the message passing `config` describes
    /// ([`super::GridConfig::interaction`]), fresh weights whose output layer starts at zero,
    /// so it predicts exactly what `self` does until it is trained further (`train
    /// --interaction R --init-from` a model without it). A model that has message passing, or
    /// a `config` without it, returns `self` as is.
    pub fn with_interaction(self, config: &super::GridConfig) -> Self {
        if self.interaction.is_some() {
            return self;
        }
        let d_u = config.latent + config.own_features();
        let device = self.head_out.weight.device();
        Self {
            interaction: config.interaction(d_u, &device),
            ..self
        }
    }

    /// This single-frame model as a bundled one predicting `k` frames per call
    /// ([`super::GridConfig::bundle`]): the U-Net's output head is tiled `k` times, so every
    /// frame of a bundle starts out reading the same latent field at the particle's position
    /// after the frames before it (the single-frame model's prediction, applied again where
    /// the particle went). `train --bundle K --init-from` a single-frame model starts from
    /// this. A model that is already bundled, `k` = 1, or a model with a grid update (grow
    /// the bundle first) is returned as is.
    pub fn with_bundle(self, k: usize) -> Self {
        if self.bundle != 1 || k <= 1 || self.update != Update::Free {
            return self;
        }
        Self {
            unet: self.unet.tile_output(k),
            bundle: k,
            ..self
        }
    }

    /// This model with [`super::GridConfig::rest_shape`] on: 6 more U-Net input channels and
    /// the rest-shape features' own head layer, all with zero weights, so it predicts what
    /// `self` does until trained further. A model that has them is returned as is.
    pub fn with_rest_shape(self) -> Self {
        if self.rest_in.is_some() {
            return self;
        }
        let hidden = self.head_a.weight.dims()[1];
        let device = self.head_a.weight.device();
        let layer = LinearConfig::new(REST_FEATURES, hidden)
            .with_initializer(Initializer::Zeros)
            .init(&device);
        Self {
            unet: self.unet.widen_input(REST_FEATURES),
            rest_in: Some(layer),
            ..self
        }
    }

    /// This free-update model with the particle update `update`
    /// ([`super::GridConfig::update`]): the U-Net gets two more output channels per bundled
    /// frame, the velocity-change field, with zero weights. With [`Update::GridHead`] the
    /// result predicts what `self` does (the head goes on, the field adds 0); with
    /// [`Update::Grid`] it starts at `dv = dv_mean` (the head is dropped). A model whose
    /// update is not [`Update::Free`], or `update` = Free, is returned as is.
    pub fn with_update(self, update: Update) -> Self {
        if self.update != Update::Free || update == Update::Free {
            return self;
        }
        Self {
            unet: self.unet.widen_output(2 * self.bundle),
            update,
            ..self
        }
    }

    /// This model with CPU inference's per-particle host passes on or off (`false`: the
    /// tensor path everywhere; for the test that holds the two equal and for measuring them).
    pub fn with_host_pass(self, host_pass: bool) -> Self {
        Self { host_pass, ..self }
    }

    /// This model with its particle-grid transfers in separable dense form (`true`) or sparse
    /// (`false`) whatever the backend would take ([`crate::ops::NetOps::dense_stencil`]); for
    /// the test that holds the two equal over a rollout.
    pub fn with_dense_transfers(self, dense: bool) -> Self {
        Self {
            dense_transfers: Some(dense),
            ..self
        }
    }

    /// This model with its rest-shape features' F taken as `deformation` says
    /// ([`super::GridConfig::deformation`]): the same weights, the six features read from
    /// another F (fine-tuning a fitted-F model into an advected-F one).
    pub fn with_deformation(self, deformation: Deformation) -> Self {
        Self {
            deformation,
            ..self
        }
    }
}

impl<B: Backend> UNet<B> {
    /// This U-Net with its output tiled `k` times along the channels (head weights and bias
    /// repeated), as [`GridModel::with_bundle`] grows a bundled model.
    pub fn tile_output(mut self, k: usize) -> Self {
        let tile = |t: Tensor<B, 4>| Tensor::cat(vec![t; k], 0).detach(); // [k C_out, C_in, 1, 1]
        let weight = Param::from_tensor(tile(self.head.weight.val()));
        let bias = (self.head.bias.as_ref())
            .map(|b| Param::from_tensor(Tensor::cat(vec![b.val(); k], 0).detach()));
        self.head = Conv2d {
            weight,
            bias,
            ..self.head
        };
        self
    }

    /// This U-Net with `extra` more output channels after the existing ones, their weights
    /// and biases zero: the new channels read 0 until trained.
    pub fn widen_output(mut self, extra: usize) -> Self {
        let w = self.head.weight.val();
        let [_, c_in, kh, kw] = w.dims();
        let zeros = Tensor::zeros([extra, c_in, kh, kw], &w.device());
        let weight = Param::from_tensor(Tensor::cat(vec![w, zeros], 0).detach());
        let bias = self.head.bias.as_ref().map(|b| {
            let b = b.val();
            let zeros = Tensor::zeros([extra], &b.device());
            Param::from_tensor(Tensor::cat(vec![b, zeros], 0).detach())
        });
        self.head = Conv2d {
            weight,
            bias,
            ..self.head
        };
        self
    }
}
