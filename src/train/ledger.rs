//! A run that lasts longer than one process: [`CallShare`], what one call (one `minflow
//! train` process, as a device session's command) may do before it checkpoints mid-epoch
//! and ends cleanly (`--call-minutes`, `--call-steps`) and how often it checkpoints
//! meanwhile (`--checkpoint-minutes`); and [`RunLedger`], what the run has used over all its
//! calls (samples seen, device-hours, the devices and dataset of each call), kept with the
//! checkpoint so that a resumed run adds to it and written as `run.json` for people to read.
//! Used by [`super::epochs::run_epochs`] and [`super::checkpoint`].

use std::time::{Instant, SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

/// What one call may do, and when it checkpoints.
#[derive(Debug, Clone)]
pub struct CallShare {
    /// End the call after this many minutes (0: no limit).
    pub minutes: f64,
    /// End the call after this many optimizer steps (0: no limit).
    pub steps: usize,
    /// Write a mid-epoch checkpoint after this many minutes without one (0: only at the end
    /// of each epoch and when the call ends).
    pub checkpoint_minutes: f64,
    started: Instant,
    last_checkpoint: Instant,
    steps_done: usize,
}

/// What a run does after an optimizer step ([`CallShare::after_step`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AfterStep {
    /// Go on.
    Continue,
    /// Write a mid-epoch checkpoint and go on.
    Checkpoint,
    /// The call's share is used: checkpoint mid-epoch and end.
    Stop,
}

impl Default for CallShare {
    /// No limit, no mid-epoch checkpoints.
    fn default() -> Self {
        Self::new(0.0, 0, 0.0)
    }
}

impl CallShare {
    /// A share of `minutes` and `steps` (0: unlimited), checkpointing every
    /// `checkpoint_minutes` (0: never mid-epoch), starting now.
    pub fn new(minutes: f64, steps: usize, checkpoint_minutes: f64) -> Self {
        let now = Instant::now();
        Self {
            minutes,
            steps,
            checkpoint_minutes,
            started: now,
            last_checkpoint: now,
            steps_done: 0,
        }
    }

    /// The same share with its clock started now.
    pub fn restarted(&self) -> Self {
        Self::new(self.minutes, self.steps, self.checkpoint_minutes)
    }

    /// Counts one optimizer step and says what comes next.
    pub fn after_step(&mut self) -> AfterStep {
        self.steps_done += 1;
        let minutes = |since: Instant| since.elapsed().as_secs_f64() / 60.0;
        if (self.steps > 0 && self.steps_done >= self.steps)
            || (self.minutes > 0.0 && minutes(self.started) >= self.minutes)
        {
            return AfterStep::Stop;
        }
        if self.checkpoint_minutes > 0.0 && minutes(self.last_checkpoint) >= self.checkpoint_minutes
        {
            self.last_checkpoint = Instant::now();
            return AfterStep::Checkpoint;
        }
        AfterStep::Continue
    }

    /// Seconds since the call began.
    pub fn seconds(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }
}

/// What a run trains on, as its ledger records it.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DatasetInfo {
    /// The `--data` inputs.
    pub inputs: Vec<String>,
    /// Scenes in the training split.
    pub train_scenes: usize,
    /// Frames of the training scenes.
    pub train_frames: usize,
    /// Whether the training scenes were streamed from the bags.
    pub streamed: bool,
}

/// One call of a run.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CallRecord {
    /// When it began, seconds since the Unix epoch.
    pub began_unix: u64,
    /// Wall-clock seconds it trained (to its last checkpoint).
    pub seconds: f64,
    /// The devices it trained on (`cpu`, `cuda:0`, ...).
    pub devices: Vec<String>,
    /// Samples (windows) it trained on.
    pub samples: u64,
    /// Its dataset.
    pub dataset: DatasetInfo,
}

/// What a run has used over all its calls (`run.json`, and `ledger.json` in the checkpoint).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RunLedger {
    /// Samples (windows) trained on, over all calls.
    pub samples: u64,
    /// Wall-clock hours times devices, over all calls (GPU-hours on GPUs).
    pub device_hours: f64,
    /// Every call, the current one last.
    pub calls: Vec<CallRecord>,
}

impl RunLedger {
    /// The ledger a call resumes (`resumed`, or a new one) with this call added: it began
    /// now, on `devices`, with `dataset`.
    pub fn begin_call(
        resumed: Option<RunLedger>,
        devices: Vec<String>,
        dataset: DatasetInfo,
    ) -> Self {
        let mut ledger = resumed.unwrap_or_default();
        let began_unix = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        ledger.calls.push(CallRecord {
            began_unix,
            devices,
            dataset,
            ..CallRecord::default()
        });
        ledger
    }

    /// The ledger, shared with the run's output ([`super::checkpoint::RunOutput`]).
    pub fn shared(self) -> std::sync::Arc<std::sync::Mutex<Self>> {
        std::sync::Arc::new(std::sync::Mutex::new(self))
    }

    /// Records that the run has now seen `samples` samples in all and this call has run
    /// `seconds`.
    pub fn update(&mut self, samples: u64, seconds: f64) {
        let before: u64 = (self.calls.iter().rev().skip(1)).map(|c| c.samples).sum();
        if let Some(call) = self.calls.last_mut() {
            call.samples = samples.saturating_sub(before);
            call.seconds = seconds;
        }
        self.samples = samples;
        self.device_hours = (self.calls.iter())
            .map(|c| c.seconds * c.devices.len().max(1) as f64 / 3600.0)
            .sum();
    }
}
