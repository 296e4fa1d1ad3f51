//! Training of the paper's architecture ([`crate::model::paper`]; docs/design.md, "Models"):
//! Adam (lr 1e-3, epsilon 1e-8 as PyTorch), effective batch reached by micro-batches with
//! gradient accumulation, the loss on the next frame ([`super::loss`]), and the shared epoch
//! loop ([`super::epochs`]: early stopping on the validation loss, best model kept,
//! checkpoint every epoch so a killed run resumes bit for bit; the backend RNG and the data
//! order are reseeded from (seed, epoch)). Backend-generic: the initial weights are always
//! drawn on the CPU backend from the seed and then moved to the training device, so a CUDA
//! run starts from the same weights as a CPU run. Batches are assembled on a helper thread
//! one ahead of the device, and the loss is read back once per optimizer step (after the
//! step is queued), so an accelerator is not left waiting on the host between micro-batches.
//! Used by `minflow train --arch paper` and `minflow bench train --arch paper`.

use super::epochs::{run_epochs, EpochPass, EpochRun};
use super::{adam, checkpoint, drawn_on_cpu, loss, BatchSource, EpochRecord, Observer, TrainError};
use crate::data::{Batch, Scaler, WindowIndex};
use crate::model::store::{self, ModelMeta};
use crate::model::{upload, Model, ModelConfig, Scaling};
use burn::module::{AutodiffModule, Module};
use burn::optim::adaptor::OptimizerAdaptor;
use burn::optim::{GradientsAccumulator, GradientsParams, MultiGradientsParams, Optimizer};
use burn::tensor::backend::{AutodiffBackend, Backend, DeviceOps};
use burn::tensor::{ElementConversion, StreamId, Tensor};
use std::path::PathBuf;
use std::time::Instant;

/// Optimisation settings.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct TrainOptions {
    /// Epochs to run at most.
    pub epochs: usize,
    /// Effective batch size (windows per optimizer step).
    pub batch_size: usize,
    /// Windows per forward/backward pass; gradients are accumulated up to `batch_size`.
    pub micro_batch: usize,
    /// Adam learning rate.
    pub lr: f64,
    /// Seed of weights, data order and dropout.
    pub seed: u64,
    /// Stop after this many epochs without a better validation loss (0: never).
    pub patience: usize,
    /// Density-map grid size G.
    pub density_grid: usize,
    /// Weight of the density-map loss.
    pub density_weight: f32,
}

/// Host data of a batch slice `[start, start + len)`, ready to upload.
struct HostSlice {
    len: usize,
    t: usize,
    n: usize,
    inputs: Vec<f32>,
    targets: Vec<f32>,
    target_pos: Vec<f32>,
    dt: Vec<f32>,
}

/// Tensors of a batch slice.
struct Slice<B: Backend> {
    inputs: Tensor<B, 4>,
    targets: Tensor<B, 3>,
    target_pos: Tensor<B, 3>,
    dt: Tensor<B, 1>,
}

/// Deals micro-batches to `k` devices in turn (the first devices get one more when they do
/// not divide evenly).
fn deal(slices: Vec<HostSlice>, k: usize) -> Vec<Vec<HostSlice>> {
    let mut shards: Vec<Vec<HostSlice>> = (0..k).map(|_| Vec::new()).collect();
    for (i, s) in slices.into_iter().enumerate() {
        shards[i % k].push(s);
    }
    shards
}

/// Cuts `batch` into micro-batches of at most `micro` windows (host side).
fn host_slices(batch: Batch, micro: usize) -> Vec<HostSlice> {
    let (t, n, b) = (batch.t, batch.n, batch.b);
    let micro = micro.clamp(1, b.max(1));
    let mut out = Vec::with_capacity(b.div_ceil(micro));
    let mut start = 0;
    while start < b {
        let len = micro.min(b - start);
        let target_pos = batch.target_phys[start * n * 4..(start + len) * n * 4]
            .chunks_exact(4)
            .flat_map(|r| [r[0], r[1]])
            .collect();
        let (inputs, targets) = if len == b {
            (batch.inputs.clone(), batch.targets.clone())
        } else {
            (
                batch.inputs[start * t * n * 5..(start + len) * t * n * 5].to_vec(),
                batch.targets[start * n * 4..(start + len) * n * 4].to_vec(),
            )
        };
        out.push(HostSlice {
            len,
            t,
            n,
            inputs,
            targets,
            target_pos,
            dt: batch.dt[start..start + len].to_vec(),
        });
        start += len;
    }
    out
}

