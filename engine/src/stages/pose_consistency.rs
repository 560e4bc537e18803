//! Consistency at the training poses, warped with the dataset's ground-truth depth.
//!
//! `render_stylized` measures consistency along its camera path, where the only depth is the
//! field's, so a method's warped error there mixes its own flicker with the field's geometric
//! error. Where the dataset has ground-truth depth (the generated scenes; datasets with depth
//! maps), the stage also renders the first `truth_views` training views, in dataset order, and
//! warps view t + g into view t for the training-view gaps [`GAPS`] twice: with the dataset's
//! depth and with the field's. The same pairs, the same frames: the difference between the two
//! columns is what the field's depth adds.

use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::eval::{GapError, PathWarps};
use crate::style2d::images::hwc_to_tensor;
use crate::views::RenderedViews;
use crate::warp::WarpConfig;
use crate::Result;

/// Gaps between training views (in dataset order) of the short- and long-range measure.
pub const GAPS: [usize; 2] = [1, 2];

/// Warped error of one method's frames at the training poses.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PoseScores {
    pub method: String,
    /// At the training-view [`GAPS`], warped with the dataset's depth.
    pub true_depth: [GapError; 2],
    /// The same pairs warped with the field's depth.
    pub field_depth: [GapError; 2],
}

/// The training views the measure uses and their warps under both depths.
pub struct PoseFrames {
    /// Indices into the views.
    pub views: Vec<usize>,
    pub cameras: Vec<Camera>,
    /// The unstylized renders `[3, H, W]`.
    pub photoreal: Vec<Tensor>,
    true_warps: Vec<PathWarps>,
    field_warps: Vec<PathWarps>,
}

impl PoseFrames {
    /// The first `count` training views of `views` with their warps; `None` when the views
    /// carry no ground-truth depth or fewer than two views are asked for. Field depth is
    /// trusted where the rendered opacity reaches `min_opacity`, as on the path;
    /// `rel_tolerance` is the warps' occlusion test ([`WarpConfig`]).
    pub fn prepare(
        views: &RenderedViews,
        count: usize,
        min_opacity: f32,
        rel_tolerance: f32,
        device: &Device,
    ) -> Result<Option<Self>> {
        let cfg = WarpConfig { rel_tolerance };
        let chosen: Vec<usize> = views.train_indices().into_iter().take(count).collect();
        if views.true_depth.is_none() || chosen.len() < 2 {
            return Ok(None);
        }
        let (w, h) = (views.width as usize, views.height as usize);
        let cameras: Vec<Camera> = chosen.iter().map(|&i| views.views[i].camera).collect();
        let truth: Vec<Vec<f32>> = chosen
            .iter()
            .map(|&i| views.true_depth(i).unwrap_or_default().to_vec())
            .collect();
        let field: Vec<Vec<f32>> = chosen
            .iter()
            .map(|&i| {
                views
                    .depth(i)
                    .iter()
                    .zip(views.opacity(i))
                    .map(|(&d, &o)| if o >= min_opacity { d } else { 0.0 })
                    .collect()
            })
            .collect();
        let warps = |depths: &[Vec<f32>]| -> Result<Vec<PathWarps>> {
            GAPS.iter()
                .map(|&gap| PathWarps::new(&cameras, depths, gap, cfg, device))
                .collect()
        };
        let photoreal = chosen
            .iter()
            .map(|&i| Ok(hwc_to_tensor(views.rgb(i), w, h, device)?.squeeze(0)?))
            .collect::<Result<Vec<_>>>()?;
        Ok(Some(Self {
            true_warps: warps(&truth)?,
            field_warps: warps(&field)?,
            views: chosen,
            cameras,
            photoreal,
        }))
    }

    /// The warped errors of `frames` (one `[3, H, W]` per chosen view) under both depths.
    pub fn score(&self, method: &str, frames: &[Tensor]) -> Result<PoseScores> {
        let errors = |warps: &[PathWarps]| -> Result<[GapError; 2]> {
            Ok([warps[0].error(frames)?, warps[1].error(frames)?])
        };
        Ok(PoseScores {
            method: method.into(),
            true_depth: errors(&self.true_warps)?,
            field_depth: errors(&self.field_warps)?,
        })
    }
}
