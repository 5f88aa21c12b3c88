"""Arm's neural super sampling (NSS) dataset layout into jtus's HDF5 format, read as
Arm's own reader reads it (``docs/data.md``, "NSS", cites each point to its file).

The layout (``docs/nss/nss_dataset_specification.md`` in arm/neural-graphics-model-gym):
one JSON per sequence at the root (``0000.json``: ``TargetResolution``, optional
``ReverseZ``, ``UpscalingRatiosIndices`` and a ``Frames`` list with
``CameraNearPlane``, ``CameraFarPlane``, ``NormalizedPerRatioJitter``, optional
``Exposure`` and ``CameraCut``), ground truth ``ground_truth/<seq>/*.exr``, full-resolution
motion ``motion_gt/<seq>/*.exr`` and per ratio ``x<ratio>/{color,depth,motion}/<seq>/*.exr``.

As Arm's reader (``scripts/safetensors_generator/dataset_readers/nss_exr_dataset_reader.py``):
each folder's EXR files are taken in sorted order and paired with ``Frames`` by
position (file names are not read), as many frames as the shortest folder holds; the
ground truth is stored Karis tone-mapped and is brought back to linear
(``truth="karis"``, Arm's default; ``truth="linear"`` is its ``--linear_truth``); the
jitter places the sample of LR pixel p at ``p + 0.5 + jitter`` (``conventions.jitter_to_jtus``
kind ``arm``); an infinite far plane (``-1``) becomes 5000; ``motion_gt`` must be there
and is checked (size, finite values) but not stored: jtus's format carries LR motion.
Motion is UV-space backward motion, y down, scaled to LR pixels; depth is device
depth, reversed when ``ReverseZ``. Frame 0 and every ``CameraCut`` (true) start a
new history. A sequence with ``Exposure`` on every frame is HDR.
"""

from __future__ import annotations

import json
import os
import pathlib

import h5py
import numpy as np
from tqdm import tqdm

from jtus.data import conventions, dataset
from jtus.data.exr import check_values, read_exr
from jtus.files import atomic_path, drop_unknown_keys

INFINITE_FAR = 5000.0  # what an infinite far plane (CameraFarPlane -1) becomes, as in Arm's reader
TRUTHS = ("karis", "linear")  # how the ground truth EXRs are stored
HDR_MAX = 65504.0  # Arm's clamp of the tone-mapped truth before its inverse


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


def _number(d, key, where, default=None):
    """A finite JSON number (not a bool, string or null) at ``d[key]``."""
    if default is not None and key not in d:
        return default
    v = _need(d, key, where)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise ValueError(f"{where}.{key}: expected a finite number, got {v!r}")
    return float(v)


def _channels(path, options, what):
    """The first of ``options`` (tuples of channel names) the file has, stacked."""
    ch, _ = read_exr(path)
    for names in options:
        if all(n in ch for n in names):
            return np.stack([ch[n] for n in names], -1).astype(np.float64)
    raise ValueError(f"{path}: {what} needs channels {' or '.join(map(str, options))}; the "
                     f"file has {sorted(ch)}")


FOLDERS = ("color", "depth", "motion", "motion_gt", "target")


def _files(root, name, factor):
    """Each folder's EXR files of one sequence, sorted as Arm's reader sorts them
    (``sorted(Path.rglob("*.exr"))``)."""
    dirs = {k: os.path.join(root, f"x{factor}", k, name) for k in ("color", "depth", "motion")}
    dirs["motion_gt"] = os.path.join(root, "motion_gt", name)
    dirs["target"] = os.path.join(root, "ground_truth", name)
    out = {}
    for k, d in dirs.items():
        files = sorted(p for p in pathlib.Path(d).rglob("*.exr") if p.is_file()) \
            if os.path.isdir(d) else []
        if not files:
            raise ValueError(f"{d}: missing or holds no .exr files (the NSS layout needs "
                             f"{k} frames there)")
        out[k] = [str(p) for p in files]
    return out


