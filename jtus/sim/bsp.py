"""Quake III Arena levels (IBSP version 46, as OpenArena ships them) as mesh scenes.

A level lives in ``.pk3`` archives (zip files): ``maps/NAME.bsp`` holds the geometry,
baked lightmaps and entities; ``textures/...`` the images (TGA or JPEG);
``scripts/*.shader`` the shaders that say how a surface is drawn. This reader takes
from them what a rasterizer of the level would show:

- world faces (polygons, triangle meshes and curved patches, tessellated here) and
  the faces of the level's brush models (doors, platforms, rotating parts), each with
  its texture coordinates, lightmap coordinates, normal and vertex colour;
- per texture, the image of its shader's first drawn stage and that shader's
  ``alphaFunc`` (alpha-tested cutouts), ``blendFunc`` (additive or alpha-blended
  layers), ``tcMod scroll`` (scrolling textures), ``rgbGen wave`` (flicker),
  ``surfaceparm nodraw`` / ``sky``;
- the entities: spawn points (where cameras start) and which brush model moves how
  (``func_door``, ``func_bobbing``, ``func_rotating``, ``func_pendulum``, ``func_plat``).

Conversion at this edge (``docs/conventions.md``): Quake's z-up inches become jtus's
y-up metres, ``(x, y, z) -> (x, z, -y) * 0.0254`` (a rotation, so handedness is kept);
image rows run down from the top as jtus's do. Lightmaps are Quake's overbright ones
(multiplied by 2, the engine's default ``r_overBrightBits 1``) and, like textures,
sRGB-encoded: both are decoded to linear here.
"""

from __future__ import annotations

import dataclasses
import io
import re
import struct
import zipfile
from pathlib import Path

import numpy as np
from PIL import Image

from jtus.sim.mesh import srgb_to_linear

UNIT = 0.0254  # metres per Quake unit (an inch, as id's tools assume)
SURF_SKY, SURF_NODRAW = 0x4, 0x80
_LUMPS = 17
_VERTEX = struct.Struct("<3f2f2f3f4B")       # 44 bytes
_FACE = struct.Struct("<7i1i2i2i3f6f3f2i")   # 104 bytes
_TEXTURE = struct.Struct("<64sii")           # 72 bytes
_MODEL = struct.Struct("<3f3f4i")            # 40 bytes
_MOVERS = ("func_door", "func_bobbing", "func_rotating", "func_pendulum", "func_plat")


def to_jtus(p):
    """Quake positions or directions ``[...,3]`` (z up, inches) in jtus's world (y up,
    metres for positions: scale directions yourself if they must stay unit)."""
    p = np.asarray(p, np.float64)
    return np.stack([p[..., 0], p[..., 2], -p[..., 1]], -1) * UNIT


@dataclasses.dataclass
class Stage:
    image: str = ""           # archive path of the image ('' for $whiteimage)
    blend: str = "opaque"     # opaque | add | blend (alpha) | filter (multiply)
    alpha_test: float = 0.0   # keep texels with alpha >= this (0: no test)
    scroll: tuple = (0.0, 0.0)  # texture units per second
    wave: tuple = ()          # rgbGen wave (base, amplitude, phase, frequency Hz)


@dataclasses.dataclass
class Shader:
    name: str
    stages: list
    sky: bool = False
    nodraw: bool = False
    lightmapped: bool = True


_TOKEN = re.compile(r'"[^"]*"|[{}]|[^\s{}"]+')


def parse_shaders(text):
    """``{name: Shader}`` of a ``.shader`` script (keywords not used here are skipped).
    The format is line-based: a name, then ``{ ... }`` holding shader keywords and
    ``{ ... }`` stages, one keyword and its arguments per line."""
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    out, name, depth, sh, st = {}, None, 0, None, None
    for raw in text.splitlines():
        words = []
        for t in _TOKEN.findall(raw.split("//")[0]):
            if t == "{":
                depth += 1
                if depth == 1 and name:
                    sh = Shader(name.lower(), [])
                elif depth == 2 and sh is not None:
                    st = Stage()
            elif t == "}":
                if words:
                    _keyword(sh, st, words)
                    words = []
                if depth == 2 and sh is not None and st is not None:
                    sh.stages.append(st)
                    st = None
                elif depth == 1 and sh is not None:
                    _finish(sh)
                    out[sh.name] = sh
                    sh, name = None, None
                depth = max(depth - 1, 0)
            elif depth == 0:
                name = t.strip('"')
            else:
                words.append(t.strip('"'))
        if words and sh is not None:
            _keyword(sh, st, words)
    return out


