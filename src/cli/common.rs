//! Pieces shared by the command modules: device selection, presets with `--set` overrides,
//! and progress bars fed by stage progress reports.

use std::time::Duration;

use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use stylenerf_engine::device::parse_device;
use stylenerf_engine::preset::{apply_overrides, parse_override, Preset};
use stylenerf_engine::stages::StageControl;

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
    /// The stage's preset configuration with the overrides applied.
    pub fn config<T: serde::Serialize + serde::de::DeserializeOwned>(
        &self,
        preset: impl Fn(Preset) -> T,
    ) -> anyhow::Result<T> {
        let overrides = self
            .overrides
            .iter()
            .map(|o| parse_override(o))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(apply_overrides(&preset(self.preset), &overrides)?)
    }

    pub fn device(&self) -> anyhow::Result<candle_core::Device> {
        Ok(parse_device(&self.device)?)
    }
}

/// A progress bar for one stage and a [`StageControl`] that feeds it.
pub fn stage_progress(stage: &str) -> (ProgressBar, StageControl) {
    let bar = ProgressBar::new(1);
    bar.set_style(
        ProgressStyle::with_template("{prefix:>16} [{bar:30}] {pos}/{len} {msg} (ETA {eta})")
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
