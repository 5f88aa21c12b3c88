"""Arm's neural super sampling (NSS) dataset layout into jtus's HDF5 format.

The layout (``docs/nss/nss_dataset_specification.md`` in arm/neural-graphics-model-gym):
one JSON per sequence at the root (``0000.json``: ``Version``, ``TargetResolution``,
``ReverseZ``, optional ``UpscalingRatiosIndices`` and a ``Frames`` list with ``Frame``,
``CameraNearPlane``, ``CameraFarPlane``, ``Jitter`` in pixels, ``NormalizedPerRatioJitter``,
optional ``Exposure``), ground truth ``ground_truth/<seq>/<frame>.exr`` (linear HDR) and
per ratio ``x<ratio>/{color,depth,motion}/<seq>/<frame>.exr``.

Conversions (``docs/conventions.md``): motion is UV-space backward motion, y down (FSR
2's: the previous position is the current one plus the vector), scaled to LR pixels;
jitter is FSR 2's (the sample of pixel p lies at ``p + 0.5 - jitter``); depth is device
depth, reversed when ``ReverseZ``; an infinite far plane (``-1``) is stored as
``INFINITE_FAR``. The specification has no camera cuts: a frame's optional
``CameraCut`` (true) starts a new history there (a jtus extension), as does frame 0.
A sequence with ``Exposure`` on every frame is HDR (its exposure stored per frame).
"""

from __future__ import annotations

import json
import os

import h5py
import numpy as np
from tqdm import tqdm

from jtus.data import conventions, dataset
from jtus.data.exr import check_values, read_exr
from jtus.files import atomic_path

INFINITE_FAR = 1e5   # metres; what an infinite far plane (CameraFarPlane -1) becomes


def sequences(root):
    """The sequence names of an NSS dataset: the stems of its root JSON files."""
    if not os.path.isdir(root):
        raise FileNotFoundError(f"--root: {root} is not a folder")
    names = sorted(f[:-5] for f in os.listdir(root) if f.endswith(".json"))
    if not names:
        raise ValueError(f"--root: {root} has no sequence JSON files (0000.json, ...); "
                         "expected Arm's NSS layout")
    return names


def _need(d, key, where, kind=None):
    if not isinstance(d, dict) or key not in d:
        raise ValueError(f"{where}: missing {key!r}")
    v = d[key]
    if kind is not None and (not isinstance(v, kind) or isinstance(v, bool) and kind is not bool):
        raise ValueError(f"{where}.{key}: expected {getattr(kind, '__name__', kind)}, "
                         f"got {v!r}")
    return v


def _channels(path, options, what):
    """The first of ``options`` (tuples of channel names) the file has, stacked."""
    ch, _ = read_exr(path)
    for names in options:
        if all(n in ch for n in names):
            return np.stack([ch[n] for n in names], -1).astype(np.float64)
    raise ValueError(f"{path}: {what} needs channels {' or '.join(map(str, options))}; the "
                     f"file has {sorted(ch)}")


def _read_meta(root, name, factor):
    """``(where, meta, frames, reverse_z, (H, W), jitter index, LR folder)`` of one
    sequence's JSON, checked."""
    where = os.path.join(root, f"{name}.json")
    try:
        with open(where) as fh:
            meta = json.load(fh)
    except json.JSONDecodeError as e:
        raise ValueError(f"{where}: not valid JSON ({e})") from e
    frames = _need(meta, "Frames", where, list)
    if not frames:
        raise ValueError(f"{where}: Frames is empty")
    reverse_z = _need(meta, "ReverseZ", where, bool)
    res = _need(meta, "TargetResolution", where, dict)
    W, H = int(_need(res, "X", f"{where}.TargetResolution")), int(
        _need(res, "Y", f"{where}.TargetResolution"))
    if W % factor or H % factor:
        raise ValueError(f"{where}: TargetResolution {W}x{H} is not a multiple of "
                         f"factor {factor}")
    index = meta.get("UpscalingRatiosIndices", {}).get(f"x{factor}_index")
    lr = os.path.join(root, f"x{factor}")
    if not os.path.isdir(lr):
        raise ValueError(f"--factor: {root} has no x{factor}/ folder (ratios: "
                         f"{sorted(d for d in os.listdir(root) if d.startswith('x'))})")
    return where, frames, reverse_z, (H, W), index, lr


def _frame_camera(fr, fw, index, lr_size, factor):
    """``(near, far, jitter in LR pixels, FSR 2's convention)`` of one frame's entry."""
    near = float(_need(fr, "CameraNearPlane", fw))
    far = float(_need(fr, "CameraFarPlane", fw))
    far = INFINITE_FAR if far == -1.0 else far
    if not 0 < near < far:
        raise ValueError(f"{fw}: expected 0 < CameraNearPlane < CameraFarPlane, got "
                         f"{near}, {far}")
    h, w = lr_size
    if index is not None:
        nj = _need(fr, "NormalizedPerRatioJitter", fw, list)
        if not 0 <= index < len(nj):
            raise ValueError(f"{fw}.NormalizedPerRatioJitter: no entry {index} "
                             f"(x{factor}_index)")
        e = nj[index]
        j = (np.array([e["X"], e["Y"]], float) if isinstance(e, dict)
             else np.asarray(e, float)) * [w, h]
    else:
        e = _need(fr, "Jitter", fw, dict)
        j = np.array([_need(e, "X", f"{fw}.Jitter"), _need(e, "Y", f"{fw}.Jitter")], float)
    return near, far, j


