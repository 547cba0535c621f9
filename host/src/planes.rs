//! Plane priors for plain regions (issue #11): the warping loss cannot place a surface without
//! texture, and a plain wall's depth is decided by its textured border. For each held frame:
//! the plain regions of its image (4-connected pixels whose colour steps to their neighbours
//! are all below [`PlaneSection::step`]), the map's rendered depth on each region's inner
//! border, a plane fitted to it (RANSAC, then least squares on the inliers; a plane's inverse
//! depth is affine in the normalised image coordinates), accepted when most of the border
//! agrees, the agreeing points span the region and their convex hull covers enough of it (a
//! plane fitted beside an object in front of a wall, whose edge belongs to the object, is not
//! extrapolated over the whole wall), or, when the border is partly the outline of objects
//! in front of the region, half of it lies on the plane and none of it behind; every pixel
//! of an accepted region then gets
//! the plane's depth as a per-pixel prior ([`Backend::set_depth_prior`], read by the mapping
//! loss as `weight * smoothL1_0.05(D - target)`). Where the border is not one plane (a plain
//! object meeting a wall of the same colour, ICL's white furniture) the fit fails and the
//! region gets no prior. Reads only frames already pushed and the map.

use crate::config::Config;
use anyhow::{bail, Result};
use himap_core::camera::{Intrinsics, Pose};
use himap_core::field::model::{Ray, RayResult};
use himap_core::mapper::{IterInfo, Mapper, MapperError, UpdateReport};
use himap_core::rng::SplitMix;
use himap_core::train::backend::Backend;
use himap_core::train::pixel::unpack_rgba8;
use serde::{Deserialize, Serialize};

/// `[planes]`: how the plane priors of plain regions are found (their weights are
/// `mapper.lambda_plane` online and `mapper.refine_lambda_plane` in the final refinement).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PlaneSection {
    /// Largest mean channel step between neighbouring pixels inside a plain region.
    pub step: f32,
    /// Smallest region, as a share of the image.
    pub min_area: f32,
    /// Width (px) of the inner border ring whose rendered depth the plane is fitted to.
    pub border: u32,
    /// Share of the border points that must lie on the plane.
    pub inliers: f32,
    /// A border point lies on the plane when its depth is within `tol_abs + tol_rel * depth`.
    pub tol_abs: f32,
    pub tol_rel: f32,
    /// Smallest spread (standard deviation along the thinner axis, px at 320 px width) of the
    /// inliers' pixels: a plane fitted to one edge of a region is not constrained across it.
    pub spread: f32,
    /// Smallest share of the region's pixels inside the convex hull of the inliers' pixels: a
    /// plane fitted to one corner of a region (the wall beside an object in front of it, whose
    /// edge belongs to the object) would be extrapolated over the rest (0 = no check).
    pub cover: f32,
    /// A region whose border fails `inliers` may still keep a plane that this share of its
    /// border lies on when at most `behind` of the border lies behind it (the rest in
    /// front: the outline of objects standing before a plain wall, whose edges carry the
    /// objects' depth). That plane is searched again with each candidate scored by its
    /// inliers less the border points behind it. 0 = off (as before 2026-12-06).
    pub occluded_inliers: f32,
    /// Largest share of the border points farther than the plane (beyond the tolerance) for
    /// `occluded_inliers` to accept it.
    pub behind: f32,
    /// Refinement iterations between two refreshes of the priors (0 = once, before it).
    pub refresh_every: u32,
    /// Border points rendered per region at most.
    pub max_points: u32,
    /// RANSAC trials per region.
    pub trials: u32,
}

impl Default for PlaneSection {
    fn default() -> Self {
        Self {
            step: 0.015,
            min_area: 0.008,
            border: 3,
            inliers: 0.75,
            tol_abs: 0.02,
            tol_rel: 0.02,
            spread: 5.0,
            cover: COVER,
            occluded_inliers: 0.5,
            behind: 0.0,
            refresh_every: 250,
            max_points: 400,
            trials: 100,
        }
    }
}

const COVER: f32 = 0.15;

/// The online plane priors (`mapper.lambda_plane`): after every online update the local
/// frames' priors are fitted to the map they were just mapped into, and the frames that left
/// the local window since lose theirs, so that only the window's newest frames carry a prior
/// (a keyframe's prior, fitted to a map long gone, would keep pulling its plain regions
/// towards an old guess). A caller driving [`Mapper::push_frame`] calls
/// [`Self::after_update`] whenever a push returns a report, as `himap map` does; a resumed
/// run rebuilds the same priors with [`Self::resume`]. Off in every preset: on the house it
/// helps the plain walls the newest frames see and hurts the frames that first look through
/// a doorway (a plain far wall seen through a door gets the plane of the door's frame, a
/// membrane the next frames must carve), so the worst stretch of some walks gets worse
/// (ARCHITECTURE.md, forty-first session).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct OnlinePriors {
    /// Ids of the frames whose image slots carry a prior (the local frames of the last update).
    carrying: Vec<u32>,
}

