"""A small real surrogate for the finder tests: a torch MLP trained on RAYX twin traces.

Uniform draws over the whole box are ~99 % dark, so a few hundred traces
teach a model nothing there.  The tests therefore work in a small region
around the centre of the box (normalized 0.5 +- 0.02, where most
configurations are bright), trace a few hundred configurations with the real
twin at few rays and fit a small MLP to them in a few seconds.  Everything
is cached per test session (both test modules share one model).
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from bluesky_offsets.physics.parameters import METRIXS

CENTER, HALF_WIDTH = 0.5, 0.02
N_SAMPLES, N_RAYS = 220, 500


class LocalMLP(torch.nn.Module):
    """Normalized parameters (..., P) -> histograms (..., 100), fraction of source rays."""

    def __init__(self, n_in: int = 34, width: int = 96):
        super().__init__()
        self.net = torch.nn.Sequential(torch.nn.Linear(n_in, width), torch.nn.SiLU(),
                                       torch.nn.Linear(width, width), torch.nn.SiLU(),
                                       torch.nn.Linear(width, 100))

    def forward(self, x):
        h = self.net((x - CENTER) / HALF_WIDTH)
        return torch.nn.functional.softplus(h) * 0.02


@functools.lru_cache(maxsize=1)
def twin_data(n: int = N_SAMPLES, n_rays: int = N_RAYS, seed: int = 0):
    from bluesky_offsets.physics.twin import Twin
    rng = np.random.default_rng(seed)
    x = CENTER + rng.uniform(-HALF_WIDTH, HALF_WIDTH, (n, len(METRIXS)))
    twin = Twin(scheduler="inline", n_rays=n_rays)
    res = twin.trace_batch(METRIXS.denormalize(x), seed=seed, progress=False)
    y = np.concatenate([res.hist_x, res.hist_y], axis=1)
    ok = np.isfinite(y).all(axis=1)
    return x[ok], y[ok]


@functools.lru_cache(maxsize=1)
def trained_model(steps: int = 1500, seed: int = 0) -> LocalMLP:
    x, y = twin_data()
    torch.manual_seed(seed)
    model = LocalMLP()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny batches: threads only fight the other jobs on the machine
    X, Y = torch.as_tensor(x, dtype=torch.float32), torch.as_tensor(y, dtype=torch.float32)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    for _ in range(steps):
        opt.zero_grad()
        loss = ((model(X) - Y) ** 2).mean()
        loss.backward()
        opt.step()
    torch.set_num_threads(threads)
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    model.train_mse = float(loss.detach())
    return model
