//! The mapping loop: frames pushed one at a time into the core's mapper, evaluation after
//! every update, checkpoints, and the errors of a run that fails midway.

#[allow(unused_imports)]
use super::*;
use himap_core::mapper::MapperConfig;

/// What [`run_map`] computed before choosing the backend.
pub(super) struct RunContext {
    pub(super) t_start: Instant,
    pub(super) k: Intrinsics,
    pub(super) aabb: Aabb,
    pub(super) box_src: &'static str,
    pub(super) reason: String,
}

/// The mapping loop, evaluation and outputs of [`run_map`] on one backend.
pub(super) fn map_with<B: MapBackend>(
    opts: &MapOptions,
    ds: &dyn crate::dataset::Dataset,
    ctx: RunContext,
    backend: B,
) -> anyhow::Result<MapSummary>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let cfg = &opts.config;
    let (n, k) = (ds.len(), ctx.k);
    let mut run = RunInfo {
        backend_name: format!("{} ({})", backend.name(), ctx.reason),
        threads: backend.threads(),
        parameters: backend.layout().param_count(),
        ctx,
    };
    let mcfg = cfg.mapper_config()?;
    // two pixel batches: the next iteration's is drawn while the backend runs the current
    // one (a GPU queues it; the map is the same bits either way)
    let mut px = vec![PixelSample::default(); 2 * mcfg.pixels as usize];
    let mut res = vec![PixelResult::default(); mcfg.pixels as usize];
    let resumed = match &opts.resume {
        Some(path) => Some(checkpoint::load(
            path,
            cfg,
            &opts.dataset,
            n,
            (k.width, k.height),
            |m| (0..m).map(|i| Ok(ds.frame(i)?.pose)).collect(),
        )?),
        None => None,
    };
    let mut mapper = start_mapper(opts, ds, backend, mcfg, k, &mut px, &mut res, &resumed)?;
    // a resumed run's map may have grown
    run.ctx.aabb = mapper.backend().layout().config.aabb;
    run.parameters = mapper.backend().layout().param_count();
    let mut rec = UpdateRecorder::new(opts, k, &mcfg, n, resumed.as_ref().map(|(r, _)| r))?;
    let progress = Progress::new(opts, n);
    let start = resumed.as_ref().map_or(0, |(r, _)| r.pushed as usize);
    let mut priors = match &resumed {
        Some((r, _)) => crate::planes::OnlinePriors::resume(&mut mapper, cfg, &r.plane_priors)?,
        None => crate::planes::OnlinePriors::default(),
    };
    let poses = push_frames(
        opts,
        ds,
        &mut run,
        start,
        &mut mapper,
        &mut rec,
        &mut priors,
        &progress,
    )?;
    progress.pb.finish_and_clear();
    if opts.profile {
        match mapper
            .backend()
            .profile_table(mapper.iterations() as usize, rec.mapping_s)
        {
            Some(t) => eprint!(
                "mapping, {} iterations (the passes of the per-update evaluation renders \
                 included):\n{t}",
                mapper.iterations()
            ),
            None => eprintln!("profile: this backend does not time its passes"),
        }
    }
    let steps = StepCounts {
        iterations: mapper.iterations(),
        rejected: mapper.rejected_steps(),
        lr_reductions: mapper.lr_reductions(),
    };
    if steps.lr_reductions > 0 {
        eprintln!(
            "warning: {} mapping steps were not finite; the learning rates were lowered {} \
             times (mapper.rejected_lr_after / rejected_lr_factor)",
            steps.rejected, steps.lr_reductions
        );
    }
    progress
        .log
        .borrow_mut()
        .done(rec.rows.len(), rec.mapping_s);
    finish_run(
        opts,
        ds,
        run,
        mapper.into_backend(),
        &mut rec,
        &poses,
        steps,
    )
}

/// What a run's summary says of the backend and the scene box.
struct RunInfo {
    backend_name: String,
    threads: usize,
    parameters: usize,
    ctx: RunContext,
}

/// The mapper's step counts at the end of a run.
struct StepCounts {
    iterations: u32,
    rejected: u32,
    lr_reductions: u32,
}

