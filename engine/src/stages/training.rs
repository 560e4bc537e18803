//! The training-loop driver of the training stages (`nerf_pretrain`, `decoder_pretrain`,
//! `mutual_learning`): resuming from the newest good checkpoint in `out/ckpt`, the steps left to
//! run, a checkpoint when one is due and before every stop, stopping and cancelling, progress
//! reports and the training time (evaluations excluded). A stage's file then holds its science:
//! what a step does, what its checkpoint holds and what it writes at the end.
//!
//! ```text
//! let mut training = Training::new(Stage::X, out, cfg.steps, control);
//! if let Some(resumed) = training.resume::<State>(device)? { restore weights and state }
//! for step in training.steps() {
//!     … one step …
//!     control.report(&training.progress(step + 1));
//!     if let Some(stopped) = training.after_step(step + 1, || Ok((tensors, state)))? {
//!         return Ok(stopped);
//!     }
//! }
//! ```

use std::collections::HashMap;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use candle_core::{Device, Tensor};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use stylenerf_plan::Stage;

use crate::checkpoint::CheckpointDir;
use crate::stages::{Outcome, Progress, StageControl};
use crate::{EngineError, Result};

/// Checkpoints kept per stage (the newest, and one to fall back to should it not load).
const KEEP: usize = 2;

/// One run of a stage's training loop.
pub struct Training<'a> {
    stage: Stage,
    ckpt: CheckpointDir,
    control: &'a StageControl,
    total: u64,
    start: u64,
    /// Training seconds of the runs before this one (from the checkpoint).
    seconds_before: f64,
    started: Instant,
    /// Time of this run not spent training (evaluations).
    untimed: Duration,
    last_checkpoint: Instant,
}

/// A checkpoint's metadata: the driver's bookkeeping and the stage's own state, side by side in
/// one JSON object.
#[derive(Serialize, Deserialize)]
struct Saved<S> {
    step: u64,
    train_seconds: f64,
    #[serde(flatten)]
    state: S,
}

/// What a stage gets back from its checkpoint.
pub struct Resumed<S> {
    pub tensors: HashMap<String, Tensor>,
    pub state: S,
    /// The checkpoint folder, for errors about its contents.
    pub source: PathBuf,
}

impl<'a> Training<'a> {
    /// A loop of `total` steps checkpointing into `out/ckpt`, starting at step 0.
    pub fn new(stage: Stage, out: &Path, total: u64, control: &'a StageControl) -> Self {
        Self {
            stage,
            ckpt: CheckpointDir::new(out.join("ckpt"), KEEP),
            control,
            total,
            start: 0,
            seconds_before: 0.0,
            started: Instant::now(),
            untimed: Duration::ZERO,
            last_checkpoint: Instant::now(),
        }
    }

    /// The newest good checkpoint's tensors and state, with the loop moved past its step;
    /// `None` (a fresh start) when there is none.
    pub fn resume<S: DeserializeOwned>(&mut self, device: &Device) -> Result<Option<Resumed<S>>> {
        let Some(c) = self.ckpt.latest::<Saved<S>>(device)? else {
            return Ok(None);
        };
        self.start = c.meta.step;
        self.seconds_before = c.meta.train_seconds;
        self.started = Instant::now();
        self.untimed = Duration::ZERO;
        tracing::info!(
            step = self.start,
            "{}: resuming from checkpoint",
            self.stage
        );
        Ok(Some(Resumed {
            tensors: c.tensors,
            state: c.meta.state,
            source: self.ckpt.path().to_path_buf(),
        }))
    }

    /// The step this run started from (0 for a fresh start).
    pub fn start(&self) -> u64 {
        self.start
    }

    /// The steps left to run.
    pub fn steps(&self) -> Range<u64> {
        self.start..self.total
    }

    /// Seconds spent training, over every run of the stage.
    pub fn seconds(&self) -> f64 {
        let run = self.started.elapsed().saturating_sub(self.untimed);
        self.seconds_before + run.as_secs_f64()
    }

    /// Runs `f` (an evaluation) without counting its time as training.
    pub fn untimed<R>(&mut self, f: impl FnOnce() -> R) -> R {
        let started = Instant::now();
        let r = f();
        self.untimed += started.elapsed();
        r
    }

