"""Helpers to call PyTorch references on NHWC numpy arrays (tests only)."""

import numpy as np
import torch
import torch.nn.functional as F


def to_nchw(x):
    return torch.from_numpy(np.ascontiguousarray(np.asarray(x).transpose(0, 3, 1, 2)))


def to_nhwc(t):
    return t.detach().numpy().transpose(0, 2, 3, 1)


def grid_sample(image, grid, mode, align_corners=False):
    out = F.grid_sample(to_nchw(image), torch.from_numpy(np.asarray(grid)), mode=mode,
                        padding_mode="border", align_corners=align_corners)
    return to_nhwc(out)


def interpolate_bilinear(x, factor):
    return to_nhwc(F.interpolate(to_nchw(x), scale_factor=factor, mode="bilinear",
                                 align_corners=False))


def interpolate_bicubic(x, factor):
    """Keys a=-0.75, indices clamped at the border (PyTorch's upsample_bicubic2d)."""
    return to_nhwc(F.interpolate(to_nchw(x), scale_factor=factor, mode="bicubic",
                                 align_corners=False))
