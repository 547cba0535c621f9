//! A default scene box that grows with the walk (issue #11).
//!
//! A robot knows only its first pose when it starts, so the default box is placed around the
//! first camera (`scene.default_horizontal`, 24 m). A walk that goes farther than half of it
//! would leave the box, and whatever lies beyond could not be mapped. With `scene.grow` (on by
//! default, for the default box only), before a frame is pushed its camera centre is checked:
//! every horizontal face of the box closer to it than `scene.grow_margin` (0: the rays' reach,
//! 1.25 `model.max_depth`) moves out by `scene.grow_step`, the bottom or top face closer than
//! `scene.grow_margin_up` (1 m: a ramp, stairs, a drone) by `scene.grow_step_up`, and the map
//! is resampled onto the
//! larger box ([`regrid`]): each grid factor (plane or line) of every level is interpolated
//! at the new vertices inside the old box (where the vertices coincide, which they do along
//! axes that did not grow, the values are copied exactly), and initialised as a fresh map is
//! (the same seeded normal draws, Adam moments 0) outside it. The decoders, beta and the
//! Adam step are kept. Only the pose of the frame being pushed is read, so mapping stays
//! online.

use anyhow::{bail, Context};
use himap_core::field::grid::{GridKind, GridLayout};
use himap_core::field::model::{Group, ModelLayout};
use himap_core::Aabb;

use crate::backend::ModelData;
use crate::config::Config;
use crate::select::MapBackend;
use himap_core::camera::Pose;
use himap_core::mapper::Mapper;

/// What [`grow_before_push`] did.
#[derive(Clone, Debug, PartialEq)]
pub enum Growth {
    /// The camera keeps the margin: nothing changed.
    Same,
    /// The box grew (the backend holds the resampled map).
    Grown {
        aabb: Aabb,
        parameters: usize,
        /// Parameters, Adam moments and the CPU backend's gradient buffers.
        bytes: u64,
    },
    /// The box would have to grow but cannot (the reason, for the user); it stays as it is.
    Refused(String),
}

/// `scene.grow_margin`, or (0) the horizontal reach of the camera's rays: `model.max_depth`
/// is a z-depth, and a ray 37 degrees off the optical axis (the corner of a 90-degree
/// diagonal field of view) reaches 1.25 times as far.
pub fn grow_margin(cfg: &Config) -> f32 {
    if cfg.scene.grow_margin > 0.0 {
        cfg.scene.grow_margin
    } else {
        1.25 * cfg.model.max_depth
    }
}

/// The horizontal axes of the default box around `first` (all but [`crate::config::up_axis`]).
pub fn horizontal_axes(first: &Pose) -> [usize; 2] {
    let up = crate::config::up_axis(first);
    let mut axes = (0..3).filter(|&a| a != up);
    [axes.next().unwrap_or(0), axes.next().unwrap_or(2)]
}

/// Grows the map of `mapper` (over `aabb`, the default box of `cfg`) before the frame at
/// `pose` is pushed, when the camera comes closer than `scene.grow_margin` to a face across
/// `axes` ([`horizontal_axes`] of the first pose): the step `himap map` takes before every
/// frame, for a caller that pushes frames itself. Whether the box may grow at all
/// (`scene.grow`, a default box) is the caller's decision.
pub fn grow_before_push<B: MapBackend>(
    cfg: &Config,
    mapper: &mut Mapper<'_, B>,
    aabb: &Aabb,
    axes: &[usize; 2],
    pose: &Pose,
) -> anyhow::Result<Growth> {
    let (margin, up) = (grow_margin(cfg), cfg.scene.grow_margin_up);
    let Some(b) = grown_default_box(cfg, aabb, axes, pose.origin()) else {
        return Ok(Growth::Same);
    };
    let threads = mapper.backend().threads();
    let (parameters, state, grads) = crate::mapper_cli::map_bytes(cfg, b, threads)?;
    let e = b.extent();
    if (state + grads) as f64 / 1e6 > cfg.scene.memory_budget_mb {
        return Ok(Growth::Refused(format!(
            "the camera comes within the growth margin of the scene box's edge \
             (scene.grow_margin {margin:.1} m, scene.grow_margin_up {up:.1} m), and the grown box \
             ({:.1} x {:.1} x {:.1} m) would need {:.0} MB, over scene.memory_budget_mb = {:.0}",
            e[0],
            e[1],
            e[2],
            (state + grads) as f64 / 1e6,
            cfg.scene.memory_budget_mb
        )));
    }
    let data = mapper.backend_mut().export()?;
    let grown = regrid(&data, layout_over(&data.layout, b)?, cfg.seed as u32)?;
    drop(data);
    if !mapper.backend_mut().regrow(grown)? {
        return Ok(Growth::Refused(format!(
            "the camera comes within the growth margin of the scene box's edge \
             (scene.grow_margin {margin:.1} m, scene.grow_margin_up {up:.1} m), and this backend \
             cannot grow its map: give a box that holds the path (scene.min, scene.max) or map \
             on the CPU"
        )));
    }
    Ok(Growth::Grown {
        aabb: b,
        parameters,
        bytes: state + grads,
    })
}

