"""DLCTUS's trunk on XLA:CPU as one image against the same trunk cut into bands of rows,
each band computed from its rows and the halo of rows its eight convolutions reach (the
halo shrinking by a row per convolution, so the values are the same, checked here in
float64 before timing). The bands share nothing, so XLA:CPU's runtime can run their
convolutions side by side where one convolution keeps only part of the cores busy.
``--channel-parts N``: the same trunk with each convolution's output channels cut into
``N`` groups instead, one convolution each over the whole image (no halo; the edge
ring and bias added to their concatenation), another way to give the runtime
independent convolutions. Timed in turn in one process (``timing.timeit_round_robin``),
with how busy the cores are while each runs (process CPU seconds per wall second); the
trunk's size is the network's, a quarter of the output's in each dimension. See docs/performance.md,
"What the inference target asks of this machine".

    python experiments/trunk_strips.py --strips 2 4 8 --valid 4 --rounds 3
    python experiments/trunk_strips.py --strips --valid --channel-parts 2 4 --rounds 3 \
        --repeats 7 --name trunk-channel-parts

Writes ``docs/results/<name>/result.{md,json}``.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from common import cpu_per_wall, rounds_ms, write
from jtus.bench.workloads import SIZES
from jtus.models import dlctus, kernels, layers


def conv_band(x, k, b, top, bottom, valid=False):
    """3x3 convolution of a band of rows ``x [B,h,W,C]``: edge-padded in columns, and in
    rows edge-padded only where the band meets the image's ``top`` or ``bottom`` (a row
    is lost on each other side). SAME on the padded band, then cropped, as
    ``layers.conv_edge_fast`` does under differentiation; ``valid``: the VALID
    convolution, which computes only the kept values."""
    xp = jnp.pad(x, ((0, 0), (int(top), int(bottom)), (1, 1), (0, 0)), mode="edge")
    if valid:
        return layers.conv(xp, k, b, padding="VALID")
    return layers.conv(xp, k, b)[:, 1:-1, 1:-1]


def trunk_bands(w1, b1, w2, b2, h, bands, valid=False):
    """``kernels.trunk_xla`` computed as ``bands`` independent bands of rows."""
    H, halo = h.shape[1], 2 * w1.shape[0]
    edges = [round(i * H / bands) for i in range(bands + 1)]
    out = []
    for r0, r1 in zip(edges[:-1], edges[1:]):
        a, z = max(r0 - halo, 0), min(r1 + halo, H)
        top, bottom = a == 0, z == H
        x = h[:, a:z]
        for i in range(w1.shape[0]):
            r = jax.nn.relu(conv_band(x, w1[i], b1[i], top, bottom, valid))
            x = x[:, (0 if top else 2):x.shape[1] - (0 if bottom else 2)] + \
                conv_band(r, w2[i], b2[i], top, bottom, valid)
        start = a if top else r0  # the band's first row once its halo has shrunk away
        out.append(x[:, r0 - start:r1 - start])
    return jnp.concatenate(out, axis=1)


def conv_parts(x, k, b, parts):
    """``layers.conv_edge(x, k, b)`` as ``parts`` SAME convolutions, each to its share of
    the output channels, concatenated, plus the edge ring and the bias."""
    n = k.shape[-1] // parts
    out = jnp.concatenate([layers.conv(x, k[..., i * n:(i + 1) * n]) for i in range(parts)], -1)
    return out + b + layers.edge_ring(x, k)


def trunk_parts(w1, b1, w2, b2, h, parts):
    """``kernels.trunk_xla`` with every convolution as ``conv_parts``."""
    for i in range(w1.shape[0]):
        r = jax.nn.relu(conv_parts(h, w1[i], b1[i], parts))
        h = h + conv_parts(r, w2[i], b2[i], parts)
    return h


def check(args, bands, parts=()):
    """The bands equal the one-image trunk in float64 (a misplaced row shows >> 1e-12)."""
    with jax.enable_x64(True):
        a64 = [a.astype(jnp.float64) for a in args]
        h = jnp.asarray(np.random.default_rng(0).normal(size=(1, 37, 9, 32)))
        want = jax.jit(lambda x: kernels.trunk_xla(*a64, x))(h)
        for n in bands:  # each variant as one program, not operation by operation
            for valid in (False, True):
                got = jax.jit(lambda x, n=n, v=valid: trunk_bands(*a64, x, n, v))(h)
                err = float(jnp.max(jnp.abs(got - want)))
                if err > 1e-12:
                    raise SystemExit(f"{n} bands (valid={valid}) differ from the trunk "
                                     f"by {err}")
        for n in parts:
            err = float(jnp.max(jnp.abs(jax.jit(lambda x, n=n: trunk_parts(*a64, x, n))(h)
                                        - want)))
            if err > 1e-12:
                raise SystemExit(f"{n} channel groups differ from the trunk by {err}")


def measure(size, args, bands, valid, repeats, rounds, parts=()):
    H, W = SIZES[size]
    h = jnp.asarray(np.random.default_rng(1).normal(size=(1, H // 4, W // 4, 32)),
                    jnp.float32)
    jitted = {"one image": jax.jit(lambda x: kernels.trunk_xla(*args, x)),
              **{f"{n} bands": jax.jit(lambda x, n=n: trunk_bands(*args, x, n))
                 for n in bands},
              **{f"{n} bands, VALID": jax.jit(lambda x, n=n: trunk_bands(*args, x, n, True))
                 for n in valid},
              **{f"{n} channel groups": jax.jit(lambda x, n=n: trunk_parts(*args, x, n))
                 for n in parts}}
    fns = {k: (lambda f=f: f(h).block_until_ready()) for k, f in jitted.items()}
    times = rounds_ms(fns, repeats, rounds)
    base = float(np.median(times["one image"]))
    return [{"size": size, "trunk": f"{H // 4}x{W // 4}", "variant": k,
             "ms": float(np.median(v)), "ms_rounds": v, "speedup": base / np.median(v),
             "cores_busy": cpu_per_wall(fns[k], 3)[1]} for k, v in times.items()]


def table(rows):
    head = ("| size | trunk | variant | ms (median of rounds) | rounds | one image / this | "
            "cores busy |\n" + "| --- " * 7 + "|\n")
    return head + "".join(
        f"| {r['size']} | {r['trunk']} | {r['variant']} | {r['ms']:.1f} | "
        f"{' '.join(f'{t:.0f}' for t in r['ms_rounds'])} | {r['speedup']:.2f} | "
        f"{r['cores_busy']:.2f} |\n" for r in rows)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", nargs="+", default=["720p", "1080p"], choices=sorted(SIZES))
    p.add_argument("--strips", nargs="*", type=int, default=[2, 4, 8], help="band counts")
    p.add_argument("--valid", nargs="*", type=int, default=[4],
                   help="band counts also timed with VALID convolutions")
    p.add_argument("--channel-parts", nargs="*", type=int, default=[],
                   help="output-channel group counts (dividing 32)")
    p.add_argument("--repeats", type=int, default=5, help="calls per round and variant")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--name", default="trunk-strips")
    args = p.parse_args()
    if min(args.strips + args.valid, default=1) < 1:
        raise SystemExit(f"--strips/--valid: expected band counts >= 1, got "
                         f"{args.strips} {args.valid}")
    if any(n < 1 or 32 % n for n in args.channel_parts):
        raise SystemExit(f"--channel-parts: expected divisors of 32, got {args.channel_parts}")
    weights = kernels.stack_blocks(dlctus.init(jax.random.PRNGKey(0)), 4)
    check(weights, sorted(set(args.strips + args.valid)), args.channel_parts)
    rows = []
    for size in args.sizes:
        rows += measure(size, weights, args.strips, args.valid, args.repeats, args.rounds,
                        args.channel_parts)
    write(args.name, table(rows), {"rows": rows},
          note="Each round times every variant in turn (`timing.timeit_round_robin`, "
               f"{args.repeats} calls each); the table gives the median over rounds. "
               "Float32, batch 1, DLCTUS's initial weights (the speed does not depend "
               "on them).")


if __name__ == "__main__":
    main()
