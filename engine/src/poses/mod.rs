//! Camera poses from plain photos or a video, with COLMAP: what `stylenerf scene from-photos`
//! runs. Frames are taken from the input ([`input`]); COLMAP extracts SIFT features, matches
//! them (exhaustively for a photo set, sequentially for a video, with a vocabulary tree built
//! from the set's own features for large sets) and maps; the largest model is written as a
//! nerfstudio dataset at the working resolution ([`dataset`]) with a report of what was
//! registered. Each COLMAP step is a checkpoint: its state (the database, the models) stays in
//! the work folder, and a run that was stopped or killed resumes at the first unfinished step.
//! As the service's `poses` stage ([`crate::stages::dispatch`]) the work folder is also saved
//! after each step as a folder checkpoint ([`CheckpointDir::save_folder`]), which the worker
//! uploads, so another worker resumes where this one stopped.
//! When registration fails or covers too few images the error says so, with the likely cause.

pub mod align;
mod dataset;
pub mod input;
pub mod model;
mod tools;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};

pub use input::{InputKind, VideoSampling};
use model::SparseModel;
pub use tools::{installed as installed_tools, Tool};

use crate::checkpoint::{write_json_atomic, CheckpointDir};
use crate::stages::{Outcome, Progress, StageControl};
use crate::{EngineError, Result};

/// How COLMAP matches features between images.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Matcher {
    /// Sequential for a video, exhaustive for up to [`EXHAUSTIVE_MAX`] photos, else a
    /// vocabulary tree.
    Auto,
    Exhaustive,
    Sequential,
    VocabTree,
}

/// Photo sets up to this size are matched exhaustively (every pair).
pub const EXHAUSTIVE_MAX: usize = 300;

/// The camera model COLMAP estimates (one camera shared by all images).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum CameraModel {
    /// Focal lengths, principal point and radial/tangential distortion (phone photos).
    #[serde(rename = "OPENCV")]
    Opencv,
    /// One focal length, principal point, one radial term.
    #[serde(rename = "SIMPLE_RADIAL")]
    SimpleRadial,
    /// No distortion.
    #[serde(rename = "PINHOLE")]
    Pinhole,
}

impl CameraModel {
    fn colmap_name(self) -> &'static str {
        match self {
            Self::Opencv => "OPENCV",
            Self::SimpleRadial => "SIMPLE_RADIAL",
            Self::Pinhole => "PINHOLE",
        }
    }
}

/// What `from-photos` and the `poses` stage do.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PosesOptions {
    /// Longest side of the dataset's images (the working resolution).
    pub max_side: u32,
    /// Longest side COLMAP extracts features at.
    pub feature_max_side: u32,
    /// Most SIFT features kept per image (CPU matching time grows with its square).
    pub max_features: u32,
    pub matcher: Matcher,
    pub camera_model: CameraModel,
    pub video: VideoSampling,
    /// Fewer registered images than this fraction is an error.
    pub min_registered: f64,
}

impl Default for PosesOptions {
    fn default() -> Self {
        Self {
            max_side: 1024,
            feature_max_side: 1600,
            max_features: 8192,
            matcher: Matcher::Auto,
            camera_model: CameraModel::Opencv,
            video: VideoSampling {
                fps: 4.0,
                max_frames: 150,
                max_side: 1600,
            },
            min_registered: 0.5,
        }
    }
}

impl PosesOptions {
    /// The `poses` stage's settings for `preset`: `tiny` (tests) works on small images and
    /// few features; the others as `from-photos`.
    pub fn preset(preset: stylenerf_plan::Preset) -> Self {
        match preset {
            stylenerf_plan::Preset::Tiny => Self {
                max_side: 256,
                feature_max_side: 1024,
                max_features: 4096,
                ..Self::default()
            },
            _ => Self::default(),
        }
    }
}

