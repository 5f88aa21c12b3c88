"""The built-in scenes: each effect alone, and in combination.

Three layouts share their objects across scenes; what a scene shows is decided by
its declared effects (an undeclared effect's parameters are ignored by the renderer).
"""

from __future__ import annotations

import dataclasses

from jtus.sim import randomized
from jtus.sim.scene import EFFECTS, LDR_EFFECTS, Light, Material, Object, Path, Scene

GROUND = Object("plane", (0, 0, 0), (-1, 0, -1),
                material=Material((0.55, 0.55, 0.5), "checker", 1.0))


def _courtyard():
    return (
        GROUND,
        Object("box", (-1.5, 0.5, 0.0), (0.5, 0.5, 0.5), 0.4,
               Material((0.8, 0.25, 0.2), "stripes", 6.0, specular=0.3),
               velocity=(0.0, 0.0, 0.06), spin=0.03),
        Object("sphere", (1.2, 0.7, 0.5), (0.7, 0, 0),
               material=Material((0.2, 0.35, 0.85), specular=0.8, shininess=64.0),
               velocity=(-0.05, 0.0, 0.0), bob=0.2),
        Object("box", (0.0, 1.5, -9.0), (5.0, 1.5, 0.1),
               material=Material((0.85, 0.85, 0.8), "zoneplate", 1.5)),
        Object("box", (0.2, 0.3, 2.0), (0.3, 0.3, 0.3),
               material=Material((1.0, 0.8, 0.3), emission=1.5, flicker_hz=4.0)),
        Object("rod", (-0.4, 1.0, 1.0), (0.02, 1.0, 0)),
        Object("rod", (2.2, 1.0, -1.2), (0.03, 1.0, 0)),
    )


def _fence():
    rods = tuple(Object("rod", (-1.5 + 0.25 * i, 0.8, 0.6), (0.015, 0.8, 0),
                        material=Material((0.9, 0.9, 0.9), specular=0.5))
                 for i in range(13))
    return (
        GROUND,
        Object("box", (0.0, 1.0, -6.5), (3.5, 1.0, 0.2), 0.1,
               Material((0.3, 0.6, 0.35), "stripes", 8.0, specular=0.2)),
        Object("sphere", (-1.0, 0.5, -0.3), (0.5, 0, 0),
               material=Material((0.9, 0.5, 0.1), "checker", 4.0, specular=0.9, shininess=96.0),
               velocity=(0.04, 0.0, 0.0)),
        Object("box", (1.4, 0.4, 1.5), (0.25, 0.4, 0.25), 0.7,
               Material((0.4, 0.9, 1.0), emission=2.0, flicker_hz=6.0), spin=0.05),
    ) + rods


def _plaza():
    return (
        GROUND,
        Object("box", (0.0, 1.2, -9.5), (6.0, 1.2, 0.1),
               material=Material((0.7, 0.7, 0.75), "checker", 3.0)),
        Object("box", (-2.0, 0.4, 0.0), (0.4, 0.4, 0.4), material=Material((0.9, 0.3, 0.3)),
               velocity=(0.08, 0.0, 0.0)),
        Object("box", (1.5, 0.6, -1.0), (0.3, 0.6, 0.3), material=Material((0.3, 0.8, 0.3),
               specular=0.4), spin=0.08),
        Object("sphere", (0.5, 0.5, 1.2), (0.5, 0, 0),
               material=Material((0.3, 0.4, 0.9), "zoneplate", 2.0, specular=0.6),
               velocity=(0.0, 0.0, -0.07), bob=0.3),
        Object("sphere", (-0.8, 0.25, -1.8), (0.25, 0, 0),
               material=Material((1.0, 0.9, 0.6), emission=1.2), velocity=(0.05, 0.0, 0.02)),
        Object("rod", (0.0, 1.2, 0.0), (0.025, 1.2, 0)),
    )


_LAYOUTS = {"courtyard": _courtyard, "fence": _fence, "plaza": _plaza}
_POINT = Light("point", (1.5, 3.0, 1.5), ambient=0.2, orbit_speed=0.08)

# Backdrop walls stand outside every orbit, so that no path looks through them.
# name: (layout, effects, path, light)
_SUITE = {
    "camera_orbit": ("courtyard", ("camera_motion",), Path("orbit", speed=0.02), Light()),
    "objects": ("plaza", ("object_motion",), Path("orbit", radius=6.5, height=2.5), Light()),
    "thin": ("fence", ("thin_geometry",), Path("orbit", radius=4.0, height=1.2), Light()),
    "textures": ("courtyard", ("texture_detail",), Path("orbit", radius=5.0, height=1.5), Light()),
    "shadows": ("plaza", ("shadows",), Path("orbit", radius=6.0, height=3.0), _POINT),
    "specular": ("fence", ("specular",), Path("orbit", radius=4.0, height=1.5), Light()),
    "moving_light": ("courtyard", ("moving_light", "shadows"), Path("orbit", height=3.0), _POINT),
    "flicker": ("fence", ("emissive_flicker",), Path("orbit", radius=5.0), Light()),
    "cuts": ("courtyard", ("camera_cut",), Path("orbit", cut_every=20), Light()),
    "fence_pan": ("fence", ("camera_motion", "thin_geometry"),
                  Path("pan", radius=4.0, height=1.2, speed=0.01), Light()),
    "moire_dolly": ("courtyard", ("camera_motion", "texture_detail"),
                    Path("dolly", radius=6.0, height=1.2, speed=0.05), Light()),
    "plaza_day": ("plaza", ("camera_motion", "object_motion", "shadows", "specular"),
                  Path("orbit", radius=7.0, height=2.5, speed=0.015), Light()),
    "everything": ("courtyard", LDR_EFFECTS, Path("orbit", speed=0.025, cut_every=30), _POINT),
}

NAMES = tuple(_SUITE)


def get(name: str) -> Scene:
    """A built-in scene by name, or ``random_<seed>`` from the randomized family."""
    seed = randomized.seed_of(name)
    if seed is not None:
        return randomized.random_scene(seed)
    if name not in _SUITE:
        raise ValueError(f"scene: expected one of {NAMES} or random_<seed>, got {name!r}")
    layout, effects, path, light = _SUITE[name]
    return Scene(name, tuple(effects), _LAYOUTS[layout](), light, path)


def with_effects(scene: Scene, add) -> Scene:
    """``scene`` with the effects ``add`` as well (those it lacks, in ``EFFECTS``
    order). A randomized scene is drawn again with them, so that effects that shape
    its objects (emitters for ``emissive_flicker``, rods for ``thin_geometry``) get
    them; layout, lights, sky and path stay those of its seed."""
    missing = [e for e in add if e not in scene.effects]
    if not missing:
        return scene
    effects = tuple(e for e in EFFECTS if e in scene.effects or e in missing)
    seed = randomized.seed_of(scene.name)
    if seed is not None and randomized.random_scene(seed) == dataclasses.replace(
            scene, name=randomized.name_of(seed)):
        return randomized.random_scene(seed, effects, name=scene.name)
    return dataclasses.replace(scene, effects=effects)
