"""DLCTUS's trunk on XLA:CPU with its 3x3 convolutions as Winograd's minimal filtering
(Lavin and Gray 2016, ``jtus.models.winograd``) against XLA's convolution op
(``kernels.trunk_xla``), at inference sizes.

F(m x m, 3 x 3) cuts the edge-padded input into overlapping (m+2) x (m+2) tiles with
stride m, transforms each tile (``B^T d B``), multiplies the (m+2)^2 transformed
positions by the transformed kernels (``G g G^T``, computed once) as (m+2)^2 matmuls
``[tiles, C] @ [C, O]``, and transforms back to m x m outputs (``A^T M A``). The
multiplies per output fall from 9 C O to (m+2)^2 / m^2 C O: 2.25x fewer with F(2x2),
4x with F(4x4). The transforms are memory passes (each tile's (m+2)^2 positions written
out and read back), which the direct convolution does not make. Values are the
direct convolution's in exact arithmetic: checked here in float64 (to 1e-10) before
timing, and the float32 difference at the timed sizes reported beside the times. The
bound this tests: docs/performance.md, "What the inference target asks of this
machine".

    python experiments/trunk_winograd.py --rounds 3

Writes ``docs/results/<name>/result.{md,json}``.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from common import cpu_per_wall, rounds_ms, write
from jtus.bench.workloads import SIZES
from jtus.models import dlctus, kernels, layers, winograd
from jtus.sampling import pad_edge


def conv_winograd(x, u, b, m):
    """Edge-padded 3x3 convolution of ``x [B,H,W,C]`` plus ``b``, with ``u`` from
    ``winograd.transform_kernel``: ``layers.conv_edge``'s values by F(m x m, 3 x 3)."""
    return winograd.conv_valid(pad_edge(x, 1), u, m) + b


def transformed(w1, b1, w2, b2, m):
    """The stacked trunk weights (``kernels.stack_blocks``) with transformed kernels."""
    t = jax.vmap(lambda k: winograd.transform_kernel(k, m))
    return t(w1), b1, t(w2), b2


def trunk_winograd(u1, b1, u2, b2, h, m):
    """``kernels.trunk_xla`` with each convolution as ``conv_winograd``."""
    for i in range(u1.shape[0]):
        r = jax.nn.relu(conv_winograd(h, u1[i], b1[i], m))
        h = h + conv_winograd(r, u2[i], b2[i], m)
    return h


def check(args, ms, size=(37, 9)):
    """Each F(m) trunk equals the XLA trunk in float64 on a map whose size no tile
    divides (a misplaced tile or tap shows far above 1e-10)."""
    with jax.enable_x64(True):
        a64 = [a.astype(jnp.float64) for a in args]
        h = jnp.asarray(np.random.default_rng(0).normal(size=(1, *size, 32)))
        want = jax.jit(lambda x: kernels.trunk_xla(*a64, x))(h)
        for m in ms:
            got = jax.jit(lambda x, m=m: trunk_winograd(*transformed(*a64, m), x, m))(h)
            err = float(jnp.max(jnp.abs(got - want)))
            if not err <= 1e-10:
                raise SystemExit(f"F({m}x{m}, 3x3) differs from the trunk by {err}")


