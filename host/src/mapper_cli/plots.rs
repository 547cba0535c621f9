//! Plots and a report without any viewer: `metrics.png` (PSNR, SSIM, Depth L1 and loss over the
//! sequence, per update and from the final map) drawn with `plotters` (bitmap backend, text
//! with the Ubuntu Light font from `epaint_default_fonts`, so no system font is needed), and
//! `report.html` (the summary table, the plots, the render strips; one self-contained page
//! that links the PNGs beside it).

#[allow(unused_imports)]
use super::*;

use plotters::prelude::*;

/// Size of `metrics.png` (px).
pub const PLOT_SIZE: (u32, u32) = (1200, 800);

/// Colour of the per-update series.
pub const UPDATE_COLOR: RGBColor = RGBColor(31, 119, 180);
/// Colour of the final map's series (and of the first-iteration loss).
pub const FINAL_COLOR: RGBColor = RGBColor(214, 39, 40);

fn register_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // The font is a compiled-in constant of a pinned crate: failing to parse it is a bug.
        plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            epaint_default_fonts::UBUNTU_LIGHT,
        )
        .unwrap_or_else(|_| panic!("the embedded plot font does not parse"));
    });
}

/// A named series of (frame, value) points.
type Series<'a> = (&'a str, RGBColor, Vec<(f64, f64)>);

/// One panel: a title, a y label and up to two series.
struct Panel<'a> {
    title: &'a str,
    y_label: &'a str,
    series: Vec<Series<'a>>,
    log_y: bool,
}

fn draw_panel(
    area: &DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>,
    p: &Panel<'_>,
) -> anyhow::Result<()> {
    let pts = p.series.iter().flat_map(|s| s.2.iter());
    let (mut x0, mut x1, mut y0, mut y1) =
        (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, 0.0f64);
    let mut y_max = f64::NEG_INFINITY;
    for &(x, y) in pts {
        if !(x.is_finite() && y.is_finite()) || (p.log_y && y <= 0.0) {
            continue;
        }
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y_max = y_max.max(y);
    }
    let empty = !x0.is_finite();
    if empty {
        (x0, x1, y0, y_max) = (0.0, 1.0, 0.0, 1.0);
    }
    if x1 <= x0 {
        x1 = x0 + 1.0;
    }
    y1 = y1.max(y_max);
    let err = |e: DrawingAreaErrorKind<_>| anyhow::anyhow!("drawing {}: {e:?}", p.title);
    let mut b = ChartBuilder::on(area);
    b.caption(p.title, ("sans-serif", 22))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(60);
    if p.log_y {
        let (lo, hi) = (y0.max(1e-12) * 0.8, (y1.max(y0 * 1.01)) * 1.25);
        let mut c = b
            .build_cartesian_2d(x0..x1, (lo..hi).log_scale())
            .map_err(err)?;
        c.configure_mesh()
            .x_desc("frame")
            .x_label_formatter(&|x| format!("{x:.0}"))
            .y_desc(p.y_label)
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(err)?;
        draw_series(&mut c, p, err)?;
    } else {
        let pad = ((y1 - y0) * 0.05).max(1e-6);
        let mut c = b
            .build_cartesian_2d(x0..x1, (y0 - pad)..(y1 + pad))
            .map_err(err)?;
        c.configure_mesh()
            .x_desc("frame")
            .x_label_formatter(&|x| format!("{x:.0}"))
            .y_desc(p.y_label)
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(err)?;
        draw_series(&mut c, p, err)?;
    }
    Ok(())
}

fn draw_series<'b, X, Y, E>(
    c: &mut ChartContext<'b, BitMapBackend<'b>, Cartesian2d<X, Y>>,
    p: &Panel<'_>,
    err: E,
) -> anyhow::Result<()>
where
    X: plotters::coord::ranged1d::Ranged<ValueType = f64>,
    Y: plotters::coord::ranged1d::Ranged<ValueType = f64>,
    E: Fn(DrawingAreaErrorKind<<BitMapBackend<'b> as DrawingBackend>::ErrorType>) -> anyhow::Error
        + Copy,
{
    let mut labelled = false;
    for (name, color, data) in &p.series {
        if data.is_empty() {
            continue;
        }
        let color = *color;
        let pts: Vec<(f64, f64)> = data
            .iter()
            .copied()
            .filter(|(x, y)| x.is_finite() && y.is_finite() && (!p.log_y || *y > 0.0))
            .collect();
        c.draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))
            .map_err(err)?
            .label(*name)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
            });
        c.draw_series(
            pts.iter()
                .map(|&(x, y)| Circle::new((x, y), 2, color.filled())),
        )
        .map_err(err)?;
        labelled = true;
    }
    if labelled {
        c.configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 14))
            .draw()
            .map_err(err)?;
    }
    Ok(())
}

