//! Pieces shared by the command modules: device selection, presets with `--set` overrides,
//! and progress bars fed by stage progress reports.

use std::path::Path;
use std::time::Duration;

use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use stylenerf_engine::device::parse_device;
use stylenerf_engine::stages::dispatch::{check_dataset_overrides, check_job_overrides};
use stylenerf_engine::stages::StageControl;
use stylenerf_plan::settings::{apply_overrides, parse_override};
use stylenerf_plan::{bounds, DatasetFacts, Preset, Stage};
use stylenerf_server::CoordinatorConfig;

/// Preset, overrides and device, shared by every training command.
#[derive(Debug, Clone, Args)]
pub struct TrainingArgs {
    /// Schedule and model size: tiny (tests), quick (CPU demo), standard, paper (GPU).
    #[arg(long, default_value = "quick")]
    pub preset: Preset,
    /// Override any setting of the stage's configuration: `--set steps=500 --set lr=0.005`.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
    /// Compute device: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

impl TrainingArgs {
    /// The configuration of `stage`: its preset with the overrides applied, within the
    /// stage's bounds.
    pub fn config<T: serde::Serialize + serde::de::DeserializeOwned>(
        &self,
        stage: Stage,
        preset: impl Fn(Preset) -> T,
    ) -> anyhow::Result<T> {
        let overrides = self
            .overrides
            .iter()
            .map(|o| parse_override(o))
            .collect::<Result<Vec<_>, _>>()?;
        let config = apply_overrides(&preset(self.preset), &overrides)?;
        bounds::check(stage, &config)?;
        Ok(config)
    }

    pub fn device(&self) -> anyhow::Result<candle_core::Device> {
        Ok(parse_device(&self.device)?)
    }
}

/// The engine's checks, for a coordinator this binary starts: a mistyped or out-of-range
/// override, or a dataset whose scene would not load, is refused at submission instead of
/// failing a worker after the upload was accepted.
struct EngineChecks;

impl stylenerf_server::EngineChecks for EngineChecks {
    fn settings(
        &self,
        preset: &str,
        overrides: &serde_json::Map<String, serde_json::Value>,
    ) -> Vec<(String, String)> {
        check_job_overrides(preset, overrides)
    }

    fn dataset(&self, archive: &Path) -> Result<DatasetFacts, String> {
        stylenerf_worker::archive::check_dataset(archive)
    }

    fn dataset_settings(
        &self,
        preset: &str,
        overrides: &serde_json::Map<String, serde_json::Value>,
        dataset: &DatasetFacts,
    ) -> Vec<(String, String)> {
        check_dataset_overrides(preset, overrides, dataset)
    }
}

/// `config` with the engine's checks installed.
pub fn with_engine_checks(mut config: CoordinatorConfig) -> CoordinatorConfig {
    config.engine_checks = Some(std::sync::Arc::new(EngineChecks));
    config
}

/// A progress bar for one stage and a [`StageControl`] that feeds it.
pub fn stage_progress(stage: &str) -> (ProgressBar, StageControl) {
    let bar = ProgressBar::new(1);
    bar.set_style(
        ProgressStyle::with_template("{prefix:>16} [{bar:30}] {pos}/{len} (ETA {eta}) {wide_msg}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_prefix(stage.to_string());
    bar.enable_steady_tick(Duration::from_millis(250));
    let b = bar.clone();
    let control = StageControl::default().with_sink(move |p| {
        b.set_length(p.total.max(1));
        b.set_position(p.step);
        let mut msg = String::new();
        if let Some(loss) = p.loss {
            msg.push_str(&format!("loss {loss:.4}"));
        }
        for (k, v) in &p.metrics {
            msg.push_str(&format!(" {k} {v:.3}"));
        }
        b.set_message(msg);
    });
    (bar, control)
}

#[cfg(test)]
mod tests {
    use stylenerf_engine::stages::camera_paths::PathKind;

    #[test]
    fn the_coordinator_accepts_the_camera_paths_the_engine_renders() {
        assert_eq!(stylenerf_server::CAMERA_PATH_KINDS, PathKind::NAMES);
    }

    /// Archives the coordinator's own checks pass (safe members, a scene file naming images
    /// that are there) but the stages would refuse: refused at upload, naming the member.
    #[tokio::test]
    async fn the_coordinator_refuses_a_dataset_the_stages_would_not_load() {
        use stylenerf_testkit::*;
        let dir = tempfile::tempdir().unwrap();
        let server = start(super::with_engine_checks(config(dir.path()))).await;
        let mut alice = jobs_client(&server, Some(ALICE)).await;
        let kind = pb::UploadKind::DatasetArchive;

        let scene = dir.path().join("scene");
        tiny_scene(&scene);
        let good = tar_dir("scene", &scene);
        upload(&mut alice, kind, "scene.tar", &good).await.unwrap();

        let transforms = std::fs::read(scene.join("transforms.json")).unwrap();
        let first = std::fs::read_dir(scene.join("images"))
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .min()
            .unwrap();
        let broken_image = dir.path().join("broken");
        tiny_scene(&broken_image);
        std::fs::write(broken_image.join("images").join(&first), b"not a png").unwrap();
        let mut bad_field: serde_json::Value = serde_json::from_slice(&transforms).unwrap();
        bad_field["k1"] = "barrel".into();
        let bad_distortion = dir.path().join("distortion");
        tiny_scene(&bad_distortion);
        std::fs::write(
            bad_distortion.join("transforms.json"),
            serde_json::to_vec(&bad_field).unwrap(),
        )
        .unwrap();

        for (folder, needle) in [
            (&broken_image, format!("scene/images/{first}")),
            (&bad_distortion, "k1".to_string()),
        ] {
            let tar = tar_dir("scene", folder);
            let status = upload(&mut alice, kind, "scene.tar", &tar)
                .await
                .unwrap_err();
            assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
            let message = format!("{status:?}");
            assert!(message.contains(&needle), "{needle}: {message}");
            assert!(!message.contains("/tmp"), "temporary paths leak: {message}");
        }
        server.shutdown().await.unwrap();
    }
}