impl OnlinePriors {
    /// Ids of the frames that carry a prior now (what a checkpoint stores).
    pub fn carrying(&self) -> &[u32] {
        &self.carrying
    }

    /// After an online update: clears the priors of the frames that left the local window and
    /// fits the local frames' priors to the map (nothing when `mapper.lambda_plane` is 0).
    pub fn after_update<B: Backend>(
        &mut self,
        mapper: &mut Mapper<'_, B>,
        config: &Config,
    ) -> Result<Option<PlaneStats>>
    where
        B::Error: std::error::Error + Send + Sync + 'static,
    {
        if mapper.config().lambda_plane == 0.0 {
            return Ok(None);
        }
        let ids: Vec<u32> = mapper.local_ids().collect();
        let left: Vec<u32> = mapper
            .state()
            .held()
            .filter(|h| self.carrying.contains(&h.id) && !ids.contains(&h.id))
            .map(|h| h.slot)
            .collect();
        if !left.is_empty() {
            let k = mapper.intrinsics();
            let none = vec![0.0f32; (k.width * k.height) as usize];
            for slot in left {
                mapper.backend_mut().set_depth_prior(slot, &none)?;
            }
        }
        let st = refresh(mapper, &ids, &config.planes, config.model.max_depth)?;
        self.carrying = ids;
        Ok(Some(st))
    }

    /// A resumed run's priors: those of the frames `carrying` (a checkpoint's
    /// [`Self::carrying`]), fitted again to the restored map, which is the map they were
    /// fitted to (a checkpoint is written between updates), so the run goes on with the same
    /// bits as one never interrupted.
    pub fn resume<B: Backend>(
        mapper: &mut Mapper<'_, B>,
        config: &Config,
        carrying: &[u32],
    ) -> Result<Self>
    where
        B::Error: std::error::Error + Send + Sync + 'static,
    {
        if mapper.config().lambda_plane != 0.0 && !carrying.is_empty() {
            refresh(mapper, carrying, &config.planes, config.model.max_depth)?;
        }
        Ok(Self {
            carrying: carrying.to_vec(),
        })
    }
}

/// Why [`refine`] failed: the mapper (its backend) or the priors.
#[derive(Debug)]
pub enum RefineError<E> {
    Mapper(MapperError<E>),
    Other(anyhow::Error),
}

/// The final refinement ([`Mapper::refine`]) with the plane priors of `config`: when
/// `mapper.refine_lambda_plane` is on, the priors of every held frame are refreshed from the
/// map before the refinement and every `planes.refresh_every` iterations of it (`on_priors`
/// hears each refresh); otherwise exactly [`Mapper::refine`]. `himap map` runs this; a caller
/// driving [`Mapper::push_frame`] itself gets the same map by calling it too.
pub fn refine<B: Backend, F: FnMut(&IterInfo), G: FnMut(&PlaneStats)>(
    mapper: &mut Mapper<'_, B>,
    config: &Config,
    on_priors: &mut G,
    observe: &mut F,
) -> std::result::Result<Option<UpdateReport>, RefineError<B::Error>>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let iters = mapper.config().refine_iters;
    let planes = mapper.config().refine_lambda_plane != 0.0;
    if !planes {
        return mapper.refine(observe).map_err(RefineError::Mapper);
    }
    let part = match config.planes.refresh_every {
        0 => iters,
        n => n,
    };
    let mut rep: Option<UpdateReport> = None;
    let mut done = 0;
    while done < iters {
        let n = part.min(iters - done);
        let ids: Vec<u32> = mapper.local_ids().chain(mapper.keyframe_ids()).collect();
        let st = refresh(mapper, &ids, &config.planes, config.model.max_depth)
            .map_err(RefineError::Other)?;
        on_priors(&st);
        let r = mapper
            .refine_part(n, &mut |info: &IterInfo| {
                observe(&IterInfo {
                    iter: done + info.iter,
                    iters,
                    ..*info
                })
            })
            .map_err(RefineError::Mapper)?;
        if let Some(r) = r {
            rep = Some(match rep {
                Some(p) => UpdateReport {
                    first: p.first,
                    ..r
                },
                None => r,
            });
        }
        done += n;
    }
    Ok(rep)
}

