"""Mutation testing of the numerics core with mutmut (issue 18): every module below is
mutated in a scratch copy of the repository (its git-tracked files) and each mutant is
run against that module's focused test selection; the kill rate per module is written
to ``docs/results/mutation/results.md``.

    python tools/mutation.py                          # every module (hours)
    python tools/mutation.py --modules jtus/metrics.py --workdir runs/mutation
    python tools/mutation.py --save-only        # results so far, to commit

A run spans sessions and machines: each module's per-mutant results are copied to
``tools/mutation-results/`` after its run (or by ``--save-only`` while it
runs), and a scratch copy without results starts from that copy.

Two facts about JAX shape the mutmut configuration (docs/testing.md):
- mutmut 3 forks a child per mutant. A child forked from a process whose XLA runtime
  already started its thread pools can deadlock (every mutant then "times out"), so
  the fork server imports nothing (``process_isolation = "forkserver"``,
  ``forkserver_warmup = "none"``) and each child imports JAX itself.
- mutmut switches mutants inside a function by a trampoline that reads an environment
  variable at call time. Under ``jax.jit`` the trampoline runs only when a function is
  traced, so in one process a program compiled before the switch would keep running
  the original. Each mutant runs in its own fresh child, where nothing is traced
  before its mutant is set, so the mutants run compiled; they share one persistent
  compilation cache (``<workdir>/jax-cache``), whose keys are the compiled programs
  themselves: a program the mutant does not change is read back instead of compiled
  again, one it changes has a new key. mutmut's call-recording run ("stats", which
  decides which tests each mutant runs) is op by op (``jax_disable_jit``, set by a hook
  appended to the scratch copy's ``tests/conftest.py``), because a jitted function
  traced once by an earlier test would not record its calls for the later ones.

Mutants shown to be equivalent are listed, with why, in ``EQUIVALENT`` below and are
left out of the rate.
"""

from __future__ import annotations

import argparse
import ast
import collections
import json
import math
import os
import re
import shutil
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# the module -> its focused tests (the ones that check its values)
TESTS = {
    "jtus/metrics.py": ["tests/test_metrics.py"],
    "jtus/losses.py": ["tests/test_losses.py", "tests/test_perceptual.py", "tests/test_hdr.py"],
    # the toy model's tests (seconds) rather than DLCTUS's (a float64 gradient compiles
    # for 35-45 s): the same identities, checked against a loop written in the test
    "jtus/rollout.py": ["tests/test_rollout_toy.py"],
    "jtus/sampling/warp.py": ["tests/test_warp_torch.py", "tests/test_warp_properties.py"],
    "jtus/sampling/upsample.py": ["tests/test_upsample_jitter.py", "tests/test_warp_torch.py"],
    "jtus/sampling/jitter.py": ["tests/test_upsample_jitter.py", "tests/test_conventions.py"],
    "jtus/sampling/color.py": ["tests/test_upsample_jitter.py", "tests/test_hdr.py",
                               "tests/test_comparison_models.py"],
    # with test_rollout.py's formulation and reset tests; its gradient and training
    # tests (10-60 s each, a DLCTUS float64 gradient compile) are left out by SKIP below
    "jtus/models/dlctus.py": ["tests/test_dlctus_torch.py", "tests/test_dlctus.py",
                              "tests/test_rollout.py"],
    "jtus/models/tus.py": ["tests/test_baselines.py"],
    "jtus/models/kpn.py": ["tests/test_comparison_models.py"],
    "jtus/models/nsrr.py": ["tests/test_comparison_models.py"],
    "jtus/models/mlp.py": ["tests/test_comparison_models.py"],
}