/// Pushes frames `start..` (up to `--stop-after`) into the mapper one at a time, records
/// every update, writes checkpoints, and runs the final update after the last frame. Returns
/// the poses of every pushed frame (the mesh level is measured over them).
#[allow(clippy::too_many_arguments)]
fn push_frames<B: MapBackend>(
    opts: &MapOptions,
    ds: &dyn crate::dataset::Dataset,
    run: &mut RunInfo,
    start: usize,
    mapper: &mut Mapper<'_, B>,
    rec: &mut UpdateRecorder<'_>,
    priors: &mut crate::planes::OnlinePriors,
    progress: &Progress,
) -> anyhow::Result<Vec<Pose>>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let n = ds.len();
    let mut poses: Vec<Pose> = Vec::with_capacity(n);
    for i in 0..start {
        poses.push(ds.frame(i)?.pose);
    }
    progress.pb.set_position(start as u64);
    // Frames pushed at the last checkpoint this run wrote (named when the backend fails).
    let mut last_checkpoint: Option<usize> = None;
    let mut last_frame: Option<crate::dataset::Frame> = None;
    let backend_name = run.backend_name.clone();
    let fail =
        |e, at: &str, last_checkpoint| mid_run_error(e, at, &backend_name, last_checkpoint, opts);
    let cfg = &opts.config;
    let mut grow = (cfg.scene.grow && run.ctx.box_src == crate::config::DEFAULT_BOX && n > 0)
        .then(|| anyhow::Ok(crate::grow::horizontal_axes(&ds.frame(0)?.pose)))
        .transpose()?;
    let pushed = opts.stop_after.map_or(n, |s| s.min(n));
    if start == n && n > 0 {
        // A checkpoint written at the last frame: the final update and the refinement (whose
        // settings may differ from the checkpointed run's) still run.
        last_frame = Some(ds.frame(n - 1)?);
    }
    for i in start..pushed {
        let frame = ds.frame(i)?;
        poses.push(frame.pose);
        if let Some(axes) = grow {
            if !grow_box(opts, run, mapper, &frame, &axes, progress)? {
                grow = None;
            }
        }
        if !inside(&run.ctx.aabb, frame.pose.origin()) {
            if rec.outside_box == 0 {
                progress.warn(&outside_box_warning(&frame, &run.ctx));
            }
            rec.outside_box += 1;
        }
        if let Some(live) = rec.live.as_mut() {
            live.frame(frame.index, &run.ctx.k, &frame.pose, &frame.rgb);
        }
        let rgba = pack_image(&frame.rgb);
        let t0 = Instant::now();
        let last_psnr = rec.last_psnr;
        let rep = mapper
            .push_frame_observed(&rgba, frame.pose, &mut |info: &IterInfo| {
                progress.iteration(i, frame.index, info, last_psnr)
            })
            .map_err(|e| fail(e, &format!("frame {}", frame.index), last_checkpoint))?;
        if let Some(r) = rep {
            let dt = t0.elapsed().as_secs_f64();
            let seen = Seen::of(mapper, &poses);
            rec.record(mapper.backend_mut(), r, &frame, dt, progress, &seen)?;
            if let Some(st) = priors.after_update(mapper, cfg)? {
                if std::env::var_os("HIMAP_PLANES_LOG").is_some() {
                    eprintln!("frame {}: {}", frame.index, st.describe());
                }
            }
        }
        progress.pb.inc(1);
        last_frame = Some(frame);
        if opts.checkpoint_every > 0 && (i + 1).is_multiple_of(opts.checkpoint_every) {
            write_checkpoint(opts, mapper, rec, priors, &poses, n)?;
            last_checkpoint = Some(i + 1);
        }
    }
    if let Some(frame) = last_frame.filter(|_| pushed == n) {
        let t0 = Instant::now();
        let rep = mapper
            .flush(&mut |_: &IterInfo| {})
            .map_err(|e| fail(e, "the final update", last_checkpoint))?;
        if let Some(r) = rep {
            let dt = t0.elapsed().as_secs_f64();
            let seen = Seen::of(mapper, &poses);
            rec.record(mapper.backend_mut(), r, &frame, dt, progress, &seen)?;
        }
        let iters = opts.config.mapper.refine_iters;
        if iters > 0 {
            if opts.progress {
                progress.warn(&format!(
                    "final refinement: {iters} iterations over {} held frames, windows of {}",
                    mapper.keyframe_ids().count() + mapper.local_ids().count(),
                    opts.config.mapper.refine_window
                ));
            }
            let t0 = Instant::now();
            let rep = crate::planes::refine(
                mapper,
                cfg,
                &mut |st: &crate::planes::PlaneStats| {
                    if opts.progress {
                        progress.warn(&st.describe());
                    }
                },
                &mut |info: &IterInfo| {
                    progress.iteration(pushed - 1, frame.index, info, rec.last_psnr)
                },
            )
            .map_err(|e| match e {
                crate::planes::RefineError::Mapper(e) => {
                    fail(e, "the final refinement", last_checkpoint)
                }
                crate::planes::RefineError::Other(e) => e,
            })?;
            let dt = t0.elapsed().as_secs_f64();
            rec.mapping_s += dt;
            if let (Some(r), true) = (rep, opts.progress) {
                progress.warn(&format!(
                    "final refinement done in {dt:.1} s: loss {:.4} -> {:.4}",
                    r.first.loss, r.last.loss
                ));
            }
        }
    }
    Ok(poses)
}

/// The mapper's view of the frames after an update, for the live view: the pushed poses,
/// the window's and the keyframe cache's frames.
struct Seen<'p> {
    poses: &'p [Pose],
    window: Vec<[f32; 3]>,
    keyframes: Vec<[f32; 3]>,
}

