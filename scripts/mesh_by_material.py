#!/usr/bin/env python3
"""Mesh accuracy and completion of a synthetic house or hall, split by the material of the
nearest solid (plain, checker, noise, stripes): which surfaces a map gets wrong.

Dev-only (numpy, scipy, plyfile; not run by CI). Samples 100 000 points on each mesh (area
weighted), takes nearest-neighbour distances both ways as `himap eval` does, and assigns each
point to the solid of `house.json` whose surface is closest.

Usage: scripts/mesh_by_material.py MESH.ply GT_MESH.ply HOUSE.json
  e.g. scripts/mesh_by_material.py out/house/mesh.ply out/house-data/gt_mesh.ply \
       out/house-data/house.json
"""
import sys, json, numpy as np
from plyfile import PlyData
from scipy.spatial import cKDTree
def load(p):
    d = PlyData.read(p)
    v = np.stack([d['vertex'][k] for k in 'xyz'], 1).astype(np.float64)
    f = np.stack(d['face']['vertex_indices'])
    return v, f
def sample(v, f, n, rng):
    a, b, c = v[f[:,0]], v[f[:,1]], v[f[:,2]]
    area = 0.5*np.linalg.norm(np.cross(b-a, c-a), axis=1)
    idx = rng.choice(len(f), n, p=area/area.sum())
    r1, r2 = rng.random(n), rng.random(n); s = np.sqrt(r1)
    return (1-s)[:,None]*a[idx] + (s*(1-r2))[:,None]*b[idx] + (s*r2)[:,None]*c[idx]
rng = np.random.default_rng(0)
rv, rf = load(sys.argv[1]); gv, gf = load(sys.argv[2])
H = json.load(open(sys.argv[3]))['house']
solids = H['solids']
lo = np.array([s['min'] for s in solids]); hi = np.array([s['max'] for s in solids])
kinds = [s['material']['kind'] for s in solids]
def box_dist(P):
    # distance from points to each box surface (outside: distance to box; inside: distance to nearest face)
    d_out = np.linalg.norm(np.maximum(0, np.maximum(lo[None]-P[:,None], P[:,None]-hi[None])), axis=2)
    inside = np.all((P[:,None] >= lo[None]) & (P[:,None] <= hi[None]), axis=2)
    d_in = np.min(np.minimum(P[:,None]-lo[None], hi[None]-P[:,None]), axis=2)
    return np.where(inside, d_in, d_out)
R = sample(rv, rf, 100000, rng); G = sample(gv, gf, 100000, rng)
da, _ = cKDTree(G).query(R); dc, _ = cKDTree(R).query(G)
def which(P):
    out = []
    for i in range(0, len(P), 5000):
        out.append(np.argmin(box_dist(P[i:i+5000]), axis=1))
    return np.concatenate(out)
wr, wg = which(R), which(G)
print('solids:', len(solids), 'kinds:', sorted(set(kinds)))
for name, d, w in [('accuracy (reconstruction points, by the nearest solid)', da, wr), ('completion (ground-truth points)', dc, wg)]:
    print(name)
    for k in sorted(set(kinds)):
        m = np.array([kinds[j] == k for j in w])
        if m.sum() == 0: continue
        print('  %-10s %5.1f %% of points  mean %.2f cm  median %.2f cm  >5 cm %.1f %%' % (k, 100*m.mean(), 100*d[m].mean(), 100*np.median(d[m]), 100*(d[m] > 0.05).mean()))
