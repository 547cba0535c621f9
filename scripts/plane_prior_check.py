#!/usr/bin/env python3
"""Dev diagnostic (reads ground truth): how far the plane priors of a run are from the true depth.

Run `himap map` with HIMAP_PLANES_DUMP=DIR (the targets of every refresh written as 16-bit
PNGs, 1 / 6553.5 m, 0 = none; later refreshes overwrite earlier ones), then
`python scripts/plane_prior_check.py DIR DATASET [DEPTH_SCALE]` (the dataset's depth PNGs at
the mapped size; the scale its cam_params.json gives, 6553.5 for the synthetic scenes).
"""
import sys, os, numpy as np
from PIL import Image
dump, ds = sys.argv[1], sys.argv[2]
scale = float(sys.argv[3]) if len(sys.argv) > 3 else 6553.5
errs = []
for f in sorted(os.listdir(dump)):
    i = int(f[5:11])
    p = np.asarray(Image.open(os.path.join(dump, f)), dtype=np.float64) / 6553.5
    g = np.asarray(Image.open(os.path.join(ds, "results", f"depth{i:06d}.png")), dtype=np.float64) / scale
    if g.shape != p.shape:
        g = g[::g.shape[0] // p.shape[0], ::g.shape[1] // p.shape[1]]
    m = (p > 0) & (g > 0)
    errs.append(p[m] - g[m])
e = np.concatenate(errs); a = np.abs(e)
print(f"{len(errs)} frames, {len(e)} prior pixels: |target - gt| median {100*np.median(a):.1f} cm, mean {100*np.mean(np.minimum(a,2)):.1f}, >5cm {100*np.mean(a>0.05):.1f}%, >20cm {100*np.mean(a>0.2):.1f}%, signed median {100*np.median(e):.1f}")