# Arm's specification (docs/nss/nss_dataset_specification.md, "Metadata") and the keys
# Arm's reader also takes (NearPlane / FarPlane, QuantisedPerRatioJitter, CameraCut)
SEQUENCE_KEYS = ("Version", "EmulatedFramerate", "TargetResolution", "Samples", "Frames",
                 "ReverseZ", "OpaqueOnlyColor_Exported", "UnjitteredSrcColor_Exported",
                 "UpscalingRatiosIndices", "MotionVectorsDilated", "NearPlane", "FarPlane")
FRAME_KEYS = ("Frame", "FovX", "FovY", "CameraNearPlane", "CameraFarPlane", "ViewProjection",
              "Jitter", "NormalizedPerRatioJitter", "QuantisedPerRatioJitter", "Exposure",
              "CameraCut")


def _warn_unknown(where, meta, frames):
    """One ``UnknownKeyWarning`` per key that neither Arm's specification nor its reader
    defines: in the sequence object, and in the frames (once per key, naming the first
    frame that has it). Such keys are not read."""
    drop_unknown_keys(where, meta, SEQUENCE_KEYS)
    seen = set(FRAME_KEYS)
    for t, fr in enumerate(frames):
        new = [k for k in (fr if isinstance(fr, dict) else ()) if k not in seen]
        if new:
            drop_unknown_keys(f"{where}.Frames[{t}]", dict.fromkeys(new), FRAME_KEYS)
            seen.update(new)


def _read_meta(root, name, factor):
    """``(where, frames, reverse_z, (H, W), jitter index)`` of one sequence's JSON,
    checked."""
    where = os.path.join(root, f"{name}.json")
    try:
        with open(where, encoding="utf-8") as fh:
            meta = json.load(fh)
    except UnicodeDecodeError as e:
        raise ValueError(f"{where}: not UTF-8 text ({e})") from e
    except json.JSONDecodeError as e:
        raise ValueError(f"{where}: not valid JSON ({e})") from e
    if not isinstance(meta, dict):
        raise ValueError(f"{where}: expected a JSON object, got {type(meta).__name__}")
    frames = _need(meta, "Frames", where, list)
    if not frames:
        raise ValueError(f"{where}: Frames is empty")
    _warn_unknown(where, meta, frames)
    reverse_z = meta.get("ReverseZ", False)  # Arm's reader: metadata.get("ReverseZ", False)
    if not isinstance(reverse_z, bool):
        raise ValueError(f"{where}.ReverseZ: expected true or false, got {reverse_z!r}")
    res = _need(meta, "TargetResolution", where, dict)
    W, H = (_number(res, k, f"{where}.TargetResolution") for k in ("X", "Y"))
    if W != int(W) or H != int(H) or W < 1 or H < 1:
        raise ValueError(f"{where}.TargetResolution: expected positive integers, got {W}x{H}")
    W, H = int(W), int(H)
    if W % factor or H % factor:
        raise ValueError(f"{where}: TargetResolution {W}x{H} is not a multiple of "
                         f"factor {factor}")
    if not os.path.isdir(os.path.join(root, f"x{factor}")):
        raise ValueError(f"--factor: {root} has no x{factor}/ folder (ratios: "
                         f"{sorted(d for d in os.listdir(root) if d.startswith('x'))})")
    ratios = _need(meta, "UpscalingRatiosIndices", where, dict)
    index = _need(ratios, f"x{factor}_index", f"{where}.UpscalingRatiosIndices", int)
    planes = {k: meta[k] for k in ("NearPlane", "FarPlane") if k in meta}
    return where, frames, reverse_z, (H, W), index, planes


def _frame_camera(fr, fw, index, lr_size, planes):
    """``(near, far, jitter in LR pixels, Arm's sign)`` of one frame's entry; the
    sequence's ``NearPlane`` / ``FarPlane`` stand in for missing per-frame planes, as in
    Arm's reader."""
    if not isinstance(fr, dict):
        raise ValueError(f"{fw}: expected a JSON object, got {fr!r}")
    fr = dict(fr)
    for key, seq in (("CameraNearPlane", "NearPlane"), ("CameraFarPlane", "FarPlane")):
        if fr.get(key) is None and planes.get(seq) is not None:
            fr[key] = planes[seq]
    near, far = _number(fr, "CameraNearPlane", fw), _number(fr, "CameraFarPlane", fw)
    far = INFINITE_FAR if far == -1.0 else far
    if not 0 < near < far:
        raise ValueError(f"{fw}: expected 0 < CameraNearPlane < CameraFarPlane, got "
                         f"{near}, {far}")
    key = ("NormalizedPerRatioJitter" if "NormalizedPerRatioJitter" in fr
           else "QuantisedPerRatioJitter")
    nj = _need(fr, key if key in fr else "NormalizedPerRatioJitter", fw, list)
    if not 0 <= index < len(nj):
        raise ValueError(f"{fw}.{key}: no entry {index} (UpscalingRatiosIndices)")
    e = nj[index]
    ew = f"{fw}.{key}[{index}]"
    if not isinstance(e, dict):
        raise ValueError(f"{ew}: expected an object with X and Y, got {e!r}")
    h, w = lr_size
    return near, far, np.array([_number(e, "X", ew) * w, _number(e, "Y", ew) * h])