/// What a run recovered (also written as `poses_report.json` beside `transforms.json`, and
/// its numbers as `metrics.json`, written last).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PosesReport {
    pub input: String,
    pub images: usize,
    pub registered: usize,
    /// Images COLMAP could not place.
    pub unregistered: Vec<String>,
    pub mean_reprojection_px: f64,
    pub points: usize,
    /// Mean SIFT features per image.
    pub mean_features: f64,
    pub matcher: Matcher,
    pub camera_model: CameraModel,
    /// Width and height of the written images.
    pub resolution: (u32, u32),
    /// The sparse points' extent (2nd to 98th percentile per axis), in the dataset's world.
    pub sparse_box: [[f64; 3]; 2],
    /// Seconds each step took, by step.
    pub seconds: BTreeMap<String, f64>,
}

/// The steps, in order; each one is a checkpoint.
const STEPS: [&str; 5] = ["frames", "features", "matches", "mapping", "dataset"];

/// The work folder's record of finished steps.
#[derive(Debug, Default, Serialize, Deserialize)]
struct Checkpoint {
    done: Vec<String>,
    images: Vec<String>,
    sharpness: BTreeMap<String, f64>,
    matcher: Option<Matcher>,
    seconds: BTreeMap<String, f64>,
}

/// Recovers camera poses for `input` (a folder of photos or a video) and writes a nerfstudio
/// dataset into `out`, keeping COLMAP's state in `work` (resumable). With `snapshots`, the
/// work folder is also saved there after each step, and restored from there when `work` has
/// no state of its own (a task resumed on another worker).
pub fn run(
    input: &Path,
    work: &Path,
    out: &Path,
    opts: &PosesOptions,
    control: &StageControl,
    snapshots: Option<&CheckpointDir>,
) -> Result<Outcome<PosesReport>> {
    let kind = InputKind::of(input)?;
    let colmap = Tool::colmap()?;
    for dir in [work, out] {
        std::fs::create_dir_all(dir).map_err(|e| EngineError::io(dir, e))?;
    }
    // The dataset's images/ are written at the working resolution: never over the originals.
    let same = |a: &Path, b: &Path| {
        a.canonicalize()
            .is_ok_and(|a| b.canonicalize().is_ok_and(|b| a == b))
    };
    if kind == InputKind::Photos && same(input, &out.join("images")) {
        return Err(EngineError::config(
            "out",
            format!(
                "{}/images is the input folder: the downscaled images would replace the \
                 photos; choose another output folder",
                out.display()
            ),
        ));
    }
    let ck_path = work.join("poses_checkpoint.json");
    if let (false, Some(dir)) = (ck_path.exists(), snapshots) {
        if let Some((step, ())) = dir.restore_folder(work)? {
            tracing::info!(step, "COLMAP's state restored from its checkpoint");
        }
    }
    let mut ck: Checkpoint = match std::fs::read(&ck_path) {
        Ok(bytes) => serde_json::from_slice(&bytes)
            .map_err(|e| EngineError::artifact(&ck_path, format!("unreadable: {e}")))?,
        Err(_) => Checkpoint::default(),
    };
    let log = work.join("colmap.log");
    let image_dir = match kind {
        InputKind::Photos => input.to_path_buf(),
        InputKind::Video => work.join("frames"),
    };
    let db = work.join("database.db");
    let sparse = work.join("sparse");
    let resumed = ck.done.len() as u64;

    for (k, &step) in STEPS.iter().enumerate() {
        if ck.done.iter().any(|d| d == step) {
            continue;
        }
        control.report(&Progress {
            stage: "poses".into(),
            step: k as u64,
            total: STEPS.len() as u64,
            resumed_from: resumed,
            ..Progress::default()
        });
        let start = Instant::now();
        match step {
            "frames" => {
                ck.images = match kind {
                    InputKind::Photos => input::photos(input)?,
                    InputKind::Video => {
                        let _ = std::fs::remove_dir_all(&image_dir);
                        let frames =
                            input::video_frames(input, &image_dir, &opts.video, &log, control)?;
                        ck.sharpness = frames.iter().cloned().collect();
                        frames.into_iter().map(|(n, _)| n).collect()
                    }
                };
            }
            "features" => {
                remove_file(&db)?;
                let list = work.join("image_list.txt");
                crate::checkpoint::write_atomic(&list, ck.images.join("\n").as_bytes())?;
                let args = args(&[
                    ("feature_extractor", None),
                    ("--database_path", Some(path(&db))),
                    ("--image_path", Some(path(&image_dir))),
                    ("--image_list_path", Some(path(&list))),
                    ("--ImageReader.single_camera", Some("1".into())),
                    (
                        "--ImageReader.camera_model",
                        Some(opts.camera_model.colmap_name().into()),
                    ),
                    ("--SiftExtraction.use_gpu", Some("0".into())),
                    (
                        "--SiftExtraction.max_image_size",
                        Some(opts.feature_max_side.to_string()),
                    ),
                    (
                        "--SiftExtraction.max_num_features",
                        Some(opts.max_features.to_string()),
                    ),
                ]);
                colmap.run("feature extraction", &args, &log, control)?;
            }
            "matches" => {
                let matcher = resolve_matcher(opts.matcher, kind, ck.images.len());
                match_features(&colmap, matcher, &db, work, &log, control)?;
                ck.matcher = Some(matcher);
            }
            "mapping" => {
                let _ = std::fs::remove_dir_all(&sparse);
                std::fs::create_dir_all(&sparse).map_err(|e| EngineError::io(&sparse, e))?;
                let args = args(&[
                    ("mapper", None),
                    ("--database_path", Some(path(&db))),
                    ("--image_path", Some(path(&image_dir))),
                    ("--output_path", Some(path(&sparse))),
                    ("--Mapper.ba_global_function_tolerance", Some("1e-6".into())),
                ]);
                // A mapper that found no initial pair exits with an error; that is a finding
                // about the photos, reported below with its likely cause.
                if let Err(e) = colmap.run("mapping", &args, &log, control) {
                    if matches!(e, EngineError::Cancelled) || !models(&sparse).is_empty() {
                        return Err(e);
                    }
                }
            }
            "dataset" => {
                let model = largest_model(&colmap, &sparse, work, &log, control)?;
                let report = report(input, kind, &ck, model.as_ref(), opts, &log)?;
                let model = model.expect("report refuses a missing model");
                let resolution =
                    dataset::write(&model, &image_dir, out, opts.max_side, &ck.sharpness)?;
                ck.seconds
                    .insert(step.into(), start.elapsed().as_secs_f64());
                let report = PosesReport {
                    resolution,
                    seconds: ck.seconds.clone(),
                    ..report
                };
                write_json_atomic(&out.join("poses_report.json"), &report)?;
                write_json_atomic(&out.join("metrics.json"), &report.metrics())?;
                ck.done.push(step.into());
                write_json_atomic(&ck_path, &ck)?;
                return Ok(Outcome::Done(report));
            }
            _ => unreachable!("STEPS lists every step"),
        }
        ck.seconds
            .insert(step.into(), start.elapsed().as_secs_f64());
        ck.done.push(step.into());
        write_json_atomic(&ck_path, &ck)?;
        if let Some(dir) = snapshots {
            dir.save_folder(k as u64 + 1, work, &())?;
        }
        if control.should_stop(k as u64 + 1) {
            return Ok(Outcome::Stopped { step: k as u64 + 1 });
        }
    }
    // Every step was done by an earlier run: its report stands.
    let report_path = out.join("poses_report.json");
    let bytes = std::fs::read(&report_path).map_err(|e| EngineError::io(&report_path, e))?;
    serde_json::from_slice(&bytes)
        .map(Outcome::Done)
        .map_err(|e| EngineError::artifact(&report_path, format!("unreadable: {e}")))
}

