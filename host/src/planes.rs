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
    /// What the online priors (`mapper.lambda_plane`) are fitted to: `border` (the plane of
    /// the region's rendered border, as the refinement's) or `floor` (a vertical plane
    /// through the line where the region meets the floor: [`floor_wall_prior`]).
    pub online: PriorSource,
    /// What the refinement's priors (`mapper.refine_lambda_plane`) are fitted to (as `online`).
    pub refine: PriorSource,
    /// `floor`: a point lies on the floor when its height is within this of the floor's (m).
    pub floor_tol: f32,
}

/// Where a plain region's plane comes from ([`PlaneSection::online`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PriorSource {
    #[default]
    Border,
    Floor,
    /// The floor's plane where a region meets the floor, the border's elsewhere.
    Both,
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
            online: PriorSource::Border,
            refine: PriorSource::Border,
            floor_tol: 0.05,
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
/// run rebuilds the same priors with [`Self::resume`]. `small` fits them to the floor
/// (`planes.online = "floor"`, [`floor_wall_prior`]); the border's plane (`"border"`) helps
/// the plain walls the newest frames see and hurts the frames that first look through a
/// doorway (a plain far wall seen through a door gets the plane of the door's frame, a
/// membrane the next frames must carve: ARCHITECTURE.md, forty-first session), where the
/// floor line is the far room's.
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
        let st = refresh_online(mapper, &ids, &config.planes, config.model.max_depth)?;
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
            refresh_online(mapper, carrying, &config.planes, config.model.max_depth)?;
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
        let st = refresh_from(
            mapper,
            &ids,
            &config.planes,
            config.model.max_depth,
            config.planes.refine,
        )
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
        if !pos(self.floor_tol) {
            bail!("planes.floor_tol must be positive (m)");
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
    refresh_from(mapper, frames, cfg, max_depth, PriorSource::Border)
}

/// [`refresh`] for the online priors: their planes come from [`PlaneSection::online`].
pub fn refresh_online<B: Backend>(
    mapper: &mut Mapper<'_, B>,
    frames: &[u32],
    cfg: &PlaneSection,
    max_depth: f32,
) -> Result<PlaneStats>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    refresh_from(mapper, frames, cfg, max_depth, cfg.online)
}

