"""Datasets rendered by the simulator: the built-in presets, ``generate`` and
``ensure_dataset``.

A preset says, per split, which scenes, how many videos per scene and how many
frames each; ``generate`` renders it into the HDF5 layout of ``jtus.data.dataset``
(``docs/data.md``), written to a temporary name beside the destination and renamed
when complete, so an interrupted run leaves nothing behind.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pickle
import subprocess
import sys
import tempfile
import threading
from typing import Optional

import h5py
import numpy as np
from tqdm import tqdm

from jtus import hostmem
from jtus.data.dataset import SPLITS, write_root_attrs, write_video
from jtus.files import atomic_path
from jtus.sampling.jitter import VARIETY
from jtus.sim import game, randomized
from jtus.sim.mesh import MESH_EFFECTS, MeshScene
from jtus.sim.paths import video_seed
from jtus.sim.suite import NAMES as SCENES
from jtus.sim.suite import get as get_scene
from jtus.sim.suite import with_effects
from jtus.sim.video import VideoRenderer


@dataclasses.dataclass(frozen=True)
class Preset:
    """What ``generate`` renders: per split, (scene names, videos per scene, frames).

    ``effects``: effects added to every scene (``("hdr", ...)`` for HDR data).
    ``jitters``: the jitter sequences a video draws from (``jtus.sampling.jitter``);
    each video's choice and its starting phase come from its own seed and are stored
    (``jitter`` per frame, the sequence's name in the video's attrs).
    ``hold_from``: each video moves for this many frames, then holds still while only
    the jitter moves (``VideoRenderer.video``), stored in the video's attrs.
    ``targets``: ``"uniform"`` (``spp`` samples in every pixel) or ``"adaptive"``
    (``VideoRenderer.adaptive_target``: 4, 16 or 64 samples; ``spp`` unused)."""
    size: tuple
    factors: tuple
    spp: int
    spp_match: int
    splits: dict
    jitters: tuple = ("thesis",)
    effects: tuple = ()   # added to every scene's own (``jtus.sim.with_effects``)
    hold_from: Optional[int] = None  # every video stands still from this frame on
    targets: str = "uniform"

    def total_frames(self):
        return sum(len(s) * n * t for s, n, t in self.splits.values())

    def budget(self, workers=1):
        """``(memory, disk)`` bytes of generating this preset (``render_budget``)."""
        longest = max(t for _, _, t in self.splits.values())
        mem, _ = render_budget(self.size[0], self.factors, longest, 1, workers,
                               width=self.size[1])
        _, disk = render_budget(self.size[0], self.factors, 1, self.total_frames(), 1,
                                width=self.size[1])
        return mem, disk


def render_budget(size, factors, frames, videos, workers, width=None):
    """``(memory, disk)`` bytes of rendering ``videos`` videos of ``frames`` frames of
    ``size`` x ``width`` (square by default): each worker holds one video as float32
    (target and every factor's colour, depth and motion) plus a frame of render
    temporaries; the dataset stores colour as float16, depth and motion as float32."""
    px = size * (width or size)
    lr = sum(px // (f * f) for f in factors)
    per_frame = px * 3 * 4 + lr * 6 * 4
    memory = workers * (frames * per_frame + 16 * px * 4 * 8)
    disk = videos * frames * (px * 3 * 2 + lr * (3 * 2 + 3 * 4))
    return memory, disk


def _random(split, count):
    return tuple(randomized.name_of(s) for s in randomized.split_seeds(split, count))


def _presets():
    all_ = tuple(SCENES)
    return {
        "tiny": Preset((32, 32), (2, 4), 4, 1, {
            "train": (("camera_orbit", "objects"), 1, 8), "val": (("camera_orbit",), 1, 8),
            "test": (("objects",), 1, 8)}),
        "default": Preset((256, 256), (2, 4), 16, 1, {
            "train": (all_, 2, 24),
            "val": (("camera_orbit", "objects", "fence_pan", "everything"), 1, 24),
            "test": (all_, 1, 30)}),
        # 40-frame videos at 128x128 for sequence-length studies (BPTT over up to 40
        # frames; the default data's training videos have 24)
        "long": Preset((128, 128), (2, 4), 16, 1, {
            "train": (all_, 1, 40), "val": (("camera_orbit", "everything"), 1, 40),
            "test": (all_, 1, 40)}),
        "paper": Preset((1080, 1920), (2, 4), 64, 1, {
            "train": (all_, 6, 60), "val": (all_[:10], 1, 60), "test": (all_[:10], 1, 60)}),
        # generalization: 200 randomized scenes for training, unseen seeds for validation
        # and test, the 13 hand-made scenes as a second test family; every jitter
        # sequence (docs/data.md)
        # (192x192: 256x256 rendered at about half the speed, docs/data.md)
        "diverse": Preset((192, 192), (2, 4), 16, 1, {
            "train": (_random("train", 200), 1, 16), "val": (_random("val", 8), 1, 16),
            "test": (_random("test", 16) + all_, 1, 24)}, VARIETY),
        # the same family in seconds, for tests
        "diverse-tiny": Preset((32, 32), (2, 4), 4, 1, {
            "train": (_random("train", 3), 1, 8), "val": (_random("val", 1), 1, 8),
            "test": (_random("test", 1) + ("objects",), 1, 8)}, VARIETY),
        # HDR: the diverse family with highlights above 1 and an exposure per frame
        "hdr": Preset((192, 192), (2, 4), 16, 1, {
            "train": (_random("train", 200), 1, 16), "val": (_random("val", 8), 1, 16),
            "test": (_random("test", 16) + all_, 1, 24)}, VARIETY, _HDR),
        "hdr-tiny": Preset((32, 32), (2, 4), 4, 1, {
            "train": (_random("train", 3), 1, 8), "val": (_random("val", 1), 1, 8),
            "test": (_random("test", 1) + ("objects",), 1, 8)}, VARIETY, _HDR),
        # game content: OpenArena's levels (data/fetch_game_assets.sh), whole levels
        # held out for validation and test, each level with the effects its content has
        "game": Preset((128, 128), (2, 4), 16, 1, {
            "train": (_levels(game.TRAIN_LEVELS), 4, 16),
            "val": (_levels(game.VAL_LEVELS), 2, 16),
            "test": (_levels(game.TEST_LEVELS), 2, 24)}, VARIETY),
        **_hold_presets(),
    }


def _hold_presets():
    """Static holds (``hold_from``), to train and check a model's steady state: each
    game level's camera path (``game-*``) or randomized scene's (``diverse-*``, the
    diverse preset's seeds) for 16 frames, then 32 still frames where only the jitter
    moves (two cycles of a 16-position sequence; ``*-holds``) or 64 (four cycles;
    ``*-long-holds``). No test split: the test levels' holds are
    experiments/static_hold.py's."""
    out = {}
    for name, frames in (("holds", 48), ("long-holds", 80)):
        out[f"game-{name}"] = Preset((128, 128), (2, 4), 16, 1, {
            "train": (_levels(game.TRAIN_LEVELS), 1, frames),
            "val": (_levels(game.VAL_LEVELS), 1, frames), "test": ((), 1, 1)}, VARIETY,
            hold_from=16)
        out[f"diverse-{name}"] = Preset((192, 192), (2, 4), 16, 1, {
            "train": (_random("train", 200), 1, frames),
            "val": (_random("val", 8), 1, frames), "test": ((), 1, 1)}, VARIETY,
            hold_from=16)
    return out


def _levels(maps):
    return tuple(game.PREFIX + m for m in maps)


def scene_of(name, custom=None):
    """The scene a preset names: a JSON-declared one, a game level, or a built-in."""
    if custom and name in custom:
        return custom[name]
    if game.is_level(name):
        return game.scene_of(name)
    return get_scene(name)


def _with_effects(scene, add):
    if isinstance(scene, MeshScene):
        return scene if not add else dataclasses.replace(
            scene, effects=tuple(e for e in MESH_EFFECTS if e in scene.effects or e in add))
    return with_effects(scene, add)


_HDR = ("hdr", "specular", "emissive_flicker")


PRESET_NAMES = ("tiny", "default", "long", "paper", "diverse", "diverse-tiny", "hdr", "hdr-tiny",
                "game", "game-holds", "diverse-holds", "game-long-holds", "diverse-long-holds")


def preset(name) -> Preset:
    p = _presets()
    if name not in p:
        raise ValueError(f"preset: expected one of {PRESET_NAMES}, got {name!r}")
    return p[name]


def video_jitter(choices, scene_name, split, index):
    """``(sequence name, phase)`` of one video: the only choice when there is one
    (phase 0, the thesis's setup), else drawn from the video's own seed."""
    if len(choices) == 1:
        return choices[0], 0
    rng = np.random.default_rng([video_seed(scene_name, split, index), 0x717])
    return str(choices[int(rng.integers(len(choices)))]), int(rng.integers(0, 64))


def _videos(p: Preset, scenes=None):
    """``[(split, scene name, index, length)]`` of a preset, in the file's order."""
    out = []
    for split in SPLITS:
        names, per_scene, length = p.splits[split]
        out += [(split, name, i, length) for name in names
                if scenes is None or name in scenes for i in range(per_scene)]
    return out


def _render_into(fh, p: Preset, videos, custom, progress):
    """Render ``videos`` of preset ``p`` into the open HDF5 file ``fh``; one compiled
    renderer per scene."""
    renderers = {}
    for split, name, i, length in videos:
        if name not in renderers:
            renderers[name] = VideoRenderer(_with_effects(scene_of(name, custom), p.effects),
                                            p.size, p.factors, p.spp, p.spp_match,
                                            targets=p.targets)
        r = renderers[name]
        jit, phase = video_jitter(p.jitters, name, split, i)
        video = r.video(split, i, length, progress=progress, jitter=jit, jitter_phase=phase,
                        hold_from=p.hold_from)
        g = fh.create_group(f"{split}/{name}_{i:02d}")
        g.attrs.update({"scene": name, "effects": json.dumps(list(r.scene.effects)),
                        "length": length, "index": i, "jitter_sequence": jit,
                        "jitter_phase": phase, "near": r.scene.near, "far": r.scene.far})
        if p.hold_from is not None:
            g.attrs["hold_from"] = p.hold_from
        write_video(g, video, p.factors, p.spp_match)


def _worker(args_path):
    """A worker process (``python -m jtus.sim.generate ARGS``): its share of the videos
    into a part file, on one core, printing a line per frame rendered."""
    with open(args_path, "rb") as fh:
        p, videos, custom, path, core = pickle.load(fh)
    if core is not None and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {core})
    with h5py.File(path, "w") as fh:
        _render_into(fh, p, videos, custom, lambda n: print(n, flush=True))


def _start_worker(p, videos, custom, path, core):
    """A worker as a fresh interpreter (``-m``: no caller's ``__main__`` re-imported, no
    forked JAX runtime), with this process's ``jtus`` first on its path."""
    with open(path + ".args", "wb") as fh:
        pickle.dump((p, videos, custom, path, core), fh)
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [root] + [x for x in os.environ.get("PYTHONPATH", "").split(os.pathsep) if x]))
    return subprocess.Popen([sys.executable, "-m", "jtus.sim.generate", path + ".args"],
                            stdout=subprocess.PIPE, text=True, env=env)


