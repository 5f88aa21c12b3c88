"""The shape every jtus model has: a NamedTuple of pure functions, after optax's
``GradientTransformation``; and the record (``Spec``) by which a model module tells
the registry (``jtus.models``) its names, configs, loss, cost and data hooks."""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp

from jtus import sampling

EXPOSURE = ("absolute", "normalized")  # a network's colour inputs: as they are, or / mean
EXPOSURE_FLOOR = 1e-4  # the least frame mean ``exposure="normalized"`` divides by

DTYPES = {"float32": jnp.float32, "bfloat16": jnp.bfloat16, "float16": jnp.float16,
          "float64": jnp.float64}


def carry_dtype(name):
    """The dtype of preparation, output construction and carried state: float32, or
    float64 when the whole model runs in float64 (references, gradient checks; needs
    ``jax.enable_x64``)."""
    return jnp.float64 if name == "float64" else jnp.float32


class Model(NamedTuple):
    """``init(key) -> params``; ``init_state(frame) -> state``;
    ``step(params, state, frame) -> (out [B,H,W,3], state)``; all pure and jit-able.

    ``step`` is ``advance(params, state, prepare(frame))``: ``prepare`` is the part of a
    step that depends on neither the parameters nor the state (input up-sampling, the
    warp's coordinates and weights), which ``jtus.rollout`` computes for every frame of
    a sequence at once, outside its ``lax.scan``. A model without such a part has the
    identity for ``prepare`` and its step for ``advance``."""

    init: Callable[..., Any]
    init_state: Callable[..., Any]
    step: Callable[..., Any]
    config: Any
    prepare: Callable[..., Any] = lambda frame: frame
    advance: Optional[Callable[..., Any]] = None


def bind(config, step, init=None, init_state=None, prepare=None, advance=None) -> Model:
    """A ``Model`` of module functions ``step(params, state, frame, config)``,
    ``init(key, config)`` and ``init_state(frame, config)`` with ``config`` bound; a
    model without parameters (or without state) leaves ``init`` (``init_state``) out
    and gets ``{}`` (``()``). ``prepare(frame, config)`` and ``advance(params, state,
    prepared, config)``, given together, split ``step`` (``Model``). The bound
    functions go through ``exposed_parts`` (HDR colour)."""
    hdr = getattr(config, "hdr", False)
    if (prepare is None) != (advance is None):
        raise ValueError("prepare, advance: give both or neither")
    if prepare is None:
        prepare = lambda frame, config: frame  # noqa: E731
        advance = step
    prep, adv = exposed_parts(lambda frame: prepare(frame, config),
                              lambda params, state, pre: advance(params, state, pre, config),
                              hdr)
    return Model(init=(lambda key: init(key, config)) if init else (lambda key: {}),
                 init_state=((lambda frame: init_state(frame, config)) if init_state
                             else (lambda frame: ())),
                 step=lambda params, state, frame: adv(params, state, prep(frame)),
                 config=config, prepare=prep, advance=adv)


def exposed_parts(prepare, advance, hdr):
    """Every model's edge for HDR colour (docs/conventions.md, "HDR and exposure"),
    around a step split as ``prepare(frame)`` and ``advance(params, state, prepared)``.

    The model body sees pre-exposed colour ``exposure * color`` and, with ``hdr``
    (a config field: the weights were trained on tone-mapped colour), tone-mapped by
    ``sampling.tonemap``; its output is mapped back (inverse tone map, divided by the
    exposure) to linear radiance. Its history stays in that pre-exposed, tone-mapped
    space, as FSR 2's does. A frame without exposure counts as exposure 1, so an LDR
    model (``hdr`` False) given exposure 1 computes exactly what it computes without.
    Returns the wrapped ``(prepare, advance)``; the exposure scale travels with the
    prepared frame."""
    def prep(frame):
        e = frame.exposure
        if e is None and not hdr:
            return prepare(frame), None
        c = frame.color
        scale = None if e is None else sampling.exposure_scale(e, c)
        if scale is not None:
            c = c * scale
        if hdr:
            c = sampling.tonemap(c)
        return prepare(frame._replace(color=c, exposure=None)), scale

    def adv(params, state, prepared):
        pre, scale = prepared
        out, state = advance(params, state, pre)
        if hdr:
            out = sampling.inverse_tonemap(out)
        if scale is not None:
            out = out / scale.astype(out.dtype)
        return out, state

    return prep, adv


class Cost(NamedTuple):
    """Analytic cost of one frame (``jtus.cost``)."""
    flops: float             # per frame
    network_flops: float     # the convolution part
    bytes: float             # compulsory, float32
    activation_bytes: float  # plus the network's intermediates written and read once


