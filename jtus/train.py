"""Training: ``python -m jtus.train``, thin over ``train_and_evaluate(config, workdir)``.

    python -m jtus.train                       # the main job: default preset, see README
    python -m jtus.train --preset tiny --workdir runs/tiny
    python -m jtus.train --preset paper --factor 2 --workdir runs/paper-x2
    python -m jtus.train --loss st-linear --theta 0.5 --seq-len 16 --mode tbptt --k1 4 --k2 8

One jit region per optimizer step with the train state donated (``make_train_step``),
over ``jtus.rollout`` windows: BPTT (the loss on the last ``loss_frames`` frames of
``seq_len``) or TBPTT (k1, k2). Sequences start with ``frame.reset`` set, so the model
initializes its history inside the step and every window shares one trace.

After each epoch: the loss on fixed validation crops, PSNR/SSIM over whole validation
videos (thesis sec. 4.3.5), an atomic checkpoint, ``metrics.json``/``metrics.csv`` and
``training.png``. ``--resume`` continues from the last checkpoint exactly: the crops of
epoch e come from ``default_rng([seed, e])`` and the checkpoint holds the step, the
parameters and the optimizer state.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import json
import os
import sys
import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jtus import losses, metrics, rollout

# ---------------------------------------------------------------- train step


class TrainState(NamedTuple):
    step: jax.Array
    params: Any
    opt_state: Any


def create_train_state(params, optimizer) -> TrainState:
    return TrainState(jnp.zeros((), jnp.int32), params, optimizer.init(params))


def make_train_step(model, loss_fn, optimizer, *, loss_frames, keep_at=None, remat=False,
                    unroll=1, jit=True):
    """``(train_state, carry, frames [T,B,...], targets [T,B,H,W,3]) ->
    (train_state, next carry, stats)``.

    BPTT: a window of the whole sequence, ``loss_frames`` = K. TBPTT(k1, k2): windows
    of k2 frames from ``rollout.tbptt_windows``, ``loss_frames = k1`` and
    ``keep_at = k1`` when k1 < k2; the returned carry (gradient cut) starts the next
    window.
    """

    def train_step(ts: TrainState, carry: rollout.Carry, frames, targets):
        def f(p):
            return rollout.window_loss(model.step, loss_fn, p, carry, frames, targets,
                                       loss_frames=loss_frames, keep_at=keep_at, remat=remat,
                                       unroll=unroll)

        (loss, (last, kept)), grads = jax.value_and_grad(f, has_aux=True)(ts.params)
        with jax.named_scope("optimizer"):
            updates, opt_state = optimizer.update(grads, ts.opt_state, ts.params)
            params = optax.apply_updates(ts.params, updates)
        nxt = jax.lax.stop_gradient(kept if keep_at is not None else last)
        stats = {"loss": loss, "grad_norm": optax.tree.norm(grads),
                 "param_norm": optax.tree.norm(params)}
        return TrainState(ts.step + 1, params, opt_state), nxt, stats

    return jax.jit(train_step, donate_argnums=(0, 1)) if jit else train_step


def data_mesh(batch):
    """A 1-D ``data`` mesh over the local devices when there are several and they
    divide the batch; None otherwise (one device: nothing to shard)."""
    devices = jax.local_devices()
    if len(devices) < 2:
        return None
    if batch % len(devices):
        print(f"warning: batch {batch} is not a multiple of the {len(devices)} devices; "
              f"training on one", file=sys.stderr)
        return None
    return jax.sharding.Mesh(np.array(devices), ("data",))


def shard(tree, mesh, axis):
    """Place every array of ``tree`` with its ``axis`` split over ``mesh``'s data axis
    (arrays without that axis, or not divisible, are replicated)."""
    from jax.sharding import NamedSharding, PartitionSpec as P

    n = mesh.devices.size

    def put(x):
        x = jnp.asarray(x)
        if x.ndim > axis and x.shape[axis] % n == 0:
            return jax.device_put(x, NamedSharding(mesh, P(*([None] * axis), "data")))
        return jax.device_put(x, NamedSharding(mesh, P()))

    return jax.tree_util.tree_map(put, tree)


# ---------------------------------------------------------------- configuration


@dataclasses.dataclass(frozen=True)
class Config:
    """A training run. The presets below are the documented starting points."""
    model: str = "dlctus"
    factor: int = 4
    loss: str = "l1"
    theta: float = 0.5
    seq_len: int = 8
    loss_frames: int = 3
    mode: str = "bptt"          # bptt | tbptt
    k1: int = 4
    k2: int = 8
    remat: bool = False
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

    def __post_init__(self):
        import math

        positive = ("factor", "seq_len", "batch", "crop", "epochs", "steps_per_epoch",
                    "val_batches", "val_videos")
        for name in positive:
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"{name}: expected a positive integer, got {v!r}")
        if self.crop % 4 or self.crop % self.factor:
            raise ValueError(f"crop: expected a multiple of 4 and of factor {self.factor}, "
                             f"got {self.crop}")
        for name in ("lr", "theta", "lr_end", "clip_norm", "perceptual_weight"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{name}: expected a finite number, got {v!r}")
        if self.lr <= 0:
            raise ValueError(f"lr: expected > 0, got {self.lr}")
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
        if self.loss not in losses.NAMES + ("kpn",):
            raise ValueError(f"loss: expected one of {losses.NAMES + ('kpn',)}, "
                             f"got {self.loss!r}")


PRESETS = {
    # seconds: for tests
    "tiny": Config(factor=4, seq_len=4, loss_frames=2, batch=2, crop=16, epochs=2,
                   steps_per_epoch=2, val_batches=1, val_videos=1, dataset="data/tiny.h5",
                   data_preset="tiny"),
    # minutes on 2 CPU cores, on the built-in default data
    "default": Config(),
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


# ---------------------------------------------------------------- pieces


def _model(config: Config):
    from jtus import models
    return models.build(config.model, config.factor, **dict(config.model_overrides))


def _loss(config: Config):
    if config.loss == "kpn":  # Herveau et al.'s alias-masked reference/gradient/temporal loss
        from jtus.models import kpn
        loss = kpn.make_loss(config.factor)
    else:
        loss = losses.make(config.loss, config.factor, theta=config.theta)
    if config.perceptual_weights:
        loss = losses.with_perceptual(loss, config.perceptual_weights, config.perceptual_weight)
    return loss


def _accept(config: Config):
    """The MLP upscaler keeps training crops with a probability rising with their
    gradient magnitude (Spencer); the other models take every crop."""
    if config.model == "mlp":
        from jtus.models import mlp
        return mlp.acceptance
    return None


def _optimizer(config: Config):
    lr = config.lr
    if config.schedule == "cosine":
        total = config.epochs * config.steps_per_epoch * len(_plan(config)[3])
        lr = optax.warmup_cosine_decay_schedule(
            0.0, config.lr, min(config.warmup_steps, max(total - 1, 0)), max(total, 1),
            config.lr * config.lr_end)
    adam = optax.adam(lr)
    return optax.chain(optax.clip_by_global_norm(config.clip_norm), adam) if config.clip_norm \
        else adam


def _plan(config: Config):
    """(window length, loss frames, keep_at, windows per sequence)."""
    if config.mode == "bptt":
        return config.seq_len, config.loss_frames, None, [rollout.Window(0, config.seq_len)]
    keep = config.k1 if config.k1 < config.k2 else None
    return config.k2, config.k1, keep, rollout.tbptt_windows(config.seq_len, config.k1, config.k2)


def ensure_dataset(config: Config, progress=True):
    if not os.path.exists(config.dataset):
        from jtus.data import dataset
        print(f"{config.dataset} is missing: generating the {config.data_preset!r} preset "
              f"(once)", file=sys.stderr)
        dataset.generate(config.data_preset, config.dataset, progress=progress)
    return config.dataset


def _start_carry(model, frames, targets):
    first = jax.tree_util.tree_map(lambda x: x[0], frames)
    return rollout.start(model.init_state(first), targets[0])


def _frame_metrics(factor):
    def fn(out, target, prev_out, prev_target, has_prev, frame):
        x, y = losses.errors(out, target, prev_out, prev_target, has_prev, frame, factor)
        mean = lambda v: jnp.mean(v, axis=(1, 2, 3))  # noqa: E731
        return {"psnr": metrics.psnr(out, target), "ssim": metrics.ssim(out, target),
                "spatial": mean(losses.st_linear_terms(x, y, 0.0)),
                "temporal": jnp.where(has_prev, mean(losses.st_linear_terms(x, y, 1.0)),
                                      jnp.nan)}
    return fn


@functools.lru_cache(maxsize=64)
def _video_metrics_fn(model, factor):
    """One jitted function per (model, factor): videos of one shape compile once."""
    return jax.jit(lambda p, s, f, t: rollout.metrics(model.step, p, s, f, t,
                                                      _frame_metrics(factor))[0])


def video_metrics(model, params, frames, targets, factor):
    """Per-frame PSNR, SSIM, spatial error (L_st-linear at θ=0) and temporal error
    (L_st-linear at θ=1, NaN on the first frame) over one video."""
    fn = _video_metrics_fn(model, factor)
    first = jax.tree_util.tree_map(lambda x: x[0], frames)
    ms = fn(params, model.init_state(first), frames, targets)
    return {k: np.asarray(v)[:, 0] for k, v in ms.items()}


# ---------------------------------------------------------------- checkpoints


def save_checkpoint(workdir, ts: TrainState, epoch, history):
    """Atomically write ``checkpoint.msgpack`` (step, epoch, params, optimizer state)
    and ``metrics.json``."""
    from flax import serialization

    from jtus.data.dataset import atomic_path

    payload = serialization.to_bytes({"epoch": epoch, "step": ts.step, "params": ts.params,
                                      "opt_state": ts.opt_state})
    with atomic_path(os.path.join(workdir, "checkpoint.msgpack")) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(payload)
    with atomic_path(os.path.join(workdir, "metrics.json")) as tmp:
        with open(tmp, "w") as fh:
            json.dump(history, fh, indent=1)


def load_checkpoint(workdir, ts: TrainState):
    """``(train_state, epoch, history)`` from ``workdir`` into the structure of ``ts``."""
    from flax import serialization

    path = os.path.join(workdir, "checkpoint.msgpack")
    with open(path, "rb") as fh:
        data = fh.read()
    target = {"epoch": 0, "step": ts.step, "params": ts.params, "opt_state": ts.opt_state}
    try:
        restored = serialization.from_bytes(target, data)
    except Exception as e:
        raise ValueError(f"{path}: not a checkpoint of this model and optimizer ({e})") from e
    history = []
    mpath = os.path.join(workdir, "metrics.json")
    if os.path.exists(mpath):
        with open(mpath) as fh:
            history = json.load(fh)
    state = TrainState(jnp.asarray(restored["step"]), restored["params"], restored["opt_state"])
    return state, int(restored["epoch"]), history


def load_params(path, config_path=None):
    """Parameters and training config of a checkpoint written by ``train`` (its config
    is ``config.json`` beside it) or by ``export_params`` (``<base>.json``)."""
    from flax import serialization

    workdir = os.path.dirname(os.path.abspath(path))
    beside = os.path.splitext(path)[0] + ".json"
    config_path = config_path or (beside if os.path.exists(beside)
                                  else os.path.join(workdir, "config.json"))
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such checkpoint")
    if not os.path.exists(config_path):
        raise FileNotFoundError(f"{path}: its config {config_path} is missing")
    config = config_from_json(config_path)
    model = _model(config)
    params = model.init(jax.random.PRNGKey(0))
    try:
        with open(path, "rb") as fh:
            raw = serialization.msgpack_restore(fh.read())
    except Exception as e:  # msgpack raises several types for damaged files
        raise ValueError(f"{path}: not a readable checkpoint ({type(e).__name__}: {e})") from e
    if not isinstance(raw, dict) or "params" not in raw:
        raise ValueError(f"{path}: no 'params' entry (keys: "
                         f"{sorted(raw) if isinstance(raw, dict) else type(raw).__name__})")
    want = {jax.tree_util.keystr(k): v for k, v in
            jax.tree_util.tree_flatten_with_path(params)[0]}
    try:
        got_tree = serialization.from_state_dict(params, raw["params"])
    except Exception as e:
        raise ValueError(f"{path}: parameters do not fit {config.model} at {config.factor}x "
                         f"({e})") from e
    for k, v in jax.tree_util.tree_flatten_with_path(got_tree)[0]:
        ref = want[jax.tree_util.keystr(k)]
        v = np.asarray(v)
        if v.shape != ref.shape or not np.issubdtype(v.dtype, np.floating):
            raise ValueError(f"{path}: parameter {jax.tree_util.keystr(k)} has shape {v.shape} "
                             f"and dtype {v.dtype}; {config.model} at {config.factor}x expects "
                             f"{ref.shape} floating")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{path}: parameter {jax.tree_util.keystr(k)} holds NaN or Inf")
    params = got_tree
    # device arrays: numpy leaves cannot be indexed by traced values (KPN's phase)
    return jax.tree_util.tree_map(jnp.asarray, params), config


def export_params(workdir, out_base):
    """Write a run's parameters alone (no optimizer state) as ``out_base.msgpack``, its
    config as ``out_base.json`` and its per-epoch log as ``out_base-training.csv``,
    each atomically: the form ``jtus/weights/`` ships and ``load_params`` reads."""
    import shutil

    from flax import serialization

    from jtus.data.dataset import atomic_path

    params, config = load_params(os.path.join(workdir, "checkpoint.msgpack"))
    os.makedirs(os.path.dirname(os.path.abspath(out_base)), exist_ok=True)
    with atomic_path(out_base + ".msgpack") as tmp:
        with open(tmp, "wb") as fh:
            fh.write(serialization.to_bytes({"params": params}))
    with atomic_path(out_base + ".json") as tmp:
        with open(tmp, "w") as fh:
            fh.write(config_to_json(config))
    csv = os.path.join(workdir, "metrics.csv")
    if os.path.exists(csv):
        with atomic_path(out_base + "-training.csv") as tmp:
            shutil.copyfile(csv, tmp)
    return out_base + ".msgpack"


def config_to_json(config: Config):
    return json.dumps(dataclasses.asdict(config), indent=1)


def config_from_json(path):
    from jtus.data.dataset import read_json_fields

    data = read_json_fields(path, Config, "config keys")
    data["model_overrides"] = tuple(tuple(x) for x in data.get("model_overrides", ()))
    try:
        return Config(**data)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: {e}") from e


def _write_csv(workdir, history):
    if not history:
        return
    keys = list(history[0])
    with open(os.path.join(workdir, "metrics.csv"), "w", newline="") as fh:
        w = csv.DictWriter(fh, keys)
        w.writeheader()
        w.writerows(history)


def plot_history(history, path):
    """Training loss, validation loss, validation PSNR and SSIM per epoch (thesis Fig. 16)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ep = [h["epoch"] for h in history]
    fig, ax = plt.subplots(1, 4, figsize=(14, 3))
    for a, key, title in zip(ax, ("train_loss", "val_loss", "val_psnr", "val_ssim"),
                             ("training loss", "validation loss", "validation PSNR (dB)",
                              "validation SSIM")):
        a.plot(ep, [h[key] for h in history], marker="o")
        a.set_title(title)
        a.set_xlabel("epoch")
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ---------------------------------------------------------------- the loop