impl PosesReport {
    /// The report's headline numbers by name.
    pub fn metrics(&self) -> BTreeMap<String, f64> {
        BTreeMap::from([
            ("images".into(), self.images as f64),
            ("registered".into(), self.registered as f64),
            ("mean_reprojection_px".into(), self.mean_reprojection_px),
            ("points".into(), self.points as f64),
            ("mean_features".into(), self.mean_features),
            ("seconds".into(), self.seconds.values().sum()),
        ])
    }
}

fn resolve_matcher(m: Matcher, kind: InputKind, images: usize) -> Matcher {
    match (m, kind) {
        (Matcher::Auto, InputKind::Video) => Matcher::Sequential,
        (Matcher::Auto, InputKind::Photos) if images <= EXHAUSTIVE_MAX => Matcher::Exhaustive,
        (Matcher::Auto, InputKind::Photos) => Matcher::VocabTree,
        (m, _) => m,
    }
}

fn match_features(
    colmap: &Tool,
    matcher: Matcher,
    db: &Path,
    work: &Path,
    log: &Path,
    control: &StageControl,
) -> Result<()> {
    let db_arg = ("--database_path", Some(path(db)));
    let no_gpu = ("--SiftMatching.use_gpu", Some("0".to_string()));
    let args = match matcher {
        Matcher::Exhaustive | Matcher::Auto => {
            args(&[("exhaustive_matcher", None), db_arg, no_gpu])
        }
        Matcher::Sequential => args(&[
            ("sequential_matcher", None),
            db_arg,
            no_gpu,
            ("--SequentialMatching.overlap", Some("10".into())),
            ("--SequentialMatching.quadratic_overlap", Some("1".into())),
        ]),
        Matcher::VocabTree => {
            // The tree is built from this set's own features: nothing is downloaded.
            let tree = work.join("vocab_tree.bin");
            let build = args(&[
                ("vocab_tree_builder", None),
                db_arg.clone(),
                ("--vocab_tree_path", Some(path(&tree))),
                ("--num_visual_words", Some("4096".into())),
            ]);
            colmap.run("vocabulary tree", &build, log, control)?;
            args(&[
                ("vocab_tree_matcher", None),
                db_arg,
                no_gpu,
                ("--VocabTreeMatching.vocab_tree_path", Some(path(&tree))),
            ])
        }
    };
    colmap.run("feature matching", &args, log, control)
}

