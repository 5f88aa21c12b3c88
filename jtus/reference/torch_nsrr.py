"""NSRR (Xiao et al. 2020, seed ``001``, sec. 3.2-3.4) as a PyTorch module of its own:
``nn.Sequential`` feature extractors, reweighting network and U-Net with their own
parameter layout, converted to jtus's tree by ``to_jtus``; zero-up-sampling, warping
and reweighting written from the paper's text, not from ``jtus/models/nsrr.py``.

From the paper: per frame, a 3-layer feature extractor maps RGB-D to 8 learned
features, concatenated with RGB-D (the current frame and the previous frames have
separate extractors, the previous ones sharing weights); the 12 channels are
zero-up-sampled to the output resolution; each previous frame's up-sampled features are
backward-warped to the current frame with bilinear interpolation, through every motion
field in between; a 3-layer reweighting network on the current RGB-D and the warped
previous RGB-D gives one weight map per previous frame, mapped to [0, 10] by
``10 (tanh + 1) / 2``, that multiplies that frame's 12 features; a 3-scale U-Net
(2x2 max-pooling, bilinear up-sampling, skip concatenations, 10 convolutions, ReLU
after all but the last) reconstructs the colour.

Choices that are jtus's (docs/comparison.md), pinned by the test against jtus:
- the widths (the paper gives them only in a figure our copy lacks): extractors
  32-32-8, reweighting 32-32-4, U-Net 64-32 / 64-64 / 128-128 / 64-64 / 32-3;
- a sample lands on the sub-pixel ``floor(f * jitter)`` of its f x f block;
- warping reads the bilinear taps clamped to the image, and zero where the warped
  position leaves the image; a reset frame's previous features are zero;
- depth is linear in [0, 1] with near 0.1 and far 100.
"""

import torch
import torch.nn.functional as F
from torch import nn

from jtus.reference.inputs import adam_step, random_frame, random_window

FEATURES = 12


def _convs(widths, ci, last_relu=True):
    layers = []
    for i, co in enumerate(widths):
        layers.append(nn.Conv2d(ci, co, 3, padding=1))
        if last_relu or i < len(widths) - 1:
            layers.append(nn.ReLU())
        ci = co
    return nn.Sequential(*layers)


class UNet(nn.Module):
    def __init__(self, ci, w=(64, 32, 64, 64, 128, 128, 64, 64, 32)):
        super().__init__()
        self.enc1 = _convs(w[0:2], ci)
        self.enc2 = _convs(w[2:4], w[1])
        self.enc3 = _convs(w[4:6], w[3])
        self.dec2 = _convs(w[6:8], w[5] + w[3])
        self.dec1 = _convs((w[8], 3), w[7] + w[1], last_relu=False)

    def forward(self, x):
        up = lambda t: F.interpolate(t, scale_factor=2, mode="bilinear", align_corners=False)  # noqa: E731
        s1 = self.enc1(x)
        s2 = self.enc2(F.max_pool2d(s1, 2))
        s3 = self.enc3(F.max_pool2d(s2, 2))
        u2 = self.dec2(torch.cat([up(s3), s2], 1))
        return self.dec1(torch.cat([up(u2), s1], 1))


class NSRR(nn.Module):
    def __init__(self, frames=4):
        super().__init__()
        self.frames = frames
        self.extract_current = _convs((32, 32, 8), 4)
        self.extract_previous = _convs((32, 32, 8), 4)
        self.reweight = _convs((32, 32, frames), 4 + 4 * frames, last_relu=False)
        self.unet = UNet(FEATURES * (1 + frames))


def to_jtus(net):
    """This module's parameters in jtus's tree (lists of HWIO kernels and biases)."""
    def convs(seq):
        return [{"kernel": m.weight.detach().numpy().transpose(2, 3, 1, 0),
                 "bias": m.bias.detach().numpy()} for m in seq if isinstance(m, nn.Conv2d)]

    u = net.unet
    return {"extract_current": convs(net.extract_current),
            "extract_previous": convs(net.extract_previous),
            "reweight": convs(net.reweight),
            "unet": convs(u.enc1) + convs(u.enc2) + convs(u.enc3) + convs(u.dec2) + convs(u.dec1)}


