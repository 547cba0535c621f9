//! himap inside a robot's loop: what a driver does with the library.
//!
//! - A *camera* thread produces posed frames from a dataset at its frame rate (default: the
//!   demo's synthetic room, written to a temporary folder; `--dataset` takes any Replica, TUM
//!   or 7-Scenes folder `himap map` reads).
//! - The *mapping* thread owns the mapper on whichever backend `auto` picks (a Vulkan GPU when
//!   there is one, the CPU otherwise) and pushes every frame it receives. Between frames it
//!   serves the planner's queries, as a mapping service would (the map is never read while a
//!   step runs, so no lock is held around it).
//! - A *planner* thread asks, every `--query-every` frames, for the signed distance to the
//!   nearest surface and its gradient along a planned path (a straight line from the first
//!   camera along its view direction), and for a mesh of the observed space, which it writes.
//!
//! At the end it reports whether mapping kept up with the frame rate (frames mapped per second
//! against the camera's, and how far behind the newest frame the mapper was).
//!
//! ```text
//! cargo run --release --example robot_loop -- [--dataset DIR] [--fps 5] [--frames 40]
//!     [--backend auto|cpu|vulkan] [--realtime] [--out robot_loop_out]
//! ```
//! `--realtime` drops the frames that queued up while the mapper was busy (a robot that maps
//! the present, not the past); by default every frame is mapped, late.

use std::path::PathBuf;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Parser;
use himap::config::Config;
use himap::dataset::{self, LoadOptions};
use himap::grow::Growth;
use himap::mapper_cli::{pack_image, start_map};
use himap::query::{self, MapQuery, QueryOptions};
use himap::select::{decide, BackendChoice, MapBackend};
use himap_core::camera::{Intrinsics, Pose};
use himap_core::mapper::Mapper;
use himap_core::train::backend::ImageStore;
use himap_core::train::pixel::{PixelResult, PixelSample};
use himap_core::Aabb;

#[derive(Parser, Debug)]
struct Args {
    /// Dataset folder (default: the demo's synthetic room, generated).
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// Camera frame rate the producer replays at.
    #[arg(long, default_value_t = 5.0)]
    fps: f64,
    /// Frames to replay (default: 40 of the room, all of a dataset).
    #[arg(long)]
    frames: Option<usize>,
    /// Image size WxH the frames are resized to (default: 128x96 for the room, the dataset's
    /// own otherwise).
    #[arg(long)]
    size: Option<String>,
    /// Configuration preset (default: demo for the room, small for a dataset).
    #[arg(long)]
    preset: Option<String>,
    /// cpu, vulkan or auto.
    #[arg(long, default_value = "auto")]
    backend: String,
    /// CPU threads (0 = all).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// The planner queries after every this many mapped frames.
    #[arg(long, default_value_t = 10)]
    query_every: usize,
    /// Drop queued frames when the mapper falls behind (map the newest only).
    #[arg(long)]
    realtime: bool,
    /// Where meshes and the path's distances go.
    #[arg(long, default_value = "robot_loop_out")]
    out: PathBuf,
}

/// A frame as the camera driver delivers it.
struct CameraFrame {
    seq: usize,
    rgba: Vec<u32>,
    pose: Pose,
    produced: Instant,
}

/// What the mapping thread tells the planner.
enum Tick {
    /// This many frames are mapped.
    Mapped(usize),
    /// The sequence is over and the final update done.
    Done(usize),
}

/// What the planner asks the mapping thread.
enum Request {
    /// Signed distances and gradients along a path.
    Path(
        Vec<[f32; 3]>,
        mpsc::Sender<anyhow::Result<Vec<query::DistanceSample>>>,
    ),
    /// The mesh of the observed space.
    Mesh(mpsc::Sender<anyhow::Result<himap::mesh::Mesh>>),
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let tmp = tempfile::tempdir()?;
    let (data_dir, preset, size, room) = match &args.dataset {
        Some(d) => (d.clone(), "small", None, None),
        None => {
            let frames = args.frames.unwrap_or(40);
            let dir = tmp.path().join("room");
            let seed = Config::demo().seed;
            himap::synth::write_synthetic(
                &dir,
                &himap::synth::SynthOptions {
                    frames,
                    width: 128,
                    height: 96,
                    seed,
                },
            )?;
            println!(
                "camera: the demo's synthetic room ({frames} frames) in {}",
                dir.display()
            );
            (dir, "demo", None, Some(himap::synth::Scene::generate(seed)))
        }
    };
    let size = match &args.size {
        Some(s) => {
            let (w, h) = s.split_once('x').context("--size is WxH, e.g. 320x240")?;
            Some((w.parse()?, h.parse()?))
        }
        None => size,
    };
    let cfg = Config::preset(args.preset.as_deref().unwrap_or(preset))?;
    let lo = LoadOptions {
        end: args.frames,
        resize: size,
        load_depth: false,
        ..LoadOptions::default()
    };
    let ds = dataset::open_with(&data_dir, &lo, &cfg.dataset)
        .with_context(|| format!("opening {}", data_dir.display()))?;
    let k = ds.intrinsics();
    let n = ds.len();
    anyhow::ensure!(n > 0, "the dataset has no frames");

