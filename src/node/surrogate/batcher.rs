//! The surrogate node's dynamic batcher, after NVIDIA Triton Inference Server's dynamic
//! batcher (docs.nvidia.com/deeplearning/triton-inference-server, "Dynamic Batcher":
//! `max_batch_size`, `max_queue_delay_microseconds`): work waits in a queue until either
//! a full batch is there or the oldest item has waited `--max-batch-delay`, and then up to
//! `--max-batch` items, oldest first, go through one network call. The items are scenes: a
//! scene's next pending frame, or the next call of its closed-loop rollout; a scene has at
//! most one item per call (its state is sequential). "Full" is `--max-batch`, or every
//! scene that could take part (scenes the node holds that are not rolled out, and
//! rollouts under way) when there are fewer: a single stream is never held back.
//! [`Surrogate::step_scenes`](crate::model::store::Surrogate::step_scenes) stacks the
//! scenes' states and splits them back; scenes of different particle counts go through
//! separate calls. Used by `run.rs`.
//!
//! Pipelined calls: on a GPU the live frames' calls ([`Predict::Next`]) go through
//! [`Surrogate::submit_scenes`](crate::model::store::Surrogate::submit_scenes): the scenes'
//! next states are kept at once, and the call ([`InFlight`]) goes to the lander thread
//! ([`super::lander`]), which waits for its predictions, projects and publishes them while
//! this thread gathers, stacks and records the next batch's call; the loop counts what comes
//! back (and publishes it where the lander does not: a live view, closed loop).
//! `--pipeline` (`NodeOptions::pipeline`) turns it on, by default on a GPU; on the CPU,
//! which computes as it records, a call's frames are published as soon as it returns.

use std::time::Instant;

use crate::model::store::{Finished, Predict, SceneStep, SceneSteps, State, StoreError};
use crate::ops::NetOps;

use super::flight::{InFlight, Job, Landed};
use super::frames::predicted_frame;
use super::lander::MAX_LANDING;
use super::node_loop::NodeLoop;
use super::scenes::Admitted;
use super::schedule::{Due, Waiting};