def _frame_images(files, fw, factor, lr_size, hr_size, reverse_z, near, far):
    """``(colour, device depth, motion in jtus's convention, target)`` of one frame,
    each image's size and values checked."""
    for k, path in files.items():
        if not os.path.exists(path):
            raise ValueError(f"{fw}: {k} image {path} is missing")
    color = _channels(files["color"], [("R", "G", "B")], "color")
    target = _channels(files["target"], [("R", "G", "B")], "ground truth")
    depth = _channels(files["depth"], [("R",), ("Y",), ("Z",), ("D",)], "depth")
    motion = _channels(files["motion"], [("R", "G"), ("X", "Y"), ("U", "V")], "motion")
    for k, v, shape in (("color", color, lr_size), ("depth", depth, lr_size),
                        ("motion", motion, lr_size), ("target", target, hr_size)):
        if v.shape[:2] != shape:
            raise ValueError(f"{files[k]}: size {v.shape[0]}x{v.shape[1]}, expected "
                             f"{shape[0]}x{shape[1]} (TargetResolution / {factor})")
    check_values(files["color"], "color", color, lo=0.0)
    check_values(files["target"], "ground truth", target, lo=0.0)
    check_values(files["depth"], "depth", depth, lo=0.0)
    check_values(files["motion"], "motion", motion)
    depth = conventions.depth_to_device(depth, "reversed" if reverse_z else "device",
                                        near, far)
    if depth.max() > 1.0:
        raise ValueError(f"{files['depth']}: device depth above 1 (max {depth.max():.4g})")
    h, w = lr_size
    return color, depth, conventions.motion_to_jtus(motion, w, h, "uv"), target


def load_sequence(root, name, factor):
    """One NSS sequence as a ``jtus.sim.video`` dict at ``factor`` (plus ``near``,
    ``far``), every value checked and converted before anything is written."""
    where, frames, reverse_z, (H, W), index, lr = _read_meta(root, name, factor)
    h, w = H // factor, W // factor
    cols = {k: [] for k in ("color", "depth", "motion", "target")}
    jit, exposure, reset, planes = [], [], [], []
    for t, fr in enumerate(frames):
        fw = f"{where}: Frames[{t}]"
        stem = f"{int(_need(fr, 'Frame', fw)):04d}.exr"
        near, far, j = _frame_camera(fr, fw, index, (h, w), factor)
        planes.append((near, far))
        jit.append(j)
        exposure.append(fr.get("Exposure"))
        reset.append(t == 0 or bool(fr.get("CameraCut", False)))
        files = {k: os.path.join(lr, k, name, stem) for k in ("color", "depth", "motion")}
        files["target"] = os.path.join(root, "ground_truth", name, stem)
        for k, v in zip(("color", "depth", "motion", "target"), _frame_images(
                files, fw, factor, (h, w), (H, W), reverse_z, near, far)):
            cols[k].append(v)
    given = [e is not None for e in exposure]
    if any(given) and not all(given):
        raise ValueError(f"{where}: Exposure on {sum(given)} of {len(given)} frames; give it on "
                         "every frame or none")
    jitter = conventions.jitter_to_jtus(np.stack(jit), "fsr2")
    if not np.all(np.isfinite(jitter) & (jitter >= 0) & (jitter < 1)):
        raise ValueError(f"{where}: jitter outside the pixel after conversion (FSR 2 "
                         f"offsets in [-0.5, 0.5) expected; min {np.nanmin(jitter):.4g}, "
                         f"max {np.nanmax(jitter):.4g})")
    out = {"reset": np.array(reset), "target": np.stack(cols["target"]).astype(np.float32),
           f"x{factor}": {k: np.stack(cols[k]).astype(np.float32)
                          for k in ("color", "depth", "motion")},
           "near": planes[0][0], "far": planes[0][1]}
    out[f"x{factor}"]["jitter"] = jitter.astype(np.float32)
    if all(given):
        e = np.asarray(exposure, float)
        if not np.all(np.isfinite(e) & (e > 0)):
            raise ValueError(f"{where}: Exposure must be finite and > 0, got min {e.min():.4g}")
        out["exposure"] = e.astype(np.float32)
    return out


def import_nss(root, factor, out, split="test", names=None, progress=True):
    """Every sequence (or ``names``) of the NSS dataset at ``root`` into one jtus HDF5
    dataset ``out`` (split ``split``, videos named after the sequences), atomically:
    all sequences are read and checked before the file is written."""

    if split not in dataset.SPLITS:
        raise ValueError(f"--split: expected one of {dataset.SPLITS}, got {split!r}")
    names = sequences(root) if names is None else list(names)
    videos = [load_sequence(root, n, factor)
              for n in tqdm(names, desc=f"read {root}", disable=not progress)]
    sizes = {v["target"].shape[1:3] for v in videos}
    if len(sizes) > 1:
        raise ValueError(f"--root: sequences of different sizes {sorted(sizes)}; import "
                         "them into separate datasets")
    H, W = sizes.pop()
    with atomic_path(out) as tmp, h5py.File(tmp, "w") as fh:
        dataset.write_root_attrs(fh, (H, W), (factor,), spp=0, spp_match=1)
        for n, v in zip(names, videos):
            g = fh.create_group(f"{split}/{n}")
            g.attrs.update({"scene": f"nss:{os.path.abspath(root)}/{n}", "effects": "[]",
                            "length": len(v["reset"]), "index": 0, "near": v["near"],
                            "far": v["far"]})
            dataset.write_video(g, v, (factor,), 1)
    return out
