"""Weights on the straight line between two checkpoints of one model: ``(1 - alpha) * A +
alpha * B``, parameter by parameter (a fine-tune ``B`` pulled back towards the weights
``A`` it started from). Written with ``B``'s run config, so that ``candidate_scores.py``
and ``static_hold.py`` load it like any checkpoint:

    python experiments/interpolate_weights.py jtus/weights/dlctus-x4.msgpack \\
        runs/steady-x4/checkpoint.msgpack --alpha 0.5 --out runs/interp-x4/interp

writes ``runs/interp-x4/interp.msgpack`` and ``interp.json``. Refuses checkpoints of
different models, factors or parameter shapes, and an ``alpha`` outside [0, 1], before
anything is written.
"""

from __future__ import annotations

import argparse

import jax

from jtus import checkpoint, config, loading


def interpolate(params_a, params_b, alpha):
    """``(1 - alpha) * params_a + alpha * params_b`` leaf by leaf; ``ValueError`` when the
    trees differ in structure or in a leaf's shape, or ``alpha`` is outside [0, 1]."""
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha: expected a number in [0, 1], got {alpha}")
    ta, tb = jax.tree_util.tree_structure(params_a), jax.tree_util.tree_structure(params_b)
    if ta != tb:
        raise ValueError(f"params: the two checkpoints hold different parameters ({ta} "
                         f"against {tb})")
    for (k, a), b in zip(jax.tree_util.tree_leaves_with_path(params_a),
                         jax.tree_util.tree_leaves(params_b)):
        if a.shape != b.shape:
            raise ValueError(f"params: {jax.tree_util.keystr(k)} has shape {a.shape} in "
                             f"the first checkpoint and {b.shape} in the second")
    return jax.tree_util.tree_map(lambda a, b: (1.0 - alpha) * a + alpha * b,
                                  params_a, params_b)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("a", help="the first checkpoint (alpha 0)")
    p.add_argument("b", help="the second checkpoint (alpha 1); its config is written")
    p.add_argument("--alpha", type=float, default=0.5)
    p.add_argument("--out", required=True, help="output base: writes OUT.msgpack, OUT.json")
    args = p.parse_args(argv)
    params_a, cfg_a = loading.load_params(args.a)
    params_b, cfg_b = loading.load_params(args.b)
    if (cfg_a.model, cfg_a.factor) != (cfg_b.model, cfg_b.factor):
        raise SystemExit(f"{args.b}: {cfg_b.model} at {cfg_b.factor}x, but {args.a} is "
                         f"{cfg_a.model} at {cfg_a.factor}x")
    try:
        mid = interpolate(params_a, params_b, args.alpha)
    except ValueError as e:
        raise SystemExit(str(e)) from e
    print(checkpoint.write_params(args.out, mid, config.to_json(cfg_b)))


if __name__ == "__main__":
    main()
