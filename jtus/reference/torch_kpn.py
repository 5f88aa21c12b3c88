"""Herveau et al.'s kernel-prediction TAA network (seed ``002``) as a PyTorch module of
its own, with jtus's adaptation to up-sampling, written from the paper's text and
``docs/comparison.md`` rather than from ``jtus/models/kpn.py``: its own parameter
layout (``nn.Conv2d`` per layer, one per jitter phase where the paper switches
weight sets), its own Catmull-Rom reprojection and its own input preparation.

From the paper (sec. 4): the input is the current RGB with per-pixel motion and depth,
plus eight feedback channels (the previous anti-aliased RGB and five hidden channels)
reprojected with Catmull-Rom; four zero-padded convolutions (3x3, 3x3, 5x5, then the
5x5 kernel layer) with ReLU after all but the last, and a 1x1 "hidden" layer without
activation from the third layer's output; the last three layers switch among weight
sets by the jitter index; two 5x5 kernels mix the 5x5 neighbourhoods of the current
colour and of the reprojected previous RGB (eq. 3).

Choices that are jtus's, not the paper's (an anti-aliasing network given an
up-sampling task; docs/comparison.md), each pinned by the test against jtus:
- the current colour is the jitter-aligned bilinear up-sampling of the LR frame, and
  depth (linearized) and motion (times f, in HR pixels) are up-sampled bilinearly;
- the kernels are normalized by a softmax over all 50 weights (the paper's text says
  a sigmoid "to normalize the sum of all kernel elements to 1", which a sigmoid does
  not do);
- Catmull-Rom taps outside the image are clamped to the edge; a reprojected position
  outside the image reads zeros; a reset frame's feedback is the current colour and
  zero hidden channels, unwarped;
- the colour mix pads the neighbourhoods with zeros (the paper's zero padding);
- the jitter index is the nearest entry of the jitter sequence;
- with ``samples=True`` (jtus's ``current="samples"``): the current kernel mixes the
  frame's samples placed at the HR pixel under each (zeros elsewhere), the input gains
  that pixel mask and the placed samples, and the softmax leaves out the current taps
  without a sample (their logits set to minus infinity);
- with ``clamp=True`` (jtus's ``history="clamped"``): the reprojected RGB is clamped,
  per channel, to the min and max of the 3x3 LR samples around the sample nearest
  each HR pixel's jitter-aligned position, every tap clamped to the image (TUS's
  neighbourhood clamp), before it enters the network and the history kernel;
- with ``normalize=True`` (jtus's ``exposure="normalized"``): the colour the network
  reads (the up-sampled colour, the feedback RGB, the placed samples) is divided by
  the frame's mean colour, at least 1e-4; the kernels mix the colours undivided.
"""

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from jtus.models import kpn  # its jitter phases only (which weight set a frame uses)
from jtus.reference.inputs import adam_step, random_frame, random_window
from jtus.reference.torch_nsrr import warp, zero_upsample

HIDDEN = 5


class KPN(nn.Module):
    def __init__(self, phases, width=12, samples=False):
        super().__init__()
        self.conv1 = nn.Conv2d(3 + 1 + 2 + 3 + HIDDEN + 4 * samples, width, 3, padding=1)
        self.conv2 = nn.ModuleList(nn.Conv2d(width, width, 3, padding=1) for _ in range(phases))
        self.conv3 = nn.ModuleList(nn.Conv2d(width, width, 5, padding=2) for _ in range(phases))
        self.hidden = nn.Conv2d(width, HIDDEN, 1)
        self.kernel = nn.ModuleList(nn.Conv2d(width, 50, 5, padding=2) for _ in range(phases))

    def forward(self, x, phase, valid=None):
        """``valid [1,50,H,W]`` (booleans): the taps the softmax runs over."""
        h = F.relu(self.conv1(x))
        h = F.relu(self.conv2[phase](h))
        h = F.relu(self.conv3[phase](h))
        logits = self.kernel[phase](h)
        if valid is not None:
            logits = logits.masked_fill(~valid, float("-inf"))
        return torch.softmax(logits, 1), self.hidden(h)


def to_jtus(net):
    """This module's parameters in jtus's tree (HWIO kernels, phase-stacked sets)."""
    def one(conv):
        return {"kernel": conv.weight.detach().numpy().transpose(2, 3, 1, 0),
                "bias": conv.bias.detach().numpy()}

    def sets(convs):
        parts = [one(c) for c in convs]
        return {k: np.stack([p[k] for p in parts]) for k in ("kernel", "bias")}

    return {"conv1": one(net.conv1), "conv2": sets(net.conv2), "conv3": sets(net.conv3),
            "hidden": one(net.hidden), "kernel": sets(net.kernel)}