impl PlaneSection {
    /// Checks the settings (the configuration's `[planes]`).
    pub fn validate(&self) -> Result<()> {
        let pos = |x: f32| x > 0.0 && x.is_finite();
        if !pos(self.step) {
            bail!("planes.step must be positive");
        }
        if !(self.min_area >= 0.0 && self.min_area < 1.0) {
            bail!("planes.min_area must be in [0, 1) (a share of the image)");
        }
        if self.border == 0 {
            bail!("planes.border must be at least 1 px");
        }
        if !(self.inliers > 0.0 && self.inliers <= 1.0) {
            bail!("planes.inliers must be in (0, 1]");
        }
        if !(self.tol_abs >= 0.0 && self.tol_rel >= 0.0 && pos(self.tol_abs + self.tol_rel)) {
            bail!("planes.tol_abs and planes.tol_rel must be >= 0 and not both 0");
        }
        if !(self.spread >= 0.0 && self.spread.is_finite()) {
            bail!("planes.spread must be >= 0");
        }
        if !(0.0..=1.0).contains(&self.cover) {
            bail!("planes.cover must be in [0, 1] (a share of the region)");
        }
        if !(0.0..=1.0).contains(&self.occluded_inliers) || !(0.0..=1.0).contains(&self.behind) {
            bail!("planes.occluded_inliers and planes.behind must be in [0, 1] (shares of the border)");
        }
        if self.max_points < 12 || self.trials == 0 {
            bail!("planes.max_points must be at least 12 and planes.trials at least 1");
        }
        Ok(())
    }
}

/// What one refresh did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PlaneStats {
    pub frames: u32,
    pub regions: u32,
    pub accepted: u32,
    /// Pixels given a prior.
    pub pixels: u64,
    /// Pixels of all frames.
    pub total: u64,
}

impl PlaneStats {
    /// One log line.
    pub fn describe(&self) -> String {
        format!(
            "plane priors: {} of {} plain regions in {} frames, {:.1} % of their pixels",
            self.accepted,
            self.regions,
            self.frames,
            100.0 * self.pixels as f64 / self.total.max(1) as f64
        )
    }
}

/// The plain regions of an RGB image (`w * h` texels): a label per pixel (0 = not plain or in
/// a region below `min_px`), and the regions' count.
pub fn plain_regions(
    rgb: &[[f32; 3]],
    w: usize,
    h: usize,
    step: f32,
    min_px: usize,
) -> (Vec<u32>, u32) {
    let diff = |a: [f32; 3], b: [f32; 3]| {
        ((a[0] - b[0]).abs() + (a[1] - b[1]).abs() + (a[2] - b[2]).abs()) / 3.0
    };
    let mut plain = vec![true; w * h];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if x + 1 < w && diff(rgb[i], rgb[i + 1]) >= step {
                plain[i] = false;
                plain[i + 1] = false;
            }
            if y + 1 < h && diff(rgb[i], rgb[i + w]) >= step {
                plain[i] = false;
                plain[i + w] = false;
            }
        }
    }
    let mut label = vec![0u32; w * h];
    let mut n = 0u32;
    let mut stack = Vec::new();
    let mut members = Vec::new();
    for s in 0..w * h {
        if !plain[s] || label[s] != 0 {
            continue;
        }
        n += 1;
        label[s] = n;
        stack.push(s);
        members.clear();
        while let Some(i) = stack.pop() {
            members.push(i);
            let (x, y) = (i % w, i / w);
            let mut visit = |j: usize| {
                if plain[j] && label[j] == 0 {
                    label[j] = n;
                    stack.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < w {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - w);
            }
            if y + 1 < h {
                visit(i + w);
            }
        }
        if members.len() < min_px {
            for &i in &members {
                label[i] = u32::MAX;
            }
            n -= 1;
        }
    }
    for l in &mut label {
        if *l == u32::MAX {
            *l = 0;
        }
    }
    (label, n)
}

/// City-block distance of every pixel to the nearest pixel labelled 0 (`u32::MAX` when there
/// is none; the image border is not a region's border).
pub fn distance_to_unlabelled(label: &[u32], w: usize, h: usize) -> Vec<u32> {
    let mut d: Vec<u32> = label
        .iter()
        .map(|&l| if l == 0 { 0 } else { u32::MAX })
        .collect();
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if x > 0 {
                d[i] = d[i].min(d[i - 1].saturating_add(1));
            }
            if y > 0 {
                d[i] = d[i].min(d[i - w].saturating_add(1));
            }
        }
    }
    for y in (0..h).rev() {
        for x in (0..w).rev() {
            let i = y * w + x;
            if x + 1 < w {
                d[i] = d[i].min(d[i + 1].saturating_add(1));
            }
            if y + 1 < h {
                d[i] = d[i].min(d[i + w].saturating_add(1));
            }
        }
    }
    d
}

/// A plane as inverse depth affine in normalised coordinates: `1 / z = a x + b y + c`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InversePlane(pub [f64; 3]);

