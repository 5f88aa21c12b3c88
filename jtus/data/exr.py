"""EXR in and out: per-frame EXR sequences from external renderers to the HDF5 layout,
and any sequence back to EXR or PNG.

Facts of OpenEXR's Python bindings this module respects: arrays must be
C-contiguous or they are silently written wrong (``mv[..., 0]``, ``rgb[..., ::-1]``),
a multi-component array under one key becomes three channels, header and pixels must
be copied inside the ``with`` block, and channels are stored alphabetically (read them
by name).

Conventions are converted here, once (``jtus.data.conventions``).
"""

from __future__ import annotations

import dataclasses
import os
import re
import shutil
import tempfile

import h5py
import numpy as np
import OpenEXR
from PIL import Image

from jtus.data import conventions, dataset
from jtus.data.conventions import FAR, NEAR
from jtus.files import atomic_path, check_out_folder, read_json_fields
from jtus.sampling import jitter_sequence

IMAGE_FORMATS = ("exr", "png")


def write_exr(path, channels, half=False):
    """Write ``{name: [H,W] array}`` as one EXR part (ZIP compression)."""

    arrays = {}
    shape = None
    for name, a in channels.items():
        a = np.asarray(a)
        if a.ndim != 2:
            raise ValueError(f"channel {name!r}: expected a 2-D array, got shape {a.shape}")
        if shape is not None and a.shape != shape:
            raise ValueError(f"channel {name!r}: shape {a.shape} differs from {shape}")
        shape = a.shape
        arrays[name] = np.ascontiguousarray(a, dtype=np.float16 if half else np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, arrays) as f:
        f.write(os.fspath(path))


def read_exr(path):
    """``({name: float32 [H,W]}, header dict)``; clear errors for missing or corrupt files."""

    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such EXR file")
    try:
        with OpenEXR.File(path, separate_channels=True) as f:
            header = dict(f.header())
            chans = {k: np.array(v.pixels, dtype=np.float32) for k, v in f.channels().items()}
    except Exception as e:  # OpenEXR raises several types for damaged files
        raise ValueError(f"{path}: not a readable EXR file ({e})") from e
    return chans, header


def _pick(chans, names, path, field):
    missing = [n for n in names if n not in chans]
    if missing:
        raise ValueError(f"{path}: {field} needs channels {missing}, which are missing; the "
                         f"file has {sorted(chans)}")
    return np.stack([chans[n] for n in names], -1)