/// The default box `aabb` grown for a camera at `c` ([`grown_box`]): across the horizontal
/// `axes` with `scene.grow_margin` ([`grow_margin`]) and `scene.grow_step`, then along the
/// remaining axis ("up") with `scene.grow_margin_up` and `scene.grow_step_up` (not at all when
/// that margin is 0). `None` when no face moves.
pub fn grown_default_box(
    cfg: &Config,
    aabb: &Aabb,
    axes: &[usize; 2],
    c: [f32; 3],
) -> Option<Aabb> {
    let s = &cfg.scene;
    let across = grown_box(aabb, c, axes, grow_margin(cfg), s.grow_step);
    let base = across.unwrap_or(*aabb);
    let up = 3usize.saturating_sub(axes[0] + axes[1]).min(2);
    let along = (s.grow_margin_up > 0.0 && up != axes[0] && up != axes[1])
        .then(|| grown_box(&base, c, &[up], s.grow_margin_up, s.grow_step_up))
        .flatten();
    along.or(across)
}

/// The box grown so that the camera centre `c` keeps `margin` from every face across the
/// `axes`: each closer face moves out by `step` (as many times as needed). `None` when no
/// face moves.
pub fn grown_box(aabb: &Aabb, c: [f32; 3], axes: &[usize], margin: f32, step: f32) -> Option<Aabb> {
    if !(step > 0.0 && margin >= 0.0) || c.iter().any(|x| !x.is_finite()) {
        return None;
    }
    let mut b = *aabb;
    for &a in axes {
        while c[a] - b.min[a] < margin {
            b.min[a] -= step;
        }
        while b.max[a] - c[a] < margin {
            b.max[a] += step;
        }
    }
    (b != *aabb).then_some(b)
}

/// Continuous index along one axis of the old grid of the new grid's vertex `i`, in f64; a
/// value within 1e-6 of an integer is that integer (a vertex that did not move is copied
/// bit for bit); up to one old cell outside the old grid the index clamps to its border.
/// `None` farther out.
fn old_index(i: usize, new: (f32, f32, u32), old: (f32, f32, u32)) -> Option<(usize, f64)> {
    let (nmin, next, nres) = new;
    let (omin, oext, ores) = old;
    let x = nmin as f64 + i as f64 * (next as f64 / (nres - 1) as f64);
    let mut q = (x - omin as f64) * ((ores - 1) as f64 / oext as f64);
    if (q - q.round()).abs() < 1e-6 {
        q = q.round();
    }
    let last = (ores - 1) as f64;
    // within one old cell outside the old box: the boundary's values, so that the new cells
    // that straddle the old faces continue the map instead of mixing in fresh values
    if !(-1.0..=last + 1.0).contains(&q) {
        return None;
    }
    let q = q.clamp(0.0, last);
    let i0 = (q.floor() as usize).min(ores as usize - 2);
    Some((i0, q - i0 as f64))
}

/// Per axis of a factor (1 or 2 axes): the new vertices' old indices.
fn axis_map(new: &GridLayout, old: &GridLayout, l: usize, a: usize) -> Vec<Option<(usize, f64)>> {
    let (ne, oe) = (new.aabb.extent(), old.aabb.extent());
    let (nr, or) = (new.level[l].res[a], old.level[l].res[a]);
    (0..nr as usize)
        .map(|i| {
            old_index(
                i,
                (new.aabb.min[a], ne[a], nr),
                (old.aabb.min[a], oe[a], or),
            )
        })
        .collect()
}

