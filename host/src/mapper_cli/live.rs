//! The live view of a run in the Rerun viewer (`himap map --rerun [URL]`, `--rerun-save
//! FILE`; cargo feature `rerun`). Per pushed frame: the camera's pose and frustum
//! (`world/camera`) and its input image; per mapping update: the rendered colour and depth of
//! the newest frame beside the input (`world/camera/render/...`), the window's and keyframes'
//! camera centres (`world/window`, `world/keyframes`), and the metrics as time series
//! (`metrics/...`); every `--rerun-mesh-every` updates the mesh culled to what the mapped views
//! saw (`world/mesh`), and the final `mesh.ply` at the end. Timeline `frame`: the source
//! frame index. World axes are the dataset's; cameras are OpenCV's (x right, y down, z
//! forward), which is Rerun's pinhole default.
//!
//! Without the feature the options exist and say how to build with it.

#[allow(unused_imports)]
use super::*;

/// Where the live view goes ([`MapOptions::live`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LiveOptions {
    /// Stream to a viewer: `Some(None)` spawns one (or uses the one listening on the default
    /// port), `Some(Some(url))` connects to `url` (`rerun+http://host:port/proxy`).
    pub viewer: Option<Option<String>>,
    /// Write the recording to this `.rrd` file.
    pub save: Option<PathBuf>,
    /// Log the observed mesh after every this many updates (0: only the final mesh).
    pub mesh_every: usize,
}

impl LiveOptions {
    /// Whether any live output is asked for.
    pub fn enabled(&self) -> bool {
        self.viewer.is_some() || self.save.is_some()
    }
}

/// What the live view shows of one mapping update.
pub struct LiveUpdate<'a> {
    /// Source index of the update's newest frame.
    pub frame: usize,
    /// Its input image and the map's render of it, both at `k` (the evaluation camera).
    pub input: &'a RgbImage,
    pub render: &'a [RayResult],
    pub k: Intrinsics,
    /// The update's metrics row.
    pub metrics: &'a UpdateMetrics,
    /// Camera centres of the window's frames and of the keyframe cache.
    pub window: Vec<[f32; 3]>,
    pub keyframes: Vec<[f32; 3]>,
}

#[cfg(not(feature = "rerun"))]
mod imp {
    use super::*;

    /// The live view (this build has no `rerun` feature: [`LiveView::start`] refuses).
    pub struct LiveView;

    impl LiveView {
        /// Refuses with the command that builds `himap` with the viewer.
        pub fn start(opts: &LiveOptions) -> anyhow::Result<Option<Self>> {
            if !opts.enabled() {
                return Ok(None);
            }
            anyhow::bail!(
                "--rerun / --rerun-save need himap built with the live view: \
                 cargo build --release -p himap --features rerun"
            )
        }
        /// Nothing to log.
        pub fn frame(&mut self, _frame: usize, _k: &Intrinsics, _pose: &Pose, _rgb: &RgbImage) {}
        /// Nothing to log.
        pub fn update(&mut self, _u: &LiveUpdate<'_>) {}
        /// Nothing to log.
        pub fn mesh(&mut self, _frame: usize, _mesh: &crate::mesh::Mesh) {}
        /// Nothing to flush.
        pub fn finish(&mut self) -> anyhow::Result<()> {
            Ok(())
        }
    }
}

#[cfg(feature = "rerun")]
mod imp {
    use super::*;
    use rerun::RecordingStream;

    /// A run's recording stream.
    pub struct LiveView {
        rec: RecordingStream,
        /// The first logging error (reported once; the run goes on).
        failed: bool,
    }

    fn rgb8(img: &RgbImage) -> Vec<u8> {
        img.data
            .iter()
            .map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
            .collect()
    }

    impl LiveView {
        /// Opens the recording: a viewer (spawned, or the one at the URL) and/or an `.rrd`
        /// file. `None` when no live output is asked for.
        pub fn start(opts: &LiveOptions) -> anyhow::Result<Option<Self>> {
            if !opts.enabled() {
                return Ok(None);
            }
            let builder = rerun::RecordingStreamBuilder::new("himap").default_enabled(true);
            let mut sinks: Vec<Box<dyn rerun::sink::LogSink>> = Vec::new();
            if let Some(viewer) = &opts.viewer {
                let url = match viewer {
                    Some(u) => u.clone(),
                    None => {
                        rerun::spawn(&rerun::SpawnOptions::default()).context(
                            "spawning the Rerun viewer (install it with `cargo install rerun-cli` \
                             or `pip install rerun-sdk`, or give --rerun a viewer's URL)",
                        )?;
                        format!(
                            "rerun+http://127.0.0.1:{}/proxy",
                            rerun::DEFAULT_SERVER_PORT
                        )
                    }
                };
                let uri: rerun::external::re_uri::ProxyUri = url
                    .parse()
                    .with_context(|| format!("--rerun {url:?} is not a Rerun proxy URL"))?;
                sinks.push(Box::new(rerun::sink::GrpcSink::new(uri)));
            }
            if let Some(path) = &opts.save {
                sinks.push(Box::new(
                    rerun::sink::FileSink::new(path)
                        .with_context(|| format!("creating {}", path.display()))?,
                ));
            }
            let rec = builder.set_sinks(sinks)?;
            Ok(Some(Self { rec, failed: false }))
        }

