"""Training: ``python -m jtus.train``, thin over ``train_and_evaluate(config, workdir)``.

    python -m jtus.train                       # the main job: default preset, see README
    python -m jtus.train --preset tiny --workdir runs/tiny
    python -m jtus.train --preset paper --factor 2 --workdir runs/paper-x2
    python -m jtus.train --loss st-linear --theta 0.5 --seq-len 16 --mode tbptt --k1 4 --k2 8

One jit region per optimizer step with the train state donated (``make_train_step``),
over ``jtus.rollout`` windows: BPTT (the loss on the last ``loss_frames`` frames of
``seq_len``) or TBPTT (k1, k2). Sequences start with ``frame.reset`` set, so the model
initializes its history inside the step and every window shares one trace. With
``--alternate PRESET`` every second sequence follows that preset's data and windows
(``recipe.alternate_config``), each kind of sequence with its own compiled step.

After each epoch: the loss on fixed validation crops, PSNR/SSIM over whole validation
videos (thesis sec. 4.3.5), an atomic checkpoint, ``metrics.json``/``metrics.csv`` and
``training.png``. ``--resume`` continues from the last checkpoint exactly: the crops of
epoch e come from ``default_rng([seed, e])`` and the checkpoint holds the step, the
parameters and the optimizer state.

The run's parts come from ``jtus.recipe`` (model, loss, optimizer, window plan), its
configuration from ``jtus.config``, its files from ``jtus.checkpoint``; the final
comparison is ``jtus.evaluate.run``, on the dataset's test split (skipped, and said so
before training, where it has none, as the holds presets' data).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import json
import os
import sys
import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.experimental import multihost_utils
from matplotlib.figure import Figure
from tqdm import tqdm

from jtus import checkpoint, cli, evaluate, loading, losses, models, recipe, rollout, sharding
from jtus import config as run_config
from jtus.config import PRESETS, REMAT_CHOICES, Config
from jtus.data.dataset import Dataset
from jtus.files import atomic_path, check_budget
from jtus.sim import generate

# ---------------------------------------------------------------- train step


class TrainState(NamedTuple):
    step: jax.Array
    params: Any
    opt_state: Any


def create_train_state(params, optimizer) -> TrainState:
    return TrainState(jnp.zeros((), jnp.int32), params, optimizer.init(params))


SPLIT_MIN_CROP = 128  # the smallest training crop the batch is split over CPU devices at


def host_devices_for(crop, asked=None):
    """The XLA CPU devices a training step of ``crop``-pixel crops splits its batch over
    (``sharding.use_host_devices``'s ``n``; None: one per core): ``asked`` when given,
    else one per core from crops of ``SPLIT_MIN_CROP`` on and one device below. The
    `diverse` step (crop 128) measured 1.08-1.24x faster split over two cores, the
    `default` one (crop 64) 0.89-1.11x in two runs: its convolutions are too small to gain
    from a core each (docs/performance.md, "Training on several cores")."""
    if asked is not None:
        return asked
    return None if crop >= SPLIT_MIN_CROP else 1


def make_train_step(model, loss_fn, optimizer, *, loss_frames, keep_at=None, remat=False,
                    unroll=1, jit=True, hoist=False, late=None, mesh=None):
    """``(train_state, carry, frames [T,B,...], targets [T,B,H,W,3]) ->
    (train_state, next carry, stats)``.

    BPTT: a window of the whole sequence, ``loss_frames`` = K. TBPTT(k1, k2): windows
    of k2 frames from ``rollout.tbptt_windows``, ``loss_frames = k1`` and
    ``keep_at = k1`` when k1 < k2; the returned carry (gradient cut) starts the next
    window.

    ``hoist``: run the model's ``prepare`` before the scan (``rollout.window_loss``;
    the same values). Off by default: on XLA:CPU it measured no faster than scanning
    the plain step (0.96-1.06x, docs/results/cpu-speed/result.md, "Training speed"). ``late``:
    ``(index, loss)`` for the window's frames from ``index`` on (``rollout.window_loss``).

    ``mesh`` (``sharding.data_mesh``): each device runs the window on its part of the
    batch and the devices average their losses and gradients once per step
    (``sharding.batch_parallel``), which equals the whole batch's mean for jtus's
    losses (means over the batch of per-crop terms; ``tests/test_sharding.py``).
    """
    step, prepare = rollout.parts(model) if hoist else (model.step, None)

    def loss_and_grads(params, carry, frames, targets):
        def f(p):
            return rollout.window_loss(step, loss_fn, p, carry, frames, targets,
                                       loss_frames=loss_frames, keep_at=keep_at, remat=remat,
                                       unroll=unroll, prepare=prepare, late=late)

        (loss, (last, kept)), grads = jax.value_and_grad(f, has_aux=True)(params)
        return loss, last, kept, grads

    if mesh is not None:
        loss_and_grads = sharding.batch_parallel(loss_and_grads, mesh, batch_axes=(
            None, 0, 1, 1), out_batch_axes=(None, 0, 0, None))

    def train_step(ts: TrainState, carry: rollout.Carry, frames, targets):
        loss, last, kept, grads = loss_and_grads(ts.params, carry, frames, targets)
        with jax.named_scope("optimizer"):
            updates, opt_state = optimizer.update(grads, ts.opt_state, ts.params)
            params = optax.apply_updates(ts.params, updates)
        nxt = jax.lax.stop_gradient(kept if keep_at is not None else last)
        stats = {"loss": loss, "grad_norm": optax.tree.norm(grads),
                 "param_norm": optax.tree.norm(params)}
        return TrainState(ts.step + 1, params, opt_state), nxt, stats

    return jax.jit(train_step, donate_argnums=(0, 1)) if jit else train_step


# ---------------------------------------------------------------- epoch log


def write_csv(workdir, history):
    """``metrics.csv``: one row per epoch (columns: every key any epoch logged)."""
    if not history:
        return
    keys = list(dict.fromkeys(k for h in history for k in h))
    with atomic_path(os.path.join(workdir, "metrics.csv")) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, keys)
            w.writeheader()
            w.writerows(history)


def plot_history(history, path):
    """Training loss, validation loss, validation PSNR and SSIM per epoch (thesis Fig. 16)."""
    ep = [h["epoch"] for h in history]
    fig = Figure(figsize=(14, 3))
    ax = fig.subplots(1, 4)
    for a, key, title in zip(ax, ("train_loss", "val_loss", "val_psnr", "val_ssim"),
                             ("training loss", "validation loss", "validation PSNR (dB)",
                              "validation SSIM")):
        a.plot(ep, [h[key] for h in history], marker="o")
        a.set_title(title)
        a.set_xlabel("epoch")
        a.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")


def collapsed(history, tiny=1e-7):
    """A reason to believe the network collapsed (saturated clamped outputs pass no
    gradient, docs/weights.md), read from the epoch log; None otherwise."""
    if history and "grad_norm" in history[-1] and history[-1]["grad_norm_max"] < tiny:
        return f"the gradient norm stayed below {tiny:g} through epoch {history[-1]['epoch']}"
    if len(history) >= 3 and len({h["val_loss"] for h in history[-3:]}) == 1:
        return "the validation loss has not changed for 3 epochs"
    return None


def _epoch_stats(stats, workdir, epoch):
    """The epoch's per-step stats, fetched from the device once: loss and gradient
    norm means, the largest gradient norm, the final parameter norm. A non-finite loss
    or gradient stops the run before anything of this epoch is written."""
    stats = sharding.to_host(stats)
    loss, gnorm, pnorm = (np.stack([s[k] for s in stats])
                          for k in ("loss", "grad_norm", "param_norm"))
    bad = ~(np.isfinite(loss) & np.isfinite(gnorm))
    if bad.any():
        i = int(np.argmax(bad))
        kept = (f"the checkpoint of epoch {epoch - 1} is kept" if epoch > 1
                else "no checkpoint was written")
        raise ValueError(f"training: non-finite loss ({loss[i]}) or gradient norm ({gnorm[i]}) "
                         f"at epoch {epoch}, step {i + 1}; stopped, {kept} in {workdir} (NaN "
                         f"or Inf in the data, or a learning rate too high)")
    return {"train_loss": float(loss.mean()), "grad_norm": float(gnorm.mean()),
            "grad_norm_max": float(gnorm.max()), "param_norm": float(pnorm[-1])}


# ---------------------------------------------------------------- the loop


def _prepare_workdir(config, workdir, resume, overwrite):
    if config.model not in models.TRAINABLE:
        raise ValueError(f"model: {config.model!r} has no parameters to train; "
                         f"trainable: {models.TRAINABLE}")
    if os.path.isfile(workdir):
        raise ValueError(f"workdir: {workdir} is a file; expected a folder")
    if os.path.exists(os.path.join(workdir, checkpoint.CHECKPOINT)) and not (resume or overwrite):
        raise ValueError(f"workdir: {workdir} holds a run (checkpoint.msgpack); pass --resume "
                         f"to continue it or --overwrite to start it again")
    cfg_path = os.path.join(workdir, "config.json")
    # a resumed run may be extended (more --epochs); anything else must match
    if (resume and os.path.exists(os.path.join(workdir, checkpoint.CHECKPOINT))
            and os.path.exists(cfg_path)
            and dataclasses.replace(run_config.from_json(cfg_path),
                                    epochs=config.epochs) != config):
        raise ValueError(f"{workdir}: --resume with a different config than "
                         f"{cfg_path} (only --epochs may change); use a new --workdir")


class _Source(NamedTuple):
    """Where a run's training sequences come from and how they become optimizer steps:
    the run's config, or its alternate (``recipe.sources``)."""
    config: Config
    plan: recipe.Plan
    loss_fn: Any        # recipe.loss_for(config)
    step_fn: Any        # the jitted optimizer step (make_train_step) for the plan's windows