def catmull_rom(img, x, y):
    """Sample ``img [B,C,H,W]`` at pixel positions ``x, y [B,H',W']`` (centres at
    i + 0.5) with the Catmull-Rom spline (Keys a = -0.5), taps clamped to the image."""
    b, c, h, w = img.shape
    u, v = x - 0.5, y - 0.5
    x0, y0 = torch.floor(u), torch.floor(v)
    tx, ty = u - x0, v - y0

    def weights(t):  # the four taps at -1, 0, 1, 2
        return [((-0.5 * t + 1.0) * t - 0.5) * t,
                (1.5 * t - 2.5) * t * t + 1.0,
                ((-1.5 * t + 2.0) * t + 0.5) * t,
                (0.5 * t - 0.5) * t * t]

    wx, wy = weights(tx), weights(ty)
    flat = img.reshape(b, c, h * w)
    out = torch.zeros(b, c, *x.shape[1:], dtype=img.dtype)
    for j in range(4):
        yy = (y0 + j - 1).clamp(0, h - 1).long()
        for i in range(4):
            xx = (x0 + i - 1).clamp(0, w - 1).long()
            idx = (yy * w + xx).reshape(b, 1, -1).expand(b, c, -1)
            tap = torch.gather(flat, 2, idx).reshape(b, c, *x.shape[1:])
            out = out + (wy[j] * wx[i])[:, None] * tap
    return out


def aligned(color, jitter, f):
    """Where each HR centre P reads the LR image, ``P / f - jitter + 0.5`` in LR pixels:
    ``(x [B,1,W'], y [B,H',1])``."""
    _, _, h, w = color.shape
    xs = (torch.arange(w * f, dtype=color.dtype) + 0.5) / f
    ys = (torch.arange(h * f, dtype=color.dtype) + 0.5) / f
    return (xs[None, None, :] - jitter[:, 0, None, None] + 0.5,
            ys[None, :, None] - jitter[:, 1, None, None] + 0.5)


def jau(color, jitter, f):
    """Jitter-aligned bilinear up-sampling: HR centre P reads the LR image at
    ``P / f - jitter + 0.5`` (border padding)."""
    b, _, h, w = color.shape
    gx, gy = aligned(color, jitter, f)
    grid = torch.stack([(2 * gx / w - 1).expand(b, h * f, w * f),
                        (2 * gy / h - 1).expand(b, h * f, w * f)], -1)
    return F.grid_sample(color, grid, mode="bilinear", padding_mode="border",
                         align_corners=False)


def box(color, jitter, f):
    """Per HR pixel, the min and max ``[B,C,H,W]`` of the 9 LR samples at the offsets
    -1, 0, 1 from the sample nearest its jitter-aligned position ``P / f - jitter +
    0.5``, read one by one with their indices clamped to the image."""
    b, c, h, w = color.shape
    gx, gy = aligned(color, jitter, f)
    nx, ny = torch.floor(gx).clamp(-1, w), torch.floor(gy).clamp(-1, h)
    nx, ny = nx.expand(b, h * f, w * f), ny.expand(b, h * f, w * f)
    flat = color.reshape(b, c, h * w)
    taps = []
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            idx = ((ny + dy).clamp(0, h - 1) * w + (nx + dx).clamp(0, w - 1)).long()
            taps.append(torch.gather(flat, 2, idx.reshape(b, 1, -1).expand(b, c, -1)))
    taps = torch.stack(taps).reshape(9, b, c, h * f, w * f)
    return taps.min(0).values, taps.max(0).values


def step(net, feedback, color, depth, motion, jitter, reset, phases, f, near=0.1, far=100.0,
         samples=False, clamp=False, normalize=False):
    """One frame, NCHW: ``feedback [B,8,H,W]`` (None on a sequence's first frame);
    returns ``(rgb [B,3,H,W], feedback)``."""
    b, _, h, w = color.shape
    cur = jau(color, jitter, f)
    lin = (near * far / (far - depth * (far - near)) - near) / (far - near)
    up = lambda t: F.interpolate(t, scale_factor=f, mode="bilinear", align_corners=False)  # noqa: E731
    mv = up(motion) * f
    fresh = torch.cat([cur, torch.zeros(b, HIDDEN, h * f, w * f, dtype=cur.dtype)], 1)
    if feedback is None:
        rep = fresh
    else:
        px = torch.arange(w * f, dtype=cur.dtype)[None, None, :] + 0.5 + mv[:, 0]
        py = torch.arange(h * f, dtype=cur.dtype)[None, :, None] + 0.5 + mv[:, 1]
        rep = catmull_rom(feedback, px, py)
        inside = ((px >= 0) & (px <= w * f) & (py >= 0) & (py <= h * f))[:, None]
        rep = torch.where(inside, rep, torch.zeros_like(rep))
        rep = torch.where(reset[:, None, None, None], fresh, rep)
    if clamp:
        lo, hi = box(color, jitter, f)
        rep = torch.cat([torch.minimum(torch.maximum(rep[:, :3], lo), hi), rep[:, 3:]], 1)
    s = 1.0 / color.mean((1, 2, 3), keepdim=True).clamp_min(1e-4) if normalize else 1.0
    x = torch.cat([cur * s, up(lin), mv, rep[:, :3] * s, rep[:, 3:]], 1)
    valid = None
    if samples:
        mask = zero_upsample(torch.ones_like(depth), jitter, f)
        cur = zero_upsample(color, jitter, f)
        x = torch.cat([x, mask, cur * s], 1)
        taps = F.unfold(mask, 5, padding=2).view(b, 25, h * f, w * f) > 0.5
        valid = torch.cat([taps, torch.ones_like(taps)], 1)
    d = (jitter[:, None, :] - phases[None]).abs().sum(-1)
    index = d.argmin(-1)
    outs, hiddens = [], []
    for i in range(b):
        wts, hid = net(x[i:i + 1], int(index[i]), None if valid is None else valid[i:i + 1])
        def mix(img, wk):
            patches = F.unfold(img, 5, padding=2).view(1, 3, 25, h * f, w * f)
            return (patches * wk[:, None]).sum(2)
        outs.append(mix(cur[i:i + 1], wts[:, :25]) + mix(rep[i:i + 1, :3], wts[:, 25:]))
        hiddens.append(hid)
    out = torch.cat(outs)
    return out, torch.cat([out, torch.cat(hiddens)], 1)