/// The models the mapper wrote (`sparse/0`, `sparse/1`, …).
fn models(sparse: &Path) -> Vec<PathBuf> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(sparse)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join("images.bin").is_file() || p.join("images.txt").is_file())
        .collect();
    dirs.sort();
    dirs
}

/// The model with the most registered images, converted to text and read; `None` when the
/// mapper produced none.
fn largest_model(
    colmap: &Tool,
    sparse: &Path,
    work: &Path,
    log: &Path,
    control: &StageControl,
) -> Result<Option<SparseModel>> {
    let mut best: Option<SparseModel> = None;
    for (i, dir) in models(sparse).iter().enumerate() {
        let text = work.join("text").join(i.to_string());
        std::fs::create_dir_all(&text).map_err(|e| EngineError::io(&text, e))?;
        let args = args(&[
            ("model_converter", None),
            ("--input_path", Some(path(dir))),
            ("--output_path", Some(path(&text))),
            ("--output_type", Some("TXT".into())),
        ]);
        colmap.run("model conversion", &args, log, control)?;
        let model = SparseModel::read(&text)?;
        if best
            .as_ref()
            .is_none_or(|b| model.images.len() > b.images.len())
        {
            best = Some(model);
        }
    }
    Ok(best)
}

/// The report of a model, or the error that explains why registration failed.
fn report(
    input: &Path,
    kind: InputKind,
    ck: &Checkpoint,
    model: Option<&SparseModel>,
    opts: &PosesOptions,
    log: &Path,
) -> Result<PosesReport> {
    let total = ck.images.len();
    let registered = model.map_or(0, |m| m.images.len());
    let mean_features = mean_features(log);
    if model.is_none() || (registered as f64) < opts.min_registered * total as f64 {
        let cause = if mean_features < 150.0 {
            format!(
                "COLMAP found few features per image (mean {mean_features:.0}): the images are \
                 likely textureless, blurred or too small"
            )
        } else if kind == InputKind::Video {
            "consecutive frames do not overlap enough to be matched: likely motion blur or a \
             camera moving too fast; move slowly, or sample more frames (--fps)"
                .to_string()
        } else {
            "the photos likely overlap too little: take them closer together, each sharing \
             60–80% of its view with the next, and avoid plain walls and reflective surfaces"
                .to_string()
        };
        return Err(EngineError::dataset(
            input,
            "images",
            format!(
                "COLMAP registered {registered} of {total} images (at least {:.0}% needed); \
                 {cause}. COLMAP's log: {}",
                opts.min_registered * 100.0,
                log.display()
            ),
        ));
    }
    let model = model.expect("checked above");
    let placed: std::collections::BTreeSet<&str> =
        model.images.iter().map(|i| i.name.as_str()).collect();
    let unregistered: Vec<String> = ck
        .images
        .iter()
        .filter(|n| !placed.contains(n.as_str()))
        .cloned()
        .collect();
    if !unregistered.is_empty() {
        tracing::warn!(
            "COLMAP registered {registered} of {total} images; not placed: {}",
            unregistered.join(", ")
        );
    }
    Ok(PosesReport {
        input: input.display().to_string(),
        images: total,
        registered,
        unregistered,
        mean_reprojection_px: model.mean_reprojection_error(),
        points: model.points.len(),
        mean_features,
        matcher: ck.matcher.unwrap_or(Matcher::Auto),
        camera_model: opts.camera_model,
        resolution: (0, 0),
        sparse_box: sparse_box(model),
        seconds: ck.seconds.clone(),
    })
}