impl HostSlice {
    fn upload<B: Backend>(self, device: &B::Device) -> Slice<B> {
        let (len, t, n) = (self.len, self.t, self.n);
        Slice {
            inputs: upload(self.inputs, [len, t, n, 5], device),
            targets: upload(self.targets, [len, n, 4], device),
            target_pos: upload(self.target_pos, [len, n, 2], device),
            dt: upload(self.dt, [len], device),
        }
    }
}

/// Fresh weights from `seed`, drawn on the CPU backend whatever `B` is and moved to `device`
/// through an f32 record, so runs on different backends start from identical weights. (For
/// `B` on ndarray these are the weights `config.init::<B>` draws after seeding.)
pub fn initial_model<B: crate::ops::NetOps>(
    config: &ModelConfig,
    seed: u64,
    device: &B::Device,
) -> Result<Model<B>, TrainError> {
    drawn_on_cpu(
        seed,
        |cpu| config.init(cpu),
        config.init::<B>(device),
        device,
    )
}

/// Predicted positions in domain units from a scaled prediction `[B, N, 4]`.
fn positions<B: burn::tensor::backend::Backend>(
    pred: Tensor<B, 3>,
    scaling: &Scaling,
) -> Tensor<B, 3> {
    let (min, range) = scaling.tensors::<B>(&pred.device());
    (pred * range + min).narrow(2, 0, 2)
}

/// The model's prediction for a batch slice and its loss (train and validation alike).
fn slice_loss<B: crate::ops::NetOps>(
    model: &Model<B>,
    s: Slice<B>,
    scaling: &Scaling,
    opts: &TrainOptions,
) -> loss::LossParts<B> {
    let pred = model.forward(s.inputs, s.dt, scaling);
    loss::loss(
        pred.clone(),
        s.targets,
        positions(pred, scaling),
        s.target_pos,
        opts.density_grid,
        opts.density_weight,
    )
}

/// Mean loss of `model` over `index` (no gradients, no dropout).
pub fn evaluate<B: crate::ops::NetOps>(
    model: &Model<B>,
    index: &mut dyn BatchSource,
    scaling: &Scaling,
    opts: &TrainOptions,
    device: &B::Device,
) -> Result<f64, TrainError> {
    let (mut sum, mut count) = (0.0, 0usize);
    for batch in index.batches(opts.micro_batch.max(1), None, 0)? {
        let batch = batch?;
        let b = batch.b;
        for host in host_slices(batch, b) {
            let len = host.len;
            let parts = slice_loss(model, host.upload::<B>(device), scaling, opts);
            sum += parts.total.into_scalar().elem::<f64>() * len as f64;
            count += len;
        }
    }
    Ok(if count == 0 {
        f64::NAN
    } else {
        sum / count as f64
    })
}

/// A training run over in-memory windows.
pub struct Trainer<B: AutodiffBackend> {
    /// Network hyper-parameters.
    pub config: ModelConfig,
    /// Optimisation settings.
    pub opts: TrainOptions,
    /// Output folder.
    pub out: PathBuf,
    /// The devices it trains on (never empty); the first, the main device, holds the model
    /// between epochs, validates and checkpoints; more than one train data-parallel.
    devices: Vec<B::Device>,
}