def infer_workload(config, size):
    """One inference step of this KPN at HR ``size`` (batch 1, random inputs and
    weights) as a blocking callable, for ``python -m jtus.bench``; ``config`` is jtus's
    KPN config (its factor and jitter phases)."""
    f = config.factor
    color, depth, motion, jitter = random_frame(f, size)
    phases = torch.from_numpy(np.asarray(config.phases(), np.float32))
    net = KPN(len(phases))
    reset = torch.zeros(1, dtype=torch.bool)
    fb = [None]

    def run():
        with torch.no_grad():
            _, fb[0] = step(net, fb[0], color, depth, motion, jitter, reset, phases, f)

    return run


def loss(out, target, prev_error, color, motion, jitter, f, weights=(1.0, 1.0, 4.0),
         alias_boost=1.5, sensitivity=4.0):
    """Herveau et al.'s training loss as jtus trains KPN with (its defaults, NCHW): the
    alias mask ``M`` (the jitter-aligned input's summed channel error against the target,
    scaled, clipped to [0, 1], max over 3x3) weighs by ``alias_boost M + 1 - M`` the
    reference L1, the L1 of the x and y differences, and the L1 of the current error
    against the previous one backward-warped (bilinear, zero outside; ``prev_error``
    None on a window's first frame)."""
    m = (sensitivity * (jau(color, jitter, f) - target).abs().sum(1, keepdim=True)).clamp(0, 1)
    m = F.max_pool2d(m, 3, stride=1, padding=1)
    wgt = alias_boost * m + (1 - m)
    ref = (wgt * (out - target).abs()).mean()

    def diffs(x):  # y and x differences on the [:-1, :-1] corner
        return x[:, :, 1:, :-1] - x[:, :, :-1, :-1], x[:, :, :-1, 1:] - x[:, :, :-1, :-1]

    (gy_o, gx_o), (gy_t, gx_t) = diffs(out), diffs(target)
    grad = (wgt[:, :, :-1, :-1] * ((gy_o - gy_t).abs() + (gx_o - gx_t).abs())).mean()
    x = out - target
    y = torch.zeros_like(x) if prev_error is None else warp(prev_error, motion, f)
    temporal = (wgt * (x - y).abs()).mean()
    wr, wg, wt = weights
    return wr * ref + wg * grad + wt * temporal


def window_loss(net, frames, targets, f, loss_frames, phases):
    """The mean of ``loss`` over the last ``loss_frames`` frames of a window of ``(color,
    depth, motion, jitter, reset)`` frames from an empty history (``rollout.window_loss``
    with jtus's ``kpn`` loss), with the graph for a backward pass; ``phases`` are the
    jitter phases that select the weight sets."""
    fb, prev_error, total, n = None, None, 0.0, len(frames)
    for i, (color, depth, motion, jitter, reset) in enumerate(frames):
        out, fb = step(net, fb, color, depth, motion, jitter, reset, phases, f)
        if i >= n - loss_frames:
            total = total + loss(out, targets[i], prev_error, color, motion, jitter, f)
        prev_error = out - targets[i]
    return total / loss_frames


def train_workload(factor, crop, batch, seq, loss_frames):
    """One BPTT training step (``window_loss``, Adam) on random crops as a callable, for
    ``python -m jtus.bench``; the weight sets of the ``thesis`` jitter sequence's phases."""
    frames, targets = random_window(factor, crop, batch, seq)
    phases = torch.from_numpy(np.asarray(kpn.Config(factor=factor).phases(), np.float32))
    net = KPN(len(phases))
    return adam_step(net, lambda: window_loss(net, frames, targets, factor, loss_frames,
                                              phases))