def _keyword(sh, st, words):
    """Apply one line of a shader (``st`` None) or of one of its stages."""
    key, args = words[0].lower(), words[1:]
    low = [a.lower() for a in args]
    if st is None:
        if key == "surfaceparm" and low:
            sh.sky |= low[0] == "sky"
            sh.nodraw |= low[0] == "nodraw"
            sh.lightmapped &= low[0] != "nolightmap"
        elif key == "skyparms":
            sh.sky = True
        return
    if key in ("map", "clampmap") and args:
        st.image = "$lightmap" if low[0] == "$lightmap" else ("" if args[0][0] == "$"
                                                               else args[0])
    elif key == "animmap" and len(args) > 1:
        st.image = args[1]
    elif key == "blendfunc" and low:
        if low[0] == "add" or low[:2] == ["gl_one", "gl_one"]:
            st.blend = "add"
        elif low[0] == "blend" or low[:2] == ["gl_src_alpha", "gl_one_minus_src_alpha"]:
            st.blend = "blend"
        elif low[0] == "filter" or "gl_dst_color" in low or low[:1] == ["gl_zero"]:
            st.blend = "filter"
        else:
            st.blend = "add"
    elif key == "alphafunc" and low:
        st.alpha_test = {"gt0": 1e-3, "lt128": 0.0, "ge128": 0.5}.get(low[0], 0.5)
    elif key == "tcmod" and len(low) >= 3 and low[0] == "scroll":
        st.scroll = (_num(args[1]), _num(args[2]))
    elif key == "rgbgen" and len(low) >= 6 and low[0] == "wave":
        st.wave = (_num(args[2]), _num(args[3]), _num(args[4]), _num(args[5]))


def _finish(sh):
    """A shader draws its lightmap stage's product when it has one (or no stages:
    the default shader is texture x lightmap); the lightmap stage is no image."""
    has_lightmap = any(s.image == "$lightmap" for s in sh.stages)
    sh.stages = [s for s in sh.stages if s.image != "$lightmap"]
    sh.lightmapped = sh.lightmapped and (has_lightmap or not sh.stages)


def _num(s):
    try:
        return float(s)
    except ValueError:
        return 0.0


@dataclasses.dataclass
class Level:
    """What a Quake III level holds, in jtus's world (see the module docstring).

    Per-vertex arrays ``[V,...]``; ``faces [F,3]`` index them; ``face_texture [F]``
    indexes ``textures`` (archive names); ``face_lightmap [F]`` indexes ``lightmaps``
    (-1: lit by vertex colour); ``face_model [F]``: 0 for the world, k for brush model
    k (``movers[k]`` says how it moves)."""
    name: str
    position: np.ndarray
    uv: np.ndarray
    lm_uv: np.ndarray
    normal: np.ndarray
    vcolor: np.ndarray
    faces: np.ndarray
    face_texture: np.ndarray
    face_lightmap: np.ndarray
    face_model: np.ndarray
    textures: list
    shaders: dict
    lightmaps: np.ndarray     # [K,128,128,3] float32 linear
    spawns: list              # [(position [3] at eye height, yaw radians about +y)]
    movers: dict              # brush model -> {"class": ..., entity keys}


def _lumps(data):
    if data[:4] != b"IBSP":
        raise ValueError(f"bsp: expected the magic 'IBSP', got {data[:4]!r}")
    version = struct.unpack_from("<i", data, 4)[0]
    if version != 46:
        raise ValueError(f"bsp: expected version 46 (Quake III), got {version}")
    d = struct.unpack_from(f"<{2 * _LUMPS}i", data, 8)
    return [data[d[2 * k]:d[2 * k] + d[2 * k + 1]] for k in range(_LUMPS)]