fn refresh_from<B: Backend>(
    mapper: &mut Mapper<'_, B>,
    frames: &[u32],
    cfg: &PlaneSection,
    max_depth: f32,
    source: PriorSource,
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
    // the floor of the frames' rendered points, along the newest frame's up
    let floor = match (source, held.iter().max_by_key(|h| h.id)) {
        (PriorSource::Floor | PriorSource::Both, Some(newest)) => {
            let up = world_up(&newest.pose);
            // the local frames' (every held frame's was measured worse: ARCHITECTURE.md,
            // fifty-third session)
            let poses: Vec<Pose> = held.iter().map(|h| h.pose).collect();
            floor_height(mapper.backend_mut(), &k, &poses, up)?.map(|f| (up, f))
        }
        _ => None,
    };
    for h in held {
        let border = |b: &mut B, st: &mut PlaneStats| {
            frame_prior(b, &k, h.slot, &h.pose, h.id, cfg, max_depth, st)
        };
        let walls = |b: &mut B, st: &mut PlaneStats| {
            floor_wall_prior(b, &k, h.slot, &h.pose, h.id, cfg, max_depth, floor, st)
        };
        let prior = match source {
            PriorSource::Border => border(mapper.backend_mut(), &mut stats)?,
            PriorSource::Floor => walls(mapper.backend_mut(), &mut stats)?,
            PriorSource::Both => {
                let (mut fs, mut bs) = (PlaneStats::default(), PlaneStats::default());
                let mut p = walls(mapper.backend_mut(), &mut fs)?;
                let b = border(mapper.backend_mut(), &mut bs)?;
                for (x, y) in p.iter_mut().zip(&b) {
                    if *x == 0.0 {
                        *x = *y;
                    }
                }
                stats.frames += 1;
                stats.total += bs.total;
                stats.regions += bs.regions;
                stats.accepted += bs.accepted.max(fs.accepted);
                stats.pixels += p.iter().filter(|&&x| x != 0.0).count() as u64;
                p
            }
        };
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

/// The world's up as the newest camera sees it: its image up (`-y` of the camera frame)
/// snapped to the nearest world axis (as the default scene box's up, `config::up_axis`).
pub fn world_up(pose: &Pose) -> [f64; 3] {
    let u = pose.rotate([0.0, -1.0, 0.0]);
    let a = crate::config::up_axis(pose);
    let mut up = [0.0f64; 3];
    up[a] = if u[a] >= 0.0 { 1.0 } else { -1.0 };
    up
}

fn dot3(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn f64x3(a: [f32; 3]) -> [f64; 3] {
    a.map(|x| x as f64)
}

/// The floor's height along `up` in the map rendered at `poses` (every 8th pixel, sparser for
/// many poses): the
/// strongest 6 cm band (2 cm bins) more than 0.3 m below each camera, when it holds at least
/// 15 % of those points (`None` otherwise: no floor in view).
pub fn floor_height<B: Backend>(
    backend: &mut B,
    k: &Intrinsics,
    poses: &[Pose],
    up: [f64; 3],
) -> Result<Option<f64>>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    floor_height_with(k, poses, up, &mut |rays: &[Ray]| {
        let mut out = vec![RayResult::default(); rays.len()];
        backend.render_depth(rays, &mut out)?;
        Ok(out)
    })
}

/// A batch of rays' rendered depth (the map's, or a test's scene).
type RenderFn<'a> = dyn FnMut(&[Ray]) -> Result<Vec<RayResult>> + 'a;

fn ray_at(pose: &Pose, k: &Intrinsics, u: f32, v: f32) -> Ray {
    let (origin, dir) = pose.ray(k, u, v);
    Ray {
        origin,
        dir,
        target: [0.0; 3],
        target_depth: 0.0,
    }
}

/// The world point a ray's rendered depth puts its surface at (`None` when the ray is not
/// opaque or the depth is not usable).
fn surface_point(r: &Ray, o: &RayResult) -> Option<[f64; 3]> {
    if o.opacity < 0.5 || !o.depth.is_finite() {
        return None;
    }
    let z = (o.depth / o.opacity) as f64;
    (z > 0.05).then(|| [0, 1, 2].map(|a| r.origin[a] as f64 + z * r.dir[a] as f64))
}

/// Most rays [`floor_height`] renders (every 8th pixel of 26 frames at 320x240).
const FLOOR_RAYS: usize = 32_768;

/// [`floor_height`] with the depth rendered by `render`.
fn floor_height_with(
    k: &Intrinsics,
    poses: &[Pose],
    up: [f64; 3],
    render: &mut RenderFn<'_>,
) -> Result<Option<f64>> {
    // every 8th pixel, sparser when that would be more than FLOOR_RAYS rays
    let per = |s: u32| (k.width - 4).div_ceil(s) as usize * (k.height - 4).div_ceil(s) as usize;
    let mut stride = 8;
    while stride < k.width.min(k.height) && per(stride) * poses.len() > FLOOR_RAYS {
        stride += 1;
    }
    let mut rays = Vec::new();
    let mut cam = Vec::new();
    for p in poses {
        for v in (4..k.height).step_by(stride as usize) {
            for u in (4..k.width).step_by(stride as usize) {
                rays.push(ray_at(p, k, u as f32, v as f32));
                cam.push(dot3(up, f64x3(p.origin())));
            }
        }
    }
    let out = render(&rays)?;
    let mut hs = Vec::new();
    for ((r, o), c) in rays.iter().zip(&out).zip(&cam) {
        if let Some(x) = surface_point(r, o) {
            let hgt = dot3(up, x);
            if hgt < c - 0.3 {
                hs.push(hgt);
            }
        }
    }
    Ok(band_peak(&hs, 0.02, 0.15))
}

/// The mean of the values in the most populated band of three `bin`-wide bins, when it holds
/// at least `share` of them (and 20 values).
pub fn band_peak(hs: &[f64], bin: f64, share: f64) -> Option<f64> {
    if hs.len() < 20 {
        return None;
    }
    let lo = hs.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = hs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let nb = (((hi - lo) / bin) as usize + 1).min(100_000);
    let mut count = vec![0usize; nb];
    for &x in hs {
        count[(((x - lo) / bin) as usize).min(nb - 1)] += 1;
    }
    let mut best = (0usize, 0usize);
    for b in 0..nb {
        let c: usize = count[b.saturating_sub(1)..(b + 2).min(nb)].iter().sum();
        if c > best.1 {
            best = (b, c);
        }
    }
    if (best.1 as f64) < share * hs.len() as f64 {
        return None;
    }
    let (a, z) = (
        lo + best.0.saturating_sub(1) as f64 * bin,
        lo + (best.0 + 2) as f64 * bin,
    );
    let sel: Vec<f64> = hs.iter().copied().filter(|&x| x >= a && x < z).collect();
    Some(sel.iter().sum::<f64>() / sel.len().max(1) as f64)
}

/// A line in the floor's plane `n . p = c` (`n` a unit normal in the plane) through most of
/// `points` (within `tol`), fitted again by least squares (principal axis) to its inliers.
pub fn floor_line(
    points: &[[f64; 2]],
    tol: f64,
    trials: u32,
    rng: &mut SplitMix,
) -> Option<([f64; 2], f64, Vec<usize>)> {
    let n = points.len();
    if n < 2 {
        return None;
    }
    let inliers = |nrm: [f64; 2], c: f64| -> Vec<usize> {
        (0..n)
            .filter(|&i| (nrm[0] * points[i][0] + nrm[1] * points[i][1] - c).abs() < tol)
            .collect()
    };
    let mut best: Option<(usize, [f64; 2], f64)> = None;
    for _ in 0..trials {
        let i = rng.below(n as u32) as usize;
        let j = rng.below(n as u32) as usize;
        let (dx, dy) = (points[j][0] - points[i][0], points[j][1] - points[i][1]);
        let len = (dx * dx + dy * dy).sqrt();
        if len < 0.05 {
            continue;
        }
        let nrm = [-dy / len, dx / len];
        let c = nrm[0] * points[i][0] + nrm[1] * points[i][1];
        let k = inliers(nrm, c).len();
        if best.is_none_or(|(b, _, _)| k > b) {
            best = Some((k, nrm, c));
        }
    }
    let (_, nrm, c) = best?;
    let inl = inliers(nrm, c);
    // principal axis of the inliers
    let m = inl.len() as f64;
    let (mx, my) = inl.iter().fold((0.0, 0.0), |(a, b), &i| {
        (a + points[i][0] / m, b + points[i][1] / m)
    });
    let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
    for &i in &inl {
        let (dx, dy) = (points[i][0] - mx, points[i][1] - my);
        sxx += dx * dx;
        syy += dy * dy;
        sxy += dx * dy;
    }
    let ang = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let nrm = [-ang.sin(), ang.cos()];
    let c = nrm[0] * mx + nrm[1] * my;
    let inl = inliers(nrm, c);
    Some((nrm, c, inl))
}

/// The online prior of one frame from the floor (`floor`: up and the floor's height; none
/// gives none): a plain region whose lower edge meets the floor along a line (the rendered
/// points a few pixels below its lowest pixel in each column lie on the floor, and the rays
/// through its lower edge meet the floor on one line) gets the vertical plane through that
/// line, over the columns the line spans. A wall's base line stays where the floor's texture
/// placed it even when the wall itself, plain and new, renders where the carved space ends;
/// at a doorway the far wall meets the far room's floor, not the door's frame.
#[allow(clippy::too_many_arguments)]
fn floor_wall_prior<B: Backend>(
    backend: &mut B,
    k: &Intrinsics,
    slot: u32,
    pose: &Pose,
    id: u32,
    cfg: &PlaneSection,
    max_depth: f32,
    floor: Option<([f64; 3], f64)>,
    stats: &mut PlaneStats,
) -> Result<Vec<f32>>
where
    B::Error: std::error::Error + Send + Sync + 'static,
{
    let (w, h) = (k.width as usize, k.height as usize);
    stats.frames += 1;
    stats.total += (w * h) as u64;
    let Some(floor) = floor else {
        return Ok(vec![0.0f32; w * h]);
    };
    let rgb: Vec<[f32; 3]> = (0..w * h)
        .map(|i| unpack_rgba8(backend.slot_texel(slot, (i % w) as u32, (i / w) as u32)))
        .collect();
    floor_wall_targets(
        &rgb,
        k,
        pose,
        id,
        cfg,
        max_depth,
        floor,
        stats,
        &mut |rays: &[Ray]| {
            let mut out = vec![RayResult::default(); rays.len()];
            backend.render_depth(rays, &mut out)?;
            Ok(out)
        },
    )
}

/// A wall's vertical plane `normal . x = offset` (`normal` horizontal) and the image columns
/// its floor line spans.
#[derive(Clone, Copy, Debug)]
struct WallPlane {
    normal: [f64; 3],
    offset: f64,
    cols: (usize, usize),
}

/// The targets of [`floor_wall_prior`] for the image `rgb` seen from `pose`, with `floor` =
/// (up, the floor's height) and the map's depth rendered by `render` (counts go to `stats`,
/// except the frame's own).
#[allow(clippy::too_many_arguments)]
fn floor_wall_targets(
    rgb: &[[f32; 3]],
    k: &Intrinsics,
    pose: &Pose,
    id: u32,
    cfg: &PlaneSection,
    max_depth: f32,
    (up, fl): ([f64; 3], f64),
    stats: &mut PlaneStats,
    render: &mut RenderFn<'_>,
) -> Result<Vec<f32>> {
    // rows between a region's lowest pixel and the pixel tested for floor (past the colour step)
    const GAP: usize = 3;
    let (w, h) = (k.width as usize, k.height as usize);
    let mut prior = vec![0.0f32; w * h];
    let min_px = ((cfg.min_area * (w * h) as f32) as usize).max(16);
    let (label, n) = plain_regions(rgb, w, h, cfg.step, min_px);
    stats.regions += n;
    if n == 0 {
        return Ok(prior);
    }
    let n = n as usize;
    // lowest pixel of each region in each column
    let mut low = vec![-1i32; n * w];
    for (i, &l) in label.iter().enumerate() {
        if l != 0 {
            let c = &mut low[(l as usize - 1) * w + i % w];
            *c = (*c).max((i / w) as i32);
        }
    }
    let mut rays = Vec::new();
    let mut owner = Vec::new();
    let mut cols = vec![0usize; n];
    for r in 0..n {
        for u in 0..w {
            let v = low[r * w + u];
            if v < 0 {
                continue;
            }
            cols[r] += 1;
            let vb = v as usize + GAP;
            if vb >= h || label[vb * w + u] as usize == r + 1 {
                continue;
            }
            rays.push(ray_at(pose, k, u as f32, vb as f32));
            owner.push((r, u, v));
        }
    }
    let out = render(&rays)?;
    // the floor's axes from `up` itself (a frame rolled past 45 degrees snaps to another axis)
    let ax = (0..3).find(|&a| up[a] != 0.0).unwrap_or(1);
    let (a0, a1) = ((ax + 1) % 3, (ax + 2) % 3);
    let o = f64x3(pose.origin());
    let oh = dot3(up, o);
    let tol = cfg.floor_tol as f64;
    let mut base: Vec<Vec<[f64; 2]>> = vec![Vec::new(); n];
    let mut base_u: Vec<Vec<usize>> = vec![Vec::new(); n];
    for ((ray, res), &(r, u, v)) in rays.iter().zip(&out).zip(&owner) {
        let Some(x) = surface_point(ray, res) else {
            continue;
        };
        if (dot3(up, x) - fl).abs() >= tol {
            continue;
        }
        // where the ray through the region's lower edge meets the floor
        let d = f64x3(pose.ray(k, u as f32, v as f32 + 1.0).1);
        let den = dot3(up, d);
        if den >= -1e-6 {
            continue;
        }
        let t = (fl - oh) / den;
        if !(t > 0.05 && t < max_depth as f64) {
            continue;
        }
        let b = [0, 1, 2].map(|a| o[a] + t * d[a]);
        base[r].push([b[a0], b[a1]]);
        base_u[r].push(u);
    }
    let mut rng = SplitMix::new(0x51f1_00f1 ^ id as u64);
    let min_span = 3.0 * cfg.spread * w as f32 / 320.0;
    let mut planes: Vec<Option<WallPlane>> = vec![None; n];
    for r in 0..n {
        let m = base[r].len();
        if m < 10 {
            continue;
        }
        let Some((nrm, c, inl)) = floor_line(&base[r], tol, cfg.trials, &mut rng) else {
            continue;
        };
        if inl.len() < 10
            || (inl.len() as f32) < 0.6 * m as f32
            || (inl.len() as f32) < 0.25 * cols[r] as f32
        {
            continue;
        }
        let umin = inl.iter().map(|&i| base_u[r][i]).min().unwrap_or(0);
        let umax = inl.iter().map(|&i| base_u[r][i]).max().unwrap_or(0);
        if ((umax - umin) as f32) < min_span {
            continue;
        }
        let mut n3 = [0.0f64; 3];
        n3[a0] = nrm[0];
        n3[a1] = nrm[1];
        planes[r] = Some(WallPlane {
            normal: n3,
            offset: c,
            cols: (umin.saturating_sub(2), (umax + 2).min(w - 1)),
        });
        stats.accepted += 1;
    }
    for (i, p) in prior.iter_mut().enumerate() {
        let l = label[i];
        if l == 0 {
            continue;
        }
        let Some(WallPlane {
            normal: nv,
            offset: c,
            cols: (ulo, uhi),
        }) = planes[l as usize - 1]
        else {
            continue;
        };
        let (u, v) = (i % w, i / w);
        if u < ulo || u > uhi {
            continue;
        }
        let d = f64x3(pose.ray(k, u as f32, v as f32).1);
        let den = dot3(nv, d);
        if den.abs() < 0.05 * dot3(d, d).sqrt() {
            continue;
        }
        let t = (c - dot3(nv, o)) / den;
        if !(t > 0.05 && t < max_depth as f64) || oh + t * dot3(up, d) < fl - tol {
            continue;
        }
        *p = t as f32;
        stats.pixels += 1;
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

    /// The defaults pass the settings check; each bad setting is an error naming it; the
    /// sources read from TOML by name.
    #[test]
    fn settings_are_checked() {
        assert!(PlaneSection::default().validate().is_ok());
        let p: PlaneSection = toml::from_str("online = \"floor\"\nrefine = \"both\"").unwrap();
        assert_eq!(
            (p.online, p.refine),
            (PriorSource::Floor, PriorSource::Both)
        );
        assert!(toml::from_str::<PlaneSection>("online = \"ceiling\"").is_err());
        let bad: [fn(&mut PlaneSection); 9] = [
            |p| p.floor_tol = 0.0,
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
    /// The floor band: the densest 6 cm of heights when it holds 15 % of them, its mean.
    #[test]
    fn band_peak_finds_the_floor() {
        let mut hs: Vec<f64> = (0..60).map(|i| -1.5 + 0.0005 * (i % 7) as f64).collect();
        hs.extend((0..40).map(|i| -1.0 + 0.03 * i as f64)); // walls: spread out
        let f = band_peak(&hs, 0.02, 0.15).expect("a floor");
        // the mean of the 60 floor heights: sum of (i % 7) over 0..60 is 8 * 21 + 6 = 174
        assert!((f - (-1.5 + 0.0005 * 174.0 / 60.0)).abs() < 1e-9, "{f}");
        // spread evenly: no band holds 15 %
        let even: Vec<f64> = (0..100).map(|i| 0.05 * i as f64).collect();
        assert_eq!(band_peak(&even, 0.02, 0.15), None);
        assert_eq!(band_peak(&hs[..10], 0.02, 0.15), None);
    }

    /// A line through 30 points (2 cm of noise) among 10 outliers: its normal and offset.
    #[test]
    fn floor_line_ignores_outliers() {
        // the line 0.6 x + 0.8 y = 2
        let mut pts: Vec<[f64; 2]> = (0..30)
            .map(|i| {
                let s = -1.0 + 0.1 * i as f64;
                let e = 0.02 * ((i % 3) as f64 - 1.0);
                [0.6 * (2.0 + e) - 0.8 * s, 0.8 * (2.0 + e) + 0.6 * s]
            })
            .collect();
        pts.extend((0..10).map(|i| [0.3 * i as f64, 0.5]));
        let mut rng = SplitMix::new(3);
        let (n, c, inl) = floor_line(&pts, 0.05, 100, &mut rng).expect("a line");
        let (n, c) = if c < 0.0 {
            ([-n[0], -n[1]], -c)
        } else {
            (n, c)
        };
        assert!(
            (n[0] - 0.6).abs() < 1e-3 && (n[1] - 0.8).abs() < 1e-3,
            "{n:?}"
        );
        assert!((c - 2.0).abs() < 1e-3, "{c}");
        assert_eq!(
            inl.len(),
            30 + pts[30..]
                .iter()
                .filter(|p| (0.6 * p[0] + 0.8 * p[1] - 2.0).abs() < 0.05)
                .count()
        );
    }

    /// A camera 1.5 m above a textured floor looks along a plain side wall 2 m to its right
    /// (world up -y, the camera's image up). The map renders the floor where it is and the
    /// wall at 60 % of its depth (a first look at the edge of the carved space): the wall's
    /// pixels get the true wall's depth from where it meets the floor, the floor's none. A
    /// floor height 30 cm off finds no contact and gives no prior.
    #[test]
    fn floor_walls_place_a_plain_wall_on_its_base_line() {
        let k = Intrinsics {
            width: 160,
            height: 120,
            fx: 114.25,
            fy: 114.25,
            cx: 79.5,
            cy: 59.5,
        };
        let pose = Pose::IDENTITY;
        let up = world_up(&pose);
        assert_eq!(up, [0.0, -1.0, 0.0]);
        // what each ray hits first: (depth, is the wall)
        let hit = |d: [f32; 3]| -> (f64, bool) {
            let (x, y) = (d[0] as f64, d[1] as f64);
            let mut best = (8.0, false); // a far wall
            if y > 1e-6 && 1.5 / y < best.0 {
                best = (1.5 / y, false);
            }
            if x > 1e-6 && 2.0 / x < best.0 {
                best = (2.0 / x, true);
            }
            best
        };
        let (w, h) = (k.width as usize, k.height as usize);
        let mut rng = SplitMix::new(11);
        let rgb: Vec<[f32; 3]> = (0..w * h)
            .map(|i| {
                let (_, d) = pose.ray(&k, (i % w) as f32, (i / w) as f32);
                if hit(d).1 {
                    [0.2, 0.5, 0.5]
                } else {
                    let g = 0.2 + 0.6 * (rng.below(1000) as f32 / 1000.0);
                    [g, g, g]
                }
            })
            .collect();
        let mut render = |rays: &[Ray]| -> Result<Vec<RayResult>> {
            Ok(rays
                .iter()
                .map(|r| {
                    let (t, wall) = hit(r.dir);
                    RayResult {
                        depth: (if wall { 0.6 * t } else { t }) as f32,
                        opacity: 1.0,
                        ..RayResult::default()
                    }
                })
                .collect())
        };
        let cfg = PlaneSection::default();
        // the floor as the map renders it
        let fl = floor_height_with(&k, &[pose], up, &mut render)
            .unwrap()
            .expect("the floor");
        assert!((fl + 1.5).abs() < 1e-3, "{fl}");
        let mut st = PlaneStats::default();
        let prior = floor_wall_targets(
            &rgb,
            &k,
            &pose,
            0,
            &cfg,
            6.0,
            (up, fl),
            &mut st,
            &mut render,
        )
        .unwrap();
        let (mut wall, mut got, mut worst) = (0, 0, 0.0f64);
        for (i, &p) in prior.iter().enumerate() {
            let (_, d) = pose.ray(&k, (i % w) as f32, (i / w) as f32);
            let (t, is_wall) = hit(d);
            if !is_wall {
                assert_eq!(p, 0.0, "pixel {i} is not the wall");
                continue;
            }
            wall += 1;
            if p > 0.0 {
                got += 1;
                worst = worst.max((p as f64 - t).abs() / t);
            }
        }
        assert!(st.accepted >= 1, "{st:?}");
        assert!(
            got as f64 > 0.8 * wall as f64,
            "{got} of {wall} wall pixels"
        );
        assert!(worst < 0.03, "worst relative error {worst}");
        let mut st = PlaneStats::default();
        let off = floor_wall_targets(
            &rgb,
            &k,
            &pose,
            0,
            &cfg,
            6.0,
            (up, fl + 0.3),
            &mut st,
            &mut render,
        )
        .unwrap();
        assert!(off.iter().all(|&p| p == 0.0));
        assert_eq!(st.accepted, 0);
    }
}
