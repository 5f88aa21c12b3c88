"""Every system as ``make(config) -> Model(init, init_state, step, config)``.

``build(name, factor, **overrides)`` names them for the CLIs: ``dlctus``,
``jau`` / ``jau-bicubic``, ``tus`` (the thesis's preset) / ``tus-clip`` / ``tus-mean``, ``nsrr`` /
``nsrr-fast``, ``kpn``, ``mlp``.
"""

from __future__ import annotations

import dataclasses

from jtus.models import dlctus, jau, kpn, mlp, nsrr, tus
from jtus.models.base import Model, param_count

_BUILDERS = {
    "dlctus": lambda f: (dlctus, dlctus.Config(factor=f)),
    "jau": lambda f: (jau, jau.Config(factor=f)),
    "jau-bicubic": lambda f: (jau, jau.Config(factor=f, method="bicubic")),
    "tus": lambda f: (tus, tus.PRESETS["tus"](f)),
    "tus-clip": lambda f: (tus, tus.PRESETS["tus-clip"](f)),
    "tus-mean": lambda f: (tus, tus.PRESETS["tus-mean"](f)),
    "nsrr": lambda f: (nsrr, nsrr.Config(factor=f)),
    "nsrr-fast": lambda f: (nsrr, nsrr.Config(factor=f, fast=True)),
    "kpn": lambda f: (kpn, kpn.Config(factor=f)),
    "mlp": lambda f: (mlp, mlp.Config(factor=f)),
}
NAMES = tuple(_BUILDERS)
TRAINABLE = ("dlctus", "nsrr", "nsrr-fast", "kpn", "mlp")


def config_for(name, factor, **overrides):
    if name not in _BUILDERS:
        raise ValueError(f"model: expected one of {NAMES}, got {name!r}")
    module, config = _BUILDERS[name](factor)
    return module, dataclasses.replace(config, **overrides)


def build(name, factor, **overrides) -> Model:
    module, config = config_for(name, factor, **overrides)
    return module.make(config)


__all__ = ["Model", "NAMES", "TRAINABLE", "build", "config_for", "dlctus", "jau", "kpn", "mlp",
           "nsrr", "param_count", "tus"]