/// Draws `metrics.png` into an RGB buffer of [`PLOT_SIZE`]: PSNR, SSIM, Depth L1 (per update
/// and, where given, the final map re-rendered at `final_frames`) and the loss of each update's
/// first and last iteration (log scale).
pub fn metrics_plot(
    rows: &[UpdateMetrics],
    final_frames: &[FinalFrame],
) -> anyhow::Result<Vec<u8>> {
    register_font();
    let (w, h) = PLOT_SIZE;
    let mut buf = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE)
            .map_err(|e| anyhow::anyhow!("plot background: {e:?}"))?;
        let upd = |f: &dyn Fn(&UpdateMetrics) -> Option<f64>| -> Vec<(f64, f64)> {
            rows.iter()
                .filter_map(|r| f(r).map(|v| (r.frame as f64, v)))
                .collect()
        };
        let fin = |f: &dyn Fn(&FinalFrame) -> Option<f64>| -> Vec<(f64, f64)> {
            final_frames
                .iter()
                .filter_map(|r| f(r).map(|v| (r.frame as f64, v)))
                .collect()
        };
        let panels = [
            Panel {
                title: "PSNR",
                y_label: "dB",
                series: vec![
                    ("after each update", UPDATE_COLOR, upd(&|r| Some(r.psnr))),
                    ("final map", FINAL_COLOR, fin(&|r| Some(r.psnr))),
                ],
                log_y: false,
            },
            Panel {
                title: "SSIM",
                y_label: "SSIM",
                series: vec![
                    ("after each update", UPDATE_COLOR, upd(&|r| Some(r.ssim))),
                    ("final map", FINAL_COLOR, fin(&|r| Some(r.ssim))),
                ],
                log_y: false,
            },
            Panel {
                title: "Depth L1",
                y_label: "cm",
                series: vec![
                    ("after each update", UPDATE_COLOR, upd(&|r| r.depth_l1_cm)),
                    ("final map", FINAL_COLOR, fin(&|r| r.depth_l1_cm)),
                ],
                log_y: false,
            },
            Panel {
                title: "loss",
                y_label: "loss",
                series: vec![
                    (
                        "last iteration",
                        UPDATE_COLOR,
                        upd(&|r| Some(f64::from(r.loss))),
                    ),
                    (
                        "first iteration",
                        FINAL_COLOR,
                        upd(&|r| Some(f64::from(r.loss_first))),
                    ),
                ],
                log_y: true,
            },
        ];
        for (area, p) in root.split_evenly((2, 2)).iter().zip(&panels) {
            draw_panel(area, p)?;
        }
        root.present().map_err(|e| anyhow::anyhow!("plot: {e:?}"))?;
    }
    Ok(buf)
}

/// Writes `metrics.png` (see [`metrics_plot`]).
pub fn write_metrics_png(
    path: &Path,
    rows: &[UpdateMetrics],
    final_frames: &[FinalFrame],
) -> anyhow::Result<()> {
    let buf = metrics_plot(rows, final_frames)?;
    let mut png = Vec::new();
    use image::ImageEncoder;
    image::codecs::png::PngEncoder::new(&mut png).write_image(
        &buf,
        PLOT_SIZE.0,
        PLOT_SIZE.1,
        image::ExtendedColorType::Rgb8,
    )?;
    crate::atomic::write_bytes_atomic(path, &png)
}

fn escape(s: &str) -> String {
    let mut o = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => o.push_str("&amp;"),
            '<' => o.push_str("&lt;"),
            '>' => o.push_str("&gt;"),
            '"' => o.push_str("&quot;"),
            '\'' => o.push_str("&#39;"),
            c => o.push(c),
        }
    }
    o
}

