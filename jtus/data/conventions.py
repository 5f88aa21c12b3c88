"""Conversions between the conventions users bring and jtus's own.

jtus's conventions (``docs/conventions.md``), used everywhere past the data edge:

- pixel (row i, col j) has its centre at (j + 0.5, i + 0.5); x right, y down;
- ``motion``: backward vectors in input (LR) pixels, x right, y down: the surface
  under pixel p was at p + motion in the previous frame;
- ``jitter``: the sample's offset inside its LR pixel in [0,1)^2, x right, y down;
- ``depth``: D3D-style device depth in [0,1] (0 near, 1 far, not reversed).

Call these when importing data (EXR sequences, other engines), never inside models.
"""

from __future__ import annotations

import numpy as np

# the clip planes every jtus scene, model and import assumes unless told otherwise
# (device depth is D3D's far/(far-near) (1 - near/z)); datasets record theirs
NEAR, FAR = 0.1, 100.0

MOTION_UNITS = ("pixels", "uv", "ndc")
DEPTH_KINDS = ("device", "reversed", "linear", "view")
JITTER_KINDS = ("unit", "centered", "fsr2", "arm")


def motion_to_jtus(motion, width, height, units="pixels", y_up=False, negate=False):
    """Bring motion vectors ``[..., 2]`` into jtus's convention.

    ``units``: ``pixels`` (of this image), ``uv`` (fractions of the image size,
    [0,1] across), ``ndc`` ([-1,1] across). ``y_up``: the source's y axis points up
    (Blender, OpenGL NDC). ``negate``: the source stores previous-to-current
    displacement (current position minus previous), the opposite of jtus's.
    """
    if units not in MOTION_UNITS:
        raise ValueError(f"units: expected one of {MOTION_UNITS}, got {units!r}")
    mv = np.asarray(motion, dtype=np.float64)
    if mv.shape[-1] != 2:
        raise ValueError(f"motion: expected a last axis of 2 (x, y), got shape {mv.shape}")
    scale = {"pixels": np.array([1.0, 1.0]), "uv": np.array([width, height], float),
             "ndc": np.array([width, height], float) / 2}[units]
    sign = np.array([1.0, -1.0 if y_up else 1.0]) * (-1.0 if negate else 1.0)
    return mv * scale * sign


def jitter_to_jtus(jitter, kind="unit", y_up=False):
    """Bring jitter offsets ``[..., 2]`` (in pixels) into [0,1)^2, x right, y down.

    ``kind``: ``unit`` (already in [0,1), 0.5 is the centre), ``centered`` (the
    sample's offset from the pixel centre, in [-0.5, 0.5)), ``fsr2`` (the offset FSR 2 is
    given: the renderer shifts the projection by it, and the sample of pixel p lies at
    ``p + 0.5 - jitter``, FSR 2's ``ComputeHrPosFromLrPos``) or ``arm`` (Arm's NSS
    datasets: the sample of pixel p lies at ``p + 0.5 + jitter``, as Arm's
    ``generate_lr_to_hr_lut`` places it, ``docs/data.md``).
    """
    if kind not in JITTER_KINDS:
        raise ValueError(f"kind: expected one of {JITTER_KINDS}, got {kind!r}")
    j = np.asarray(jitter, dtype=np.float64)
    if kind == "centered":
        j = j + 0.5
    elif kind == "fsr2":
        j = 0.5 - j
    elif kind == "arm":
        j = 0.5 + j
    if y_up:
        j = j * np.array([1.0, -1.0]) + np.array([0.0, 1.0])
        # y up 0 (the pixel's bottom edge) is y down 1: the same edge, kept inside [0,1)
        j[..., 1] = np.where(j[..., 1] == 1.0, np.nextafter(1.0, 0.0), j[..., 1])
    return j


def depth_to_device(depth, kind, near, far):
    """Bring depth into D3D device depth in [0,1] (not reversed) for planes near/far.

    ``kind``: ``device`` (unchanged), ``reversed`` (reversed-Z device depth, 1 at the
    near plane), ``linear`` ((z - near) / (far - near)), ``view`` (view-space distance z
    along the axis, in scene units).
    """
    if kind not in DEPTH_KINDS:
        raise ValueError(f"kind: expected one of {DEPTH_KINDS}, got {kind!r}")
    _check_planes(near, far)
    d = np.asarray(depth, dtype=np.float64)
    if kind == "device":
        return d
    if kind == "reversed":
        return 1.0 - d
    z = near + d * (far - near) if kind == "linear" else d
    return far / (far - near) * (1.0 - near / z)


def _check_planes(near, far):
    if not (0 < near < far):
        raise ValueError(f"near/far: expected 0 < near < far, got near={near}, far={far}")


def view_depth(device, near, far):
    """Inverse of the D3D projection: view-space z from device depth (array-generic)."""
    _check_planes(near, far)
    return near * far / (far - device * (far - near))


def linearize_depth(device, near, far):
    """Device depth -> linear depth (z - near) / (far - near) in [0, 1]; works on numpy
    and JAX arrays. This is the depth channel the networks see."""
    return (view_depth(device, near, far) - near) / (far - near)
