"""The shape every jtus model has: a NamedTuple of pure functions, after optax's
``GradientTransformation``."""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax.numpy as jnp

DTYPES = {"float32": jnp.float32, "bfloat16": jnp.bfloat16, "float16": jnp.float16,
          "float64": jnp.float64}


def carry_dtype(name):
    """The dtype of preparation, output construction and carried state: float32, or
    float64 when the whole model runs in float64 (references, gradient checks; needs
    ``jax.enable_x64``)."""
    return jnp.float64 if name == "float64" else jnp.float32


class Model(NamedTuple):
    """``init(key) -> params``; ``init_state(frame) -> state``;
    ``step(params, state, frame) -> (out [B,H,W,3], state)``; all pure and jit-able."""

    init: Callable[..., Any]
    init_state: Callable[..., Any]
    step: Callable[..., Any]
    config: Any


def compute_dtype(name):
    if name not in DTYPES:
        raise ValueError(f"dtype: expected one of {tuple(DTYPES)}, got {name!r}")
    return DTYPES[name]


def param_count(params):
    import jax
    return sum(int(x.size) for x in jax.tree_util.tree_leaves(params))


def reset_select(reset, fresh, value):
    """Per batch element, ``fresh`` where ``reset [B]`` is set, else ``value``
    (``[B,...]`` arrays); ``value`` itself when there is no reset flag. Every model's
    history on a first frame or a camera cut goes through here: the fresh history is
    used as it is, never reprojected (docs/conventions.md)."""
    if reset is None:
        return value
    return jnp.where(reset.reshape(reset.shape + (1,) * (value.ndim - 1)), fresh, value)
