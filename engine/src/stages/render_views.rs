//! Stage 2, `render_views`: render RGB, z-depth (the median of each ray's termination) and
//! opacity from the trained field at every training pose and along an interpolated camera path
//! (slerp of rotations, lerp of centres, through evenly spaced training poses). These views are
//! the training data of the 2D network and of mutual learning; their depth gives the geometry
//! used for warping. The dataset's ground-truth depth, when the field carries it, is laid over
//! the training views, and the rendered depth is graded against it (`metrics.json`).

use std::path::Path;

use candle_core::Device;
use serde::{Deserialize, Serialize};

use crate::depth_error::DepthErrors;
use crate::field::saved;
use crate::per_view::per_view;
use crate::render::render_image;
use crate::stages::camera_paths::interpolated_path;
use crate::stages::{Outcome, Progress, StageControl};
use crate::views::{RenderedViews, ViewInfo, ViewKind};
use crate::{EngineError, Result};
use stylenerf_plan::Preset;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RenderViewsConfig {
    /// Frames on the interpolated path.
    pub path_frames: usize,
    /// Training poses the path passes through (evenly spaced in dataset order, looped).
    pub path_keyframes: usize,
    /// Rays per rendering chunk.
    pub chunk: usize,
}

impl RenderViewsConfig {
    pub fn preset(preset: Preset) -> Self {
        match preset {
            Preset::Tiny => Self {
                path_frames: 12,
                path_keyframes: 4,
                chunk: 4096,
            },
            Preset::Quick => Self {
                path_frames: 60,
                path_keyframes: 8,
                chunk: 8192,
            },
            Preset::Standard | Preset::Paper => Self {
                path_frames: 120,
                path_keyframes: 12,
                chunk: 8192,
            },
        }
    }
}

/// Renders the views of the field in `field_dir` into `out`.
pub fn run(
    field_dir: &Path,
    cfg: &RenderViewsConfig,
    out: &Path,
    control: &StageControl,
    device: &Device,
) -> Result<Outcome<RenderedViews>> {
    let started = std::time::Instant::now();
    let (field, meta) = saved::load(field_dir, device)?;
    let first = meta.train_cameras.first().ok_or_else(|| {
        EngineError::artifact(
            field_dir.join("field.json"),
            "the field has no training cameras",
        )
    })?;
    let (width, height) = (first.intrinsics.width, first.intrinsics.height);
    let mut views: Vec<ViewInfo> = meta
        .train_cameras
        .iter()
        .enumerate()
        .map(|(i, c)| ViewInfo {
            name: format!("train_{i:04}"),
            kind: ViewKind::Train { frame: i },
            camera: *c,
        })
        .collect();
    views.extend(
        interpolated_path(&meta.train_cameras, cfg.path_keyframes, cfg.path_frames)
            .into_iter()
            .enumerate()
            .map(|(i, c)| ViewInfo {
                name: format!("path_{i:04}"),
                kind: ViewKind::Path,
                camera: c,
            }),
    );
    let mut rendered = RenderedViews {
        width,
        height,
        views: Vec::new(),
        rgb: Vec::new(),
        depth: Vec::new(),
        opacity: Vec::new(),
        true_depth: None,
    };
    let truth = saved::load_train_depth(field_dir, meta.train_cameras.len(), width, height)?;
    let total = views.len() as u64;
    // Views of another size than the first would not stack; scale their intrinsics.
    for view in &mut views {
        let camera = &mut view.camera;
        if (camera.intrinsics.width, camera.intrinsics.height) != (width, height) {
            camera.intrinsics = camera
                .intrinsics
                .scaled(width as f32 / camera.intrinsics.width as f32);
            camera.intrinsics.height = height;
        }
    }
    let images = per_view(
        views.len(),
        device,
        Some(control),
        |i| {
            render_image(
                &field,
                &meta.camera_rays(&views[i].camera),
                &meta.sampling,
                &|s| field.colour(s),
                cfg.chunk,
            )
        },
        |done| {
            control.report(&Progress {
                stage: "render_views".into(),
                step: done as u64,
                total,
                ..Default::default()
            })
        },
    )?;
    for img in images {
        rendered.rgb.extend(img.rgb);
        rendered.depth.extend(img.depth);
        rendered.opacity.extend(img.opacity);
    }
    rendered.views = views;
    rendered.true_depth = truth.map(|truth| carry_true_depth(&rendered, &truth));
    // The depth every later stage warps with, graded where the dataset has the truth.
    let depth_errors = rendered.true_depth.as_ref().and_then(|truth| {
        let mut errors = DepthErrors::default();
        errors.add(&rendered.depth, &rendered.opacity, truth);
        errors.summary()
    });
    let (near, far) = depth_range(&rendered);
    rendered.save(out, near, far)?;
    // Written last: its presence marks the stage complete.
    crate::checkpoint::write_json_atomic(
        &out.join("metrics.json"),
        &serde_json::json!({
            "views": rendered.len(),
            "seconds": started.elapsed().as_secs_f64(),
            "depth_against_truth": depth_errors,
        }),
    )?;
    Ok(Outcome::Done(rendered))
}

/// The training frames' ground-truth depth (`truth`: one map per training camera) laid out
/// over `views`: each training view gets its frame's map, the path's views zeros (unknown).
fn carry_true_depth(views: &RenderedViews, truth: &[f32]) -> Vec<f32> {
    let n = (views.width * views.height) as usize;
    views
        .views
        .iter()
        .flat_map(|v| match v.kind {
            ViewKind::Train { frame } => truth[frame * n..(frame + 1) * n].to_vec(),
            ViewKind::Path => vec![0.0; n],
        })
        .collect()
}

/// The 2nd and 98th percentiles of the valid depths, for previews.
fn depth_range(views: &RenderedViews) -> (f32, f32) {
    let mut d: Vec<f32> = views.depth.iter().copied().filter(|d| *d > 0.0).collect();
    if d.is_empty() {
        return (0.0, 1.0);
    }
    d.sort_by(f32::total_cmp);
    (
        d[d.len() * 2 / 100],
        d[(d.len() * 98 / 100).min(d.len() - 1)],
    )
}