impl<'p> Seen<'p> {
    fn of<B: MapBackend>(mapper: &Mapper<'_, B>, poses: &'p [Pose]) -> Self {
        let centre = |id: u32| poses.get(id as usize).map(|p| p.origin());
        Self {
            poses,
            window: mapper
                .window_ids()
                .iter()
                .filter_map(|&i| centre(i))
                .collect(),
            keyframes: mapper.keyframe_ids().filter_map(centre).collect(),
        }
    }
}

/// Saves the map, the mapper's state, the learning rates and the metrics so far
/// (`--checkpoint-every`).
fn write_checkpoint<B: MapBackend>(
    opts: &MapOptions,
    mapper: &mut Mapper<'_, B>,
    rec: &UpdateRecorder<'_>,
    priors: &crate::planes::OnlinePriors,
    poses: &[Pose],
    n: usize,
) -> anyhow::Result<()>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let cfg = &opts.config;
    let k = mapper.intrinsics();
    let id = DatasetId::new(&opts.dataset, n, k.width, k.height, poses);
    let lrs = Group::ALL.map(|g| mapper.backend().adam_lr(g));
    let state = mapper.state();
    let run = RunState::new(
        cfg,
        id,
        &state,
        lrs,
        &rec.rows,
        rec.outside_box,
        rec.mapping_s,
        priors.carrying(),
    );
    let data = mapper.backend_mut().export()?;
    checkpoint::save(&opts.out, cfg, &data, &run)
}

/// After the last frame: the final-map evaluation, the meshes and their metrics, the saved
/// map and `summary.json`.
fn finish_run<B: MapBackend>(
    opts: &MapOptions,
    ds: &dyn crate::dataset::Dataset,
    run: RunInfo,
    mut backend: B,
    rec: &mut UpdateRecorder<'_>,
    poses: &[Pose],
    steps: StepCounts,
) -> anyhow::Result<MapSummary>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let cfg = &opts.config;
    let (n, k, ctx) = (ds.len(), run.ctx.k, &run.ctx);
    let fin = final_map_eval(&mut backend, ds, &rec.ek, cfg.eval.final_every as usize)?;
    if opts.progress {
        let spread = match (fin.depth_median_cm, fin.depth_far_share) {
            (Some(m), Some(f)) => format!(
                " (median {m:.1} cm, {:.1} % of pixels off by {FAR_ERROR_M} m or more)",
                100.0 * f
            ),
            _ => String::new(),
        };
        eprintln!(
            "final map over {} frames of the sequence: PSNR {} dB, SSIM {}, Depth L1 {} cm{spread}",
            fin.frames,
            fmt_opt(fin.psnr, 2),
            fmt_opt(fin.ssim, 3),
            fmt_opt(fin.depth_l1_cm, 2)
        );
    }
    let surface = write_meshes(&mut backend, opts, &rec.ek, &k, poses, ctx.aabb)?;
    if let Some(live) = rec.live.as_mut() {
        let last = rec.rows.last().map_or(0, |r| r.frame);
        live.mesh(last, &crate::mesh::Mesh::read_ply(&surface.path)?);
        live.finish()?;
    }
    use crate::eval::Culling;
    let (mesh_metrics, mesh_gt, mesh_err) = evaluate_mesh(opts, ds, &surface, Culling::None);
    // Against a ground-truth mesh, also against its part the frames observe (frustum and
    // occlusion with a depth ground truth, else frustum).
    let mesh_observed_gt = match (&mesh_gt, &mesh_metrics) {
        (Some(kind), Some(_)) if kind == "mesh" => {
            let c = if ds.has_depth() {
                Culling::FrustumOcclusion
            } else {
                Culling::Frustum
            };
            evaluate_mesh(opts, ds, &surface, c).0
        }
        _ => None,
    };
    let data = backend.export()?;
    save_map(&opts.out.join("map.safetensors"), cfg, &data)?;

    let rows = &rec.rows;
    let mapping_s = rec.mapping_s;
    let summary = MapSummary {
        dataset: opts.dataset.clone(),
        frames: n,
        width: k.width,
        height: k.height,
        backend: run.backend_name,
        threads: run.threads,
        scene_box: [ctx.aabb.min, ctx.aabb.max],
        scene_box_source: ctx.box_src.to_string(),
        updates: rows.len(),
        iterations: steps.iterations,
        rejected_steps: steps.rejected,
        lr_reductions: steps.lr_reductions,
        mean_psnr: mean(rows.iter().map(|r| r.psnr)),
        mean_ssim: mean(rows.iter().map(|r| r.ssim)),
        mean_depth_l1_cm: mean(rows.iter().filter_map(|r| r.depth_l1_cm)),
        frames_outside_box: rec.outside_box,
        final_frames: fin.frames,
        final_psnr: fin.psnr,
        final_ssim: fin.ssim,
        final_depth_l1_cm: fin.depth_l1_cm,
        final_depth_median_cm: fin.depth_median_cm,
        final_depth_far_share: fin.depth_far_share,
        final_per_frame: fin.per_frame,
        mesh: mesh_metrics,
        mesh_observed_gt,
        mesh_ground_truth: mesh_gt,
        mesh_error: mesh_err,
        mesh_faces: surface.faces,
        mesh_full_faces: surface.full_faces,
        mesh_level: surface.level,
        mesh_spacing: surface.spacing,
        beta: surface.beta,
        seconds_total: ctx.t_start.elapsed().as_secs_f64(),
        seconds_mapping: mapping_s,
        seconds_per_iteration: mapping_s / steps.iterations.max(1) as f64,
        seconds_per_frame: mapping_s / n.max(1) as f64,
        parameters: run.parameters,
        config: cfg.clone(),
    };
    let sp = opts.out.join("summary.json");
    crate::atomic::write_bytes_atomic(&sp, serde_json::to_string_pretty(&summary)?.as_bytes())?;
    // The plots and the page are a view of what is already written: a failure there is
    // reported, not fatal to the run.
    if let Err(e) = write_report(&opts.out, &summary, rows) {
        eprintln!("warning: metrics.png / report.html not written: {e:#}");
    }
    Ok(summary)
}

