"""Training: the jitted train step over ``jtus.rollout`` windows (CLI to come).

One jit region per optimizer step with the train state donated (big_vision's
habit). Sequences start with ``frame.reset`` set, so the model initializes its
history inside the step: BPTT and every TBPTT window share one trace.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import optax

from jtus import rollout


class TrainState(NamedTuple):
    step: jax.Array
    params: Any
    opt_state: Any


def create_train_state(params, optimizer) -> TrainState:
    import jax.numpy as jnp
    return TrainState(jnp.zeros((), jnp.int32), params, optimizer.init(params))


def make_train_step(model, loss_fn, optimizer, *, loss_frames, keep_at=None, remat=False,
                    unroll=1, jit=True):
    """``(train_state, carry, frames [T,B,...], targets [T,B,H,W,3]) ->
    (train_state, next carry, metrics)``.

    BPTT: a window of the whole sequence, ``loss_frames`` = K. TBPTT(k1, k2): windows
    of k2 frames from ``rollout.tbptt_windows``, ``loss_frames = k1`` and
    ``keep_at = k1`` when k1 < k2; the returned carry (gradient cut) starts the next
    window.
    """

    def train_step(ts: TrainState, carry: rollout.Carry, frames, targets):
        def f(p):
            return rollout.window_loss(model.step, loss_fn, p, carry, frames, targets,
                                       loss_frames=loss_frames, keep_at=keep_at, remat=remat,
                                       unroll=unroll)

        (loss, (last, kept)), grads = jax.value_and_grad(f, has_aux=True)(ts.params)
        updates, opt_state = optimizer.update(grads, ts.opt_state, ts.params)
        params = optax.apply_updates(ts.params, updates)
        nxt = jax.lax.stop_gradient(kept if keep_at is not None else last)
        stats = {"loss": loss, "grad_norm": optax.tree.norm(grads),
                 "param_norm": optax.tree.norm(params)}
        return TrainState(ts.step + 1, params, opt_state), nxt, stats

    return jax.jit(train_step, donate_argnums=(0, 1)) if jit else train_step
