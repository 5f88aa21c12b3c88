"""The input frame pytree shared by every model, and its validation.

Shapes and conventions are those of ``docs/conventions.md``. A sequence of frames
is the same ``Frame`` with a leading time axis on every field (``[T,B,...]``).
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np


class Frame(NamedTuple):
    color: jax.Array   # [B,h,w,3] linear RGB at the jittered sample positions
    depth: jax.Array   # [B,h,w,1] D3D device depth in [0,1]
    motion: jax.Array  # [B,h,w,2] backward motion in LR pixels, x right, y down
    jitter: jax.Array  # [B,2] sample offset inside the LR pixel, [0,1)^2
    reset: Optional[jax.Array] = None  # [B] bool: camera cut, re-initialize history
    exposure: Optional[jax.Array] = None  # [B] > 0: pre-exposure of HDR colour (None: LDR)


_CHANNELS = {"color": 3, "depth": 1, "motion": 2}


def validate(frame: Frame, factor: int | None = None, time_major: bool = False,
             check_finite: bool = True, multiple: int = 1) -> Frame:
    """Check a frame (or a time-major sequence of frames) and raise ``ValueError``
    naming the field and what was expected.

    ``factor`` and ``multiple``: when given, the HR size ``factor * (h, w)`` must be a
    multiple of ``multiple`` (DLCTUS's network works at 1/4 of HR). ``check_finite``
    needs concrete arrays: use it at the API boundary, not inside jitted loops.
    """
    if not isinstance(frame, Frame):
        raise TypeError(f"frame: expected jtus.Frame, got {type(frame).__name__}")
    lead = 2 if time_major else 1
    what = "[T,B," if time_major else "[B,"
    color = frame.color
    if color.ndim != lead + 3 or color.shape[-1] != 3:
        raise ValueError(f"color: expected {what}h,w,3], got shape {color.shape}")
    base = color.shape[:-1]
    for name, c in _CHANNELS.items():
        arr = getattr(frame, name)
        if arr.shape != base + (c,):
            raise ValueError(f"{name}: expected shape {base + (c,)} to match color, "
                             f"got {arr.shape}")
        if not jnp.issubdtype(arr.dtype, jnp.floating):
            raise ValueError(f"{name}: expected a floating dtype, got {arr.dtype}")
    lead_shape = color.shape[:lead]
    if frame.jitter.shape != lead_shape + (2,):
        raise ValueError(f"jitter: expected shape {lead_shape + (2,)}, got {frame.jitter.shape}")
    if not jnp.issubdtype(frame.jitter.dtype, jnp.floating):
        raise ValueError(f"jitter: expected a floating dtype, got {frame.jitter.dtype}")
    if frame.reset is not None and frame.reset.shape != lead_shape:
        raise ValueError(f"reset: expected shape {lead_shape}, got {frame.reset.shape}")
    if frame.reset is not None and frame.reset.dtype != jnp.bool_:
        raise ValueError(f"reset: expected bool, got {frame.reset.dtype}")
    if frame.exposure is not None:
        if frame.exposure.shape != lead_shape:
            raise ValueError(f"exposure: expected shape {lead_shape} (one value per frame), "
                             f"got {frame.exposure.shape}")
        if not jnp.issubdtype(frame.exposure.dtype, jnp.floating):
            raise ValueError(f"exposure: expected a floating dtype, got {frame.exposure.dtype}")
    if factor is not None:
        h, w = color.shape[lead:lead + 2]
        if (factor * h) % multiple or (factor * w) % multiple:
            raise ValueError(f"color: HR size {factor * h}x{factor * w} (factor {factor} x "
                             f"{h}x{w}) must be a multiple of {multiple}")
    if check_finite:
        _check_values(frame)
    return frame


def _check_values(frame: Frame):
    """No NaN or Inf, colour >= 0, device depth in [0, 1], exposures > 0, jitter inside
    the pixel (concrete arrays only)."""
    for name in ("color", "depth", "motion", "jitter"):
        arr = np.asarray(getattr(frame, name))
        if not np.all(np.isfinite(arr)):
            bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
            raise ValueError(f"{name}: {bad} NaN or Inf values")
    if frame.exposure is not None:
        e = np.asarray(frame.exposure)
        if not np.all(np.isfinite(e) & (e > 0)):
            bad = int(np.size(e) - np.count_nonzero(np.isfinite(e) & (e > 0)))
            raise ValueError("exposure: expected finite values > 0 (the multiplier that "
                             f"pre-exposes HDR colour); {bad} are not")
    color, depth = np.asarray(frame.color), np.asarray(frame.depth)
    if np.any(color < 0):
        raise ValueError(f"color: {int(np.sum(color < 0))} negative values (expected linear "
                         "RGB >= 0)")
    if np.any((depth < 0) | (depth > 1)):
        raise ValueError(f"depth: {int(np.sum((depth < 0) | (depth > 1)))} values outside "
                         "[0, 1] (expected D3D device depth; convert others with "
                         "jtus.data.conventions.depth_to_device)")
    jit = np.asarray(frame.jitter)
    if np.any((jit < 0) | (jit >= 1)):
        raise ValueError("jitter: expected values in [0, 1) (offset inside the LR pixel); "
                         "convert centred [-0.5, 0.5) jitter with "
                         "jtus.data.conventions.jitter_to_jtus")