impl<B: AutodiffBackend + crate::ops::NetOps> Trainer<B>
where
    B::InnerBackend: crate::ops::NetOps,
{
    /// A trainer writing to `out`.
    pub fn new(config: ModelConfig, opts: TrainOptions, out: PathBuf, device: B::Device) -> Self {
        Self::data_parallel(config, opts, out, vec![device])
    }

    /// A trainer that trains data-parallel on `devices` (the first is the main device), with
    /// burn's multi-device strategy (`burn-train`'s `MultiDevice` with `OptimSharded`): every
    /// optimizer step forks the model to each device, each device runs forward and backward
    /// on its share of the batch's micro-batches, and
    /// [`Optimizer::step_multi`](burn::optim::Optimizer::step_multi) sums each parameter's
    /// gradients on one device (chosen by parameter id, so the optimizer state is sharded
    /// over the devices) and updates it there. The effective batch, the data order and the
    /// loss scaling are those of a one-device run; only the dropout masks differ (each
    /// device draws its own).
    ///
    /// # Panics
    /// If `devices` is empty.
    pub fn data_parallel(
        config: ModelConfig,
        opts: TrainOptions,
        out: PathBuf,
        devices: Vec<B::Device>,
    ) -> Self {
        assert!(
            !devices.is_empty(),
            "data_parallel needs at least one device"
        );
        Self {
            config,
            opts,
            out,
            devices,
        }
    }

    /// The main device.
    fn main(&self) -> &B::Device {
        &self.devices[0]
    }

    /// Forward and backward of `slices` (micro-batches of one optimizer step of `b`
    /// windows) on `device`: the accumulated gradients (scaled so that the shares of all
    /// devices sum to the batch mean) and the summed, window-weighted loss (not read back).
    fn shard_step(
        &self,
        model: &Model<B>,
        slices: Vec<HostSlice>,
        b: usize,
        scaling: &Scaling,
        device: &B::Device,
    ) -> (GradientsParams, Option<Tensor<B::InnerBackend, 1>>) {
        let mut accumulator = GradientsAccumulator::new();
        let mut batch_loss: Option<Tensor<B::InnerBackend, 1>> = None;
        let started = Instant::now();
        for host in slices {
            let len = host.len;
            let parts = slice_loss(model, host.upload::<B>(device), scaling, &self.opts);
            let weighted = parts.total.clone().inner().mul_scalar(len as f32);
            batch_loss = Some(match batch_loss {
                Some(acc) => acc + weighted,
                None => weighted,
            });
            let forward = started.elapsed();
            let grads = parts.total.mul_scalar(len as f32 / b as f32).backward();
            let backward = started.elapsed();
            accumulator.accumulate(model, GradientsParams::from_grads(grads, model));
            tracing::trace!(?forward, ?backward, accumulated = ?started.elapsed(), "micro-batch");
        }
        (accumulator.grads(), batch_loss)
    }

    /// Trains on `train`, validating on `val`; resumes from `out/checkpoint` when `resume`.
    /// `on_epoch` sees each finished epoch with the number of batches per epoch.
    pub fn fit(
        &self,
        train: &WindowIndex,
        val: Option<&WindowIndex>,
        scaler: &Scaler,
        resume: bool,
        mut on_epoch: impl FnMut(&EpochRecord, usize),
    ) -> Result<Vec<EpochRecord>, TrainError> {
        struct Adapter<'a, F: FnMut(&EpochRecord, usize)>(&'a mut F, usize);
        impl<F: FnMut(&EpochRecord, usize)> Observer for Adapter<'_, F> {
            fn epoch(&mut self, record: &EpochRecord, _: &[EpochRecord]) {
                (self.0)(record, self.1)
            }
        }
        let batches = train.num_batches(self.opts.batch_size.max(1));
        let mut train = train;
        let mut val = val;
        self.fit_observed(
            &mut train,
            val.as_mut().map(|v| v as &mut dyn BatchSource),
            scaler,
            resume,
            &mut Adapter(&mut on_epoch, batches),
        )
    }

    /// [`Trainer::fit`] over any [`BatchSource`] (in memory or streamed from the bags),
    /// reporting to an [`Observer`] (per batch and per epoch).
    ///
    /// Per epoch ([`run_epochs`]): seed every device, train ([`Trainer::train_epoch`]),
    /// validate, save the model when its validation loss is the best so far, checkpoint.
    /// Stops after `epochs`, or `patience` epochs without a better validation loss.
    pub fn fit_observed(
        &self,
        train: &mut dyn BatchSource,
        val: Option<&mut dyn BatchSource>,
        scaler: &Scaler,
        resume: bool,
        observer: &mut dyn Observer,
    ) -> Result<Vec<EpochRecord>, TrainError> {
        self.check_particle_counts(&train.particle_counts())?;
        let start = self.start(resume)?;
        let mut run = PaperRun {
            trainer: self,
            scaling: self.meta(scaler, 0, 0.0).scaling(),
            streams: self.stream_ids(),
            scaler: *scaler,
            train,
            val,
        };
        run_epochs(&mut run, start, observer)
    }

    /// The global decoder is built for the config's N: an error when the data has another.
    fn check_particle_counts(&self, counts: &[usize]) -> Result<(), TrainError> {
        if self.config.decoder == crate::model::DecoderKind::Global
            && counts.iter().any(|&n| n != self.config.particles)
        {
            return Err(TrainError::Mismatch(format!(
                "the global decoder is built for N = {} particles but the data has N = {counts:?}; use --decoder pointwise or matching bags",
                self.config.particles
            )));
        }
        Ok(())
    }

    /// The stored metadata of this run's model after `epoch` epochs.
    fn meta(&self, scaler: &Scaler, epoch: usize, val_loss: f64) -> ModelMeta {
        ModelMeta {
            net: store::NetConfig::Paper(self.config.clone()),
            scaler: *scaler,
            epoch,
            val_loss,
        }
    }

    /// The model, optimizer and history to start from: freshly initialised (seeded), or
    /// those of `out/checkpoint` when `resume` and there is one.
    fn start(&self, resume: bool) -> Result<(Model<B>, Optim<B>, Vec<EpochRecord>), TrainError> {
        B::seed(self.main(), self.opts.seed);
        let model: Model<B> = initial_model(&self.config, self.opts.seed, self.main())?;
        let optim = adam::FusedAdam::default().init::<B, Model<B>>();
        if resume {
            if let Some(state) = checkpoint::load::<B, _, _>(
                &self.out,
                self.config.init::<B>(self.main()),
                self.main(),
                &optim,
            )? {
                let optim = optim.load_record(state.optim);
                return Ok((state.model, optim, state.history));
            }
        }
        Ok((model, optim, Vec::new()))
    }

    /// One fixed stream id per device for the whole run (this thread's for the main
    /// device, a fresh one each for the others). burn's fusion streams and cubecl's CUDA
    /// streams and memory pools are per stream id, which is per thread by default: workers
    /// spawned every step would open a new ~10 GB pool per step at the paper's size (the
    /// allocator then failed), and two threads sharing one id on a device corrupt its
    /// stream (illegal addresses).
    fn stream_ids(&self) -> Vec<StreamId> {
        (0..self.devices.len())
            .map(|k| match k {
                0 => StreamId::current(),
                _ => std::thread::spawn(StreamId::current)
                    .join()
                    .expect("a thread that only reads its id"),
            })
            .collect()
    }

    /// Seeds each device's random numbers (dropout) for `epoch`.
    fn seed_epoch(&self, epoch: usize) {
        for (k, device) in self.devices.iter().enumerate() {
            B::seed(
                device,
                self.opts
                    .seed
                    .wrapping_mul(1_000_003)
                    .wrapping_add(epoch as u64)
                    .wrapping_add((k as u64) << 32),
            );
        }
    }

    /// One epoch over `train` (0-based `epoch`, started at `started`): host batches are
    /// assembled one ahead on a second thread; each is one optimizer step, its loss read
    /// back once. Returns the trained model (on the main device) and the epoch's totals.
    #[allow(clippy::too_many_arguments)]
    fn train_epoch(
        &self,
        model: Model<B>,
        optim: &mut Optim<B>,
        train: &mut dyn BatchSource,
        epoch: usize,
        scaling: &Scaling,
        streams: &[StreamId],
        observer: &mut dyn Observer,
        started: Instant,
    ) -> Result<(Model<B>, EpochPass), TrainError> {
        let total = train.num_batches(self.opts.batch_size.max(1));
        let batches = train.batches(
            self.opts.batch_size.max(1),
            Some(self.opts.seed),
            epoch as u64,
        )?;
        let micro = self.opts.micro_batch;
        let parallel = self.devices.len();
        // The model moves into the step loop and back out (`optim.step` consumes it, so
        // the parameters are updated in place when nothing else holds them).
        let mut slot = Some(model);
        let totals = std::thread::scope(|scope| {
            // Host batches are assembled (and cut into micro-batches) one ahead.
            let (tx, rx) = std::sync::mpsc::sync_channel(1);
            scope.spawn(move || {
                for batch in batches {
                    // Data parallel: at least one micro-batch per device.
                    let item = batch.map(|b| {
                        let micro = micro.min(b.b.div_ceil(parallel));
                        (b.b, host_slices(b, micro))
                    });
                    if tx.send(item).is_err() {
                        break;
                    }
                }
            });
            let mut totals = EpochPass::default();
            let mut k = 0;
            loop {
                let waited = Instant::now();
                let Ok(item) = rx.recv() else { break };
                totals.data_seconds += waited.elapsed().as_secs_f64();
                let (b, slices) = item?;
                let model = slot.take().expect("the model is put back after every step");
                let step_started = Instant::now();
                let (model, losses) =
                    self.optimizer_step(model, optim, slices, b, scaling, streams);
                slot = Some(model);
                tracing::trace!(step = ?step_started.elapsed(), "optimizer step");
                // One read per step, after the step is queued: the host waits here for
                // the device to finish it.
                let waited = Instant::now();
                let value: f64 = losses
                    .into_iter()
                    .flatten()
                    .map(|l| l.into_scalar().elem::<f64>())
                    .sum::<f64>()
                    / b.max(1) as f64;
                totals.wait_seconds += waited.elapsed().as_secs_f64();
                if !value.is_finite() {
                    return Err(TrainError::NonFinite {
                        epoch: epoch + 1,
                        batch: k,
                        loss: value as f32,
                    });
                }
                totals.sum += value * b as f64;
                totals.seen += b;
                k += 1;
                let rate = totals.seen as f64 / started.elapsed().as_secs_f64().max(1e-9);
                observer.batch(epoch + 1, k, total, totals.sum / totals.seen as f64, rate);
            }
            Ok(totals)
        })?;
        let mut model = slot.expect("the model is put back after every step");
        if parallel > 1 {
            // `step_multi` left each parameter on the device that updated it.
            model = model.fork(self.main());
        }
        Ok((model, totals))
    }

    /// One optimizer step on a batch of `b` windows cut into `slices`: on the main device,
    /// or data-parallel with the slices dealt over the devices. Returns the updated model
    /// and the summed losses of each device (not read back).
    fn optimizer_step(
        &self,
        model: Model<B>,
        optim: &mut Optim<B>,
        slices: Vec<HostSlice>,
        b: usize,
        scaling: &Scaling,
        streams: &[StreamId],
    ) -> (Model<B>, Vec<Option<Tensor<B::InnerBackend, 1>>>) {
        let parallel = self.devices.len();
        if parallel == 1 {
            let (grads, loss) = self.shard_step(&model, slices, b, scaling, self.main());
            return (optim.step(self.opts.lr, model, grads), vec![loss]);
        }
        let shards = deal(slices, parallel);
        // The workers are new threads every step, on the run's fixed stream ids (see
        // `stream_ids`).
        let results: Vec<_> = std::thread::scope(|workers| {
            let handles: Vec<_> = shards
                .into_iter()
                .zip(self.devices.iter().zip(streams))
                .map(|(shard, (device, &stream))| {
                    let model = &model;
                    workers.spawn(move || {
                        stream.executes(|| {
                            let local = model.clone().fork(device);
                            let (grads, loss) = self.shard_step(&local, shard, b, scaling, device);
                            (grads, device.id(), loss)
                        })
                    })
                })
                .collect();
            handles
                .into_iter()
                .map(|h| h.join().expect("a data-parallel worker panicked"))
                .collect()
        });
        let mut multi = MultiGradientsParams::default();
        let mut losses = Vec::new();
        for (grads, id, loss) in results {
            multi.grads.push((grads, id));
            losses.push(loss);
        }
        (optim.step_multi(self.opts.lr, model, multi), losses)
    }
}

