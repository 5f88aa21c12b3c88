"""Every system as ``make(config) -> Model(init, init_state, step, config)``, and the
registry that names them and says what each can do.

Each model module lists its names in ``SPECS`` (``base.Spec``: the config for a
factor, ``make``, whether it trains, its loss, its cost formula, its training-crop
acceptance hook); ``_MODULES`` below collects them, one line per module. Names:
``dlctus``, ``jau`` / ``jau-bicubic``, ``tus`` (the thesis's preset) / ``tus-clip`` /
``tus-mean``, ``nsrr`` / ``nsrr-fast``, ``kpn``, ``mlp``.

Loading weights and checkpoints is ``jtus.loading``'s.
"""

from __future__ import annotations

import dataclasses

from jtus.models import dlctus, jau, kpn, mlp, nsrr, tus
from jtus.models.base import Cost, Model, Spec, param_count

# one line per model module: its SPECS join the registry
_MODULES = (dlctus, jau, tus, nsrr, kpn, mlp)

REGISTRY: dict[str, Spec] = {s.name: s for m in _MODULES for s in m.SPECS}
NAMES = tuple(REGISTRY)
TRAINABLE = tuple(n for n, s in REGISTRY.items() if s.trainable)
# the model whose trained weights ship with jtus (``shipped``)
(SHIPPED,) = tuple(n for n, s in REGISTRY.items() if s.shipped)


def spec(name) -> Spec:
    if name not in REGISTRY:
        raise ValueError(f"model: expected one of {NAMES}, got {name!r}")
    return REGISTRY[name]


def config_for(name, factor, **overrides):
    """The config of ``name`` at ``factor`` with field overrides; ``ValueError`` naming
    the model on a field it does not have."""
    config = spec(name).config(factor)
    try:
        return dataclasses.replace(config, **overrides)
    except TypeError as e:
        raise ValueError(f"model_overrides: {name} has no such field ({e})") from e


def build(name, factor, **overrides) -> Model:
    """The ``Model`` of ``name`` at ``factor`` with config field overrides."""
    return spec(name).make(config_for(name, factor, **overrides))


__all__ = ["Cost", "Model", "NAMES", "REGISTRY", "SHIPPED", "Spec", "TRAINABLE", "build",
           "config_for", "dlctus", "jau", "kpn", "mlp", "nsrr", "param_count", "spec", "tus"]