def parse_entities(text):
    """The entity lump as a list of ``{key: value}``."""
    out = []
    for block in re.findall(r"\{([^{}]*)\}", text):
        out.append(dict(re.findall(r'"([^"]*)"\s+"([^"]*)"', block)))
    return out


def _bezier_patch(ctrl, w, h, level):
    """Tessellate a Quake patch: ``ctrl [h*w, C]`` control points (w, h odd) into
    quadratic Bezier blocks of ``(level+1)^2`` vertices; returns ``(verts, tris)``."""
    t = np.linspace(0, 1, level + 1)
    b = np.stack([(1 - t) ** 2, 2 * t * (1 - t), t ** 2], -1)  # [L+1,3]
    grid = ctrl.reshape(h, w, -1)
    verts, tris, base = [], [], 0
    n = level + 1
    ii, jj = np.mgrid[0:level, 0:level]
    q = (ii * n + jj).reshape(-1)
    quads = np.concatenate([np.stack([q, q + n, q + 1], -1),
                            np.stack([q + 1, q + n, q + n + 1], -1)])
    for by in range(0, h - 1, 2):
        for bx in range(0, w - 1, 2):
            block = grid[by:by + 3, bx:bx + 3]                # [3,3,C]
            v = np.einsum("ia,jb,abc->ijc", b, b, block).reshape(n * n, -1)
            verts.append(v)
            tris.append(quads + base)
            base += n * n
    return np.concatenate(verts), np.concatenate(tris)


def load_level(data: bytes, name="level", shaders=None, patch_level=6):
    """Parse a BSP file's bytes into a ``Level`` (see ``Level``); ``shaders``: the
    archive's ``{name: Shader}`` to know which textures are sky or not drawn."""
    shaders = shaders or {}
    lumps = _lumps(data)
    ents = parse_entities(lumps[0].decode("latin-1"))
    texs = [(n.split(b"\0")[0].decode("latin-1").lower(), fl, ct)
            for n, fl, ct in _TEXTURE.iter_unpack(lumps[1])]
    models = list(_MODEL.iter_unpack(lumps[7]))
    verts = np.array(list(_VERTEX.iter_unpack(lumps[10])), np.float64).reshape(-1, 14)
    meshverts = np.frombuffer(lumps[11], "<i4")
    faces = list(_FACE.iter_unpack(lumps[13]))
    lm = np.frombuffer(lumps[14], np.uint8).reshape(-1, 128, 128, 3)
    face_model = np.zeros(len(faces), np.int32)
    for k, m in enumerate(models):
        face_model[m[6]:m[6] + m[7]] = k
    a, faces_arr, ftex, flm, fmod = _triangles(faces, face_model, texs, verts, meshverts,
                                               shaders, len(lm), patch_level, name)
    normal = to_jtus(a[:, 7:10]) / UNIT
    return Level(name=name, position=to_jtus(a[:, 0:3]), uv=a[:, 3:5].astype(np.float32),
                 lm_uv=a[:, 5:7].astype(np.float32), normal=normal.astype(np.float32),
                 vcolor=(a[:, 10:13] / 255.0).astype(np.float32), faces=faces_arr,
                 face_texture=np.array(ftex, np.int32), face_lightmap=np.array(flm, np.int32),
                 face_model=np.array(fmod, np.int32), textures=[t[0] for t in texs],
                 shaders=shaders, lightmaps=decode_lightmaps(lm / 255.0), spawns=_spawns(ents),
                 movers=_movers(ents, models))


