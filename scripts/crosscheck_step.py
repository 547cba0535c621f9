#!/usr/bin/env python3
"""Recompute a `himap dump-step` file with PyTorch autograd and compare.

Dev-only cross-check (never used at run time). Reads only the safetensors file: the parameters,
rays, sample depths and targets, plus the layout metadata, re-implements the forward pass from
the formulas in the README ("Cross-checking a training step") in float64, differentiates the
loss with autograd and compares the loss, the rendered outputs and every gradient group with
himap's values. Exits non-zero if any relative error exceeds the tolerance (default 1e-4).

    pip install torch safetensors numpy
    himap dump-step --out step.safetensors --seed 3
    python3 scripts/crosscheck_step.py step.safetensors
"""
import argparse
import json
import sys

import numpy as np
import torch
from safetensors import safe_open

torch.set_default_dtype(torch.float64)


def load(path):
    tensors = {}
    with safe_open(path, framework="np") as f:
        meta = f.metadata()
        for k in f.keys():
            tensors[k] = f.get_tensor(k)
    return tensors, json.loads(meta["himap_config"])


def lerp_index(x, res):
    """Align-corners continuous index of normalised coordinate x in [-1, 1] on `res` vertices:
    returns (i0, frac) with i0 in [0, res - 2] (detached) and frac differentiable."""
    ci = (x + 1.0) * 0.5 * (res - 1)
    i0 = torch.clamp(torch.floor(ci.detach()), 0, res - 2).long()
    return i0, ci - i0


def grid_features(params, g, pn):
    """Features of a factorized (TensoRF VM) or dense grid at normalised positions pn [M, 3]."""
    C = g["channels"]
    feats = []
    for lv in g["levels"]:
        rx, ry, rz = lv["res"]
        (ix, fx), (iy, fy), (iz, fz) = (lerp_index(pn[:, a], r) for a, r in enumerate((rx, ry, rz)))
        if g["kind"] == "factorized":
            def plane(off, ia, fa, ib, fb, ra):
                # plane "ab": row-major over (b, a), channel-last
                def at(a, b):
                    idx = ((b * ra + a) * C)[:, None] + torch.arange(C)[None, :]
                    return params[off + idx]
                fa_, fb_ = fa[:, None], fb[:, None]
                return (at(ia, ib) * (1 - fa_) * (1 - fb_) + at(ia + 1, ib) * fa_ * (1 - fb_)
                        + at(ia, ib + 1) * (1 - fa_) * fb_ + at(ia + 1, ib + 1) * fa_ * fb_)

            def line(off, ia, fa):
                idx = (ia * C)[:, None] + torch.arange(C)[None, :]
                fa_ = fa[:, None]
                return params[off + idx] * (1 - fa_) + params[off + idx + C] * fa_

            pxy, pxz, pyz = lv["plane_offsets"]
            lx, ly, lz = lv["line_offsets"]
            f = (line(lx, ix, fx) * plane(pyz, iy, fy, iz, fz, ry)
                 + line(ly, iy, fy) * plane(pxz, ix, fx, iz, fz, rx)
                 + line(lz, iz, fz) * plane(pxy, ix, fx, iy, fy, rx))
        else:
            off = lv["offset"]
            f = 0
            for dz in (0, 1):
                for dy in (0, 1):
                    for dx in (0, 1):
                        w = ((fx if dx else 1 - fx) * (fy if dy else 1 - fy) * (fz if dz else 1 - fz))[:, None]
                        idx = ((((iz + dz) * ry + (iy + dy)) * rx + (ix + dx)) * C)[:, None] + torch.arange(C)[None, :]
                        f = f + params[off + idx] * w
        feats.append(f)
    return torch.cat(feats, dim=1)


def mlp(params, m, x):
    """ReLU MLP; per layer: weights row-major [out][in], then biases [out]."""
    off = 0
    n_in = m["n_in"]
    for k in range(m["hidden_layers"] + 1):
        n_out = m["hidden"] if k < m["hidden_layers"] else m["n_out"]
        w = params[off: off + n_out * n_in].reshape(n_out, n_in)
        off += n_out * n_in
        b = params[off: off + n_out]
        off += n_out
        x = x @ w.T + b
        if k < m["hidden_layers"]:
            x = torch.relu(x)
        n_in = n_out
    return x


