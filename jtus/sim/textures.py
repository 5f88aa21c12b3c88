"""Procedural textures, prefiltered analytically with a box filter over the sample's
footprint (``width`` in texture periods), so that a mip bias can be simulated
exactly: a wider footprint blurs, a narrower one aliases.

Values are in [0, 1]."""

from __future__ import annotations

import jax.numpy as jnp

_EPS = 1e-4


def _tri(u):
    """Integral of the period-2 square wave s (+1 on [0,1), -1 on [1,2))."""
    return 1.0 - jnp.abs(jnp.mod(u, 2.0) - 1.0)


def square_box(u, width):
    """The square wave s(u) box-filtered over [u - w/2, u + w/2], in [-1, 1]."""
    w = jnp.maximum(width, _EPS)
    return (_tri(u + w / 2) - _tri(u - w / 2)) / w


def checker(u, v, width):
    return 0.5 + 0.5 * square_box(2 * u, 2 * width) * square_box(2 * v, 2 * width)


def stripes(u, v, width):
    return 0.5 + 0.5 * square_box(2 * u, 2 * width)


def zoneplate(u, v, width, k=6.0):
    """cos(k r^2), attenuated by the box filter's sinc at the local frequency k r / pi."""
    r2 = u * u + v * v
    freq = k * jnp.sqrt(r2) / jnp.pi
    return 0.5 + 0.5 * jnp.cos(k * r2) * jnp.sinc(freq * width)


TEXTURE_FNS = {"checker": checker, "stripes": stripes, "zoneplate": zoneplate}


# ---------------------------------------------------------------- the random family's textures
# Each is prefiltered over the footprint ``width`` (in texture periods) so that the
# mip bias of eq. 47 is simulated as for the ones above: pulses and bars by exact box
# filters (differences of their integrals), periodic patterns by the box filter's sinc
# at their local frequency, and noise octaves faded out as their lattice frequency
# approaches the footprint (the octave's box-filtered mean is 0).


def _hash(ix, iy, seed):
    """A 32-bit integer hash of lattice points -> float in [0, 1)."""
    h = (ix.astype(jnp.uint32) * jnp.uint32(0x8DA6B343)
         ^ iy.astype(jnp.uint32) * jnp.uint32(0xD8163841)
         ^ (seed.astype(jnp.uint32) + jnp.uint32(1)) * jnp.uint32(0xCB1AB31F))
    h = h ^ (h >> 15)
    h = h * jnp.uint32(0x2C1B3C6D)
    h = h ^ (h >> 12)
    h = h * jnp.uint32(0x297A2D39)
    h = h ^ (h >> 15)
    return (h >> 8).astype(jnp.float32) / jnp.float32(1 << 24)


def _value_noise(u, v, seed):
    """Value noise in [-1, 1] on the unit lattice, quintic interpolation."""
    fu, fv = jnp.floor(u), jnp.floor(v)
    tu, tv = u - fu, v - fv
    su = tu * tu * tu * (tu * (tu * 6 - 15) + 10)
    sv = tv * tv * tv * (tv * (tv * 6 - 15) + 10)
    iu, iv = fu.astype(jnp.int32), fv.astype(jnp.int32)
    n00, n10 = _hash(iu, iv, seed), _hash(iu + 1, iv, seed)
    n01, n11 = _hash(iu, iv + 1, seed), _hash(iu + 1, iv + 1, seed)
    n = (n00 * (1 - su) + n10 * su) * (1 - sv) + (n01 * (1 - su) + n11 * su) * sv
    return 2.0 * n - 1.0


def _fade(freq_width):
    """Weight of a band of frequency ``freq`` under a footprint ``width``: 1 while the
    band is resolved, 0 once a footprint spans most of its period."""
    x = jnp.clip((freq_width - 0.25) / 0.5, 0.0, 1.0)
    return 1.0 - x * x * (3 - 2 * x)


def fbm(u, v, width, seed, octaves=6, aniso=1.0):
    """Fractal value noise (``octaves`` doublings); ``aniso`` > 1 stretches it along u
    (brushed metal, wood grain). Footprint along the finer axis decides the fade."""
    total = jnp.zeros_like(u)
    amp, freq, norm = 0.5, 1.0, 0.0
    for o in range(octaves):
        w = _fade(freq * width * aniso)
        total = total + amp * w * _value_noise(u * freq, v * freq * aniso, seed + o)
        norm += amp
        amp, freq = amp * 0.55, freq * 2.0
    return jnp.clip(0.5 + 0.9 * total / norm, 0.0, 1.0)


def _pulse_integral(u, m):
    """Integral over [0, u] of the period-1 pulse train that is 1 on [0, m)."""
    return jnp.floor(u) * m + jnp.clip(u - jnp.floor(u), 0.0, m)


def pulse_box(u, m, width):
    """The pulse train (1 on [k, k+m)) box-filtered over [u - w/2, u + w/2], in [0, 1]."""
    w = jnp.maximum(width, _EPS)
    return (_pulse_integral(u + w / 2, m) - _pulse_integral(u - w / 2, m)) / w


