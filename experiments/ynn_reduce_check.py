"""Training gradients with and without XLA:CPU's YNNPACK reduction fusion.

    python experiments/ynn_reduce_check.py
    PYTHONPATH=<an older checkout> python experiments/ynn_reduce_check.py --name NAME

jaxlib 0.10.2's XLA:CPU compiled the jitted gradient of a one-sum bilinear up-sampling
into a YNNPACK reduction fusion that returned wrong values (``jtus.sampling.upsample``;
``tests/test_upsample_jitter.py::test_jitted_gradient_of_bilinear_upsampling_equals_torch``).
This computes the gradient of one training window (the bench's random crops, the model's
own loss, loss on the last 5 of 8 frames) for each model, factor and batch, once in this
process and once in a child process with that fusion removed
(``XLA_FLAGS=--xla_cpu_experimental_ynn_fusion_type=-reduce``), and reports the largest
difference of each parameter's gradient relative to its largest value. Run against an
older checkout (``PYTHONPATH``), it says whether weights trained with that checkout
followed the right gradients. Writes ``docs/results/<name>/result.{md,json}``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

import numpy as np

MODELS = ("nsrr", "nsrr-fast", "kpn", "mlp", "dlctus")


def gradients(name, factor, batch, crop, out):
    """Write the window's loss and gradient leaves to ``out`` (``.npz``)."""
    import jax

    from jtus import bench, losses, models, rollout

    model = models.build(name, factor)
    params = model.init(jax.random.PRNGKey(0))
    frames, targets = bench.random_window(factor, crop, batch, 8)
    loss_fn = losses.make(models.spec(name).loss, factor)

    def loss(p):
        carry = rollout.start(rollout.first_state(model, frames), targets[0])
        return rollout.window_loss(model.step, loss_fn, p, carry, frames, targets,
                                   loss_frames=5)[0]

    value, grads = jax.jit(jax.value_and_grad(loss))(params)
    np.savez(out, loss=np.asarray(value),
             **{f"g{i}": np.asarray(g) for i, g in enumerate(jax.tree_util.tree_leaves(grads))})


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", default=["nsrr", "nsrr-fast"], choices=MODELS,
                   help="default: the models whose gradients pass through the up-sampling")
    p.add_argument("--factors", nargs="+", type=int, default=[4, 2])
    p.add_argument("--batches", nargs="+", type=int, default=[2],
                   help="2: a device's share of python -m jtus.train's batch of 4")
    p.add_argument("--crop", type=int, default=128)
    p.add_argument("--name", default="ynn-reduce-check", help="docs/results/<name>/")
    p.add_argument("--child", nargs=5, metavar=("MODEL", "FACTOR", "BATCH", "CROP", "OUT"),
                   help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        m, f, b, c, out = args.child
        gradients(m, int(f), int(b), int(c), out)
        return 0
    from common import write  # noqa: E402 (the child needs no results folder)

    rows, data = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for m in args.models:
            for f in args.factors:
                for b in args.batches:
                    files = {}
                    for variant, flags in (("default", ""),
                                           ("no YNNPACK reduce",
                                            "--xla_cpu_experimental_ynn_fusion_type=-reduce")):
                        out = os.path.join(tmp, f"{m}-{f}-{b}-{len(files)}.npz")
                        env = dict(os.environ, XLA_FLAGS=(os.environ.get("XLA_FLAGS", "")
                                                          + " " + flags).strip())
                        subprocess.run([sys.executable, __file__, "--child", m, str(f), str(b),
                                        str(args.crop), out], env=env, check=True)
                        files[variant] = np.load(out)
                    a, ref = files["default"], files["no YNNPACK reduce"]
                    keys = [k for k in ref.files if k != "loss"]
                    rel = max(float(np.abs(a[k] - ref[k]).max())
                              / (float(np.abs(ref[k]).max()) + 1e-30) for k in keys)
                    finite = all(np.isfinite(a[k]).all() for k in keys)
                    rows.append(f"| {m} | {f}x | {b} | {float(a['loss']):.6f} | "
                                f"{float(ref['loss']):.6f} | {rel:.1e} | {finite} |")
                    data.append({"model": m, "factor": f, "batch": b, "loss": float(a["loss"]),
                                 "loss_no_reduce": float(ref["loss"]), "grad_rel_diff": rel,
                                 "finite": finite})
                    print(rows[-1], file=sys.stderr)
    import jtus

    table = (f"Gradient of one training window (crop {args.crop}, 8 frames, loss on the last "
             f"5) with XLA:CPU's defaults and without its YNNPACK reduction fusion; jtus "
             f"imported from `{os.path.dirname(jtus.__file__)}`.\n\n"
             "| model | factor | batch | loss | loss, no reduce fusion | largest gradient "
             "difference (relative) | finite |\n| --- | --- | --- | --- | --- | --- | --- |\n"
             + "\n".join(rows))
    write(args.name, table, {"jtus": os.path.dirname(jtus.__file__), "rows": data})
    return 0


if __name__ == "__main__":
    sys.exit(main())
