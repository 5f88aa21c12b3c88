"""Game content: OpenArena's Quake III levels as mesh scenes, and where they live.

``data/fetch_game_assets.sh`` downloads Debian's OpenArena data packages (GPL-2+,
``docs/data.md``) and unpacks their ``.pk3`` archives under ``data/game/`` (or
``$JTUS_GAME_ASSETS``); nothing from them is in the repository. A level is named
``oa:<map>`` (``oa:oa_dm1``); ``level_scene`` turns it into a ``MeshScene`` with the
effects asked for, its brush models moving as the level's entities say.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import os
from pathlib import Path

import numpy as np

from jtus.sim import bsp
from jtus.sim.mesh import MESH_EFFECTS, Material, MeshScene, Motion, Part, mip_pyramid
from jtus.sim.mesh import srgb_to_linear

PREFIX = "oa:"
GAME_EFFECTS = MESH_EFFECTS  # what a game level may declare; the preset picks per level
_GREY = np.full((4, 4, 4), (0.5, 0.5, 0.5, 1.0), np.float32)


def assets_dir():
    """Where the unpacked game data is: ``$JTUS_GAME_ASSETS`` or ``data/game``."""
    env = os.environ.get("JTUS_GAME_ASSETS")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "data" / "game"


def pk3_files(root=None):
    root = Path(root) if root else assets_dir()
    return sorted(root.rglob("*.pk3")) if root.is_dir() else []


@functools.lru_cache(maxsize=2)
def archive(root=None):
    files = pk3_files(root)
    if not files:
        raise FileNotFoundError(
            f"game assets: no .pk3 archives under {root or assets_dir()}; run "
            "`bash data/fetch_game_assets.sh` (or set JTUS_GAME_ASSETS)")
    return bsp.Archive(files)


def is_level(name):
    return isinstance(name, str) and name.startswith(PREFIX)


def levels(root=None):
    """The map names the installed archives hold."""
    return [n[5:-4] for n in archive(root).names("maps/", ".bsp")]


def _material(arc: bsp.Archive, name, shaders, cache):
    sh = shaders.get(name)
    stage = sh.stages[0] if sh and sh.stages else bsp.Stage(image=name)
    key = (stage.image or name).lower()
    if key not in cache:
        img = arc.image(stage.image) if stage.image else None
        if img is None:
            img = arc.image(name)
        if img is None:
            cache[key] = mip_pyramid(_GREY)
        else:
            x = img.astype(np.float32) / 255.0
            x[..., :3] = srgb_to_linear(x[..., :3])
            cache[key] = mip_pyramid(x)
    return Material(cache[key], blend=stage.blend, alpha_test=stage.alpha_test,
                    scroll=stage.scroll, wave=stage.wave,
                    lit=sh.lightmapped if sh else True, name=name)


def _motion(m, center):
    """A brush model's ``Motion`` from its entity keys (Quake's defaults where absent)."""
    cls = m["class"]
    num = lambda k, d: float(m.get(k, d))  # noqa: E731
    flags = int(float(m.get("spawnflags", 0)))
    size = np.abs(m["maxs"] - m["mins"])
    pivot = bsp.to_jtus([float(x) for x in m["origin"].split()]) if "origin" in m else center
    if cls == "func_rotating":
        axis = (1, 0, 0) if flags & 4 else (0, 1, 0) if flags & 8 else (0, 0, 1)
        return Motion("rotate", tuple(bsp.to_jtus(axis) / bsp.UNIT),
                      period=360.0 / max(abs(num("speed", 100)), 1.0), pivot=tuple(pivot))
    if cls == "func_bobbing":
        axis = (1, 0, 0) if flags & 1 else (0, 1, 0) if flags & 2 else (0, 0, 1)
        return Motion("bob", tuple(bsp.to_jtus(axis) / bsp.UNIT),
                      amount=num("height", 32) * bsp.UNIT, period=max(num("speed", 4), 0.5))
    if cls == "func_pendulum":
        return Motion("swing", tuple(bsp.to_jtus((1, 0, 0)) / bsp.UNIT),
                      amount=np.radians(num("speed", 30)), period=2.5, pivot=tuple(pivot))
    if cls == "func_plat":
        h = num("height", 0) * bsp.UNIT or max(size[1] - 8 * bsp.UNIT, 0.1)
        return Motion("slide", (0.0, -1.0, 0.0), amount=h, period=6.0)
    angle = num("angle", 0)  # func_door
    if angle == -1:
        axis = np.array([0.0, 1.0, 0.0])
    elif angle == -2:
        axis = np.array([0.0, -1.0, 0.0])
    else:
        a = np.radians(angle)
        axis = np.array([np.cos(a), 0.0, -np.sin(a)])
    dist = float(np.abs(axis) @ size) - num("lip", 8) * bsp.UNIT
    speed = num("speed", 400) * bsp.UNIT
    return Motion("slide", tuple(axis), amount=max(dist, 0.1),
                  period=max(2 * max(dist, 0.1) / max(speed, 1e-3) + 2 * num("wait", 2), 2.0))


# Whole levels are held out: variants of one level (VARIANTS) share a split.
VARIANTS = (("oa_bases3", "oa_bases3cl", "oa_bases3plus3"), ("hydronex", "hydronex2"),
            ("am_underworks", "am_underworks2"), ("kaos", "kaos2"), ("oa_ctf2", "oa_ctf2old"),
            ("ps37ctf", "ps37ctf2"), ("islanddm", "islandctf"), ("czest1dm", "czest1tourney"),
            ("oa_koth1", "oa_koth2"), ("czest2ctf", "czest3ctf"))
VAL_LEVELS = ("oa_dm6", "oacmpdm7", "czest1dm", "czest1tourney", "fan")
TEST_LEVELS = ("oa_dm1", "oa_dm4", "oacmpdm3", "oacmpctf2", "delta", "suspended", "wrackdm17",
               "ps9ctf")
TRAIN_LEVELS = (
    "aggressor", "am_galmevish", "am_underworks", "am_underworks2", "blitzkrieg3", "cbctf1",
    "ce1m7", "ctf_compromise", "ctf_gate1", "ctf_inyard", "czest2ctf", "czest3ctf", "dm4ish",
    "dm6ish", "hydronex", "hydronex2", "islandctf", "islanddm", "kaos", "kaos2", "oa_bases3",
    "oa_bases3cl", "oa_bases3plus3", "oa_bases5", "oa_bases7", "oa_ctf2", "oa_ctf2old",
    "oa_ctf4ish", "oa_dm2", "oa_dm3", "oa_dm5", "oa_dm7", "oa_koth1", "oa_koth2", "oa_minia",
    "oa_pvomit", "oa_reptctf11", "oa_rpg3dm2", "oa_shine", "oa_shouse", "oa_spirit3",
    "oacmpctf1", "oacmpctf3", "oacmpdm1", "oacmpdm10", "oacmpdm2", "oacmpdm4", "oacmpdm5",
    "oacmpdm6", "oacmpdm8", "oacmpdm9", "oasago2", "ps37ctf", "ps37ctf2", "pul1ctf",
    "q3dm6ish", "sleekgrinder", "slimefac")


def content_effects(scene: MeshScene):
    """The effects a level's own content calls for: cutouts, layers, scrolling and
    flickering shaders and moving brush models where it has them; every level has
    camera motion and cuts. A seeded half of the levels also gets the moving light and
    glossy highlights (games have both, and not everywhere)."""
    mats = scene.materials
    has = {"alpha_cutout": any(m.alpha_test > 0 and m.blend == "opaque" for m in mats),
           "transparency": any(m.blend != "opaque" for m in mats),
           "scrolling_texture": any(m.scroll != (0.0, 0.0) for m in mats),
           "emissive_flicker": any(m.wave for m in mats),
           "object_motion": any(p.motion.kind != "static" for p in scene.parts)}
    seed = int(hashlib.sha256(scene.name.encode()).hexdigest()[:8], 16)
    has["moving_light"] = has["specular"] = seed % 2 == 0
    has["camera_motion"] = has["camera_cut"] = True
    return tuple(e for e in MESH_EFFECTS if has.get(e))


def scene_of(name, effects=None, root=None):
    """A game level by its scene name ``oa:<map>``, declaring ``effects`` (default:
    ``content_effects``)."""
    if not is_level(name):
        raise ValueError(f"scene: expected a game level named {PREFIX}<map>, got {name!r}")
    sc = level_scene(name[len(PREFIX):], ("camera_motion",), root, name)
    return dataclasses.replace(sc, effects=tuple(effects) if effects is not None
                               else content_effects(sc))


def level_scene(map_name, effects=("camera_motion",), root=None, name=None, patch_level=6):
    """OpenArena level ``map_name`` as a ``MeshScene`` declaring ``effects``."""
    arc = archive(root)
    level = arc.level(map_name, patch_level)
    shaders, cache = level.shaders, {}
    used = np.unique(level.face_texture)
    mats, index = [], {}
    for t in used:
        index[int(t)] = len(mats)
        mats.append(_material(arc, level.textures[t], shaders, cache))
    fmat = np.array([index[int(t)] for t in level.face_texture], np.int64)
    light = bsp.decode_lightmaps(level.vcolor)
    parts = []
    groups = [("world", np.isin(level.face_model, list(level.movers), invert=True))]
    groups += [(k, level.face_model == k) for k in sorted(level.movers)]
    for key, sel in groups:
        if not sel.any():
            continue
        faces = level.faces[sel]
        used_v, inv = np.unique(faces, return_inverse=True)
        motion = Motion()
        if key != "world":
            m = level.movers[key]
            motion = _motion(m, (m["mins"] + m["maxs"]) / 2)
        parts.append(Part(position=level.position[used_v], faces=inv.reshape(-1, 3),
                          uv=level.uv[used_v], normal=level.normal[used_v],
                          face_material=fmat[sel], light=light[used_v],
                          lm_uv=level.lm_uv[used_v], face_lightmap=level.face_lightmap[sel],
                          motion=motion))
    return MeshScene(name=name or PREFIX + map_name, effects=tuple(effects), parts=parts,
                     materials=mats, spawns=level.spawns, lightmaps=level.lightmaps,
                     exposure_stops=1.0 if "hdr" in effects else 0.0)