def measure(size, args, ms, repeats, rounds):
    H, W = SIZES[size]
    h = jnp.asarray(np.random.default_rng(1).normal(size=(1, H // 4, W // 4, 32)),
                    jnp.float32)
    xla = jax.jit(lambda x: kernels.trunk_xla(*args, x))
    jitted = {"XLA convolution": (xla, 9.0)}
    for m in ms:
        u = transformed(*args, m)
        jitted[f"F({m}x{m}, 3x3)"] = (jax.jit(lambda x, u=u, m=m: trunk_winograd(*u, x, m)),
                                      (m + 2) ** 2 / m ** 2)
    want = xla(h)
    scale = float(jnp.max(jnp.abs(want)))
    fns = {k: (lambda f=f: f(h).block_until_ready()) for k, (f, _) in jitted.items()}
    times = rounds_ms(fns, repeats, rounds)
    base = float(np.median(times["XLA convolution"]))
    return [{"size": size, "trunk": f"{H // 4}x{W // 4}", "variant": k,
             "multiplies_per_output": mult * 32 * 32, "ms": float(np.median(times[k])),
             "ms_rounds": times[k], "speedup": base / np.median(times[k]),
             "max_rel_diff": float(jnp.max(jnp.abs(f(h) - want))) / scale,
             "cores_busy": cpu_per_wall(fns[k], 3)[1]}
            for k, (f, mult) in jitted.items()]


def stages(size, k, m, repeats, rounds):
    """One convolution's three stages, each a program of its own, against XLA's
    convolution (ms, median of rounds)."""
    H, W = SIZES[size]
    x = jnp.asarray(np.random.default_rng(2).normal(size=(1, H // 4, W // 4, 32)),
                    jnp.float32)
    u = winograd.transform_kernel(k, m)
    tiles = jax.jit(lambda x: winograd.tiles_in(pad_edge(x, 1), m))
    products = jax.jit(lambda v: jnp.einsum("ktc,kco->kto", v, u))
    v = tiles(x)
    mm = products(v)
    progs = {"input transform": (tiles, x), "matmuls": (products, v),
             "output transform": (jax.jit(lambda mm: winograd.tiles_out(mm, x.shape, m)), mm),
             "XLA convolution": (jax.jit(lambda x: layers.conv_edge(x, k)), x)}
    fns = {k: (lambda f=f, a=a: f(a).block_until_ready()) for k, (f, a) in progs.items()}
    times = rounds_ms(fns, repeats, rounds)
    return {"size": size, "m": m, **{k: float(np.median(v)) for k, v in times.items()}}


def stage_table(rows):
    names = ("input transform", "matmuls", "output transform", "XLA convolution")
    return ("| size | F(m x m, 3x3) | " + " | ".join(f"{n} ms" for n in names) + " |\n"
            + "| --- " * 6 + "|\n" + "".join(
                f"| {r['size']} | {r['m']} | " + " | ".join(f"{r[n]:.1f}" for n in names)
                + " |\n" for r in rows))


def table(rows):
    head = ("| size | trunk | variant | multiplies per output pixel and convolution | "
            "ms (median of rounds) | rounds | XLA / this | max difference / max value "
            "(float32) | cores busy |\n" + "| --- " * 9 + "|\n")
    return head + "".join(
        f"| {r['size']} | {r['trunk']} | {r['variant']} | {r['multiplies_per_output']:.0f} | "
        f"{r['ms']:.1f} | {' '.join(f'{t:.0f}' for t in r['ms_rounds'])} | "
        f"{r['speedup']:.2f} | {r['max_rel_diff']:.1e} | {r['cores_busy']:.2f} |\n"
        for r in rows)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", nargs="+", default=["720p", "1080p"], choices=sorted(SIZES))
    p.add_argument("--tiles", nargs="+", type=int, default=[2, 4],
                   choices=sorted(winograd.MATRICES),
                   help="m of F(m x m, 3 x 3)")
    p.add_argument("--repeats", type=int, default=5, help="calls per round and variant")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--name", default="trunk-winograd")
    args = p.parse_args()
    if args.repeats < 1 or args.rounds < 1:
        raise SystemExit(f"--repeats/--rounds: expected at least 1, got {args.repeats} "
                         f"{args.rounds}")
    weights = kernels.stack_blocks(dlctus.init(jax.random.PRNGKey(0)), 4)
    check(weights, args.tiles)
    rows, split = [], []
    for size in args.sizes:
        rows += measure(size, weights, args.tiles, args.repeats, args.rounds)
        split += [stages(size, weights[0][0], m, args.repeats, args.rounds) for m in args.tiles]
    write(args.name, table(rows) + "\nOne convolution (the first block's first), its "
          "stages each timed as a program of its own:\n\n" + stage_table(split),
          {"rows": rows, "stages": split},
          note="Each round times every variant in turn (`timing.timeit_round_robin`, "
               f"{args.repeats} calls each); the table gives the median over rounds. "
               "Float32, batch 1, DLCTUS's initial weights (the speed does not depend on "
               "them); the kernels' transforms are computed before timing, as a deployed "
               "network would hold them.")


if __name__ == "__main__":
    main()
