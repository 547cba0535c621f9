//! Evaluation of a view after an update, and of the final map over the whole sequence.

#[allow(unused_imports)]
use super::*;

/// A frame's view rendered from the map at `ek` and compared with the frame.
pub(super) struct ViewEval {
    pub(super) out: Vec<RayResult>,
    pub(super) input: crate::dataset::RgbImage,
    pub(super) gt_depth: Option<Vec<f32>>,
    pub(super) psnr: f64,
    pub(super) ssim: f64,
    pub(super) depth_l1_cm: Option<f64>,
    /// What the Depth L1 is made of: in front of / behind the truth, plain / textured.
    pub(super) depth_split: Option<crate::metrics::DepthSplit>,
}

/// Renders `frame`'s view at `ek` and computes PSNR, SSIM and (with a depth) Depth L1.
pub(super) fn evaluate_view<B: Backend>(
    backend: &mut B,
    ek: &Intrinsics,
    frame: &crate::dataset::Frame,
) -> anyhow::Result<ViewEval>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let out = render_view(backend, ek, &frame.pose)?;
    let input = frame.rgb.resized(ek.width, ek.height);
    let rendered: Vec<f32> = out.iter().flat_map(|r| r.color).collect();
    let psnr = crate::metrics::psnr(&rendered, &input.data);
    let ssim = crate::metrics::ssim(
        &rendered,
        &input.data,
        ek.width as usize,
        ek.height as usize,
    );
    let gt_depth = frame
        .depth
        .as_ref()
        .map(|d| d.resized(ek.width, ek.height).data);
    let depth: Vec<f32> = out.iter().map(|r| r.depth).collect();
    // The split sums `|rendered - gt|` in `depth_l1_cm`'s order: its `l1_cm` is that value.
    let depth_split = gt_depth.as_ref().and_then(|g| {
        crate::metrics::depth_split_cm(
            &depth,
            g,
            &input.data,
            ek.width as usize,
            ek.height as usize,
        )
    });
    Ok(ViewEval {
        out,
        input,
        gt_depth,
        psnr,
        ssim,
        depth_l1_cm: depth_split.map(|s| s.l1_cm),
        depth_split,
    })
}

/// Averages of the final map re-rendered over the sequence.
pub(super) struct FinalEval {
    pub(super) frames: usize,
    pub(super) psnr: Option<f64>,
    pub(super) ssim: Option<f64>,
    pub(super) depth_l1_cm: Option<f64>,
    /// Over every evaluated pixel: the median depth error (cm) and the share of pixels off
    /// by [`FAR_ERROR_M`] or more.
    pub(super) depth_median_cm: Option<f64>,
    pub(super) depth_far_share: Option<f64>,
    pub(super) per_frame: Vec<FinalFrame>,
}

/// The depth error (m) from which the final-map evaluation counts a pixel as far off.
pub const FAR_ERROR_M: f64 = 0.5;

/// One frame of the final-map evaluation (`summary.json`: `final_per_frame`), so that
/// forgetting shows where along the sequence it happens.
#[derive(Clone, Debug, Serialize)]
pub struct FinalFrame {
    pub frame: usize,
    pub psnr: f64,
    pub ssim: f64,
    pub depth_l1_cm: Option<f64>,
}

/// Renders frames 0, k, 2k, ... of `ds` from the map in `backend` at `ek` (after mapping: the
/// evaluation may read any frame) and averages PSNR, SSIM and Depth L1 over them.
pub(super) fn final_map_eval<B: Backend>(
    backend: &mut B,
    ds: &dyn crate::dataset::Dataset,
    ek: &Intrinsics,
    every: usize,
) -> anyhow::Result<FinalEval>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let mut per_frame = Vec::new();
    let mut spread = crate::metrics::DepthErrorSpread::default();
    if every > 0 {
        for i in (0..ds.len()).step_by(every) {
            let v = evaluate_view(backend, ek, &ds.frame(i)?)?;
            if let Some(g) = &v.gt_depth {
                let depth: Vec<f32> = v.out.iter().map(|r| r.depth).collect();
                spread.add(&depth, g);
            }
            per_frame.push(FinalFrame {
                frame: i,
                psnr: v.psnr,
                ssim: v.ssim,
                depth_l1_cm: v.depth_l1_cm,
            });
        }
    }
    Ok(FinalEval {
        frames: per_frame.len(),
        psnr: mean(per_frame.iter().map(|f| f.psnr)),
        ssim: mean(per_frame.iter().map(|f| f.ssim)),
        depth_l1_cm: mean(per_frame.iter().filter_map(|f| f.depth_l1_cm)),
        depth_median_cm: spread.median_cm(),
        depth_far_share: spread.share_at_least(FAR_ERROR_M),
        per_frame,
    })
}