        fn check(&mut self, r: Result<(), rerun::RecordingStreamError>) {
            if let Err(e) = r {
                if !self.failed {
                    eprintln!("warning: live view: {e} (the run goes on)");
                }
                self.failed = true;
            }
        }

        /// A pushed frame: the camera's pose and frustum, and its input image.
        pub fn frame(&mut self, frame: usize, k: &Intrinsics, pose: &Pose, rgb: &RgbImage) {
            self.rec.set_time_sequence("frame", frame as i64);
            let m = pose.m;
            let cols = [
                [m[0][0], m[1][0], m[2][0]],
                [m[0][1], m[1][1], m[2][1]],
                [m[0][2], m[1][2], m[2][2]],
            ];
            let r = self.rec.log(
                "world/camera",
                &rerun::Transform3D::from_translation_mat3x3(pose.origin(), cols),
            );
            self.check(r);
            let r = self.rec.log(
                "world/camera",
                &rerun::Pinhole::from_focal_length_and_resolution(
                    [k.fx, k.fy],
                    [k.width as f32, k.height as f32],
                )
                .with_principal_point([k.cx + 0.5, k.cy + 0.5]),
            );
            self.check(r);
            let r = self.rec.log(
                "world/camera/input",
                &rerun::Image::from_rgb24(rgb8(rgb), [rgb.width, rgb.height]),
            );
            self.check(r);
        }

        /// A mapping update: the render beside the input, window and keyframes, metrics.
        pub fn update(&mut self, u: &LiveUpdate<'_>) {
            self.rec.set_time_sequence("frame", u.frame as i64);
            let (w, h) = (u.k.width, u.k.height);
            let color: Vec<u8> = u
                .render
                .iter()
                .flat_map(|r| r.color.map(|c| (c.clamp(0.0, 1.0) * 255.0 + 0.5) as u8))
                .collect();
            let depth: Vec<u8> = u
                .render
                .iter()
                .flat_map(|r| {
                    let d = if r.opacity >= 0.5 && r.depth.is_finite() {
                        r.depth / r.opacity
                    } else {
                        0.0
                    };
                    d.to_le_bytes()
                })
                .collect();
            let r = self.rec.log(
                "update/input",
                &rerun::Image::from_rgb24(rgb8(u.input), [u.input.width, u.input.height]),
            );
            self.check(r);
            let r = self.rec.log(
                "update/render_color",
                &rerun::Image::from_rgb24(color, [w, h]),
            );
            self.check(r);
            let r = self.rec.log(
                "update/render_depth",
                &rerun::DepthImage::from_data_type_and_bytes(
                    depth,
                    [w, h],
                    rerun::ChannelDatatype::F32,
                )
                .with_meter(1.0),
            );
            self.check(r);
            let r = self.rec.log(
                "world/window",
                &rerun::Points3D::new(u.window.clone())
                    .with_colors([rerun::Color::from_rgb(31, 119, 180)])
                    .with_radii([0.04]),
            );
            self.check(r);
            let r = self.rec.log(
                "world/keyframes",
                &rerun::Points3D::new(u.keyframes.clone())
                    .with_colors([rerun::Color::from_rgb(214, 39, 40)])
                    .with_radii([0.025]),
            );
            self.check(r);
            let m = u.metrics;
            let mut series: Vec<(&str, f64)> = vec![
                ("metrics/loss", f64::from(m.loss)),
                ("metrics/warp_valid", f64::from(m.warp_valid)),
                ("metrics/seconds", m.seconds),
            ];
            if m.psnr.is_finite() {
                series.push(("metrics/psnr_db", m.psnr));
                series.push(("metrics/ssim", m.ssim));
            }
            if let Some(d) = m.depth_l1_cm {
                series.push(("metrics/depth_l1_cm", d));
            }
            for (path, v) in series {
                let r = self.rec.log(path, &rerun::Scalars::single(v));
                self.check(r);
            }
        }

        /// A mesh of the observed scene (replaces the last one).
        pub fn mesh(&mut self, frame: usize, mesh: &crate::mesh::Mesh) {
            self.rec.set_time_sequence("frame", frame as i64);
            let mut m = rerun::Mesh3D::new(mesh.vertices.iter().copied())
                .with_triangle_indices(mesh.faces.iter().map(|f| rerun::TriangleIndices::from(*f)));
            if let Some(c) = &mesh.colors {
                m = m
                    .with_vertex_colors(c.iter().map(|c| rerun::Color::from_rgb(c[0], c[1], c[2])));
            }
            let r = self.rec.log("world/mesh", &m);
            self.check(r);
        }

        /// Flushes what is buffered (the file is complete after this).
        pub fn finish(&mut self) -> anyhow::Result<()> {
            self.rec
                .flush_blocking()
                .map_err(|e| anyhow::anyhow!("flushing the live view: {e}"))
        }
    }
}

pub use imp::LiveView;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nothing_asked_starts_nothing() {
        assert!(LiveView::start(&LiveOptions::default()).unwrap().is_none());
    }

    /// Without the feature a live option is an error that names the build to use.
    #[cfg(not(feature = "rerun"))]
    #[test]
    fn without_the_feature_the_options_say_how_to_build() {
        let opts = LiveOptions {
            save: Some("run.rrd".into()),
            ..LiveOptions::default()
        };
        let e = LiveView::start(&opts).err().expect("refused").to_string();
        assert!(e.contains("--features rerun"), "{e}");
    }
}