def check_data(config: Config):
    """Refuse, before anything is written, a dataset this config cannot train on: the
    factor, the crop against the frame size, the window against the videos' lengths,
    empty train or validation splits."""
    from jtus.data.dataset import Dataset

    with Dataset(config.dataset) as ds:
        if config.factor not in ds.factors:
            raise ValueError(f"factor: {config.dataset} holds factors {ds.factors}, got "
                             f"{config.factor}")
        if config.crop > min(ds.size):
            raise ValueError(f"crop: {config.crop} exceeds the frame size "
                             f"{ds.size[0]}x{ds.size[1]} of {config.dataset}")
        window = _plan(config)[0]
        for split, need in (("train", config.seq_len), ("val", window)):
            names = ds.videos(split)
            if not names:
                raise ValueError(f"dataset: no videos in split {split!r} of {config.dataset}")
            shortest = min(ds.file[f"{split}/{n}/target"].shape[0] for n in names)
            if need > shortest:
                raise ValueError(f"seq_len: {need} frames exceed the shortest {split} video "
                                 f"of {config.dataset} ({shortest} frames)")


def _finite_or_stop(stats, workdir, epoch, step, last_good):
    loss, gnorm = float(stats["loss"]), float(stats["grad_norm"])
    if not (np.isfinite(loss) and np.isfinite(gnorm)):
        kept = (f"the checkpoint of epoch {last_good} is kept" if last_good
                else "no checkpoint was written")
        raise ValueError(f"training: non-finite loss ({loss}) or gradient norm ({gnorm}) at "
                         f"epoch {epoch}, step {step}; stopped, {kept} in {workdir} (NaN or Inf "
                         f"in the data, or a learning rate too high)")
    return loss