def _render_parallel(fh, p, videos, custom, workers, bar):
    """Render ``videos`` in ``workers`` processes (scenes dealt round-robin, each
    worker pinned to a core of this process's), then copy their videos into ``fh`` in
    the preset's order: the same file a single process writes."""
    names = list(dict.fromkeys(v[1] for v in videos))
    share = [[v for v in videos if names.index(v[1]) % workers == k] for k in range(workers)]
    cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    with tempfile.TemporaryDirectory(dir=os.path.dirname(os.path.abspath(fh.filename))) as d:
        parts = [os.path.join(d, f"part{k}.h5") for k in range(workers)]
        procs = [_start_worker(p, share[k], custom, parts[k],
                               cores[k % len(cores)] if cores else None)
                 for k in range(workers) if share[k]]
        try:
            readers = [threading.Thread(target=lambda proc=proc: [
                bar.update(int(line)) for line in proc.stdout], daemon=True) for proc in procs]
            for t in readers:
                t.start()
            codes = [proc.wait() for proc in procs]
            for t in readers:
                t.join()
        finally:
            for proc in procs:
                if proc.poll() is None:
                    proc.kill()
        if any(codes):
            raise RuntimeError(f"generate: worker processes failed (exit codes {codes}); "
                               f"nothing was written")
        srcs = [h5py.File(part, "r") if share[k] else None for k, part in enumerate(parts)]
        try:
            for split, name, i, _ in videos:
                src = srcs[names.index(name) % workers]
                src.copy(src[f"{split}/{name}_{i:02d}"], fh.require_group(split),
                         name=f"{name}_{i:02d}")
        finally:
            for src in srcs:
                if src is not None:
                    src.close()


