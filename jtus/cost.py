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


def _conv(kernel_shape, px):
    kh, kw, ci, co = kernel_shape[-4:]
    return (kh * kw * ci * co * 2 + co) * px


def _nsrr(config, H, W):
    import jax

    from jtus.models import nsrr
    p = jax.eval_shape(lambda: nsrr.init(jax.random.PRNGKey(0), config))
    px, lr = H * W, H * W // config.factor ** 2
    ext = sum(_conv(q["kernel"].shape, lr) for k in ("extract_current", "extract_previous")
              for q in p[k])
    rew = sum(_conv(q["kernel"].shape, px) for q in p["reweight"])
    scales = [px, px, px // 4, px // 4, px // 16, px // 16, px // 4, px // 4, px, px]
    unet = sum(_conv(q["kernel"].shape, n) for q, n in zip(p["unet"], scales))
    feats = nsrr.FEATURES * config.frames
    warp = px * feats * 4 * 2
    compulsory = 4 * (lr * 6 + 2 * px * feats + px * 3)
    act = 4 * 2 * px * (sum(config.unet_widths()) + feats * 2)
    return Cost(ext + rew + unet + warp + px * feats, ext + rew + unet, compulsory,
                compulsory + act)


def _kpn(config, H, W):
    import jax

    from jtus.models import kpn
    p = jax.eval_shape(lambda: kpn.init(jax.random.PRNGKey(0), config))
    px, lr = H * W, H * W // config.factor ** 2
    net = sum(_conv(p[k]["kernel"].shape, px) for k in ("conv1", "conv2", "conv3", "hidden",
                                                        "kernel"))
    n = 2 * kpn.K * kpn.K
    apply = px * (n * 3 * 2 + n * 4)  # the two kernels on 3 channels, softmax
    warp = px * (16 * 8 * 2 + 20) + px * 4 * 3 * 2
    compulsory = 4 * (lr * 6 + 2 * px * 8 + px * 3)
    act = 4 * 2 * px * (kpn.IN_CHANNELS + 3 * config.width + n + kpn.HIDDEN)
    return Cost(net + apply + warp, net, compulsory, compulsory + act)


def _mlp(config, H, W):
    lr = H * W // config.factor ** 2
    sizes = (50,) + tuple(config.hidden) + (config.factor ** 2,)
    dense = sum(i * o * 2 + o for i, o in zip(sizes[:-1], sizes[1:])) * lr * 3
    compulsory = 4 * (lr * 4 + H * W * 3)
    return Cost(dense + lr * 3 * 60, dense, compulsory, compulsory + 4 * 2 * lr * 3 * sum(sizes))


def cost(model_name, config, H, W) -> Cost:
    """``model_name`` as in ``jtus.models.NAMES`` (its module decides the formula)."""
    kind = model_name.split("-")[0]
    fns = {"dlctus": _dlctus, "jau": _jau, "tus": _tus, "nsrr": _nsrr, "kpn": _kpn, "mlp": _mlp}
    if kind not in fns:
        raise ValueError(f"cost: no formula for model {model_name!r}")
    return fns[kind](config, H, W)


def table(names=None, factors=(4, 2), height=1080, width=1920) -> str:
    """A markdown table of parameters, FLOPs and bytes per output pixel and per frame
    (the layout of Table 2 of Herveau et al.)."""
    import jax

    from jtus import models

    names = names or models.NAMES
    lines = [f"Per output pixel and per {width}x{height} frame, float32 "
             "(`jtus/cost.py`):", "",
             "| model | factor | parameters | FLOP / pixel | network FLOP / pixel | "
             "bytes / pixel (compulsory) | GFLOP / frame | MB / frame |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name in names:
        for f in factors:
            m = models.build(name, f)
            c = cost(name, m.config, height, width)
            params = (models.param_count(jax.eval_shape(m.init, jax.random.PRNGKey(0)))
                      if name in models.TRAINABLE else 0)
            px = height * width
            lines.append(f"| {name} | {f}x | {params:,} | {c.flops / px:,.0f} | "
                         f"{c.network_flops / px:,.0f} | {c.bytes / px:.1f} | "
                         f"{c.flops / 1e9:.2f} | {c.bytes / 1e6:.0f} |")
    return "\n".join(lines)


def main(argv=None):
    import argparse

    from jtus import models

    p = argparse.ArgumentParser(prog="python -m jtus.cost",
                                description="FLOPs and bytes per output pixel of every model.")
    p.add_argument("--models", nargs="+", default=list(models.NAMES), choices=models.NAMES)
    p.add_argument("--factors", nargs="+", type=int, default=[4, 2])
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--width", type=int, default=1920)
    args = p.parse_args(argv)
    print(table(args.models, args.factors, args.height, args.width))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