class _Run(NamedTuple):
    """What every epoch of a run shares."""
    config: Config
    model: Any
    sources: list       # _Source per kind of training sequence, taken in turn; the
                        # first is the run's own (validation crops are its window long)
    eval_loss: Any      # jitted validation loss of one crop
    mesh: Any           # the data mesh, or None on one device
    accept: Any         # the model's training-crop acceptance hook
    replacing: bool     # --overwrite of a run: its files stay until the first checkpoint


def _start(config, workdir, resume, overwrite, progress, force=False):
    """Check everything, then set the run up: ``(_Run, train state, first epoch,
    history)``; the config is written, and a replaced run cleared, only once valid.
    On one device the optimizer step is compiled here and its memory (XLA's buffer
    assignment) checked against the machine's before any file is written (``force``:
    go on past it)."""
    procs, main = jax.process_count(), sharding.is_main()
    _prepare_workdir(config, workdir, resume, overwrite)
    configs = recipe.sources(config)  # an unknown alternate preset is refused here
    if main:
        for c in configs:
            generate.ensure_dataset(c.dataset, c.data_preset, progress)
    if procs > 1:
        multihost_utils.sync_global_devices("jtus: dataset ready")
        if config.batch % procs:
            raise ValueError(f"batch: {config.batch} is not a multiple of the {procs} "
                             "processes")
    recipe.check_data(config)
    model, opt = recipe.model_for(config), recipe.optimizer_for(config)
    ts = create_train_state(loading.init_params(config), opt)
    mesh = sharding.data_mesh(config.batch)
    srcs = []
    for c in configs:
        plan, loss_fn = recipe.plan(c), recipe.loss_for(c)
        step_fn = make_train_step(model, loss_fn, opt, loss_frames=plan.loss_frames,
                                  keep_at=plan.keep_at, remat=config.remat,
                                  hoist=config.hoist, late=recipe.late_loss_for(c), mesh=mesh)
        if mesh is None:  # one device: each step compiled once, its memory checked up front
            step_fn, memory = compile_step(c, model, step_fn, ts, plan)
            check_budget(memory, 4 * _nbytes(ts.params) + 2 ** 20, workdir, force,
                         what="this training step",
                         smaller="a smaller --batch, --crop or --k2/--seq-len, or --remat")
        srcs.append(_Source(c, plan, loss_fn, step_fn))
    replacing = overwrite and not resume and os.path.exists(
        os.path.join(workdir, checkpoint.CHECKPOINT))
    if main:
        os.makedirs(workdir, exist_ok=True)
    start_epoch, history = 0, []
    if resume and os.path.exists(os.path.join(workdir, checkpoint.CHECKPOINT)):
        ts, start_epoch, history = checkpoint.restore_train_state(workdir, ts)
        print(f"resumed {workdir} after epoch {start_epoch}", file=sys.stderr)
    if main and not replacing:  # a replaced run keeps its files until the new checkpoint
        _write_config(workdir, config)
    if mesh is not None:  # batch split over the devices, parameters replicated
        ts = sharding.replicate(ts, mesh)
    # the validation loss is the run's own objective, the late weight included
    eval_loss = jax.jit(lambda p, c, f, t: rollout.window_loss(
        model.step, srcs[0].loss_fn, p, c, f, t, loss_frames=srcs[0].plan.loss_frames,
        late=recipe.late_loss_for(srcs[0].config))[0])
    run = _Run(config, model, srcs, eval_loss, mesh, recipe.accept_for(config), replacing)
    return run, ts, start_epoch, history


