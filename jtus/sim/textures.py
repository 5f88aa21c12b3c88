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