impl<B: NetOps> NodeLoop<'_, B> {
    /// Triton's rule (module doc) on what waits now ([`super::schedule::Schedule::due`]).
    pub(super) fn batch_due(&self, now: Instant) -> Due {
        let (max_batch, delay) = (self.options.max_batch, self.options.max_batch_delay);
        self.schedule.due(now, self.scenes.live(), max_batch, delay)
    }

    /// Takes up to `--max-batch` items, oldest first, and steps them: the single-frame
    /// items through one set of calls, whole calls (rollouts) through another.
    pub(super) fn step_batch(&mut self) {
        let mut jobs = Vec::new();
        for waiting in self.schedule.oldest_first() {
            if jobs.len() >= self.options.max_batch.max(1) {
                break;
            }
            let job = match waiting {
                Waiting::Rollout(scene) => self.rollout_job(&scene),
                Waiting::Live(scene) => self.live_job(&scene),
            };
            jobs.extend(job);
        }
        self.warm_up(&jobs);
        let (bundles, single): (Vec<_>, Vec<_>) =
            jobs.into_iter().partition(|j| j.predict == Predict::Bundle);
        if !single.is_empty() {
            // `run` starts the lander thread when `--pipeline` asks for it.
            match self.lander.is_some() {
                true => self.submit_jobs(single),
                false => self.run_jobs(single, Predict::Next),
            }
        }
        if !bundles.is_empty() {
            // A rollout's frames follow the live frame before them, and a scene's
            // projections run in call order (its first builds its constraint data from that
            // call's input frame): every call handed over lands before a call on this thread.
            self.publish_landed(0);
            self.run_jobs(bundles, Predict::Bundle);
        }
        self.publish_due_rollouts();
    }

    /// Records the call of `jobs` (live frames, [`Predict::Next`]), keeps the scenes' next
    /// states, and hands the call to the lander thread (module doc).
    fn submit_jobs(&mut self, mut jobs: Vec<Job<B>>) {
        let steps = self.steps_of(&mut jobs);
        let mut submitted = self.surrogate.submit_scenes(steps, Predict::Next);
        self.batches.record(&submitted.calls);
        // The loop's share of the call; what lands it is timed where it waits for it.
        self.times.step += std::mem::take(&mut submitted.times);
        let states = std::mem::take(&mut submitted.states);
        let mut flying = Vec::with_capacity(jobs.len());
        for (job, state) in jobs.into_iter().zip(states) {
            match state {
                Ok(state) => {
                    self.scenes.keep(&job.scene, Some(state));
                    flying.push(Some(job));
                }
                Err(e) => {
                    self.fail_job(job, e);
                    flying.push(None);
                }
            }
        }
        let call = InFlight {
            submitted,
            jobs: flying,
        };
        // The oldest calls handed over first, so that at most MAX_LANDING are.
        self.publish_landed(MAX_LANDING - 1);
        self.lander
            .as_mut()
            .expect("submit_jobs runs with a lander thread (step_batch)")
            .hand_over(call);
    }

    /// Publishes the calls the lander has handed back, waiting for them until at most `keep`
    /// are still landing (`usize::MAX`: only those back already; 0: all).
    pub(super) fn publish_landed(&mut self, keep: usize) {
        loop {
            let Some(lander) = self.lander.as_mut() else {
                return;
            };
            let block = lander.landing > keep;
            let start = Instant::now();
            let landed = lander.next(block);
            // Blocked on the lander: the loop waits for the call (the GPU, the projection).
            if block {
                self.times.landing += start.elapsed();
            }
            let Some(landed) = landed else {
                return;
            };
            self.publish_call(landed);
        }
    }

    /// Publishes a landed call's predictions (a live job's next frame; none in closed loop
    /// before its rollout starts) unless the lander did, and counts them; a failed read
    /// restarts its scenes.
    fn publish_call(&mut self, call: Landed<B>) {
        // The lander thread's time is not the loop's: `publish_landed` times the loop's waits.
        let Finished { frames, .. } = call.finished;
        // The lander published the call's frames where it had the outlet (`Lander::start`).
        let published = call.published.is_some();
        if let Some(p) = call.published {
            self.count_published(p);
        }
        for (job, result) in call.jobs.into_iter().zip(frames) {
            let Some(job) = job else { continue };
            match result {
                Ok(mut bundle) => {
                    self.tally.report.predicted += 1;
                    if published {
                        continue;
                    }
                    if let (None, Some(input)) = (self.options.rollout, job.input) {
                        let next = predicted_frame(&input.frame, &bundle.swap_remove(0), 1);
                        self.emit_timed(&next, input.arrived);
                    }
                }
                Err(e) => self.fail_job(job, e),
            }
        }
    }

    /// Counts and logs a job whose call failed; a live job's scene starts again, a
    /// rollout's is cancelled.
    fn fail_job(&mut self, job: Job<B>, e: StoreError) {
        match job.input {
            Some(_) => {
                self.tally.report.rejected += 1;
                self.scenes.keep(&job.scene, None);
            }
            None => self.schedule.rollouts.cancel(&job.scene),
        }
        self.tally.note(&job.scene, e.to_string());
    }

    /// The jobs' inputs to the model's step (rows and state moved out of each job).
    fn steps_of<'j>(&self, jobs: &'j mut [Job<B>]) -> Vec<SceneStep<'j, B>> {
        let placeholder = || self.surrogate.init_state();
        jobs.iter_mut()
            .map(|j| SceneStep {
                rows: std::mem::take(&mut j.rows),
                material: &j.material,
                dt: j.dt,
                state: std::mem::replace(&mut j.state, placeholder()),
            })
            .collect()
    }

    /// `scene`'s next pending frame as a job, under the state rules (None: dropped or
    /// ignored, counted as they say).
    fn live_job(&mut self, scene: &str) -> Option<Job<B>> {
        let mut input = self.schedule.take_pending(scene)?;
        self.make_room_for(scene);
        let index = input.frame.frame_index;
        let state = match self
            .scenes
            .admit(scene, index, self.options, self.surrogate)
        {
            Admitted::Step(state) => state,
            Admitted::Dropped => {
                self.tally.report.dropped += 1;
                return None;
            }
            Admitted::Ignored => return None,
        };
        // In closed loop the scene's T-th frame starts the rollout: a whole network call
        // (K frames for a bundled model); before it, and fed live frames, one step.
        let starts_rollout = self.options.rollout.is_some() && state.frames + 1 >= self.window;
        if starts_rollout {
            self.scenes.mark_rolled_out(scene);
        }
        let predict = match starts_rollout {
            true => Predict::Bundle,
            false => Predict::Next,
        };
        Some(Job {
            scene: scene.to_owned(),
            rows: std::mem::take(&mut input.rows),
            material: input.frame.material.clone(),
            dt: input.frame.dt,
            state,
            predict,
            input: Some(input),
        })
    }

    /// The call `scene`'s rollout waits for, as a job.
    fn rollout_job(&mut self, scene: &str) -> Option<Job<B>> {
        let call = self.schedule.rollouts.take_call(scene)?;
        Some(Job {
            scene: scene.to_owned(),
            rows: call.rows,
            material: call.material,
            dt: call.dt,
            state: call.state,
            predict: Predict::Bundle,
            input: None,
        })
    }

    /// Before a new scene is admitted at `--max-scenes`, evicts the least recently active
    /// one (counted; the first and every 100th logged).
    fn make_room_for(&mut self, scene: &str) {
        let Some(evicted) = self.scenes.make_room_for(scene, self.options.max_scenes) else {
            return;
        };
        self.evicted.full += 1;
        // The first, then every 100th: a stream of new scenes must not flood the log.
        if self.evicted.full == 1 || self.evicted.full % 100 == 0 {
            tracing::info!(
                "{}: scene {evicted:?} evicted at --max-scenes {} ({} so far; a scene that \
                 comes back starts again)",
                self.options.name,
                self.options.max_scenes,
                self.evicted.full
            );
        }
    }

    /// Steps `jobs` (all of them `predict`) through `Surrogate::step_scenes` and hands each
    /// its result.
    fn run_jobs(&mut self, mut jobs: Vec<Job<B>>, predict: Predict) {
        let steps = self.steps_of(&mut jobs);
        let SceneSteps {
            results,
            calls,
            times,
        } = self.surrogate.step_scenes(steps, predict);
        self.batches.record(&calls);
        self.times.step += times;
        for (job, result) in jobs.into_iter().zip(results) {
            self.finish_job(job, result);
        }
    }

    /// Publishes, keeps or hands on what a job's call returned.
    fn finish_job(&mut self, job: Job<B>, result: Result<(Vec<Vec<f32>>, State<B>), StoreError>) {
        let (mut bundle, state) = match result {
            Ok(v) => v,
            Err(e) => return self.fail_job(job, e),
        };
        self.tally.report.predicted += 1;
        let Some(input) = job.input else {
            self.schedule.rollouts.feed(&job.scene, bundle, state);
            return;
        };
        let keep = match self.options.rollout {
            None => {
                let next = predicted_frame(&input.frame, &bundle.swap_remove(0), 1);
                self.emit_timed(&next, input.arrived);
                Some(state)
            }
            Some(k) if job.predict == Predict::Bundle => {
                let rate = self.options.rate;
                self.schedule
                    .rollouts
                    .start(&input.frame, bundle, state, k, rate);
                None
            }
            Some(_) => Some(state),
        };
        self.scenes.keep(&job.scene, keep);
    }
}
