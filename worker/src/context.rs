//! What a stage running inside a task sees: the assignment and its parsed configuration, the
//! worker's settings, downloads of the inputs the stage reads, and the engine call on a blocking
//! thread. [`crate::stages`] builds on it; [`crate::task`] creates it for each leased task.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use candle_core::Device;
use stylenerf_engine::checkpoint::CheckpointDir;
use stylenerf_engine::stages::{Outcome, StageControl};
use stylenerf_engine::EngineError;
use stylenerf_plan::{Source, Stage};
use stylenerf_proto::v1 as pb;

use crate::archive::{self, ArchiveLimits};
use crate::error::TaskError;
use crate::progress::ProgressTracker;
use crate::store::Store;
use crate::task_config::TaskConfig;

/// Named final metrics of a stage, sent with `CompleteTask`.
pub type Metrics = BTreeMap<String, f64>;

/// Settings every task of a worker shares.
#[derive(Debug, Clone)]
pub struct RunSettings {
    pub worker_id: String,
    pub device: Device,
    /// VGG encoder weights for the 2D stages; `None` = the bundled VGG-16.
    pub encoder: Option<PathBuf>,
    pub checkpoint_every_steps: u64,
    pub checkpoint_every: Option<Duration>,
    /// How often new checkpoints are looked for and uploaded.
    pub checkpoint_upload_every: Duration,
    pub scratch_dir: PathBuf,
    pub keep_scratch: bool,
}

/// Everything a stage function needs: the assignment, its parsed config, the store, the local
/// folders and the stage control.
pub struct TaskContext {
    pub assignment: pb::TaskAssignment,
    pub config: TaskConfig,
    pub store: Store,
    pub settings: Arc<RunSettings>,
    pub control: StageControl,
    pub tracker: Arc<ProgressTracker>,
    /// `<scratch>/inputs`: downloaded inputs.
    pub inputs: PathBuf,
    /// `<scratch>/out`: the stage's output folder (checkpoints in `out/ckpt`).
    pub out: PathBuf,
}

impl TaskContext {
    /// Downloads and unpacks the dataset archive; returns the scene folder.
    pub async fn dataset(&self) -> Result<PathBuf, TaskError> {
        self.tracker.set_message("downloading the dataset");
        let dest = self.unpack_input("dataset").await?;
        tokio::task::spawn_blocking(move || archive::scene_root(&dest))
            .await
            .map_err(|e| TaskError::retryable(format!("finding the scene: {e}")))?
    }

    /// Downloads the job's plain photos (unpacked; returns their folder) or video (returns
    /// the file).
    pub async fn photos(&self) -> Result<PathBuf, TaskError> {
        self.tracker.set_message("downloading the photos");
        let key = &self.assignment.dataset_key;
        if Source::of_input_key(key) == Source::Video {
            let name = key.rsplit('/').next().unwrap_or("video");
            let path = self.inputs.join(name);
            self.store.download(key, "", &path).await?;
            return Ok(path);
        }
        let dest = self.unpack_input("photos").await?;
        tokio::task::spawn_blocking(move || archive::photos_root(&dest))
            .await
            .map_err(|e| TaskError::retryable(format!("finding the photos: {e}")))?
    }

    /// Downloads the job's scene archive and unpacks it into `inputs/<name>/`.
    async fn unpack_input(&self, name: &str) -> Result<PathBuf, TaskError> {
        let key = self.assignment.dataset_key.clone();
        let tar = self.inputs.join(format!("{name}.tar"));
        self.store.download(&key, "", &tar).await?;
        let dest = self.inputs.join(name);
        tokio::task::spawn_blocking(move || -> Result<PathBuf, TaskError> {
            let file = std::fs::File::open(&tar)
                .map_err(|e| TaskError::retryable(format!("{}: {e}", tar.display())))?;
            archive::unpack(
                std::io::BufReader::new(file),
                &dest,
                &key,
                ArchiveLimits::default(),
            )?;
            let _ = std::fs::remove_file(&tar);
            Ok(dest)
        })
        .await
        .map_err(|e| TaskError::retryable(format!("unpacking {name}: {e}")))?
    }

    /// Downloads the outputs of the upstream `stage` into `inputs/<stage>/`; returns that
    /// folder.
    pub async fn upstream(&self, stage: Stage) -> Result<PathBuf, TaskError> {
        let name = stage.name();
        let input = self
            .assignment
            .inputs
            .iter()
            .find(|i| pb::Stage::of(i.stage) == Some(stage))
            .ok_or_else(|| {
                TaskError::permanent(format!(
                    "the assignment lists no outputs of the upstream stage {name}"
                ))
            })?;
        self.tracker
            .set_message(format!("downloading the outputs of {name}"));
        let dir = self.inputs.join(name);
        self.store
            .download_all(&input.artifacts, &input.prefix, &dir)
            .await?;
        Ok(dir)
    }

    /// Downloads the style images, in style order; returns their paths.
    pub async fn styles(&self) -> Result<Vec<PathBuf>, TaskError> {
        self.tracker.set_message("downloading the style images");
        let mut paths = Vec::new();
        for (i, key) in self.assignment.style_keys.iter().enumerate() {
            let ext = key.rsplit_once('.').map_or("img", |(_, e)| e);
            let path = self.inputs.join("styles").join(format!("{i}.{ext}"));
            self.store.download(key, "", &path).await?;
            paths.push(path);
        }
        Ok(paths)
    }

    /// Runs `f(control, device, out)` (the engine call) on a blocking thread. A cancelled
    /// stage comes back as `Outcome::Stopped` at its last checkpoint.
    pub async fn run_engine<R: Send + 'static>(
        &self,
        f: impl FnOnce(&StageControl, &Device, &Path) -> Result<Outcome<R>, EngineError>
            + Send
            + 'static,
    ) -> Result<Outcome<R>, TaskError> {
        if self.control.is_cancelled() {
            return Ok(Outcome::Stopped {
                step: self.tracker.resumed_from(),
            });
        }
        let (control, device, out) = (
            self.control.clone(),
            self.settings.device.clone(),
            self.out.clone(),
        );
        let ckpt = self.out.join("ckpt");
        let joined = tokio::task::spawn_blocking(move || {
            let outcome = f(&control, &device, &out);
            // The stage's tensors are gone: give their memory back while the worker idles.
            stylenerf_engine::release_free_memory();
            outcome
        })
        .await;
        match joined {
            Ok(Ok(outcome)) => Ok(outcome),
            Ok(Err(EngineError::Cancelled)) => Ok(Outcome::Stopped {
                step: latest_checkpoint(&ckpt).unwrap_or(0),
            }),
            Ok(Err(e)) => Err(e.into()),
            Err(e) => Err(TaskError::retryable(format!("the stage panicked: {e}"))),
        }
    }
}

/// The newest complete local checkpoint step in `dir`.
pub(crate) fn latest_checkpoint(dir: &Path) -> Option<u64> {
    CheckpointDir::new(dir, 1)
        .steps()
        .ok()
        .and_then(|s| s.last().copied())
}