@dataclasses.dataclass(frozen=True)
class ImportSpec:
    """How to read an external renderer's EXR sequence (also loadable from a JSON
    sidecar with these keys)."""
    color: tuple = ("R", "G", "B")
    depth: str = "Z"
    motion: tuple = ("motion.X", "motion.Y")
    target_color: tuple = ("R", "G", "B")
    motion_units: str = "pixels"     # pixels | uv | ndc
    motion_y_up: bool = False
    motion_negate: bool = False      # the source stores current minus previous position
    depth_kind: str = "device"       # device | reversed | linear | view
    near: float = NEAR
    far: float = FAR
    jitter: object = "thesis"        # "thesis", a list of [x, y] per frame, or one [x, y]
    jitter_kind: str = "unit"        # unit [0,1) | centered [-0.5, 0.5) | fsr2 (centre - j)
    jitter_y_up: bool = False
    exposure: object = None          # HDR: one number, or one per frame (None: LDR)
    exposure_channel: str = ""       # or the input channel holding it (its frame mean)

    def __post_init__(self):
        def names(field, n):
            v = getattr(self, field)
            if (not isinstance(v, (tuple, list)) or len(v) != n
                    or not all(isinstance(x, str) and x for x in v)):
                raise ValueError(f"{field}: expected {n} channel names, got {v!r}")
        names("color", 3)
        names("target_color", 3)
        names("motion", 2)
        if not isinstance(self.depth, str) or not self.depth:
            raise ValueError(f"depth: expected a channel name, got {self.depth!r}")
        for field in ("motion_y_up", "motion_negate", "jitter_y_up"):
            if not isinstance(getattr(self, field), bool):
                raise ValueError(f"{field}: expected true or false, got "
                                 f"{getattr(self, field)!r}")
        for field, allowed in (("motion_units", conventions.MOTION_UNITS),
                               ("depth_kind", conventions.DEPTH_KINDS),
                               ("jitter_kind", conventions.JITTER_KINDS)):
            if getattr(self, field) not in allowed:
                raise ValueError(f"{field}: expected one of {allowed}, got "
                                 f"{getattr(self, field)!r}")
        for field in ("near", "far"):
            v = getattr(self, field)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise ValueError(f"{field}: expected a finite number, got {v!r}")
        if isinstance(self.jitter, str) and self.jitter != "thesis":
            raise ValueError(f"jitter: expected 'thesis' or numbers, got {self.jitter!r}")
        if not isinstance(self.jitter, str):
            j = np.asarray(self.jitter, dtype=object)
            if (j.ndim not in (1, 2) or j.shape[-1] != 2 or not all(
                    isinstance(x, (int, float)) and not isinstance(x, bool)
                    for x in j.reshape(-1))):
                raise ValueError(f"jitter: expected 'thesis', one [x, y] or a list of [x, y] "
                                 f"numbers, got {self.jitter!r}")
        if not isinstance(self.exposure_channel, str):
            raise ValueError(f"exposure_channel: expected a channel name, got "
                             f"{self.exposure_channel!r}")
        if self.exposure is not None and self.exposure_channel:
            raise ValueError("exposure, exposure_channel: give one of them, not both")
        if self.exposure is not None:
            e = np.asarray(self.exposure, dtype=object)
            if e.ndim > 1 or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                     for x in e.reshape(-1)):
                raise ValueError(f"exposure: expected a number or a list of numbers, got "
                                 f"{self.exposure!r}")

    @classmethod
    def from_json(cls, path):
        data = read_json_fields(path, cls, "key")
        data = {k: tuple(v) if isinstance(v, list) and k in ("color", "motion", "target_color")
                else v for k, v in data.items()}
        try:
            return cls(**data)
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from e


def _frames(folder):
    """``{frame number: path}`` of a folder's EXRs, the number being the last group of
    digits in each name (``frame10.exr`` is frame 10, after ``frame2.exr``)."""

    if not os.path.isdir(folder):
        raise FileNotFoundError(f"{folder}: no such folder")
    files = [f for f in os.listdir(folder) if f.lower().endswith(".exr")]
    if not files:
        raise ValueError(f"{folder}: no .exr files")
    out = {}
    for f in files:
        if not os.path.isfile(os.path.join(folder, f)):
            raise ValueError(f"{os.path.join(folder, f)}: expected an EXR file, got a folder "
                             "or another non-file")
        digits = re.findall(r"\d+", os.path.splitext(f)[0])
        if not digits:
            raise ValueError(f"{os.path.join(folder, f)}: no frame number in the name")
        n = int(digits[-1])
        if n in out:
            raise ValueError(f"{folder}: {os.path.basename(out[n])} and {f} are both frame {n}")
        out[n] = os.path.join(folder, f)
    numbers = sorted(out)
    gaps = sorted(set(range(numbers[0], numbers[-1] + 1)) - set(numbers))
    if gaps:
        raise ValueError(f"{folder}: frames {gaps[:10]} are missing between {numbers[0]} and "
                         f"{numbers[-1]}")
    return out


def check_values(path, field, v, lo=None, hi=None):
    """``ValueError`` naming ``path`` and ``field`` on NaN/Inf or values outside [lo, hi]."""
    bad = ~np.isfinite(v)
    if bad.any():
        raise ValueError(f"{path}: {field} has {int(bad.sum())} NaN or Inf values")
    if lo is not None and v.min() < lo:
        raise ValueError(f"{path}: {field} has values below {lo} (min {float(v.min()):.4g})")
    if hi is not None and v.max() > hi:
        raise ValueError(f"{path}: {field} has values above {hi} (max {float(v.max()):.4g})")


