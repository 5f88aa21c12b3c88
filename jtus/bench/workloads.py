"""The bench's workloads: the machine's peak, one inference step of any registered
model, one training step of any trainable model, and the PyTorch reference's where
the model has one (``Spec.torch_reference``), each as a blocking callable; and the
records ``python -m jtus.bench`` reports.

Every timing is jitted, warm (the first call compiles and is not counted), blocked
until ready, and the median of ``repeats`` runs (``jtus.timing``). A reference runs
the same workload, each repeat alternating with jtus's (``timing.timeit_pair``), so
both medians come from the same minutes of a noisy machine; ratios are torch time /
jtus time.
"""

from __future__ import annotations

import importlib
import os

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jtus import cost, losses, models, rollout, sharding, train
from jtus.frame import Frame
from jtus.models import layers
from jtus.timing import timeit, timeit_pair, timeit_round_robin

SIZES = {"720p": (720, 1280), "1080p": (1080, 1920), "4k": (2160, 3840), "256": (256, 256),
         "64": (64, 64)}


def peaks(repeats):
    """GFLOP/s of a 2048^3 float32 matmul, of DLCTUS's own 3x3 32->32 convolution at
    the 1080p network size and of a 3x3 64->64 one: what this machine can do."""
    out = {}
    n = 2048
    a = jnp.asarray(np.random.default_rng(0).normal(size=(n, n)), jnp.float32)
    mm = jax.jit(lambda x: x @ x)
    out["matmul_gflops"] = 2 * n ** 3 / timeit(lambda: mm(a).block_until_ready(), repeats) / 1e9
    for name, (h, w, c) in {"conv_dlctus_gflops": (270, 480, 32),
                            "conv_64_gflops": (256, 256, 64)}.items():
        x = jnp.asarray(np.random.default_rng(1).normal(size=(1, h, w, c)), jnp.float32)
        k = jnp.asarray(np.random.default_rng(2).normal(size=(3, 3, c, c)), jnp.float32) * 0.05
        cv = jax.jit(lambda x, k: layers.conv(x, k))
        flops = h * w * c * c * 9 * 2
        out[name] = flops / timeit(lambda: cv(x, k).block_until_ready(), repeats) / 1e9
    return out


def random_frame(h, w, b=1, seed=0):
    """A random LR ``Frame`` (``b`` x ``h`` x ``w``) for timings: colour and jitter
    uniform, depth in [0.5, 1), motion normal with 0.5 LR pixels' spread."""
    r = np.random.default_rng(seed)
    return Frame(jnp.asarray(r.uniform(size=(b, h, w, 3)), jnp.float32),
                 jnp.asarray(r.uniform(0.5, 1.0, size=(b, h, w, 1)), jnp.float32),
                 jnp.asarray(r.normal(scale=0.5, size=(b, h, w, 2)), jnp.float32),
                 jnp.asarray(r.uniform(size=(b, 2)), jnp.float32))


def torch_reference(name):
    """The PyTorch reference module of model ``name`` (``jtus.reference``), or None
    when it has none or torch is not installed."""
    ref = models.spec(name).torch_reference
    if not ref:
        return None
    try:
        import torch  # lazy: torch is optional, only for the reference timings
    except ImportError:
        return None
    # as many threads as cores this process may run on (taskset), as XLA:CPU does
    torch.set_num_threads(len(os.sched_getaffinity(0)))
    return importlib.import_module(f"jtus.reference.{ref}")


def infer_workload(name, factor, size, dtype="float32", **overrides):
    """One jitted inference step of ``name`` at HR ``size``, its state donated.
    Returns ``(run, hlo, model, params, state, frame)``: ``run()`` steps once and
    blocks; ``hlo()`` is the compiled module's text (for profiles)."""
    H, W = size
    over = dict({"dtype": dtype} if len(models.spec(name).dtypes) > 1 else {}, **overrides)
    model = models.build(name, factor, **over)
    params = model.init(jax.random.PRNGKey(0))
    frame = random_frame(H // factor, W // factor)
    state = [model.init_state(frame)]
    step = jax.jit(model.step, donate_argnums=(1,))

    def run():
        out, state[0] = step(params, state[0], frame)
        out.block_until_ready()

    def hlo():
        return step.lower(params, state[0], frame).compile().as_text()

    return run, hlo, model, params, state, frame


def bench_infer(name, factor, size, repeats, dtype="float32", reference=True, **overrides):
    """One model's inference timing record; with ``reference``, its PyTorch reference
    (when it has one) timed alternately with it."""
    H, W = size
    run, _, model, params, state, frame = infer_workload(name, factor, size, dtype, **overrides)
    c = cost.cost(name, model.config, H, W)
    ref = torch_reference(name) if reference else None
    against = ref.infer_workload(model.config, size) if ref is not None else None
    fns = {"step": run}
    if against is not None:
        fns["torch"] = against
    network = models.spec(name).network
    if network is not None:
        fn, args = network(params, state[0], frame, model.config)
        net = jax.jit(fn)
        fns["network"] = lambda: net(*args).block_until_ready()
    t = timeit_round_robin(fns, repeats)  # in turn: the columns see the same machine
    seconds = t["step"]
    rec = {"model": name, "factor": factor, "size": f"{H}x{W}", "dtype": dtype, **overrides,
           "ms": seconds * 1e3, "gflop": c.flops / 1e9, "gflops": c.flops / seconds / 1e9,
           "mbytes": c.bytes / 1e6}
    if hasattr(model.config, "trunk_form"):  # the form that ran ("auto" resolved)
        rec["kernels"] = model.config.trunk_form()
    if "torch" in t:
        rec.update(torch_ms=t["torch"] * 1e3, torch_over_jtus=t["torch"] / seconds)
    if "network" in t:
        rec.update(network_ms=t["network"] * 1e3,
                   network_gflops=c.network_flops / t["network"] / 1e9)
    return rec


def random_window(factor, crop, batch, seq):
    """A training window of random data: time-major ``Frame [T,B,...]`` of ``crop //
    factor`` pixels (reset on the first frame) and HR targets ``[T,B,crop,crop,3]``."""
    h = crop // factor
    frames = [random_frame(h, h, batch, seed=t) for t in range(seq)]
    frames = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *frames)
    frames = frames._replace(reset=jnp.zeros((seq, batch), bool).at[0].set(True))
    targets = jnp.asarray(np.random.default_rng(9).uniform(size=(seq, batch, crop, crop, 3)),
                          jnp.float32)
    return frames, targets


