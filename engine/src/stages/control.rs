//! How a running stage talks to whoever runs it: progress reports, cancellation, and the
//! checkpoint policy (every N steps or T seconds).

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

/// A progress report of a stage.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Progress {
    pub stage: String,
    pub step: u64,
    pub total: u64,
    /// Main training loss, when the stage trains something.
    pub loss: Option<f64>,
    /// Other numbers worth showing (PSNR, learning rate, samples/s…).
    pub metrics: BTreeMap<String, f64>,
    /// Step the stage resumed from (0 for a fresh start).
    pub resumed_from: u64,
}

impl Progress {
    /// A report before a stage's first step: `done` of its inputs prepared, as `metric`.
    pub fn preparing(stage: &str, metric: &str, done: usize) -> Self {
        Self {
            stage: stage.into(),
            metrics: [(metric.to_string(), done as f64)].into(),
            ..Default::default()
        }
    }
}

type Sink = Arc<dyn Fn(&Progress) + Send + Sync>;

/// Progress sink, cancellation flag and checkpoint policy handed to every stage.
#[derive(Clone)]
pub struct StageControl {
    cancel: Arc<AtomicBool>,
    sink: Option<Sink>,
    /// Checkpoint at least every this many steps (0: only by time).
    pub checkpoint_every_steps: u64,
    /// Checkpoint when this much time passed since the last checkpoint.
    pub checkpoint_every: Option<Duration>,
    /// Stop (as if interrupted, after checkpointing) once this step is reached. Used by tests
    /// and by workers that are asked to shut down.
    pub stop_after_step: Option<u64>,
}

impl Default for StageControl {
    fn default() -> Self {
        Self {
            cancel: Arc::new(AtomicBool::new(false)),
            sink: None,
            checkpoint_every_steps: 500,
            checkpoint_every: Some(Duration::from_secs(60)),
            stop_after_step: None,
        }
    }
}

impl std::fmt::Debug for StageControl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StageControl")
            .field("cancelled", &self.is_cancelled())
            .field("checkpoint_every_steps", &self.checkpoint_every_steps)
            .field("checkpoint_every", &self.checkpoint_every)
            .field("stop_after_step", &self.stop_after_step)
            .finish()
    }
}

impl StageControl {
    /// Sends progress reports to `sink`.
    pub fn with_sink(mut self, sink: impl Fn(&Progress) + Send + Sync + 'static) -> Self {
        self.sink = Some(Arc::new(sink));
        self
    }

    /// The shared cancellation flag: set it from anywhere to stop the stage.
    pub fn cancel_flag(&self) -> Arc<AtomicBool> {
        self.cancel.clone()
    }

    pub fn is_cancelled(&self) -> bool {
        self.cancel.load(Ordering::Relaxed)
    }

    pub fn report(&self, progress: &Progress) {
        if let Some(sink) = &self.sink {
            sink(progress);
        }
    }

    /// Whether a checkpoint is due after `step`, given when the last one was written.
    pub fn checkpoint_due(&self, step: u64, last: Instant) -> bool {
        (self.checkpoint_every_steps > 0 && step.is_multiple_of(self.checkpoint_every_steps))
            || self
                .checkpoint_every
                .is_some_and(|every| last.elapsed() >= every)
            || self.stop_after_step == Some(step)
    }

    /// Whether the stage should stop after `step` (checkpoint first).
    pub fn should_stop(&self, step: u64) -> bool {
        self.is_cancelled() || self.stop_after_step == Some(step)
    }
}

/// How a stage run ended when it did not fail.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome<T> {
    /// The stage finished and wrote its outputs.
    Done(T),
    /// The stage was asked to stop (shutdown, or `stop_after_step`) and checkpointed at `step`;
    /// running it again resumes from there.
    Stopped { step: u64 },
}

impl<T> Outcome<T> {
    /// The outcome with its report mapped by `f`.
    pub fn map<U>(self, f: impl FnOnce(T) -> U) -> Outcome<U> {
        match self {
            Outcome::Done(report) => Outcome::Done(f(report)),
            Outcome::Stopped { step } => Outcome::Stopped { step },
        }
    }
}