def _jitters(spec, n, factor):
    if isinstance(spec.jitter, str):
        if spec.jitter != "thesis":
            raise ValueError(f"jitter: expected 'thesis' or numbers, got {spec.jitter!r}")
        seq = jitter_sequence("thesis", factor)
        return np.stack([seq[t % len(seq)] for t in range(n)])
    j = np.asarray(spec.jitter, dtype=np.float64)
    if j.shape == (2,):
        j = np.broadcast_to(j, (n, 2))
    if j.shape != (n, 2):
        raise ValueError(f"jitter: expected one [x, y] or {n} of them, got shape {j.shape}")
    return conventions.jitter_to_jtus(j, spec.jitter_kind, spec.jitter_y_up)


def _paired(input_dir, target_dir):
    """``(input files, target files or Nones)`` in frame-number order; ``ValueError``
    naming the frames that do not pair."""
    by_number = _frames(input_dir)
    numbers = sorted(by_number)
    inputs = [by_number[n] for n in numbers]
    if target_dir is None:
        return inputs, [None] * len(inputs)
    tby = _frames(target_dir)
    if sorted(tby) != numbers:
        only_in = sorted(set(numbers) - set(tby))[:10]
        only_tg = sorted(set(tby) - set(numbers))[:10]
        raise ValueError(f"frames do not pair: {input_dir} has frames {numbers[0]}-"
                         f"{numbers[-1]}, {target_dir} has {min(tby)}-{max(tby)}"
                         + (f"; no target for {only_in}" if only_in else "")
                         + (f"; no input for {only_tg}" if only_tg else ""))
    return inputs, [tby[n] for n in numbers]


def _read_input(fin, spec: ImportSpec):
    """One input frame: ``(colour, device depth, motion in jtus's convention, exposure
    or None)``, each channel checked and converted at this edge."""
    ch, _ = read_exr(fin)
    color = _pick(ch, spec.color, fin, "color")
    h, w = color.shape[:2]
    check_values(fin, "color (linear, stored as float16)", color, lo=0.0,
                 hi=dataset.COLOR_MAX)
    depth = _pick(ch, (spec.depth,), fin, "depth")
    check_values(fin, f"depth ({spec.depth_kind})", depth, lo=0.0,
                 hi=1.0 if spec.depth_kind in ("device", "reversed", "linear") else None)
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = conventions.depth_to_device(depth, spec.depth_kind, spec.near, spec.far)
    check_values(fin, f"depth (as device depth, from {spec.depth_kind} with near "
                 f"{spec.near}, far {spec.far})", depth, lo=0.0, hi=1.0)
    motion = conventions.motion_to_jtus(_pick(ch, spec.motion, fin, "motion"), w, h,
                                        spec.motion_units, spec.motion_y_up,
                                        spec.motion_negate)
    check_values(fin, "motion", motion)
    exposure = (float(_pick(ch, (spec.exposure_channel,), fin, "exposure").mean())
                if spec.exposure_channel else None)
    return color, depth, motion, exposure


def _read_target(ftg, spec: ImportSpec, lr_size, factor):
    tch, _ = read_exr(ftg)
    target = _pick(tch, spec.target_color, ftg, "target")
    check_values(ftg, "target (linear, stored as float16)", target, lo=0.0,
                 hi=dataset.COLOR_MAX)
    h, w = lr_size
    if target.shape[:2] != (h * factor, w * factor):
        raise ValueError(f"{ftg}: target size {target.shape[0]}x{target.shape[1]} is "
                         f"not factor {factor} x the input's {h}x{w}")
    return target.astype(np.float32)


