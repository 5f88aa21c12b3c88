"""The configuration of a training run (``Config``), its presets and its JSON form.

A run's ``config.json`` (and the ``.json`` beside exported weights) is
``to_json(config)``; ``from_json`` reads it back with every field checked, naming the
file and the field on bad input. ``jtus.recipe`` turns a config into the model, loss,
optimizer and window plan of a run; ``jtus.train`` runs it.
"""

from __future__ import annotations

import dataclasses
import json
import math

from jtus import losses, rollout
from jtus.files import read_json_fields

# --remat's names -> Config.remat: rematerialization of the scanned step trades time for
# memory (docs/performance.md, "Memory")
REMAT_CHOICES = {"none": False, "full": True, **{k: k for k in rollout.REMAT_POLICIES},
                 "reverse": "reverse"}


@dataclasses.dataclass(frozen=True)
class Config:
    """A training run. The presets below are the documented starting points."""
    model: str = "dlctus"
    factor: int = 4
    loss: str = "l1"
    theta: float = 0.5
    temporal_weight: float = 1.0  # the weight of the temporal term of losses.WEIGHTED_TEMPORAL
    temporal_from: int = 0      # > 0: temporal_weight from this frame of each sequence on,
                                # the thesis's weight 1 before it (recipe.late_loss_for)
    seq_len: int = 8
    loss_frames: int = 3
    mode: str = "bptt"          # bptt | tbptt
    k1: int = 4
    k2: int = 8
    remat: bool | str = False   # False, True (full), a rollout.REMAT_POLICIES name, "reverse"
    hoist: bool = False         # the model's per-frame preparation before the scan
    batch: int = 4
    crop: int = 64
    lr: float = 1e-3
    schedule: str = "constant"  # constant | cosine (warm-up, then cosine decay to lr_end)
    warmup_steps: int = 0
    lr_end: float = 0.05        # cosine: final rate as a fraction of lr
    clip_norm: float = 0.0      # global gradient-norm clip; 0 = off
    epochs: int = 8
    steps_per_epoch: int = 100
    val_batches: int = 2
    val_videos: int = 4
    dataset: str = "data/default.h5"
    data_preset: str = "default"  # generated into ``dataset`` when the file is missing
    seed: int = 0
    perceptual_weights: str = ""  # .npz of VGG-16 (jtus.perceptual): adds NSRR's term
    perceptual_weight: float = 0.1
    model_overrides: tuple = ()   # (("warp", "bilinear"), ...) for the model's config
    init_from: str = ""           # start from these parameters (a checkpoint of the same
                                  # model and factor); the optimizer starts fresh
    test_videos: int = 0          # the final comparison: the first this many test videos
                                  # of each family; 0 = all
    mix_dataset: str = ""         # a second dataset whose training videos give a share of
    mix_fraction: float = 0.5     # each batch (rounded to whole crops); validation and the
                                  # final comparison stay on ``dataset``
    extend_holds: bool = False    # a held video shorter than seq_len continues its hold
                                  # (jtus.data.Dataset.sequence_frames)
    alternate: str = ""           # a preset: every second training sequence is drawn from
                                  # its data and cut into its windows (recipe.alternate_config)
    alternate_loss: str = ""      # the loss of those sequences; '' = the run's own

    def __post_init__(self):
        positive = ("factor", "seq_len", "batch", "crop", "epochs", "steps_per_epoch",
                    "val_batches", "val_videos")
        for name in positive:
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"{name}: expected a positive integer, got {v!r}")
        if self.crop % 4 or self.crop % self.factor:
            raise ValueError(f"crop: expected a multiple of 4 and of factor {self.factor}, "
                             f"got {self.crop}")
        for name in ("lr", "theta", "lr_end", "clip_norm", "perceptual_weight",
                     "temporal_weight"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{name}: expected a finite number, got {v!r}")
        if self.lr <= 0:
            raise ValueError(f"lr: expected > 0, got {self.lr}")
        if (not isinstance(self.seed, int) or isinstance(self.seed, bool)
                or not 0 <= self.seed < 2 ** 32):
            raise ValueError(f"seed: expected an integer in [0, 2**32), got {self.seed!r}")
        if not 0 <= self.lr_end <= 1:
            raise ValueError(f"lr_end: expected a fraction of lr in [0, 1], got {self.lr_end}")
        if self.clip_norm < 0 or self.warmup_steps < 0:
            raise ValueError(f"clip_norm, warmup_steps: expected >= 0, got {self.clip_norm}, "
                             f"{self.warmup_steps}")
        if self.mode not in ("bptt", "tbptt"):
            raise ValueError(f"mode: expected bptt or tbptt, got {self.mode!r}")
        if self.mode == "bptt" and not 1 <= self.loss_frames <= self.seq_len:
            raise ValueError(f"loss_frames: expected 1..seq_len={self.seq_len}, "
                             f"got {self.loss_frames}")
        if self.mode == "tbptt":
            rollout.tbptt_windows(self.seq_len, self.k1, self.k2)
        if self.schedule not in ("constant", "cosine"):
            raise ValueError(f"schedule: expected constant or cosine, got {self.schedule!r}")
        if self.remat not in REMAT_CHOICES.values():
            raise ValueError(f"remat: expected one of {tuple(REMAT_CHOICES.values())}, got "
                             f"{self.remat!r}")
        if not isinstance(self.test_videos, int) or self.test_videos < 0:
            raise ValueError(f"test_videos: expected an integer >= 0, got {self.test_videos!r}")
        if not isinstance(self.mix_dataset, str):
            raise ValueError(f"mix_dataset: expected a path or '', got {self.mix_dataset!r}")
        if (not isinstance(self.mix_fraction, (int, float)) or isinstance(self.mix_fraction, bool)
                or not 0 < self.mix_fraction < 1):
            raise ValueError(f"mix_fraction: expected a fraction in (0, 1), got "
                             f"{self.mix_fraction!r}")
        if not isinstance(self.alternate, str):
            raise ValueError(f"alternate: expected a preset name or '', got {self.alternate!r}")
        self._check_losses()

    def _check_losses(self):
        """The loss names, and a temporal weight only where a loss of the run has one."""
        if self.loss not in losses.NAMES:
            raise ValueError(f"loss: expected one of {losses.NAMES}, got {self.loss!r}")
        if self.alternate_loss not in ("",) + losses.NAMES:
            raise ValueError(f"alternate_loss: expected '' or one of {losses.NAMES}, got "
                             f"{self.alternate_loss!r}")
        if self.temporal_weight < 0:
            raise ValueError(f"temporal_weight: expected >= 0, got {self.temporal_weight}")
        if (self.temporal_weight != 1.0 and self.loss not in losses.WEIGHTED_TEMPORAL
                and self.alternate_loss not in losses.WEIGHTED_TEMPORAL):
            raise ValueError(f"temporal_weight: {self.temporal_weight} weighs the temporal "
                             f"term of {' or '.join(losses.WEIGHTED_TEMPORAL)}, which this "
                             f"config's loss ({self.loss!r}) does not use")
        if self.alternate_loss and not self.alternate:
            raise ValueError(f"alternate_loss: {self.alternate_loss!r} needs an alternate "
                             "preset (alternate), which this config does not name")
        self._check_temporal_from()

    def _check_temporal_from(self):
        """``temporal_from`` counts frames of a sequence: it needs a weighted temporal
        term to move and one training window per sequence (the window's index is then
        the sequence's)."""
        v = self.temporal_from
        if not isinstance(v, int) or isinstance(v, bool) or v < 0:
            raise ValueError(f"temporal_from: expected an integer >= 0, got {v!r}")
        if not v:
            return
        if self.loss not in losses.WEIGHTED_TEMPORAL or self.temporal_weight == 1.0:
            raise ValueError(f"temporal_from: {v} moves the temporal weight of "
                             f"{' or '.join(losses.WEIGHTED_TEMPORAL)} from 1 to "
                             f"temporal_weight, but this config has loss {self.loss!r} and "
                             f"temporal_weight {self.temporal_weight}")
        if self.mode == "tbptt" and not self.k1 == self.k2 == self.seq_len:
            raise ValueError(f"temporal_from: needs one window per sequence (mode bptt, or "
                             f"k1 = k2 = seq_len), got k1={self.k1}, k2={self.k2}, "
                             f"seq_len={self.seq_len}")
        if v >= self.seq_len:
            raise ValueError(f"temporal_from: expected a frame before seq_len={self.seq_len}, "
                             f"got {v}")


PRESETS = {
    # seconds: for tests
    "tiny": Config(factor=4, seq_len=4, loss_frames=2, batch=2, crop=16, epochs=2,
                   steps_per_epoch=2, val_batches=1, val_videos=1, dataset="data/tiny.h5",
                   data_preset="tiny"),
    # minutes on 2 CPU cores, on the built-in default data; the final comparison on 4
    # test videos
    "default": Config(test_videos=4),
    # thesis sec. 4.3: 256 crops, batch 4, sequence 30, loss on the last 5, Adam 1e-4,
    # 200 epochs; for a GPU machine and the paper-size data
    "paper": Config(seq_len=30, loss_frames=5, batch=4, crop=256, lr=1e-4, epochs=200,
                    steps_per_epoch=500, val_batches=10, val_videos=10,
                    dataset="data/paper.h5", data_preset="paper"),
    # generalization (docs/weights.md): the randomized data with every jitter sequence,
    # crop 128, 16-frame sequences as TBPTT windows of 8 (the best of the sequence-
    # length sweep, docs/results.md), warm-up then cosine decay, gradient clipping;
    # 60 epochs x 200 sequences (24,000 optimizer steps), hours on 2 CPU cores:
    #   nohup python -m jtus.train --preset diverse --factor 4 --workdir runs/diverse-x4 &
    #   python -m jtus.train --preset diverse --factor 4 --workdir runs/diverse-x4 --resume
    "diverse": Config(seq_len=16, mode="tbptt", k1=8, k2=8, loss_frames=8, batch=4, crop=128,
                      lr=1e-3, schedule="cosine", warmup_steps=300, lr_end=0.05,
                      clip_norm=1.0, epochs=60, steps_per_epoch=200, val_batches=4,
                      val_videos=8, dataset="data/diverse.h5", data_preset="diverse"),
}
# HDR (docs/conventions.md): the diverse recipe on the same scenes with highlights above
# 1 and an exposure per frame; the model runs on tone-mapped pre-exposed colour
PRESETS["hdr"] = dataclasses.replace(PRESETS["diverse"], dataset="data/hdr.h5",
                                     data_preset="hdr", model_overrides=(("hdr", True),))
# game content (docs/weights.md): the diverse recipe on OpenArena's levels (data preset
# game), meant to start from a diverse run's weights at a lower rate:
#   python -m jtus.train --preset game --init-from experiments/weights/dlctus-diverse-x4.msgpack
PRESETS["game"] = dataclasses.replace(PRESETS["diverse"], dataset="data/game.h5",
                                      data_preset="game", lr=3e-4, warmup_steps=100,
                                      epochs=20)
# game content mixed with the randomized scenes: half of each batch from each; the
# shipped weights' second stage (12 epochs at 4x, 8 at 2x; docs/weights.md)
# (python -m jtus.data generate --preset diverse --out data/diverse.h5 first)
PRESETS["game-mix"] = dataclasses.replace(PRESETS["game"], mix_dataset="data/diverse.h5",
                                          mix_fraction=0.5)
# the game levels' static holds (data preset game-holds: 16 moving frames, then 32
# where only the jitter moves): whole 48-frame sequences as TBPTT windows of 16, so the
# state after a jitter cycle of stillness gets a gradient; a fine-tune from weights
# that already upsample moving content (docs/weights.md):
#   python -m jtus.train --preset game-holds --init-from jtus/weights/dlctus-x4.msgpack
PRESETS["game-holds"] = dataclasses.replace(
    PRESETS["game"], dataset="data/game-holds.h5", data_preset="game-holds", seq_len=48,
    k1=16, k2=16, loss_frames=16, lr=1e-4, warmup_steps=20, epochs=4, steps_per_epoch=100,
    val_videos=5, val_batches=2)
# both families' holds, half and half in every batch
#   (python -m jtus.data generate --preset diverse-holds --out data/diverse-holds.h5 first)
PRESETS["holds-mix"] = dataclasses.replace(PRESETS["game-holds"],
                                           mix_dataset="data/diverse-holds.h5",
                                           mix_fraction=0.5)
# the same with 64 still frames (data presets game-long-holds and diverse-long-holds):
# 80-frame sequences as five TBPTT windows of 16, so the state after four jitter cycles
# of stillness gets a gradient
PRESETS["long-holds-mix"] = dataclasses.replace(PRESETS["holds-mix"],
                                                dataset="data/game-long-holds.h5",
                                                data_preset="game-long-holds",
                                                mix_dataset="data/diverse-long-holds.h5",
                                                seq_len=80)
# the same sequences as one BPTT window of 80 frames (one Adam step per sequence, 400
# in all), so the loss on the last still frames reaches back through the whole hold; the
# shipped weights' fourth stage at both factors, from the third (docs/weights.md)
PRESETS["long-holds-bptt"] = dataclasses.replace(PRESETS["long-holds-mix"], k1=80, k2=80)
# the holds-mix data with each hold continued to 256 still frames (the stored jitter
# cycle repeated: the frames a longer hold would render), as TBPTT windows of 16: the
# states deep in a hold, where the accumulation has settled, get a gradient
# (17 windows, so 17 Adam steps, a sequence: 2 epochs of 50 sequences are 1,700 steps)
PRESETS["deep-holds-mix"] = dataclasses.replace(PRESETS["holds-mix"], seq_len=272,
                                                extend_holds=True, epochs=2,
                                                steps_per_epoch=50)
PRESETS["hdr-tiny"] = dataclasses.replace(PRESETS["tiny"], dataset="data/hdr-tiny.h5",
                                          data_preset="hdr-tiny",
                                          model_overrides=(("hdr", True),))


def to_json(config: Config) -> str:
    return json.dumps(dataclasses.asdict(config), indent=1)


def from_json(path) -> Config:
    """The ``Config`` in the JSON file ``path``; ``ValueError`` naming the file on an
    unknown key or an invalid value."""
    data = read_json_fields(path, Config, "config key")
    over = data.get("model_overrides", ())
    if not isinstance(over, (list, tuple)) or not all(
            isinstance(x, (list, tuple)) and len(x) == 2 and isinstance(x[0], str) for x in over):
        raise ValueError(f"{path}: model_overrides: expected a list of [name, value] pairs, "
                         f"got {over!r}")
    data["model_overrides"] = tuple(tuple(x) for x in over)
    try:
        return Config(**data)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: {e}") from e
