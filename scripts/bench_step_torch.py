#!/usr/bin/env python3
"""The paper model's training step written plainly in PyTorch: the peer `himap bench` compares
its CPU step against (dev-only, never used at run time).

Same model and batch as `himap bench --config paper-step`: a 4 m cube, geometry 6 factorized
levels (64..2 cm) x 2 channels, appearance 2 levels (24 cm, 2 cm) x 32 channels, two decoders
with two hidden layers of 32 (geometry: 12 -> 1; appearance: 3 + 64 -> 3, sigmoid), SDF-as-
density rendering (sigma = beta sigmoid(-beta s)), 2048 rays x 64 stratified samples (random
origins in the box, random unit directions, t in [0.1, 3.0] m), L1 colour loss, Adam on every
group. float32, `grid_sample` (align_corners, border), autograd, fused Adam where available.

    pip install torch
    python3 scripts/bench_step_torch.py --threads 2 --steps 5
"""
import argparse
import resource
import time

import torch
import torch.nn.functional as F


def vertices(extent, cell):
    return int(-(-extent // cell)) + 1  # ceil(extent / cell) + 1


class Grid(torch.nn.Module):
    """Factorized (TensoRF VM) levels: three planes and three lines per level, channel-wise."""

    def __init__(self, extent, cells, channels, std=0.01):
        super().__init__()
        self.planes = torch.nn.ParameterList()
        self.lines = torch.nn.ParameterList()
        for c in cells:
            r = vertices(extent, c)
            for _ in range(3):
                self.planes.append(torch.nn.Parameter(torch.randn(1, channels, r, r) * std))
                self.lines.append(torch.nn.Parameter(torch.randn(1, channels, r, 1) * std))
        self.levels = len(cells)

    def forward(self, x):  # x: [M, 3] in [-1, 1]
        m = x.shape[0]
        # plane xy, xz, yz with the complementary line z, y, x
        pairs = [((0, 1), 2), ((0, 2), 1), ((1, 2), 0)]
        feats = []
        for lv in range(self.levels):
            f = 0
            for k, ((a, b), c) in enumerate(pairs):
                pg = torch.stack([x[:, a], x[:, b]], dim=-1).view(1, m, 1, 2)
                lg = torch.stack([torch.zeros_like(x[:, c]), x[:, c]], dim=-1).view(1, m, 1, 2)
                p = F.grid_sample(self.planes[3 * lv + k], pg, align_corners=True,
                                  padding_mode="border").view(-1, m)
                li = F.grid_sample(self.lines[3 * lv + k], lg, align_corners=True,
                                   padding_mode="border").view(-1, m)
                f = f + p * li
            feats.append(f.t())
        return torch.cat(feats, dim=1)


def mlp(n_in, n_out, hidden=32):
    return torch.nn.Sequential(
        torch.nn.Linear(n_in, hidden), torch.nn.ReLU(),
        torch.nn.Linear(hidden, hidden), torch.nn.ReLU(),
        torch.nn.Linear(hidden, n_out))


class Field(torch.nn.Module):
    def __init__(self, extent):
        super().__init__()
        self.extent = extent
        self.geo = Grid(extent, [0.64, 0.32, 0.16, 0.08, 0.04, 0.02], 2)
        self.app = Grid(extent, [0.24, 0.02], 32)
        self.geo_mlp = mlp(12, 1)
        self.app_mlp = mlp(3 + 64, 3)
        self.beta = torch.nn.Parameter(torch.tensor(10.0))

    def render(self, o, d, t):  # o, d: [N, 3]; t: [N, S]
        n, s = t.shape
        p = o[:, None, :] + t[..., None] * d[:, None, :]
        x = (p / (self.extent * 0.5)).clamp(-1, 1).view(-1, 3)
        sdf = self.geo_mlp(self.geo(x)).view(n, s)
        rgb = torch.sigmoid(self.app_mlp(torch.cat([x, self.app(x)], dim=1))).view(n, s, 3)
        sigma = self.beta * torch.sigmoid(-self.beta * sdf)
        alpha = 1 - torch.exp(-sigma)
        trans = torch.exp(-torch.cumsum(torch.cat([torch.zeros_like(sigma[:, :1]), sigma[:, :-1]], 1), 1))
        w = trans * alpha
        return (w[..., None] * rgb).sum(1)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rays", type=int, default=2048)
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--steps", type=int, default=5)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    extent = 4.0
    field = Field(extent)
    params = sum(p.numel() for p in field.parameters())
    groups = [
        {"params": list(field.geo.parameters()) + list(field.app.parameters()), "lr": 0.01},
        {"params": list(field.geo_mlp.parameters()) + list(field.app_mlp.parameters()) + [field.beta],
         "lr": 1e-5},
    ]
    try:
        opt = torch.optim.Adam(groups, fused=True)
        fused = "fused"
    except (RuntimeError, TypeError):
        opt = torch.optim.Adam(groups, foreach=True)
        fused = "foreach"

    def batch():
        o = (torch.rand(a.rays, 3) * 2 - 1) * extent * 0.4
        d = F.normalize(torch.randn(a.rays, 3), dim=1)
        edges = torch.linspace(0.1, 3.0, a.samples + 1)
        t = edges[:-1] + (edges[1:] - edges[:-1]) * torch.rand(a.rays, a.samples)
        return o, d, t, torch.rand(a.rays, 3)

    o, d, t, target = batch()
    with torch.no_grad():
        field.render(o, d, t)  # warm-up
        t0 = time.perf_counter()
        for _ in range(a.steps):
            field.render(o, d, t)
        fwd = (time.perf_counter() - t0) / a.steps

    def step():
        opt.zero_grad(set_to_none=True)
        loss = (field.render(o, d, t) - target).abs().sum(1).mean()
        loss.backward()
        opt.step()

    step()  # warm-up
    t0 = time.perf_counter()
    for _ in range(a.steps):
        step()
    train = (time.perf_counter() - t0) / a.steps
    samples = a.rays * a.samples
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(f"pytorch {torch.__version__} ({a.threads} threads, Adam {fused}): params {params}, "
          f"{a.rays} rays x {a.samples} samples")
    print(f"pytorch forward {samples / fwd:,.0f} samples/s ({fwd * 1e3:.1f} ms)")
    print(f"pytorch train step {train * 1e3:.1f} ms ({samples / train:,.0f} samples/s)")
    print(f"pytorch peak memory {peak / 1e6:.0f} MB (max RSS)")


if __name__ == "__main__":
    main()
