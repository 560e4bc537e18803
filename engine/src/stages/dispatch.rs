//! The one entry point to every stage, used by the worker (on the folders it downloaded) and by
//! `stylenerf run` (on its own output folder): [`StageConfig::new`] builds a stage's
//! configuration from a preset and a job's overrides, [`run`] runs it on the output folders of
//! the stages the catalogue says it reads ([`Stage::upstream`]), and
//! [`check_job_overrides`] is the same configuration step run for every stage at once, for the
//! coordinator to refuse at submission what a worker would refuse later.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use candle_core::Device;
use serde::Serialize;
use stylenerf_plan::settings::{configure, flatten_overrides};
use stylenerf_plan::{DatasetFacts, Override, Preset, Stage};

use crate::checkpoint::CheckpointDir;
use crate::field::saved;
use crate::poses::{self, PosesOptions, PosesReport};
use crate::scene::Scene;
use crate::stages::camera_paths::{camera_path, PathKind};
use crate::stages::decoder_pretrain::{self, DecoderPretrainConfig, DecoderPretrainReport};
use crate::stages::mutual_learning::{self, MutualConfig, MutualReport};
use crate::stages::nerf_pretrain::{self, NerfConfig, NerfReport};
use crate::stages::render_stylized::{self, RenderStylizedConfig, RenderStylizedReport};
use crate::stages::render_views::{self, RenderViewsConfig};
use crate::stages::{Outcome, StageControl};
use crate::style2d::images::StyleImage;
use crate::style2d::weights::EncoderWeights;
use crate::views::RenderedViews;
use crate::{EngineError, Result};

/// A stage's configuration, typed by its stage.
#[derive(Debug, Clone)]
pub enum StageConfig {
    Poses(PosesOptions),
    NerfPretrain(NerfConfig),
    RenderViews(RenderViewsConfig),
    DecoderPretrain(DecoderPretrainConfig),
    MutualLearning(MutualConfig),
    RenderStylized(RenderStylizedConfig),
}

impl StageConfig {
    /// `stage`'s configuration: its `preset` with the job overrides addressed to it
    /// (`<stage>.<key>`), within its bounds. Errors name the full key.
    pub fn new(stage: Stage, preset: Preset, overrides: &[Override]) -> Result<Self> {
        Ok(match stage {
            Stage::Poses => {
                Self::Poses(configure(&PosesOptions::preset(preset), stage, overrides)?)
            }
            Stage::NerfPretrain => {
                Self::NerfPretrain(configure(&NerfConfig::preset(preset), stage, overrides)?)
            }
            Stage::RenderViews => Self::RenderViews(configure(
                &RenderViewsConfig::preset(preset),
                stage,
                overrides,
            )?),
            Stage::DecoderPretrain => Self::DecoderPretrain(configure(
                &DecoderPretrainConfig::preset(preset),
                stage,
                overrides,
            )?),
            Stage::MutualLearning => {
                Self::MutualLearning(configure(&MutualConfig::preset(preset), stage, overrides)?)
            }
            Stage::RenderStylized => Self::RenderStylized(configure(
                &RenderStylizedConfig::preset(preset),
                stage,
                overrides,
            )?),
        })
    }

    pub fn stage(&self) -> Stage {
        match self {
            Self::Poses(_) => Stage::Poses,
            Self::NerfPretrain(_) => Stage::NerfPretrain,
            Self::RenderViews(_) => Stage::RenderViews,
            Self::DecoderPretrain(_) => Stage::DecoderPretrain,
            Self::MutualLearning(_) => Stage::MutualLearning,
            Self::RenderStylized(_) => Stage::RenderStylized,
        }
    }
}

