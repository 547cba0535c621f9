//! What a run reports: the per-update metrics (`metrics.csv`, flushed row by row), the plain
//! log lines when stdout is not a terminal, the render strips and the summary table.

#[allow(unused_imports)]
use super::*;

/// One row of `metrics.csv`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct UpdateMetrics {
    /// Index of the update's newest frame in the source sequence.
    pub frame: usize,
    pub kind: String,
    pub psnr: f64,
    pub ssim: f64,
    pub depth_l1_cm: Option<f64>,
    /// What the Depth L1 is made of ([`crate::metrics::depth_split_cm`]): its part from
    /// pixels rendered in front of the truth, the share of plain pixels (nothing for the
    /// warping loss to compare) and their Depth L1 alone.
    #[serde(default)]
    pub depth_near_cm: Option<f64>,
    #[serde(default)]
    pub plain_share: Option<f64>,
    #[serde(default)]
    pub depth_l1_plain_cm: Option<f64>,
    /// Loss of the update's first and last iteration.
    pub loss_first: f32,
    pub loss: f32,
    pub color_loss: f32,
    pub warp_loss: f32,
    /// Fraction of the last iteration's pixels with a valid warp term.
    pub warp_valid: f32,
    /// Share of the last iteration's sampled rays that left the scene box unabsorbed.
    pub open_rays: f32,
    /// Before the update's first step: the mean loss of the frames new since the last update
    /// over that of the window's other frames, and the share of their pixels with a valid
    /// warp term (`IterInfo::new_loss_ratio`, `new_warp_valid`; 0 when not measured).
    #[serde(default)]
    pub new_loss_ratio: f32,
    #[serde(default)]
    pub new_warp_valid: f32,
    pub window_keyframes: u32,
    pub iters: u32,
    /// Optimisation time of the update (s), excluding evaluation.
    pub seconds: f64,
}

/// `summary.json`.
#[derive(Clone, Debug, Serialize)]
pub struct MapSummary {
    pub dataset: PathBuf,
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    pub backend: String,
    pub threads: usize,
    pub scene_box: [[f32; 3]; 2],
    pub scene_box_source: String,
    pub updates: usize,
    pub iterations: u32,
    /// Mapping steps rejected as not finite (skipped, parameters kept), and the times the
    /// learning rates were lowered after `mapper.rejected_lr_after` of them in a row.
    pub rejected_steps: u32,
    pub lr_reductions: u32,
    pub mean_psnr: Option<f64>,
    pub mean_ssim: Option<f64>,
    pub mean_depth_l1_cm: Option<f64>,
    /// Frames whose camera centre lay outside the scene box (warned at the first).
    pub frames_outside_box: usize,
    /// The final map re-rendered at every `eval.final_every`-th frame of the whole sequence:
    /// how many frames, and their average PSNR, SSIM, Depth L1 (cm).
    pub final_frames: usize,
    pub final_psnr: Option<f64>,
    pub final_ssim: Option<f64>,
    pub final_depth_l1_cm: Option<f64>,
    /// Over every pixel of the final-map evaluation: the median depth error (cm) and the
    /// share (0..1) of pixels off by 0.5 m or more (the mean can be carried by a few surfaces
    /// placed far from the truth while most pixels are close).
    pub final_depth_median_cm: Option<f64>,
    pub final_depth_far_share: Option<f64>,
    pub final_per_frame: Vec<FinalFrame>,
    /// Accuracy, Completion (cm), Completion ratio (%) when a ground truth exists.
    pub mesh: Option<crate::eval::MeshMetrics>,
    /// The same metrics against the ground-truth mesh culled by the sequence's frames
    /// (frustum and occlusion: the surfaces they observe), when the dataset has a
    /// `gt_mesh.ply`. `mesh.ply` holds only observed surfaces, so against the whole mesh its
    /// completion also counts what no frame saw.
    pub mesh_observed_gt: Option<crate::eval::MeshMetrics>,
    pub mesh_ground_truth: Option<String>,
    pub mesh_error: Option<String>,
    pub mesh_faces: usize,
    /// Faces of `mesh_full.ply` (the extraction region before the visibility culling).
    pub mesh_full_faces: usize,
    /// SDF level of `mesh.ply` (m) and the trained beta it was derived from: the whole map's;
    /// with `eval.mesh_level_cell` each cube's level lies within `eval.mesh_level_spread` of it.
    pub mesh_level: f32,
    /// Marching-cubes spacing of `mesh.ply` (m; `mesh_full.ply`'s is `eval.mesh_resolution`).
    pub mesh_spacing: f32,
    pub beta: f32,
    pub seconds_total: f64,
    pub seconds_mapping: f64,
    pub seconds_per_iteration: f64,
    pub seconds_per_frame: f64,
    pub parameters: usize,
    pub config: Config,
}