def _nbytes(tree):
    return sum(x.size * x.dtype.itemsize for x in jax.tree_util.tree_leaves(tree))


def compile_step(config, model, step_fn, ts, plan):
    """``(step, memory)``: the jitted optimizer step compiled ahead of time for the run's
    window shapes, and the bytes XLA's buffer assignment holds at once for one call
    (arguments, outputs not aliased to them, temporaries). Windows of different
    lengths (none of the built-in plans has them) keep the jitted step for the others.
    The shapes come from one training crop (read with a throwaway random stream) with
    the batch axis set to the config's: nothing of the batch's size is allocated.
    """
    with Dataset(config.dataset) as ds:
        one = ds.crops("train", config.factor, 1, config.seq_len, config.crop,
                       np.random.default_rng(0), extend_holds=config.extend_holds)
    w = plan.windows[0]
    frames, targets = jax.tree_util.tree_map(
        lambda x: jax.ShapeDtypeStruct((w.stop - w.start, config.batch) + x.shape[2:],
                                       x.dtype), one)
    carry = jax.eval_shape(lambda f, t: recipe.start_carry(model, f, t), frames, targets)
    compiled = step_fn.lower(ts, carry, frames, targets).compile()
    m = compiled.memory_analysis()
    memory = (m.argument_size_in_bytes + m.output_size_in_bytes - m.alias_size_in_bytes
              + m.temp_size_in_bytes)
    length = w.stop - w.start

    def step(ts, carry, frames, targets):
        fn = compiled if len(targets) == length else step_fn
        return fn(ts, carry, frames, targets)

    return step, memory


