"""Can a training window skip the scan's zero fill? Its residuals written into buffers the
caller donates, against JAX's autodiff of the scan.

JAX's autodiff of ``lax.scan`` stacks each frame's residuals in buffers that XLA:CPU
first fills with zeros, every step (``docs/performance.md``, "The scan's buffers"). Here
the window's forward scan calls ``jax.vjp`` on each frame and writes the leaves of the
returned pullback into buffers passed in and donated (so XLA updates them in place and
fills nothing), and a reverse scan rebuilds each frame's pullback from them. Three
variants of the bench's DLCTUS window (random frames, the loss on every frame, no
optimizer), timed round-robin in one process:

- ``autodiff``: ``jax.value_and_grad`` of ``rollout.window_loss`` (what training runs);
- ``pullbacks, donated``: the pullbacks' residuals in donated buffers;
- ``pullbacks, fresh``: the same with the buffers made (zero-filled) inside the step.

    python experiments/donated_residuals.py             # 2x, crop 128, batch 4, 8 frames

Writes ``docs/results/donated-residuals/result.{md,json}``.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
from common import write

from jtus import losses, models, rollout
from jtus.bench import random_window


def window(factor, crop, batch, seq):
    """``(variants, residual MiB per frame, largest gradient difference)``; each variant
    a function that runs one step and blocks."""
    model = models.build("dlctus", factor)
    loss_fn = losses.make(models.spec("dlctus").loss, factor)
    params = model.init(jax.random.PRNGKey(0))
    frames, targets = random_window(factor, crop, batch, seq)
    c0 = rollout.start(rollout.first_state(model, frames), targets[0])

    def plain(p, c):
        return rollout.window_loss(model.step, loss_fn, p, c, frames, targets,
                                   loss_frames=seq)[0]

    def frame_fn(p, cd, has_prev, frame, target):
        state, prev_out, prev_target = cd
        out, s = model.step(p, state, frame)
        loss = loss_fn(out, target, prev_out, prev_target, has_prev, frame)
        return (s, out.astype(jnp.float32), target.astype(jnp.float32)), loss

    tree = {}

    def pullback_leaves(p, cd, has_prev, frame, target):
        _, vjp = jax.vjp(lambda p, cd: frame_fn(p, cd, has_prev, frame, target), p, cd)
        leaves, tree["def"] = jax.tree_util.tree_flatten(vjp)
        return leaves

    cd0 = (c0.state, c0.prev_out, c0.prev_target)
    shapes = jax.eval_shape(pullback_leaves, params, cd0, c0.has_prev,
                            jax.tree_util.tree_map(lambda x: x[0], frames), targets[0])
    mib = sum(int(np.prod(s.shape)) * s.dtype.itemsize for s in shapes) / 2 ** 20

    def pullbacks(p, c, bufs):
        def fwd(carry, xs):
            cd, has_prev, bufs = carry
            t, frame, target = xs
            (cd2, loss), vjp = jax.vjp(
                lambda p, cd: frame_fn(p, cd, has_prev, frame, target), p, cd)
            bufs = tuple(jax.lax.dynamic_update_index_in_dim(b, x, t, 0)
                         for b, x in zip(bufs, jax.tree_util.tree_leaves(vjp)))
            return (cd2, jnp.asarray(True), bufs), loss

        ts = jnp.arange(seq)
        (cd, _, bufs), ls = jax.lax.scan(
            fwd, ((c.state, c.prev_out, c.prev_target), c.has_prev, bufs),
            (ts, frames, targets))

        def bwd(acc, xs):
            g, ct = acc
            t, ct_loss = xs
            vjp = jax.tree_util.tree_unflatten(
                tree["def"], [jax.lax.dynamic_index_in_dim(b, t, 0, False) for b in bufs])
            dp, dc = vjp((ct, ct_loss))
            return (jax.tree_util.tree_map(jnp.add, g, dp), dc), None

        zeros = jax.tree_util.tree_map(jnp.zeros_like, (p, cd))
        (g, _), _ = jax.lax.scan(bwd, zeros, (ts, jnp.full((seq,), 1 / seq, jnp.float32)),
                                 reverse=True)
        return ls.mean(), g, bufs

    def fresh():
        return tuple(jnp.zeros((seq,) + s.shape, s.dtype) for s in shapes)

    autodiff = jax.jit(jax.value_and_grad(plain))
    donated = jax.jit(pullbacks, donate_argnums=(2,))
    inside = jax.jit(lambda p, c: pullbacks(p, c, fresh())[:2])
    held = [fresh()]
    _, g_ref = autodiff(params, c0)
    _, g_don, held[0] = donated(params, c0, held[0])
    diff = max(float(jnp.max(jnp.abs(a - b))) for a, b in
               zip(jax.tree_util.tree_leaves(g_ref), jax.tree_util.tree_leaves(g_don)))

    def run_donated():
        loss, g, held[0] = donated(params, c0, held[0])
        jax.block_until_ready((loss, g))

    variants = {"autodiff": lambda: jax.block_until_ready(autodiff(params, c0)),
                "pullbacks, donated": run_donated,
                "pullbacks, fresh": lambda: jax.block_until_ready(inside(params, c0))}
    for fn in variants.values():  # compile and warm
        fn()
    return variants, mib, diff


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--factor", type=int, default=2, choices=(2, 4))
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--seq", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--name", default="donated-residuals")
    a = ap.parse_args(argv)
    variants, mib, diff = window(a.factor, a.crop, a.batch, a.seq)
    times = {k: [] for k in variants}
    for _ in range(a.repeats):
        for k, fn in variants.items():
            t = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t)
    base = np.median(times["autodiff"])
    rows = ["| variant | s/step (median) | against autodiff |", "| --- | --- | --- |"]
    for k, v in times.items():
        rows.append(f"| {k} | {np.median(v):.4f} | {base / np.median(v):.2f}x |")
    note = (f"DLCTUS {a.factor}x, crop {a.crop}, batch {a.batch}, {a.seq} frames, one device, "
            f"{a.repeats} rounds. The pullbacks keep {mib:.2f} MiB a frame; their gradients "
            f"differ from autodiff's by at most {diff:.1e}.")
    write(a.name, "\n".join(rows), {"args": vars(a), "seconds": times,
                                     "residual_mib_per_frame": mib, "max_grad_diff": diff},
          note)
    print("\n".join(rows))
    print(note)


if __name__ == "__main__":
    main()