/// What a stage reads besides its configuration. The catalogue ([`Stage::inputs`],
/// [`Stage::upstream`]) says which of these a stage needs; the others may be left empty.
#[derive(Debug, Clone, Copy)]
pub struct Inputs<'a> {
    /// The job's dataset folder (in a job from photos, `nerf_pretrain` reads the `poses`
    /// stage's output instead).
    pub dataset: Option<&'a Path>,
    /// The job's photos: a folder of images or a video file.
    pub photos: Option<&'a Path>,
    /// The output folder of each upstream stage.
    pub upstream: &'a BTreeMap<Stage, PathBuf>,
    /// The job's styles, in the job's order.
    pub styles: &'a [StyleImage],
    /// The 2D encoder (the bundled VGG-16 unless the caller loaded other weights).
    pub encoder: Option<&'a EncoderWeights>,
    /// A decoder for `decoder_pretrain` to start from.
    pub init_decoder: Option<&'a Path>,
    /// A camera path for `render_stylized` to render instead of `render_views`' path.
    pub path: Option<PathRequest>,
}

/// A camera path through the training cameras.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PathRequest {
    pub kind: PathKind,
    pub frames: usize,
}

/// A stage's report, typed by its stage.
#[derive(Debug, Clone)]
pub enum StageReport {
    Poses(PosesReport),
    NerfPretrain(NerfReport),
    RenderViews { views: usize },
    DecoderPretrain(DecoderPretrainReport),
    MutualLearning(MutualReport),
    RenderStylized(RenderStylizedReport),
}

impl StageReport {
    /// The report's headline numbers (PSNR, seconds, losses, counts) by name.
    pub fn metrics(&self) -> BTreeMap<String, f64> {
        match self {
            Self::Poses(r) => r.metrics(),
            Self::NerfPretrain(r) => numeric_fields(r),
            Self::RenderViews { views } => BTreeMap::from([("views".into(), *views as f64)]),
            Self::DecoderPretrain(r) => numeric_fields(r),
            Self::MutualLearning(r) => numeric_fields(r),
            Self::RenderStylized(r) => BTreeMap::from([
                ("specs".into(), r.specs.len() as f64),
                ("seconds".into(), r.seconds),
            ]),
        }
    }
}

/// The top-level numeric fields of a report.
fn numeric_fields(report: &impl Serialize) -> BTreeMap<String, f64> {
    match serde_json::to_value(report) {
        Ok(serde_json::Value::Object(map)) => map
            .into_iter()
            .filter_map(|(k, v)| v.as_f64().map(|v| (k, v)))
            .collect(),
        _ => BTreeMap::new(),
    }
}