def _triangles(faces, face_model, texs, verts, meshverts, shaders, n_lightmaps, patch_level,
               name):
    """The drawn faces as triangles: ``(vertex attributes [V,14], faces [F,3], texture,
    lightmap and brush model per face)``; sky and nodraw faces and billboards left out."""
    attrs, tris, ftex, flm, fmod = [], [], [], [], []
    base = 0
    for fi, f in enumerate(faces):
        tex, _, kind, v0, nv, m0, nm, lmi = f[:8]
        size = f[-2:]
        tname, flags, _ = texs[tex]
        sh = shaders.get(tname)
        if flags & SURF_NODRAW or (sh and sh.nodraw) or kind == 4:
            continue
        if flags & SURF_SKY or (sh and sh.sky):
            continue  # the sky: rays that leave the level see the scene's sky colour
        if kind in (1, 3):
            a = verts[v0:v0 + nv]
            t = meshverts[m0:m0 + nm].reshape(-1, 3)
        elif kind == 2:
            w, h = size
            if w < 3 or h < 3 or w * h != nv:
                continue
            a, t = _bezier_patch(verts[v0:v0 + nv], w, h, patch_level)
        else:
            continue
        attrs.append(a)
        tris.append(t + base)
        base += len(a)
        ftex += [tex] * len(t)
        flm += [lmi if 0 <= lmi < n_lightmaps else -1] * len(t)
        fmod += [face_model[fi]] * len(t)
    if not attrs:
        raise ValueError(f"bsp: {name} has no drawable faces")
    # winding is kept as stored: shading uses the vertex normals, turned to the viewer
    return np.concatenate(attrs), np.concatenate(tris).astype(np.int32), ftex, flm, fmod


def _spawns(ents):
    """Camera starts: the player spawn points at eye height, with their yaw."""
    spawns = []
    for e in ents:
        cls = e.get("classname", "").lower()
        if "origin" in e and (cls.startswith("info_player") or cls.startswith("team_ctf_")
                              and ("spawn" in cls or "player" in cls)):
            o = np.array([float(x) for x in e["origin"].split()[:3]])
            o[2] += 26.0  # the player's eye above the entity origin
            yaw = np.radians(float(e.get("angle", 0.0)))
            spawns.append((to_jtus(o), yaw))
    return spawns


def _movers(ents, models):
    """Brush models that entities move: ``{model: entity keys + class, mins, maxs}``."""
    movers = {}
    for e in ents:
        if e.get("classname") in _MOVERS and e.get("model", "").startswith("*"):
            k = int(e["model"][1:])
            if 0 < k < len(models):
                movers[k] = dict(e, **{"class": e["classname"],
                                       "mins": to_jtus(models[k][0:3]),
                                       "maxs": to_jtus(models[k][3:6])})
    return movers


def decode_lightmaps(lm):
    """Quake's overbright sRGB-coded light (lightmaps or vertex colours, in [0,1]) as
    linear light (x2 overbright, then decoded; values past 1 stay: bright is bright)."""
    return srgb_to_linear(np.asarray(lm, np.float32) * 2.0)


class Archive:
    """The files of one or more ``.pk3`` archives, later ones overriding earlier ones
    (as the engine loads them in name order)."""

    def __init__(self, paths):
        self.files = {}
        for p in sorted(Path(x) for x in paths):
            z = zipfile.ZipFile(p)
            for n in z.namelist():
                self.files[n.lower()] = (z, n)
        if not self.files:
            raise ValueError(f"pk3: no files in {list(paths)}")

    def read(self, name):
        z, n = self.files[name.lower()]
        return z.read(n)

    def __contains__(self, name):
        return name.lower() in self.files

    def names(self, prefix="", suffix=""):
        return sorted(n for n in self.files if n.startswith(prefix) and n.endswith(suffix))

    def shaders(self):
        out = {}
        for n in self.names("scripts/", ".shader"):
            out.update(parse_shaders(self.read(n).decode("latin-1")))
        return out

    def image(self, name):
        """The RGBA image (``[H,W,4]`` uint8) at archive path ``name``, trying the
        other extensions Quake accepts; None when there is none."""
        stem = re.sub(r"\.(tga|jpg|jpeg|png)$", "", name.lower())
        for ext in (".tga", ".jpg", ".png", ".jpeg"):
            if stem + ext in self:
                with Image.open(io.BytesIO(self.read(stem + ext))) as im:
                    return np.asarray(im.convert("RGBA"))
        return None

    def level(self, map_name, patch_level=6):
        path = f"maps/{map_name}.bsp"
        if path not in self:
            maps = [n[5:-4] for n in self.names("maps/", ".bsp")]
            raise ValueError(f"map: expected one of {maps}, got {map_name!r}")
        return load_level(self.read(path), map_name, self.shaders(), patch_level)
