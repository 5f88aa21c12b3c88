"""Scene specifications: what a scene holds and which effects it exhibits.

A scene declares its ``effects``; the renderer (``jtus.sim.render``) assembles and
compiles the code of those effects only, and ignores the parameters of undeclared
ones (a texture on an object of a scene without ``texture_detail`` renders as its
flat base colour; a rod in a scene without ``thin_geometry`` is not there).

Specs are frozen dataclasses that round-trip through JSON (``to_json`` /
``from_json``). World space: y up, metres; object yaw is a rotation about +y.
"""

from __future__ import annotations

import dataclasses
import json
import math

from jtus.data.conventions import FAR, NEAR
from jtus.files import drop_unknown_keys

# every effect of the display-referred (LDR) simulator; "everything" has all of them
LDR_EFFECTS = ("camera_motion", "object_motion", "thin_geometry", "texture_detail", "shadows",
               "specular", "moving_light", "emissive_flicker", "camera_cut")
EFFECTS = LDR_EFFECTS + ("hdr",)
KINDS = ("plane", "box", "sphere", "rod")
TEXTURES = ("none", "checker", "stripes", "zoneplate", "fbm", "fbm_aniso", "bricks", "tiles",
            "glyphs", "wood", "marble", "dots")
PATHS = ("orbit", "dolly", "pan", "fly")


@dataclasses.dataclass(frozen=True)
class Material:
    color: tuple = (0.7, 0.7, 0.7)       # linear RGB albedo
    texture: str = "none"                 # used only with texture_detail
    texture_scale: float = 1.0            # texture periods per metre
    texture_seed: int = 0                 # variant of the seeded textures (noise, glyphs...)
    texture_aspect: float = 1.0           # v periods per u period
    contrast: float = 0.85                # albedo = color * (1 - contrast + contrast * value)
    color2: tuple = ()                    # or, when given, lerp(color2, color, value)
    specular: float = 0.0                 # Blinn-Phong weight, used only with specular
    shininess: float = 32.0
    emission: float = 0.0                 # peak emitted radiance, used only with emissive_flicker
    flicker_hz: float = 3.0               # flicker rate in cycles per second (30 fps frames)


@dataclasses.dataclass(frozen=True)
class Object:
    kind: str                             # plane | box | sphere | rod
    position: tuple = (0.0, 0.0, 0.0)
    size: tuple = (1.0, 1.0, 1.0)         # plane: (half x, -, half z); box: half extents;
                                          # sphere: (radius, -, -); rod: (radius, half height, -)
    yaw: float = 0.0                      # radians about +y
    material: Material = Material()
    velocity: tuple = (0.0, 0.0, 0.0)     # metres per frame, used only with object_motion
    spin: float = 0.0                     # radians per frame about +y, likewise
    bob: float = 0.0                      # vertical oscillation amplitude in metres, likewise


@dataclasses.dataclass(frozen=True)
class Light:
    kind: str = "directional"             # directional | point
    vector: tuple = (-0.4, -1.0, -0.3)    # direction the light travels, or the point's position
    color: tuple = (1.0, 0.97, 0.9)
    ambient: float = 0.25
    orbit_speed: float = 0.05             # radians per frame, used only with moving_light


@dataclasses.dataclass(frozen=True)
class Path:
    kind: str = "orbit"                   # orbit | dolly | pan
    center: tuple = (0.0, 0.5, 0.0)       # orbit / pan look-at centre
    radius: float = 6.0
    height: float = 2.0
    speed: float = 0.02                   # radians (orbit, pan) or metres (dolly) per frame
    speed_variation: float = 0.5          # relative amplitude of the slow speed change
    holds: int = 1                        # stationary holds per video
    hold_frames: int = 8
    cut_every: int = 24                   # frames between cuts, used only with camera_cut
    fov_y: float = 0.9                    # radians