class ExportIO(NamedTuple):
    """How a model's step crosses a serialized boundary (``jtus.export``): its state as
    named plain arrays."""
    names: tuple                                   # the state's arrays, in order
    shapes: Callable[[Any, int, int], tuple]       # (config, H, W) -> their shapes
    to_arrays: Callable[[Any], tuple]              # state -> arrays
    from_arrays: Callable[..., Any]                # *arrays -> state
    # (params, config) -> onnx.ModelProto of the step in the runtime's native operators,
    # symbolic in batch and size; NotImplementedError where the config needs one ONNX
    # lacks (``jtus.export`` then converts the JAX step with jax2onnx)
    onnx_graph: Optional[Callable] = None


class Spec(NamedTuple):
    """One registered model name and what tools may ask of it. A model module lists
    its ``SPECS``; the registry in ``jtus/models/__init__.py`` collects them
    (docs/architecture.md). Tools ask these capabilities, never a model's name."""
    name: str
    make: Callable[[Any], Model]
    config: Callable[[int], Any]        # factor -> the module's Config for this name
    cost: Callable[[Any, int, int], Cost]  # (config, H, W) -> Cost, H x W the output
    trainable: bool = False
    loss: str = "l1"                    # the loss it trains with (``jtus.losses.make``)
    accept: Optional[Callable] = None   # target crop [T,H,W,3] -> keep probability
    # capabilities
    dtypes: tuple = ("float32",)        # compute dtypes its config's ``dtype`` takes
    formulations: tuple = ()            # equivalent formulations (config ``formulation``)
    kernels: tuple = ()                 # its trunk's implementations (config ``kernels``)
    network: Optional[Callable] = None  # (params, state, frame, config) -> (fn, args):
                                        # the network alone, for its timing
    torch_checkpoint: Optional[Callable] = None  # (path, config) -> params of a .pt
    torch_state_dict: Optional[Callable] = None  # (params, config) -> PyTorch state_dict
    torch_reference: str = ""           # its module in jtus.reference (bench, tests)
    export: Optional[ExportIO] = None   # its step exports (stablehlo, onnx)
    shipped: bool = False               # weights ship as jtus/weights/<name>-x<f>.msgpack
    adapt: Optional[Callable] = None    # (params, config) -> params grown to the config's
                                        # inputs (a fine-tune of another design's weights)
    stages: tuple = ()                  # the named scopes its step labels its stages with,
                                        # in order (python -m jtus.profile)


def compute_dtype(name):
    if name not in DTYPES:
        raise ValueError(f"dtype: expected one of {tuple(DTYPES)}, got {name!r}")
    return DTYPES[name]


def exposure_normalizer(color, exposure):
    """What a network's colour inputs are multiplied by under ``exposure`` (a config
    field, one of ``EXPOSURE``): ``1.0`` for ``"absolute"`` (a Python float, so the graph
    is unchanged), else ``[B,1,1,1]``, one over each frame's mean colour ``color
    [B,h,w,3]`` (at least ``EXPOSURE_FLOOR``). A network that multiplies its colour
    output by the mean (or mixes colours as they are) then computes, for a video scaled
    by ``s``, its outputs scaled by ``s``."""
    if exposure == "absolute":
        return 1.0
    mean = jnp.mean(color.astype(jnp.float32), axis=(1, 2, 3), keepdims=True)
    return 1.0 / jnp.maximum(mean, EXPOSURE_FLOOR)


def check_exposure_switch(config, mean):
    """Refuse to switch ``config`` (a model config with ``exposure``) to normalized
    colour at frame mean ``mean`` when it is normalized already or ``mean`` is not
    positive (the models' ``normalize_exposure``)."""
    if config.exposure != "absolute":
        raise ValueError("config: exposure is already normalized")
    if not mean > 0:
        raise ValueError(f"mean: expected a positive mean colour, got {mean}")


def param_count(params):
    return sum(int(x.size) for x in jax.tree_util.tree_leaves(params))


def reset_select(reset, fresh, value):
    """Per batch element, ``fresh`` where ``reset [B]`` is set, else ``value``
    (``[B,...]`` arrays); ``value`` itself when there is no reset flag. Every model's
    history on a first frame or a camera cut goes through here: the fresh history is
    used as it is, never reprojected (docs/conventions.md)."""
    if reset is None:
        return value
    return jnp.where(reset.reshape(reset.shape + (1,) * (value.ndim - 1)), fresh, value)
