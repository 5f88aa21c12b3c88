"""What a training run is made of, from its ``Config``: the model, the loss, the
optimizer, the window plan and the first carry; and the checks on its dataset.

``jtus.train`` runs these; the experiments and tests call the same functions, so a
sweep trains exactly what ``python -m jtus.train`` would.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import optax

from jtus import losses, models, rollout
from jtus.config import Config
from jtus.data.dataset import Dataset


class Plan(NamedTuple):
    """How one training sequence becomes optimizer steps."""
    window: int                 # frames per optimizer step (BPTT: seq_len; TBPTT: k2)
    loss_frames: int            # the loss is averaged over the last this many of a window
    keep_at: Optional[int]      # TBPTT with k1 < k2: the carry after k1 frames starts the next
    windows: list               # rollout.Window per optimizer step of one sequence


def model_config(config: Config):
    """The model's own config for a run: its model, factor and model overrides."""
    return models.config_for(config.model, config.factor, **dict(config.model_overrides))


def model_for(config: Config) -> models.Model:
    """The ``Model`` a run trains (``model_config``)."""
    return models.spec(config.model).make(model_config(config))


def loss_for(config: Config):
    """``losses.make(config.loss, ...)``, plus NSRR's perceptual term when the config
    names VGG-16 weights."""
    return losses.make(config.loss, config.factor, theta=config.theta,
                       perceptual_weights=config.perceptual_weights or None,
                       perceptual_weight=config.perceptual_weight)


def accept_for(config: Config):
    """The model's training-crop acceptance hook (the MLP upscaler keeps crops with a
    probability rising with their gradient magnitude, Spencer); None: take every crop."""
    return models.spec(config.model).accept


def plan(config: Config) -> Plan:
    if config.mode == "bptt":
        return Plan(config.seq_len, config.loss_frames, None,
                    [rollout.Window(0, config.seq_len)])
    keep = config.k1 if config.k1 < config.k2 else None
    return Plan(config.k2, config.k1, keep,
                rollout.tbptt_windows(config.seq_len, config.k1, config.k2))


def optimizer_for(config: Config):
    """Adam at ``lr``, or warm-up then cosine decay to ``lr * lr_end`` over the run's
    optimizer steps; after global-norm clipping when ``clip_norm`` > 0."""
    lr = config.lr
    if config.schedule == "cosine":
        total = config.epochs * config.steps_per_epoch * len(plan(config).windows)
        lr = optax.warmup_cosine_decay_schedule(
            0.0, config.lr, min(config.warmup_steps, max(total - 1, 0)), max(total, 1),
            config.lr * config.lr_end)
    adam = optax.adam(lr)
    return optax.chain(optax.clip_by_global_norm(config.clip_norm), adam) if config.clip_norm \
        else adam


def start_carry(model, frames, targets) -> rollout.Carry:
    """The carry at the start of time-major training sequences."""
    return rollout.start(rollout.first_state(model, frames), targets[0])


def check_data(config: Config):
    """Refuse, before anything is written, a dataset this config cannot train on: the
    factor, the crop against the frame size, the window against the videos' lengths,
    empty train or validation splits."""
    with Dataset(config.dataset) as ds:
        if config.factor not in ds.factors:
            raise ValueError(f"factor: {config.dataset} holds factors {ds.factors}, got "
                             f"{config.factor}")
        if ds.hdr and not model_config(config).hdr:
            raise ValueError(f"dataset: {config.dataset} holds HDR colour with an exposure "
                             "per frame; train a model on tone-mapped colour (preset hdr, "
                             "or model override hdr=True)")
        if config.crop > min(ds.size):
            raise ValueError(f"crop: {config.crop} exceeds the frame size "
                             f"{ds.size[0]}x{ds.size[1]} of {config.dataset}")
        window = plan(config).window
        for split, need in (("train", config.seq_len), ("val", window)):
            names = ds.videos(split)
            if not names:
                raise ValueError(f"dataset: no videos in split {split!r} of {config.dataset}")
            shortest = min(ds.file[f"{split}/{n}/target"].shape[0] for n in names)
            if need > shortest:
                raise ValueError(f"seq_len: {need} frames exceed the shortest {split} video "
                                 f"of {config.dataset} ({shortest} frames)")
