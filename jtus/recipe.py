"""What a training run is made of, from its ``Config``: the model, the loss, the
optimizer, the window plan and the first carry; and the checks on its dataset.

``jtus.train`` runs these; the experiments and tests call the same functions, so a
sweep trains exactly what ``python -m jtus.train`` would.
"""

from __future__ import annotations

import dataclasses
import os
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jtus import losses, models, rollout
from jtus.config import PRESETS, Config
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
    names VGG-16 weights; with ``temporal_from``, the loss of the frames before it
    (temporal weight 1; ``late_loss_for`` gives the rest)."""
    return _loss(config, 1.0 if config.temporal_from else config.temporal_weight)


def late_loss_for(config: Config):
    """``(temporal_from, the loss with temporal_weight)`` for ``rollout.window_loss``'s
    ``late``, or None when every frame has the same loss."""
    if not config.temporal_from:
        return None
    return config.temporal_from, _loss(config, config.temporal_weight)


def _loss(config, temporal_weight):
    return losses.make(config.loss, config.factor, theta=config.theta,
                       temporal_weight=temporal_weight,
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


# what ``Config.alternate`` takes from its preset: where the sequences come from and
# how they are cut into optimizer steps; the model, optimizer, crop and batch stay, and
# so does the loss unless ``Config.alternate_loss`` names another
ALTERNATE_FIELDS = ("dataset", "data_preset", "mix_dataset", "mix_fraction", "seq_len",
                    "mode", "k1", "k2", "loss_frames", "extend_holds")


def alternate_config(config: Config) -> Optional[Config]:
    """The config of a run's every second training sequence (the 2nd, 4th, ... of each
    epoch): ``config`` with ``ALTERNATE_FIELDS`` from the preset ``config.alternate``,
    and the loss ``config.alternate_loss`` when one is named (else the run's own);
    None when the run does not alternate. Moving content between whole long holds, for
    example, needs two sequence lengths, which one batch cannot hold."""
    if not config.alternate:
        return None
    if config.alternate not in PRESETS:
        raise ValueError(f"alternate: unknown preset {config.alternate!r}; expected one of "
                         f"{', '.join(PRESETS)}")
    base = PRESETS[config.alternate]
    if base.alternate:
        raise ValueError(f"alternate: preset {config.alternate!r} alternates itself "
                         f"(with {base.alternate!r}); name a preset that does not")
    loss = config.alternate_loss or config.loss
    # the temporal weight belongs to the loss: it stays only with a loss that weighs
    weighted = loss in losses.WEIGHTED_TEMPORAL
    return dataclasses.replace(config, alternate="", alternate_loss="", loss=loss,
                               temporal_weight=config.temporal_weight if weighted else 1.0,
                               temporal_from=config.temporal_from if weighted else 0,
                               **{f: getattr(base, f) for f in ALTERNATE_FIELDS})


def sources(config: Config) -> list:
    """The configs whose sequences a run's epoch takes in turn: ``[config]``, or
    ``[config, alternate_config(config)]``."""
    alt = alternate_config(config)
    return [config] if alt is None else [config, alt]


def steps_per_epoch(config: Config) -> int:
    """Optimizer steps in one epoch: each sequence gives one per window of its plan."""
    kinds = sources(config)
    return sum(len(plan(c).windows) * len(range(i, config.steps_per_epoch, len(kinds)))
               for i, c in enumerate(kinds))


def optimizer_for(config: Config):
    """Adam at ``lr``, or warm-up then cosine decay to ``lr * lr_end`` over the run's
    optimizer steps; after global-norm clipping when ``clip_norm`` > 0."""
    lr = config.lr
    if config.schedule == "cosine":
        total = config.epochs * steps_per_epoch(config)
        lr = optax.warmup_cosine_decay_schedule(
            0.0, config.lr, min(config.warmup_steps, max(total - 1, 0)), max(total, 1),
            config.lr * config.lr_end)
    adam = optax.adam(lr)
    return optax.chain(optax.clip_by_global_norm(config.clip_norm), adam) if config.clip_norm \
        else adam


def start_carry(model, frames, targets) -> rollout.Carry:
    """The carry at the start of time-major training sequences."""
    return rollout.start(rollout.first_state(model, frames), targets[0])


def training_sequence(config: Config, model, ds, mix, batch, rng, accept=None):
    """``(frames, targets, carry)`` on the device: one draw of ``train_crops`` and the
    carry at its start."""
    frames, targets, _ = train_crops(config, ds, mix, batch, rng, accept)
    frames, targets = jax.tree_util.tree_map(jnp.asarray, (frames, targets))
    return frames, targets, start_carry(model, frames, targets)


def window_slices(plan: Plan, frames, targets):
    """``(frames, targets)`` of each of ``plan``'s windows in turn (time-major slices)."""
    for w in plan.windows:
        yield jax.tree_util.tree_map(lambda x: x[w.start:w.stop], (frames, targets))


def mix_count(config: Config, batch):
    """How many of ``batch`` crops come from ``config.mix_dataset`` (at least one from
    each dataset when mixing)."""
    if not config.mix_dataset:
        return 0
    return int(min(max(round(batch * config.mix_fraction), 1), batch - 1))


def train_crops(config: Config, ds, mix, batch, rng, accept=None):
    """``(Frame [T,B,...], targets, [(dataset path, video, t0, y, x)])``: ``batch``
    training crops, the last ``mix_count`` of them from ``mix`` (an open ``Dataset``
    of ``config.mix_dataset``, or None)."""
    n_mix = mix_count(config, batch) if mix is not None else 0
    frames, targets, index = ds.crops("train", config.factor, batch - n_mix, config.seq_len,
                                      config.crop, rng, return_index=True, accept=accept,
                                      extend_holds=config.extend_holds)
    index = [(config.dataset, *i) for i in index]
    if n_mix:
        f2, t2, i2 = mix.crops("train", config.factor, n_mix, config.seq_len, config.crop, rng,
                               return_index=True, accept=accept,
                               extend_holds=config.extend_holds)
        frames, targets = jax.tree_util.tree_map(lambda a, b: np.concatenate([a, b], 1),
                                                 (frames, targets), (f2, t2))
        index += [(config.mix_dataset, *i) for i in i2]
    return frames, targets, index


def check_data(config: Config):
    """Refuse, before anything is written, a dataset this config cannot train on: the
    factor, the crop against the frame size, the window against the videos' lengths,
    empty train or validation splits; the same for an alternate preset's data."""
    for c in sources(config):
        _check_source(c)


def _check_source(config: Config):
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
        _check_lengths(config, ds, "train", config.seq_len, config.extend_holds)
        _check_lengths(config, ds, "val", plan(config).window, config.extend_holds)
        if config.mix_dataset:
            _check_mix(config, ds)


def _check_mix(config: Config, ds):
    """The mixed-in dataset: there, the same factor and colour kind as ``dataset``,
    frames that hold the crop, training videos that hold the sequence."""
    path = config.mix_dataset
    if not os.path.isfile(path):
        raise ValueError(f"mix_dataset: {path} does not exist; generate it first (python -m "
                         f"jtus.data generate --preset diverse --out {path})")
    with Dataset(path) as mix:
        if config.factor not in mix.factors:
            raise ValueError(f"mix_dataset: {path} holds factors {mix.factors}, got "
                             f"{config.factor}")
        if mix.hdr != ds.hdr:
            raise ValueError(f"mix_dataset: {path} and {config.dataset} differ in HDR colour")
        if config.crop > min(mix.size):
            raise ValueError(f"crop: {config.crop} exceeds the frame size "
                             f"{mix.size[0]}x{mix.size[1]} of {path}")
        if not mix.videos("train"):
            raise ValueError(f"mix_dataset: no videos in split 'train' of {path}")
        _check_lengths(config, mix, "train", config.seq_len, config.extend_holds)


def _check_lengths(config: Config, ds, split, need, extend_holds):
    """Every video of ``split`` holds ``need`` frames; with ``extend_holds``, at least
    one gives them (the others are not drawn)."""
    names = ds.videos(split)
    if not names:
        raise ValueError(f"dataset: no videos in split {split!r} of {ds.path}")
    if extend_holds:
        if not any(ds.sequence_frames(split, n, config.factor, need, True) is not None
                   for n in names):
            raise ValueError(f"seq_len: no {split} video of {ds.path} gives {need} frames, "
                             "not even with its hold continued (extend_holds needs videos "
                             "generated with a hold of at least one jitter period)")
        return
    shortest = min(ds.file[f"{split}/{n}/target"].shape[0] for n in names)
    if need > shortest:
        held = any(ds.hold_period(split, n, config.factor) is not None for n in names)
        raise ValueError(f"seq_len: {need} frames exceed the shortest {split} video "
                         f"of {ds.path} ({shortest} frames)" + (
                             "; extend_holds (--extend-holds) continues its holds"
                             if held and split == "train" else ""))