/// The mapper a run starts with: a new one, or the one `--resume`'s checkpoint holds (its
/// learning rates and state restored, the images of the frames it holds uploaded again).
#[allow(clippy::too_many_arguments)]
fn start_mapper<'a, B: MapBackend>(
    opts: &MapOptions,
    ds: &dyn crate::dataset::Dataset,
    backend: B,
    mcfg: MapperConfig,
    k: Intrinsics,
    px: &'a mut [PixelSample],
    res: &'a mut [PixelResult],
    resumed: &Option<(RunState, ModelData)>,
) -> anyhow::Result<Mapper<'a, B>>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let Some((run, data)) = resumed else {
        return Mapper::new(backend, mcfg, k, px, res).map_err(|e| anyhow::anyhow!("mapper: {e}"));
    };
    let mut backend = backend;
    if data.layout == *backend.layout() {
        backend.import(data)?;
    } else if !backend.regrow(data.clone())? {
        // a map over a grown box: `regrow` installs it whole (parameters, moments, step)
        bail!("the checkpoint's scene box grew, and this backend cannot resize its map: resume on the CPU");
    }
    for (g, lr) in Group::ALL.into_iter().zip(run.lrs()?) {
        backend.set_adam_lr(g, lr)?;
    }
    let state = run.mapper_state()?;
    let mut m = Mapper::restore(backend, mcfg, k, px, res, &state)
        .map_err(|e| anyhow::anyhow!("mapper: {e}"))?;
    // the images of the frames the mapper holds, back into their slots
    for e in state.held() {
        let frame = ds.frame(e.id as usize)?;
        m.backend_mut()
            .upload_frame(e.slot, &pack_image(&frame.rgb))?;
    }
    if opts.progress {
        eprintln!(
            "resuming after frame {} of {} from {}",
            run.pushed,
            ds.len(),
            checkpoint::path_of(opts.resume.as_deref().unwrap_or(Path::new("."))).display()
        );
    }
    Ok(m)
}

/// Grows the default scene box before `frame` is pushed ([`crate::grow::grow_before_push`])
/// and says so. `Ok(false)` when the box can grow no more (said once; the run goes on in the
/// box it has).
fn grow_box<B: MapBackend>(
    opts: &MapOptions,
    run: &mut RunInfo,
    mapper: &mut Mapper<'_, B>,
    frame: &crate::dataset::Frame,
    axes: &[usize; 2],
    progress: &Progress,
) -> anyhow::Result<bool>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    use crate::grow::Growth;
    let t0 = Instant::now();
    match crate::grow::grow_before_push(&opts.config, mapper, &run.ctx.aabb, axes, &frame.pose)? {
        Growth::Same => Ok(true),
        Growth::Refused(why) => {
            progress.warn(&format!("warning: frame {}: {why}", frame.index));
            Ok(false)
        }
        Growth::Grown {
            aabb: b,
            parameters,
            bytes,
        } => {
            let e = b.extent();
            progress.warn(&format!(
                "frame {}: the scene box grows to [{:.2}, {:.2}, {:.2}]..[{:.2}, {:.2}, {:.2}] \
                 ({:.1} x {:.1} x {:.1} m, {parameters} parameters, {:.0} MB) in {:.1} s",
                frame.index,
                b.min[0],
                b.min[1],
                b.min[2],
                b.max[0],
                b.max[1],
                b.max[2],
                e[0],
                e[1],
                e[2],
                bytes as f64 / 1e6,
                t0.elapsed().as_secs_f64()
            ));
            run.ctx.aabb = b;
            run.parameters = parameters;
            Ok(true)
        }
    }
}