    /// A progress report after `done` steps, for the stage to add its loss and metrics to.
    pub fn progress(&self, done: u64) -> Progress {
        Progress {
            stage: self.stage.name().into(),
            step: done,
            total: self.total,
            resumed_from: self.start,
            ..Default::default()
        }
    }

    /// Call after step `done`: writes a checkpoint (`save` gives its tensors and the stage's
    /// state) when one is due or the stage is to stop before its last step. Returns the
    /// outcome to end the stage with when it must stop here; a cancelled stage ends with
    /// [`EngineError::Cancelled`].
    pub fn after_step<S: Serialize, T>(
        &mut self,
        done: u64,
        save: impl FnOnce() -> Result<(Vec<(String, Tensor)>, S)>,
    ) -> Result<Option<Outcome<T>>> {
        if done >= self.total {
            return Ok(None);
        }
        let stop = self.control.should_stop(done);
        if stop || self.control.checkpoint_due(done, self.last_checkpoint) {
            let (tensors, state) = save()?;
            let meta = Saved {
                step: done,
                train_seconds: self.seconds(),
                state,
            };
            self.ckpt.save(done, &tensors, &meta)?;
            self.last_checkpoint = Instant::now();
        }
        if !stop {
            return Ok(None);
        }
        if self.control.is_cancelled() {
            return Err(EngineError::Cancelled);
        }
        Ok(Some(Outcome::Stopped { step: done }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, Serialize, Deserialize, PartialEq)]
    struct State {
        sum: u64,
    }

    /// A toy loop (a running sum) through the driver: `Some(step)` when it stopped there.
    fn run(out: &Path, control: &StageControl, total: u64) -> Result<(Outcome<u64>, u64)> {
        let device = Device::Cpu;
        let mut training = Training::new(Stage::NerfPretrain, out, total, control);
        let mut sum = 0u64;
        let mut weight = Tensor::zeros(1, candle_core::DType::F32, &device)?;
        if let Some(r) = training.resume::<State>(&device)? {
            sum = r.state.sum;
            weight = r.tensors["w"].clone();
        }
        let resumed_from = training.start();
        for step in training.steps() {
            sum += step;
            weight = (weight + 1.0)?;
            let w = weight.clone();
            if let Some(stopped) =
                training.after_step(step + 1, || Ok((vec![("w".to_string(), w)], State { sum })))?
            {
                return Ok((stopped, resumed_from));
            }
        }
        let w = weight.to_vec1::<f32>()?[0] as u64;
        assert_eq!(w, total, "one increment per step, over every run");
        Ok((Outcome::Done(sum), resumed_from))
    }

    #[test]
    fn a_stopped_loop_resumes_where_it_stopped_and_ends_as_an_uninterrupted_one() {
        let dir = tempfile::tempdir().unwrap();
        let mut stop_at_4 = StageControl::default();
        stop_at_4.stop_after_step = Some(4);
        let (first, from) = run(dir.path(), &stop_at_4, 10).unwrap();
        assert_eq!((first, from), (Outcome::Stopped { step: 4 }, 0));
        let (second, from) = run(dir.path(), &StageControl::default(), 10).unwrap();
        assert_eq!(from, 4);
        assert_eq!(second, Outcome::Done((0..10).sum()));
        // The checkpoint's JSON keeps the driver's fields beside the stage's.
        let json: serde_json::Value = serde_json::from_slice(
            &std::fs::read(dir.path().join("ckpt/step-00000004.json")).unwrap(),
        )
        .unwrap();
        let text = json.to_string();
        assert!(
            text.contains("\"step\":4") && text.contains("\"sum\":6"),
            "{text}"
        );
    }

    #[test]
    fn a_cancelled_loop_checkpoints_then_fails_as_cancelled() {
        let dir = tempfile::tempdir().unwrap();
        let control = StageControl::default();
        control
            .cancel_flag()
            .store(true, std::sync::atomic::Ordering::Relaxed);
        let err = run(dir.path(), &control, 10).unwrap_err();
        assert!(matches!(err, EngineError::Cancelled), "{err}");
        let (_, from) = run(dir.path(), &StageControl::default(), 10).unwrap();
        assert_eq!(from, 1);
    }
}