# "module.x_function__mutmut_N": why it cannot change behaviour
EQUIVALENT: dict[str, str] = {
    # np.arange of int bounds without dtype=float64 gives int64; the next line divides by
    # SSIM_SIGMA (a float), so the taps are the same float64 values
    "jtus.metrics.x__gaussian_taps__mutmut_4": "arange dtype None: int64 taps, divided "
                                               "by a float next",
    "jtus.metrics.x__gaussian_taps__mutmut_7": "arange without dtype: the same as above",
    # the clipped value is a sum of absolute differences times a positive sensitivity,
    # never below 0, so dropping the lower bound of the clip changes nothing
    "jtus.losses.x_alias_mask__mutmut_1": "clip's lower bound 0 on a value >= 0",
    "jtus.losses.x_alias_mask__mutmut_4": "clip's lower bound 0 on a value >= 0",
    # kpn_loss casts the frame's colour and jitter to float32 before the bilinear JAU,
    # which itself computes in promote_types(dtype, float32) (weights and jitter), so
    # the cast changes no value (tests/test_losses.py checks half-precision frames)
    "jtus.losses.x_kpn_loss__mutmut_27": "astype(None) before JAU, which promotes to float32",
    "jtus.losses.x_kpn_loss__mutmut_28": "astype(None) before JAU, which promotes to float32",
    # integer cell indices (dtype None or left out) plus a float64 (0.5, or a Halton
    # element) give the same float64 values
    "jtus.sampling.jitter.x_thesis_4x4__mutmut_4": "int cells + 0.5: the same float64",
    "jtus.sampling.jitter.x_thesis_4x4__mutmut_6": "int cells + 0.5: the same float64",
    "jtus.sampling.jitter.x_thesis_2x2__mutmut_10": "int cells + float64 Halton: the same",
    "jtus.sampling.jitter.x_thesis_2x2__mutmut_12": "int cells + float64 Halton: the same",
    # halton's start defaults to 1, the value fsr2 passes
    "jtus.sampling.jitter.x_fsr2__mutmut_7": "start=1 left out: halton's default is 1",
    "jtus.sampling.color.x__apply__mutmut_8": "einsum subscripts in upper case: the same sum",
    # JAX clamps a static out-of-range index (it does not raise, unlike numpy): channel
    # 3 of a 3-channel image reads channel 2, the one the original reads
    "jtus.sampling.color.x_rgb_to_ycbcr__mutmut_4": "[..., 3] of 3 channels is [..., 2] "
                                                    "in JAX (clamped)",
    "jtus.sampling.color.x_ycbcr_to_rgb__mutmut_7": "[..., 3] of 3 channels is [..., 2] "
                                                    "in JAX (clamped)",
    "jtus.sampling.upsample.x_zero_upsample__mutmut_22": "cell[:, 1:3] of a [B,2] array is "
                                                         "cell[:, 1:2]",
    # the edge branch (pad_edge) and jnp.pad(mode="edge") give the same array
    "jtus.sampling.upsample.x_neighbourhood__mutmut_10": "'edge' sent to jnp.pad's own edge "
                                                         "mode: the same padding",
    "jtus.sampling.upsample.x_neighbourhood__mutmut_11": "'edge' sent to jnp.pad's own edge "
                                                         "mode: the same padding",
    # bilinear up-sampling through the warp's sampler instead of the dense stencil: the
    # same values to rounding (test_dense_bilinear_equals_sampling: to 1e-12 in float64;
    # the stencil is a faster way to the same function, not another function)
    "jtus.sampling.upsample.x_upsample__mutmut_6": "bilinear through sample(): the same "
                                                   "values to rounding",
    "jtus.sampling.upsample.x_upsample__mutmut_7": "bilinear through sample(): the same "
                                                   "values to rounding",
    "jtus.sampling.upsample.x_jitter_aligned_upsample__mutmut_11": "bilinear through "
                                                                   "sample(): the same values "
                                                                   "to rounding",
    "jtus.sampling.upsample.x_jitter_aligned_upsample__mutmut_10": "bilinear through "
                                                                   "sample(): the same values "
                                                                   "to rounding",
    "jtus.sampling.upsample.x_jitter_aligned_upsample__mutmut_36": "j[:, 1:3] of a [B,2] array "
                                                                   "is j[:, 1:2]",
    # lo is 0 or 1, exact in any float type: with 64-bit types on, a float64 lo makes each
    # weight a product with an exact 0 or 1 (and a sum with an exact 0), and
    # _bilinear_phases casts the weights back to the image's type: the same bits
    "jtus.sampling.upsample.x__phase_weights__mutmut_6": "0/1 mask as float64: the same "
                                                         "weights after the cast back",
    # the HR pixel centres k + 0.5 are exact in float32 (below 2**23), and adding them
    # to float64 motion promotes: the same float64 positions
    "jtus.sampling.upsample.x_reproject_coords__mutmut_15": "float32 pixel centres are "
                                                            "exact: the same positions",
    "jtus.sampling.upsample.x_dilate_motion__mutmut_35": "take_along_axis's axis defaults to "
                                                         "-1 in JAX",
    "jtus.sampling.upsample.x_dilate_motion__mutmut_38": "[..., 1] of a size-1 axis is "
                                                         "[..., 0] in JAX (clamped)",
    "jtus.rollout.x__check__mutmut_10": "check_finite=True left out: validate's default "
                                        "is True",
    # a custom_vjp backward may return None for an input's cotangent: JAX instantiates
    # zeros of that input's tangent type (float0 for the bool flag, the frames' own
    # type), the same as the explicit zeros (checked by editing the source: the
    # cotangent-type test passes with None)
    "jtus.rollout.x__segment_reverse__mutmut_106": "None for the flag's cotangent: JAX "
                                                   "instantiates float0 zeros",
    "jtus.rollout.x__segment_reverse__mutmut_109": "None for the flag's cotangent: JAX "
                                                   "instantiates float0 zeros",
    "jtus.rollout.x__segment_reverse__mutmut_111": "None for the frames' cotangents: JAX "
                                                   "instantiates zeros of their types",
    "jtus.rollout.x__segment_reverse__mutmut_108": "flags[1] for flags[0]: a zero of the "
                                                   "same shape and type",
    # lax.scan's unroll is a schedule (how many steps one loop iteration runs), not a
    # value; remat only changes what a backward pass recomputes, and metrics has none
    "jtus.rollout.x__body__mutmut_11": "checkpoint policy None (save nothing): what a "
                                       "backward recomputes, not a value",
    "jtus.rollout.x__body__mutmut_13": "checkpoint policy left out (None): the same",
    "jtus.rollout.x__segment__mutmut_51": "unroll left out (1): a schedule, the same values",
    "jtus.rollout.x_window_loss__mutmut_1": "remat=True by default: a backward's "
                                            "recomputation, the same gradients",
    "jtus.rollout.x_outputs__mutmut_1": "remat=True by default: changes a backward "
                                        "pass's recomputation, not a value",
    "jtus.rollout.x_outputs__mutmut_2": "unroll=2 by default: a schedule, the same values",
    "jtus.rollout.x_outputs__mutmut_28": "unroll left out (1): a schedule, the same values",
    "jtus.rollout.x_metrics__mutmut_1": "unroll=2 by default: a schedule, the same values",
    "jtus.rollout.x_metrics__mutmut_54": "unroll left out (1): a schedule, the same values",
    "jtus.rollout.x_metrics__mutmut_10": "remat None for False: both falsy",
    "jtus.rollout.x_metrics__mutmut_14": "remat True in a rollout that is never "
                                         "differentiated: the same forward",
    "jtus.rollout.x_tbptt_grads__mutmut_1": "remat=True by default: a schedule, the same "
                                            "gradients",
    "jtus.rollout.x_tbptt_grads__mutmut_11": "remat None for False: both falsy",
    "jtus.rollout.x_tbptt_grads__mutmut_21": "remat left out (False, the default passed)",
    "jtus.rollout.x_tbptt_grads__mutmut_2": "unroll=2 by default: a schedule, the same values",
    "jtus.rollout.x_tbptt_grads__mutmut_22": "unroll left out (1): a schedule, the same values",
    # k1 <= k2 always (tbptt_windows checks it); at k1 == k2 keep_at=k1 keeps the carry
    # after the window's last frame, which is the final carry handed on without keep_at
    "jtus.rollout.x_tbptt_grads__mutmut_24": "keep_at=k1=k2: the window's final carry, "
                                             "as without keep_at",
    "jtus.rollout.x_tbptt_grads__mutmut_25": "keep_at=k1=k2: the window's final carry, "
                                             "as without keep_at",
    # start() reads only the shape and dtype of its template, the same for every frame
    # (and targets[1] of a one-frame sequence is targets[0]: JAX clamps static indices)
    "jtus.rollout.x_metrics__mutmut_59": "targets[1] as the carry's template: same shape "
                                         "and dtype",
    # a custom_vjp's cotangent for a bool input (the reset flag) is float0 whatever the
    # backward returns: JAX replaces it (tests/test_rollout_toy.py checks the types)
    "jtus.rollout.x__zero_cotangent__mutmut_3": "bool zeros for the flag: JAX makes it float0",
    "jtus.rollout.x__zero_cotangent__mutmut_9": "float64 zeros for the flag: JAX makes it "
                                                "float0",
    "jtus.rollout.x__zero_cotangent__mutmut_11": "float64 zeros for the flag: JAX makes it "
                                                 "float0",
    # grid_sample: the image size [w, h] as integers times a float grid is in the grid's
    # float type in JAX (int64 * float32 -> float32), and small integers are exact
    "jtus.sampling.warp.x_grid_sample__mutmut_13": "integer size times the float grid: the "
                                                   "grid's type, exact values",
    "jtus.sampling.warp.x_grid_sample__mutmut_15": "integer size times the float grid: the "
                                                   "grid's type, exact values",
    "jtus.sampling.warp.x__bicubic5__mutmut_23": "i0[..., 2] of a size-2 axis is i0[..., 1] "
                                                 "in JAX (clamped)",
    "jtus.sampling.warp.x__bicubic5__mutmut_24": "t[..., 2] of a size-2 axis is t[..., 1] "
                                                 "in JAX (clamped)",
    "jtus.sampling.warp.x__bicubic9__mutmut_23": "i0[..., 2] of a size-2 axis is i0[..., 1] "
                                                 "in JAX (clamped)",
    "jtus.sampling.warp.x__bicubic9__mutmut_24": "t[..., 2] of a size-2 axis is t[..., 1] "
                                                 "in JAX (clamped)",
    # every caller casts _split's fraction to the image's type; u - floor(u) is exact,
    # and float32 -> float64 -> float32 gives it back
    "jtus.sampling.warp.x__split__mutmut_7": "the fraction in float64 before every caller's "
                                             "cast back: exact",
    "jtus.sampling.warp.x_inside_mask__mutmut_5": "xy[..., 1:3] of a size-2 axis is "
                                                  "xy[..., 1:2]",
    # warp_plan's cast of integer coordinates: jnp.clip against the float bound already
    # makes them floating, and integer coordinates (fractions 0 or 1/2) are exact in any
    # float type; float32 coordinates widened later give the same fractions (|xy| < 2**22)
    "jtus.sampling.warp.x_warp_plan__mutmut_7": "the integer-coordinate cast: exact in "
                                                 "any float type",
    "jtus.sampling.warp.x_warp_plan__mutmut_11": "the integer-coordinate cast: exact in "
                                                 "any float type",
    "jtus.sampling.warp.x_warp_plan__mutmut_12": "the integer-coordinate cast: exact in "
                                                 "any float type",
    "jtus.sampling.warp.x_warp_plan__mutmut_13": "the integer-coordinate cast: exact in "
                                                 "any float type",
    "jtus.sampling.warp.x_warp_plan__mutmut_14": "the integer-coordinate cast: exact in "
                                                 "any float type",
    "jtus.sampling.warp.x_warp_plan__mutmut_6": "issubdtype(None, floating): never cast; the "
                                                "clip makes integer coordinates floating",
    # _bilinear_at is handed x and y as [..., 1]: index 1 of that axis is index 0
    "jtus.sampling.warp.x__bilinear_at__mutmut_15": "iy[..., 1] of a size-1 axis is iy[..., 0] "
                                                    "in JAX (clamped)",
    "jtus.sampling.warp.x__bilinear_at__mutmut_16": "ix[..., 1] of a size-1 axis is ix[..., 0] "
                                                    "in JAX (clamped)",
    "jtus.sampling.warp.x_pixel_grid__mutmut_25": "meshgrid's indexing defaults to 'xy'",
    # pixel_grid: jnp.arange(n) + 0.5 without a dtype is a weakly typed float, which the
    # stack with the other axis (typed) turns into that type; half-integers are exact
    "jtus.sampling.warp.x_pixel_grid__mutmut_4": "one axis's arange untyped: a weakly "
                                                 "typed float that takes the other's type",
    "jtus.sampling.warp.x_pixel_grid__mutmut_6": "one axis's arange untyped: a weakly "
                                                 "typed float that takes the other's type",
    "jtus.sampling.warp.x_pixel_grid__mutmut_11": "one axis's arange untyped: a weakly "
                                                 "typed float that takes the other's type",
    "jtus.sampling.warp.x_pixel_grid__mutmut_13": "one axis's arange untyped: a weakly "
                                                 "typed float that takes the other's type",
    # the nearest, bilinear and 16-tap plans index the [..., 2] corner (x, y): 2 is 1
    "jtus.sampling.warp.x_warp_plan__mutmut_77": "i0[..., 2] of a size-2 axis is i0[..., 1] "
                                                 "in JAX (clamped)",
    "jtus.sampling.warp.x_warp_plan__mutmut_102": "i0[..., 2] of a size-2 axis is i0[..., 1] "
                                                  "in JAX (clamped)",
    "jtus.sampling.warp.x_warp_plan__mutmut_138": "i0[..., 2] of a size-2 axis is i0[..., 1] "
                                                  "in JAX (clamped)",
    "jtus.models.tus.x__scaled_input__mutmut_11": "the tent's read left at sample's default "
                                                  "method, which is bilinear",
    "jtus.models.tus.x__scaled_input__mutmut_15": "u shifted by a whole pixel: the same "
                                                  "distance to the nearest sample (to float32 "
                                                  "rounding of the shifted coordinate)",
    "jtus.models.tus.x__scaled_input__mutmut_16": "u shifted by a whole pixel: as above",
    "jtus.models.tus.x__scaled_input__mutmut_46": "integer offsets: int + float32 is float32, "
                                                  "the same values",
    "jtus.models.tus.x__scaled_input__mutmut_48": "integer offsets: as above",
    "jtus.models.tus.x__scaled_input__mutmut_77": "bilinear at a pixel centre (border "
                                                  "clamped, as nearest) is that pixel exactly",
    "jtus.models.tus.x__beta__mutmut_21": "jitter in float64 (under 64-bit types) only "
                                          "picks the sample's cell: the same cell",
    "jtus.models.tus.x_step__mutmut_5": "depth in float64 (under 64-bit types) is only "
                                        "compared, for dilation: the same nearest sample",
    "jtus.models.tus.x__rectify__mutmut_26": "with_mean None for False: both falsy",
    # Initialization keys. Under JAX's partitionable threefry (its default) split(k, 6)
    # begins with split(k, 5), and a key array indexed past its end is clamped to the
    # last key: both give the same parameters. A key shared by a single layer and a
    # per-phase stack's parent is no shared draw either (the stack draws from that key's
    # children); a key shared by two layers is, and tests/test_comparison_models.py::
    # test_every_layer_draws_its_own_initialization kills it (r = 1 over their prefix).
    **{f"jtus.models.kpn.x_init__mutmut_{n}": why for n, why in (
        (9, "split(key, 6) begins with split(key, 5): the same parameters"),
        (77, "ks[5] of a 5-key array is ks[4] (clamped): the same parameters"),
        (31, "conv1 from the key that is the parent of conv2's per-phase keys: no shared "
             "draw"),
        (56, "conv3's per-phase stack from the hidden layer's key: no shared draw"),
        (64, "hidden from the per-phase kernel stack's parent key: no shared draw"))},
    **{f"jtus.models.nsrr.x_init__mutmut_{n}": why for n, why in (
        (7, "split(key, 5) begins with split(key, 4): the same parameters"),
        (38, "k[4] of a 4-key array is k[3] (clamped): the same parameters"),
        (39, "split(k[3], 11) begins with split(k[3], 10): the same parameters"))},
    "jtus.models.nsrr.x_step__mutmut_32": "the history read left at sample's default "
                                          "method, which is bilinear",
    "jtus.models.nsrr.x_features__mutmut_8": "jitter in float64 (under 64-bit types) only "
                                             "picks the zero-up-sampling cell: the same cell",
    "jtus.models.nsrr.x_reweight_maps__mutmut_21": "last_relu None for False: both falsy",
    "jtus.models.kpn.x_phase_index__mutmut_3": "the jitter table in float64 (under 64-bit "
                                               "types): the same nearest entry",
    "jtus.models.kpn.x_phase_index__mutmut_5": "the jitter table in float64: as above",
    "jtus.models.kpn.x_phase_index__mutmut_10": "the jitter in float64: the same nearest "
                                                "entry",
    "jtus.models.kpn.x_phase_index__mutmut_17": "argmin over axis 1 of a [B,n] array is "
                                                "axis -1",
    "jtus.models.kpn.x__switched_conv__mutmut_4": "concatenate's axis defaults to 0",
    "jtus.models.kpn.x_kernels__mutmut_49": "softmax's axis defaults to -1",
    "jtus.models.kpn.x_step__mutmut_38": "einsum subscripts in upper case: the same sum",
    "jtus.models.kpn.x_step__mutmut_47": "einsum subscripts in upper case: the same sum",
    "jtus.models.kpn.x_prepare__mutmut_3": "jitter uncast before JAU, which casts it to "
                                           "the colour's float32",
    "jtus.models.kpn.x_init_state__mutmut_9": "jitter uncast before JAU, as above",
    # gamma 1 through the formula: sign(r) |r|^1 is r to the bit (checked on 1e5 float32
    # normals); only the derivative in the frame's colour at r = 0 differs, never taken
    "jtus.models.mlp.x__boost__mutmut_1": "gamma 1 through sign(r)|r|^1: r to the bit",
    # the de-jittering read casts the jitter to the colour's type (float32) itself
    "jtus.models.mlp.x_step__mutmut_15": "jitter uncast before JAU, which casts it to the "
                                         "colour's float32",
    # DLCTUS's formulations and convolution backwards give the same values and gradients
    # by design (test_formulations_equal_standard, test_opt2_gradients_equal_standard_
    # float64, test_custom_conv_backward_equals_autodiff): a mutant that swaps one for
    # another changes the speed only
    **{f"jtus.models.dlctus.x__trunk__mutmut_{n}": "the autodiff convolution backward "
       "for the custom one (or back): the same values and gradients" for n in range(2, 7)},
    **{f"jtus.models.dlctus.x__down__mutmut_{n}": "opt2's down-sampling for the "
       "convolution's (or back): the same values" for n in (10, 11, 12)},
    **{f"jtus.models.dlctus.x__output__mutmut_{n}": "opt1's output construction for the "
       "standard one (or back): the same values" for n in (11, 12, 13)},
    "jtus.models.dlctus.x__down__mutmut_22": "conv's default SAME padding is none at "
                                             "kernel 4, stride 4 on sizes divisible by 4 "
                                             "(the pixel shuffle requires them)",
    "jtus.models.dlctus.x__down__mutmut_29": "'valid' for 'VALID': XLA's padding names "
                                             "are read case-insensitively",
    "jtus.models.dlctus.x__down__mutmut_47": "cell[:, 1:3] of a [B,2] array is "
                                             "cell[:, 1:2]",
    "jtus.models.dlctus.x__down__mutmut_81": "pixel_unshuffle by m = 1 is the identity",
    "jtus.models.dlctus.x__down__mutmut_86": "pixel_unshuffle by m = 1 is the identity",
    "jtus.models.dlctus.x__down__mutmut_96": "einsum subscripts in upper case: the same sum",
    **{f"jtus.models.dlctus.x__output__mutmut_{n}": "o[..., 1:3] of the network's 2 "
       "outputs is o[..., 1:2]" for n in (77, 114)},
    "jtus.models.dlctus.x_init__mutmut_8": "split(key, 10) begins with split(key, 9): the "
                                          "same parameters",
    "jtus.models.dlctus.x_init__mutmut_10": "split(key, 13) begins with split(key, 9): the "
                                           "same parameters",
    "jtus.models.dlctus.x__jau__mutmut_17": "jitter_aligned_upsample's method defaults to "
                                           "bilinear",
    # every layer casts its kernel and bias to the activation's dtype itself
    # (layers.conv), so the cast of the whole tree changes no forward value; in bfloat16
    # training the parameter gradients then skip one rounding to bfloat16
    "jtus.models.dlctus.x_network__mutmut_9": "the parameters left in float32: the layers "
                                             "cast them to the activation's dtype",
    "jtus.models.dlctus.x_make__mutmut_2": "bind's step argument is used only without "
                                           "prepare and advance, which make gives",
    "jtus.models.dlctus.x_assemble__mutmut_12": "the history and the zero-up-sampled input "
                                                "both come in the carry dtype",
}