/// Whether the point is inside the box (false for NaN).
fn inside(aabb: &Aabb, o: [f32; 3]) -> bool {
    (0..3).all(|a| o[a] >= aabb.min[a] && o[a] <= aabb.max[a])
}

/// The warning for the first camera outside the scene box.
fn outside_box_warning(frame: &crate::dataset::Frame, ctx: &RunContext) -> String {
    let (o, b) = (frame.pose.origin(), &ctx.aabb);
    format!(
        "warning: frame {}: the camera ({:.2}, {:.2}, {:.2}) is outside the scene box ({}) \
         [{:.2}, {:.2}, {:.2}]..[{:.2}, {:.2}, {:.2}]; the map cannot hold what lies beyond \
         the box: give a box that contains the path (scene.min, scene.max)",
        frame.index,
        o[0],
        o[1],
        o[2],
        ctx.box_src,
        b.min[0],
        b.min[1],
        b.min[2],
        b.max[0],
        b.max[1],
        b.max[2]
    )
}

/// What a run shows while it maps: a progress bar on a terminal, plain log lines every few
/// seconds otherwise (a log file, a service), nothing without `opts.progress`.
struct Progress {
    pb: indicatif::ProgressBar,
    log: std::cell::RefCell<PlainLog>,
}

impl Progress {
    fn new(opts: &MapOptions, n: usize) -> Self {
        let plain = opts.progress && !std::io::stderr().is_terminal();
        let pb = if opts.progress && !plain {
            let pb = indicatif::ProgressBar::new(n as u64);
            pb.set_style(
                indicatif::ProgressStyle::with_template(
                    "{elapsed_precise} [{bar:30}] frame {pos}/{len} {msg}",
                )
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
                .progress_chars("=> "),
            );
            pb
        } else {
            indicatif::ProgressBar::hidden()
        };
        Self {
            pb,
            log: std::cell::RefCell::new(PlainLog::new(plain, n)),
        }
    }

    /// A warning printed above the bar.
    fn warn(&self, msg: &str) {
        self.pb.suspend(|| eprintln!("{msg}"));
    }

    /// One mapping iteration of the update at pushed frame `i` (source frame `frame`).
    fn iteration(&self, i: usize, frame: usize, info: &IterInfo, last_psnr: f64) {
        self.pb.set_message(format!(
            "{} it {}/{} loss {:.4} (c {:.4} w {:.4}) PSNR {:.2}",
            kind_label(info.kind),
            info.iter + 1,
            info.iters,
            info.loss,
            info.color_loss,
            info.warp_loss,
            last_psnr
        ));
        if info.iter.is_multiple_of(10) {
            self.pb.tick();
        }
        if info.rejected {
            self.warn(&format!(
                "warning: frame {frame}: {} iteration {}/{} was not finite (loss {}); skipped, \
                 parameters kept",
                kind_label(info.kind),
                info.iter + 1,
                info.iters,
                info.loss
            ));
        }
        self.log.borrow_mut().iteration(i, info);
    }
}

/// The metrics of a run's updates: each update's evaluation (every `eval.every`-th; a render
/// strip every `render_every`-th) appended to `rows`, and `metrics.csv` rewritten whole
/// (atomically) after every update, so a run killed halfway keeps what it measured.
struct UpdateRecorder<'o> {
    opts: &'o MapOptions,
    /// The evaluation camera (`eval.scale` of the mapping camera).
    ek: Intrinsics,
    render_every: usize,
    csv_path: PathBuf,
    rows: Vec<UpdateMetrics>,
    /// PSNR of the last evaluated update (shown in the progress message).
    last_psnr: f64,
    /// Seconds spent in updates.
    mapping_s: f64,
    /// Pushed frames whose camera was outside the scene box.
    outside_box: usize,
    /// The live view, when asked for.
    live: Option<LiveView>,
}

impl<'o> UpdateRecorder<'o> {
    /// Starts the metrics (from a resumed run's rows) and writes `metrics.csv`'s header.
    fn new(
        opts: &'o MapOptions,
        k: Intrinsics,
        mcfg: &MapperConfig,
        n: usize,
        resumed: Option<&RunState>,
    ) -> anyhow::Result<Self> {
        let cfg = &opts.config;
        let ek = {
            let w = ((k.width as f32 * cfg.eval.scale).round() as u32).max(1);
            let h = ((k.height as f32 * cfg.eval.scale).round() as u32).max(1);
            k.resized(w, h)
        };
        let expected_updates = if n >= mcfg.init_frames as usize {
            1 + (n - mcfg.init_frames as usize).div_ceil(mcfg.update_every as usize)
        } else {
            1
        };
        let (rows, mapping_s, outside_box) = match resumed {
            Some(run) => (run.rows.clone(), run.mapping_s, run.outside_box),
            None => (Vec::new(), 0.0f64, 0usize),
        };
        let csv_path = opts.out.join("metrics.csv");
        write_metrics(&csv_path, &rows)?;
        let last_psnr = rows
            .iter()
            .rev()
            .map(|r| r.psnr)
            .find(|p| !p.is_nan())
            .unwrap_or(f64::NAN);
        Ok(Self {
            opts,
            ek,
            render_every: (expected_updates / cfg.eval.renders.max(1) as usize).max(1),
            csv_path,
            rows,
            last_psnr,
            mapping_s,
            outside_box,
            live: LiveView::start(&opts.live)?,
        })
    }