/// Resamples one grid group's tensor (`src` over `old`) into `dst` (over `new`), factor by
/// factor; entries outside the old box are left as they are in `dst`.
fn regrid_tensor(old: &GridLayout, new: &GridLayout, src: &[f32], dst: &mut [f32]) {
    let ch = new.channels as usize;
    for l in 0..new.levels as usize {
        let maps: [Vec<Option<(usize, f64)>>; 3] =
            core::array::from_fn(|a| axis_map(new, old, l, a));
        let (ol, nl) = (&old.level[l], &new.level[l]);
        // planes xy, xz, yz: (first axis, second axis); row-major over (second, first)
        for (p, (a, b)) in [(0, 1), (0, 2), (1, 2)].into_iter().enumerate() {
            let (ora, nra) = (ol.res[a] as usize, nl.res[a] as usize);
            for (jb, mb) in maps[b].iter().enumerate() {
                let Some((ib, fb)) = *mb else { continue };
                for (ja, ma) in maps[a].iter().enumerate() {
                    let Some((ia, fa)) = *ma else { continue };
                    let at = |i: usize, j: usize| ol.plane_offsets[p] as usize + (j * ora + i) * ch;
                    let (c00, c10) = (at(ia, ib), at(ia + 1, ib));
                    let (c01, c11) = (at(ia, ib + 1), at(ia + 1, ib + 1));
                    let d = nl.plane_offsets[p] as usize + (jb * nra + ja) * ch;
                    for c in 0..ch {
                        let v = |o: usize| src[o + c] as f64;
                        let lo = v(c00) + fa * (v(c10) - v(c00));
                        let hi = if fb > 0.0 {
                            v(c01) + fa * (v(c11) - v(c01))
                        } else {
                            lo
                        };
                        dst[d + c] = if fa == 0.0 && fb == 0.0 {
                            src[c00 + c]
                        } else {
                            (lo + fb * (hi - lo)) as f32
                        };
                    }
                }
            }
        }
        for (a, map) in maps.iter().enumerate() {
            for (j, m) in map.iter().enumerate() {
                let Some((i, f)) = *m else { continue };
                let s = ol.line_offsets[a] as usize + i * ch;
                let d = nl.line_offsets[a] as usize + j * ch;
                for c in 0..ch {
                    dst[d + c] = if f == 0.0 {
                        src[s + c]
                    } else {
                        let (x0, x1) = (src[s + c] as f64, src[s + ch + c] as f64);
                        (x0 + f * (x1 - x0)) as f32
                    };
                }
            }
        }
    }
}

/// `data` (a map over a box) resampled onto `layout`, the same model over a box that
/// contains it (see the module documentation). `seed` is the run's: the new region's
/// parameters are the ones a fresh map over `layout` would start with.
pub fn regrid(data: &ModelData, layout: ModelLayout, seed: u32) -> anyhow::Result<ModelData> {
    let old = &data.layout;
    let (ob, nb) = (old.config.aabb, layout.config.aabb);
    if !(0..3).all(|a| nb.min[a] <= ob.min[a] && nb.max[a] >= ob.max[a]) {
        bail!("the grown scene box must contain the old one");
    }
    let mut same = layout.config;
    same.aabb = ob;
    if same != old.config {
        bail!("only the scene box may change when the map grows");
    }
    for g in [&layout.geometry_grid, &layout.appearance_grid] {
        if g.kind != GridKind::Factorized {
            bail!("only factorized grids can grow (model.grid_kind = \"factorized\")");
        }
    }
    let mut out = ModelData::new(layout, seed).map_err(|e| anyhow::anyhow!("model init: {e}"))?;
    for (i, g) in Group::ALL.into_iter().enumerate() {
        let grids = match g {
            Group::GeometryGrid => Some((&old.geometry_grid, &layout.geometry_grid)),
            Group::AppearanceGrid => Some((&old.appearance_grid, &layout.appearance_grid)),
            _ => None,
        };
        match grids {
            Some((o, n)) => {
                // `out`'s moments start at zero: the new region keeps them so
                regrid_tensor(o, n, &data.params[i], &mut out.params[i]);
                regrid_tensor(o, n, &data.m[i], &mut out.m[i]);
                regrid_tensor(o, n, &data.v[i], &mut out.v[i]);
            }
            None => {
                out.params[i].clone_from(&data.params[i]);
                out.m[i].clone_from(&data.m[i]);
                out.v[i].clone_from(&data.v[i]);
            }
        }
    }
    out.t = data.t;
    Ok(out)
}