@dataclasses.dataclass(frozen=True)
class Scene:
    name: str
    effects: tuple
    objects: tuple
    light: Light = Light()
    path: Path = Path()
    extra_lights: tuple = ()              # more Lights (point or directional): diffuse,
                                          # shadows and specular as the first; its ambient only
    sky: tuple = ((0.75, 0.8, 0.9), (0.3, 0.45, 0.75))  # horizon, zenith
    near: float = NEAR
    far: float = FAR
    highlight_gain: float = 12.0          # hdr: specular and emissive radiance scale
    exposure_stops: float = 1.0           # hdr: amplitude of the exposure curve, in stops

    def __post_init__(self):
        bad = [e for e in self.effects if e not in EFFECTS]
        if bad:
            raise ValueError(f"effects: unknown {bad}; expected a subset of {EFFECTS}")
        if len(set(self.effects)) != len(self.effects):
            raise ValueError(f"effects: duplicates in {self.effects}")
        for i, o in enumerate(self.objects):
            if o.kind not in KINDS:
                raise ValueError(f"objects[{i}].kind: expected one of {KINDS}, got {o.kind!r}")
            if o.material.texture not in TEXTURES:
                raise ValueError(f"objects[{i}].material.texture: expected one of {TEXTURES}, "
                                 f"got {o.material.texture!r}")
        if self.path.kind not in PATHS:
            raise ValueError(f"path.kind: expected one of {PATHS}, got {self.path.kind!r}")
        for where, light in [("light", self.light)] + [
                (f"extra_lights[{i}]", x) for i, x in enumerate(self.extra_lights)]:
            if light.kind not in ("directional", "point"):
                raise ValueError(f"{where}.kind: expected directional or point, "
                                 f"got {light.kind!r}")
        for i, o in enumerate(self.objects):
            c2 = o.material.color2
            if c2 and len(c2) != 3:
                raise ValueError(f"objects[{i}].material.color2: expected () or 3 numbers, "
                                 f"got {c2!r}")
        if not self.highlight_gain > 0 or not self.exposure_stops >= 0:
            raise ValueError(f"highlight_gain/exposure_stops: expected > 0 and >= 0, got "
                             f"{self.highlight_gain}, {self.exposure_stops}")
        if not 0 < self.near < self.far:
            raise ValueError(f"near/far: expected 0 < near < far, got {self.near}, {self.far}")
        self._check_picture()

    def _check_picture(self):
        """Values that are well-typed but make no picture (or NaN in one)."""
        if not self.objects:
            raise ValueError("objects: expected at least one object")
        if not 0.01 < self.path.fov_y < 3.1:
            raise ValueError(f"path.fov_y: expected radians in (0.01, 3.1), got {self.path.fov_y}")
        if not self.path.radius > 0:
            raise ValueError(f"path.radius: expected > 0, got {self.path.radius}")
        for where, light in [("light", self.light)] + [
                (f"extra_lights[{i}]", x) for i, x in enumerate(self.extra_lights)]:
            if light.kind == "directional" and not any(light.vector):
                raise ValueError(f"{where}.vector: a directional light needs a non-zero "
                                 f"direction, got {light.vector}")
        for i, o in enumerate(self.objects):
            used = {"plane": (), "box": (0, 1, 2), "sphere": (0,), "rod": (0, 1)}[o.kind]
            if not all(o.size[k] > 0 for k in used):
                raise ValueError(f"objects[{i}].size: a {o.kind} needs positive sizes at "
                                 f"{list(used)}, got {o.size}")

    def has(self, effect: str) -> bool:
        return effect in self.effects

    def visible_objects(self):
        """The objects the renderer intersects: rods only with thin_geometry."""
        return tuple(o for o in self.objects if o.kind != "rod" or self.has("thin_geometry"))


def _build(cls, data, where):
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected an object, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    data = drop_unknown_keys(where, data, fields)
    kw = {}
    for k, v in data.items():
        if k not in ("material", "light", "path", "objects", "extra_lights"):
            default = fields[k].default
            _check_value(f"{where}.{k}", v,
                         None if default is dataclasses.MISSING else default)
        if k == "material":
            v = _build(Material, v, f"{where}.material")
        elif k == "light":
            v = _build(Light, v, f"{where}.light")
        elif k == "path":
            v = _build(Path, v, f"{where}.path")
        elif k in ("objects", "extra_lights"):
            if not isinstance(v, list):
                raise ValueError(f"{where}.{k}: expected a list, got {v!r}")
            item = Object if k == "objects" else Light
            v = tuple(_build(item, o, f"{where}.{k}[{i}]") for i, o in enumerate(v))
        elif isinstance(v, list):
            v = tuple(tuple(x) if isinstance(x, list) else x for x in v)
        kw[k] = v
    try:
        return cls(**kw)
    except ValueError as e:  # a check across fields (``__post_init__``), named from here
        raise ValueError(f"{where}: {e}") from e


def _is_number(v):
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check_value(where, v, default):
    """A JSON value against its field's default: numbers finite (not strings, bools or
    null), integers whole, strings strings, vectors of the default's length of numbers
    (``()`` allowed where the default is empty)."""
    if default is None and where.endswith(".effects"):  # required, no default
        ok = isinstance(v, list) and all(isinstance(x, str) for x in v)
        what = "a list of effect names"
    elif default is None:  # name, kind
        ok, what = isinstance(v, str) and bool(v), "a non-empty string"
    elif isinstance(default, bool):
        ok, what = isinstance(v, bool), "true or false"
    elif isinstance(default, int):
        ok, what = isinstance(v, int) and not isinstance(v, bool), "an integer"
    elif isinstance(default, float):
        ok, what = _is_number(v), "a finite number"
    elif isinstance(default, str):
        ok, what = isinstance(v, str), "a string"
    elif isinstance(default, tuple) and default and isinstance(default[0], tuple):
        ok = (isinstance(v, list) and len(v) == len(default) and all(
            isinstance(x, list) and len(x) == len(d) and all(map(_is_number, x))
            for x, d in zip(v, default)))
        what = f"{len(default)} lists of {len(default[0])} finite numbers"
    elif isinstance(default, tuple):
        n = len(default) or 3
        ok = isinstance(v, list) and (len(v) == n or (not default and not v)) and all(
            map(_is_number, v))
        what = f"a list of {n} finite numbers" + (" or []" if not default else "")
    else:
        return
    if not ok:
        raise ValueError(f"{where}: expected {what}, got {v!r}")


def from_dict(data, where="scene") -> Scene:
    """The ``Scene`` of a JSON-like dict; ``ValueError`` naming the field (``where``
    starts its path) for a wrong type, a non-finite or out-of-range value; keys that are
    not fields are dropped with an ``UnknownKeyWarning`` naming them."""
    return _build(Scene, data, where)


def from_json(text_or_path) -> Scene:
    """A scene from JSON text or a path to a ``.json`` file (messages then start with
    the path)."""
    text, where = str(text_or_path), "scene"
    if not text.lstrip().startswith("{"):
        where = f"{text}: scene"
        with open(text) as fh:
            text = fh.read()
    return from_dict(json.loads(text), where)


def to_json(scene: Scene) -> str:
    return json.dumps(dataclasses.asdict(scene), indent=1)