# "module.x_function__mutmut_N": mutants that make the module itself fail to import
# (a default argument ``Config()`` evaluated at import raises). mutmut's child then exits
# with 255 before any test runs, which mutmut reports as a timeout; run by hand, every
# test of the selection errors at collection. Counted as killed, and listed.
BREAKS_IMPORT: dict[str, str] = {
    "jtus.models.mlp.xǁConfigǁ__post_init____mutmut_1": "the jitter check inverted: "
                                                        "Config() raises at import",
    # TUS: Config() (its defaults: colour space "rgb", alpha 1.0) refused, or the checks
    # iterating None
    **{f"jtus.models.tus.x\u01c1Config\u01c1__post_init____mutmut_{n}": why for n, why in (
        (1, "the checks replaced by None: iterating it raises at import"),
        (10, "'rgb' renamed in the allowed colour spaces: Config() raises at import"),
        (11, "'rgb' renamed in the allowed colour spaces: Config() raises at import"),
        (18, "every check inverted: Config() raises at import"),
        (20, "the alpha check inverted: Config() raises at import"),
        (21, "alpha's range emptied (1 < alpha <= 1): Config() raises at import"),
        (23, "alpha 1 refused (alpha < 1): Config() with alpha 1.0 raises at import"))},
    # DLCTUS: a check inverted or its allowed values changed so that Config() (factor 4,
    # near 0.1, far 100, warp bicubic, formulation opt2, 32 channels, custom backward,
    # float32) is refused
    **{f"jtus.models.dlctus.x\u01c1Config\u01c1__post_init____mutmut_{n}": why for n, why in (
        (1, "the factor check inverted: Config() raises at import"),
        (3, "factor 4 refused (2 or 5): Config() raises at import"),
        (5, "the near/far check inverted: Config() raises at import"),
        (6, "near 0.1 refused (1 < near): Config() raises at import"),
        (10, "the warp check inverted: Config() raises at import"),
        (12, "the formulation check inverted: Config() raises at import"),
        (14, "the channels check inverted: Config() raises at import"),
        (15, "32 channels refused (2 * 4 / 4 = 2): Config() raises at import"),
        (16, "32 channels refused (2 / 4 * 4 = 2): Config() raises at import"),
        (17, "32 channels refused (3 * 4 * 4 = 48): Config() raises at import"),
        (22, "the conv_backward check inverted: Config() raises at import"),
        (24, "compute_dtype(None) raises: Config() raises at import"))},
    # NSRR: Config() (extract (32, 32, 8), 9 U-Net widths) refused
    **{f"jtus.models.nsrr.x\u01c1Config\u01c1__post_init____mutmut_{n}": why for n, why in (
        (1, "extract[+1] (32) checked for 8: Config() raises at import"),
        (2, "extract[-2] (32) checked for 8: Config() raises at import"),
        (3, "the extract check inverted: Config() raises at import"),
        (4, "extract's last width checked for 16: Config() raises at import"),
        (5, "extract's last width checked for 7: Config() raises at import"),
        (9, "the unet check inverted: Config() raises at import"),
        (10, "10 U-Net widths required: Config() raises at import"))},
}

