"""What the references' bench workloads share: random inputs in jtus.bench's
distribution (colour and jitter uniform, depth in [0.5, 1), motion normal with 0.5 LR
pixels' spread) as NCHW torch tensors, and the Adam step of a training workload."""

import numpy as np
import torch


def _tensor(a, device):
    return torch.from_numpy(np.ascontiguousarray(a, np.float32)).to(device)


def _draw_frame(r, batch, h, w, device):
    """``(color, depth, motion, jitter)`` of ``batch`` random ``h x w`` LR frames drawn
    from ``r`` in that order (the distribution above)."""
    return (_tensor(r.uniform(size=(batch, 3, h, w)), device),
            _tensor(r.uniform(0.5, 1.0, size=(batch, 1, h, w)), device),
            _tensor(r.normal(scale=0.5, size=(batch, 2, h, w)), device),
            _tensor(r.uniform(size=(batch, 2)), device))


def random_frame(factor, size, device="cpu"):
    """``(color, depth, motion, jitter)`` of one LR frame (batch 1) for HR ``size``."""
    return _draw_frame(np.random.default_rng(0), 1, size[0] // factor, size[1] // factor,
                       device)


def random_window(factor, crop, batch, seq, device="cpu"):
    """A training window of ``seq`` random LR frames (``batch`` crops of ``crop //
    factor`` pixels, the distribution above, a reset on the first frame) as a list of
    ``(color, depth, motion, jitter, reset)`` and its HR targets ``[batch,3,crop,crop]``
    uniform in [0, 1): the references' training workloads."""
    h = crop // factor
    r = np.random.default_rng(0)
    frames = [_draw_frame(r, batch, h, h, device)
              + (torch.full((batch,), i == 0, dtype=torch.bool, device=device),)
              for i in range(seq)]
    targets = [_tensor(r.uniform(size=(batch, 3, crop, crop)), device) for _ in range(seq)]
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
