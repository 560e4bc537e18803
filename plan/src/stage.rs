//! The stages of a job: their names (as stored, in task configurations and override keys),
//! the stages whose outputs each reads, which job inputs it reads, the programs a worker needs
//! to run it and the memory a task of it reserves by default; and what a job starts from
//! ([`Source`]: a posed dataset, or plain photos or a video, which add the `poses` stage).

use serde::{Deserialize, Serialize};

/// One stage of a job. `Stage::ALL` is in dependency order: every stage comes after its
/// upstream stages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    /// Recovers camera poses for plain photos or a video with COLMAP and writes a posed
    /// dataset; only in jobs that start from photos.
    Poses,
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
    /// The job's posed dataset: the uploaded one, or in a job from photos the `poses` stage's
    /// output (then among the stage's upstream outputs).
    pub dataset: bool,
    /// The job's plain photos or video.
    pub photos: bool,
    /// The job's style images.
    pub styles: bool,
    /// The 2D encoder's weights.
    pub encoder: bool,
}

const MIB: i64 = 1 << 20;

impl Stage {
    /// Every stage, in dependency order.
    pub const ALL: [Stage; 6] = [
        Stage::Poses,
        Stage::NerfPretrain,
        Stage::RenderViews,
        Stage::DecoderPretrain,
        Stage::MutualLearning,
        Stage::RenderStylized,
    ];

    /// The snake_case name (`nerf_pretrain`, …).
    pub const fn name(self) -> &'static str {
        match self {
            Stage::Poses => "poses",
            Stage::NerfPretrain => "nerf_pretrain",
            Stage::RenderViews => "render_views",
            Stage::DecoderPretrain => "decoder_pretrain",
            Stage::MutualLearning => "mutual_learning",
            Stage::RenderStylized => "render_stylized",
        }
    }

    /// Every stage's name, in dependency order.
    pub fn names() -> [&'static str; 6] {
        Stage::ALL.map(Stage::name)
    }

    /// The stage named `name`, if any.
    pub fn parse(name: &str) -> Option<Stage> {
        Stage::ALL.into_iter().find(|s| s.name() == name)
    }

    /// The stages whose outputs this stage reads (each of them must have succeeded first).
    /// A job holds only the stages of its [`Source`]: an upstream stage it lacks is not
    /// waited for (`nerf_pretrain` reads `poses` only in a job from photos).
    pub const fn upstream(self) -> &'static [Stage] {
        match self {
            Stage::Poses => &[],
            Stage::NerfPretrain => &[Stage::Poses],
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
            Stage::Poses | Stage::RenderViews => (false, false),
            Stage::NerfPretrain => (true, false),
            Stage::DecoderPretrain | Stage::MutualLearning | Stage::RenderStylized => (false, true),
        };
        StageInputs {
            dataset,
            photos: matches!(self, Stage::Poses),
            styles,
            encoder: styles,
        }
    }

    /// The programs (from the OS packages) a worker must have to run this stage of a job
    /// from `source`; workers advertise theirs and are handed only what they can run.
    pub fn tools(self, source: Source) -> &'static [&'static str] {
        match (self, source) {
            (Stage::Poses, Source::Video) => &[COLMAP, FFMPEG],
            (Stage::Poses, _) => &[COLMAP],
            _ => &[],
        }
    }

    /// Memory reserved for a task of this stage when the job does not say.
    pub const fn default_memory_bytes(self) -> i64 {
        match self {
            Stage::Poses => 2048 * MIB,
            Stage::NerfPretrain => 1024 * MIB,
            Stage::RenderViews => 512 * MIB,
            Stage::DecoderPretrain => 2048 * MIB,
            Stage::MutualLearning => 2048 * MIB,
            Stage::RenderStylized => 1024 * MIB,
        }
    }
}

/// COLMAP, which recovers camera poses.
pub const COLMAP: &str = "colmap";
/// ffmpeg, which takes frames from a video.
pub const FFMPEG: &str = "ffmpeg";

/// What a job starts from, which decides its stages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Source {
    /// A dataset with camera poses (nerfstudio, Blender, LLFF), as a tar archive.
    Dataset,
    /// Plain photos, as a tar archive: the job starts with `poses`.
    Photos,
    /// A video file: the job starts with `poses` on frames taken from it.
    Video,
}

/// File extensions of the video files a job may start from.
pub const VIDEO_EXTENSIONS: [&str; 7] = ["mp4", "mov", "m4v", "mkv", "avi", "webm", "mts"];

impl Source {
    /// The stages of a job from this source, in dependency order.
    pub fn stages(self) -> Vec<Stage> {
        Stage::ALL
            .into_iter()
            .filter(|&s| s != Stage::Poses || self != Source::Dataset)
            .collect()
    }

    /// The upstream stages of `stage` in a job from this source.
    pub fn upstream(self, stage: Stage) -> Vec<Stage> {
        let present = self.stages();
        stage
            .upstream()
            .iter()
            .copied()
            .filter(|s| present.contains(s))
            .collect()
    }

    /// The file name a job's scene input is stored under (`scene.tar`, `photos.tar`,
    /// `video.mp4`); `extension` is the video's.
    pub fn input_name(self, extension: &str) -> String {
        match self {
            Source::Dataset => "scene.tar".into(),
            Source::Photos => "photos.tar".into(),
            Source::Video => format!("video.{extension}"),
        }
    }

    /// The source of a job whose scene input is stored as `key` (see [`Source::input_name`]).
    pub fn of_input_key(key: &str) -> Source {
        let name = key.rsplit('/').next().unwrap_or(key);
        match name.split_once('.') {
            Some(("photos", "tar")) => Source::Photos,
            Some(("video", ext)) if VIDEO_EXTENSIONS.contains(&ext) => Source::Video,
            _ => Source::Dataset,
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
        assert_eq!(roots, [Stage::Poses]);
        assert!(Stage::NerfPretrain.inputs().dataset);
        assert!(Stage::Poses.inputs().photos);
        let e = "render".parse::<Stage>().unwrap_err().to_string();
        assert!(e.contains("render") && e.contains("render_views"), "{e}");
    }

    #[test]
    fn a_job_from_photos_starts_with_poses_on_a_worker_that_has_colmap() {
        assert_eq!(Source::Dataset.stages()[0], Stage::NerfPretrain);
        assert_eq!(Source::Dataset.stages().len(), Stage::ALL.len() - 1);
        assert_eq!(Source::Photos.stages(), Stage::ALL);
        assert_eq!(Source::Dataset.upstream(Stage::NerfPretrain), []);
        assert_eq!(Source::Video.upstream(Stage::NerfPretrain), [Stage::Poses]);
        assert_eq!(Stage::Poses.tools(Source::Photos), [COLMAP]);
        assert_eq!(Stage::Poses.tools(Source::Video), [COLMAP, FFMPEG]);
        assert!(Stage::NerfPretrain.tools(Source::Video).is_empty());
        for source in [Source::Dataset, Source::Photos, Source::Video] {
            let key = format!("jobs/j-1/inputs/{}", source.input_name("mov"));
            assert_eq!(Source::of_input_key(&key), source, "{key}");
        }
        assert_eq!(
            Source::of_input_key("jobs/j/inputs/video.txt"),
            Source::Dataset
        );
    }
}