    /// Records an update that took `seconds` and ended at `frame`.
    fn record<B: MapBackend>(
        &mut self,
        backend: &mut B,
        report: UpdateReport,
        frame: &crate::dataset::Frame,
        seconds: f64,
        progress: &Progress,
        seen: &Seen<'_>,
    ) -> anyhow::Result<()>
    where
        B::Error: std::error::Error + Send + Sync + 'static,
    {
        self.mapping_s += seconds;
        let u = self.rows.len();
        let cfg = &self.opts.config;
        let eval = cfg.eval.every > 0 && u.is_multiple_of(cfg.eval.every as usize);
        let (mut psnr, mut ssim, mut dl1) = (f64::NAN, f64::NAN, None);
        let mut split = None;
        // The live view shows every update's render, evaluated or not.
        let mut view = None;
        if eval || self.live.is_some() {
            view = Some(evaluate_view(backend, &self.ek, frame)?);
        }
        if let Some(v) = view.as_ref().filter(|_| eval) {
            (psnr, ssim, dl1) = (v.psnr, v.ssim, v.depth_l1_cm);
            split = v.depth_split;
            if u.is_multiple_of(self.render_every) {
                let p = self
                    .opts
                    .out
                    .join("renders")
                    .join(format!("frame{:06}.png", frame.index));
                write_render(&p, &v.input, &v.out, v.gt_depth.as_deref())?;
            }
            self.last_psnr = psnr;
        }
        self.rows.push(UpdateMetrics {
            frame: frame.index,
            kind: match report.kind {
                UpdateKind::Init => "init".into(),
                UpdateKind::Online => "online".into(),
                UpdateKind::Refine => "refine".into(),
            },
            psnr,
            ssim,
            depth_l1_cm: dl1,
            depth_near_cm: split.map(|s| s.near_cm),
            plain_share: split.map(|s| s.plain_share),
            depth_l1_plain_cm: split.and_then(|s| s.plain_l1_cm),
            loss_first: report.first.loss,
            loss: report.last.loss,
            color_loss: report.last.color_loss,
            warp_loss: report.last.warp_loss,
            warp_valid: report.last.warp_valid,
            open_rays: report.last.open_rays,
            new_loss_ratio: report.first.new_loss_ratio,
            new_warp_valid: report.first.new_warp_valid,
            window_keyframes: report.window_keyframes,
            iters: report.iters,
            seconds,
        });
        write_metrics(&self.csv_path, &self.rows)?;
        if let Some(r) = self.rows.last() {
            progress.log.borrow_mut().update(r);
        }
        if let (Some(live), Some(v), Some(row)) = (self.live.as_mut(), &view, self.rows.last()) {
            live.update(&LiveUpdate {
                frame: frame.index,
                input: &v.input,
                render: &v.out,
                k: self.ek,
                metrics: row,
                window: seen.window.clone(),
                keyframes: seen.keyframes.clone(),
            });
            let every = self.opts.live.mesh_every;
            if every > 0 && (u + 1).is_multiple_of(every) {
                let mesh = observed_mesh(backend, cfg, &self.ek, seen.poses)?;
                live.mesh(frame.index, &mesh);
            }
        }
        Ok(())
    }
}

/// A quick mesh of the observed scene for the live view: the level from 4 views rendered at
/// half the evaluation size (or the configured one), the region and the culling from 16
/// views, at twice the configured mesh spacing.
fn observed_mesh<B: MapBackend>(
    backend: &mut B,
    cfg: &Config,
    ek: &Intrinsics,
    poses: &[Pose],
) -> anyhow::Result<crate::mesh::Mesh>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let aabb = backend.layout().config.aabb;
    let level = match cfg.eval.mesh_level {
        Some(l) => l,
        None => {
            let mut b = [0.0f32; 1];
            backend.read_params(Group::Beta, &mut b)?;
            let lk = ek.resized((ek.width / 2).max(1), (ek.height / 2).max(1));
            rendered_surface_level(backend, &lk, poses, 4)?
                .unwrap_or_else(|| cfg.surface_level(b[0]))
        }
    };
    let views = observed_views(backend, ek, poses, 16)?;
    let res = 2.0 * cfg.eval.mesh_resolution;
    let Some(region) = observed_region(&views, aabb, 2.0 * res) else {
        return Ok(crate::mesh::Mesh::default());
    };
    let full = map_mesh(backend, region, res, crate::query::Level::Global(level))?;
    Ok(SeenSurface::new(&views, cfg.eval.observed_margin, f32::INFINITY)?.cull(&full))
}