def _write_config(workdir, config):
    with atomic_path(os.path.join(workdir, "config.json")) as tmp:
        with open(tmp, "w") as fh:
            fh.write(run_config.to_json(config))


def _train_epoch(run, ts, data, epoch, progress):
    """One epoch of optimizer steps: ``(train state, per-step stats on the device)``.
    ``data``: an open ``(dataset, mix dataset or None)`` per source; sequence i comes
    from source ``i % len(run.sources)``. One random stream per epoch (and per process),
    so a resumed run draws the same crops."""
    config, procs = run.config, jax.process_count()
    rng = np.random.default_rng([config.seed, epoch] + (
        [jax.process_index()] if procs > 1 else []))
    stats = []
    bar = tqdm(range(config.steps_per_epoch), desc=f"epoch {epoch}/{config.epochs}",
               disable=not progress, leave=False)
    for i in bar:
        src, (ds, mix) = run.sources[i % len(run.sources)], data[i % len(run.sources)]
        frames, targets, carry = recipe.training_sequence(
            src.config, run.model, ds, mix, config.batch // procs, rng, run.accept)
        if run.mesh is not None:
            frames, targets = sharding.shard((frames, targets), run.mesh, axis=1)
            carry = sharding.shard(carry, run.mesh, axis=0)
        for sl in recipe.window_slices(src.plan, frames, targets):
            ts, carry, st = src.step_fn(ts, carry, *sl)
            stats.append(st)
        if progress and i % 10 == 9:  # one device sync per 10 sequences
            recent = sharding.to_host([s["loss"] for s in stats[-20:]])
            bar.set_postfix(loss=f"{float(np.mean(recent)):.4f}")
    return ts, stats


def _validate(run, params, ds, val_crops):
    """The validation loss on fixed crops and PSNR / SSIM over whole validation videos."""
    config = run.config
    val = [float(run.eval_loss(params, recipe.start_carry(run.model, *c), *c))
           for c in val_crops]
    psnr, ssim = [], []
    for name in ds.videos("val")[:config.val_videos]:
        vf, vt = ds.video("val", name, config.factor)
        m = evaluate.video_metrics(run.model, params,
                                   *jax.tree_util.tree_map(jnp.asarray, (vf, vt)),
                                   config.factor)
        psnr.append(m["psnr"])
        ssim.append(m["ssim"])
    return {"val_loss": float(np.mean(val)),
            "val_psnr": float(np.mean(np.concatenate(psnr))) if psnr else float("nan"),
            "val_ssim": float(np.mean(np.concatenate(ssim))) if ssim else float("nan")}


def _record_epoch(run, workdir, ts, epoch, history):
    """The epoch's checkpoint, CSV, plot and log line (process 0 alone). A run that
    replaces another (``--overwrite``) swaps it out here, at its first checkpoint: the
    new checkpoint replaces the old one atomically, then the old run's other files and
    its config.json go. A kill before this moment leaves the old run whole."""
    rec = history[-1]
    checkpoint.save_train_state(workdir, sharding.to_host(ts) if jax.process_count() > 1
                                else ts, epoch, history)
    if run.replacing and len(history) == 1:
        for name in ("metrics.csv", "training.png"):
            with contextlib.suppress(FileNotFoundError):
                os.remove(os.path.join(workdir, name))
        _write_config(workdir, run.config)
    write_csv(workdir, history)
    plot_history(history, os.path.join(workdir, "training.png"))
    print(f"epoch {epoch}: train {rec['train_loss']:.4f}  val {rec['val_loss']:.4f}  "
          f"PSNR {rec['val_psnr']:.2f} dB  SSIM {rec['val_ssim']:.4f}  "
          f"|g| {rec['grad_norm']:.3g}  ({rec['seconds']:.0f} s)", file=sys.stderr)


def train_and_evaluate(config: Config, workdir, resume=False, progress=True, stop_after=None,
                       overwrite=False, stop_when=None, force=False):
    """Train ``config`` into ``workdir``; returns ``(params, history)``.

    A workdir that holds a run is continued with ``resume`` or replaced with
    ``overwrite``, never silently mixed; everything is checked before the first write,
    the step's memory included (``force``: go on past the machine's free memory).
    A non-finite loss or gradient stops the run and leaves the last good checkpoint.
    ``stop_after``: stop (as if killed) after that many epochs of this call, for tests.
    ``stop_when(history) -> reason or None``: checked on a resumed history and after each
    epoch's checkpoint; the run stops there when it gives a reason (the ablations pass
    ``collapsed``: a collapsed network's further epochs are wasted).

    In a multi-process run (``sharding.initialize`` first) every process trains on its
    own ``batch / processes`` crops of each step (its own random stream) and process 0
    alone writes files; the workdir and dataset must be on a file system they share.
    """
    run, ts, start_epoch, history = _start(config, workdir, resume, overwrite, progress,
                                           force)
    end = config.epochs
    if stop_when is not None and history and stop_when(history):
        end = start_epoch  # stopped in an earlier call: nothing more to train
    with contextlib.ExitStack() as stack:
        data = [(stack.enter_context(Dataset(s.config.dataset)),
                 stack.enter_context(Dataset(s.config.mix_dataset))
                 if s.config.mix_dataset else None) for s in run.sources]
        ds = data[0][0]
        val_rng = np.random.default_rng([config.seed, 10**6])
        val_crops = [jax.tree_util.tree_map(jnp.asarray, ds.crops(
            "val", config.factor, config.batch, run.sources[0].plan.window, config.crop, val_rng,
            extend_holds=config.extend_holds))
            for _ in range(config.val_batches)]
        for done, epoch in enumerate(range(start_epoch + 1, end + 1), 1):
            t0 = time.perf_counter()
            ts, stats = _train_epoch(run, ts, data, epoch, progress)
            rec = {"epoch": epoch, "step": int(sharding.to_host(ts.step)),
                   **_epoch_stats(stats, workdir, epoch)}
            # validation runs on one device: replicated parameters would run it on each
            params = ts.params if run.mesh is None else sharding.to_host(ts.params)
            rec.update(_validate(run, params, ds, val_crops))
            rec["seconds"] = time.perf_counter() - t0
            history.append(rec)
            why = collapsed(history)
            if why:
                print(f"warning: {why}: the network may have collapsed (saturated outputs pass "
                      f"no gradient; try a lower --lr, see docs/weights.md)", file=sys.stderr)
            if sharding.is_main():  # the other processes hold the same state and history
                _record_epoch(run, workdir, ts, epoch, history)
            if stop_after is not None and done >= stop_after:
                break
            if stop_when is not None and stop_when(history):
                break
    return ts.params, history


# ---------------------------------------------------------------- CLI


# help for the Config fields whose values are names
_FIELD_HELP = {
    "loss": f"one of {', '.join(losses.NAMES)} (jtus.losses); default: the preset's",
    "model": f"one of {', '.join(models.TRAINABLE)}; default: the preset's",
    "alternate": "a preset whose data and windows give every second training sequence "
                 "(e.g. game-mix: moving content between whole long holds); the model, "
                 "optimizer, crop and batch stay this run's, and so does the loss unless "
                 "--alternate-loss names another",
    "alternate_loss": "the loss of the --alternate sequences (one of the --loss names); "
                      "default: this run's --loss",
    "temporal_weight": "the weight of the temporal term of --loss salvi, log-salvi and "
                       "log-salvi-unsampled "
                       "(default 1, the thesis's eq. 43)",
    "temporal_from": "apply --temporal-weight from this frame of each sequence on, weight "
                     "1 before it (e.g. only once a static hold has had time to converge); "
                     "needs one window per sequence; default 0: every frame",
    "extend_holds": "continue the holds of held videos (data presets *-holds) past their "
                    "stored length to --seq-len frames",
}


def _parser():
    p = argparse.ArgumentParser(prog="python -m jtus.train", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", choices=tuple(PRESETS), default="default")
    p.add_argument("--workdir", default=None, help="default: runs/<preset>-x<factor>")
    p.add_argument("--resume", action="store_true")
    p.add_argument("--overwrite", action="store_true",
                   help="start again in a --workdir that holds a run")
    p.add_argument("--force", action="store_true",
                   help="go on past the memory budget (the compiled step's buffers against "
                        "the machine's free memory)")
    p.add_argument("--no-eval", action="store_true",
                   help="skip the final comparison with JAU, TUS and the shipped weights")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--host-devices", type=int, default=None, metavar="N",
                   help="XLA CPU devices to split the batch over (default: from crop 128 "
                        "on, one per core, as many as divide --batch; below, one; 1: one "
                        "device). XLA:CPU runs a convolution on one thread, so one device "
                        "leaves cores idle (docs/performance.md, 'Training on several "
                        "cores')")
    for f in dataclasses.fields(Config):
        if f.name in ("model_overrides", "remat"):
            continue
        flag = "--" + f.name.replace("_", "-")
        if f.type in ("bool", bool):
            p.add_argument(flag, action=argparse.BooleanOptionalAction, default=None,
                           help=_FIELD_HELP.get(f.name))
        else:
            typ = {"int": int, "float": float}.get(str(f.type), str)
            p.add_argument(flag, type=typ, default=None, help=_FIELD_HELP.get(f.name))
    p.add_argument("--remat", choices=tuple(REMAT_CHOICES), default=None,
                   help="rematerialization of the scanned step (docs/performance.md): none "
                        "(the default), full, a jax.checkpoint policy (dots, dots_no_batch), "
                        "or reverse (a hand-written reverse-time backward); each trades "
                        "time for memory")
    p.add_argument("--model-override", action="append", default=[], metavar="KEY=VALUE",
                   help="set a field of the model's config (e.g. warp=bilinear, hdr=true); "
                        "merged with the preset's overrides; repeatable")
    d = p.add_argument_group("multi-process data parallelism (docs/distributed.md)")
    d.add_argument("--distributed", action="store_true",
                   help="join a multi-process run (jax.distributed); without the three "
                        "flags below JAX reads them from the cluster (SLURM, Open MPI)")
    d.add_argument("--coordinator", help="host:port of process 0")
    d.add_argument("--num-processes", type=int)
    d.add_argument("--process-id", type=int)
    return p


def config_from_args(args) -> Config:
    base = PRESETS[args.preset]
    over = {f.name: getattr(args, f.name) for f in dataclasses.fields(Config)
            if f.name != "model_overrides" and getattr(args, f.name, None) is not None}
    if args.remat is not None:
        over["remat"] = REMAT_CHOICES[args.remat]
    if "model" in over and "loss" not in over:  # a model's own loss (KPN's masked loss)
        over["loss"] = models.spec(over["model"]).loss
    config = dataclasses.replace(base, **over)
    if config.mode == "tbptt" and "loss_frames" in over and config.loss_frames != config.k1:
        raise ValueError(f"loss_frames: tbptt mode takes the loss on each window's last k1="
                         f"{config.k1} frames, so --loss-frames {config.loss_frames} would be "
                         f"ignored; pass --k1 instead, or --mode bptt")
    if args.model_override:
        merged = dict(config.model_overrides)
        merged.update(parse_override(o) for o in args.model_override)
        config = dataclasses.replace(config, model_overrides=tuple(merged.items()))
        recipe.model_config(config)  # an unknown field is refused here, naming it
    return config


def parse_override(text):
    """``KEY=VALUE`` -> ``(key, value)``; the value read as JSON (``true``, ``0.5``)
    when it is JSON, else kept as a string (``bilinear``)."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise ValueError(f"--model-override: expected KEY=VALUE, got {text!r}")
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def config_from_argv(argv) -> Config:
    """The training config that ``python -m jtus.train ARGV`` would run (argparse errors
    exit as the command would; a bad combination raises ``ValueError``)."""
    return config_from_args(_parser().parse_args(argv))


def main(argv=None):
    args = _parser().parse_args(argv)
    cli.sigterm_as_exit()
    given = [x is not None for x in (args.coordinator, args.num_processes, args.process_id)]
    if any(given) and not (args.distributed and all(given)):
        print("error: --coordinator, --num-processes and --process-id go together, with "
              "--distributed", file=sys.stderr)
        return 2
    try:
        config = config_from_args(args)
        if args.host_devices is not None and args.host_devices < 1:
            raise ValueError(f"--host-devices: expected a positive count, got "
                             f"{args.host_devices}")
        # a multi-process run keeps one device per process unless asked
        host = None if args.distributed and args.host_devices is None else \
            sharding.use_host_devices(host_devices_for(config.crop, args.host_devices),
                                      config.batch)
        if host and not args.quiet:
            print(f"training on {host} XLA CPU devices (one per core), the batch split "
                  f"over them; --host-devices 1 for one", file=sys.stderr)
        if args.distributed:
            sharding.initialize(args.coordinator, args.num_processes, args.process_id)
        workdir = args.workdir or os.path.join("runs", f"{args.preset}-x{config.factor}")
        test_videos = has_test_videos(config.dataset)
        if not (args.no_eval or test_videos):
            print(_NO_TEST.format(config.dataset), file=sys.stderr)
        train_and_evaluate(config, workdir, resume=args.resume, progress=not args.quiet,
                           overwrite=args.overwrite, force=args.force)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if not sharding.is_main():
        return 0
    print(f"checkpoint: {os.path.join(workdir, checkpoint.CHECKPOINT)}", file=sys.stderr)
    if args.no_eval:
        return 0
    if not has_test_videos(config.dataset):  # said before training if the file was there
        if test_videos:
            print(_NO_TEST.format(config.dataset), file=sys.stderr)
        return 0
    return _evaluate_after(args, config, workdir)


_NO_TEST = "{} has no test split: no evaluation after training (--no-eval says so)"


def has_test_videos(dataset):
    """Whether ``dataset`` has videos in its test split (the training data of the holds
    presets has none: their test holds are other files). True for a file that does not
    exist yet: training then says what is missing."""
    try:
        with Dataset(dataset) as ds:
            return bool(ds.videos("test"))
    except FileNotFoundError:
        return True


def _evaluate_after(args, config, workdir):
    """The test-split evaluation after training: JAU, TUS, the shipped and the trained
    weights (``python -m jtus.evaluate``)."""
    specs = ["jau", "tus", "shipped", f"trained={os.path.join(workdir, checkpoint.CHECKPOINT)}"]
    try:
        summary = evaluate.run(specs, config.dataset, [config.factor],
                               os.path.join(workdir, "eval"),
                               max_videos=config.test_videos or None, progress=not args.quiet)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(evaluate.markdown(summary))
    print(f"wrote the evaluation (results.md, per-frame plots, crop grids) to "
          f"{os.path.join(workdir, 'eval')}/; training curves in "
          f"{os.path.join(workdir, 'training.png')}")
    return 0


if __name__ == "__main__":
    cli.run(main)
