"""Which engine casts the rays of mesh scenes: Embree (``embreex``) against Mitsuba 3,
on the same triangles of a game level, timed in turn in one process.

    bash data/fetch_game_assets.sh
    python experiments/mesh_engine.py --level oa_dm4 --size 256 --spp 16

Per engine: milliseconds to find the nearest hit of every ray of one frame's target
(``size``² pixels x ``spp`` samples, primary rays from one camera of the level's first
video), the median of ``--repeats`` rounds, and the share of rays on which the two
agree (same triangle hit, or both miss). Then jtus's whole mesh frame (target, inputs
at 2x and 4x, shading, motion) at the same size. Mitsuba needs its LLVM variant
(``llvm_ad_rgb``), which needs the system's LLVM library; it is skipped when it does
not load. Writes ``docs/results/mesh-engine/result.{json,md}``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from common import write

from jtus.sim import game
from jtus.sim.mesh import MeshRenderer
from jtus.sim.video import VideoRenderer, subsample_offsets


def _rays(r: MeshRenderer, size, spp):
    st = VideoRenderer(r.scene, (size, size), (4,), spp).timeline("test", 0, 1)[0]
    cam = st.camera
    y, x = np.mgrid[0:size, 0:size].reshape(2, -1).astype(np.float64)
    off = subsample_offsets(spp)
    xy = np.concatenate([np.stack([(x + ox) / size, (y + oy) / size], -1) for ox, oy in off])
    sx, sy = 2 * xy[:, 0:1] - 1, 1 - 2 * xy[:, 1:2]
    d = cam.forward + sx * cam.tan_half[0] * cam.right + sy * cam.tan_half[1] * cam.up
    return np.broadcast_to(cam.eye, d.shape).astype(np.float32), d.astype(np.float32), st


def _mitsuba(part):
    try:
        import mitsuba as mi  # lazy: optional, and its LLVM variant may not load
        mi.set_variant("llvm_ad_rgb")
    except Exception as e:  # noqa: BLE001 - any failure means: not measured here
        return None, f"{type(e).__name__}: {e}"
    mesh = mi.Mesh("level", len(part.position), len(part.faces))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(part.position.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(part.faces.astype(np.uint32).ravel())
    params.update()
    scene = mi.load_dict({"type": "scene", "level": mesh})

    def cast(o, d):
        ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, i]) for i in range(3)]),
                       mi.Vector3f(*[mi.Float(d[:, i]) for i in range(3)]))
        si = scene.ray_intersect_preliminary(ray)
        t = np.array(si.t)
        return np.where(np.isfinite(t), np.array(si.prim_index), -1)
    return cast, f"mitsuba {mi.__version__} llvm_ad_rgb"


def _timed(fn, repeats):
    out, times = None, []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, 1e3 * float(np.median(times))


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--level", default="oa_dm4")
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args()
    sc = game.scene_of(game.PREFIX + args.level, effects=("camera_motion",))
    r = MeshRenderer(sc)
    world = r.parts[0]
    o, d, st = _rays(r, args.size, args.spp)
    bvh = r.bvh[0]
    emb, t_emb = _timed(lambda: bvh.run(o, d, output=1)["primID"], args.repeats)
    rows = [{"engine": "embree (embreex)", "ms": t_emb, "agree": 1.0}]
    cast, label = _mitsuba(world)
    if cast is not None:
        cast(o[:1024], d[:1024])  # compile its kernels first
        mit, t_mit = _timed(lambda: cast(o, d), args.repeats)
        rows.append({"engine": label, "ms": t_mit, "agree": float(np.mean(mit == emb))})
    else:
        rows.append({"engine": "mitsuba (not measured)", "ms": None, "agree": None,
                     "why": label})
    vr = VideoRenderer(sc, (args.size, args.size), (2, 4), args.spp)
    _, t_frame = _timed(lambda: (vr.target(st), vr.input(st, 2, (0.5, 0.5)),
                                 vr.input(st, 4, (0.5, 0.5))), max(1, args.repeats // 2))
    rays = len(o)
    md = [f"Level `{args.level}` (world part, {len(world.faces)} triangles), {args.size}² x "
          f"{args.spp} spp = {rays} primary rays of one target frame; median of "
          f"{args.repeats} rounds, one process.", "",
          "| engine | ms per frame's rays | Mrays/s | same hit as Embree |",
          "| --- | --- | --- | --- |"]
    for row in rows:
        ms = row["ms"]
        md.append(f"| {row['engine']} | {'-' if ms is None else f'{ms:.0f}'} | "
                  f"{'-' if ms is None else f'{rays / ms / 1e3:.1f}'} | "
                  f"{'-' if row['agree'] is None else format(row['agree'], '.4f')} |")
    md += ["", f"jtus's whole mesh frame at {args.size}² (target at {args.spp} spp, inputs at "
               f"2x and 4x, shading, motion; no optional effect): {t_frame:.0f} ms."]
    write("mesh-engine", "\n".join(md), {"args": vars(args), "rays": rays, "rows": rows,
                                         "frame_ms": t_frame})


if __name__ == "__main__":
    main()