/// What [`write_meshes`] wrote.
struct SurfaceOutputs {
    /// `mesh.ply`: the surface culled to what the mapped views saw.
    path: std::path::PathBuf,
    faces: usize,
    /// Faces of `mesh_full.ply` (the whole observed region, uncut).
    full_faces: usize,
    /// The field level the surface was extracted at (configured or rendered).
    level: f32,
    beta: f32,
    /// The marching-cubes spacing of `mesh.ply` (m).
    spacing: f32,
}

/// Early termination of the renders [`write_meshes`] places the surface with (the level and the
/// observed views): with the default of no termination a render evaluates every sample behind
/// the surface too; this share of the transmittance moves a rendered depth by less than 1e-4
/// of the ray's length and saves about half the samples.
pub(super) const SURFACE_RENDER_TRANSMITTANCE: f32 = 1e-4;

/// The final map's meshes: the whole observed region's (`mesh_full.ply`) and the part some
/// mapped view saw (`mesh.ply`), the level they were extracted at and beta. The level comes
/// from the configuration or from the rendered depth of the views at `ek`; the observed region
/// and the culling from the depth of up to `eval.observed_views` of `poses` rendered at a quarter
/// of `k`. With samples beyond `model.max_depth` (`model.far_samples`) a face counts as seen
/// only by a view that has it within `max_depth`: the far samples reach a large space's far
/// walls, but their bins are metres wide there (ARCHITECTURE.md, issue #11).
pub(crate) fn final_meshes<B: MapBackend>(
    backend: &mut B,
    cfg: &Config,
    ek: &Intrinsics,
    k: &Intrinsics,
    poses: &[Pose],
    aabb: Aabb,
    progress: bool,
) -> anyhow::Result<(crate::mesh::Mesh, crate::mesh::Mesh, f32, f32, f32)>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let t0 = Instant::now();
    let beta = {
        let mut b = [0.0f32; 1];
        backend.read_params(Group::Beta, &mut b)?;
        b[0]
    };
    // The renders that place the surface stop a ray where its transmittance falls below
    // SURFACE_RENDER_TRANSMITTANCE (what lies behind changes a depth by less than that share).
    let t_saved = backend.layout().config.min_transmittance;
    backend.set_min_transmittance(t_saved.max(SURFACE_RENDER_TRANSMITTANCE))?;
    let level = match cfg.eval.mesh_level {
        Some(l) => Some(l),
        None => {
            let lk = ek.resized((ek.width / 2).max(1), (ek.height / 2).max(1));
            rendered_surface_level(backend, &lk, poses, 8)?
        }
    };
    let level = level.unwrap_or_else(|| cfg.surface_level(beta));
    let t_level = t0.elapsed().as_secs_f64();
    let views = observed_views(backend, k, poses, cfg.eval.observed_views as usize);
    backend.set_min_transmittance(t_saved)?;
    let views = views?;
    let t_views = t0.elapsed().as_secs_f64();
    let region = observed_region(&views, aabb, 2.0 * cfg.eval.mesh_resolution).unwrap_or(aabb);
    let mcfg = backend.layout().config;
    let within = if mcfg.has_far_segment() {
        mcfg.max_depth
    } else {
        f32::INFINITY
    };
    let surface = SeenSurface::new(&views, cfg.eval.observed_margin, within)?;
    // The level place by place (unless the configuration fixes one).
    let local = match (cfg.eval.mesh_level, cfg.eval.mesh_level_cell) {
        (None, cell) if cell > 0.0 => Some(local_surface_level(
            backend,
            &surface,
            cell,
            level,
            cfg.eval.mesh_level_spread,
        )?),
        _ => None,
    };
    let at = local.as_ref().map_or(
        crate::query::Level::Global(level),
        crate::query::Level::Local,
    );
    let full = map_mesh(backend, region, cfg.eval.mesh_resolution, at)?;
    let t_full = t0.elapsed().as_secs_f64();
    let cull = |m: &crate::mesh::Mesh| surface.cull(m);
    let seen = cull(&full);
    let t_cull = t0.elapsed().as_secs_f64();
    let res = cfg.eval.mesh_resolution;
    let (mesh, spacing) =
        match refined_spacing(&seen, res, cfg.eval.mesh_refine, cfg.eval.mesh_max_faces) {
            Some(s) => {
                let fine = refined_mesh(backend, region, res, &seen, s, at)?;
                (cull(&fine), s)
            }
            None => (seen, res),
        };
    if progress {
        let t = t0.elapsed().as_secs_f64();
        eprintln!(
            "mesh: {} faces over the observed region ({:.1} cm grid, mesh_full.ply), {} seen by \
             the mapped views at {:.1} cm (mesh.ply), the level estimated again in {} cubes, in \
             {t:.1} s (level {t_level:.1} s, {} views rendered {:.1} s, local level and \
             extraction {:.1} s, culling {:.1} s, finer grid {:.1} s)",
            full.faces.len(),
            res * 100.0,
            mesh.faces.len(),
            spacing * 100.0,
            local.as_ref().map_or(0, |l| l.cells()),
            views.len(),
            t_views - t_level,
            t_full - t_views,
            t_cull - t_full,
            t - t_cull,
        );
    }
    Ok((full, mesh, level, beta, spacing))
}