    // The mapping thread needs only what the first frame tells (online, like `himap map`).
    let first = ds.pose(0);
    let start = start_map(&cfg, &data_dir, &first, args.threads, true)?;
    let store = ImageStore {
        width: k.width,
        height: k.height,
        slots: cfg.mapper_config()?.slots_needed(),
    };
    // The default box grows with the walk, as in `himap map` (the horizontal axes of the
    // first camera's box).
    let grow = (cfg.scene.grow && start.box_src == himap::config::DEFAULT_BOX)
        .then(|| himap::grow::horizontal_axes(&first));
    let choice: BackendChoice = args.backend.parse()?;
    let decision = decide(choice);
    println!("backend: {}", decision.reason);

    let (frame_tx, frame_rx) = mpsc::channel::<CameraFrame>();
    let (req_tx, req_rx) = mpsc::channel::<Request>();
    let period = Duration::from_secs_f64(1.0 / args.fps.max(1e-3));

    std::thread::scope(|s| -> anyhow::Result<()> {
        // Camera: one frame per period, whatever the mapper does.
        let ds = &ds;
        s.spawn(move || {
            let t0 = Instant::now();
            for i in 0..n {
                let due = t0 + period * i as u32;
                if let Some(wait) = due.checked_duration_since(Instant::now()) {
                    std::thread::sleep(wait);
                }
                let f = match ds.frame(i) {
                    Ok(f) => f,
                    Err(e) => {
                        eprintln!("camera: frame {i}: {e}");
                        break;
                    }
                };
                let frame = CameraFrame {
                    seq: i,
                    rgba: pack_image(&f.rgb),
                    pose: f.pose,
                    produced: Instant::now(),
                };
                if frame_tx.send(frame).is_err() {
                    break;
                }
            }
        });

        // Planner: a straight path from the first camera along its view direction.
        let path: Vec<[f32; 3]> = {
            let o = first.origin();
            let fwd = first.rotate([0.0, 0.0, 1.0]);
            (0..=60)
                .map(|i| {
                    let t = 0.05 * i as f32;
                    [0, 1, 2].map(|a| o[a] + t * fwd[a])
                })
                .collect()
        };
        let out = args.out.clone();
        let every = args.query_every.max(1);
        let (tick_tx, tick_rx) = mpsc::channel::<Tick>();
        let planner_path = path.clone();
        let planner = s.spawn(move || -> anyhow::Result<()> {
            let mut asked = 0;
            // Query after every `every` mapped frames and once more after the final update;
            // dropping `req_tx` on return tells the mapping thread the planner is done.
            while let Ok(tick) = tick_rx.recv() {
                let (mapped, done) = match tick {
                    Tick::Mapped(m) => (m, false),
                    Tick::Done(m) => (m, true),
                };
                if !done && mapped % every != 0 {
                    continue;
                }
                let t = Instant::now();
                let (tx, rx) = mpsc::channel();
                if req_tx
                    .send(Request::Path(planner_path.clone(), tx))
                    .is_err()
                {
                    break;
                }
                let d = rx.recv()??;
                let ms = t.elapsed().as_secs_f64() * 1e3;
                let clear = d
                    .iter()
                    .enumerate()
                    .find(|(_, s)| s.within_range && s.distance < 0.2)
                    .map(|(i, _)| i as f32 * 0.05);
                let truth = room.as_ref().map(|r| {
                    let errs: Vec<f32> = planner_path
                        .iter()
                        .zip(&d)
                        .filter(|(_, s)| s.within_range)
                        .map(|(p, s)| (s.distance - himap::synth::scene_sdf(r, *p)).abs())
                        .collect();
                    errs.iter().sum::<f32>() / errs.len().max(1) as f32
                });
                println!(
                    "planner: after {mapped} frames: path free for {} (0.2 m clearance), \
                     lowest signed distance {:.2} m{}; query {ms:.0} ms",
                    clear.map_or("its whole 3 m".into(), |c| format!("{c:.2} m")),
                    d.iter()
                        .filter(|s| s.within_range)
                        .map(|s| s.distance)
                        .fold(f32::INFINITY, f32::min),
                    truth.map_or(String::new(), |e| format!(
                        ", off the room's true distance by {:.1} cm on average",
                        100.0 * e
                    )),
                );
                let (tx, rx) = mpsc::channel();
                if req_tx.send(Request::Mesh(tx)).is_err() {
                    break;
                }
                let mesh = rx.recv()??;
                let file = out.join(format!("mesh_{asked:03}.ply"));
                mesh.write_ply(&file)?;
                println!(
                    "planner: wrote {} ({} faces)",
                    file.display(),
                    mesh.faces.len()
                );
                let csv: String = std::iter::once("t_m,distance_m,gx,gy,gz,within_range\n".into())
                    .chain(d.iter().enumerate().map(|(i, s)| {
                        format!(
                            "{:.2},{},{},{},{},{}\n",
                            i as f32 * 0.05,
                            s.distance,
                            s.gradient[0],
                            s.gradient[1],
                            s.gradient[2],
                            s.within_range
                        )
                    }))
                    .collect();
                std::fs::write(out.join(format!("path_{asked:03}.csv")), csv)?;
                asked += 1;
                if done {
                    break;
                }
            }
            Ok(())
        });

        // Mapping, on this thread.
        let served = if decision.vulkan {
            match himap::select::vulkan_backend(&start.data, cfg.adam_config(), store) {
                Ok(b) => Some(map_loop(
                    b,
                    &cfg,
                    k,
                    &frame_rx,
                    &req_rx,
                    tick_tx.clone(),
                    args.realtime,
                    grow,
                )),
                Err(e) if choice == BackendChoice::Auto => {
                    println!("backend: the Vulkan backend failed ({e}); using the CPU");
                    None
                }
                Err(e) => return Err(e.into()),
            }
        } else {
            None
        };
        let stats = match served {
            Some(r) => r?,
            None => {
                let b = himap::backend::ParallelCpuBackend::new(
                    start.data.clone(),
                    cfg.adam_config(),
                    args.threads,
                )?
                .with_images(store);
                map_loop(
                    b,
                    &cfg,
                    k,
                    &frame_rx,
                    &req_rx,
                    tick_tx.clone(),
                    args.realtime,
                    grow,
                )?
            }
        };
        drop(tick_tx);
        planner.join().expect("planner thread")?;
        stats.report(args.fps, n);
        Ok(())
    })?;
    println!("outputs in {}", args.out.display());
    Ok(())
}