OUT = os.path.join(ROOT, "docs", "results", "mutation", "results.md")


def scratch_copy(dest):
    """The git-tracked files of the repository (no weights history, no data) in ``dest``."""
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True,
                           check=True).stdout.split()
    for f in files:
        if f.startswith(("experiments/checkpoints/", "tools/mutation-results/", "docs/")):
            continue
        os.makedirs(os.path.join(dest, os.path.dirname(f)), exist_ok=True)
        shutil.copy2(os.path.join(ROOT, f), os.path.join(dest, f))


# tests of a selection left out of a module's runs. For the models, short trainings and
# a build of every model, a minute of compiling each: the forward, reset and reference
# tests left in are what check the values a mutant of a model's step changes. For the
# warps, the finite-difference gradient checks (up to 34 s each, to second order): the
# values against PyTorch and the separable read's derivatives against autodiff stay in.
SKIP = {m: "not test_trains_with_decreasing_loss and not test_registry_builds_every_model"
        for m in ("jtus/models/kpn.py", "jtus/models/nsrr.py", "jtus/models/mlp.py")}
SKIP["jtus/sampling/warp.py"] = "not test_check_grads_float64"
SKIP["jtus/models/dlctus.py"] = ("not (hoisted or scan_equals or tbptt or check_grads or "
                                 "reverse_time or custom_conv or video_runs or "
                                 "train_step_traces or remat or opt2_gradients or "
                                 "conv_same_fast)")