/// Extracts the final map's surface: the level from the configuration or from the rendered
/// depth of the mapped views, the observed region from their depth (`mesh_full.ply`) and the
/// part some view saw (`mesh.ply`).
fn write_meshes<B: MapBackend>(
    backend: &mut B,
    opts: &MapOptions,
    ek: &Intrinsics,
    k: &Intrinsics,
    poses: &[Pose],
    aabb: Aabb,
) -> anyhow::Result<SurfaceOutputs>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let (full, mesh, level, beta, spacing) =
        final_meshes(backend, &opts.config, ek, k, poses, aabb, opts.progress)?;
    full.write_ply(&opts.out.join("mesh_full.ply"))?;
    let path = opts.out.join("mesh.ply");
    mesh.write_ply(&path)?;
    Ok(SurfaceOutputs {
        path,
        faces: mesh.faces.len(),
        full_faces: full.faces.len(),
        level,
        beta,
        spacing,
    })
}

/// The mesh metrics against the dataset's ground truth (its `gt_mesh.ply`, else its depth)
/// with the configured culling: metrics, the kind of ground truth, or why there are none
/// (`(None, None, None)` when the dataset has no ground truth).
/// `gt_culling` culls a ground-truth mesh by the dataset's frames (the observed ground truth).
fn evaluate_mesh(
    opts: &MapOptions,
    ds: &dyn crate::dataset::Dataset,
    surface: &SurfaceOutputs,
    gt_culling: crate::eval::Culling,
) -> (
    Option<crate::eval::MeshMetrics>,
    Option<String>,
    Option<String>,
) {
    use crate::eval::{Culling, EvalOptions};
    let cfg = &opts.config;
    let gt_mesh = opts.dataset.join("gt_mesh.ply").is_file();
    if !gt_mesh && !ds.has_depth() {
        return (None, None, None);
    }
    if surface.faces == 0 {
        return (None, None, Some("empty reconstruction".to_string()));
    }
    // "auto": none against a ground-truth mesh, frustum against a depth ground truth
    let culling = Culling::from_name(&cfg.eval.cull).unwrap_or(if gt_mesh {
        Culling::None
    } else {
        Culling::Frustum
    });
    let eo = EvalOptions {
        n_samples: cfg.eval.mesh_samples,
        culling,
        gt_culling,
        // the ground truth at the files' size, as `himap eval` (whatever size was mapped)
        dataset: crate::dataset::DatasetConfig {
            max_width: 0,
            ..cfg.dataset.clone()
        },
        ..EvalOptions::default()
    };
    match crate::eval::eval_report(&surface.path, &opts.dataset, &eo) {
        Ok(r) => (Some(r.metrics), Some(r.gt_kind), None),
        Err(e) => (None, None, Some(format!("{e:#}"))),
    }
}

/// A mapping failure mid-run (`at`: the frame or the final update): the backend's own error
/// stays in the chain (a GPU failure exits with code 3), with the backend named and the way
/// to go on. The mapper's state inside a failed update is partial, so no checkpoint is
/// written then: the last periodic one (`--checkpoint-every`) is what a run resumes from.
pub(super) fn mid_run_error<E: std::error::Error + Send + Sync + 'static>(
    e: MapperError<E>,
    at: &str,
    backend: &str,
    last_checkpoint: Option<usize>,
    opts: &MapOptions,
) -> anyhow::Error {
    let hint = match last_checkpoint {
        Some(f) => format!(
            "the last checkpoint (after {f} frames) is {}: continue with `--resume {}` (also \
             on another backend, e.g. `--backend cpu`: the same bits)",
            opts.out.join(checkpoint::FILE).display(),
            opts.out.display()
        ),
        None if opts.checkpoint_every == 0 => {
            "no checkpoint was kept: `--checkpoint-every N` keeps one to resume from".into()
        }
        None => "no checkpoint was written yet".into(),
    };
    match e {
        MapperError::Backend(e) => {
            anyhow::Error::new(e).context(format!("{at}: the {backend} backend failed; {hint}"))
        }
        MapperError::Core(e) => anyhow::anyhow!("{at}: mapper: {e}"),
    }
}
