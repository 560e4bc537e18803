//! Pieces shared by the command modules: device selection, presets with `--set` overrides,
//! and progress bars fed by stage progress reports.

use std::time::Duration;

use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use stylenerf_engine::device::parse_device;
use stylenerf_engine::stages::dispatch::check_job_overrides;
use stylenerf_engine::stages::StageControl;
use stylenerf_plan::settings::{apply_overrides, parse_override};
use stylenerf_plan::{bounds, Preset, Stage};

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

/// The engine's check of a job's preset and overrides, for a coordinator this binary starts:
/// a mistyped or out-of-range override is refused at submission instead of failing a worker.
pub fn engine_settings_check() -> stylenerf_server::SettingsCheck {
    stylenerf_server::SettingsCheck(std::sync::Arc::new(check_job_overrides))
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
}