def _checked_jitter(spec: ImportSpec, n, factor):
    jitter = _jitters(spec, n, factor)
    if not (np.all(np.isfinite(jitter)) and np.all((jitter >= 0) & (jitter < 1))):
        raise ValueError(f"jitter: expected values in [0, 1) after the {spec.jitter_kind!r} "
                         f"convention, got min {np.nanmin(jitter):.4g}, max "
                         f"{np.nanmax(jitter):.4g} ({int((~np.isfinite(jitter)).sum())} NaN "
                         f"or Inf)")
    return jitter.astype(np.float32)


def _checked_exposure(exposure, n):
    """``[n]`` float32 exposures from one number or one per frame; None stays None."""
    if exposure is None:
        return None
    e = np.broadcast_to(np.asarray(exposure, np.float64), (n,)) if np.ndim(exposure) == 0 \
        else np.asarray(exposure, np.float64)
    if e.shape != (n,):
        raise ValueError(f"exposure: expected one number or {n} (one per frame), got "
                         f"{e.shape[0]}")
    if not np.all(np.isfinite(e) & (e > 0)):
        raise ValueError(f"exposure: expected finite values > 0, got min {np.nanmin(e):.4g}")
    return e.astype(np.float32)


def _exr_size(path):
    """``(height, width)`` from an EXR's header alone (its data window)."""
    try:
        with OpenEXR.File(os.fspath(path), header_only=True) as f:
            lo, hi = (np.asarray(v) for v in f.header()["dataWindow"])
    except Exception as e:  # OpenEXR raises several types for damaged files
        raise ValueError(f"{path}: not a readable EXR file ({e})") from e
    return int(hi[1] - lo[1] + 1), int(hi[0] - lo[0] + 1)


def sequence_budget(input_dir, target_dir, factor):
    """``(memory, disk)`` bytes of importing an EXR sequence, from the frame count and
    the first frames' headers, before any pixel is read: ``load_sequence`` holds every
    frame as float32 (input colour, depth and motion; target colour) and stacks them
    (two copies at its peak); the dataset stores colours as float16, depth and motion
    as float32."""
    inputs, targets = _paired(input_dir, target_dir)
    h, w = _exr_size(inputs[0])
    hr = _exr_size(targets[0]) if targets[0] is not None else (h * factor, w * factor)
    lr_px, hr_px, n = h * w, hr[0] * hr[1], len(inputs)
    memory = 2 * n * (lr_px * 6 * 4 + hr_px * 3 * 4)
    disk = n * (lr_px * (3 * 2 + 3 * 4) + (hr_px * 3 * 2 if targets[0] is not None else 0))
    return memory, disk


def load_sequence(input_dir, target_dir, factor, spec: ImportSpec = ImportSpec()):
    """Read an EXR sequence into the ``jtus.sim.video`` dict layout (one factor).
    ``target_dir`` None reads the inputs alone (``target`` is then absent)."""
    inputs, targets = _paired(input_dir, target_dir)
    cols = {"color": [], "depth": [], "motion": [], "target": [], "exposure": []}
    shape = None
    for fin, ftg in zip(inputs, targets):
        color, depth, motion, exposure = _read_input(fin, spec)
        h, w = color.shape[:2]
        if shape is None:
            shape = (h, w)
        elif (h, w) != shape:
            raise ValueError(f"{fin}: size {h}x{w} differs from the first frame's "
                             f"{shape[0]}x{shape[1]}")
        for k, v in (("color", color), ("depth", depth), ("motion", motion)):
            cols[k].append(v.astype(np.float32))
        cols["exposure"].append(exposure)
        if ftg is not None:
            cols["target"].append(_read_target(ftg, spec, shape, factor))
    n = len(inputs)
    out = {"reset": np.arange(n) == 0,
           f"x{factor}": {"color": np.stack(cols["color"]), "depth": np.stack(cols["depth"]),
                          "motion": np.stack(cols["motion"]),
                          "jitter": _checked_jitter(spec, n, factor)}}
    if cols["target"]:
        out["target"] = np.stack(cols["target"])
    exposure = _checked_exposure(cols["exposure"] if spec.exposure_channel else spec.exposure,
                                 n)
    if exposure is not None:
        out["exposure"] = exposure
    return out


