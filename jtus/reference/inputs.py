"""What the references' bench workloads share: random inputs in jtus.bench's
distribution (colour and jitter uniform, depth in [0.5, 1), motion normal with 0.5 LR
pixels' spread) as NCHW torch tensors, and the Adam step of a training workload."""

import numpy as np
import torch


def random_frame(factor, size, device="cpu"):
    """``(color, depth, motion, jitter)`` of one LR frame (batch 1) for HR ``size``."""
    h, w = size[0] // factor, size[1] // factor
    r = np.random.default_rng(0)

    def t(a):
        return torch.from_numpy(np.ascontiguousarray(a, np.float32)).to(device)

    color = t(r.uniform(size=(1, 3, h, w)))
    depth = t(r.uniform(0.5, 1.0, size=(1, 1, h, w)))
    motion = t(r.normal(scale=0.5, size=(1, 2, h, w)))
    return color, depth, motion, t(r.uniform(size=(1, 2)))


def random_window(factor, crop, batch, seq, device="cpu"):
    """A training window of ``seq`` random LR frames (``batch`` crops of ``crop //
    factor`` pixels, the distribution above, a reset on the first frame) as a list of
    ``(color, depth, motion, jitter, reset)`` and its HR targets ``[batch,3,crop,crop]``
    uniform in [0, 1): the references' training workloads."""
    h = crop // factor
    r = np.random.default_rng(0)

    def t(a):
        return torch.from_numpy(np.ascontiguousarray(a, np.float32)).to(device)

    frames = [(t(r.uniform(size=(batch, 3, h, h))), t(r.uniform(0.5, 1.0, size=(batch, 1, h, h))),
               t(r.normal(scale=0.5, size=(batch, 2, h, h))), t(r.uniform(size=(batch, 2))),
               torch.full((batch,), i == 0, dtype=torch.bool, device=device))
              for i in range(seq)]
    targets = [t(r.uniform(size=(batch, 3, crop, crop))) for _ in range(seq)]
    return frames, targets


def adam_step(net, window_loss):
    """One training step as a callable: ``window_loss()`` (a scalar with its graph)
    backward, then Adam (lr 1e-4, as jtus.bench's step) on ``net``'s parameters."""
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)

    def run():
        opt.zero_grad()
        window_loss().backward()
        opt.step()

    return run
