//! What the poses step starts from: a folder of photos, or a video whose frames are sampled
//! with ffmpeg and filtered by sharpness (the sharpest frame of each stretch is kept, so motion
//! blur does not reach COLMAP).

use std::path::Path;

use image::GrayImage;
use rayon::prelude::*;

use super::tools::Tool;
use crate::image_io::image_files;
use crate::stages::StageControl;
use crate::{EngineError, Result};
use stylenerf_plan::stage::VIDEO_EXTENSIONS;

/// The kind of input, which also decides how COLMAP matches the images.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum InputKind {
    Photos,
    Video,
}

impl InputKind {
    pub fn of(input: &Path) -> Result<Self> {
        if input.is_dir() {
            return Ok(Self::Photos);
        }
        let ext = input
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match ext {
            Some(e) if VIDEO_EXTENSIONS.contains(&e.as_str()) && input.is_file() => Ok(Self::Video),
            _ if !input.exists() => Err(EngineError::dataset(input, "input", "does not exist")),
            _ => Err(EngineError::dataset(
                input,
                "input",
                format!(
                    "neither a folder of photos nor a video ({})",
                    VIDEO_EXTENSIONS.join(", ")
                ),
            )),
        }
    }
}

/// The photos of a folder (PNG and JPEG, in name order), as names relative to it.
pub fn photos(dir: &Path) -> Result<Vec<String>> {
    let names: Vec<String> = image_files(dir)?
        .iter()
        .filter_map(|p| Some(p.file_name()?.to_str()?.to_string()))
        .collect();
    if names.len() < 3 {
        return Err(EngineError::dataset(
            dir,
            "images",
            format!(
                "found {} PNG/JPEG photos; camera poses need at least 3 overlapping views \
                 (20 or more around the subject work best)",
                names.len()
            ),
        ));
    }
    Ok(names)
}

/// How frames are taken from a video.
#[derive(Debug, Clone, Copy, serde::Serialize, serde::Deserialize)]
pub struct VideoSampling {
    /// Candidate frames per second of video.
    pub fps: f32,
    /// Frames kept at most: the candidates are split into this many stretches, and the sharpest
    /// of each is kept.
    pub max_frames: usize,
    /// Longest side of the extracted frames.
    pub max_side: u32,
}