# functions of a module left out of its mutation runs: not what a model's step computes
# (FLOP accounting, PyTorch checkpoint conversion, a crop-sampling heuristic), and tested
# by other files than the module's selection. Their mutants are neither run nor counted.
OUT_OF_SCOPE = {
    "jtus/models/dlctus.py": ("cost", "_torch_names", "_to_numpy", "params_from_torch",
                              "_torch_shape", "params_to_torch", "load_torch_checkpoint"),
    "jtus/models/tus.py": ("cost",),
    "jtus/models/kpn.py": ("cost",),
    "jtus/models/nsrr.py": ("_conv_flops", "cost"),
    "jtus/models/mlp.py": ("acceptance", "cost"),
}


def in_scope(module, key):
    """Whether the mutant ``key`` (``pkg.mod.x_function__mutmut_N``, or ``xǁClassǁmethod``
    for a method) is of a function in ``module``'s scope."""
    m = re.search(r"\.x_(\w+?)__mutmut_\d+$", key)
    return not (m and m.group(1) in OUT_OF_SCOPE.get(module, ()))


def scope_globs(module):
    """mutmut name patterns of the functions in ``module``'s scope (``[]``: all of them)."""
    if module not in OUT_OF_SCOPE:
        return []
    tree = ast.parse(open(os.path.join(ROOT, module)).read())
    dotted = module.removesuffix(".py").replace("/", ".")
    globs = []
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and node.name not in OUT_OF_SCOPE[module]:
            globs.append(f"{dotted}.x_{node.name}__mutmut_*")
        elif isinstance(node, ast.ClassDef) and any(
                isinstance(b, ast.FunctionDef) for b in node.body):
            globs.append(f"{dotted}.x\u01c1{node.name}\u01c1*")
    return globs