/// Runs the configured stage into `out` (its checkpoints included: an interrupted run resumes).
pub fn run(
    config: &StageConfig,
    inputs: &Inputs,
    out: &Path,
    control: &StageControl,
    device: &Device,
) -> Result<Outcome<StageReport>> {
    let stage = config.stage();
    let dir = |of: Stage| -> Result<&Path> {
        inputs
            .upstream
            .get(&of)
            .map(PathBuf::as_path)
            .ok_or_else(|| EngineError::config(stage.name(), format!("needs the output of {of}")))
    };
    let encoder = || {
        inputs
            .encoder
            .ok_or_else(|| EngineError::config(stage.name(), "needs the 2D encoder's weights"))
    };
    Ok(match config {
        StageConfig::Poses(cfg) => {
            let photos = inputs.photos.ok_or_else(|| {
                EngineError::config(stage.name(), "needs the job's photos or video")
            })?;
            // COLMAP's state lives under ckpt/ (never an output) and is checkpointed there.
            let ckpt = CheckpointDir::new(out.join("ckpt"), 1);
            let work = ckpt.path().join("work");
            poses::run(photos, &work, out, cfg, control, Some(&ckpt))?.map(StageReport::Poses)
        }
        StageConfig::NerfPretrain(cfg) => {
            // A job from photos trains on the dataset its poses stage wrote.
            let data = inputs
                .upstream
                .get(&Stage::Poses)
                .map(PathBuf::as_path)
                .or(inputs.dataset)
                .ok_or_else(|| EngineError::config(stage.name(), "needs the job's dataset"))?;
            let scene = Scene::load(data, &cfg.load_options())?;
            nerf_pretrain::run(&scene, cfg, out, control, device)?.map(StageReport::NerfPretrain)
        }
        StageConfig::RenderViews(cfg) => {
            render_views::run(dir(Stage::NerfPretrain)?, cfg, out, control, device)?
                .map(|views| StageReport::RenderViews { views: views.len() })
        }
        StageConfig::DecoderPretrain(cfg) => {
            let views = RenderedViews::load(dir(Stage::RenderViews)?)?;
            let encoder = encoder()?;
            let inputs = decoder_pretrain::Inputs {
                views: &views,
                styles: inputs.styles,
                encoder,
                init_decoder: inputs.init_decoder,
            };
            decoder_pretrain::run(inputs, cfg, out, control, device)?
                .map(StageReport::DecoderPretrain)
        }
        StageConfig::MutualLearning(cfg) => {
            let views = RenderedViews::load(dir(Stage::RenderViews)?)?;
            let encoder = encoder()?;
            let inputs = mutual_learning::Inputs {
                field_dir: dir(Stage::NerfPretrain)?,
                views: &views,
                decoder_dir: dir(Stage::DecoderPretrain)?,
                styles: inputs.styles,
                encoder,
            };
            mutual_learning::run(inputs, cfg, out, control, device)?
                .map(StageReport::MutualLearning)
        }
        StageConfig::RenderStylized(cfg) => {
            let field_dir = dir(Stage::NerfPretrain)?;
            let views = RenderedViews::load(dir(Stage::RenderViews)?)?;
            let encoder = encoder()?;
            let path = match inputs.path {
                None => None,
                Some(request) => {
                    let train = saved::load_meta(field_dir)?.train_cameras;
                    let keyframes = train.len().clamp(2, 8);
                    Some(camera_path(request.kind, &train, request.frames, keyframes))
                }
            };
            let inputs = render_stylized::Inputs {
                field_dir,
                views: &views,
                decoder_dir: dir(Stage::DecoderPretrain)?,
                mutual_dir: dir(Stage::MutualLearning)?,
                styles: inputs.styles,
                encoder,
                path: path.as_deref(),
            };
            render_stylized::run(inputs, cfg, out, control, device)?
                .map(StageReport::RenderStylized)
        }
    })
}

/// Checks a job's overrides for `preset` as every stage will apply them: keys name a stage and
/// one of its settings, values have the setting's type and lie within its bounds. Returns
/// every problem as `(key, reason)`.
pub fn check_job_overrides(
    preset: &str,
    overrides: &serde_json::Map<String, serde_json::Value>,
) -> Vec<(String, String)> {
    let preset: Preset = match preset.parse() {
        Ok(preset) => preset,
        Err(e) => return vec![("preset".into(), e.to_string())],
    };
    let overrides = &flatten_overrides(overrides);
    let mut problems: Vec<(String, String)> = Vec::new();
    for stage in Stage::ALL {
        let problem = match StageConfig::new(stage, preset, overrides) {
            Ok(_) => continue,
            Err(EngineError::Config { field, reason }) => (field, reason),
            Err(e) => ("config_overrides_json".into(), e.to_string()),
        };
        // A key that names no stage is refused by every stage: report it once.
        if !problems.contains(&problem) {
            problems.push(problem);
        }
    }
    problems
}

/// Checks a job's overrides (already found valid by [`check_job_overrides`]) against what its
/// dataset holds: what a stage would refuse on this dataset, as `(key, reason)`.
pub fn check_dataset_overrides(
    preset: &str,
    overrides: &serde_json::Map<String, serde_json::Value>,
    dataset: &DatasetFacts,
) -> Vec<(String, String)> {
    let Ok(preset) = preset.parse::<Preset>() else {
        return Vec::new();
    };
    let overrides = &flatten_overrides(overrides);
    let mut problems = Vec::new();
    if let Ok(StageConfig::NerfPretrain(cfg)) =
        StageConfig::new(Stage::NerfPretrain, preset, overrides)
    {
        let refusal = (!dataset.train_depth)
            .then(|| nerf_pretrain::without_depth(&cfg, "the dataset"))
            .flatten();
        if let Some(EngineError::Config { field, reason }) = refusal {
            problems.push((field, reason));
        }
    }
    problems
}

