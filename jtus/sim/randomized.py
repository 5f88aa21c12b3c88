"""The randomized scene family: ``random_scene(seed)``, deterministic per seed.

Each seed draws a whole scene spec (``jtus.sim.scene.Scene``, JSON round-trippable):
a textured floor, backdrop walls, 8 to 40 objects of every kind the renderer has
(large blocks and platforms, boxes, spheres, rods, wires) clustered so that they
occlude each other, materials from the full texture library at scales from well
below to above the input's Nyquist limit, a sun and 0-2 point lights, a sky, and a
camera path (orbit, dolly, pan or fly-through) with a speed from holds to more than
16 output pixels per frame. The effects are drawn too (or given): a scene declares
them, and the renderer computes only those (a wire or rod is intersected only with
``thin_geometry``, textures only with ``texture_detail``...).

The name ``random_<seed>`` resolves through ``jtus.sim.get_scene``, so a dataset
preset lists random scenes by name; train, validation and test presets draw from
disjoint seed ranges (``SEED_BASE``).
"""

from __future__ import annotations

import colorsys
import dataclasses

import numpy as np

from jtus.sim.scene import Light, Material, Object, Path, Scene

PREFIX = "random_"
# seeds per split: train 0.., val 1,000,000.., test 2,000,000.. (never shared)
SEED_BASE = {"train": 0, "val": 1_000_000, "test": 2_000_000}

# probability of each effect when the effects are drawn
_EFFECT_P = {"camera_motion": 0.85, "object_motion": 0.5, "thin_geometry": 0.6,
             "texture_detail": 0.9, "shadows": 0.6, "specular": 0.5, "moving_light": 0.2,
             "emissive_flicker": 0.2, "camera_cut": 0.15}
_SEEDED = ("fbm", "fbm_aniso", "bricks", "tiles", "glyphs", "wood", "marble", "dots")
_ALL_TEXTURES = ("checker", "stripes", "zoneplate") + _SEEDED


def name_of(seed: int) -> str:
    return f"{PREFIX}{int(seed)}"


def seed_of(name: str):
    """The seed of a ``random_<seed>`` name, or None for any other name."""
    if not name.startswith(PREFIX):
        return None
    tail = name[len(PREFIX):]
    if not tail.isdigit():
        raise ValueError(f"scene: {name!r} is not random_<non-negative integer>")
    return int(tail)


def split_seeds(split: str, count: int, start: int = 0):
    """``count`` seeds of a split's range (disjoint from the other splits')."""
    if split not in SEED_BASE:
        raise ValueError(f"split: expected one of {tuple(SEED_BASE)}, got {split!r}")
    return [SEED_BASE[split] + start + i for i in range(count)]


def _colour(rng, sat=(0.1, 0.9), val=(0.25, 0.95)):
    h = rng.uniform()
    return tuple(round(float(c), 4) for c in colorsys.hsv_to_rgb(h, rng.uniform(*sat),
                                                                 rng.uniform(*val)))


def _material(rng, scale_range=(0.3, 40.0), specular_p=0.3):
    texture = str(rng.choice(_ALL_TEXTURES)) if rng.uniform() < 0.9 else "none"
    color = _colour(rng)
    two_tone = rng.uniform() < 0.5
    spec = float(rng.uniform(0.2, 1.0)) if rng.uniform() < specular_p else 0.0
    return Material(
        color=color, texture=texture,
        texture_scale=round(float(np.exp(rng.uniform(*np.log(scale_range)))), 4),
        texture_seed=int(rng.integers(0, 10_000)),
        texture_aspect=round(float(np.exp(rng.uniform(np.log(0.5), np.log(2.0)))), 4),
        contrast=round(float(rng.uniform(0.3, 0.95)), 4),
        color2=_colour(rng) if two_tone else (),
        specular=round(spec, 4), shininess=round(float(np.exp(rng.uniform(np.log(8),
                                                                             np.log(200)))), 2))


def _motion(rng, moving_p):
    if rng.uniform() >= moving_p:
        return {}
    speed = rng.uniform(0.01, 0.15)
    ang = rng.uniform(0, 2 * np.pi)
    return {"velocity": (round(speed * np.cos(ang), 4), 0.0, round(speed * np.sin(ang), 4)),
            "spin": round(float(rng.uniform(-0.12, 0.12)), 4),
            "bob": round(float(rng.uniform(0, 0.3)) if rng.uniform() < 0.4 else 0.0, 4)}