impl InversePlane {
    /// The plane through three points `(x, y, z)` (`None` when degenerate).
    pub fn through(p: [[f64; 3]; 3]) -> Option<Self> {
        let m = p.map(|q| [q[0], q[1], 1.0]);
        let r = p.map(|q| 1.0 / q[2]);
        solve3(m, r).map(Self)
    }

    /// Depth at normalised coordinates `(x, y)` (`None` behind the camera or at infinity).
    pub fn depth(&self, x: f64, y: f64) -> Option<f64> {
        let inv = self.0[0] * x + self.0[1] * y + self.0[2];
        (inv > 1e-6).then(|| 1.0 / inv)
    }

    /// Least squares over points `(x, y, z)`, each inverse-depth residual weighted by `z^2`
    /// (so that it measures depth: `dz ~ z^2 d(1/z)`).
    pub fn fit(points: &[[f64; 3]]) -> Option<Self> {
        let mut a = [[0.0f64; 3]; 3];
        let mut b = [0.0f64; 3];
        for p in points {
            let w = p[2] * p[2] * p[2] * p[2];
            let row = [p[0], p[1], 1.0];
            for i in 0..3 {
                for j in 0..3 {
                    a[i][j] += w * row[i] * row[j];
                }
                b[i] += w * row[i] / p[2];
            }
        }
        solve3(a, b).map(Self)
    }
}

