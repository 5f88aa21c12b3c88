"""Hand-written sampling primitives: warps, up-sampling, jitter, colour spaces."""

from jtus.sampling.color import (display, exposure_scale, inverse_tonemap, rgb_to_ycbcr,
                                 rgb_to_ycocg, srgb_encode, tonemap, ycbcr_to_rgb, ycocg_to_rgb)
from jtus.sampling.jitter import (fsr2, halton, jitter_sequence, thesis_2x2, thesis_4x4,
                                  van_der_corput)
from jtus.sampling.upsample import (dilate_motion, filter_neighbourhood,
                                    jitter_aligned_coords, jitter_aligned_upsample,
                                    jitter_cell, neighbourhood,
                                    neighbourhood_box, pad_edge, pixel_shuffle, pixel_unshuffle,
                                    reproject_coords, reproject_plan, upsample,
                                    zero_upsample)
from jtus.sampling.warp import (CATMULL_ROM_A, METHODS, PYTORCH_A, TAPS, WarpPlan, grid_sample,
                                inside_mask, keys_weights, offset_plan, pixel_grid, sample,
                                warp_plan, warp_read)

__all__ = [
    "CATMULL_ROM_A", "dilate_motion", "display", "exposure_scale", "filter_neighbourhood", "fsr2",
    "grid_sample", "halton",
    "inside_mask", "inverse_tonemap", "jitter_aligned_coords", "jitter_aligned_upsample",
    "jitter_cell", "jitter_sequence", "keys_weights", "METHODS", "neighbourhood",
    "neighbourhood_box", "offset_plan", "pad_edge", "pixel_grid", "pixel_shuffle",
    "pixel_unshuffle", "PYTORCH_A", "reproject_coords", "reproject_plan", "rgb_to_ycbcr",
    "rgb_to_ycocg", "sample", "srgb_encode", "TAPS", "thesis_2x2", "thesis_4x4", "tonemap",
    "upsample", "van_der_corput", "warp_plan", "warp_read", "WarpPlan", "ycbcr_to_rgb",
    "ycocg_to_rgb", "zero_upsample"
]