def _draw_effects(rng):
    # only the effects in _EFFECT_P are drawn (hdr is asked for): one draw each, in
    # this order, so adding an effect to EFFECTS changes no existing scene
    effects = tuple(e for e in _EFFECT_P if rng.uniform() < _EFFECT_P[e])
    return effects or ("texture_detail",)


def _walls(rng):
    """Backdrop walls outside every camera path (paths stay within 11 m of the centre)."""
    walls = []
    for _ in range(int(rng.integers(0, 4))):
        ang = rng.uniform(0, 2 * np.pi)
        dist = rng.uniform(11.5, 15.0)
        h = round(float(rng.uniform(1.0, 4.0)), 3)
        walls.append(Object("box", (round(float(dist * np.cos(ang)), 3), h,
                                    round(float(dist * np.sin(ang)), 3)),
                            (round(float(rng.uniform(4, 9)), 3), h, 0.15),
                            round(float(-ang + np.pi / 2), 4),
                            _material(rng, (0.2, 15.0))))
    return walls


def _object(rng, thin, rad, moving_p):
    """One object of the cluster (within ``rad`` metres of the centre)."""
    if thin:
        kind = rng.choice(["box", "sphere", "rod", "wire", "platform", "block"],
                          p=[0.26, 0.22, 0.2, 0.12, 0.08, 0.12])
    else:  # rods and wires are thin geometry: drawn only where the scene declares it
        kind = rng.choice(["box", "sphere", "platform", "block"], p=[0.4, 0.34, 0.1, 0.16])
    r = rad * np.sqrt(rng.uniform())
    a = rng.uniform(0, 2 * np.pi)
    x, z = round(float(r * np.cos(a)), 3), round(float(r * np.sin(a)), 3)
    yaw = round(float(rng.uniform(0, 2 * np.pi)), 4)
    mat = _material(rng)
    mot = _motion(rng, moving_p)
    if kind == "box":
        s = tuple(round(float(v), 3) for v in rng.uniform(0.08, 0.7, 3))
        y = s[1] + (rng.uniform(0, 1.2) if rng.uniform() < 0.25 else 0.0)
        return Object("box", (x, round(float(y), 3), z), s, yaw, mat, **mot)
    if kind == "block":  # large: occluders with long depth edges
        s = (round(float(rng.uniform(0.5, 1.2)), 3), round(float(rng.uniform(0.4, 1.3)), 3),
             round(float(rng.uniform(0.2, 1.0)), 3))
        return Object("box", (x, s[1], z), s, yaw, mat)
    if kind == "sphere":
        rr = float(np.exp(rng.uniform(np.log(0.05), np.log(0.8))))
        y = rr + (rng.uniform(0, 1.2) if rng.uniform() < 0.3 else 0.0)
        return Object("sphere", (x, round(y, 3), z), (round(rr, 4), 0, 0), yaw, mat, **mot)
    if kind == "rod":  # sub-pixel to a few pixels wide at typical distances
        rr = float(np.exp(rng.uniform(np.log(0.004), np.log(0.05))))
        hh = float(rng.uniform(0.3, 1.3))
        return Object("rod", (x, round(hh, 3), z), (round(rr, 4), round(hh, 3), 0), yaw, mat,
                      **mot)
    if kind == "wire":
        th = float(np.exp(rng.uniform(np.log(0.003), np.log(0.03))))
        y = float(rng.uniform(0.3, 2.5))
        return Object("box", (x, round(y, 3), z),
                      (round(float(rng.uniform(1.0, 4.0)), 3), round(th, 4), round(th, 4)),
                      yaw, mat)
    # a raised platform (a finite horizontal plane)
    s = (round(float(rng.uniform(0.4, 1.5)), 3), 0, round(float(rng.uniform(0.4, 1.5)), 3))
    return Object("plane", (x, round(float(rng.uniform(0.3, 1.2)), 3), z), s, yaw, mat)


def _with_emitters(rng, objs):
    """At least two objects made emitters that can flicker (``emissive_flicker``)."""
    objs = list(objs)
    for i in rng.choice(np.arange(1, len(objs)), size=min(2, len(objs) - 1), replace=False):
        o = objs[int(i)]
        m = dataclasses.replace(o.material, emission=round(float(rng.uniform(0.5, 2.0)), 3),
                                flicker_hz=round(float(rng.uniform(1.0, 8.0)), 3))
        objs[int(i)] = dataclasses.replace(o, material=m)
    return objs