def train_and_evaluate(config: Config, workdir, resume=False, progress=True, stop_after=None,
                       overwrite=False):
    """Train ``config`` into ``workdir``; returns ``(params, history)``.

    A workdir that holds a run is continued with ``resume`` or replaced with
    ``overwrite``, never silently mixed; everything is checked before the first write.
    A non-finite loss or gradient stops the run and leaves the last good checkpoint.
    ``stop_after``: stop (as if killed) after that many epochs of this call, for tests.
    """
    from tqdm import tqdm

    from jtus.data.dataset import Dataset

    from jtus import models

    if config.model not in models.TRAINABLE:
        raise ValueError(f"model: {config.model!r} has no parameters to train; "
                         f"trainable: {models.TRAINABLE}")
    ckpt = os.path.join(workdir, "checkpoint.msgpack")
    if os.path.isfile(workdir):
        raise ValueError(f"workdir: {workdir} is a file; expected a folder")
    if os.path.exists(ckpt) and not (resume or overwrite):
        raise ValueError(f"workdir: {workdir} holds a run (checkpoint.msgpack); pass --resume "
                         f"to continue it or --overwrite to start it again")
    ensure_dataset(config, progress)
    check_data(config)
    os.makedirs(workdir, exist_ok=True)
    if overwrite and not resume:  # the old run goes only once the new one is valid
        for name in ("checkpoint.msgpack", "metrics.json", "metrics.csv", "training.png"):
            if os.path.exists(os.path.join(workdir, name)):
                os.remove(os.path.join(workdir, name))
    model, loss_fn, opt = _model(config), _loss(config), _optimizer(config)
    params = model.init(jax.random.PRNGKey(config.seed))
    if config.init_from:
        params, init_cfg = load_params(config.init_from)
        if (init_cfg.model, init_cfg.factor) != (config.model, config.factor):
            raise ValueError(f"init_from: {config.init_from} holds {init_cfg.model} at "
                             f"{init_cfg.factor}x, this run trains {config.model} at "
                             f"{config.factor}x")
    ts = create_train_state(params, opt)
    start_epoch, history = 0, []
    cfg_path = os.path.join(workdir, "config.json")
    if resume and os.path.exists(os.path.join(workdir, "checkpoint.msgpack")):
        # a resumed run may be extended (more --epochs); anything else must match
        if (os.path.exists(cfg_path) and dataclasses.replace(
                config_from_json(cfg_path), epochs=config.epochs) != config):
            raise ValueError(f"{workdir}: --resume with a different config than "
                             f"{cfg_path} (only --epochs may change); use a new --workdir")
        ts, start_epoch, history = load_checkpoint(workdir, ts)
        print(f"resumed {workdir} after epoch {start_epoch}", file=sys.stderr)
    with open(cfg_path, "w") as fh:
        fh.write(config_to_json(config))
    mesh = data_mesh(config.batch)
    if mesh is not None:  # batch split over the devices, parameters replicated
        ts = shard(ts, mesh, axis=10**6)
    window, loss_frames, keep, windows = _plan(config)
    step_fn = make_train_step(model, loss_fn, opt, loss_frames=loss_frames, keep_at=keep,
                              remat=config.remat)
    eval_loss = jax.jit(lambda p, c, f, t: rollout.window_loss(
        model.step, loss_fn, p, c, f, t, loss_frames=loss_frames)[0])
    with Dataset(config.dataset) as ds:
        val_rng = np.random.default_rng([config.seed, 10**6])
        val_crops = [ds.crops("val", config.factor, config.batch, window, config.crop, val_rng)
                     for _ in range(config.val_batches)]
        val_names = ds.videos("val")[:config.val_videos]
        done = 0
        for epoch in range(start_epoch + 1, config.epochs + 1):
            rng = np.random.default_rng([config.seed, epoch])
            t0 = time.perf_counter()
            run = []
            bar = tqdm(range(config.steps_per_epoch), desc=f"epoch {epoch}/{config.epochs}",
                       disable=not progress, leave=False)
            for _ in bar:
                frames, targets = ds.crops("train", config.factor, config.batch, config.seq_len,
                                           config.crop, rng, accept=_accept(config))
                frames, targets = jax.tree_util.tree_map(jnp.asarray, (frames, targets))
                carry = _start_carry(model, frames, targets)
                if mesh is not None:
                    frames, targets = shard((frames, targets), mesh, axis=1)
                    carry = shard(carry, mesh, axis=0)
                for w in windows:
                    sl = jax.tree_util.tree_map(lambda x: x[w.start:w.stop], (frames, targets))
                    ts, carry, stats = step_fn(ts, carry, *sl)
                    run.append(_finite_or_stop(stats, workdir, epoch, len(run) + 1,
                                               epoch - 1 if epoch > 1 else 0))
                bar.set_postfix(loss=f"{np.mean(run[-20:]):.4f}")
            val = [float(eval_loss(ts.params, _start_carry(model, *c), *c))
                   for c in (jax.tree_util.tree_map(jnp.asarray, c) for c in val_crops)]
            psnr, ssim = [], []
            for name in val_names:
                vf, vt = ds.video("val", name, config.factor)
                m = video_metrics(model, ts.params, *jax.tree_util.tree_map(jnp.asarray, (vf, vt)),
                                  config.factor)
                psnr.append(m["psnr"])
                ssim.append(m["ssim"])
            rec = {"epoch": epoch, "step": int(ts.step), "train_loss": float(np.mean(run)),
                   "val_loss": float(np.mean(val)),
                   "val_psnr": float(np.mean(np.concatenate(psnr))) if psnr else float("nan"),
                   "val_ssim": float(np.mean(np.concatenate(ssim))) if ssim else float("nan"),
                   "seconds": time.perf_counter() - t0}
            history.append(rec)
            if len(history) >= 3 and len({h["val_loss"] for h in history[-3:]}) == 1:
                print("warning: the validation loss has not changed for 3 epochs: the "
                      "network may have collapsed (saturated outputs pass no gradient; "
                      "try a lower --lr, see docs/weights.md)", file=sys.stderr)
            save_checkpoint(workdir, ts, epoch, history)
            _write_csv(workdir, history)
            plot_history(history, os.path.join(workdir, "training.png"))
            print(f"epoch {epoch}: train {rec['train_loss']:.4f}  val {rec['val_loss']:.4f}  "
                  f"PSNR {rec['val_psnr']:.2f} dB  SSIM {rec['val_ssim']:.4f}  "
                  f"({rec['seconds']:.0f} s)", file=sys.stderr)
            done += 1
            if stop_after is not None and done >= stop_after:
                break
    return ts.params, history