def config_block(module, tests):
    q = lambda xs: "[" + ", ".join(f'"{x}"' for x in xs) + "]"  # noqa: E731
    args = ["-n", "0", "-p", "no:cacheprovider", "-q"]
    if module in SKIP:
        args += ["-k", SKIP[module]]
    return (f"\n[tool.mutmut]\npaths_to_mutate = {q([module])}\ntests_dir = {q(tests)}\n"
            f'pytest_add_cli_args = {q(args)}\n'
            f'also_copy = ["tests/", "jtus/"]\ntimeout_constant = 60.0\n'
            f'timeout_multiplier = 5.0\nprocess_isolation = "forkserver"\n'
            f'forkserver_warmup = "none"\n')


SAVED = os.path.join(ROOT, "tools", "mutation-results")

# appended to the scratch copy's tests/conftest.py: mutmut runs its clean, forced-fail
# and call-recording ("stats") test runs in one process, one after another, so the mode
# is set at each session's start, not at import
STATS_OP_BY_OP = """

def pytest_sessionstart(session):  # added by tools/mutation.py
    jax.config.update("jax_disable_jit", os.environ.get("MUTANT_UNDER_TEST") == "stats")
"""


def scratch_dir(module, workdir):
    """The scratch copy of the repository in which ``module``'s mutants run."""
    return os.path.join(workdir, module.replace("/", "_").removesuffix(".py"))