/// The layout of `old`'s model over `aabb`.
pub fn layout_over(old: &ModelLayout, aabb: Aabb) -> anyhow::Result<ModelLayout> {
    let mut mc = old.config;
    mc.aabb = aabb;
    ModelLayout::new(&mc)
        .map_err(|e| anyhow::anyhow!("model: {e}"))
        .context("the grown scene box")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use himap_core::field::grid::{grid_forward, MAX_GRID_FEATURES};

    fn small_over(aabb: Aabb) -> ModelData {
        let mut c = Config::small();
        c.model.geometry.cell_sizes = vec![0.64, 0.32, 0.16];
        c.model.appearance.cell_sizes = vec![0.24, 0.08];
        let mc = c.model_config(aabb).unwrap();
        ModelData::new(ModelLayout::new(&mc).unwrap(), 7).unwrap()
    }

    #[test]
    fn faces_move_out_until_the_camera_keeps_the_margin() {
        let b = Aabb::new([-12.0, -2.0, -12.0], [12.0, 3.0, 12.0]);
        assert_eq!(grown_box(&b, [0.0, 0.0, 0.0], &[0, 2], 6.0, 6.0), None);
        let g = grown_box(&b, [7.0, 0.0, -10.0], &[0, 2], 6.0, 6.0).unwrap();
        assert_eq!(g.min, [-12.0, -2.0, -18.0]);
        assert_eq!(g.max, [18.0, 3.0, 12.0]);
        // several steps at once, and the up axis (1) never moves
        let g = grown_box(&b, [20.0, 9.0, 0.0], &[0, 2], 6.0, 5.0).unwrap();
        assert_eq!((g.min, g.max), ([-12.0, -2.0, -12.0], [27.0, 3.0, 12.0]));
        assert_eq!(grown_box(&b, [f32::NAN, 0.0, 0.0], &[0, 2], 6.0, 6.0), None);
        assert_eq!(grown_box(&b, [11.0, 0.0, 0.0], &[0, 2], 6.0, 0.0), None);
    }

    /// The default box grows along "up" only when the camera comes within
    /// `scene.grow_margin_up` of the bottom or top face (by `scene.grow_step_up`), across the
    /// horizontal axes as before, and not along "up" when that margin is 0.
    #[test]
    fn the_default_box_grows_up_and_down_with_the_camera() {
        let mut cfg = Config::preset("small").unwrap();
        cfg.scene.grow_margin = 6.0;
        let b = Aabb::new([-12.0, -2.0, -12.0], [12.0, 3.0, 12.0]);
        let axes = [0, 2];
        // a handheld camera's height changes (ICL: -0.12 .. +0.75 m) grow nothing
        assert_eq!(grown_default_box(&cfg, &b, &axes, [0.0, 0.75, 0.0]), None);
        assert_eq!(grown_default_box(&cfg, &b, &axes, [0.0, -0.9, 0.0]), None);
        // up a flight of stairs: the top moves by whole 2 m steps until 1 m is kept
        let g = grown_default_box(&cfg, &b, &axes, [0.0, 2.5, 0.0]).unwrap();
        assert_eq!((g.min, g.max), ([-12.0, -2.0, -12.0], [12.0, 5.0, 12.0]));
        let g = grown_default_box(&cfg, &b, &axes, [0.0, 4.5, 0.0]).unwrap();
        assert_eq!(g.max[1], 7.0);
        // down and sideways at once
        let g = grown_default_box(&cfg, &b, &axes, [7.0, -1.5, 0.0]).unwrap();
        assert_eq!((g.min, g.max), ([-12.0, -4.0, -12.0], [18.0, 3.0, 12.0]));
        // another up axis (z up: the horizontal axes are x and y)
        let bz = Aabb::new([-12.0, -12.0, -2.0], [12.0, 12.0, 3.0]);
        let g = grown_default_box(&cfg, &bz, &[0, 1], [0.0, 0.0, 2.5]).unwrap();
        assert_eq!(g.max, [12.0, 12.0, 5.0]);
        // margin 0: never along up
        cfg.scene.grow_margin_up = 0.0;
        assert_eq!(grown_default_box(&cfg, &b, &axes, [0.0, 2.9, 0.0]), None);
        let g = grown_default_box(&cfg, &b, &axes, [7.0, 2.9, 0.0]).unwrap();
        assert_eq!(g.max, [18.0, 3.0, 12.0]);
    }

    #[test]
    fn the_grown_map_keeps_the_field_inside_the_old_box() {
        let old_box = Aabb::new([-3.0, -1.0, -2.0], [3.0, 2.0, 2.0]);
        let mut data = small_over(old_box);
        let a_grid = Group::AppearanceGrid as usize;
        // moments to carry
        for (i, m) in data.m.0.iter_mut().enumerate() {
            m.iter_mut()
                .enumerate()
                .for_each(|(j, x)| *x = (i + j % 7) as f32);
        }
        // every factor a linear function of its vertex's world position, which bilinear
        // resampling keeps: the features inside the old box must stay
        let grid = data.layout.appearance_grid;
        let ch = grid.channels as usize;
        let world = |l: usize, a: usize, i: usize| {
            let e = grid.aabb.extent()[a];
            grid.aabb.min[a] + i as f32 * e / (grid.level[l].res[a] - 1) as f32
        };
        for l in 0..grid.levels as usize {
            let lv = grid.level[l];
            for (p, (a, b)) in [(0, 1), (0, 2), (1, 2)].into_iter().enumerate() {
                for j in 0..lv.res[b] as usize {
                    for i in 0..lv.res[a] as usize {
                        let o = lv.plane_offsets[p] as usize + (j * lv.res[a] as usize + i) * ch;
                        for c in 0..ch {
                            let v = 1.0 + 0.1 * world(l, a, i)
                                - 0.05 * (c as f32 + 1.0) * world(l, b, j);
                            data.params[a_grid][o + c] = v;
                        }
                    }
                }
            }
            for a in 0..3 {
                for i in 0..lv.res[a] as usize {
                    let o = lv.line_offsets[a] as usize + i * ch;
                    for c in 0..ch {
                        data.params[a_grid][o + c] = 0.5 + 0.03 * (c as f32) * world(l, a, i);
                    }
                }
            }
        }
        let new_box = Aabb::new([-3.0, -1.0, -8.0], [9.0, 2.0, 2.0]);
        let grown = regrid(&data, layout_over(&data.layout, new_box).unwrap(), 7).unwrap();
        assert_eq!(grown.layout.config.aabb, new_box);
        assert_eq!(grown.t, data.t);
        let (g, a) = (Group::GeometryMlp as usize, a_grid);
        assert_eq!(grown.params[g], data.params[g]);
        assert_eq!(grown.m[g], data.m[g]);
        let feature = |d: &ModelData, p: [f32; 3]| {
            let mut out = [0.0; MAX_GRID_FEATURES];
            grid_forward(&d.layout.appearance_grid, &d.params[a][..], p, &mut out);
            out
        };
        let mut worst = 0.0f32;
        for i in 0..300u32 {
            let t = |k: u32| ((i * 37 + k * 101) % 997) as f32 / 997.0;
            // away from the faces that moved (x max, z min), where the new cells straddle them
            let p = [-2.9 + 5.4 * t(1), -0.9 + 2.8 * t(2), -1.6 + 3.5 * t(3)];
            let (x, y) = (feature(&data, p), feature(&grown, p));
            for k in 0..grid.levels as usize * ch {
                // (features near 0 are differences of terms near 1: rounding is absolute)
                worst = worst.max((x[k] - y[k]).abs() / (1.0 + x[k].abs()));
            }
        }
        assert!(
            worst < 1e-5,
            "change of a feature inside the old box: {worst}"
        );
        // the moments are resampled the same way
        assert!(grown.m[a].iter().any(|&x| x != 0.0));
        // the y axis did not grow: its line is copied bit for bit at level 0
        let (ol, nl) = (
            &data.layout.appearance_grid.level[0],
            &grown.layout.appearance_grid.level[0],
        );
        assert_eq!(ol.res[1], nl.res[1]);
        let ch = data.layout.appearance_grid.channels as usize;
        let n = ol.res[1] as usize * ch;
        assert_eq!(
            data.params[a][ol.line_offsets[1] as usize..][..n],
            grown.params[a][nl.line_offsets[1] as usize..][..n]
        );
        // outside the old box: a fresh map's values, moments 0
        let fresh = ModelData::new(grown.layout, 7).unwrap();
        let last = nl.line_offsets[0] as usize + (nl.res[0] as usize - 1) * ch;
        assert_eq!(
            grown.params[a][last..last + ch],
            fresh.params[a][last..last + ch]
        );
        assert!(grown.m[a][last..last + ch].iter().all(|&x| x == 0.0));
        // a box that does not contain the old one is refused
        let smaller = Aabb::new([-2.0, -1.0, -2.0], [3.0, 2.0, 2.0]);
        assert!(regrid(&data, layout_over(&data.layout, smaller).unwrap(), 7).is_err());
    }
}