# ---------------------------------------------------------------- CLI


def _parser():
    p = argparse.ArgumentParser(prog="python -m jtus.train", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", choices=tuple(PRESETS), default="default")
    p.add_argument("--workdir", default=None, help="default: runs/<preset>-x<factor>")
    p.add_argument("--resume", action="store_true")
    p.add_argument("--overwrite", action="store_true",
                   help="start again in a --workdir that holds a run")
    p.add_argument("--no-eval", action="store_true",
                   help="skip the final comparison with JAU, TUS and the shipped weights")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    for f in dataclasses.fields(Config):
        if f.name in ("model_overrides",):
            continue
        flag = "--" + f.name.replace("_", "-")
        if f.type in ("bool", bool):
            p.add_argument(flag, action=argparse.BooleanOptionalAction, default=None)
        else:
            typ = {"int": int, "float": float}.get(str(f.type), str)
            p.add_argument(flag, type=typ, default=None)
    p.add_argument("--warp", help="DLCTUS reprojection warp (any jtus.sampling method)")
    return p


def config_from_args(args) -> Config:
    base = PRESETS[args.preset]
    over = {f.name: getattr(args, f.name) for f in dataclasses.fields(Config)
            if f.name != "model_overrides" and getattr(args, f.name, None) is not None}
    config = dataclasses.replace(base, **over)
    if args.warp:
        config = dataclasses.replace(config, model_overrides=(("warp", args.warp),))
    return config


def main(argv=None):
    args = _parser().parse_args(argv)
    from jtus.cli import sigterm_as_exit
    sigterm_as_exit()
    try:
        config = config_from_args(args)
        workdir = args.workdir or os.path.join("runs", f"{args.preset}-x{config.factor}")
        train_and_evaluate(config, workdir, resume=args.resume, progress=not args.quiet,
                           overwrite=args.overwrite)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"checkpoint: {os.path.join(workdir, 'checkpoint.msgpack')}", file=sys.stderr)
    if not args.no_eval:
        from jtus import evaluate
        evaluate.main(["--dataset", config.dataset, "--factor", str(config.factor),
                       "--models", "jau", "tus", "shipped",
                       f"trained={os.path.join(workdir, 'checkpoint.msgpack')}",
                       "--out", os.path.join(workdir, "eval")]
                      + (["--max-videos", "4"] if args.preset == "default" else []))
    return 0


if __name__ == "__main__":
    sys.exit(main())
