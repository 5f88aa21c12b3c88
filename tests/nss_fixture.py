"""A small dataset in Arm's NSS layout, written from the specification's text alone
(``docs/nss/nss_dataset_specification.md`` and ``nss_data_capture_guide.md`` in
arm/neural-graphics-model-gym), with numpy and OpenEXR only: nothing of jtus is used,
so that the importer is checked against an independent reading of the format.

The scene is an analytic image ``radiance(u, v)`` (u, v in [0, 1] across the frame).
Per frame:

- ``ground_truth``: the image at the full-resolution pixel centres, stored Karis
  tone-mapped (``c / (1 + max(r, g, b))``), as Arm's captures are;
- ``x<f>/color``: one point sample per low-resolution pixel, at
  ``GetTexCoord(idx) + _Jitter.xy``: pixel ``p``'s centre plus the jitter, i.e.
  ``(p + 0.5 + J) / size``, with ``J = NormalizedPerRatioJitter * size`` in pixels;
- ``x<f>/depth`` a constant, ``x<f>/motion`` and ``motion_gt`` zero (a still camera);
- files numbered from 1 (``0001.exr`` ...): Arm's reader takes them in sorted order.

``jau_reference`` computes, from the same convention, what jitter-aligned bilinear
up-sampling must give: each output pixel interpolates the four low-resolution samples
around it, where sample ``p`` lies at ``p + 0.5 + J``.

    python tests/nss_fixture.py OUT_FOLDER   # writes the dataset, prints its frames
"""

from __future__ import annotations

import json
import os
import sys

import numpy as np
import OpenEXR

H, W, T = 24, 32, 5
FACTORS = (2, 4)


def radiance(u, v):
    """Linear RGB of the analytic scene at ``u, v`` (arrays), up to about 3."""
    r = 1.2 + np.sin(2 * np.pi * (2.0 * u + 0.5 * v))
    g = 1.0 + 0.9 * np.cos(2 * np.pi * (1.5 * v - 0.7 * u) + 0.3)
    b = 0.8 + 0.6 * np.sin(2 * np.pi * (2.5 * u * v + 0.2))
    return np.stack([r, g, b], -1)


def jitters(factor, frames=T, seed=5):
    """Per frame, the offsets J in low-resolution pixels, each in [-0.5, 0.5)."""
    return np.random.default_rng(seed + factor).uniform(-0.5, 0.5, (frames, 2))


def _write(path, channels):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {k: np.ascontiguousarray(v, np.float32)
                               for k, v in channels.items()}) as f:
        f.write(path)


def lr_samples(factor, j):
    """The low-resolution colour: one sample per pixel at ``(p + 0.5 + J) / size``."""
    h, w = H // factor, W // factor
    x = (np.arange(w) + 0.5 + j[0]) / w
    y = (np.arange(h) + 0.5 + j[1]) / h
    return radiance(x[None, :], y[:, None])


def jau_reference(factor, j):
    """Jitter-aligned bilinear up-sampling of ``lr_samples(factor, j)``, from Arm's
    convention: output pixel X (centre at (X + 0.5) / factor in low-resolution pixels)
    reads between the samples around it, sample p lying at p + 0.5 + J; the border
    sample is repeated beyond the edge."""
    img = lr_samples(factor, j)
    h, w = img.shape[:2]

    def taps(n_out, n_in, jj):
        pos = (np.arange(n_out) + 0.5) / factor - 0.5 - jj   # in sample indices
        i0 = np.floor(pos).astype(int)
        t = pos - i0
        return np.clip(i0, 0, n_in - 1), np.clip(i0 + 1, 0, n_in - 1), t

    x0, x1, tx = taps(W, w, j[0])
    y0, y1, ty = taps(H, h, j[1])
    top = img[y0][:, x0] * (1 - tx)[None, :, None] + img[y0][:, x1] * tx[None, :, None]
    bot = img[y1][:, x0] * (1 - tx)[None, :, None] + img[y1][:, x1] * tx[None, :, None]
    return top * (1 - ty)[:, None, None] + bot * ty[:, None, None]


def write_dataset(root, name="0000"):
    """The NSS layout under ``root``; returns ``{factor: jitters [T,2]}``."""
    v, u = np.meshgrid((np.arange(H) + 0.5) / H, (np.arange(W) + 0.5) / W, indexing="ij")
    truth = radiance(u, v)
    truth = truth / (1 + truth.max(-1, keepdims=True))  # Karis tone map
    zero_hr = np.zeros((H, W), np.float32)
    used = {f: jitters(f) for f in FACTORS}
    frames = []
    for t in range(T):
        stem = f"{t + 1:04d}.exr"
        _write(os.path.join(root, "ground_truth", name, stem),
               {"R": truth[..., 0], "G": truth[..., 1], "B": truth[..., 2]})
        _write(os.path.join(root, "motion_gt", name, stem), {"R": zero_hr, "G": zero_hr})
        for f in FACTORS:
            c = lr_samples(f, used[f][t])
            lr = os.path.join(root, f"x{f}")
            zero = np.zeros(c.shape[:2], np.float32)
            _write(os.path.join(lr, "color", name, stem),
                   {"R": c[..., 0], "G": c[..., 1], "B": c[..., 2]})
            _write(os.path.join(lr, "depth", name, stem), {"R": zero + 0.5})
            _write(os.path.join(lr, "motion", name, stem), {"R": zero, "G": zero})
        per_ratio = [{"X": float(used[f][t][0]) / (W // f),
                      "Y": float(used[f][t][1]) / (H // f)} for f in FACTORS]
        frames.append({"Frame": t + 1, "CameraNearPlane": 0.1, "CameraFarPlane": -1,
                       "FovX": 1.2, "FovY": 0.9, "ViewProjection": [0.0] * 16,
                       "NormalizedPerRatioJitter": per_ratio})
    meta = {"Version": "1.0.1", "EmulatedFramerate": 60,
            "TargetResolution": {"X": W, "Y": H}, "ReverseZ": False,
            "Samples": {"Count": 16},
            "UpscalingRatiosIndices": {f"x{f}_index": i for i, f in enumerate(FACTORS)},
            "Frames": frames}
    with open(os.path.join(root, f"{name}.json"), "w") as fh:
        json.dump(meta, fh, indent=1)
    return used


if __name__ == "__main__":
    out = sys.argv[1]
    for f, j in write_dataset(out).items():
        print(f"x{f}: jitter (pixels) per frame {j.round(3).tolist()}")