/// The page `report.html` holds: the summary table, `metrics.png` and the render strips
/// (`renders`: file names relative to the page, in order).
pub fn report_html(s: &MapSummary, renders: &[String]) -> String {
    let f = |x: Option<f64>, p: usize| x.map_or("-".to_string(), |v| format!("{v:.p$}"));
    let mut rows: Vec<(String, String)> = vec![
        ("dataset".into(), s.dataset.display().to_string()),
        (
            "frames".into(),
            format!("{} at {}x{}", s.frames, s.width, s.height),
        ),
        (
            "backend".into(),
            format!("{} ({} threads)", s.backend, s.threads),
        ),
        (
            "scene box".into(),
            format!(
                "{:?} .. {:?} m ({})",
                s.scene_box[0], s.scene_box[1], s.scene_box_source
            ),
        ),
        (
            "updates / iterations".into(),
            format!("{} / {}", s.updates, s.iterations),
        ),
        (
            "PSNR (per update)".into(),
            format!("{} dB", f(s.mean_psnr, 2)),
        ),
        ("SSIM (per update)".into(), f(s.mean_ssim, 3)),
        (
            "Depth L1 (per update)".into(),
            format!("{} cm", f(s.mean_depth_l1_cm, 2)),
        ),
    ];
    if s.final_frames > 0 {
        rows.push((
            format!("final map over {} frames", s.final_frames),
            format!(
                "PSNR {} dB, SSIM {}, Depth L1 {} cm",
                f(s.final_psnr, 2),
                f(s.final_ssim, 3),
                f(s.final_depth_l1_cm, 2)
            ),
        ));
    }
    rows.push((
        "mesh".into(),
        match &s.mesh {
            Some(m) => format!(
                "{} faces ({:.1} cm grid, level {:.3} m) vs {}: Accuracy {:.2} cm, Completion {:.2} \
                 cm, ratio {:.1} %",
                s.mesh_faces,
                s.mesh_spacing * 100.0,
                s.mesh_level,
                s.mesh_ground_truth.as_deref().unwrap_or("?"),
                m.accuracy_cm,
                m.completion_cm,
                m.completion_ratio_pct
            ),
            None => format!(
                "{} faces: {}",
                s.mesh_faces,
                s.mesh_error.as_deref().unwrap_or("no ground truth")
            ),
        },
    ));
    rows.push((
        "time".into(),
        format!(
            "{:.1} s total, mapping {:.1} s ({:.1} ms per iteration, {:.2} s per frame)",
            s.seconds_total,
            s.seconds_mapping,
            1e3 * s.seconds_per_iteration,
            s.seconds_per_frame
        ),
    ));
    let mut h = String::new();
    h += "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n";
    h += &format!(
        "<title>himap map: {}</title>\n",
        escape(&s.dataset.display().to_string())
    );
    h += "<style>body{font-family:sans-serif;margin:2em;max-width:1300px}\
          table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:4px 8px;text-align:left}\
          img{max-width:100%}</style>\n</head>\n<body>\n";
    h += "<h1>himap map</h1>\n<h2>Summary</h2>\n<table>\n";
    for (k, v) in &rows {
        h += &format!("<tr><th>{}</th><td>{}</td></tr>\n", escape(k), escape(v));
    }
    h += "</table>\n<h2>Metrics</h2>\n";
    h += "<p>Per update (the newest frame rendered right after its update) and from the final \
          map (re-rendered over the whole sequence). Data: <a href=\"metrics.csv\">metrics.csv</a>, \
          <a href=\"summary.json\">summary.json</a>.</p>\n";
    h += "<img src=\"metrics.png\" alt=\"PSNR, SSIM, Depth L1 and loss over the sequence\">\n";
    h += "<h2>Renders</h2>\n<p>input | rendered colour | rendered depth | ground-truth depth \
          (when the dataset has it)</p>\n";
    for r in renders {
        h += &format!(
            "<figure><img src=\"{0}\" alt=\"{0}\"><figcaption>{0}</figcaption></figure>\n",
            escape(r)
        );
    }
    h += "<h2>Configuration</h2>\n<pre>";
    h += &escape(&toml::to_string(&s.config).unwrap_or_else(|e| format!("({e})")));
    h += "</pre>\n</body>\n</html>\n";
    h
}