def meta_paths(module, workdir):
    """``(mutmut's result file for module in the scratch copy, its committed copy)``.
    mutmut keeps each mutant's exit code in ``mutants/<module>.meta`` with a hash of every
    function, and on a new run keeps the results of the functions whose hash is the same:
    restoring the file into a fresh scratch copy resumes a run on another machine."""
    dest = scratch_dir(module, workdir)
    return (os.path.join(dest, "mutants", module + ".meta"),
            os.path.join(SAVED, module.replace("/", "_") + ".meta"))


def save_meta(module, workdir):
    live, saved = meta_paths(module, workdir)
    if os.path.exists(live):
        os.makedirs(SAVED, exist_ok=True)
        shutil.copyfile(live, saved + ".tmp")
        os.replace(saved + ".tmp", saved)
        print(f"saved {os.path.relpath(live, ROOT)} -> {os.path.relpath(saved, ROOT)}")


def module_status(module, workdir, env=None):
    """``{mutant: status}`` of ``module``'s scratch copy, as mutmut reports it, for the
    mutants in its scope."""
    res = subprocess.run(["mutmut", "results", "--all", "true"],
                         cwd=scratch_dir(module, workdir), env=env,
                         capture_output=True, text=True, check=True).stdout
    return {k: v for k, v in re.findall(r"^\s+(\S+): (.+)$", res, re.M)
            if in_scope(module, k)}


def effective(status):
    """mutmut's statuses with the ``BREAKS_IMPORT`` mutants' exits counted as kills."""
    return {k: "killed" if k in BREAKS_IMPORT and v == "timeout" else v
            for k, v in status.items()}


def row(module, status, seconds):
    """A results row: ``(module, mutants, run, killed, rate, seconds, survivors)``."""
    status = effective(status)
    counts, tested, killed = summarize(status)
    survivors = sorted(k + (" (timed out)" if v == "timeout" else "")
                       for k, v in status.items()
                       if v in ("survived", "timeout") and k not in EQUIVALENT)
    # rounded down to 0.1%: 202 of 203 is 99.5%, not a rounded-up 100%
    rate = f"{math.floor(1000 * killed / tested) / 10:g}%" if tested else "n/a"
    print(f"{module}: {killed}/{tested} killed ({rate}), {dict(counts)}"
          + (f", {seconds:.0f} s" if seconds is not None else ""))
    return (module, len(status), tested, killed, rate, seconds, survivors)


def run_module(module, workdir, max_children, recheck=False, fresh=False, op_by_op=False):
    dest = scratch_dir(module, workdir)
    scratch_copy(dest)  # the current sources and tests (mutmut re-mutates what changed)
    live, saved = meta_paths(module, workdir)
    if not fresh and not os.path.exists(live) and os.path.exists(saved):
        os.makedirs(os.path.dirname(live), exist_ok=True)
        shutil.copyfile(saved, live)
        print(f"resuming {module} from {os.path.relpath(saved, ROOT)}")
    with open(os.path.join(dest, "pyproject.toml"), "a") as fh:
        fh.write(config_block(module, TESTS[module]))
    with open(os.path.join(dest, "tests", "conftest.py"), "a") as fh:
        fh.write(STATS_OP_BY_OP)
    env = dict(os.environ, JTUS_TEST_JAX_CACHE=os.path.join(workdir, "jax-cache"))
    env.pop("JAX_DISABLE_JIT", None)
    if op_by_op:
        env["JAX_DISABLE_JIT"] = "1"
    os.makedirs(env["JTUS_TEST_JAX_CACHE"], exist_ok=True)

    t0 = time.perf_counter()
    if not recheck:
        subprocess.run(["mutmut", "run", "--max-children", str(max_children),
                        *scope_globs(module)],
                       cwd=dest, env=env, stdout=subprocess.DEVNULL, check=False)  # resumes
    else:  # the survivors (and the mutants not run yet), against the tests as they are now
        # mutmut records which tests call each function only for test names it has not
        # seen: a test that kept its name but now calls more (a new assertion on an error
        # message) would not be run against those functions' mutants. Recording again
        # from scratch keeps the results and costs one op-by-op run of the selection.
        stats = os.path.join(dest, "mutants", "mutmut-stats.json")
        if os.path.exists(stats):
            os.remove(stats)
        survivors = [k for k, v in effective(module_status(module, workdir, env)).items()
                     if v in ("survived", "no tests", "not checked", "timeout")
                     and k not in EQUIVALENT]
        if survivors:
            subprocess.run(["mutmut", "run", "--max-children", str(max_children), *survivors],
                           cwd=dest, env=env, stdout=subprocess.DEVNULL, check=False)
    save_meta(module, workdir)
    return module_status(module, workdir, env), time.perf_counter() - t0


