"""Sub-pixel jitter sequences.

A jitter is the offset of a frame's sample inside its LR pixel, (x, y) in
[0,1)^2 with x right and y down; (0.5, 0.5) is the pixel centre
(``docs/conventions.md``). Sequences are returned as float64 numpy arrays
``[N,2]`` and repeat with period N: frame ``t`` uses ``seq[t % N]``.
"""

from __future__ import annotations

import math

import numpy as np

# The thesis's 4x4 pattern (sec. 4.2.2, Figure 6a) is shown only as a picture;
# this order meets its two stated rules: every one of the 16 HR-pixel centres
# once, and no two consecutive samples (cyclically) in neighbouring cells
# (8-neighbourhood). Found by a depth-first search that prefers far cells.
_ORDER_4X4 = ((0, 0), (3, 3), (3, 0), (0, 3), (1, 1), (3, 1), (2, 3), (2, 0),
              (0, 2), (1, 0), (1, 2), (3, 2), (1, 3), (2, 1), (0, 1), (2, 2))

# The 2x2 pattern visits the four HR pixels of an LR pixel in an hourglass
# order: top-left, top-right, bottom-left, bottom-right (thesis Figure 6b).
_HOURGLASS_2X2 = ((0, 0), (1, 0), (0, 1), (1, 1))


def van_der_corput(n, base):
    """The n-th element (n >= 0) of the base-``base`` Van der Corput sequence (eq. 25)."""
    if n < 0 or base < 2:
        raise ValueError(f"van_der_corput: need n >= 0 and base >= 2, got n={n}, base={base}")
    out, scale = 0.0, 1.0 / base
    while n:
        n, digit = divmod(n, base)
        out += digit * scale
        scale /= base
    return out


def halton(count, start=1, bases=(2, 3)):
    """Halton elements ``start .. start+count-1`` (eq. 26), ``[count,2]``."""
    if count < 1:
        raise ValueError(f"count: expected >= 1, got {count}")
    return np.array([[van_der_corput(i, b) for b in bases] for i in range(start, start + count)])


def thesis_4x4():
    """16 jitters at the centres of the 4x4 HR pixels of an LR pixel (4x up-sampling)."""
    return (np.array(_ORDER_4X4, dtype=np.float64) + 0.5) / 4


def thesis_2x2():
    """16 jitters for 2x up-sampling: Halton(2,3) elements 2-5 inside each HR pixel,
    the HR pixels visited in hourglass order for each element."""
    inner = halton(4, start=2)
    cells = np.array(_HOURGLASS_2X2, dtype=np.float64)
    return np.array([(cell + h) / 2 for h in inner for cell in cells])


def fsr2(factor):
    """FSR2-style Halton(2,3) of length ceil(8 * factor^2), elements 1..N."""
    if factor <= 0:
        raise ValueError(f"factor: expected > 0, got {factor}")
    return halton(math.ceil(8 * factor * factor), start=1)


SEQUENCES = ("thesis", "halton", "fsr2")
# What a video of the randomized data draws from: the thesis's patterns, Halton(2,3)
# of the lengths engines use, and FSR 2's length rule.
VARIETY = ("thesis", "halton8", "halton16", "halton32", "fsr2")


def jitter_sequence(name, factor, length=16):
    """A named sequence for up-sampling factor ``factor``.

    ``thesis``: the thesis's pattern for the factor (4x4 for f=4, 2x2 for f=2);
    ``halton``: Halton(2,3) elements 1..``length``; ``halton<N>``: the same with
    length N; ``fsr2``: see ``fsr2``.
    """
    if name.startswith("halton") and name[6:].isdigit():
        return halton(int(name[6:]))
    if name == "thesis":
        if factor == 4:
            return thesis_4x4()
        if factor == 2:
            return thesis_2x2()
        raise ValueError(f"factor: the thesis patterns exist for 2 and 4, got {factor}")
    if name == "halton":
        return halton(length)
    if name == "fsr2":
        return fsr2(factor)
    raise ValueError(f"name: expected one of {SEQUENCES} or halton<N>, got {name!r}")
