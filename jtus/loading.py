"""Runnable models from what a user names: a built-in model, ``shipped`` weights, or
``LABEL=PATH`` for a checkpoint written by ``jtus.train`` (``.msgpack`` with its config
JSON) or a PyTorch checkpoint (``.pt``) of a model that reads them.

Checkpoints are checked before use: structure, shapes, dtypes and finite values, each
failure naming the file and the parameter (``checkpoint.read_params``). Also here: the
starting parameters of a run (``init_params``) and a run's parameters exported alone
(``export_params``), both of which read checkpoints the same way.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jtus import checkpoint, models, recipe
from jtus import config as run_config
from jtus.config import Config

WEIGHTS = os.path.join(os.path.dirname(__file__), "weights")


class Entry(NamedTuple):
    """A runnable model: a label for tables, the ``Model``, its parameters and its
    registry name (whose ``Spec`` says what it can do)."""
    label: str
    model: models.Model
    params: Any
    name: str = ""


def shipped_path(factor, name=None):
    """Where the shipped weights of ``name`` (default: the registry's one shipped
    model) at ``factor`` live: ``jtus/weights/<name>-x<factor>.msgpack``."""
    name = name or models.SHIPPED
    return os.path.join(WEIGHTS, f"{name}-x{factor}.msgpack")


def config_path_for(path):
    """The training config that belongs to a ``.msgpack``: ``<base>.json`` beside it
    (exported weights), else ``config.json`` in its folder (a run's workdir)."""
    beside = os.path.splitext(path)[0] + ".json"
    if os.path.exists(beside):
        return beside
    return os.path.join(os.path.dirname(os.path.abspath(path)), "config.json")


def load_checkpoint(path, config_path=None):
    """``(model, params, run config)`` of a checkpoint written by ``jtus.train``
    (``checkpoint.msgpack`` with ``config.json`` beside it) or exported weights
    (``<base>.msgpack`` with ``<base>.json``), checked against the model the config
    names."""
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such checkpoint")
    config_path = config_path or config_path_for(path)
    if not os.path.exists(config_path):
        raise FileNotFoundError(f"{path}: its config {config_path} is missing")
    config = run_config.from_json(config_path)
    model = recipe.model_for(config)
    # shapes only: running the initializers op by op took 14 s (DLCTUS) to 98 s
    # (NSRR-fast) of a loaded core, each random draw of a new shape a new compile
    template = jax.eval_shape(model.init, jax.random.PRNGKey(0))
    params = checkpoint.read_params(path, template, f"{config.model} at {config.factor}x")
    # device arrays: numpy leaves cannot be indexed by traced values (KPN's phase)
    return model, jax.tree_util.tree_map(jnp.asarray, params), config


def load_params(path, config_path=None):
    """``(params, run config)`` of a checkpoint (``load_checkpoint``)."""
    _, params, config = load_checkpoint(path, config_path)
    return params, config


def _load_torch(label, path, factor):
    readers = [s for s in models.REGISTRY.values() if s.torch_checkpoint]
    if len(readers) != 1:
        raise ValueError(f"{label}: a .pt file needs exactly one model that reads PyTorch "
                         f"checkpoints; the registry has {[s.name for s in readers]}")
    spec = readers[0]
    # the thesis's network has the same shapes at every factor: nothing in the file
    # says which it was trained for
    print(f"note: {label}: a .pt checkpoint carries no factor; running it as a {factor}x "
          f"{spec.name} model", file=sys.stderr)
    config = spec.config(factor)
    return Entry(label, spec.make(config), spec.torch_checkpoint(path, config), spec.name)


def load(spec_text, factor) -> Entry | None:
    """A model spec -> ``Entry``; None (with a warning) for ``shipped`` weights that do
    not exist or a checkpoint trained for another factor. ``{f}`` in a PATH becomes
    ``factor``."""
    if spec_text == "shipped":
        path = shipped_path(factor)
        if not os.path.exists(path):
            print(f"warning: no shipped weights for factor {factor} ({path}); skipped",
                  file=sys.stderr)
            return None
        spec_text = f"{models.SHIPPED}-shipped={path}"
    if "=" in spec_text:
        label, path = spec_text.split("=", 1)
        path = path.replace("{f}", str(factor))
        if not label:
            raise ValueError(f"model: {spec_text!r} has an empty label; expected LABEL=PATH")
        if not os.path.exists(path):
            raise FileNotFoundError(f"{label}: {path} does not exist")
        if not os.path.isfile(path):
            raise ValueError(f"{label}: {path} is a folder; expected a checkpoint file "
                             "(.msgpack or .pt)")
        if path.endswith(".pt"):
            return _load_torch(label, path, factor)
        model, params, config = load_checkpoint(path)
        if config.factor != factor:
            print(f"warning: {label} was trained for factor {config.factor}; skipped at "
                  f"{factor}x", file=sys.stderr)
            return None
        return Entry(label, model, params, config.model)
    if spec_text in models.TRAINABLE:
        raise ValueError(f"model: {spec_text!r} needs weights; give LABEL=PATH (a .msgpack from "
                         f"jtus.train or a .pt), or 'shipped' for {models.SHIPPED}")
    if spec_text not in models.NAMES:
        raise ValueError(f"model: {spec_text!r} is not a model; expected one of "
                         f"{tuple(n for n in models.NAMES if n not in models.TRAINABLE)}, "
                         f"'shipped' or LABEL=PATH")
    return Entry(spec_text, models.build(spec_text, factor), {}, spec_text)


def load_all(specs, factor):
    """Entries for every spec (those without weights at ``factor`` skipped, with a
    warning); refuses repeated labels and an empty result."""
    entries = [e for e in (load(s, factor) for s in specs) if e is not None]
    labels = [e.label for e in entries]
    repeated = sorted({lab for lab in labels if labels.count(lab) > 1})
    if repeated:
        raise ValueError(f"models: the labels {repeated} are given more than once; give each "
                         f"model its own LABEL=PATH")
    if not entries:
        raise ValueError(f"models: none of {list(specs)} can run at factor {factor}")
    return entries


def init_params(config: Config):
    """A run's starting parameters: from ``init_from`` (a checkpoint of the same model
    and factor) or freshly initialized from ``seed``."""
    if config.init_from:
        params, init_cfg = load_params(config.init_from)
        if (init_cfg.model, init_cfg.factor) != (config.model, config.factor):
            raise ValueError(f"init_from: {config.init_from} holds {init_cfg.model} at "
                             f"{init_cfg.factor}x, this run trains {config.model} at "
                             f"{config.factor}x")
        model_config = recipe.model_config(config)
        changed = model_changes(recipe.model_config(init_cfg), model_config)
        if changed:
            print(f"note: init_from: {config.init_from} was trained with another design "
                  f"than this run's model ({'; '.join(changed)}); --model-override sets "
                  f"this run's", file=sys.stderr)
        spec = models.spec(config.model)
        return spec.adapt(params, model_config) if spec.adapt else params
    return recipe.model_for(config).init(jax.random.PRNGKey(config.seed))


def model_changes(before, after):
    """``["field: old -> new", ...]`` for the fields in which model config ``after``
    differs from ``before`` (dataclasses of one model module)."""
    return [f"{f.name}: {getattr(before, f.name)!r} -> {getattr(after, f.name)!r}"
            for f in dataclasses.fields(before)
            if getattr(before, f.name) != getattr(after, f.name)]


def training_log(path):
    """The per-epoch log beside saved weights ``path``: ``<base>-training.csv`` of
    exported weights, ``metrics.csv`` beside a run's checkpoint; None if there is none."""
    base = path[:-len(".msgpack")] if path.endswith(".msgpack") else path
    for log in (base + "-training.csv", os.path.join(os.path.dirname(path), "metrics.csv")):
        if os.path.exists(log):
            return log
    return None


def _check_same_start(started, named):
    """Refuse ``named`` as the weights a run started from unless it holds the same
    parameters as ``started`` (the run's own ``init_from``, when it still exists)."""
    if not os.path.exists(named):
        raise FileNotFoundError(f"init_from: {named}: no such weights")
    if not started or not os.path.exists(started):
        return
    same = jax.tree_util.tree_map(lambda a, b: bool(jnp.array_equal(a, b)),
                                  load_params(started)[0], load_params(named)[0])
    if not all(jax.tree_util.tree_leaves(same)):
        raise ValueError(f"init_from: {named} does not hold the parameters the run "
                         f"started from ({started})")


def export_params(workdir, out_base, init_from=None):
    """Write a run's parameters alone (no optimizer state) with its config and
    per-epoch log: ``out_base.msgpack``, ``.json``, ``-training.csv`` (the form
    ``jtus/weights/`` ships and ``load`` reads).

    ``init_from`` (exported weights) replaces the run's own ``init_from`` in the
    written config, for a fine-tune that started from a run's checkpoint (a path
    under ``runs/`` that is not kept) whose parameters were exported there: the chain
    of fine-tunes then stays traceable, and a budget can count every run in it. It must
    hold exactly the parameters the run started from, while those can still be read."""
    params, config = load_params(os.path.join(workdir, checkpoint.CHECKPOINT))
    if init_from is not None:
        _check_same_start(config.init_from, init_from)
        config = dataclasses.replace(config, init_from=init_from)
    return checkpoint.write_params(out_base, params, run_config.to_json(config),
                                   training_log(os.path.join(workdir, checkpoint.CHECKPOINT)))
