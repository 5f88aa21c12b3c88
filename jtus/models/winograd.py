"""3x3 convolutions by Winograd's minimal filtering F(m x m, 3 x 3) (Lavin and Gray,
"Fast Algorithms for Convolutional Neural Networks", 2016), NHWC / HWIO.

The VALID output is cut into m x m tiles. Each tile's (m+2) x (m+2) input window ``d``
is transformed (``B^T d B``), the kernel ``g`` once (``G g G^T``), the (m+2)^2
transformed positions are multiplied as (m+2)^2 matmuls ``[tiles, C] @ [C, O]``, and
each product ``M`` is transformed back to its m x m outputs (``A^T M A``): (m+2)^2 / m^2
multiplies per output and channel pair instead of 9, 4x fewer for m = 4, plus the
transforms, which are passes over memory. The values are the direct convolution's in
exact arithmetic; in float32 F(4x4) differs by about 1e-6 of the largest output (its
transforms' coefficients reach 8), so the training step uses it and bfloat16 does not.

On XLA:CPU it pays where the maps are small but not tiny: DLCTUS's training step ran
1.08-1.12x as fast at crop 128 (32x32 trunk maps, a batch of 2 per device) and 1.06x at
crop 256 with the forward and input-gradient convolutions in this form
(``layers.conv_edge_winograd``), 0.97x on 16x16 maps (its many small operations) and on
128x128 maps (transformed tiles beyond the cache), which ``dlctus.WINOGRAD_PIXELS``
leaves to the direct form; the inference frames' trunk (180x320 and larger) gains too
little to use (``python experiments/trunk_winograd.py``, docs/performance.md). NSRR's
training step (``layers.conv_same_winograd`` on its layers of 32 or more channels to 16
or more, maps up to 2 x 128 x 128) ran 1.03x as fast, NSRR-fast's halved widths no
faster (``python experiments/same_winograd.py``).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

# (B^T, G, A^T) of F(m x m, 3 x 3), m = 2 and 4 (Lavin and Gray 2016, sec. 4)
MATRICES = {
    2: (np.array([[1, 0, -1, 0], [0, 1, 1, 0], [0, -1, 1, 0], [0, 1, 0, -1]]),
        np.array([[1, 0, 0], [1 / 2, 1 / 2, 1 / 2], [1 / 2, -1 / 2, 1 / 2], [0, 0, 1]]),
        np.array([[1, 1, 1, 0], [0, 1, -1, -1]])),
    4: (np.array([[4, 0, -5, 0, 1, 0], [0, -4, -4, 1, 1, 0], [0, 4, -4, -1, 1, 0],
                  [0, -2, -1, 2, 1, 0], [0, 2, -1, -2, 1, 0], [0, 4, 0, -5, 0, 1]]),
        np.array([[1 / 4, 0, 0], [-1 / 6, -1 / 6, -1 / 6], [-1 / 6, 1 / 6, -1 / 6],
                  [1 / 24, 1 / 12, 1 / 6], [1 / 24, -1 / 12, 1 / 6], [0, 0, 1]]),
        np.array([[1, 1, 1, 1, 1, 0], [0, 1, -1, 2, -2, 0], [0, 1, 1, 4, 4, 0],
                  [0, 1, -1, 8, -8, 1]])),
}
TILE = 4  # m of the form the library uses


def _combine(mat, xs):
    """``[sum_r mat[i, r] * xs[r] for each row i]``: zero coefficients skipped,
    coefficients of +-1 as additions and subtractions."""
    out = []
    for row in mat:
        acc = None
        for c, x in zip(row.tolist(), xs):
            if c == 0:
                continue
            t = x if c == 1 else -x if c == -1 else c * x
            acc = t if acc is None else acc + t
        out.append(acc)
    return out


def _check(m):
    if m not in MATRICES:
        raise ValueError(f"m: expected one of {sorted(MATRICES)}, got {m!r}")


def transform_kernel(k, m=TILE):
    """``G k G^T`` of a ``[3,3,C,O]`` kernel, as ``[(m+2)^2, C, O]``."""
    _check(m)
    if k.shape[:2] != (3, 3):
        raise ValueError(f"kernel: expected a [3,3,C,O] kernel, got shape {k.shape}")
    g = jnp.asarray(MATRICES[m][1], k.dtype)
    return jnp.einsum("ai,ijco,bj->abco", g, k, g).reshape(-1, *k.shape[2:])


def tiles_in(xp, m=TILE):
    """The transformed input tiles ``B^T d B`` of the padded ``xp [B,H+2,W+2,C]`` for
    an ``H x W`` VALID output, as ``[(m+2)^2, tiles, C]``; the last row and column of
    tiles may overhang the output (their inputs zero, their outputs cropped)."""
    _check(m)
    bt, a = MATRICES[m][0], m + 2
    n, hp, wp, c = xp.shape
    th, tw = -(-(hp - 2) // m), -(-(wp - 2) // m)
    xp = jnp.pad(xp, ((0, 0), (0, th * m + 2 - hp), (0, tw * m + 2 - wp), (0, 0)))
    v = []
    for t in _combine(bt, [xp[:, r:r + m * th:m] for r in range(a)]):    # B^T d
        v += _combine(bt, [t[:, :, s:s + m * tw:m] for s in range(a)])  # (B^T d) B
    return jnp.stack(v).reshape(a * a, n * th * tw, c)


def tiles_out(mm, shape, m=TILE):
    """``A^T M A`` of the products ``mm [(m+2)^2, tiles, O]``, as the ``[B,H,W,O]`` image
    of ``shape`` (its first three entries)."""
    _check(m)
    at, a = MATRICES[m][2], m + 2
    n, h, w = shape[:3]
    th, tw = -(-h // m), -(-w // m)
    mm = mm.reshape(a, a, n, th, tw, -1)
    y = [_combine(at, [r[j] for j in range(a)]) for r in _combine(at, list(mm))]
    y = jnp.stack([jnp.stack(r, 3) for r in y], 2)                   # [n,th,m,tw,m,O]
    return y.reshape(n, th * m, tw * m, -1)[:, :h, :w]


def conv_valid(xp, u, m=TILE):
    """VALID 3x3 convolution of ``xp [B,H+2,W+2,C]`` with a transformed kernel ``u``
    (``transform_kernel``): ``[B,H,W,O]``."""
    n, hp, wp, _ = xp.shape
    if hp < 3 or wp < 3:
        raise ValueError(f"xp: expected at least 3x3 pixels, got shape {xp.shape}")
    mm = jnp.einsum("ktc,kco->kto", tiles_in(xp, m), u.astype(xp.dtype))
    return tiles_out(mm, (n, hp - 2, wp - 2), m)


def conv3x3_valid(xp, k, m=TILE):
    """VALID 3x3 convolution of ``xp [B,H+2,W+2,C]`` with the ``[3,3,C,O]`` kernel ``k``
    (cross-correlation, as ``lax.conv_general_dilated``)."""
    return conv_valid(xp, transform_kernel(k.astype(xp.dtype), m), m)