/// A blue-to-red colour map of depth in [lo, hi] (black where there is none).
pub(super) fn depth_color(d: f32, lo: f32, hi: f32) -> [u8; 3] {
    if d <= 0.0 || !d.is_finite() {
        return [0, 0, 0];
    }
    let x = ((d - lo) / (hi - lo).max(1e-6)).clamp(0.0, 1.0);
    let r = (1.5 - (4.0 * x - 3.0).abs()).clamp(0.0, 1.0);
    let g = (1.5 - (4.0 * x - 2.0).abs()).clamp(0.0, 1.0);
    let b = (1.5 - (4.0 * x - 1.0).abs()).clamp(0.0, 1.0);
    [(r * 255.0) as u8, (g * 255.0) as u8, (b * 255.0) as u8]
}

/// Writes `input | rendered | rendered depth | gt depth` side by side.
pub(super) fn write_render(
    path: &Path,
    input: &RgbImage,
    out: &[RayResult],
    gt_depth: Option<&[f32]>,
) -> anyhow::Result<()> {
    let (w, h) = (input.width as usize, input.height as usize);
    let panels = if gt_depth.is_some() { 4 } else { 3 };
    let mut img = vec![0u8; w * panels * h * 3];
    let (mut lo, mut hi) = (f32::INFINITY, 0.0f32);
    for d in gt_depth
        .unwrap_or(&[])
        .iter()
        .copied()
        .chain(out.iter().map(|r| r.depth))
    {
        if d > 0.0 && d.is_finite() {
            lo = lo.min(d);
            hi = hi.max(d);
        }
    }
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let mut put = |panel: usize, c: [u8; 3]| {
                let o = 3 * (y * w * panels + panel * w + x);
                img[o..o + 3].copy_from_slice(&c);
            };
            let q = |v: f32| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
            put(0, [0, 1, 2].map(|c| q(input.data[3 * i + c])));
            put(1, out[i].color.map(q));
            put(2, depth_color(out[i].depth, lo, hi));
            if let Some(g) = gt_depth {
                put(3, depth_color(g[i], lo, hi));
            }
        }
    }
    let mut png = Vec::new();
    use image::ImageEncoder;
    image::codecs::png::PngEncoder::new(&mut png)
        .write_image(
            &img,
            (w * panels) as u32,
            h as u32,
            image::ExtendedColorType::Rgb8,
        )
        .with_context(|| format!("encoding {}", path.display()))?;
    crate::atomic::write_bytes_atomic(path, &png)
}

pub(super) fn mean(v: impl Iterator<Item = f64>) -> Option<f64> {
    let (mut s, mut n) = (0.0, 0usize);
    for x in v {
        if x.is_finite() {
            s += x;
            n += 1;
        }
    }
    (n > 0).then(|| s / n as f64)
}

/// The columns of `metrics.csv`, one row per mapping update.
pub(super) const CSV_HEADER: &str =
    "frame,kind,psnr,ssim,depth_l1_cm,loss_first,loss,color_loss,warp_loss,\
warp_valid,window_keyframes,iters,seconds,open_rays,new_loss_ratio,new_warp_valid,\
depth_near_cm,plain_share,depth_l1_plain_cm";

/// Writes `metrics.csv`: the header and every row so far, atomically ([`crate::atomic`]).
pub(super) fn write_metrics(path: &Path, rows: &[UpdateMetrics]) -> anyhow::Result<()> {
    crate::atomic::write_atomic(path, |w| {
        writeln!(w, "{CSV_HEADER}")?;
        for r in rows {
            write_csv_row(w, r)?;
        }
        Ok(())
    })
}

