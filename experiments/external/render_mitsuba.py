"""An independent-renderer test set: clips rendered by Mitsuba 3, brought into jtus only
through ``python -m jtus.data import-exr``, as a user's renders would be.

    pip install mitsuba          # its CPU backend needs LLVM's shared library, 16 or
                                 # newer (Debian 12: apt install libllvm19; 14 and 15
                                 # fail with "Cannot select: fmaximum")
    python experiments/external/render_mitsuba.py --out data/external

Nothing here imports jtus: the scenes, the cameras, the textures (numpy bitmaps), the
shading (Mitsuba's ``direct`` integrator with delta lights) and the motion vectors
(numpy projections of Mitsuba's hit positions) are this file's own or Mitsuba's.
Per clip (32 frames): 256x256 targets at 64 samples per pixel (Mitsuba's film, box
filter), and at 2x and 4x one sample per LR pixel at the frame's Halton(2,3) jitter,
with view depth and exact backward motion vectors in LR pixels. Written as EXR with a
JSON sidecar per input folder, then imported with

    python -m jtus.data import-exr --input CLIP/x4 --target CLIP/target --factor 4 \\
        --sidecar CLIP/x4/sidecar.json --out data/external/CLIP-x4.h5 --name CLIP

The clips: ``library`` (text-like glyphs, bricks, a held camera for 14 frames, a light
moving across: shading that motion vectors cannot explain), ``fence`` (wires and thin
posts, a fast sideways camera, a box crossing in front: disocclusion), ``turntable``
(a spinning textured cube and a bobbing sphere on a checker floor, an orbiting camera,
a flickering light). They are held out: never trained on, never used to choose
anything but the final comparison (docs/data.md).

Run ``experiments/external_conventions.py`` afterwards: it verifies, through the
imported datasets, that the vectors warp the previous target onto the current one
better than no warp and than the negated vectors, and that each input matches the
target sampled at its stated jitter.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

SIZE = 256
FRAMES = 32
SPP = 64
NEAR, FAR = 0.05, 200.0
FOV = 50.0  # degrees, horizontal (square film)
SKY = np.array([0.55, 0.65, 0.8], np.float32)


# ---------------------------------------------------------------- textures (numpy)


def glyph_texture(n=1024, seed=0):
    """Dark strokes on paper: rows of random 5x7-cell glyphs, 1-3 texels thick."""
    rng = np.random.default_rng(seed)
    img = np.ones((n, n), np.float32) * 0.9
    cw, ch = 12, 18
    for y0 in range(8, n - ch, ch + 6):
        x0 = 8
        while x0 < n - cw:
            if rng.uniform() < 0.15:
                x0 += cw
                continue
            for _ in range(rng.integers(2, 5)):
                if rng.uniform() < 0.5:
                    yy = y0 + rng.integers(0, ch)
                    img[yy:yy + rng.integers(1, 3), x0:x0 + cw - 3] = 0.08
                else:
                    xx = x0 + rng.integers(0, cw - 3)
                    img[y0:y0 + ch, xx:xx + rng.integers(1, 3)] = 0.08
            x0 += cw + 2
    return np.repeat(img[..., None], 3, -1) * np.array([1.0, 0.97, 0.9], np.float32)


def brick_texture(n=1024, rows=16, seed=1):
    rng = np.random.default_rng(seed)
    img = np.zeros((n, n, 3), np.float32)
    bh = n // rows
    bw = 2 * bh
    for r in range(rows):
        off = (bw // 2) * (r % 2)
        for c in range(-1, n // bw + 1):
            x0 = c * bw + off
            col = np.array([0.55, 0.25, 0.18]) * rng.uniform(0.7, 1.2)
            img[r * bh:(r + 1) * bh, max(x0, 0):max(min(x0 + bw, n), 0)] = col
    mortar = np.zeros((n, n), bool)
    mortar[np.arange(n) % bh < 3, :] = True
    for r in range(rows):
        off = (bw // 2) * (r % 2)
        for c in range(0, n + bw, bw):
            x = (c + off) % n
            mortar[r * bh:(r + 1) * bh, x:x + 3] = True
    img[mortar] = 0.8
    return img


def checker_texture(n=512, cells=32):
    i, j = np.mgrid[0:n, 0:n] // (n // cells)
    v = ((i + j) % 2).astype(np.float32)
    return np.stack([0.15 + 0.7 * v, 0.15 + 0.6 * v, 0.2 + 0.5 * v], -1)


def noise_texture(n=512, seed=2):
    rng = np.random.default_rng(seed)
    out = np.zeros((n, n), np.float32)
    for o in range(6):
        k = 4 * 2 ** o
        g = rng.uniform(size=(k, k))
        up = np.kron(g, np.ones((n // k, n // k)))
        out += up * 0.5 ** o
    out = (out - out.min()) / (out.max() - out.min())
    return np.stack([0.3 + 0.5 * out, 0.4 + 0.4 * out, 0.2 + 0.3 * out], -1).astype(np.float32)


# ---------------------------------------------------------------- cameras and transforms


def look_at(origin, target, up=(0.0, 1.0, 0.0)):
    f = np.asarray(target, float) - origin
    f /= np.linalg.norm(f)
    right = np.cross(f, up)
    right /= np.linalg.norm(right)
    u = np.cross(right, f)
    return {"origin": np.asarray(origin, float), "forward": f, "right": right, "up": u,
            "target": np.asarray(target, float)}


def project(cam, p):
    """World points [N,3] -> film positions [N,2] in [0,1]^2 (x right, y down) and view
    depth [N]."""
    q = p - cam["origin"]
    z = q @ cam["forward"]
    t = np.tan(np.radians(FOV) / 2)
    x = (q @ cam["right"]) / (z * t)
    y = (q @ cam["up"]) / (z * t)
    return np.stack([0.5 + 0.5 * x, 0.5 - 0.5 * y], -1), z


def project_direction(cam, d):
    z = d @ cam["forward"]
    t = np.tan(np.radians(FOV) / 2)
    z = np.where(np.abs(z) < 1e-9, 1e-9, z)
    return np.stack([0.5 + 0.5 * (d @ cam["right"]) / (z * t),
                     0.5 - 0.5 * (d @ cam["up"]) / (z * t)], -1)


def affine(translate=(0, 0, 0), yaw=0.0, scale=(1, 1, 1)):
    c, s = np.cos(yaw), np.sin(yaw)
    m = np.eye(4)
    m[:3, :3] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ np.diag(scale)
    m[:3, 3] = translate
    return m


# ---------------------------------------------------------------- clips


def clip_library(t):
    """Glyph wall and brick floor; camera holds for frames 10-23; a point light sweeps."""
    u = np.clip(t, 0, 9) + np.clip(t - 23, 0, None)       # phase: still from 10 to 23
    cam = look_at((-1.2 + 0.06 * u, 1.4, 3.2 - 0.03 * u), (0.2 + 0.05 * u, 1.1, 0.0))
    shapes = {
        "wall": ("rectangle", affine((0, 1.5, -0.5), 0, (2.5, 1.5, 1)), "glyphs", 1.0),
        "floor": ("floor", affine((0, 0, 0), 0, (4, 1, 4)), "bricks", 4.0),
        "post": ("cube", affine((1.1, 0.6, 0.6), 0.4, (0.12, 0.6, 0.12)), "noise", 1.0),
    }
    a = -0.9 + 0.06 * t  # the sun swings across: shading the vectors cannot explain
    light = {"dir": (np.sin(a), -1.0, -0.6 * np.cos(a)), "irradiance": 2.2}
    return cam, shapes, light


def clip_fence(t):
    """Thin posts and wires, fast strafing camera, a box crossing in front."""
    cam = look_at((-1.5 + 0.12 * t, 1.0, 4.0), (-1.5 + 0.12 * t + 0.3, 0.8, 0.0))
    shapes = {"floor": ("floor", affine((0, 0, 0), 0, (8, 1, 8)), "checker", 6.0),
              "back": ("rectangle", affine((0, 1.5, -2.0), 0, (8, 1.5, 1)), "noise", 2.0),
              "mover": ("cube", affine((2.5 - 0.25 * t, 0.35, 1.8), 0.3 * t, (0.35, 0.35, 0.35)),
                        "bricks", 1.0)}
    for i in range(14):
        shapes[f"postL{i}"] = ("cylinder", ((-2.0 + 0.4 * i, 0.0, 0.5), (-2.0 + 0.4 * i, 1.4, 0.5),
                                            0.012 + 0.004 * (i % 3)), "white", 1.0)
    for k in range(3):
        shapes[f"wire{k}"] = ("cylinder", ((-2.2, 0.5 + 0.35 * k, 0.5), (3.4, 0.5 + 0.35 * k, 0.5),
                                           0.006), "white", 1.0)
    light = {"dir": (-0.3, -1.0, -0.7), "irradiance": 2.2}
    return cam, shapes, light


def clip_turntable(t):
    """Spinning textured cube, bobbing sphere, orbiting camera, flickering light."""
    a = 0.05 * t
    cam = look_at((3.2 * np.sin(a), 1.6, 3.2 * np.cos(a)), (0.0, 0.5, 0.0))
    shapes = {"floor": ("floor", affine((0, 0, 0), 0, (5, 1, 5)), "checker", 10.0),
              "cube": ("cube", affine((-0.5, 0.5, 0), 0.12 * t, (0.45, 0.45, 0.45)), "glyphs", 1.0),
              "ball": ("sphere", affine((0.8, 0.45 + 0.25 * np.sin(0.4 * t), 0.3), 0, (0.35,) * 3),
                       "noise", 1.0)}
    light = {"dir": (-0.4, -1.0, -0.5), "irradiance": 2.2 * (0.6 + 0.4 * (np.sin(1.3 * t) > 0))}
    return cam, shapes, light


def clip_hold(t):
    """Glyph wall, brick floor, thin posts: the camera glides for 16 frames, then nothing
    moves but the jitter (frames 16-79, four cycles of the 16-position jitter): the
    convergence test of a temporal upsampler."""
    u = min(t, 15)
    cam = look_at((-0.9 + 0.05 * u, 1.3, 3.0 - 0.02 * u), (0.1 + 0.03 * u, 1.1, 0.0))
    shapes = {
        "wall": ("rectangle", affine((0, 1.5, -0.5), 0, (2.5, 1.5, 1)), "glyphs", 1.5),
        "floor": ("floor", affine((0, 0, 0), 0, (4, 1, 4)), "bricks", 4.0),
        "box": ("cube", affine((-0.8, 0.3, 0.4), 0.6, (0.3, 0.3, 0.3)), "noise", 1.0),
    }
    for i in range(6):
        shapes[f"post{i}"] = ("cylinder", ((0.2 + 0.25 * i, 0.0, 0.8), (0.2 + 0.25 * i, 1.2, 0.8),
                                           0.008 + 0.003 * (i % 2)), "white", 1.0)
    light = {"dir": (-0.5, -1.0, -0.6), "irradiance": 2.2}
    return cam, shapes, light


CLIPS = {"library": clip_library, "fence": clip_fence, "turntable": clip_turntable}
# a clip kept apart from the three above (its own --out): the static hold of
# experiments/static_hold.py, 80 frames of which the last 64 hold still
HOLD_CLIPS = {"hold": clip_hold}
ALL_CLIPS = {**CLIPS, **HOLD_CLIPS}
HOLD_FRAMES = 80


# ---------------------------------------------------------------- Mitsuba


def _texture(mi, name, cache):
    if name not in cache:
        img = {"glyphs": glyph_texture, "bricks": brick_texture, "checker": checker_texture,
               "noise": noise_texture}.get(name)
        if img is None:  # white
            cache[name] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.85] * 3}}
        else:
            cache[name] = img()
    return cache[name]


def _bsdf(mi, tex, repeat, cache):
    t = _texture(mi, tex, cache)
    if isinstance(t, dict):
        return t
    return {"type": "diffuse", "reflectance": {
        "type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(t)), "raw": True,
        "filter_type": "bilinear", "to_uv": mi.ScalarTransform4f().scale([repeat, repeat, 1])}}


def build_scene(mi, cam, shapes, light, cache, spp=SPP, size=SIZE):
    T = mi.ScalarTransform4f
    d = {"type": "scene",
         "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
         "sensor": {"type": "perspective", "fov": FOV, "fov_axis": "x",
                    "near_clip": NEAR, "far_clip": FAR,
                    "to_world": T().look_at(origin=cam["origin"].tolist(),
                                            target=cam["target"].tolist(), up=[0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": size, "height": size,
                             "rfilter": {"type": "box"}, "pixel_format": "rgba"},
                    "sampler": {"type": "stratified", "sample_count": spp}},
         # one delta emitter: its direct lighting needs no random choice, so a 1-spp
         # input is exact (with two emitters the integrator would pick one at random)
         "sun": {"type": "directional", "direction": list(map(float, light["dir"])),
                 "irradiance": {"type": "rgb", "value": [light["irradiance"]] * 3}}}
    for name, (kind, m, tex, rep) in shapes.items():
        bsdf = _bsdf(mi, tex, rep, cache)
        if kind == "cylinder":
            p0, p1, r = m
            d[name] = {"type": "cylinder", "p0": list(p0), "p1": list(p1), "radius": r,
                       "bsdf": bsdf}
            continue
        if kind == "floor":  # a rectangle in the xz-plane facing up
            m = m @ np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])
            kind = "rectangle"
        d[name] = {"type": kind, "to_world": T(m.tolist()), "bsdf": bsdf}
    return mi.load_dict(d)


def _rigid(shapes, name):
    kind, m, _, _ = shapes[name]
    return None if kind == "cylinder" else m


def render_frame(mi, clip, t, jitters, cache):
    """The target and, per factor, the jittered 1-spp input with depth and motion."""
    cam, shapes, light = ALL_CLIPS[clip](t)
    pcam, pshapes, _ = ALL_CLIPS[clip](t - 1)
    scene = build_scene(mi, cam, shapes, light, cache)
    # the sky is no emitter (see build_scene): it is composited where rays miss, in the
    # target by the film's coverage (alpha: the box-filtered fraction of hits)
    img = np.asarray(mi.render(scene, spp=SPP), np.float32)
    target = img[..., :3] + SKY * (1.0 - img[..., 3:4])
    sensor = scene.sensors()[0]
    integrator = scene.integrator()
    aov = mi.load_dict({"type": "aov", "aovs": "pp:position"})
    out = {"target": target}
    for f, jit in jitters.items():
        n = SIZE // f
        jj, ii = np.meshgrid(np.arange(n), np.arange(n))
        fx = ((jj + jit[0]) / n).ravel()
        fy = ((ii + jit[1]) / n).ravel()
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(t, n * n)
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(fx, fy), mi.Point2f(0.5, 0.5))
        spec, _, _ = integrator.sample(scene, sampler, ray)
        col = np.stack([np.asarray(spec.x), np.asarray(spec.y), np.asarray(spec.z)], -1)
        _, _, aovs = aov.sample(scene, sampler, ray)
        pos = np.stack([np.asarray(aovs[i]) for i in range(3)], -1)
        si = scene.ray_intersect(ray)
        hit = np.asarray(si.is_valid()).astype(bool)
        # which shape each ray hit, by comparing the hit's shape pointer with each shape
        # of the scene. Not the `shape_index` AOV: that is the shape's slot in Dr.Jit's
        # instance registry (creation order, reused across scenes), not its index in
        # scene.shapes(); Mitsuba 3.9.1 numbers them differently, which carried hit
        # points back through another object's motion.
        owner = [(s, np.asarray(si.shape == mi.ShapePtr(s)).astype(bool) & hit)
                 for s in scene.shapes()]
        bad = 0  # hit points outside their own shape's bounding box (must be none)
        for s, sel in owner:
            lo, hi = (np.array([v.x, v.y, v.z]) for v in (s.bbox().min, s.bbox().max))
            bad += int((~((pos[sel] >= lo - 1e-3) & (pos[sel] <= hi + 1e-3)).all(-1)).sum())
        col = np.where(hit[:, None], col, SKY)
        ray_d = np.stack([np.asarray(ray.d.x), np.asarray(ray.d.y), np.asarray(ray.d.z)], -1)
        # backward motion: each hit point carried back through its object's previous pose
        prev_p = pos.copy()
        for s, sel in owner:
            m, pm = _rigid(shapes, s.id()), _rigid(pshapes, s.id())
            if m is None or np.allclose(m, pm):
                continue
            ph = np.concatenate([pos[sel], np.ones((sel.sum(), 1))], -1)
            prev_p[sel] = (ph @ (pm @ np.linalg.inv(m)).T)[:, :3]
        prev_xy, _ = project(pcam, np.where(hit[:, None], prev_p, 0.0))
        prev_xy = np.where(hit[:, None], prev_xy, project_direction(pcam, ray_d))
        cur_xy = np.stack([fx, fy], -1)
        motion = (prev_xy - cur_xy) * n  # LR pixels
        _, z = project(cam, np.where(hit[:, None], pos, cam["origin"] + cam["forward"]))
        z = np.where(hit, z, FAR)
        out[f] = {"color": col.reshape(n, n, 3).astype(np.float32),
                  "depth": z.reshape(n, n).astype(np.float32),
                  "motion": motion.reshape(n, n, 2).astype(np.float32),
                  "check_xy": np.abs(project(cam, pos[hit])[0] - cur_xy[hit]).max()
                  if hit.any() else 0.0,
                  "check_owner": bad}
    return out


def halton(n, base):
    out = np.zeros(n)
    for i in range(n):
        k, f, r = i + 1, 1.0, 0.0
        while k:
            f /= base
            r += f * (k % base)
            k //= base
        out[i] = r
    return out


def write_exr(path, channels):
    import OpenEXR
    chans = {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION,
                       "type": OpenEXR.scanlineimage}, chans) as fh:
        fh.write(path)


def render_clip(mi, clip, out, frames=FRAMES):
    jit = np.stack([halton(16, 2), halton(16, 3)], -1)
    seq = [jit[t % 16] for t in range(frames)]
    cache = {}
    worst = 0.0
    for t in range(frames):
        r = render_frame(mi, clip, t, {2: seq[t], 4: seq[t]}, cache)
        for f in (2, 4):
            if r[f]["check_owner"]:
                raise SystemExit(f"{clip} frame {t} at {f}x: {r[f]['check_owner']} hit points "
                                 "lie outside the bounding box of the shape they were "
                                 "assigned to; their motion vectors would be wrong")
        os.makedirs(os.path.join(out, clip, "target"), exist_ok=True)
        write_exr(os.path.join(out, clip, "target", f"frame{t:04d}.exr"),
                  {c: r["target"][..., i] for i, c in enumerate("RGB")})
        for f in (2, 4):
            d = os.path.join(out, clip, f"x{f}")
            os.makedirs(d, exist_ok=True)
            x = r[f]
            worst = max(worst, float(x["check_xy"]))
            write_exr(os.path.join(d, f"frame{t:04d}.exr"),
                      {"R": x["color"][..., 0], "G": x["color"][..., 1], "B": x["color"][..., 2],
                       "Z": x["depth"], "motion.X": x["motion"][..., 0],
                       "motion.Y": x["motion"][..., 1]})
        print(f"{clip} frame {t + 1}/{frames}", end="\r", file=sys.stderr, flush=True)
    for f in (2, 4):
        with open(os.path.join(out, clip, f"x{f}", "sidecar.json"), "w") as fh:
            json.dump({"color": ["R", "G", "B"], "depth": "Z", "depth_kind": "view",
                       "near": NEAR, "far": FAR, "motion": ["motion.X", "motion.Y"],
                       "motion_units": "pixels", "jitter": [list(map(float, j)) for j in seq],
                       "jitter_kind": "unit"}, fh, indent=1)
    print(f"{clip}: {frames} frames; the hit points re-project onto their own sample "
          f"positions to {worst:.1e} of the frame (projection check)", file=sys.stderr)
    return worst


def _newest_llvm():
    """Dr.Jit loads the first libLLVM it finds; point it at the newest one."""
    import glob
    import re
    libs = (glob.glob("/usr/lib/x86_64-linux-gnu/libLLVM*.so*")
            + glob.glob("/usr/lib/llvm-*/lib/libLLVM*.so*"))
    ver = lambda p: int((re.findall(r"LLVM[-.]?(?:so\.)?(\d+)", p) or ["0"])[0])  # noqa: E731
    return max(libs, key=ver) if libs else None


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="data/external")
    p.add_argument("--clips", nargs="+", default=list(CLIPS), choices=list(ALL_CLIPS),
                   help="the test clips (default), or hold (experiments/static_hold.py: "
                        "render it into its own --out, e.g. data/external-hold)")
    p.add_argument("--frames", type=int, default=None,
                   help=f"frames per clip (default {FRAMES}; hold: {HOLD_FRAMES})")
    p.add_argument("--no-import", action="store_true")
    args = p.parse_args()
    if "DRJIT_LIBLLVM_PATH" not in os.environ and _newest_llvm():
        os.environ["DRJIT_LIBLLVM_PATH"] = _newest_llvm()
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    t0 = time.perf_counter()
    frames = {c: args.frames or (HOLD_FRAMES if c in HOLD_CLIPS else FRAMES) for c in args.clips}
    for clip in args.clips:
        worst = render_clip(mi, clip, os.path.join(args.out, "exr"), frames[clip])
        if worst > 1e-4:
            raise SystemExit(f"{clip}: the projection used for the motion vectors disagrees "
                             f"with Mitsuba's camera by {worst:.2e} of the frame")
        if args.no_import:
            continue
        for f in (2, 4):
            src = os.path.join(args.out, "exr", clip)
            subprocess.run([sys.executable, "-m", "jtus.data", "import-exr",
                            "--input", os.path.join(src, f"x{f}"),
                            "--target", os.path.join(src, "target"), "--factor", str(f),
                            "--sidecar", os.path.join(src, f"x{f}", "sidecar.json"),
                            "--out", os.path.join(args.out, f"{clip}-x{f}.h5"),
                            "--name", clip, "--force"], check=True)
    # what made these renders. Earlier renders took each hit's shape from the
    # `shape_index` AOV, whose numbering changed between Mitsuba builds (TUS on `fence`
    # at 4x scored 21.86 dB on one render and 21.43 on another; JAU, which reads no
    # vectors, the same to 0.01 dB); the shape pointer comparison above does not depend
    # on it, and the bounding-box check refuses a render where it would go wrong
    import drjit
    with open(os.path.join(args.out, "render.json"), "w") as fh:
        json.dump({"mitsuba": mi.__version__, "drjit": drjit.__version__,
                   "llvm": os.environ.get("DRJIT_LIBLLVM_PATH"), "clips": args.clips,
                   "frames": frames, "seconds": round(time.perf_counter() - t0)}, fh,
                  indent=1)
    print(f"rendered {len(args.clips)} clips in {time.perf_counter() - t0:.0f} s",
          file=sys.stderr)


if __name__ == "__main__":
    main()