/// What the mapping thread measured.
struct LoopStats {
    mapped: usize,
    dropped: usize,
    busy: Duration,
    wall: Duration,
    max_lag: Duration,
    lag_sum: Duration,
}

impl LoopStats {
    fn report(&self, fps: f64, produced: usize) {
        let rate = self.mapped as f64 / self.busy.as_secs_f64().max(1e-9);
        let keeps_up = rate >= fps;
        println!(
            "mapping: {} of {produced} frames mapped ({} dropped) in {:.1} s; {:.2} frames/s \
             while busy against the camera's {fps:.2}: {}",
            self.mapped,
            self.dropped,
            self.wall.as_secs_f64(),
            rate,
            if keeps_up {
                "keeps up"
            } else {
                "does not keep up"
            }
        );
        println!(
            "mapping: latency from capture to mapped {:.2} s on average, {:.2} s at most",
            self.lag_sum.as_secs_f64() / self.mapped.max(1) as f64,
            self.max_lag.as_secs_f64()
        );
    }
}

#[allow(clippy::too_many_arguments)]
fn map_loop<B: MapBackend>(
    backend: B,
    cfg: &Config,
    k: Intrinsics,
    frames: &mpsc::Receiver<CameraFrame>,
    requests: &mpsc::Receiver<Request>,
    ticks: mpsc::Sender<Tick>,
    realtime: bool,
    mut grow: Option<[usize; 2]>,
) -> anyhow::Result<LoopStats>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let mc = cfg.mapper_config()?;
    // two pixel batches let a GPU backend queue each next iteration (same map either way)
    let mut px = vec![PixelSample::default(); 2 * mc.pixels as usize];
    let mut res = vec![PixelResult::default(); mc.pixels as usize];
    let mut mapper = Mapper::new(backend, mc, k, &mut px, &mut res)
        .map_err(|e| anyhow::anyhow!("mapper: {e}"))?;
    let mut poses: Vec<Pose> = Vec::new();
    let t0 = Instant::now();
    let mut st = LoopStats {
        mapped: 0,
        dropped: 0,
        busy: Duration::ZERO,
        wall: Duration::ZERO,
        max_lag: Duration::ZERO,
        lag_sum: Duration::ZERO,
    };
    // The rendered surface's level, estimated once per map state (`epoch`: frames mapped, plus
    // one after the final update).
    let mut level_at: Option<(usize, f32)> = None;
    let mut serve = |mapper: &mut Mapper<'_, B>,
                     poses: &[Pose],
                     epoch: usize,
                     r: Request|
     -> anyhow::Result<()> {
        let be = mapper.backend_mut();
        let level = match level_at {
            Some((e, l)) if e == epoch => l,
            _ => {
                let l = query::surface_level(be, &k, poses)?.unwrap_or(0.0);
                level_at = Some((epoch, l));
                l
            }
        };
        match r {
            Request::Path(p, reply) => {
                let region = intersect(around(&p, 1.0), cfg_box(be));
                let ans = MapQuery::build(
                    be,
                    region,
                    QueryOptions {
                        level,
                        ..QueryOptions::default()
                    },
                )
                .and_then(|q| q.distance(be, &p));
                let _ = reply.send(ans);
            }
            Request::Mesh(reply) => {
                let views = himap::mapper_cli::observed_views(be, &k, poses, 32)?;
                let region = himap::mapper_cli::observed_region(&views, cfg_box(be), 0.1);
                let ans = match region {
                    Some(r) => query::region_mesh(be, r, 0.05, level),
                    None => Ok(himap::mesh::Mesh::default()),
                };
                let _ = reply.send(ans);
            }
        }
        Ok(())
    };
    loop {
        // Serve whatever the planner asked while the last frame was mapped.
        while let Ok(r) = requests.try_recv() {
            serve(&mut mapper, &poses, st.mapped, r)?;
        }
        let mut f = match frames.recv_timeout(Duration::from_millis(20)) {
            Ok(f) => f,
            Err(mpsc::RecvTimeoutError::Timeout) => continue,
            Err(mpsc::RecvTimeoutError::Disconnected) => break,
        };
        if realtime {
            while let Ok(newer) = frames.try_recv() {
                st.dropped += 1;
                f = newer;
            }
        }
        let t = Instant::now();
        if let Some(axes) = grow {
            let aabb = cfg_box(mapper.backend());
            match himap::grow::grow_before_push(cfg, &mut mapper, &aabb, &axes, &f.pose)? {
                Growth::Same => {}
                Growth::Grown { aabb, .. } => {
                    println!("mapping: frame {}: the scene box grows to {aabb:?}", f.seq)
                }
                Growth::Refused(why) => {
                    println!("mapping: frame {}: {why}", f.seq);
                    grow = None;
                }
            }
        }
        mapper
            .push_frame(&f.rgba, f.pose)
            .map_err(|e| anyhow::anyhow!("mapping frame {}: {e}", f.seq))?;
        st.busy += t.elapsed();
        poses.push(f.pose);
        st.mapped += 1;
        let lag = f.produced.elapsed();
        st.lag_sum += lag;
        st.max_lag = st.max_lag.max(lag);
        let _ = ticks.send(Tick::Mapped(st.mapped));
    }
    let t = Instant::now();
    mapper
        .flush(&mut |_| {})
        .map_err(|e| anyhow::anyhow!("final mapping update: {e}"))?;
    st.busy += t.elapsed();
    st.wall = t0.elapsed();
    // The planner's last requests come after the final tick; serve until it hangs up.
    let _ = ticks.send(Tick::Done(st.mapped));
    while let Ok(r) = requests.recv() {
        serve(&mut mapper, &poses, st.mapped + 1, r)?;
    }
    Ok(st)
}

/// The box of `points` grown by `margin`.
fn around(points: &[[f32; 3]], margin: f32) -> Aabb {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in points {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a] - margin);
            hi[a] = hi[a].max(p[a] + margin);
        }
    }
    Aabb::new(lo, hi)
}

/// The common part of two boxes (possibly empty: not [`Aabb::is_valid`]).
fn intersect(a: Aabb, b: Aabb) -> Aabb {
    Aabb::new(
        [0, 1, 2].map(|i| a.min[i].max(b.min[i])),
        [0, 1, 2].map(|i| a.max[i].min(b.max[i])),
    )
}

fn cfg_box<B: MapBackend>(b: &B) -> Aabb {
    b.layout().config.aabb
}