/// Appends one update's row to `metrics.csv`.
pub(super) fn write_csv_row(
    csv: &mut (impl Write + ?Sized),
    r: &UpdateMetrics,
) -> std::io::Result<()> {
    writeln!(
        csv,
        "{},{},{:.4},{:.4},{},{:.6},{:.6},{:.6},{:.6},{:.4},{},{},{:.3},{:.4},{:.3},{:.4},{},{},{}",
        r.frame,
        r.kind,
        r.psnr,
        r.ssim,
        r.depth_l1_cm.map(|d| format!("{d:.3}")).unwrap_or_default(),
        r.loss_first,
        r.loss,
        r.color_loss,
        r.warp_loss,
        r.warp_valid,
        r.window_keyframes,
        r.iters,
        r.seconds,
        r.open_rays,
        r.new_loss_ratio,
        r.new_warp_valid,
        r.depth_near_cm
            .map(|d| format!("{d:.3}"))
            .unwrap_or_default(),
        r.plain_share.map(|d| format!("{d:.4}")).unwrap_or_default(),
        r.depth_l1_plain_cm
            .map(|d| format!("{d:.3}"))
            .unwrap_or_default()
    )
}

/// "init", "map" or "refine": the kind of an iteration in progress lines.
pub(super) fn kind_label(kind: UpdateKind) -> &'static str {
    match kind {
        UpdateKind::Init => "init",
        UpdateKind::Online => "map",
        UpdateKind::Refine => "refine",
    }
}

/// Progress as plain lines on stderr, at most one every [`PlainLog::EVERY`] (plus one per
/// mapping update and one at the end), for runs whose stderr is not a terminal.
pub(super) struct PlainLog {
    pub(super) on: bool,
    pub(super) frames: usize,
    pub(super) start: Instant,
    pub(super) last: Option<Instant>,
    pub(super) updates: usize,
}

impl PlainLog {
    const EVERY: std::time::Duration = std::time::Duration::from_secs(5);

    pub(super) fn new(on: bool, frames: usize) -> Self {
        Self {
            on,
            frames,
            start: Instant::now(),
            last: None,
            updates: 0,
        }
    }

    pub(super) fn due(&mut self) -> bool {
        let now = Instant::now();
        let due = self.on && self.last.is_none_or(|t| now - t >= Self::EVERY);
        if due {
            self.last = Some(now);
        }
        due
    }

    pub(super) fn iteration(&mut self, frame: usize, info: &IterInfo) {
        if self.due() {
            eprintln!(
                "[{:7.1} s] frame {}/{} {} iteration {}/{} loss {:.4}",
                self.start.elapsed().as_secs_f64(),
                frame + 1,
                self.frames,
                kind_label(info.kind),
                info.iter + 1,
                info.iters,
                info.loss
            );
        }
    }

    pub(super) fn update(&mut self, r: &UpdateMetrics) {
        if self.on {
            self.last = Some(Instant::now());
            self.updates += 1;
            eprintln!(
                "[{:7.1} s] update {} ({}) at frame {}: PSNR {:.2} dB, SSIM {:.3}, Depth L1 {}, \
                 {} iterations in {:.1} s, {:.0} % of rays left the box unabsorbed{}",
                self.start.elapsed().as_secs_f64(),
                self.updates,
                r.kind,
                r.frame,
                r.psnr,
                r.ssim,
                r.depth_l1_cm
                    .map(|d| format!("{d:.1} cm"))
                    .unwrap_or_else(|| "-".into()),
                r.iters,
                r.seconds,
                100.0 * r.open_rays,
                new_frames_note(r)
            );
        }
    }

    pub(super) fn done(&mut self, updates: usize, mapping_s: f64) {
        if self.on {
            eprintln!(
                "[{:7.1} s] mapping done: {updates} updates in {mapping_s:.1} s; evaluating and writing outputs",
                self.start.elapsed().as_secs_f64()
            );
        }
    }
}

/// The log line's note on an online update's new frames: the share of their pixels whose
/// warping term had enough views before the update's first step; below half, their depth is
/// not yet constrained (it settles once later frames see the same region).
fn new_frames_note(r: &UpdateMetrics) -> String {
    if r.kind != "online" {
        return String::new();
    }
    let pct = 100.0 * r.new_warp_valid;
    let warn = if r.new_warp_valid < 0.5 {
        " (their depth is not constrained yet)"
    } else {
        ""
    };
    format!(", new frames' pixels with enough views {pct:.0} %{warn}")
}

pub(super) fn fmt_opt(x: Option<f64>, digits: usize) -> String {
    x.map(|v| format!("{v:.digits$}"))
        .unwrap_or_else(|| "-".into())
}

