"""Every system as ``make(config) -> Model(init, init_state, step, config)``, and the
registry that names them.

Each model module lists its names in ``SPECS`` (``base.Spec``: the config for a
factor, ``make``, whether it trains, its loss, its cost formula, its training-crop
acceptance hook); ``_MODULES`` below collects them, one line per module. Names:
``dlctus``, ``jau`` / ``jau-bicubic``, ``tus`` (the thesis's preset) / ``tus-clip`` /
``tus-mean``, ``nsrr`` / ``nsrr-fast``, ``kpn``, ``mlp``.

``load(spec, factor)`` is how every tool gets a runnable model: a built-in name,
``shipped`` (the DLCTUS weights under ``jtus/weights/``) or ``LABEL=PATH`` for a
checkpoint written by ``jtus.train`` (``.msgpack`` with its config JSON) or a
PyTorch DLCTUS checkpoint (``.pt``). Checkpoints are checked before use: structure,
shapes, dtypes and finite values, each failure naming the file and the parameter.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from typing import Any, NamedTuple

from jtus.models import dlctus, jau, kpn, mlp, nsrr, tus
from jtus.models.base import Cost, Model, Spec, param_count

# one line per model module: its SPECS join the registry
_MODULES = (dlctus, jau, tus, nsrr, kpn, mlp)

REGISTRY: dict[str, Spec] = {s.name: s for m in _MODULES for s in m.SPECS}
NAMES = tuple(REGISTRY)
TRAINABLE = tuple(n for n, s in REGISTRY.items() if s.trainable)
WEIGHTS = os.path.join(os.path.dirname(os.path.dirname(__file__)), "weights")


def spec(name) -> Spec:
    if name not in REGISTRY:
        raise ValueError(f"model: expected one of {NAMES}, got {name!r}")
    return REGISTRY[name]


def config_for(name, factor, **overrides):
    """``(module's make, config)`` of ``name`` at ``factor`` with field overrides."""
    s = spec(name)
    config = s.config(factor)
    try:
        return s.make, dataclasses.replace(config, **overrides)
    except TypeError as e:
        raise ValueError(f"model_overrides: {name} has no such field ({e})") from e


def build(name, factor, **overrides) -> Model:
    make, config = config_for(name, factor, **overrides)
    return make(config)


def for_run(run_config) -> Model:
    """The model a training run's config (``jtus.config.Config``) names: its model,
    factor and model overrides."""
    return build(run_config.model, run_config.factor, **dict(run_config.model_overrides))


# ---------------------------------------------------------------- loading


class Entry(NamedTuple):
    """A runnable model: a label for tables, the ``Model`` and its parameters."""
    label: str
    model: Model
    params: Any


def shipped_path(factor):
    return os.path.join(WEIGHTS, f"dlctus-x{factor}.msgpack")


def config_path_for(path):
    """The training config that belongs to a ``.msgpack``: ``<base>.json`` beside it
    (exported weights), else ``config.json`` in its folder (a run's workdir)."""
    beside = os.path.splitext(path)[0] + ".json"
    if os.path.exists(beside):
        return beside
    return os.path.join(os.path.dirname(os.path.abspath(path)), "config.json")


def load_params(path, config_path=None):
    """``(params, run config)`` of a checkpoint written by ``jtus.train``
    (``checkpoint.msgpack`` with ``config.json`` beside it) or exported weights
    (``<base>.msgpack`` with ``<base>.json``), checked against the model the config
    names."""
    _, params, config = _load_checkpoint(path, config_path)
    return params, config


def _load_checkpoint(path, config_path=None):
    """``(model, params, run config)``: ``load_params`` with the model it built."""
    import jax
    import jax.numpy as jnp

    from jtus import checkpoint
    from jtus import config as run_config

    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such checkpoint")
    config_path = config_path or config_path_for(path)
    if not os.path.exists(config_path):
        raise FileNotFoundError(f"{path}: its config {config_path} is missing")
    config = run_config.from_json(config_path)
    model = for_run(config)
    # shapes only: running the initializers op by op took 14 s (DLCTUS) to 98 s
    # (NSRR-fast) of a loaded core, each random draw of a new shape a new compile
    template = jax.eval_shape(model.init, jax.random.PRNGKey(0))
    params = checkpoint.read_params(path, template, f"{config.model} at {config.factor}x")
    # device arrays: numpy leaves cannot be indexed by traced values (KPN's phase)
    return model, jax.tree_util.tree_map(jnp.asarray, params), config


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
        spec_text = f"dlctus-shipped={path}"
    if "=" in spec_text:
        label, path = spec_text.split("=", 1)
        path = path.replace("{f}", str(factor))
        if not os.path.exists(path):
            raise FileNotFoundError(f"{label}: {path} does not exist")
        if path.endswith(".pt"):
            # the thesis's network has the same shapes at every factor: nothing in the
            # file says which it was trained for
            print(f"note: {label}: a .pt checkpoint carries no factor; running it as a "
                  f"{factor}x model", file=sys.stderr)
            config = dlctus.Config(factor=factor)
            return Entry(label, dlctus.make(config), dlctus.load_torch_checkpoint(path, config))
        model, params, config = _load_checkpoint(path)
        if config.factor != factor:
            print(f"warning: {label} was trained for factor {config.factor}; skipped at "
                  f"{factor}x", file=sys.stderr)
            return None
        return Entry(label, model, params)
    if spec_text in TRAINABLE:
        raise ValueError(f"model: {spec_text!r} needs weights; give LABEL=PATH (a .msgpack from "
                         f"jtus.train or a .pt), or 'shipped' for DLCTUS")
    if spec_text not in NAMES:
        raise ValueError(f"model: {spec_text!r} is not a model; expected one of "
                         f"{tuple(n for n in NAMES if n not in TRAINABLE)}, "
                         f"'shipped' or LABEL=PATH")
    return Entry(spec_text, build(spec_text, factor), {})


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


__all__ = ["Cost", "Entry", "Model", "NAMES", "REGISTRY", "Spec", "TRAINABLE", "WEIGHTS",
           "build", "config_for", "config_path_for", "for_run", "dlctus", "jau", "kpn", "load",
           "load_all", "load_params", "mlp", "nsrr", "param_count", "shipped_path", "spec",
           "tus"]