#[cfg(test)]
mod tests {
    use super::*;
    use stylenerf_plan::settings::parse_override;

    fn check(preset: &str, overrides: &[&str]) -> Vec<(String, String)> {
        let parsed = overrides
            .iter()
            .map(|o| parse_override(o).unwrap())
            .collect();
        check_job_overrides(preset, &parsed)
    }

    #[test]
    fn a_depth_loss_is_refused_for_a_dataset_without_depth_naming_the_key() {
        let overrides = ["nerf_pretrain.depth_weight=0.1"]
            .iter()
            .map(|o| parse_override(o).unwrap())
            .collect();
        let without = DatasetFacts { train_depth: false };
        let problems = check_dataset_overrides("quick", &overrides, &without);
        assert_eq!(problems.len(), 1, "{problems:?}");
        assert_eq!(problems[0].0, "nerf_pretrain.depth_weight");
        assert!(problems[0].1.contains("depth map"), "{problems:?}");
        let with = DatasetFacts { train_depth: true };
        assert_eq!(check_dataset_overrides("quick", &overrides, &with), []);
        // Without the setting, no dataset lacks anything.
        let none = serde_json::Map::new();
        assert_eq!(check_dataset_overrides("quick", &none, &without), []);
    }

    #[test]
    fn every_preset_is_within_bounds() {
        for preset in Preset::ALL {
            assert_eq!(check(preset.name(), &[]), [], "{preset}");
        }
    }

    #[test]
    fn overrides_that_would_exhaust_a_worker_are_refused_naming_the_key() {
        for (overrides, key) in [
            (
                vec!["nerf_pretrain.rays_per_batch=1000000000000"],
                "nerf_pretrain.rays_per_batch",
            ),
            (
                vec!["nerf_pretrain.field.grid.levels=1000000"],
                "nerf_pretrain.field.grid.levels",
            ),
            (
                vec!["nerf_pretrain.field.grid.log2_table_size=60"],
                "nerf_pretrain.field.grid.log2_table_size",
            ),
            (
                vec![
                    "nerf_pretrain.field.grid.log2_table_size=24",
                    "nerf_pretrain.field.grid.levels=32",
                ],
                "nerf_pretrain.field.grid",
            ),
            (
                vec!["nerf_pretrain.steps=1000000000000"],
                "nerf_pretrain.steps",
            ),
            (vec!["mutual_learning.steps=-3"], "mutual_learning.steps"),
            (vec!["decoder_pretrain.lr=1e400"], "decoder_pretrain.lr"),
            (
                vec!["decoder_pretrain.start=bundle"],
                "decoder_pretrain.start",
            ),
            (vec!["render_views.chunk=0"], "render_views.chunk"),
            (vec!["nerf_pretrain.nope=1"], "nerf_pretrain.nope"),
            (vec!["steps=3"], "steps"),
        ] {
            let problems = check("quick", &overrides);
            assert!(
                problems.iter().any(|(k, _)| k == key),
                "{overrides:?}: {problems:?}"
            );
        }
        assert_eq!(
            check(
                "quick",
                &["nerf_pretrain.steps=50", "nerf_pretrain.seed=123456789012"]
            ),
            []
        );
        assert_eq!(check("huge", &[])[0].0, "preset");
    }

    #[test]
    fn a_stage_refuses_to_run_without_what_it_reads() {
        let config = StageConfig::new(Stage::RenderViews, Preset::Tiny, &[]).unwrap();
        let none = BTreeMap::new();
        let inputs = Inputs {
            dataset: None,
            photos: None,
            upstream: &none,
            styles: &[],
            encoder: None,
            init_decoder: None,
            path: None,
        };
        let out = std::env::temp_dir().join("stylenerf-dispatch-test-unused");
        let err = run(
            &config,
            &inputs,
            &out,
            &StageControl::default(),
            &Device::Cpu,
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("render_views") && err.contains("nerf_pretrain"),
            "{err}"
        );
        assert!(!out.exists());
    }
}