/// The optimizer of a run: [`adam::FusedAdam`] through burn's adaptor.
type Optim<B> = OptimizerAdaptor<adam::FusedAdam, Model<B>, B>;

/// A paper run in progress: the trainer and the batch sources, as [`run_epochs`] drives it.
struct PaperRun<'a, 't, 'v, B: AutodiffBackend> {
    trainer: &'a Trainer<B>,
    scaling: Scaling,
    streams: Vec<StreamId>,
    scaler: Scaler,
    train: &'t mut dyn BatchSource,
    val: Option<&'v mut dyn BatchSource>,
}

impl<B: AutodiffBackend + crate::ops::NetOps> EpochRun for PaperRun<'_, '_, '_, B>
where
    B::InnerBackend: crate::ops::NetOps,
{
    type Model = Model<B>;
    type Optim = Optim<B>;

    fn limits(&self) -> (usize, usize) {
        (self.trainer.opts.epochs, self.trainer.opts.patience)
    }

    fn train_epoch(
        &mut self,
        model: Model<B>,
        optim: &mut Optim<B>,
        epoch: usize,
        observer: &mut dyn Observer,
    ) -> Result<(Model<B>, EpochPass), TrainError> {
        self.trainer.seed_epoch(epoch);
        let started = Instant::now();
        self.trainer.train_epoch(
            model,
            optim,
            &mut *self.train,
            epoch,
            &self.scaling,
            &self.streams,
            observer,
            started,
        )
    }

    fn validate(&mut self, model: &Model<B>, _: usize, train_loss: f64) -> Result<f64, TrainError> {
        let t = self.trainer;
        match self.val.as_mut() {
            Some(v) if v.windows() > 0 => {
                evaluate(&model.valid(), &mut **v, &self.scaling, &t.opts, t.main())
            }
            _ => Ok(train_loss),
        }
    }

    fn save_best(&self, model: &Model<B>, epoch: usize, val_loss: f64) -> Result<(), TrainError> {
        let meta = self.trainer.meta(&self.scaler, epoch, val_loss);
        Ok(store::save(&self.trainer.out, model, &meta)?)
    }

    fn checkpoint(
        &self,
        model: &Model<B>,
        optim: &Optim<B>,
        history: &[EpochRecord],
    ) -> Result<(), TrainError> {
        checkpoint::save(&self.trainer.out, model, optim, history)
    }
}