def generate(name_or_preset, out, progress=True, scenes=None, custom=None, workers=1):
    """Render a preset into ``out`` (HDF5), atomically, with a progress bar.

    ``scenes``: render only these names of the preset; ``custom``: ``{name: Scene}``
    for names that are not built-in (scenes declared in JSON); ``workers``: processes
    rendering in parallel, each pinned to a core (``default_workers()``: one per core
    this process may use); every count writes the same videos."""
    p = preset(name_or_preset) if isinstance(name_or_preset, str) else name_or_preset
    if not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers: expected a positive integer, got {workers!r}")
    videos = _videos(p, scenes)
    bar = tqdm(total=sum(v[3] for v in videos), unit="frame", desc=f"generate {out}",
               disable=not progress)
    with atomic_path(out) as tmp, h5py.File(tmp, "w") as fh:
        write_root_attrs(fh, p.size, p.factors, p.spp, p.spp_match, p.targets)
        if workers > 1 and len({v[1] for v in videos}) > 1:
            _render_parallel(fh, p, videos, custom, workers, bar)
        else:
            _render_into(fh, p, videos, custom, bar.update)
        fh.flush()
    bar.close()
    return out


def default_workers():
    """One rendering process per core this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else \
        (os.cpu_count() or 1)


def ensure_dataset(path, preset_name, progress=True, workers=None):
    """``path``, generated from the built-in preset ``preset_name`` first if missing
    (``workers``: default one process per core)."""
    if not os.path.exists(path):
        print(f"{path} is missing: generating the {preset_name!r} preset (once)",
              file=sys.stderr)
        generate(preset_name, path, progress=progress, workers=workers or default_workers())
    return path


if __name__ == "__main__":
    hostmem.keep_freed_memory()
    _worker(sys.argv[1])
