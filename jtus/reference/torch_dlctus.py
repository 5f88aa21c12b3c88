"""An independent PyTorch DLCTUS forward, written from the thesis text (sec. 4.1),
NCHW, built on torch's own grid_sample / interpolate / Conv2d / PixelShuffle.
Module names follow the thesis's released state_dicts (down.0, cnn1.0, cnn1.2, ...)."""

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from jtus.reference.inputs import random_frame


class Net(nn.Module):
    def __init__(self, channels=32, blocks=4):
        super().__init__()
        self.down = nn.Sequential(nn.Conv2d(8, channels, 4, stride=4))
        self.blocks = blocks
        for i in range(1, blocks + 1):
            setattr(self, f"cnn{i}", nn.Sequential(
                nn.Conv2d(channels, channels, 3, padding=1, padding_mode="replicate"),
                nn.ReLU(),
                nn.Conv2d(channels, channels, 3, padding=1, padding_mode="replicate")))
        self.shuffle = nn.PixelShuffle(4)

    def forward(self, x):
        h = self.down(x)
        for i in range(1, self.blocks + 1):
            h = h + getattr(self, f"cnn{i}")(h)
        return self.shuffle(h)


def _pixel_centres(n, device, dtype):
    return torch.arange(n, device=device, dtype=dtype) + 0.5


def jau(color, jitter, f):
    """color [B,3,h,w], jitter [B,2] -> [B,4,H,W] (RGB, ones), bilinear, border."""
    b, _, h, w = color.shape
    x = torch.cat([color, torch.ones_like(color[:, :1])], 1)
    xs = _pixel_centres(w * f, x.device, x.dtype) / f  # HR centres in LR pixels
    ys = _pixel_centres(h * f, x.device, x.dtype) / f
    gx = xs[None, None, :] - jitter[:, 0, None, None] + 0.5
    gy = ys[None, :, None] - jitter[:, 1, None, None] + 0.5
    grid = torch.stack([(2 * gx / w - 1).expand(b, h * f, w * f),
                        (2 * gy / h - 1).expand(b, h * f, w * f)], -1)
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=False)


def zero_up(x, jitter, f):
    b, c, h, w = x.shape
    out = torch.zeros(b, c, h * f, w * f, dtype=x.dtype, device=x.device)
    cell = torch.floor(jitter * f).long().clamp(0, f - 1)
    for i in range(b):
        out[i, :, cell[i, 1]::f, cell[i, 0]::f] = x[i]
    return out


def step(net, history, color, depth, motion, jitter, f, near=0.1, far=100.0, reset=None):
    """One DLCTUS step; all tensors NCHW; returns (rgb [B,3,H,W], history [B,4,H,W]).

    ``reset [B]`` (bool): as the thesis's listing does for its first frame, a reset
    frame's history is the fresh jitter-aligned input, not reprojected (its motion
    points into a frame the history never saw)."""
    b, _, h, w = color.shape
    hh, ww = h * f, w * f
    lin = (near * far / (far - depth * (far - near)) - near) / (far - near)
    zero = zero_up(torch.cat([color, lin], 1), jitter, f)
    j = jau(color, jitter, f)
    mv = F.interpolate(motion, scale_factor=f, mode="bilinear", align_corners=False) * f
    px = _pixel_centres(ww, color.device, color.dtype)[None, None, :] + mv[:, 0]
    py = _pixel_centres(hh, color.device, color.dtype)[None, :, None] + mv[:, 1]
    grid = torch.stack([2 * px / ww - 1, 2 * py / hh - 1], -1)
    rep = F.grid_sample(history, grid, mode="bicubic", padding_mode="border",
                        align_corners=False)
    inside = ((grid >= -1) & (grid <= 1)).all(-1)[:, None]
    hist = torch.where(inside, rep, j)
    if reset is not None:
        hist = torch.where(reset[:, None, None, None], j, hist)
    o = net(torch.cat([zero, hist], 1)).clamp(0, 1)
    o1, o2 = o[:, 0:1], o[:, 1:2]
    out = j * o1 + hist * (1 - o1)
    out = torch.cat([out[:, :3], out[:, 3:] * o2], 1).clamp(0, 1)
    return out[:, :3], out


def init_history(color, jitter, f):
    return jau(color, jitter, f)


# ---------------------------------------------------------------- bench workloads
# The same random inputs as jtus.bench's workloads, as blocking callables timed
# alternately with jtus's (python -m jtus.bench).

DEVICE = "cuda" if torch.cuda.is_available() else "cpu"  # a GPU's when torch has one


def _tensor(a):
    return torch.from_numpy(np.ascontiguousarray(a, np.float32)).to(DEVICE)


def _sync():
    if DEVICE == "cuda":
        torch.cuda.synchronize()


def infer_workload(config, size):
    """One inference step at HR ``size`` (batch 1, channels-last) as a callable;
    ``config`` is jtus's DLCTUS config (its factor)."""
    factor = config.factor
    color, depth, motion, jitter = random_frame(factor, size, DEVICE)
    net = Net().to(DEVICE, memory_format=torch.channels_last)
    hist = [init_history(color, jitter, factor)]

    def run():
        with torch.no_grad():
            _, hist[0] = step(net, hist[0], color, depth, motion, jitter, factor)
        _sync()

    return run


def train_workload(factor, crop, batch, seq, loss_frames):
    """One BPTT training step (L1 on the last ``loss_frames``, Adam) as a callable."""
    h = crop // factor
    r = np.random.default_rng(0)
    xs = [(_tensor(r.uniform(size=(batch, 3, h, h))),
           _tensor(r.uniform(0.5, 1, size=(batch, 1, h, h))),
           _tensor(r.normal(scale=0.5, size=(batch, 2, h, h))),
           _tensor(r.uniform(size=(batch, 2)))) for _ in range(seq)]
    targets = [_tensor(r.uniform(size=(batch, 3, crop, crop))) for _ in range(seq)]
    net = Net().to(DEVICE)
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)

    def run():
        opt.zero_grad()
        hist = init_history(xs[0][0], xs[0][3], factor)
        loss = 0
        for i, (c, d, m, j) in enumerate(xs):
            out, hist = step(net, hist, c, d, m, j, factor)
            if i >= seq - loss_frames:
                loss = loss + (out - targets[i]).abs().mean()
        (loss / loss_frames).backward()
        opt.step()
        _sync()

    return run
