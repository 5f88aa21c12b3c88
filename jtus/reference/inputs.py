"""The random inputs the references' bench workloads share: jtus.bench's distribution
(colour and jitter uniform, depth in [0.5, 1), motion normal with 0.5 LR pixels'
spread), NCHW torch tensors."""

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
