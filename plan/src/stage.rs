//! The stages of a job: their names (as stored, in task configurations and override keys),
//! the stages whose outputs each reads, which job inputs it reads and the memory a task of it
//! reserves by default.

use serde::{Deserialize, Serialize};

/// One stage of a job. `Stage::ALL` is in dependency order: every stage comes after its
/// upstream stages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    /// Trains the radiance field on the posed photos.
    NerfPretrain,
    /// Renders the field's views (training cameras and a camera path) with depth.
    RenderViews,
    /// Trains the 2D AdaIN decoder on the rendered views and the styles.
    DecoderPretrain,
    /// The stylized field and the decoder learn from each other.
    MutualLearning,
    /// Renders the stylized views, animations and the evaluation.
    RenderStylized,
}

/// What a stage reads besides the outputs of its upstream stages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StageInputs {
    /// The job's dataset (the posed photos).
    pub dataset: bool,
    /// The job's style images.
    pub styles: bool,
    /// The 2D encoder's weights.
    pub encoder: bool,
}

const MIB: i64 = 1 << 20;

impl Stage {
    /// Every stage, in dependency order.
    pub const ALL: [Stage; 5] = [
        Stage::NerfPretrain,
        Stage::RenderViews,
        Stage::DecoderPretrain,
        Stage::MutualLearning,
        Stage::RenderStylized,
    ];

    /// The snake_case name (`nerf_pretrain`, …).
    pub const fn name(self) -> &'static str {
        match self {
            Stage::NerfPretrain => "nerf_pretrain",
            Stage::RenderViews => "render_views",
            Stage::DecoderPretrain => "decoder_pretrain",
            Stage::MutualLearning => "mutual_learning",
            Stage::RenderStylized => "render_stylized",
        }
    }

    /// Every stage's name, in dependency order.
    pub fn names() -> [&'static str; 5] {
        Stage::ALL.map(Stage::name)
    }

    /// The stage named `name`, if any.
    pub fn parse(name: &str) -> Option<Stage> {
        Stage::ALL.into_iter().find(|s| s.name() == name)
    }

    /// The stages whose outputs this stage reads (each of them must have succeeded first).
    pub const fn upstream(self) -> &'static [Stage] {
        match self {
            Stage::NerfPretrain => &[],
            Stage::RenderViews => &[Stage::NerfPretrain],
            Stage::DecoderPretrain => &[Stage::RenderViews],
            Stage::MutualLearning => &[
                Stage::NerfPretrain,
                Stage::RenderViews,
                Stage::DecoderPretrain,
            ],
            Stage::RenderStylized => &[
                Stage::NerfPretrain,
                Stage::RenderViews,
                Stage::DecoderPretrain,
                Stage::MutualLearning,
            ],
        }
    }

    /// The job inputs this stage reads.
    pub const fn inputs(self) -> StageInputs {
        let (dataset, styles) = match self {
            Stage::NerfPretrain => (true, false),
            Stage::RenderViews => (false, false),
            Stage::DecoderPretrain | Stage::MutualLearning | Stage::RenderStylized => (false, true),
        };
        StageInputs {
            dataset,
            styles,
            encoder: styles,
        }
    }

    /// Memory reserved for a task of this stage when the job does not say.
    pub const fn default_memory_bytes(self) -> i64 {
        match self {
            Stage::NerfPretrain => 1024 * MIB,
            Stage::RenderViews => 512 * MIB,
            Stage::DecoderPretrain => 2048 * MIB,
            Stage::MutualLearning => 2048 * MIB,
            Stage::RenderStylized => 1024 * MIB,
        }
    }
}

impl std::fmt::Display for Stage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A name that is not a stage's.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown stage `{0}` (expected one of {names})", names = Stage::names().join(", "))]
pub struct UnknownStage(pub String);

impl std::str::FromStr for Stage {
    type Err = UnknownStage;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Stage::parse(s).ok_or_else(|| UnknownStage(s.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_stage_comes_after_what_it_reads() {
        for (i, stage) in Stage::ALL.into_iter().enumerate() {
            for up in stage.upstream() {
                let j = Stage::ALL.iter().position(|s| s == up).unwrap();
                assert!(j < i, "{stage} reads {up}, which comes later");
            }
            assert_eq!(stage.name().parse::<Stage>(), Ok(stage));
            assert_eq!(
                serde_json::to_value(stage).unwrap(),
                serde_json::json!(stage.name())
            );
        }
        // Only the first stage starts from the job's inputs alone.
        let roots: Vec<Stage> = Stage::ALL
            .into_iter()
            .filter(|s| s.upstream().is_empty())
            .collect();
        assert_eq!(roots, [Stage::NerfPretrain]);
        assert!(Stage::NerfPretrain.inputs().dataset);
        let e = "render".parse::<Stage>().unwrap_err().to_string();
        assert!(e.contains("render") && e.contains("render_views"), "{e}");
    }
}