def render(mode, sdf, rgb, t, beta):
    """Weights, colour, depth, opacity for [N, S] samples."""
    if mode == "SdfDensity":
        sigma = beta * torch.sigmoid(-beta * sdf)
        alpha = 1 - torch.exp(-sigma)
        acc = torch.cumsum(sigma, dim=1) - sigma
        w = torch.exp(-acc) * alpha
    elif mode == "Occupancy":
        alpha = torch.sigmoid(-beta * sdf)
        trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], dim=1), dim=1)
        w = trans * alpha
    elif mode == "SdfDirect":
        bell = torch.sigmoid(beta * sdf) * torch.sigmoid(-beta * sdf)
        w = bell / (bell.sum(dim=1, keepdim=True) + 1e-8)
    else:
        raise ValueError(mode)
    color = (w[:, :, None] * rgb).sum(dim=1)
    depth = (w * t).sum(dim=1)
    return w, color, depth, w.sum(dim=1)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("file")
    ap.add_argument("--tol", type=float, default=1e-4, help="relative tolerance (L2 norm per tensor)")
    ap.add_argument("--abs", type=float, default=1e-8,
                    help="absolute floor: a tensor whose L2 error is below it passes (gradients that are "
                         "cancellations of much larger terms, e.g. beta under SdfDirect, are ~1e-6 and "
                         "f32 limits their relative accuracy)")
    args = ap.parse_args()
    T, cfg = load(args.file)
    groups = ["geometry_grid", "appearance_grid", "geometry_mlp", "appearance_mlp", "beta"]
    P = {g: torch.tensor(T["params." + g].astype(np.float64), requires_grad=True) for g in groups}

    o, d, t = (torch.tensor(T[k].astype(np.float64)) for k in ("rays.origin", "rays.dir", "samples.t"))
    count = T["samples.count"]
    N, S = t.shape
    lo, hi = torch.tensor(cfg["aabb"]["min"]), torch.tensor(cfg["aabb"]["max"])
    pts = o[:, None, :] + t[:, :, None] * d[:, None, :]                     # [N, S, 3]
    pn = torch.clamp((pts - lo) / (hi - lo) * 2 - 1, -1, 1).reshape(-1, 3)
    fg = grid_features(P["geometry_grid"], cfg["geometry_grid"], pn)
    sdf = mlp(P["geometry_mlp"], cfg["geometry_mlp"], fg)[:, 0].reshape(N, S)
    fa = grid_features(P["appearance_grid"], cfg["appearance_grid"], pn)
    app_in = torch.cat([pn, fa], dim=1) if cfg["dual_path"] else fa
    rgb = torch.sigmoid(mlp(P["appearance_mlp"], cfg["appearance_mlp"], app_in)).reshape(N, S, 3)
    beta = P["beta"][0]
    hit = torch.tensor(count > 0)
    if not cfg["color_to_geometry"]:
        raise SystemExit("detached colour weights are not reproduced by this script")
    w, color, depth, opacity = render(cfg["render_mode"], sdf, rgb, t, beta)
    zero = torch.zeros(())
    color = torch.where(hit[:, None], color, zero)
    depth = torch.where(hit, depth, zero)
    opacity = torch.where(hit, opacity, zero)
    tc = torch.tensor(T["target.color"].astype(np.float64))
    td = torch.tensor(T["target.depth"].astype(np.float64))
    per_ray = cfg["lambda_color"] * (color - tc).abs().sum(dim=1)
    per_ray = per_ray + torch.where(td > 0, cfg["lambda_depth"] * (depth - td).abs(), zero)
    loss = cfg["ray_scale"] * per_ray.sum()
    loss.backward()

    def rel(a, b):
        """Relative L2 error; a tensor whose absolute L2 error is within --abs counts as 0."""
        a, b = np.asarray(a, np.float64).ravel(), np.asarray(b, np.float64).ravel()
        err = float(np.linalg.norm(a - b))
        return 0.0 if err <= args.abs else err / max(float(np.linalg.norm(b)), 1e-30)

    rows = [
        ("loss", rel(T["loss"], loss.detach().numpy())),
        ("render.color", rel(T["render.color"], color.detach().numpy())),
        ("render.depth", rel(T["render.depth"], depth.detach().numpy())),
        ("render.opacity", rel(T["render.opacity"], opacity.detach().numpy())),
        ("render.weights", rel(T["render.weights"], torch.where(hit[:, None], w, zero).detach().numpy())),
    ]
    for g in groups:
        rows.append(("grad." + g, rel(T["grad." + g], P[g].grad.numpy())))
    worst = 0.0
    print(f"loss: himap {float(T['loss'][0]):.9g}  torch {loss.item():.9g}")
    for name, r in rows:
        worst = max(worst, r)
        print(f"{name:24s} relative error {r:.3e} {'ok' if r <= args.tol else 'FAIL'}")
    print(f"worst relative error {worst:.3e} (tolerance {args.tol:g})")
    sys.exit(0 if worst <= args.tol else 1)


if __name__ == "__main__":
    main()
