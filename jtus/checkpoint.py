"""Checkpoints: a run's train state, and parameters exported with their config.

Files, all written atomically (``jtus.files.atomic_path``: a temporary file renamed
into place, removed on any error or interrupt):

- ``<workdir>/checkpoint.msgpack``: ``{"epoch", "step", "params", "opt_state"}``,
  flax's msgpack of the whole train state, which ``--resume`` restores bit for bit;
- ``<workdir>/metrics.json``: the per-epoch log;
- ``<base>.msgpack`` + ``<base>.json`` (+ ``<base>-training.csv``): parameters alone
  with the run config that builds their model; what ``jtus/weights/`` ships.

Why flax's msgpack and not orbax-checkpoint: a DLCTUS train state is about 1 MB,
written once per epoch by one process on one host; one self-contained file is what a
session commits to git to resume elsewhere and what ``jtus/weights/`` ships. Orbax
writes a directory of files per step, asynchronously, and is built for sharded
multi-host state; it would add a dependency and a layout nobody here needs.
"""

from __future__ import annotations

import json
import math
import os
import shutil

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from jtus.files import atomic_path

CHECKPOINT = "checkpoint.msgpack"
METRICS = "metrics.json"


def save_train_state(workdir, ts, epoch, history):
    """Atomically write ``checkpoint.msgpack`` (epoch, and the train state's step,
    params and opt_state) and ``metrics.json`` (``history``)."""
    payload = serialization.to_bytes({"epoch": epoch, "step": ts.step, "params": ts.params,
                                      "opt_state": ts.opt_state})
    with atomic_path(os.path.join(workdir, CHECKPOINT)) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(payload)
    with atomic_path(os.path.join(workdir, METRICS)) as tmp:
        with open(tmp, "w") as fh:
            json.dump(history, fh, indent=1)


def restore_train_state(workdir, ts):
    """``(train state, epoch, history)`` from ``workdir``, restored into the structure
    of ``ts`` (a NamedTuple with ``step``, ``params``, ``opt_state``)."""
    path = os.path.join(workdir, CHECKPOINT)
    with open(path, "rb") as fh:
        data = fh.read()
    target = {"epoch": 0, "step": ts.step, "params": ts.params, "opt_state": ts.opt_state}
    try:
        restored = serialization.from_bytes(target, data)
    except Exception as e:
        raise ValueError(f"{path}: not a checkpoint of this model and optimizer ({e})") from e
    history = read_history(os.path.join(workdir, METRICS), int(restored["epoch"]))
    state = ts._replace(step=jnp.asarray(restored["step"]), params=restored["params"],
                        opt_state=restored["opt_state"])
    return state, int(restored["epoch"]), history


def read_history(path, epochs):
    """The per-epoch records of ``metrics.json`` (``[]`` when absent): a list of
    ``epochs`` objects, each with an ``epoch`` number; ``ValueError`` naming the file
    and what is wrong otherwise (a resumed run must not carry a damaged history)."""
    if not os.path.exists(path):
        return []
    try:
        with open(path, encoding="utf-8") as fh:
            history = json.load(fh)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not valid JSON ({e}); restore it or start again with "
                         "--overwrite") from e
    if (not isinstance(history, list) or len(history) != epochs
            or not all(isinstance(r, dict) and r.get("epoch") == i + 1
                       for i, r in enumerate(history))):
        raise ValueError(f"{path}: expected a list of {epochs} epoch records (epoch 1 ... "
                         f"{epochs}) matching the checkpoint; restore it or start again "
                         "with --overwrite")
    for r in history:  # what training writes: finite numbers, whole step counts
        for k, v in r.items():
            whole = k in ("epoch", "step")
            if (isinstance(v, bool) or not isinstance(v, int if whole else (int, float))
                    or not math.isfinite(v) or (whole and v < 0)):
                raise ValueError(f"{path}: epoch {r['epoch']}: {k}: expected "
                                 f"{'a whole number >= 0' if whole else 'a finite number'}, "
                                 f"got {v!r}; restore it or start again with --overwrite")
    return history


def read_params(path, template, what):
    """The ``params`` entry of the msgpack file ``path`` in the structure of
    ``template``; ``ValueError`` naming the file and the parameter when the file is
    unreadable, the structure differs, a leaf has another shape or a non-float dtype,
    or holds NaN/Inf. ``what`` names the model in messages ("dlctus at 4x")."""
    try:
        with open(path, "rb") as fh:
            raw = serialization.msgpack_restore(fh.read())
    except Exception as e:  # msgpack raises several types for damaged files
        raise ValueError(f"{path}: not a readable checkpoint ({type(e).__name__}: {e})") from e
    if not isinstance(raw, dict) or "params" not in raw:
        raise ValueError(f"{path}: no 'params' entry (keys: "
                         f"{sorted(raw) if isinstance(raw, dict) else type(raw).__name__})")
    want = {jax.tree_util.keystr(k): v for k, v in
            jax.tree_util.tree_flatten_with_path(template)[0]}
    try:
        got = serialization.from_state_dict(template, raw["params"])
    except Exception as e:
        raise ValueError(f"{path}: parameters do not fit {what} ({e})") from e
    for k, v in jax.tree_util.tree_flatten_with_path(got)[0]:
        ref = want[jax.tree_util.keystr(k)]
        v = np.asarray(v)
        if v.shape != ref.shape or not np.issubdtype(v.dtype, np.floating):
            raise ValueError(f"{path}: parameter {jax.tree_util.keystr(k)} has shape {v.shape} "
                             f"and dtype {v.dtype}; {what} expects {ref.shape} floating")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{path}: parameter {jax.tree_util.keystr(k)} holds NaN or Inf")
    return got


def write_params(out_base, params, config_json, training_csv=None):
    """Write ``out_base.msgpack`` (parameters alone), ``out_base.json`` (the run
    config, ``jtus.config.to_json``) and, given a per-epoch CSV, a copy as
    ``out_base-training.csv``; each atomically. Returns the ``.msgpack`` path."""
    os.makedirs(os.path.dirname(os.path.abspath(out_base)), exist_ok=True)
    with atomic_path(out_base + ".msgpack") as tmp:
        with open(tmp, "wb") as fh:
            fh.write(serialization.to_bytes({"params": params}))
    with atomic_path(out_base + ".json") as tmp:
        with open(tmp, "w") as fh:
            fh.write(config_json)
    if training_csv and os.path.exists(training_csv):
        with atomic_path(out_base + "-training.csv") as tmp:
            shutil.copyfile(training_csv, tmp)
    return out_base + ".msgpack"
