#!/usr/bin/env python3
"""What a synthetic house's completion is made of: the floor any observed-only mesh has, and
where a mesh's completion goes (floor, ceiling, other horizontal, vertical surfaces).

Dev-only (numpy, scipy, pillow, plyfile; not run by CI; reads ground truth).
- The "perfect observed reconstruction": the exact depth of every 2nd frame back-projected
  (1 cm voxels), scored against the whole `gt_mesh.ply` as `himap eval` scores a mesh
  (200 000 area-weighted samples, completion = mean distance from them, ratio = share within
  5 cm). No mesh.ply that keeps only what the frames saw can do better than this.
- With a MESH: its completion split by the ground truth's surface class, and the ceiling's
  holes (samples farther than 20 cm from the mesh): whether MESH_FULL (mesh_full.ply, not
  culled) has a surface there, and in how many frames the exact depth sees them (a pixel back-projected
  within 5 cm), at which image row and depth.

Usage: scripts/completion_floor.py DATASET [MESH.ply [MESH_FULL.ply]]
  e.g. scripts/completion_floor.py out/whole/house-data out/whole/house/mesh.ply \
       out/whole/house/mesh_full.ply
"""
import sys, json, numpy as np
from PIL import Image
from plyfile import PlyData
from scipy.spatial import cKDTree


def load(p):
    d = PlyData.read(p)
    v = np.stack([d['vertex'][k] for k in 'xyz'], 1).astype(np.float64)
    return v, np.stack(d['face']['vertex_indices'])


def sample(v, f, n, seed):
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    nrm = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(nrm, axis=1)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True) + 1e-12
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(f), n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    pts = (1 - s)[:, None] * a[idx] + (s * (1 - r2))[:, None] * b[idx] + (s * r2)[:, None] * c[idx]
    return pts, nrm[idx]


ds = sys.argv[1]
cam = json.load(open(ds + "/cam_params.json"))["camera"]
fx, fy, cx, cy, sc = cam["fx"], cam["fy"], cam["cx"], cam["cy"], cam["scale"]
W, H = cam["w"], cam["h"]
poses = np.loadtxt(ds + "/traj.txt").reshape(-1, 4, 4)
depths = [np.asarray(Image.open(f"{ds}/results/depth{i:06d}.png"), dtype=np.float64) / sc
          for i in range(len(poses))]
gv, gf = load(ds + "/gt_mesh.ply")
G, GN = sample(gv, gf, 200_000, 1)

pts = []
for i in range(0, len(poses), 2):
    d = depths[i]
    v, u = np.nonzero(d > 0)
    z = d[v, u]
    c = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z, np.ones_like(z)], 0)
    pts.append((poses[i] @ c)[:3].T)
obs = np.unique(np.round(np.concatenate(pts) / 0.01).astype(np.int64), axis=0) * 0.01
d, _ = cKDTree(obs).query(G)
print(f"perfect observed reconstruction: completion {100 * d.mean():.2f} cm, "
      f"ratio {100 * (d < 0.05).mean():.1f} %")
if len(sys.argv) < 3:
    sys.exit(0)

mv, mf = load(sys.argv[2])
M, _ = sample(mv, mf, 400_000, 2)
d, _ = cKDTree(M).query(G)
print(f"{sys.argv[2]}: completion {100 * d.mean():.2f} cm, ratio {100 * (d < 0.05).mean():.1f} %")
z = G[:, 2]
top = gv[:, 2].max()
horiz = np.abs(GN[:, 2]) > 0.9
classes = {
    "floor": horiz & (z < 0.05),
    "ceiling": horiz & (z > top - 0.5),
    "other horizontal": horiz & (z >= 0.05) & (z <= top - 0.5),
    "vertical": ~horiz,
}
for name, m in classes.items():
    if m.any():
        print(f"  {name:17s} {100 * m.mean():5.1f} % of the ground truth, mean distance "
              f"{100 * d[m].mean():6.2f} cm, contributes {100 * d[m].sum() / len(d):5.2f} cm, "
              f"beyond 20 cm {100 * (d[m] > 0.2).mean():5.1f} %")
hole = G[classes["ceiling"] & (d > 0.2)]
if len(hole) == 0:
    sys.exit(0)
if len(sys.argv) > 3:
    fv, ff = load(sys.argv[3])
    F, _ = sample(fv, ff, 800_000, 3)
    df, _ = cKDTree(F).query(hole)
    print(f"  ceiling holes ({len(hole)} samples): {sys.argv[3]} within 5 / 10 cm of "
          f"{100 * (df < 0.05).mean():.1f} / {100 * (df < 0.1).mean():.1f} %")
count = np.zeros(len(hole), int)
rows, dist = [], []
for i, p in enumerate(poses):
    d = depths[i]
    v, u = np.nonzero(d > 0)
    z = d[v, u]
    c = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z, np.ones_like(z)], 0)
    near, j = cKDTree((p @ c)[:3].T).query(hole, distance_upper_bound=0.05)
    vis = np.isfinite(near)
    count += vis
    rows.append(v[j[vis]])
    dist.append(z[j[vis]])
rows, dist = np.concatenate(rows), np.concatenate(dist)
print(f"  seen (a pixel's exact depth within 5 cm) by no frame {100 * (count == 0).mean():.1f} %, by 1-3 "
      f"{100 * ((count >= 1) & (count <= 3)).mean():.1f} %, by 4 or more {100 * (count >= 4).mean():.1f} %")
if len(rows):
    print(f"  where seen: image row median {np.median(rows):.0f} of {H}, depth median "
          f"{np.median(dist):.2f} m (10-90 %: {np.percentile(dist, 10):.2f}-{np.percentile(dist, 90):.2f} m)")