def bricks(u, v, width, seed, mortar=0.06):
    """Running-bond bricks 1 x 0.5 periods with thin dark mortar lines; each brick's
    shade varies by its own hash."""
    row = jnp.floor(2 * v)
    uu = u + 0.5 * jnp.mod(row, 2.0)
    horiz = pulse_box(2 * v - mortar, mortar * 2, 2 * width)          # rows 0.5 high
    vert = pulse_box(uu - mortar / 2, mortar, width)
    line = 1.0 - (1.0 - horiz) * (1.0 - vert)
    shade = 0.65 + 0.35 * _hash(jnp.floor(uu).astype(jnp.int32), row.astype(jnp.int32), seed)
    # a brick's shade varies per brick: fade it to its mean once bricks are sub-footprint
    shade = 0.825 + (shade - 0.825) * _fade(width)
    return (1.0 - line) * shade + line * 0.08


def tiles(u, v, width, seed, mortar=0.04):
    """Square tiles with thin light grout on both axes, per-tile shade."""
    g = 1.0 - (1.0 - pulse_box(u - mortar / 2, mortar, width)) * (
        1.0 - pulse_box(v - mortar / 2, mortar, width))
    shade = 0.3 + 0.6 * _hash(jnp.floor(u).astype(jnp.int32), jnp.floor(v).astype(jnp.int32),
                              seed)
    shade = 0.6 + (shade - 0.6) * _fade(width)
    return (1.0 - g) * shade + g * 0.95


# Glyph strokes on a 3 x 5 grid inside a cell (x0, y0, x1, y1 in cell units): the
# segments of a 14-segment-like display, thin bars that alias like small text.
_STROKES = ((0.15, 0.10, 0.85, 0.18), (0.15, 0.46, 0.85, 0.54), (0.15, 0.82, 0.85, 0.90),
            (0.15, 0.10, 0.25, 0.54), (0.75, 0.10, 0.85, 0.54), (0.15, 0.46, 0.25, 0.90),
            (0.75, 0.46, 0.85, 0.90), (0.45, 0.10, 0.55, 0.90), (0.15, 0.28, 0.85, 0.34))


def _bar_box(u, a, b, width):
    """Indicator of [a, b) box-filtered over width (one bar, not a train)."""
    w = jnp.maximum(width, _EPS)
    lo, hi = u - w / 2, u + w / 2
    return jnp.clip(jnp.minimum(hi, b) - jnp.maximum(lo, a), 0.0, None) / w


def glyphs(u, v, width, seed):
    """Line-art 'text': a cell per character (1 wide, 1.6 high), strokes chosen per cell
    by a hash; dark ink on a light ground. Bars are exact box filters within a cell;
    past a footprint of about a cell the value fades to the page's mean."""
    cu, cv = jnp.floor(u), jnp.floor(v / 1.6)
    lu, lv = u - cu, v / 1.6 - cv
    ink = jnp.zeros_like(u)
    bits = _hash(cu.astype(jnp.int32), cv.astype(jnp.int32), seed)
    blank = _hash(cu.astype(jnp.int32) + 7, cv.astype(jnp.int32), seed) < 0.15  # spaces
    for k, (x0, y0, x1, y1) in enumerate(_STROKES):
        on = jnp.mod(jnp.floor(bits * (1 << (k + 1))), 2.0)
        ink = jnp.maximum(ink, on * _bar_box(lu, x0, x1, width) * _bar_box(lv, y0, y1, width / 1.6))
    ink = jnp.where(blank, 0.0, ink)
    mean_ink = 0.22
    ink = mean_ink + (ink - mean_ink) * _fade(0.5 * width)
    return 0.92 - 0.85 * ink


def rings(u, v, width, seed, k=5.0):
    """Wood rings: cos(2 pi k r) around a hashed centre, the radius perturbed by noise;
    attenuated by the box filter's sinc at the ring frequency k."""
    r = jnp.sqrt((u - 0.3) ** 2 + (v + 2.0) ** 2) + 0.15 * _value_noise(u * 2.0, v * 0.5, seed)
    base = jnp.cos(2 * jnp.pi * k * r) * jnp.sinc(k * width)
    grain = (fbm(u * 8.0, v * 0.5, width * 8.0, seed + 11, octaves=3) - 0.5)
    return jnp.clip(0.55 + 0.3 * base + 0.3 * grain, 0.0, 1.0)


def marble(u, v, width, seed, k=2.0):
    """Marble veins: sin of u plus turbulence, sharpened; sinc-attenuated at k."""
    turb = fbm(u, v, width, seed, octaves=5) - 0.5
    s = jnp.sin(2 * jnp.pi * (k * u + 2.5 * turb))
    vein = jnp.abs(s) ** 0.35
    att = jnp.sinc(2 * k * width)
    mean = 0.7  # mean of |sin|^0.35
    return jnp.clip(0.15 + 0.85 * (mean + (vein - mean) * att), 0.0, 1.0)


def dots(u, v, width, seed, radius=0.28):
    """Polka dots on a unit grid, a disc of ``radius`` per cell; coverage of the disc
    by the footprint (a linear ramp across the edge), faded to pi r^2 when the disc
    falls under the footprint."""
    du, dv = u - jnp.floor(u) - 0.5, v - jnp.floor(v) - 0.5
    d = jnp.sqrt(du * du + dv * dv)
    w = jnp.maximum(width, _EPS)
    cov = jnp.clip((radius - d) / w + 0.5, 0.0, 1.0)
    mean = jnp.pi * radius * radius
    cov = mean + (cov - mean) * _fade(0.5 * width / radius)
    return 1.0 - 0.85 * cov


SEEDED_FNS = {"fbm": fbm, "fbm_aniso": lambda u, v, w, s: fbm(u, v, w, s, aniso=6.0),
              "bricks": bricks, "tiles": tiles, "glyphs": glyphs, "wood": rings,
              "marble": marble, "dots": dots}
