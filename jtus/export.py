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

import jax
import jax.numpy as jnp
from jax import export

from jtus import cli, loading, models
from jtus.files import atomic_path, check_out_file
from jtus.frame import Frame


def load_exportable(spec, factor):
    """``(model, params, Spec)`` of weights whose model exports (``Spec.export``):
    ``shipped``, a ``.msgpack`` written by ``jtus.train`` or a ``.pt`` checkpoint."""
    builtin = spec == "shipped" or "=" in spec or spec in models.NAMES
    entry = loading.load(spec if builtin else f"m={spec}", factor)
    if entry is None:
        raise ValueError(f"--model: {spec} has no weights for factor {factor}")
    s = models.spec(entry.name)
    if s.export is None:
        exportable = [n for n, x in models.REGISTRY.items() if x.export is not None]
        raise ValueError(f"--model: {spec} is a {entry.name} model, which does not export; "
                         f"exportable: {exportable}")
    return entry.model, entry.params, s


def to_torch(params, config, spec, out):
    """The parameters as the PyTorch ``state_dict`` of the model's reference layout,
    saved with ``torch.save`` atomically."""
    if spec.torch_state_dict is None:
        raise ValueError(f"--format torch: {spec.name} has no PyTorch layout")
    import torch  # lazy: torch is optional, needed only for --format torch

    sd = spec.torch_state_dict(params, config)
    with atomic_path(out) as tmp:
        torch.save(sd, tmp)
    return out


FRAME_INPUTS = ("color", "depth", "motion", "jitter", "exposure", "reset")


def io_names(spec):
    """``(input names, output names)`` of an exported step: the frame's arrays, then
    the state's (``Spec.export``); the frame, then the next state (suffix ``_out``)."""
    state = spec.export.names
    return FRAME_INPUTS + state, ("frame",) + tuple(f"{n}_out" for n in state)


def step_signature(model, params, spec, size):
    """``(one_step, argument shapes)``: the exported function, one step at HR ``size``,
    taking and returning plain arrays in ``io_names`` order."""

    f = model.config.factor
    H, W = size
    if not (4 <= H <= 16384 and 4 <= W <= 16384):
        raise ValueError(f"--size: expected H and W in [4, 16384], got {H}x{W}")
    if H % 4 or W % 4 or H % f or W % f:
        raise ValueError(f"--size: {H}x{W} must be a multiple of 4 and of factor {f}")
    h, w = H // f, W // f

    io = spec.export

    def one_step(color, depth, motion, jitter, exposure, reset, *state):
        out, nxt = model.step(params, io.from_arrays(*state),
                              Frame(color, depth, motion, jitter, reset, exposure))
        return (out, *io.to_arrays(nxt))

    S = jax.ShapeDtypeStruct
    args = (S((1, h, w, 3), jnp.float32), S((1, h, w, 1), jnp.float32),
            S((1, h, w, 2), jnp.float32), S((1, 2), jnp.float32), S((1,), jnp.float32),
            S((1,), jnp.bool_)) + tuple(S(shape, jnp.float32)
                                        for shape in io.shapes(model.config, H, W))
    return one_step, args


def to_onnx(model, params, spec, size, out, native=True):
    """One step as an ONNX model, written atomically: the model's own graph of native
    operators (``ExportIO.onnx_graph``: symbolic batch and size, so ``size`` is not
    used) where it has one and ``native``; otherwise jtus's step at ``size`` converted
    by ``jax2onnx`` (opset 23, fixed sizes). Returns ``"native"`` or ``"converted"``."""
    proto = None
    if native and spec.export.onnx_graph is not None:
        try:
            import onnx  # noqa: F401  lazy: optional (the export extra)
        except ImportError as e:
            raise ValueError("--format onnx needs onnx: pip install -e \".[export]\"") from e
        try:
            proto = spec.export.onnx_graph(params, model.config)
        except NotImplementedError as e:
            print(f"note: {e}; converting jtus's step with jax2onnx at {size[0]}x{size[1]}",
                  file=sys.stderr)
    kind = "native" if proto is not None else "converted"
    if proto is None:
        try:
            from jax2onnx import to_onnx as convert  # lazy: optional (the export extra)
        except ImportError as e:
            raise ValueError("--format onnx needs jax2onnx: pip install -e \".[export]\"") from e
        one_step, args = step_signature(model, params, spec, size)
        inputs, outputs = io_names(spec)
        proto = convert(one_step, list(args), model_name=f"{spec.name}_step",
                        input_names=list(inputs), output_names=list(outputs))
    with atomic_path(out) as tmp, open(tmp, "wb") as fh:
        fh.write(proto.SerializeToString())
    return kind


PLATFORMS = ("cpu", "cuda", "rocm", "tpu")


def to_stablehlo(model, params, spec, size, out, platforms=("cpu",)):
    """One step serialized by ``jax.export`` (StableHLO) for ``platforms`` (one
    serialized program that runs on each of them), written atomically."""
    bad = [p for p in platforms if p not in PLATFORMS]
    if bad or not platforms:
        raise ValueError(f"--platform: expected some of {PLATFORMS}, got {list(platforms)}")
    one_step, args = step_signature(model, params, spec, size)
    try:
        import flatbuffers  # noqa: F401  lazy: optional, jax.export's serializer needs it
    except ImportError as e:
        raise ValueError("--format stablehlo needs the flatbuffers package: "
                         "pip install -e \".[export]\"") from e
    exp = export.export(jax.jit(one_step), platforms=tuple(platforms))(*args)
    with atomic_path(out) as tmp, open(tmp, "wb") as fh:
        fh.write(exp.serialize())
    return out


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m jtus.export", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default="shipped", help="shipped, a .msgpack or a .pt file")
    p.add_argument("--factor", type=int, required=True, choices=(2, 4))
    p.add_argument("--format", required=True, choices=("torch", "stablehlo", "onnx"))
    p.add_argument("--size", type=int, nargs=2, default=(1080, 1920), metavar=("H", "W"),
                   help="output size of the exported step (stablehlo; onnx only where the "
                        "graph is converted: the native graph takes any size); "
                        "default: %(default)s")
    p.add_argument("--platform", nargs="+", default=["cpu"], choices=PLATFORMS,
                   help="stablehlo: the platforms the program is lowered for; "
                        "default: %(default)s")
    p.add_argument("--converted", action="store_true",
                   help="onnx: convert jtus's step with jax2onnx at --size instead of "
                        "writing the native-operator graph")
    p.add_argument("--out", required=True)
    p.add_argument("--force", action="store_true", help="replace an existing --out")
    args = p.parse_args(argv)
    cli.sigterm_as_exit()
    try:
        check_out_file(args.out, args.force, kind="a file")
        model, params, spec = load_exportable(args.model, args.factor)
        if args.format == "torch":
            to_torch(params, model.config, spec, args.out)
        elif args.format == "onnx":
            kind = to_onnx(model, params, spec, tuple(args.size), args.out,
                           native=not args.converted)
            print(f"onnx graph: {kind}")
        else:
            to_stablehlo(model, params, spec, tuple(args.size), args.out, args.platform)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    cli.run(main)