def zero_upsample(x, jitter, f):
    b, c, h, w = x.shape
    out = torch.zeros(b, c, h * f, w * f, dtype=x.dtype)
    cell = torch.floor(jitter * f).long().clamp(0, f - 1)
    for i in range(b):
        out[i, :, int(cell[i, 1])::f, int(cell[i, 0])::f] = x[i]
    return out


def warp(img, motion, f):
    """Backward-warp HR ``img`` by LR ``motion`` [B,2,h,w] (pixels): bilinear at
    ``P + f * up(motion)``, taps clamped, zero outside."""
    b, _, hh, ww = img.shape
    mv = F.interpolate(motion, scale_factor=f, mode="bilinear", align_corners=False) * f
    px = torch.arange(ww, dtype=img.dtype)[None, None, :] + 0.5 + mv[:, 0]
    py = torch.arange(hh, dtype=img.dtype)[None, :, None] + 0.5 + mv[:, 1]
    grid = torch.stack([2 * px / ww - 1, 2 * py / hh - 1], -1)
    out = F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=False)
    inside = ((px >= 0) & (px <= ww) & (py >= 0) & (py <= hh))[:, None]
    return torch.where(inside, out, torch.zeros_like(out))


def step(net, previous, color, depth, motion, jitter, reset, f, normalize=False):
    """One frame, NCHW. ``previous``: a list of the up to ``frames`` previous frames'
    12-channel HR features, newest first, in the previous frame's view (empty at the
    start). ``normalize``: the colour read divided by the frame's mean (at least 1e-4),
    the output multiplied by it. Returns ``(rgb, previous)``."""
    n = net.frames
    b = color.shape[0]
    mean = color.mean((1, 2, 3), keepdim=True).clamp_min(1e-4) if normalize else 1.0
    color = color / mean
    lin = (10.0 / (100.0 - depth * 99.9) - 0.1) / 99.9
    rgbd = torch.cat([color, lin], 1)
    cur = zero_upsample(torch.cat([rgbd, net.extract_current(rgbd)], 1), jitter, f)
    mine = zero_upsample(torch.cat([rgbd, net.extract_previous(rgbd)], 1), jitter, f)
    keep = (~reset)[:, None, None, None].to(color.dtype)
    hr = cur.shape[2:]
    prev = [warp(p * keep, motion, f) for p in previous]
    prev += [torch.zeros(b, FEATURES, *hr, dtype=color.dtype)] * (n - len(prev))
    wts = net.reweight(torch.cat([cur[:, :4]] + [p[:, :4] for p in prev], 1))
    wts = 10.0 * (torch.tanh(wts) + 1) / 2
    scaled = [p * wts[:, i:i + 1] for i, p in enumerate(prev)]
    out = net.unet(torch.cat([cur] + scaled, 1)) * mean
    return out, [mine] + prev[:n - 1]


def infer_workload(config, size):
    """One inference step of this NSRR at HR ``size`` (batch 1, random inputs and
    weights, a full window of previous frames) as a blocking callable, for
    ``python -m jtus.bench``; ``config`` is jtus's NSRR config (its factor)."""
    f = config.factor
    h, w = size[0] // f, size[1] // f
    color, depth, motion, jitter = random_frame(f, size)
    net = NSRR()
    reset = torch.zeros(1, dtype=torch.bool)
    prev = [[torch.zeros(1, FEATURES, h * f, w * f)] * net.frames]

    def run():
        with torch.no_grad():
            _, prev[0] = step(net, prev[0], color, depth, motion, jitter, reset, f)

    return run


def window_loss(net, frames, targets, f, loss_frames, normalize=False):
    """The mean over the last ``loss_frames`` frames of the L1 error (NSRR's training
    loss in jtus, ``rollout.window_loss``) of a window of ``(color, depth, motion,
    jitter, reset)`` frames from an empty history, with the graph for a backward pass."""
    prev, total, n = [], 0.0, len(frames)
    for i, (color, depth, motion, jitter, reset) in enumerate(frames):
        out, prev = step(net, prev, color, depth, motion, jitter, reset, f, normalize)
        if i >= n - loss_frames:
            total = total + (out - targets[i]).abs().mean()
    return total / loss_frames


def train_workload(factor, crop, batch, seq, loss_frames):
    """One BPTT training step (``window_loss``, Adam) on random crops as a callable, for
    ``python -m jtus.bench``."""
    frames, targets = random_window(factor, crop, batch, seq)
    net = NSRR()
    return adam_step(net, lambda: window_loss(net, frames, targets, factor, loss_frames))
