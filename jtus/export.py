"""``python -m jtus.export``: DLCTUS weights out of jtus, for PyTorch or a runtime.

    python -m jtus.export --model shipped --factor 4 --format torch --out dlctus-x4.pt
    python -m jtus.export --model runs/diverse-x4/checkpoint.msgpack --factor 4 \\
        --format stablehlo --size 1080 1920 --out dlctus-x4-1080p.stablehlo
    python -m jtus.export --model shipped --factor 4 --format onnx --size 1080 1920 \\
        --out dlctus-x4-1080p.onnx

``torch``: the thesis's ``state_dict`` layout (``down.0.weight`` ..., NCHW kernels),
saved with ``torch.save``; the thesis's PyTorch model and
``jtus.models.dlctus.load_torch_checkpoint`` load it (torch needed only here).
``stablehlo`` and ``onnx``: one DLCTUS step at a fixed output size, serialized with
``jax.export`` (``jax.export.deserialize(bytes).call(...)`` runs it) or converted by
``jax2onnx`` (onnxruntime runs it). Inputs, in this order and with these ONNX names:
``color [1,h,w,3]`` linear RGB, ``depth [1,h,w,1]`` device depth, ``motion [1,h,w,2]``
backward motion in LR pixels, ``jitter [1,2]`` in [0,1)^2, ``exposure [1]`` (1 for LDR
colour), ``reset [1]`` bool and ``history [1,H,W,4]``; outputs ``frame [1,H,W,3]``
and the next ``history`` (``docs/conventions.md``, ``docs/integration.md``).
"""

from __future__ import annotations

import argparse
import sys


def load_dlctus(spec, factor):
    """``(model, params)`` of DLCTUS weights: ``shipped``, a ``.msgpack`` written by
    ``jtus.train`` or a ``.pt`` PyTorch checkpoint."""
    from jtus import models

    builtin = spec == "shipped" or "=" in spec or spec in models.NAMES
    entry = models.load(spec if builtin else f"m={spec}", factor)
    if entry is None:
        raise ValueError(f"--model: {spec} has no weights for factor {factor}")
    if not hasattr(entry.model.config, "formulation"):
        raise ValueError(f"--model: {spec} is not a DLCTUS network")
    return entry.model, entry.params


def to_torch(params, config, out):
    import torch

    from jtus.files import atomic_path
    from jtus.models import dlctus

    sd = dlctus.params_to_torch(params, config)
    with atomic_path(out) as tmp:
        torch.save(sd, tmp)
    return out


INPUTS = ("color", "depth", "motion", "jitter", "exposure", "reset", "history")
OUTPUTS = ("frame", "history_out")


def step_signature(model, params, size):
    """``(one_step, argument shapes)``: the exported function, one DLCTUS step at HR
    ``size``, taking and returning plain arrays in ``INPUTS`` / ``OUTPUTS`` order."""
    import jax
    import jax.numpy as jnp

    from jtus.frame import Frame
    from jtus.models import dlctus

    f = model.config.factor
    H, W = size
    if H % 4 or W % 4 or H % f or W % f:
        raise ValueError(f"--size: {H}x{W} must be a multiple of 4 and of factor {f}")
    h, w = H // f, W // f

    def one_step(color, depth, motion, jitter, exposure, reset, history):
        out, state = model.step(params, dlctus.State(history),
                                Frame(color, depth, motion, jitter, reset, exposure))
        return out, state.history

    S = jax.ShapeDtypeStruct
    args = (S((1, h, w, 3), jnp.float32), S((1, h, w, 1), jnp.float32),
            S((1, h, w, 2), jnp.float32), S((1, 2), jnp.float32), S((1,), jnp.float32),
            S((1,), jnp.bool_), S((1, H, W, 4), jnp.float32))
    return one_step, args


def to_onnx(model, params, size, out):
    """One step as an ONNX model (opset 23) by ``jax2onnx``, written atomically."""
    try:
        from jax2onnx import to_onnx as convert
    except ImportError as e:
        raise ValueError("--format onnx needs jax2onnx: pip install -e \".[export]\"") from e
    from jtus.files import atomic_path

    one_step, args = step_signature(model, params, size)
    proto = convert(one_step, list(args), model_name="dlctus_step",
                    input_names=list(INPUTS), output_names=list(OUTPUTS))
    with atomic_path(out) as tmp, open(tmp, "wb") as fh:
        fh.write(proto.SerializeToString())
    return out


def to_stablehlo(model, params, size, out):
    import jax
    from jax import export

    from jtus.files import atomic_path

    one_step, args = step_signature(model, params, size)
    try:
        import flatbuffers  # noqa: F401  (jax.export's serializer needs it)
    except ImportError as e:
        raise ValueError("--format stablehlo needs the flatbuffers package: "
                         "pip install -e \".[export]\"") from e
    exp = export.export(jax.jit(one_step))(*args)
    with atomic_path(out) as tmp, open(tmp, "wb") as fh:
        fh.write(exp.serialize())
    return out


def main(argv=None):
    from jtus.cli import sigterm_as_exit

    p = argparse.ArgumentParser(prog="python -m jtus.export", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default="shipped", help="shipped, a .msgpack or a .pt file")
    p.add_argument("--factor", type=int, required=True, choices=(2, 4))
    p.add_argument("--format", required=True, choices=("torch", "stablehlo", "onnx"))
    p.add_argument("--size", type=int, nargs=2, default=(1080, 1920), metavar=("H", "W"),
                   help="output size of the exported step (stablehlo, onnx)")
    p.add_argument("--out", required=True)
    p.add_argument("--force", action="store_true", help="replace an existing --out")
    args = p.parse_args(argv)
    sigterm_as_exit()
    try:
        from jtus.files import check_out_file
        check_out_file(args.out, args.force, kind="a file")
        model, params = load_dlctus(args.model, args.factor)
        if args.format == "torch":
            to_torch(params, model.config, args.out)
        elif args.format == "onnx":
            to_onnx(model, params, tuple(args.size), args.out)
        else:
            to_stablehlo(model, params, tuple(args.size), args.out)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    from jtus import cli  # not ``from jtus.cli import run``: a module may have its own run
    cli.run(main)
