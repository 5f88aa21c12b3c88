"""DLCTUS's forward as the thesis's own code listing (appendix A.1 of seed ``000``)
builds it, in PyTorch on the CPU: every design decision here is the listing's, not
jtus's (``jtus/reference/torch_dlctus.py``, the bench's reference, mirrors jtus's structure).

The listing's steps, in its order:
- zero-up-sampling: a grouped ``conv_transpose2d`` with a kernel whose only 1 is at
  (0, 0), then ``JitterAlign``: pad by f with zeros and slice, shifting each sample by
  ``floor(f * jitter)`` sub-pixels;
- jitter-aligned input: ``affine_grid`` with a translation of ``2 (0.5 - jitter) / W``
  in normalized units, then bilinear ``grid_sample`` with border padding;
- motion: the listing takes an absolute LR sampling grid in normalized units
  (``IdentityGrid`` plus the motion), removes the identity, up-samples bilinearly,
  adds the HR identity and samples the history bicubically with border padding;
- where that grid leaves [-1, 1] (either axis) the history is the jitter-aligned
  input ("special case for padding");
- the first frame (``history is None``) takes the jitter-aligned input, unwarped;
- the network, clamp, lerp, accumulation product, clamp.

Where the listing is silent and a choice was needed (each pinned by a test):
- camera cuts: the listing knows only a first frame; here a reset batch element is
  treated as a first frame (its history is None), the reading docs/conventions.md
  states;
- jtus's motion (backward, LR pixels) becomes the listing's grid as
  ``identity + 2 * motion / (w, h)``;
- the listing hard-codes near 0.1 and far 100 in ``DepthToLinear``; so does this file.
"""

import torch
import torch.nn.functional as F


def zero_upsampling(x, factor):
    c = x.shape[1]
    w = torch.zeros(factor, factor, dtype=x.dtype)
    w[0, 0] = 1
    return F.conv_transpose2d(x, w.expand(c, 1, factor, factor), stride=factor, groups=c)


def jitter_align(img, jitter, factor):
    index = torch.floor(jitter * factor).int()
    img = F.pad(img, (factor, factor, factor, factor), mode="constant")
    out = []
    for b in range(img.shape[0]):
        i, j = int(index[b, 1]), int(index[b, 0])
        out.append(img[b, :, factor - i:-factor - i, factor - j:-factor - j])
    return torch.stack(out)


def jitter_aligned_interpolation(img, jitter, factor):
    n, c, h, w = img.shape
    theta = torch.stack([torch.tensor([[1.0, 0.0, 2.0 * (0.5 - float(jitter[i, 0])) / w],
                                       [0.0, 1.0, 2.0 * (0.5 - float(jitter[i, 1])) / h]],
                                      dtype=img.dtype) for i in range(n)])
    grid = F.affine_grid(theta, (n, c, h * factor, w * factor), align_corners=False)
    return F.grid_sample(img, grid, mode="bilinear", align_corners=False,
                         padding_mode="border")


def identity_grid(n, h, w, dtype):
    theta = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=dtype)
    return F.affine_grid(theta.unsqueeze(0).expand(n, -1, -1), (n, 1, h, w),
                         align_corners=False)


def depth_to_linear(depth):
    far, near = 100.0, 0.1
    depth = near * far / (far - depth * (far - near))
    return (depth - near) / (far - near)


def motion_to_listing_grid(motion):
    """jtus's backward motion [B,2,h,w] in LR pixels -> the listing's absolute LR grid
    [B,h,w,2] in normalized units."""
    n, _, h, w = motion.shape
    scale = torch.tensor([2.0 / w, 2.0 / h], dtype=motion.dtype)
    return identity_grid(n, h, w, motion.dtype) + motion.permute(0, 2, 3, 1) * scale


def forward(net, frame, depth, mv, jitter, history, factor):
    """The listing's ``MasterNet.forward``: ``frame [B,3,h,w]``, device ``depth``,
    ``mv`` the listing's grid [B,h,w,2], ``jitter [B,2]``, ``history`` [B,4,H,W] or
    None. ``net`` is ``torch_dlctus.Net`` (the same layers as the listing's)."""
    n, _, h, w = frame.shape
    depth = depth_to_linear(depth)
    frame_ones = torch.cat((frame, torch.ones(n, 1, h, w, dtype=frame.dtype)), 1)
    frame_bilinear = jitter_aligned_interpolation(frame_ones, jitter, factor)
    frame = torch.cat((frame, depth), 1)
    frame = jitter_align(zero_upsampling(frame, factor), jitter, factor)
    if history is None:
        history = frame_bilinear
    else:
        mv = mv - identity_grid(n, h, w, mv.dtype)
        mv = torch.movedim(mv, 3, 1)
        mv = F.interpolate(mv, scale_factor=factor, mode="bilinear", align_corners=False)
        mv = torch.movedim(mv, 1, 3)
        mv = mv + identity_grid(n, h * factor, w * factor, mv.dtype)
        history = F.grid_sample(history, mv, mode="bicubic", align_corners=False,
                                padding_mode="border")
        mask = torch.logical_or(torch.greater(mv, 1.0), torch.less(mv, -1.0))
        mask = torch.logical_or(mask[..., 0], mask[..., 1]).unsqueeze(1)
        mask = mask.expand(n, 4, h * factor, w * factor)
        history = torch.where(mask, frame_bilinear, history)
    residual = torch.clamp(net(torch.cat((frame, history), 1)), 0.0, 1.0)
    alpha = residual[:, 0:1]
    history = history * (1.0 - alpha) + frame_bilinear * alpha
    history = torch.cat((history[:, 0:3], history[:, 3:4] * residual[:, 1:2]), 1)
    history = torch.clamp(history, 0.0, 1.0)
    return history[:, :3], history


def rollout(net, color, depth, motion, jitter, reset, factor):
    """Frames [T,B,...] (NCHW, jtus's conventions): outputs and the last history. A
    reset element runs the listing's first-frame path; the others continue."""
    outs, history = [], None
    for t in range(color.shape[0]):
        mv = motion_to_listing_grid(motion[t])
        if history is None:
            out, history = forward(net, color[t], depth[t], mv, jitter[t], None, factor)
        else:
            _, cont = forward(net, color[t], depth[t], mv, jitter[t], history, factor)
            _, first = forward(net, color[t], depth[t], mv, jitter[t], None, factor)
            history = torch.where(reset[t][:, None, None, None], first, cont)
            out = history[:, :3]
        outs.append(out)
    return torch.stack(outs), history