def _karis_inverse(x):
    """Arm's ``tonemap_inverse(x, mode="karis")``: ``x / (1 - max(r, g, b))`` after
    clamping into ``[0, karis(HDR_MAX)]``."""
    x = np.clip(x, 0.0, HDR_MAX / (1.0 + HDR_MAX))
    return x / (1.0 - x.max(-1, keepdims=True))


def _frame_images(files, fw, lr_size, hr_size, reverse_z, near, far, truth):
    """``(colour, device depth, motion in jtus's convention, target)`` of one frame,
    each image's size and values checked (``motion_gt`` too)."""
    color = _channels(files["color"], [("R", "G", "B")], "color")
    target = _channels(files["target"], [("R", "G", "B")], "ground truth")
    depth = _channels(files["depth"], [("R",), ("Y",), ("Z",), ("D",)], "depth")
    motion = _channels(files["motion"], [("R", "G"), ("X", "Y"), ("U", "V")], "motion")
    motion_gt = _channels(files["motion_gt"], [("R", "G"), ("X", "Y"), ("U", "V")],
                          "motion_gt")
    for k, v, shape in (("color", color, lr_size), ("depth", depth, lr_size),
                        ("motion", motion, lr_size), ("target", target, hr_size),
                        ("motion_gt", motion_gt, hr_size)):
        if v.shape[:2] != shape:
            raise ValueError(f"{files[k]}: size {v.shape[0]}x{v.shape[1]}, expected "
                             f"{shape[0]}x{shape[1]} ({fw})")
    check_values(files["color"], "color (stored as float16)", color, lo=0.0,
                 hi=dataset.COLOR_MAX)
    check_values(files["target"], "ground truth", target, lo=0.0)
    check_values(files["depth"], "depth", depth, lo=0.0)
    check_values(files["motion"], "motion", motion)
    check_values(files["motion_gt"], "motion_gt", motion_gt)
    if truth == "karis":
        if target.max() >= 1.0:
            raise ValueError(f"{files['target']}: ground truth reaches {target.max():.4g}, "
                             "but a Karis tone-mapped truth lies in [0, 1); if it is linear, "
                             "pass --linear-truth")
        target = _karis_inverse(target)
    check_values(files["target"], "ground truth (linear, stored as float16)", target,
                 hi=dataset.COLOR_MAX)
    depth = conventions.depth_to_device(depth, "reversed" if reverse_z else "device",
                                        near, far)
    if depth.max() > 1.0:
        raise ValueError(f"{files['depth']}: device depth above 1 (max {depth.max():.4g})")
    h, w = lr_size
    return color, depth, conventions.motion_to_jtus(motion, w, h, "uv"), target


def _camera_cut(fr, fw):
    cut = fr.get("CameraCut", False)
    if not isinstance(cut, bool):
        raise ValueError(f"{fw}.CameraCut: expected true or false, got {cut!r}")
    return cut


