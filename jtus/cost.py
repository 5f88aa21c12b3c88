"""Analytic FLOPs and bytes per frame, from a model's config and the HR size.

Counts are multiply-adds x 2 for convolutions and matmuls, and the arithmetic of the
hand-written stages (taps x channels x 2 for a warp). Bytes are the compulsory
traffic of one frame in float32: the LR inputs read, the carried state read and
written, the output written; ``activation_bytes`` adds one write and one read of every
intermediate network tensor, the traffic of an unfused implementation.
"""

from __future__ import annotations

from typing import NamedTuple

_WARP_TAPS = {"nearest": 1, "bilinear": 4, "bicubic": 16, "catmull_rom": 16, "bicubic9": 36,
              "bicubic5": 20}


class Cost(NamedTuple):
    flops: float             # per frame
    network_flops: float     # the convolution part
    bytes: float             # compulsory, float32
    activation_bytes: float  # plus the network's intermediates written and read once


def _dlctus(config, H, W):
    n = (H // 4) * (W // 4)
    c = config.channels
    down = n * c * (4 * 4 * 8) * 2
    convs = 2 * config.blocks * n * c * c * 9 * 2
    net = down + convs + n * c * config.blocks * 3  # bias, ReLU, residual add
    px = H * W
    warp = _WARP_TAPS[config.warp] * 4 * 2 + 20  # 4 channels, plus the tap weights
    prep = px * (warp + 4 * 4 * 2 + 2 * 4 * 2 + 8)  # JAU, motion up-sampling, zero-up
    out = px * 4 * 4  # eq. 44-45 and clamps
    lr = px // (config.factor ** 2)
    compulsory = 4 * (lr * 6 + 2 * px * 4 + px * 3)
    act = 4 * 2 * (px * 8 + n * c * (1 + 2 * config.blocks) + px * 2)
    return Cost(net + prep + out, net, compulsory, compulsory + act)


def _jau(config, H, W):
    px = H * W
    taps = _WARP_TAPS[config.method]
    lr = px // (config.factor ** 2)
    return Cost(px * 3 * taps * 2 + px * 10, 0.0, 4 * (lr * 3 + px * 3), 4 * (lr * 3 + px * 3))


def _tus(config, H, W):
    px = H * W
    lr = px // (config.factor ** 2)
    scaled = px * (3 * 4 * 2 if config.filter == "tent" else 9 * (3 * 2 + 8))
    warp = px * (_WARP_TAPS[config.warp] * 4 * 2 + 20)
    rect = 0 if config.rectify == "none" else px * 9 * 3 * 3
    blend = px * 12
    compulsory = 4 * (lr * 6 + 2 * px * 4 + px * 3)
    return Cost(scaled + warp + rect + blend, 0.0, compulsory, compulsory)


def cost(model_name, config, H, W) -> Cost:
    """``model_name`` as in ``jtus.models.NAMES`` (its module decides the formula)."""
    kind = model_name.split("-")[0]
    fns = {"dlctus": _dlctus, "jau": _jau, "tus": _tus}
    if kind not in fns:
        raise ValueError(f"cost: no formula for model {model_name!r}")
    return fns[kind](config, H, W)