/// Mean of the `Features: N` lines COLMAP's feature extractor logs per image (0 when absent).
fn mean_features(log: &Path) -> f64 {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    let counts: Vec<f64> = text
        .lines()
        .filter_map(|l| l.trim().strip_prefix("Features:"))
        .filter_map(|v| v.trim().parse().ok())
        .collect();
    counts.iter().sum::<f64>() / counts.len().max(1) as f64
}

fn sparse_box(model: &SparseModel) -> [[f64; 3]; 2] {
    let mut lo = [0.0; 3];
    let mut hi = [0.0; 3];
    for axis in 0..3 {
        let mut v: Vec<f64> = model.points.iter().map(|p| p.position[axis]).collect();
        if v.is_empty() {
            continue;
        }
        v.sort_by(f64::total_cmp);
        let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
        (lo[axis], hi[axis]) = (at(0.02), at(0.98));
    }
    [lo, hi]
}

fn remove_file(p: &Path) -> Result<()> {
    match std::fs::remove_file(p) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(EngineError::io(p, e)),
        _ => Ok(()),
    }
}

fn path(p: &Path) -> String {
    p.to_string_lossy().into_owned()
}

fn args(pairs: &[(&str, Option<String>)]) -> Vec<String> {
    pairs
        .iter()
        .flat_map(|(k, v)| std::iter::once(k.to_string()).chain(v.clone()))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_matcher_follows_the_input() {
        for (asked, kind, images, chosen) in [
            (Matcher::Auto, InputKind::Video, 10, Matcher::Sequential),
            (Matcher::Auto, InputKind::Photos, 50, Matcher::Exhaustive),
            (Matcher::Auto, InputKind::Photos, 301, Matcher::VocabTree),
            (
                Matcher::Sequential,
                InputKind::Photos,
                5,
                Matcher::Sequential,
            ),
        ] {
            assert_eq!(resolve_matcher(asked, kind, images), chosen);
        }
    }

    #[test]
    fn feature_counts_are_read_from_the_log() {
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("log");
        std::fs::write(
            &log,
            "Processed file [1/2]\n  Features:        300\n  Features: 100\n",
        )
        .unwrap();
        assert_eq!(mean_features(&log), 200.0);
        assert_eq!(mean_features(&dir.path().join("none")), 0.0);
    }
}