/// Extracts frames of `video` into `dir` (empty or missing): ffmpeg writes candidates, the
/// sharpest of each stretch are kept as `frame_00000.png`, … and the rest deleted. Returns
/// the kept names and their sharpness.
pub fn video_frames(
    video: &Path,
    dir: &Path,
    sampling: &VideoSampling,
    log: &Path,
    control: &StageControl,
) -> Result<Vec<(String, f64)>> {
    let ffmpeg = Tool::ffmpeg()?;
    let candidates = dir.join("candidates");
    std::fs::create_dir_all(&candidates).map_err(|e| EngineError::io(&candidates, e))?;
    let side = sampling.max_side;
    let filter = format!(
        "fps={},scale='if(gt(iw,ih),min({side},iw),-2)':'if(gt(iw,ih),-2,min({side},ih))'",
        sampling.fps
    );
    let args: Vec<String> = [
        "-nostdin",
        "-hide_banner",
        "-loglevel",
        "error",
        "-y",
        "-i",
        &video.to_string_lossy(),
        "-vf",
        &filter,
        &candidates.join("c_%06d.png").to_string_lossy(),
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    // A file ffmpeg cannot decode is the user's input at fault, not the tool.
    ffmpeg
        .run("frame extraction", &args, log, control)
        .map_err(|e| match e {
            EngineError::Tool { reason, .. } => EngineError::dataset(
                video,
                "input",
                format!("ffmpeg cannot read it as a video: {reason}"),
            ),
            e => e,
        })?;
    let names = photos(&candidates).map_err(|_| {
        EngineError::dataset(
            video,
            "input",
            "ffmpeg decoded fewer than 3 frames: the video is too short or not a video",
        )
    })?;
    let scores: Vec<f64> = names
        .par_iter()
        .map(|n| {
            let img = image::open(candidates.join(n))
                .map_err(|e| EngineError::dataset(video, "input", format!("frame {n}: {e}")))?;
            Ok(sharpness(&img.to_luma8()))
        })
        .collect::<Result<_>>()?;
    let kept = sharpest_per_stretch(&scores, sampling.max_frames);
    let mut out = Vec::with_capacity(kept.len());
    for (k, &i) in kept.iter().enumerate() {
        let name = format!("frame_{k:05}.png");
        let to = dir.join(&name);
        std::fs::rename(candidates.join(&names[i]), &to).map_err(|e| EngineError::io(&to, e))?;
        out.push((name, scores[i]));
    }
    std::fs::remove_dir_all(&candidates).map_err(|e| EngineError::io(&candidates, e))?;
    Ok(out)
}

/// Indices of the sharpest score in each of `count` equal stretches of `scores` (all of them
/// when there are fewer).
pub(crate) fn sharpest_per_stretch(scores: &[f64], count: usize) -> Vec<usize> {
    let n = scores.len();
    if n <= count {
        return (0..n).collect();
    }
    (0..count)
        .map(|k| {
            let (lo, hi) = (k * n / count, ((k + 1) * n / count).max(k * n / count + 1));
            (lo..hi)
                .max_by(|&a, &b| scores[a].total_cmp(&scores[b]))
                .expect("a stretch holds at least one frame")
        })
        .collect()
}

/// Sharpness as the variance of the image's Laplacian (the usual focus measure, as in
/// instant-ngp's `colmap2nerf` and nerfstudio's frame filter): blur removes high frequencies.
pub fn sharpness(gray: &GrayImage) -> f64 {
    let (w, h) = gray.dimensions();
    if w < 3 || h < 3 {
        return 0.0;
    }
    let px = |x: u32, y: u32| gray.get_pixel(x, y).0[0] as f64;
    let mut sum = 0.0;
    let mut sum_sq = 0.0;
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let l = px(x - 1, y) + px(x + 1, y) + px(x, y - 1) + px(x, y + 1) - 4.0 * px(x, y);
            sum += l;
            sum_sq += l * l;
        }
    }
    let n = ((w - 2) * (h - 2)) as f64;
    sum_sq / n - (sum / n).powi(2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::Luma;

    #[test]
    fn blur_lowers_sharpness() {
        let sharp = GrayImage::from_fn(32, 32, |x, y| {
            Luma([if (x / 2 + y / 2) % 2 == 0 { 255 } else { 0 }])
        });
        let blurred = image::imageops::blur(&sharp, 2.0);
        assert!(sharpness(&sharp) > 10.0 * sharpness(&blurred));
        assert_eq!(sharpness(&GrayImage::new(8, 8)), 0.0);
    }

    #[test]
    fn the_sharpest_frame_of_each_stretch_is_kept() {
        let scores = [1.0, 5.0, 2.0, 9.0, 3.0, 4.0, 0.5];
        assert_eq!(sharpest_per_stretch(&scores, 3), vec![1, 3, 5]);
        assert_eq!(
            sharpest_per_stretch(&scores, 10),
            (0..7).collect::<Vec<_>>()
        );
    }

    #[test]
    fn inputs_are_told_apart_and_too_few_photos_refused() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(InputKind::of(dir.path()).unwrap(), InputKind::Photos);
        let err = photos(dir.path()).unwrap_err().to_string();
        assert!(err.contains("found 0 PNG/JPEG photos"), "{err}");
        let txt = dir.path().join("notes.txt");
        std::fs::write(&txt, "x").unwrap();
        let err = InputKind::of(&txt).unwrap_err().to_string();
        assert!(
            err.contains("neither a folder of photos nor a video"),
            "{err}"
        );
        assert!(InputKind::of(&dir.path().join("none.mp4")).is_err());
    }
}