def summarize(status):
    counts = collections.Counter(v for k, v in status.items() if k not in EQUIVALENT)
    tested = sum(n for s, n in counts.items() if s not in ("not checked", "skipped"))
    killed = counts["killed"]  # a timeout is not counted as a kill (see the note below)
    return counts, tested, killed


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--modules", nargs="+", default=list(TESTS), choices=list(TESTS))
    p.add_argument("--workdir", default=os.path.join(ROOT, "runs", "mutation"))
    p.add_argument("--max-children", type=int, default=2)
    p.add_argument("--out", default=OUT)
    p.add_argument("--recheck", action="store_true",
                   help="run only the surviving, timed-out, untested and not yet run mutants "
                        "of earlier runs, against the tests as they are now")
    p.add_argument("--op-by-op", action="store_true",
                   help="run the mutants with JAX_DISABLE_JIT=1 (faster where the tests are "
                        "small and every mutant changes the compiled programs: "
                        "jtus/metrics.py)")
    p.add_argument("--fresh", action="store_true",
                   help="do not start from the committed results (a new workdir then runs "
                        "every mutant)")
    p.add_argument("--save-only", action="store_true",
                   help="copy each module's mutmut results (mutants/<module>.meta) to "
                        "tools/mutation-results/ to commit, and exit")
    args = p.parse_args(argv)
    command = "python tools/mutation.py " + " ".join(
        argv if argv is not None else sys.argv[1:])
    if args.save_only:  # and the results so far of every module with a scratch copy
        rows = []
        for m in args.modules:
            save_meta(m, args.workdir)
            live, _ = meta_paths(m, args.workdir)
            if os.path.exists(live) and shutil.which("mutmut"):
                rows.append(row(m, module_status(m, args.workdir), None))
        write_results(args.out, rows, command)
        return
    if shutil.which("mutmut") is None:
        sys.exit("error: mutmut is not installed (pip install mutmut)")
    rows = []
    for m in args.modules:  # the results file is written after each module
        status, seconds = run_module(m, args.workdir, args.max_children, args.recheck,
                                     args.fresh, args.op_by_op)
        rows.append(row(m, status, seconds))
        write_results(args.out, rows, command)


def write_results(out, rows, command):
    """Merges this invocation's rows into ``out`` (and the JSON beside it): a module run now
    replaces its earlier row, the other modules keep theirs with the command that made them."""
    os.makedirs(os.path.dirname(out), exist_ok=True)
    store = os.path.splitext(out)[0] + ".json"
    table = json.load(open(store)) if os.path.exists(store) else {}
    for m, n, tested, killed, rate, seconds, survivors in rows:
        table[m] = dict(mutants=n, run=tested, killed=killed, rate=rate,
                        seconds=None if seconds is None else round(seconds),
                        survivors=survivors, command=command,
                        date=time.strftime("%Y-%m-%d"))
    tmp = store + ".tmp"
    with open(tmp, "w") as fh:
        json.dump(table, fh, indent=1, sort_keys=True)
    os.replace(tmp, store)
    order = [m for m in TESTS if m in table]
    with open(out, "w") as fh:
        fh.write("# Mutation testing (mutmut)\n\n| module | mutants | run | killed | kill rate "
                 "| seconds | made by (date) |\n| --- | --- | --- | --- | --- | --- | --- |\n")
        for m in order:
            r = table[m]
            secs = "-" if r["seconds"] is None else f"{r['seconds']:,}"
            fh.write(f"| `{m}` | {r['mutants']} | {r['run']} | {r['killed']} | {r['rate']} | "
                     f"{secs} | `{r['command']}` ({r['date']}) |\n")
        fh.write("\nA timed-out mutant is not counted as killed: with JAX a hang can be the "
                 "harness's, not the mutant's. A `--recheck` row's seconds are those of the "
                 "recheck only. A `--save-only` row, without seconds, is the results saved so far: "
                 "mutants not run yet (mutants minus run minus equivalents), survivors not yet "
                 "run again against newer tests. Surviving mutants:\n\n")
        for m in order:
            fh.write(f"- `{m}`: " + (", ".join(f"`{s}`" for s in table[m]["survivors"])
                                     or "none") + "\n")
        fh.write("\nEquivalent mutants left out: " + (", ".join(
            f"`{k}` ({v})" for k, v in EQUIVALENT.items()) or "none") + ".\n")
        fh.write("\nMutants that stop the module from importing, counted as killed (mutmut's "
                 "child exits before any test and mutmut reports a timeout; by hand every "
                 "test errors at collection): " + (", ".join(
                     f"`{k}` ({v})" for k, v in BREAKS_IMPORT.items()) or "none") + ".\n")

if __name__ == "__main__":
    main()