/// `m x = r` by Cramer's rule (`None` when nearly singular).
fn solve3(m: [[f64; 3]; 3], r: [f64; 3]) -> Option<[f64; 3]> {
    let det = |m: [[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(m);
    let scale = m.iter().flatten().fold(0.0f64, |s, v| s.max(v.abs()));
    if !d.is_finite() || d.abs() <= 1e-12 * scale * scale * scale {
        return None;
    }
    let mut x = [0.0; 3];
    for (c, xc) in x.iter_mut().enumerate() {
        let mut mc = m;
        for (row, rv) in mc.iter_mut().zip(r) {
            row[c] = rv;
        }
        *xc = det(mc) / d;
    }
    Some(x)
}

/// The plane of one region from its border points `(x, y, z)` and their pixels, or `None`
/// when the border is not one plane ([`PlaneSection`]'s acceptance rules).
pub fn region_plane(
    points: &[[f64; 3]],
    pixels: &[[f32; 2]],
    cfg: &PlaneSection,
    spread_px: f32,
    rng: &mut SplitMix,
) -> Option<(InversePlane, Vec<usize>)> {
    let n = points.len();
    if n < 12 {
        return None;
    }
    let tol = |z: f64| cfg.tol_abs as f64 + cfg.tol_rel as f64 * z;
    let on = |pl: &InversePlane, p: &[f64; 3]| {
        pl.depth(p[0], p[1])
            .is_some_and(|d| (d - p[2]).abs() < tol(p[2]))
    };
    // The least-squares plane of a RANSAC plane's inliers, and its own inliers.
    let refit = |pl: InversePlane| {
        let pts: Vec<[f64; 3]> = points.iter().filter(|p| on(&pl, p)).copied().collect();
        let pl = InversePlane::fit(&pts)?;
        let inl: Vec<usize> = (0..n).filter(|&i| on(&pl, &points[i])).collect();
        Some((pl, inl))
    };
    let (pl, inl) = refit(ransac(points, cfg.trials, rng, |pl| {
        points.iter().filter(|p| on(pl, p)).count() as i64
    })?)?;
    if (inl.len() as f32) < cfg.inliers * n as f32 {
        // A border that is partly the outline of objects in front of the region: keep the
        // plane that most of the rest lies on when none of the border lies behind it.
        let (occ, bmax) = (cfg.occluded_inliers, cfg.behind);
        if occ <= 0.0 {
            return None;
        }
        let behind = |pl: &InversePlane, p: &[f64; 3]| {
            pl.depth(p[0], p[1]).is_none_or(|d| d < p[2] - tol(p[2]))
        };
        let (pl, inl) = refit(ransac(points, cfg.trials, rng, |pl| {
            points
                .iter()
                .map(|p| on(pl, p) as i64 - behind(pl, p) as i64)
                .sum()
        })?)?;
        let nb = points.iter().filter(|p| behind(&pl, p)).count();
        if (inl.len() as f32) < occ * n as f32 || nb as f32 > bmax * n as f32 {
            return None;
        }
        return spread_ok(&inl, pixels, spread_px).then_some((pl, inl));
    }
    spread_ok(&inl, pixels, spread_px).then_some((pl, inl))
}

/// RANSAC over `trials` draws of three border points: the plane through them with the
/// highest `score` (the first of equals), or `None` when no draw gives a plane.
fn ransac(
    points: &[[f64; 3]],
    trials: u32,
    rng: &mut SplitMix,
    score: impl Fn(&InversePlane) -> i64,
) -> Option<InversePlane> {
    let n = points.len() as u32;
    let mut best: Option<(i64, InversePlane)> = None;
    for _ in 0..trials {
        let i = rng.below(n) as usize;
        let j = rng.below(n) as usize;
        let k = rng.below(n) as usize;
        if i == j || j == k || i == k {
            continue;
        }
        let Some(pl) = InversePlane::through([points[i], points[j], points[k]]) else {
            continue;
        };
        let c = score(&pl);
        if best.is_none_or(|(b, _)| c > b) {
            best = Some((c, pl));
        }
    }
    best.map(|(_, pl)| pl)
}

/// Whether the inliers' pixels spread at least `spread_px` along their thinner axis.
fn spread_ok(inl: &[usize], pixels: &[[f32; 2]], spread_px: f32) -> bool {
    // spread of the inliers' pixels along the thinner axis
    let m = inl.len() as f64;
    let (mut su, mut sv) = (0.0f64, 0.0f64);
    for &i in inl {
        su += pixels[i][0] as f64;
        sv += pixels[i][1] as f64;
    }
    let (mu, mv) = (su / m, sv / m);
    let (mut cuu, mut cvv, mut cuv) = (0.0f64, 0.0f64, 0.0f64);
    for &i in inl {
        let (du, dv) = (pixels[i][0] as f64 - mu, pixels[i][1] as f64 - mv);
        cuu += du * du;
        cvv += dv * dv;
        cuv += du * dv;
    }
    let (cuu, cvv, cuv) = (cuu / m, cvv / m, cuv / m);
    let tr = cuu + cvv;
    let disc = ((cuu - cvv) * (cuu - cvv) / 4.0 + cuv * cuv).sqrt();
    let small = tr / 2.0 - disc;
    small.max(0.0).sqrt() >= spread_px as f64
}

/// Convex hull (counter-clockwise in image coordinates, no repeated first point) of `pts`
/// (Andrew's monotone chain); fewer than three distinct points give what there is.
pub fn convex_hull(pts: &[[f32; 2]]) -> Vec<[f32; 2]> {
    let mut p: Vec<[f32; 2]> = pts.to_vec();
    p.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    p.dedup();
    if p.len() < 3 {
        return p;
    }
    let cross = |o: [f32; 2], a: [f32; 2], b: [f32; 2]| {
        (a[0] - o[0]) as f64 * (b[1] - o[1]) as f64 - (a[1] - o[1]) as f64 * (b[0] - o[0]) as f64
    };
    let chain = |pts: &mut dyn Iterator<Item = [f32; 2]>| {
        let mut c: Vec<[f32; 2]> = Vec::new();
        for q in pts {
            while c.len() >= 2 && cross(c[c.len() - 2], c[c.len() - 1], q) <= 0.0 {
                c.pop();
            }
            c.push(q);
        }
        c.pop();
        c
    };
    let mut hull = chain(&mut p.iter().copied());
    hull.extend(chain(&mut p.iter().rev().copied()));
    hull
}

/// The span `[lo, hi]` of columns of the convex polygon `hull` on row `v` (None when the row
/// misses it).
fn hull_row_span(hull: &[[f32; 2]], v: f32) -> Option<(f32, f32)> {
    if hull.len() < 3 {
        return None;
    }
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    for i in 0..hull.len() {
        let (a, b) = (hull[i], hull[(i + 1) % hull.len()]);
        let (ya, yb) = (a[1].min(b[1]), a[1].max(b[1]));
        if v < ya || v > yb {
            continue;
        }
        // the edge's column on row v (a horizontal edge: both its ends)
        let (xa, xb) = if yb > ya {
            let x = a[0] + (b[0] - a[0]) * (v - a[1]) / (b[1] - a[1]);
            (x, x)
        } else {
            (a[0], b[0])
        };
        lo = lo.min(xa.min(xb));
        hi = hi.max(xa.max(xb));
    }
    (lo <= hi).then_some((lo, hi))
}

/// The share of the pixels labelled `region` in `label` (width `w`) that lie inside the convex
/// polygon `hull`.
pub fn hull_cover(label: &[u32], w: usize, region: u32, hull: &[[f32; 2]]) -> f32 {
    let h = label.len() / w.max(1);
    let (mut inside, mut all) = (0u64, 0u64);
    for v in 0..h {
        let span = hull_row_span(hull, v as f32);
        for u in 0..w {
            if label[v * w + u] != region {
                continue;
            }
            all += 1;
            if span.is_some_and(|(lo, hi)| u as f32 >= lo && u as f32 <= hi) {
                inside += 1;
            }
        }
    }
    if all == 0 {
        0.0
    } else {
        inside as f32 / all as f32
    }
}

/// Recomputes the plane priors of the held frames `frames` (their ids; others keep theirs).
pub fn refresh<B: Backend>(
    mapper: &mut Mapper<'_, B>,
    frames: &[u32],
    cfg: &PlaneSection,
    max_depth: f32,
) -> Result<PlaneStats>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let k = mapper.intrinsics();
    let held: Vec<_> = mapper
        .state()
        .held()
        .filter(|h| frames.contains(&h.id))
        .copied()
        .collect();
    let mut stats = PlaneStats::default();
    for h in held {
        let prior = frame_prior(
            mapper.backend_mut(),
            &k,
            h.slot,
            &h.pose,
            h.id,
            cfg,
            max_depth,
            &mut stats,
        )?;
        if let Some(dir) = std::env::var_os("HIMAP_PLANES_DUMP") {
            // dev diagnostic: the targets as 16-bit depth PNGs (1 / 6553.5 m; 0 = none)
            let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(
                k.width,
                k.height,
                |u, v| {
                    let p = prior[(v * k.width + u) as usize];
                    image::Luma([(p * 6553.5).round().min(65535.0) as u16])
                },
            );
            img.save(std::path::Path::new(&dir).join(format!("prior{:06}.png", h.id)))?;
        }
        if !mapper.backend_mut().set_depth_prior(h.slot, &prior)? {
            bail!("[planes]: the plane priors need the cpu backend (this backend has no per-pixel depth priors)");
        }
    }
    Ok(stats)
}

/// The prior of one frame (image slot `slot`, camera `pose`).
#[allow(clippy::too_many_arguments)]
fn frame_prior<B: Backend>(
    backend: &mut B,
    k: &Intrinsics,
    slot: u32,
    pose: &Pose,
    id: u32,
    cfg: &PlaneSection,
    max_depth: f32,
    stats: &mut PlaneStats,
) -> Result<Vec<f32>>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let (w, h) = (k.width as usize, k.height as usize);
    stats.frames += 1;
    stats.total += (w * h) as u64;
    let mut prior = vec![0.0f32; w * h];
    let rgb: Vec<[f32; 3]> = (0..w * h)
        .map(|i| unpack_rgba8(backend.slot_texel(slot, (i % w) as u32, (i / w) as u32)))
        .collect();
    let min_px = ((cfg.min_area * (w * h) as f32) as usize).max(16);
    let (label, n) = plain_regions(&rgb, w, h, cfg.step, min_px);
    if n == 0 {
        return Ok(prior);
    }
    let dist = distance_to_unlabelled(&label, w, h);
    // border pixels of each region, thinned to at most max_points
    let mut border: Vec<Vec<u32>> = vec![Vec::new(); n as usize];
    for i in 0..w * h {
        let l = label[i];
        if l != 0 && dist[i] <= cfg.border {
            border[l as usize - 1].push(i as u32);
        }
    }
    let mut rays = Vec::new();
    let mut owner = Vec::new();
    for (r, b) in border.iter().enumerate() {
        let stride = b.len().div_ceil(cfg.max_points.max(1) as usize).max(1);
        for &i in b.iter().step_by(stride) {
            let (u, v) = (i as usize % w, i as usize / w);
            let (origin, dir) = pose.ray(k, u as f32, v as f32);
            rays.push(Ray {
                origin,
                dir,
                target: [0.0; 3],
                target_depth: 0.0,
            });
            owner.push((r, i));
        }
    }
    let mut out = vec![RayResult::default(); rays.len()];
    backend.render_depth(&rays, &mut out)?;
    let nx = |u: usize| (u as f64 - k.cx as f64) / k.fx as f64;
    let ny = |v: usize| (v as f64 - k.cy as f64) / k.fy as f64;
    let mut pts: Vec<Vec<[f64; 3]>> = vec![Vec::new(); n as usize];
    let mut pix: Vec<Vec<[f32; 2]>> = vec![Vec::new(); n as usize];
    for ((r, i), o) in owner.iter().zip(&out) {
        if o.opacity < 0.5 || !o.depth.is_finite() {
            continue;
        }
        let z = (o.depth / o.opacity) as f64;
        if z <= 0.05 {
            continue;
        }
        let (u, v) = (*i as usize % w, *i as usize / w);
        pts[*r].push([nx(u), ny(v), z]);
        pix[*r].push([u as f32, v as f32]);
    }
    let spread_px = cfg.spread * w as f32 / 320.0;
    let mut rng = SplitMix::new(0x9e37_79b9 ^ id as u64);
    let mut planes = vec![None; n as usize];
    for r in 0..n as usize {
        stats.regions += 1;
        planes[r] =
            region_plane(&pts[r], &pix[r], cfg, spread_px, &mut rng).and_then(|(pl, inl)| {
                if cfg.cover > 0.0 {
                    let ip: Vec<[f32; 2]> = inl.iter().map(|&i| pix[r][i]).collect();
                    let hull = convex_hull(&ip);
                    if hull_cover(&label, w, r as u32 + 1, &hull) < cfg.cover {
                        return None;
                    }
                }
                Some(pl)
            });
        if planes[r].is_some() {
            stats.accepted += 1;
        }
    }
    for (i, p) in prior.iter_mut().enumerate() {
        let l = label[i];
        if l == 0 {
            continue;
        }
        let Some(pl) = planes[l as usize - 1] else {
            continue;
        };
        if let Some(d) = pl.depth(nx(i % w), ny(i / w)) {
            if d > 0.05 && d < max_depth as f64 {
                *p = d as f32;
                stats.pixels += 1;
            }
        }
    }
    Ok(prior)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A plane through three points gives their depths back; the fit recovers a plane from
    /// points on it.
    #[test]
    fn inverse_plane_through_and_fit() {
        // the plane z = 2 + 0.5 x_world... as points (x, y, z) in normalised coordinates
        let truth = InversePlane([0.1, -0.05, 0.4]);
        let pts: Vec<[f64; 3]> = [
            (-0.3, -0.2),
            (0.2, 0.1),
            (0.0, 0.3),
            (0.4, -0.3),
            (-0.1, 0.0),
        ]
        .iter()
        .map(|&(x, y)| [x, y, truth.depth(x, y).unwrap()])
        .collect();
        let p = InversePlane::through([pts[0], pts[1], pts[2]]).unwrap();
        for q in &pts {
            assert!((p.depth(q[0], q[1]).unwrap() - q[2]).abs() < 1e-9);
        }
        let f = InversePlane::fit(&pts).unwrap();
        for (a, b) in f.0.iter().zip(truth.0) {
            assert!((a - b).abs() < 1e-9, "{:?}", f.0);
        }
        // collinear points have no plane
        assert!(
            InversePlane::through([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0], [0.2, 0.0, 1.0]]).is_none()
        );
    }

    /// Two plain halves split by a sharp edge are two regions; a small blob is dropped; the
    /// distance counts to the edge, not the image border.
    #[test]
    fn regions_split_at_edges() {
        let (w, h) = (20, 10);
        let mut rgb = vec![[0.2f32; 3]; w * h];
        for y in 0..h {
            for x in 10..w {
                rgb[y * w + x] = [0.8; 3];
            }
        }
        let (label, n) = plain_regions(&rgb, w, h, 0.015, 5);
        assert_eq!(n, 2);
        assert_eq!(label[0], 1);
        assert_eq!(label[19], 2);
        assert_eq!(label[9], 0); // on the edge
        assert_eq!(label[10], 0);
        let d = distance_to_unlabelled(&label, w, h);
        assert_eq!(d[8], 1);
        assert_eq!(d[0], 9);
        // a 2-pixel-wide blob below min_px is no region
        let mut rgb2 = vec![[0.5f32; 3]; w * h];
        for y in 0..h {
            rgb2[y * w + 10] = [0.9; 3];
            rgb2[y * w + 12] = [0.1; 3];
        }
        let (label2, n2) = plain_regions(&rgb2, w, h, 0.015, 30);
        assert_eq!(n2, 2);
        assert!(label2[10] == 0 && label2[11] == 0 && label2[12] == 0);
    }

    /// The defaults pass the settings check; each bad setting is an error naming it.
    #[test]
    fn settings_are_checked() {
        assert!(PlaneSection::default().validate().is_ok());
        let bad: [fn(&mut PlaneSection); 8] = [
            |p| p.occluded_inliers = -0.1,
            |p| p.behind = f32::NAN,
            |p| p.step = 0.0,
            |p| p.cover = 1.5,
            |p| p.inliers = 1.5,
            |p| p.border = 0,
            |p| p.max_points = 3,
            |p| p.tol_rel = f32::NAN,
        ];
        for f in bad {
            let mut p = PlaneSection::default();
            f(&mut p);
            let e = p.validate().unwrap_err().to_string();
            assert!(e.starts_with("planes."), "{e}");
        }
    }

    /// The hull of the inliers' pixels and the share of a region inside it (`planes.cover`).
    #[test]
    fn convex_hull_and_region_cover() {
        // a square with points inside and on an edge: the hull is its four corners
        let pts = [
            [0.0, 0.0],
            [10.0, 0.0],
            [5.0, 0.0],
            [10.0, 10.0],
            [0.0, 10.0],
            [4.0, 6.0],
            [0.0, 10.0],
        ];
        let hull = convex_hull(&pts);
        assert_eq!(hull.len(), 4, "{hull:?}");
        for c in [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]] {
            assert!(hull.contains(&c));
        }
        assert_eq!(hull_row_span(&hull, 3.0), Some((0.0, 10.0)));
        assert_eq!(hull_row_span(&hull, 11.0), None);
        // A 40 x 30 region (everything but a 10 x 10 block in its lower right corner, another
        // region): the border of the block's two edges covers a small corner of it, the top
        // and bottom rows all of it.
        let (w, h) = (40usize, 30usize);
        let mut label = vec![1u32; w * h];
        for v in 20..h {
            for u in 30..w {
                label[v * w + u] = 2;
            }
        }
        let ell: Vec<[f32; 2]> = (20..h)
            .map(|v| [29.0, v as f32])
            .chain((30..w).map(|u| [u as f32, 19.0]))
            .collect();
        let c = hull_cover(&label, w, 1, &convex_hull(&ell));
        assert!(c < 0.1, "{c}");
        let rows: Vec<[f32; 2]> = (0..w)
            .flat_map(|u| [[u as f32, 0.0], [u as f32, (h - 1) as f32]])
            .collect();
        let c = hull_cover(&label, w, 1, &convex_hull(&rows));
        assert!((c - 1.0).abs() < 1e-6, "{c}");
        // the region's own count: 40 * 30 - 100 pixels, half of them in the upper half
        let top: Vec<[f32; 2]> = vec![[0.0, 0.0], [39.0, 0.0], [39.0, 14.5], [0.0, 14.5]];
        let c = hull_cover(&label, w, 1, &convex_hull(&top));
        assert!((c - 600.0 / 1100.0).abs() < 1e-6, "{c}");
    }

    /// A border on one plane is accepted with that plane; a border on two planes at
    /// different depths (an object meeting a wall) is rejected.
    #[test]
    fn region_plane_accepts_one_plane_only() {
        let cfg = PlaneSection {
            occluded_inliers: 0.0,
            ..PlaneSection::default()
        };
        let (mut pts, pix) = wall_border(0..0, 0.0);
        let mut rng = SplitMix::new(1);
        let (p, _) = region_plane(&pts, &pix, &cfg, 5.0, &mut rng).expect("one plane");
        assert!((p.depth(0.0, 0.0).unwrap() - 2.0).abs() < 1e-6);
        // the right half 60 cm closer: no plane holds 75 % of the border
        for q in pts.iter_mut().filter(|q| q[0] > 0.0) {
            q[2] -= 0.6;
        }
        assert!(region_plane(&pts, &pix, &cfg, 5.0, &mut rng).is_none());
    }

    /// A plain wall's border: 40 points of an ellipse on the plane `1 / z = 0.1 y + 0.5`
    /// (2 m at the centre), of which the arc `moved` (indices) is shifted by `dz` m.
    fn wall_border(moved: std::ops::Range<usize>, dz: f64) -> (Vec<[f64; 3]>, Vec<[f32; 2]>) {
        let truth = InversePlane([0.0, 0.1, 0.5]);
        let mut pts = Vec::new();
        let mut pix = Vec::new();
        for i in 0..40 {
            let t = i as f64 / 40.0 * std::f64::consts::TAU;
            let (u, v) = (160.0 + 60.0 * t.cos(), 120.0 + 50.0 * t.sin());
            let (x, y) = ((u - 160.0) / 200.0, (v - 120.0) / 200.0);
            let z = truth.depth(x, y).unwrap() + if moved.contains(&i) { dz } else { 0.0 };
            pts.push([x, y, z]);
            pix.push([u as f32, v as f32]);
        }
        (pts, pix)
    }

    /// With `occluded_inliers`, a border that is 45 % the outline of an object 60 cm in front
    /// of the region still gives the region's own plane (the 55 % that agree, none behind
    /// it); the same arc 60 cm behind (the region's own pixels beyond the plane: not an
    /// occluder) gives none, and so does an occluder that leaves less than half the border
    /// on the plane, or the rule switched off.
    #[test]
    fn region_plane_keeps_the_plane_behind_occluders() {
        let cfg = PlaneSection::default();
        assert_eq!(cfg.occluded_inliers, 0.5);
        let mut rng = SplitMix::new(7);
        let (pts, pix) = wall_border(0..18, -0.6);
        let (p, inl) = region_plane(&pts, &pix, &cfg, 5.0, &mut rng).expect("the wall's plane");
        assert!((p.depth(0.0, 0.0).unwrap() - 2.0).abs() < 1e-6);
        assert_eq!(inl, (18..40).collect::<Vec<_>>());
        let off = PlaneSection {
            occluded_inliers: 0.0,
            ..cfg.clone()
        };
        assert!(region_plane(&pts, &pix, &off, 5.0, &mut rng).is_none());
        let (pts, pix) = wall_border(0..18, 0.6);
        assert!(region_plane(&pts, &pix, &cfg, 5.0, &mut rng).is_none());
        let (pts, pix) = wall_border(0..22, -0.6);
        assert!(region_plane(&pts, &pix, &cfg, 5.0, &mut rng).is_none());
    }
}