def train_workload(factor, crop, batch, seq, loss_frames, remat=False, unroll=1,
                   conv_backward="auto", warp="bicubic", hoist=False, name="dlctus",
                   kernels="auto", remat_edges=True, split=True):
    """One BPTT training step of ``name`` (its own loss, Adam) on random data; with
    ``split`` and several devices, the batch split over them as ``jtus.train`` does (with
    several processes, ``batch`` is each process's part).
    ``conv_backward``, ``warp``, ``kernels`` and ``remat_edges`` apply to models whose
    config has them. Returns
    ``(run, hlo, model)``: ``run()`` takes one step and blocks; ``hlo()`` is the
    compiled module's text (for profiles)."""
    spec = models.spec(name)
    fields = spec.config(factor).__dataclass_fields__
    over = {k: v for k, v in (("conv_backward", conv_backward), ("warp", warp),
                              ("kernels", kernels), ("remat_edges", remat_edges))
            if k in fields}
    model = models.build(name, factor, **over)
    opt = optax.adam(1e-4)
    ts = [train.create_train_state(model.init(jax.random.PRNGKey(0)), opt)]
    mesh = sharding.data_mesh(batch) if split else None
    step = train.make_train_step(model, losses.make(spec.loss, factor), opt,
                                 loss_frames=loss_frames, remat=remat, unroll=unroll,
                                 hoist=hoist, mesh=mesh)
    frames, targets = random_window(factor, crop, batch, seq)
    local = frames, targets  # this process's part (with several processes, ``batch`` each)
    if mesh is not None:
        ts[0] = sharding.replicate(ts[0], mesh)
        frames, targets = sharding.shard((frames, targets), mesh, axis=1)

    def carry():
        c = rollout.start(rollout.first_state(model, local[0]), local[1][0])
        return c if mesh is None else sharding.shard(c, mesh, axis=0)

    def run():
        ts[0], _, stats = step(ts[0], carry(), frames, targets)
        stats["loss"].block_until_ready()

    def compiled():
        return step.lower(ts[0], carry(), frames, targets).compile()

    def hlo():
        return compiled().as_text()

    run.compiled = compiled  # for the memory the compiled step needs (bench_train)
    run.devices = 1 if mesh is None else mesh.devices.size
    return run, hlo, model


def bench_train(factor, crop, batch, seq, loss_frames, repeats, remat=False, unroll=1,
                conv_backward="auto", warp="bicubic", reference=True, hoist=False,
                name="dlctus", kernels="auto"):
    """The training-step timing record; with ``reference``, the PyTorch reference's
    step (when it has one with a training workload) timed alternately with it."""
    run, _, model = train_workload(factor, crop, batch, seq, loss_frames, remat, unroll,
                                   conv_backward, warp, hoist, name, kernels)
    # a training step runs the network forward and, for the frames that reach the loss,
    # its two backward products (input and kernel gradients), each as costly as the
    # forward: at least 3x the forward FLOPs of every frame (BPTT reaches all of them)
    fwd = cost.cost(name, model.config, crop, crop).flops * batch * seq
    rec = {"model": name, "factor": factor, "crop": crop, "batch": batch, "seq": seq,
           "loss_frames": loss_frames, "gflop_per_step": 3 * fwd / 1e9,
           "remat": remat, "unroll": bool(unroll is True),
           "conv_backward": (model.config.train_conv_form(batch // run.devices, crop)
                             if hasattr(model.config, "train_conv_form") else "-"),
           "warp": getattr(model.config, "warp", "-"), "hoist": hoist,
           "kernels": model.config.trunk_form() if hasattr(model.config, "trunk_form") else "-",
           "devices": run.devices}
    try:  # what XLA plans for the step: temporaries plus arguments and outputs
        mem = run.compiled().memory_analysis()
        rec["peak_mib"] = (mem.temp_size_in_bytes + mem.argument_size_in_bytes
                           + mem.output_size_in_bytes) / 2 ** 20
    except Exception:  # not every backend reports it
        pass
    frames = batch * seq
    ref = torch_reference(name) if reference else None
    against = (ref.train_workload(factor, crop, batch, seq, loss_frames)
               if ref is not None and hasattr(ref, "train_workload") else None)
    if against is None:
        seconds = timeit(run, repeats)
        return dict(rec, s_per_step=seconds, frames_per_s=frames / seconds)
    seconds, other = timeit_pair(run, against, repeats)
    return dict(rec, s_per_step=seconds, torch_s_per_step=other, torch_over_jtus=other / seconds,
                frames_per_s=frames / seconds, torch_frames_per_s=frames / other)