def _lights(rng):
    """``(sun, point lights)``: a directional sun, and zero to two point lights."""
    elev = rng.uniform(0.25, 1.2)
    az = rng.uniform(0, 2 * np.pi)
    sun = Light("directional", (round(float(-np.cos(elev) * np.cos(az)), 4),
                                round(float(-np.sin(elev)), 4),
                                round(float(-np.cos(elev) * np.sin(az)), 4)),
                _colour(rng, (0.0, 0.25), (0.8, 1.0)), round(float(rng.uniform(0.1, 0.4)), 3),
                round(float(rng.uniform(0.02, 0.08)), 4))
    extra = tuple(Light("point", (round(float(rng.uniform(-3, 3)), 3),
                                  round(float(rng.uniform(1.0, 3.0)), 3),
                                  round(float(rng.uniform(-3, 3)), 3)),
                        _colour(rng, (0.0, 0.6), (0.6, 1.0)), 0.0,
                        round(float(rng.uniform(0.03, 0.1)), 4))
                  for _ in range(int(rng.choice([0, 0, 1, 2]))))
    return sun, extra


def random_scene(seed: int, effects=None, name=None) -> Scene:
    """The scene of ``seed``; ``effects`` (a subset of ``EFFECTS``) overrides the
    drawn ones. Same seed and effects, same spec."""
    if int(seed) < 0:
        raise ValueError(f"seed: expected a non-negative integer, got {seed}")

    # independent streams: overriding the effects (which changes which kinds of
    # object are drawn) leaves the layout, lights, sky and camera path as they are
    def stream(*k):
        return np.random.default_rng([int(seed), 0x5CE4E, *k])

    rng = stream(0)
    drawn = _draw_effects(rng)
    effects = tuple(effects) if effects is not None else drawn
    rad = float(rng.uniform(2.0, 4.0))                       # cluster radius, metres
    objs = [Object("plane", (0.0, 0.0, 0.0), (-1, 0, -1), material=_material(rng, (0.2, 12.0)))]
    objs += _walls(rng)
    n = int(rng.integers(8, 41))
    moving_p = rng.uniform(0.2, 0.7)
    objs += [_object(stream(1, i), "thin_geometry" in effects, rad, moving_p) for i in range(n)]
    if "emissive_flicker" in effects:
        objs = _with_emitters(stream(2), objs)
    sun, extra = _lights(stream(5))
    path = _path(stream(3), rad)
    rng = stream(4)
    sky = (_colour(rng, (0.0, 0.4), (0.5, 0.95)), _colour(rng, (0.2, 0.8), (0.3, 0.9)))
    return Scene(name or name_of(seed), effects, tuple(objs), sun, path, extra, sky)


def _path(rng, rad):
    kind = str(rng.choice(["orbit", "dolly", "pan", "fly"], p=[0.35, 0.2, 0.2, 0.25]))
    # speed, log-uniform over two decades; about one scene in seven crawls (near-static)
    slow = rng.uniform() < 0.15
    if kind in ("orbit", "fly"):
        speed = np.exp(rng.uniform(np.log(0.003), np.log(0.2)))
    elif kind == "dolly":
        speed = np.exp(rng.uniform(np.log(0.02), np.log(0.8)))
    else:  # pan: the view swings 4.8x the phase's rate (paths.py), up to ~0.2 rad/frame
        speed = np.exp(rng.uniform(np.log(0.001), np.log(0.04)))
    if slow:
        speed *= 0.1
    # outside the objects' cluster (blocks reach ~1.7 m past ``rad``); a dolly comes in
    # to 0.65 of its radius; a fly-through passes above the tallest objects (2.9 m)
    cy = rng.uniform(0.2, 1.0)
    if kind == "fly":
        radius, height = rad * rng.uniform(0.8, 1.5), rng.uniform(3.1, 4.5) - cy
    elif kind == "dolly":
        radius, height = 1.5 * rad + rng.uniform(3.5, 5.0), rng.uniform(0.6, 3.5)
    else:
        radius, height = rad + rng.uniform(2.5, 5.0), rng.uniform(0.6, 3.5)
    return Path(kind, (0.0, round(float(cy), 3), 0.0), round(float(radius), 3),
                round(float(height), 3), round(float(speed), 5),
                round(float(rng.uniform(0.0, 0.9)), 3), int(rng.integers(0, 3)),
                int(rng.integers(4, 17)), int(rng.integers(12, 31)),
                round(float(rng.uniform(0.6, 1.2)), 3))


__all__ = ["PREFIX", "SEED_BASE", "name_of", "random_scene", "seed_of", "split_seeds"]