/// Prints a short table of a summary.
pub fn summary_table(s: &MapSummary) -> String {
    let f = |x: Option<f64>, p: usize| x.map(|v| format!("{v:.p$}")).unwrap_or("-".into());
    let mut t = String::new();
    t += &format!(
        "{} frames {}x{}, {} updates, {} iterations, backend {}\n",
        s.frames, s.width, s.height, s.updates, s.iterations, s.backend
    );
    t += &format!(
        "PSNR {} dB | SSIM {} | Depth L1 {} cm\n",
        f(s.mean_psnr, 2),
        f(s.mean_ssim, 3),
        f(s.mean_depth_l1_cm, 2)
    );
    if s.final_frames > 0 {
        t += &format!(
            "final map over {} frames of the sequence: PSNR {} dB | SSIM {} | Depth L1 {} cm\n",
            s.final_frames,
            f(s.final_psnr, 2),
            f(s.final_ssim, 3),
            f(s.final_depth_l1_cm, 2)
        );
    }
    match &s.mesh {
        Some(m) => {
            t += &format!(
                "mesh ({} faces, level {:.3} m) vs {}: Accuracy {:.2} cm | Completion {:.2} cm | Completion ratio {:.1} %\n",
                s.mesh_faces,
                s.mesh_level,
                s.mesh_ground_truth.as_deref().unwrap_or("?"),
                m.accuracy_cm,
                m.completion_cm,
                m.completion_ratio_pct
            );
            if let Some(o) = &s.mesh_observed_gt {
                t += &format!(
                    "  vs the observed ground truth (gt_mesh.ply culled by the frames): Accuracy {:.2} cm | Completion {:.2} cm | Completion ratio {:.1} %\n",
                    o.accuracy_cm, o.completion_cm, o.completion_ratio_pct
                );
            }
        }
        None => {
            t += &format!(
                "mesh ({} faces): {}\n",
                s.mesh_faces,
                s.mesh_error.as_deref().unwrap_or("no ground truth")
            )
        }
    }
    t += &format!(
        "time {:.1} s total, mapping {:.1} s ({:.1} ms per iteration, {:.2} s per frame)",
        s.seconds_total,
        s.seconds_mapping,
        1e3 * s.seconds_per_iteration,
        s.seconds_per_frame
    );
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_metrics_row_has_a_field_per_column_and_empty_fields_for_missing_values() {
        let mut r = UpdateMetrics {
            frame: 94,
            kind: "online".into(),
            psnr: 22.5,
            ssim: 0.75,
            depth_l1_cm: Some(48.259),
            loss_first: 0.12,
            loss: 0.1,
            color_loss: 0.01,
            warp_loss: 0.09,
            warp_valid: 0.8,
            open_rays: 0.0,
            new_loss_ratio: 2.6,
            new_warp_valid: 0.8,
            depth_near_cm: Some(36.857),
            plain_share: Some(0.4549),
            depth_l1_plain_cm: Some(62.095),
            window_keyframes: 3,
            iters: 60,
            seconds: 2.7,
        };
        let columns: Vec<&str> = CSV_HEADER.split(',').collect();
        let line = |r: &UpdateMetrics| {
            let mut buf = Vec::new();
            write_csv_row(&mut buf, r).unwrap();
            String::from_utf8(buf).unwrap().trim_end().to_string()
        };
        let full = line(&r);
        let fields: Vec<&str> = full.split(',').collect();
        assert_eq!(fields.len(), columns.len(), "{full}");
        let at = |name: &str| fields[columns.iter().position(|c| *c == name).unwrap()];
        assert_eq!(at("depth_l1_cm"), "48.259");
        assert_eq!(at("depth_near_cm"), "36.857");
        assert_eq!(at("plain_share"), "0.4549");
        assert_eq!(at("depth_l1_plain_cm"), "62.095");
        // the columns the earlier sessions' scripts read by position stay where they were
        assert_eq!(columns[4], "depth_l1_cm");
        assert_eq!(columns[15], "new_warp_valid");
        // a view without ground-truth depth leaves the depth fields empty
        r.depth_l1_cm = None;
        r.depth_near_cm = None;
        r.plain_share = None;
        r.depth_l1_plain_cm = None;
        let bare = line(&r);
        let fields: Vec<&str> = bare.split(',').collect();
        assert_eq!(fields.len(), columns.len(), "{bare}");
        assert!(fields[16..].iter().all(|f| f.is_empty()), "{bare}");
    }
}