/// Writes `metrics.png` and `report.html` into `out` (the run's folder, with its `renders/`).
pub fn write_report(out: &Path, s: &MapSummary, rows: &[UpdateMetrics]) -> anyhow::Result<()> {
    write_metrics_png(&out.join("metrics.png"), rows, &s.final_per_frame)?;
    let mut renders: Vec<String> = match std::fs::read_dir(out.join("renders")) {
        Ok(d) => d
            .filter_map(|e| e.ok())
            .filter_map(|e| e.file_name().into_string().ok())
            .filter(|n| n.ends_with(".png"))
            .map(|n| format!("renders/{n}"))
            .collect(),
        Err(_) => Vec::new(),
    };
    renders.sort();
    crate::atomic::write_bytes_atomic(
        &out.join("report.html"),
        report_html(s, &renders).as_bytes(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(frame: usize, psnr: f64) -> UpdateMetrics {
        UpdateMetrics {
            frame,
            kind: "online".into(),
            psnr,
            ssim: 0.5 + 0.01 * frame as f64,
            depth_l1_cm: Some(10.0 - 0.1 * frame as f64),
            loss_first: 0.2,
            loss: 0.05,
            color_loss: 0.0,
            warp_loss: 0.0,
            warp_valid: 0.9,
            open_rays: 0.0,
            new_loss_ratio: 0.0,
            new_warp_valid: 0.0,
            depth_near_cm: None,
            plain_share: None,
            depth_l1_plain_cm: None,
            window_keyframes: 3,
            iters: 10,
            seconds: 1.0,
        }
    }

    fn count(buf: &[u8], c: RGBColor) -> usize {
        buf.chunks(3).filter(|p| p == &[c.0, c.1, c.2]).count()
    }

    #[test]
    fn plot_draws_both_series_and_text() {
        let rows: Vec<_> = (0..30).map(|i| row(i, 20.0 + 0.2 * i as f64)).collect();
        let fin: Vec<_> = (0..30)
            .step_by(5)
            .map(|i| FinalFrame {
                frame: i,
                psnr: 19.0,
                ssim: 0.6,
                depth_l1_cm: Some(8.0),
            })
            .collect();
        let buf = metrics_plot(&rows, &fin).unwrap();
        assert_eq!(buf.len(), (PLOT_SIZE.0 * PLOT_SIZE.1 * 3) as usize);
        let (upd, fin_px) = (count(&buf, UPDATE_COLOR), count(&buf, FINAL_COLOR));
        assert!(
            upd > 2000 && fin_px > 1000,
            "{upd} / {fin_px} series pixels"
        );
        // text and axes: dark pixels that are neither series
        let dark = buf.chunks(3).filter(|p| p.iter().all(|&v| v < 60)).count();
        assert!(dark > 2000, "{dark} dark pixels");
        // without the final map, its colour appears only in the loss panel's first-iteration
        // series: fewer pixels
        let only = metrics_plot(&rows, &[]).unwrap();
        assert!(count(&only, FINAL_COLOR) < fin_px);
        // no rows at all still gives a (blank-axes) plot, not an error
        assert!(metrics_plot(&[], &[]).is_ok());
    }

    #[test]
    fn report_lists_the_summary_plots_and_renders_escaped() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("renders")).unwrap();
        for n in ["update_0003.png", "update_0001.png", "notes.txt"] {
            std::fs::write(dir.path().join("renders").join(n), b"x").unwrap();
        }
        let s = MapSummary {
            dataset: PathBuf::from("/data/<room>&co"),
            frames: 30,
            width: 128,
            height: 96,
            backend: "cpu".into(),
            threads: 2,
            scene_box: [[0.0; 3], [1.0; 3]],
            scene_box_source: "configuration".into(),
            updates: 6,
            iterations: 300,
            rejected_steps: 0,
            lr_reductions: 0,
            mean_psnr: Some(23.456),
            mean_ssim: Some(0.81),
            mean_depth_l1_cm: None,
            frames_outside_box: 0,
            final_frames: 0,
            final_psnr: None,
            final_ssim: None,
            final_depth_l1_cm: None,
            final_depth_median_cm: None,
            final_depth_far_share: None,
            final_per_frame: Vec::new(),
            mesh: None,
            mesh_observed_gt: None,
            mesh_ground_truth: None,
            mesh_error: Some("no ground truth".into()),
            mesh_faces: 1234,
            mesh_full_faces: 2000,
            mesh_level: 0.0,
            mesh_spacing: 0.04,
            beta: 10.0,
            seconds_total: 12.0,
            seconds_mapping: 10.0,
            seconds_per_iteration: 0.03,
            seconds_per_frame: 0.3,
            parameters: 1000,
            config: Config::small(),
        };
        let rows: Vec<_> = (0..6).map(|i| row(5 * i, 22.0)).collect();
        write_report(dir.path(), &s, &rows).unwrap();
        let html = std::fs::read_to_string(dir.path().join("report.html")).unwrap();
        assert!(html.contains("23.46 dB"), "{html}");
        assert!(html.contains("/data/&lt;room&gt;&amp;co"));
        assert!(!html.contains("<room>"));
        assert!(html.contains("src=\"metrics.png\""));
        let a = html.find("renders/update_0001.png").unwrap();
        let b = html.find("renders/update_0003.png").unwrap();
        assert!(a < b, "renders in order");
        assert!(!html.contains("notes.txt"));
        assert!(html.contains("[mapper]"), "the configuration is listed");
        let png = image::open(dir.path().join("metrics.png")).unwrap();
        assert_eq!((png.width(), png.height()), PLOT_SIZE);
    }
}
