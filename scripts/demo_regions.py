#!/usr/bin/env python3
"""Per-region mesh metrics of a synthetic room (dev-only diagnosis; needs numpy and scipy).

`himap demo` / `himap map` report one Accuracy / Completion / ratio for the whole room. This
splits them by surface: the six room faces (with their material from scene.json) and the
objects, with the signed offset of the reconstruction from each room face (positive = in front
of it, inside the room), and optionally a coverage map of one face (% of ground-truth points
within 5 cm per cell), which shows holes.

Usage: scripts/demo_regions.py ROOM_DIR MESH.ply [--face K] [--samples N]
  ROOM_DIR  the synthetic dataset (gt_mesh.ply, scene.json), e.g. `himap demo --out D` -> D/room
  --face K  also print the coverage map of room face K (0 -x, 1 +x, 2 -y, 3 +y, 4 floor, 5 ceiling)
"""
import argparse
import json

import numpy as np
from scipy.spatial import cKDTree


def read_ply(path):
    """Vertices and triangles of a binary little-endian PLY as himap writes it."""
    b = open(path, "rb").read()
    i = b.index(b"end_header\n") + len(b"end_header\n")
    h = b[:i].decode()
    nv = int(h.split("element vertex ")[1].split()[0])
    nf = int(h.split("element face ")[1].split()[0])
    fields = [("p", "<f4", 3)] + ([("c", "u1", 3)] if "property uchar red" in h else [])
    vt = np.dtype(fields)
    v = np.frombuffer(b[i:i + nv * vt.itemsize], dtype=vt)["p"].astype(np.float64)
    o = i + nv * vt.itemsize
    ft = np.dtype([("n", "u1"), ("i", "<i4", 3)])
    f = np.frombuffer(b[o:o + nf * ft.itemsize], dtype=ft)["i"]
    return v, f


def sample(v, f, n, rng):
    """n area-weighted surface samples."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    k = rng.choice(len(f), n, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    return (a[k] * (1 - r1)[:, None] + b[k] * (r1 * (1 - r2))[:, None]
            + c[k] * (r1 * r2)[:, None])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("room")
    ap.add_argument("mesh")
    ap.add_argument("--face", type=int)
    ap.add_argument("--samples", type=int, default=50000)
    a = ap.parse_args()
    scene = json.load(open(a.room + "/scene.json"))["scene"]
    lo, hi = np.array(scene["room_min"]), np.array(scene["room_max"])
    faces = ["-x", "+x", "-y", "+y", "floor", "ceiling"]
    names = [f"{n} {w['kind']}" for n, w in zip(faces, scene["walls"])] + ["objects"]
    rng = np.random.default_rng(0)
    g = sample(*read_ply(a.room + "/gt_mesh.ply"), a.samples, rng)
    r = sample(*read_ply(a.mesh), a.samples, rng)

    label = np.full(len(g), 6)
    for k in range(3):
        label[np.abs(g[:, k] - lo[k]) < 1e-3] = 2 * k
        label[np.abs(g[:, k] - hi[k]) < 1e-3] = 2 * k + 1
    dg, _ = cKDTree(r).query(g)  # completion distances
    dr, nearest = cKDTree(g).query(r)  # accuracy distances
    rl = label[nearest]
    print(f"all: Accuracy {dr.mean() * 100:.2f} cm, Completion {dg.mean() * 100:.2f} cm, "
          f"ratio {(dg < 0.05).mean() * 100:.1f} %")
    print(f"{'region':<18} {'Comp':>6} {'ratio%':>7} {'Acc':>6} {'offset p10/50/90 (cm)':>24}")
    for k, name in enumerate(names):
        m, mr = label == k, rl == k
        off = ""
        if k < 6 and mr.any():
            ax, sign = k // 2, (1 if k % 2 == 0 else -1)
            base = lo[ax] if k % 2 == 0 else hi[ax]
            o = (r[mr, ax] - base) * sign * 100
            off = "%7.2f %7.2f %7.2f" % tuple(np.percentile(o, [10, 50, 90]))
        acc = dr[mr].mean() * 100 if mr.any() else float("nan")
        print(f"{name:<18} {dg[m].mean() * 100:6.2f} {(dg[m] < 0.05).mean() * 100:7.1f} "
              f"{acc:6.2f} {off:>24}")

    if a.face is not None:
        k = a.face
        ax = k // 2
        m = label == k
        other = [x for x in range(3) if x != ax]
        nb = 8
        e0 = np.linspace(lo[other[0]], hi[other[0]], nb + 1)
        e1 = np.linspace(lo[other[1]], hi[other[1]], nb + 1)
        print(f"\n{names[k]}: % of ground truth within 5 cm; rows axis {other[1]} high to low, "
              f"columns axis {other[0]} low to high")
        for j in reversed(range(nb)):
            row = []
            for i in range(nb):
                c = (m & (g[:, other[0]] >= e0[i]) & (g[:, other[0]] < e0[i + 1])
                     & (g[:, other[1]] >= e1[j]) & (g[:, other[1]] < e1[j + 1]))
                row.append("  --" if c.sum() < 5 else "%4d" % int((dg[c] < 0.05).mean() * 100))
            print(" ".join(row))


if __name__ == "__main__":
    main()