def load_sequence(root, name, factor, truth="karis"):
    """One NSS sequence as a ``jtus.sim.video`` dict at ``factor`` (plus ``near``,
    ``far``), every value checked and converted before anything is written."""
    if truth not in TRUTHS:
        raise ValueError(f"truth: expected one of {TRUTHS}, got {truth!r}")
    where, frames, reverse_z, (H, W), index, planes = _read_meta(root, name, factor)
    files = _files(root, name, factor)
    n = min(len(v) for v in files.values())
    for k, v in files.items():
        if len(v) != n or len(v) != len(files["target"]):
            counts = ", ".join(f"{os.path.dirname(p[0])} holds {len(p)} .exr files"
                               for p in files.values())
            raise ValueError(f"{where}: the frame folders differ ({counts}); Arm's reader "
                             "would pair files by position and drop the extra ones, which "
                             "shifts frames silently: give every folder the same frames")
    if len(frames) < n:
        raise ValueError(f"{where}: Frames lists {len(frames)} frames, the image folders hold "
                         f"{n} (Arm's reader pairs them by position)")
    h, w = H // factor, W // factor
    cols = {k: [] for k in ("color", "depth", "motion", "target")}
    jit, exposure, reset, planes_t = [], [], [], []
    for t in range(n):
        fw = f"{where}: Frames[{t}]"
        near, far, j = _frame_camera(frames[t], fw, index, (h, w), planes)
        planes_t.append((near, far))
        jit.append(j)
        exposure.append(None if "Exposure" not in frames[t]
                        else _number(frames[t], "Exposure", fw))
        reset.append(t == 0 or _camera_cut(frames[t], fw))
        for k, v in zip(("color", "depth", "motion", "target"), _frame_images(
                {k: files[k][t] for k in FOLDERS}, fw, (h, w), (H, W), reverse_z, near,
                far, truth)):
            cols[k].append(v)
    return _assemble(where, cols, jit, exposure, reset, planes_t, factor)


def _assemble(where, cols, jit, exposure, reset, planes, factor):
    given = [e is not None for e in exposure]
    if any(given) and not all(given):
        raise ValueError(f"{where}: Exposure on {sum(given)} of {len(given)} frames; give it on "
                         "every frame or none")
    jitter = conventions.jitter_to_jtus(np.stack(jit), "arm")
    if not np.all(np.isfinite(jitter) & (jitter >= 0) & (jitter < 1)):
        raise ValueError(f"{where}: jitter outside the pixel after conversion (offsets in "
                         f"[-0.5, 0.5) expected; min {np.nanmin(jitter):.4g}, "
                         f"max {np.nanmax(jitter):.4g})")
    out = {"reset": np.array(reset), "target": np.stack(cols["target"]).astype(np.float32),
           f"x{factor}": {k: np.stack(cols[k]).astype(np.float32)
                          for k in ("color", "depth", "motion")},
           "near": planes[0][0], "far": planes[0][1]}
    out[f"x{factor}"]["jitter"] = jitter.astype(np.float32)
    if all(given):
        e = np.asarray(exposure, float)
        if not np.all(e > 0):
            raise ValueError(f"{where}: Exposure must be > 0, got min {e.min():.4g}")
        out["exposure"] = e.astype(np.float32)
    return out


def budget(root, factor, names=None):
    """``(memory, disk)`` bytes of ``import_nss``, from each sequence's JSON and its
    frame count before any pixel is read: every sequence is held as float32 (input
    colour, depth and motion; target colour) until the file is written, the largest
    twice while it is stacked; the dataset stores colours as float16, depth and motion
    as float32."""
    names = sequences(root) if names is None else list(names)
    memory = disk = peak = 0
    for name in names:
        _, _, _, (H, W), _, _ = _read_meta(root, name, factor)
        n = len(_files(root, name, factor)["color"])
        lr_px, hr_px = (H // factor) * (W // factor), H * W
        held = n * (lr_px * 6 * 4 + hr_px * 3 * 4)
        memory, peak = memory + held, max(peak, held)
        disk += n * (lr_px * (3 * 2 + 3 * 4) + hr_px * 3 * 2)
    return memory + peak, disk


def import_nss(root, factor, out, split="test", names=None, progress=True, truth="karis"):
    """Every sequence (or ``names``) of the NSS dataset at ``root`` into one jtus HDF5
    dataset ``out`` (split ``split``, videos named after the sequences), atomically:
    all sequences are read and checked before the file is written."""

    if split not in dataset.SPLITS:
        raise ValueError(f"--split: expected one of {dataset.SPLITS}, got {split!r}")
    names = sequences(root) if names is None else list(names)
    videos = [load_sequence(root, n, factor, truth)
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