def import_exr(input_dir, target_dir, factor, out, spec: ImportSpec = ImportSpec(),
               split="test", name="video_00"):
    """Write an EXR sequence as a one-video jtus HDF5 dataset (atomically)."""

    video = load_sequence(input_dir, target_dir, factor, spec)
    T, H, W, _ = video["target"].shape
    with atomic_path(out) as tmp, h5py.File(tmp, "w") as fh:
        dataset.write_root_attrs(fh, (H, W), (factor,), spp=0, spp_match=1)
        g = fh.create_group(f"{split}/{name}")
        g.attrs.update({"scene": f"exr:{os.path.abspath(input_dir)}", "effects": "[]",
                        "length": T, "index": 0, "near": spec.near, "far": spec.far})
        dataset.write_video(g, video, (factor,), 1)
    return out


def linear_to_srgb(x):
    """Linear RGB -> sRGB-encoded values in [0, 1] (clipped first)."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def sequence_files(folder, prefix="frame"):
    """The frames a ``write_sequence`` into ``folder`` wrote (any format)."""

    if not os.path.isdir(folder):
        return []
    pat = re.compile(re.escape(prefix) + r"\d{4,}\.(" + "|".join(IMAGE_FORMATS) + ")")
    return sorted(f for f in os.listdir(folder) if pat.fullmatch(f))


def check_sequence_folder(folder, force=False, prefix="frame", field="--out"):
    """Refuse, before any work, a folder holding the frames of an earlier sequence
    (new frames beside stale ones would read as one sequence) unless ``force``."""

    check_out_folder(folder, field)
    old = sequence_files(folder, prefix)
    if old and not force:
        raise ValueError(f"{field}: {folder} holds {len(old)} frames of an earlier sequence "
                         f"({old[0]} ...); pass --force to replace them")


def write_sequence(frames, folder, fmt="exr", prefix="frame", srgb=True):
    """Write ``[T,H,W,3]`` linear RGB frames as ``folder/{prefix}{t:04d}.{fmt}``,
    replacing the frames of an earlier sequence there (``check_sequence_folder``
    refuses them first unless forced) only once every new frame is written: the new
    frames go to a staging folder beside them and are then renamed over the old ones
    (each rename atomic), and old frames the new sequence lacks are deleted last.
    PNGs are 8-bit, sRGB-encoded unless ``srgb=False``. Returns the paths."""

    if fmt not in IMAGE_FORMATS:
        raise ValueError(f"fmt: expected one of {IMAGE_FORMATS}, got {fmt!r}")
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"frames: expected [T,H,W,3], got shape {frames.shape}")
    if not np.all(np.isfinite(frames)):
        raise ValueError(f"frames: {int(np.sum(~np.isfinite(frames)))} values are NaN or "
                         "infinite; nothing written")
    os.makedirs(folder, exist_ok=True)
    stage = tempfile.mkdtemp(prefix=".staging-", dir=folder)
    try:
        for t, img in enumerate(frames):
            path = os.path.join(stage, f"{prefix}{t:04d}.{fmt}")
            if fmt == "exr":
                write_exr(path, {c: img[..., i] for i, c in enumerate("RGB")})
            else:
                v = linear_to_srgb(img) if srgb else np.clip(img, 0, 1)
                Image.fromarray(np.round(v * 255).astype(np.uint8)).save(path, format="PNG")
        old = sequence_files(folder, prefix)
        paths = []
        for f in sorted(os.listdir(stage)):  # each rename replaces one frame whole
            os.replace(os.path.join(stage, f), os.path.join(folder, f))
            paths.append(os.path.join(folder, f))
        for f in set(old) - {os.path.basename(p) for p in paths}:
            os.remove(os.path.join(folder, f))
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return paths
