"""HDF5 datasets of rendered videos, and the readers that feed training and evaluation.

Layout (``docs/data.md``)::

    /                  attrs: format="jtus-dataset", version, spp, targets (generated
                              files: uniform or adaptive, spp 0 for adaptive), mip_bias,
                              spp_match,
                              conventions (JSON), factors, size
    /{split}/{video}/  attrs: scene, effects (JSON), length, index, jitter_sequence,
                              jitter_phase, near, far (the depth's clip planes)
        target   [T,H,W,3]  float16, linear RGB in [0,1]
        reset    [T]        bool, True at the first frame and at camera cuts
        x{f}/    attrs: mip_bias (eq. 47 for this factor)
            color  [T,h,w,3] float16
            depth  [T,h,w,1] float32, device depth
            motion [T,h,w,2] float32, backward, LR pixels
            jitter [T,2]     float32, in [0,1)^2

The writers here (``write_root_attrs``, ``write_video``) are what every producer of a
dataset calls: the simulator (``jtus.sim.generate``) and the importers (``exr``,
``nss``), each into a file opened under ``jtus.files.atomic_path``.
"""

from __future__ import annotations

import json
import math
import os

import h5py
import numpy as np

from jtus.frame import Frame
from jtus.sampling import jitter_sequence

FORMAT = "jtus-dataset"
# colours are stored as float16: larger values would be stored as inf
COLOR_MAX = float(np.finfo(np.float16).max)  # 65504
VERSION = 1
SPLITS = ("train", "val", "test")
CONVENTIONS = {
    "pixel_centre": "(j + 0.5, i + 0.5)", "axes": "x right, y down",
    "motion": "backward, LR pixels: the surface under p was at p + motion",
    "jitter": "offset inside the LR pixel in [0,1)^2", "depth": "D3D device depth, not reversed",
    "color": "linear RGB", "doc": "docs/conventions.md",
}


def mip_bias(factor, spp_match):
    """Eq. 47: the input's mip bias for up-sampling ``factor`` matching ``spp_match``."""
    return -0.5 * math.log2(factor * factor) - 0.5 * math.log2(spp_match)


def _chunks(shape, t=8, s=64):
    return (min(t, shape[0]),) + tuple(min(s, n) for n in shape[1:3]) + tuple(shape[3:])


def check_video(name, video, factors):
    """``ValueError`` naming the video, field and first frame when a video about to be
    stored holds a NaN or infinite value or a colour past float16 (``COLOR_MAX``): every
    writer (generation, ``sim render``, the imports) calls it, so no dataset is written
    that a reader would have to refuse."""
    fields = [("target", video["target"], True)]
    if video.get("exposure") is not None:
        fields.append(("exposure", np.asarray(video["exposure"]), False))
    for f in factors:
        v = video[f"x{f}"]
        fields += [(f"x{f}/{k}", v[k], k == "color") for k in ("color", "depth", "motion",
                                                                 "jitter")]
    for field, a, colour in fields:
        a = np.asarray(a, np.float64)
        bad = ~np.isfinite(a) | (np.abs(a) > COLOR_MAX if colour else False)
        if bad.any():
            t = int(np.argwhere(bad)[0][0])
            raise ValueError(f"{name}: {field} has {int(bad.sum())} NaN, infinite or "
                             f"float16-overflowing values (first in frame {t}); nothing "
                             "written")


def write_video(group, video, factors, spp_match):
    """Write one rendered video dict (``jtus.sim.video``'s layout) into ``group``,
    checked first (``check_video``)."""
    check_video(group.name, video, factors)
    tgt = video["target"]
    group.create_dataset("target", data=tgt.astype(np.float16), chunks=_chunks(tgt.shape))
    group.create_dataset("reset", data=video["reset"].astype(bool))
    if video.get("exposure") is not None:  # HDR colour (docs/conventions.md)
        group.create_dataset("exposure", data=np.asarray(video["exposure"], np.float32))
    for f in factors:
        g = group.create_group(f"x{f}")
        g.attrs["mip_bias"] = mip_bias(f, spp_match)
        v = video[f"x{f}"]
        g.create_dataset("color", data=v["color"].astype(np.float16),
                         chunks=_chunks(v["color"].shape, s=64 // f))
        for k in ("depth", "motion"):
            g.create_dataset(k, data=v[k].astype(np.float32), chunks=_chunks(v[k].shape, s=64 // f))
        g.create_dataset("jitter", data=v["jitter"].astype(np.float32))


def write_root_attrs(fh, size, factors, spp, spp_match, targets=None):
    """The file's attributes. ``targets``: how the simulator supersampled the targets
    (``"uniform"``, or ``"adaptive"``: 4, 16 or 64 samples per pixel,
    ``jtus.sim.video.VideoRenderer.adaptive_target``, stored with ``spp`` 0); an
    imported file has none."""
    if targets is not None:
        fh.attrs["targets"] = targets
    spp = 0 if targets == "adaptive" else spp
    fh.attrs.update({"format": FORMAT, "version": VERSION, "spp": spp,
                     "spp_match": spp_match,
                     "mip_bias": 0.0 - 0.5 * math.log2(spp_match), "factors": list(factors),
                     "size": list(size), "conventions": json.dumps(CONVENTIONS)})


class Dataset:
    """Read a jtus HDF5 dataset: whole videos for evaluation, aligned crops for training."""

    def __init__(self, path):
        self.path = os.fspath(path)
        if not os.path.exists(self.path):
            raise FileNotFoundError(f"dataset: {self.path} does not exist (generate it with "
                                    f"`python -m jtus.data generate --preset default --out "
                                    f"{self.path}`)")
        try:
            self.file = h5py.File(self.path, "r")
        except OSError as e:
            raise ValueError(f"dataset: {self.path} is not a readable HDF5 file ({e})") from e
        fmt = self.file.attrs.get("format")
        if fmt != FORMAT:
            raise ValueError(f"dataset: {self.path} has format {fmt!r}, expected {FORMAT!r}")
        if int(self.file.attrs["version"]) != VERSION:
            raise ValueError(f"dataset: version {self.file.attrs['version']} is not {VERSION}")
        self.factors = tuple(int(f) for f in self.file.attrs["factors"])
        self.size = tuple(int(s) for s in self.file.attrs["size"])
        # HDR when any video carries an exposure per frame; its LDR videos then read
        # as exposure 1, so that every batch has one layout
        self.hdr = any("exposure" in self.file[s][n] for s in SPLITS if s in self.file
                       for n in self.file[s])
        self._sources_cache = {}  # crops' draw: (split, factor, seq_len, extend) -> videos

    def close(self):
        self.file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def videos(self, split):
        if split not in self.file:
            return []
        return sorted(self.file[split].keys())

    def _check_factor(self, factor):
        if factor not in self.factors:
            raise ValueError(f"factor: the dataset holds {self.factors}, got {factor}")

    def group(self, split, name):
        """The HDF5 group of one video; ``ValueError`` naming what exists when the split
        or the video does not."""
        if split not in self.file:
            raise ValueError(f"split: {self.path} has no split {split!r}; it has "
                             f"{sorted(self.file.keys())}")
        if name not in self.file[split]:
            names = self.videos(split)
            raise ValueError(f"video: no {name!r} in split {split!r} of {self.path}; it has "
                             f"{len(names)} videos ({', '.join(names[:5])}"
                             f"{', ...' if len(names) > 5 else ''})")
        return self.file[f"{split}/{name}"]

    def video(self, split, name, factor):
        """A whole video: ``(Frame [T,1,...], targets [T,1,H,W,3])`` float32, reset at t=0."""
        self._check_factor(factor)
        g = self.group(split, name)
        missing = [k for k in ("target", "reset", f"x{factor}/color", f"x{factor}/depth",
                               f"x{factor}/motion", f"x{factor}/jitter") if k not in g]
        if missing:
            raise ValueError(f"{self.path}: {split}/{name} lacks {missing}; not a complete "
                             "jtus dataset video")
        x = g[f"x{factor}"]
        reset = g["reset"][:].copy()
        reset[0] = True
        e = self._exposure(g, slice(None))
        frame = Frame(x["color"][:].astype(np.float32)[:, None], x["depth"][:][:, None],
                      x["motion"][:][:, None], x["jitter"][:][:, None], reset[:, None],
                      None if e is None else e[:, None])
        target = g["target"][:].astype(np.float32)[:, None]
        _check_read(f"{self.path}: {split}/{name}", frame, target)
        return frame, target

    def _exposure(self, g, ts):
        """``[T]`` exposure of frames ``ts`` of video group ``g``, None in LDR datasets."""
        if not self.hdr:
            return None
        if "exposure" in g:
            return g["exposure"][ts].astype(np.float32)
        return np.ones(g["reset"][ts].shape, np.float32)

    def hold_period(self, split, name, factor):
        """``(hold_from, period)`` of a held video (generated with ``hold_from``: it
        stands still from that frame on while only the jitter moves), or None for any
        other video. ``period`` is its jitter sequence's length at ``factor``: a held
        frame's input and target equal those ``period`` frames earlier. ``ValueError``
        when the stored jitter contradicts that period."""
        g = self.group(split, name)
        if "hold_from" not in g.attrs or "jitter_sequence" not in g.attrs:
            return None
        hold_from = int(g.attrs["hold_from"])
        period = len(jitter_sequence(str(g.attrs["jitter_sequence"]), factor))
        j = g[f"x{factor}/jitter"][hold_from:]
        if len(j) > period and not np.array_equal(j[period:], j[:-period]):
            raise ValueError(f"{self.path}: {split}/{name}: the held frames' jitter does not "
                             f"repeat with its sequence's period {period}")
        return hold_from, period

    def sequence_frames(self, split, name, factor, seq_len, extend_holds=False):
        """The stored frame numbers behind a ``seq_len``-frame sequence from frame 0 of
        a video, or None when the video cannot give one. Within its length, ``0 ..
        seq_len-1``. Past it, with ``extend_holds`` and a held video whose still part
        spans at least one jitter period, the hold goes on: frame ``t`` reads the last
        stored frame ``t - k * period``, which has the same input and target (a longer
        hold rendered outright gives the same frames, ``tests/test_data.py``)."""
        T = self.group(split, name)["target"].shape[0]
        if seq_len <= T:
            return np.arange(seq_len)
        held = self.hold_period(split, name, factor) if extend_holds else None
        if held is None or T - held[0] < held[1]:
            return None
        t = np.arange(seq_len)
        past = t >= T
        t[past] -= held[1] * np.ceil((t[past] - T + 1) / held[1]).astype(t.dtype)
        return t

    def _sources(self, split, factor, seq_len, extend_holds):
        """``[(name, frame numbers of its first sequence, count of start frames)]``
        of the videos of ``split`` that give ``seq_len``-frame sequences."""
        key = (split, factor, seq_len, extend_holds)
        if key not in self._sources_cache:
            out = []
            for name in self.videos(split):
                t = self.sequence_frames(split, name, factor, seq_len, extend_holds)
                T = self.file[f"{split}/{name}/target"].shape[0]
                if t is None and not extend_holds:
                    raise ValueError(f"seq_len: {seq_len} exceeds the length {T} of video "
                                     f"{name!r} (extend_holds continues held videos' holds)")
                if t is not None:
                    out.append((name, t, max(T - seq_len + 1, 1)))
            self._sources_cache[key] = out
        return self._sources_cache[key]

    def _read_crop(self, g, factor, ts, sel, y, x, crop):
        """One crop's columns: frames ``ts`` (a slice) of video group ``g`` taken in the
        order ``sel``, the LR block at ``(y, x)`` and the HR crop over it."""
        c, lr = crop // factor, g[f"x{factor}"]
        reset = g["reset"][ts][sel]
        reset[0] = True
        e = self._exposure(g, ts)
        return {"color": lr["color"][ts, y:y + c, x:x + c][sel].astype(np.float32),
                "depth": lr["depth"][ts, y:y + c, x:x + c][sel],
                "motion": lr["motion"][ts, y:y + c, x:x + c][sel],
                "jitter": lr["jitter"][ts][sel], "reset": reset,
                "target": g["target"][ts, y * factor:y * factor + crop,
                                      x * factor:x * factor + crop][sel].astype(np.float32),
                "exposure": None if e is None else e[sel]}

    def crops(self, split, factor, batch, seq_len, crop, rng, return_index=False, accept=None,
              max_tries=20, extend_holds=False):
        """Random aligned crops: ``(Frame [T,B,...], targets [T,B,crop,crop,3])``.

        The HR crop starts at a multiple of ``factor`` so that the LR crop lies exactly
        under it; ``crop`` must be a multiple of 4 and of ``factor``. The first frame
        of each crop has ``reset`` set (the model starts its history there).
        ``extend_holds``: a held video shorter than ``seq_len`` gives a sequence from its
        first frame with its hold continued (``sequence_frames``); videos that cannot
        give ``seq_len`` frames are not drawn.
        """
        self._check_factor(factor)
        if crop % 4 or crop % factor:
            raise ValueError(f"crop: expected a multiple of 4 and of factor {factor}, got {crop}")
        H, W = self.size
        if crop > min(H, W):
            raise ValueError(f"crop: {crop} exceeds the frame size {H}x{W}")
        if not self.videos(split):
            raise ValueError(f"dataset: no videos in split {split!r}")
        sources = self._sources(split, factor, seq_len, extend_holds)
        if not sources:
            raise ValueError(f"seq_len: no video of split {split!r} gives {seq_len} frames, "
                             "not even with its hold continued (a held video's still part "
                             "must span one jitter period)")
        cols = {k: [] for k in ("color", "depth", "motion", "jitter", "reset", "target",
                                "exposure")}
        index = []
        for _ in range(batch):
            for _ in range(max_tries):
                name, frames, starts = sources[rng.integers(len(sources))]
                g = self.file[f"{split}/{name}"]
                t0 = int(rng.integers(0, starts))
                y = int(rng.integers(0, (H - crop) // factor + 1))
                xx = int(rng.integers(0, (W - crop) // factor + 1))
                ts = frames + t0
                lo, sel = int(ts[0]), ts - ts[0]
                ts_read = slice(lo, int(ts.max()) + 1)
                if accept is None or rng.uniform() < accept(
                        g["target"][ts_read, y * factor:y * factor + crop,
                                    xx * factor:xx * factor + crop][sel]):
                    break
            index.append((name, t0, y, xx))
            for k, v in self._read_crop(g, factor, ts_read, sel, y, xx, crop).items():
                cols[k].append(v)
        exposure = cols.pop("exposure")
        exposure = np.stack(exposure, 1) if self.hdr else None
        st = {k: np.stack(v, 1) for k, v in cols.items()}
        frame = Frame(st["color"], st["depth"], st["motion"], st["jitter"], st["reset"],
                      exposure)
        _check_read(f"{self.path}: {split} crops of {sorted({i[0] for i in index})}", frame,
                    st["target"])
        return (frame, st["target"], index) if return_index else (frame, st["target"])


def _check_read(where, frame, target):
    """``ValueError`` naming the video and the first bad frame when what was read holds
    NaN or infinite values, or a jitter outside [0, 1): a file written by another tool
    (or damaged) is refused where it is read, before any model runs on it."""
    arrays = {"color": frame.color, "depth": frame.depth, "motion": frame.motion,
              "jitter": frame.jitter, "target": target}
    if frame.exposure is not None:
        arrays["exposure"] = frame.exposure
    for field, a in arrays.items():
        bad = ~np.isfinite(a)
        if field == "jitter":
            bad |= (a < 0) | (a >= 1)
        if bad.any():
            t = int(np.argwhere(bad)[0][0])
            what = "outside [0, 1) or not finite" if field == "jitter" else "NaN or infinite"
            raise ValueError(f"{where}: {field} has {int(bad.sum())} values {what} (first "
                             f"in frame {t})")
