"""A user's own mesh files (glTF 2.0 ``.gltf``/``.glb``, Wavefront ``.obj``) as mesh
scenes, read with trimesh.

Every mesh node becomes triangles in world space with its UVs, normals and material:
the base-colour image (or factor, or an OBJ material's diffuse image or colour), glTF's
``alphaMode`` ``MASK`` (an alpha-tested cutout at ``alphaCutoff``) or ``BLEND`` (an
alpha-blended layer). The scene is lit by a sun and ambient light. Cameras start at
the file's camera, if it has one, and on a ring inside the scene's bounds at eye
height, looking across it. A glTF file's first animation moves its nodes rigidly
(translation and rotation channels, linear, slerp or step, looped over the last key):
each animated node's triangles become a part with a ``mesh.Keyframes`` motion, so the
motion vectors follow the animation exactly; without ``object_motion`` declared the
nodes stay at their rest pose. Refused with a clear error: scale or morph-target
channels, cubic-spline keys, an animated node under another animated node, or under a
non-uniformly scaled parent (none of which is a rigid motion). Not read yet: normal
and roughness maps.

Conventions converted here: glTF and OBJ are y-up and right-handed like jtus (metres
assumed for OBJ); trimesh gives texture coordinates with v up from the image's bottom
row, jtus samples with v down from the top (``v -> 1 - v``); images are sRGB-encoded
and decoded to linear.
"""

from __future__ import annotations

import base64
import json
import struct
from pathlib import Path

import numpy as np

from jtus.sim.mesh import (Keyframes, Material, MeshScene, Motion, Part, mip_pyramid, quat_matrix,
                           srgb_to_linear)

SUFFIXES = (".gltf", ".glb", ".obj")


def _image(material):
    """Linear RGBA ``[H,W,4]`` of a trimesh material (its texture, else its colour)."""
    img, color = None, None
    if material is not None:
        img = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
        c = getattr(material, "baseColorFactor", None)
        if c is None:
            c = getattr(material, "diffuse", None)
        if c is not None:
            c = np.asarray(c, np.float64).ravel()
            color = tuple((c / 255.0 if c.max() > 1 else c)[:4]) + (1.0,) * (4 - len(c[:4]))
    if color is None:  # glTF's default factor is 1 over a texture; untextured: grey
        color = (1.0, 1.0, 1.0, 1.0) if img is not None else (0.7, 0.7, 0.7, 1.0)
    if img is not None:
        x = np.asarray(img.convert("RGBA"), np.float32) / 255.0
        x[..., :3] = srgb_to_linear(x[..., :3])
        x = x * np.asarray(color, np.float32)[None, None]
    else:
        x = np.empty((2, 2, 4), np.float32)
        x[...] = np.asarray(color, np.float32)
        x[..., :3] = srgb_to_linear(x[..., :3])
    return x


def _ring(lo, hi):
    """Camera starts: 8 points on a ring inside the bounds at eye height (at most 1.6 m
    above the lowest point), each looking at the centre."""
    center, extent = (lo + hi) / 2, hi - lo
    spawns = []
    for a in np.linspace(0, 2 * np.pi, 8, endpoint=False):
        eye = center + 0.35 * np.array([extent[0] * np.cos(a), 0.0, extent[2] * np.sin(a)])
        eye[1] = lo[1] + min(1.6, 0.5 * extent[1] + 0.1)
        to_c = center - eye
        spawns.append((eye, float(np.arctan2(-to_c[2], to_c[0]))))
    return spawns


def _camera(scene):
    """The file's own camera as a start (none when it has none): glTF cameras look
    along their -z."""
    if not scene.has_camera:
        return []
    pose = np.asarray(scene.camera_transform, float)
    fwd = -pose[:3, 2]
    return [(pose[:3, 3].copy(), float(np.arctan2(-fwd[2], fwd[0])))]


def _material(material, fallback):
    """A jtus ``Material`` of a trimesh material: its image and alpha mode."""
    mode = str(getattr(material, "alphaMode", "OPAQUE") or "OPAQUE").upper()
    cutoff = getattr(material, "alphaCutoff", None)
    return Material(mip_pyramid(_image(material)), blend="blend" if mode == "BLEND" else "opaque",
                    alpha_test=float(cutoff if cutoff is not None else 0.5)
                    if mode == "MASK" else 0.0,
                    name=str(getattr(material, "name", "") or fallback))


def _gltf(path):
    """``(header, [buffer bytes])`` of a ``.gltf`` or ``.glb`` file."""
    raw = path.read_bytes()
    if path.suffix.lower() == ".glb":
        if raw[:4] != b"glTF" or len(raw) < 20:
            raise ValueError(f"scene: {path} is not a binary glTF file")
        n = struct.unpack_from("<I", raw, 12)[0]
        header = json.loads(raw[20:20 + n])
        rest = raw[20 + n:]
        blobs = [rest[8:8 + struct.unpack_from("<I", rest, 0)[0]]] if len(rest) >= 8 else []
    else:
        header, blobs = json.loads(raw), []
    buffers = []
    for i, b in enumerate(header.get("buffers", [])):
        uri = b.get("uri")
        if uri is None:
            buffers.append(blobs[0] if blobs else b"")
        elif uri.startswith("data:"):
            buffers.append(base64.b64decode(uri.split(",", 1)[1]))
        else:
            buffers.append((path.parent / uri).read_bytes())
    return header, buffers


_WIDTH = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}


def _accessor(header, buffers, index, where):
    """A float accessor as ``[count, width]`` float64."""
    acc = header["accessors"][index]
    if acc.get("componentType") != 5126 or acc.get("type") not in _WIDTH:
        raise ValueError(f"{where}: expected float SCALAR/VEC3/VEC4 keys, got componentType "
                         f"{acc.get('componentType')} {acc.get('type')}")
    width, count = _WIDTH[acc["type"]], acc["count"]
    view = header["bufferViews"][acc["bufferView"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    stride = view.get("byteStride", 4 * width)
    data = buffers[view["buffer"]]
    out = np.array([struct.unpack_from(f"<{width}f", data, start + k * stride)
                    for k in range(count)], np.float64)
    if not np.isfinite(out).all():
        raise ValueError(f"{where}: NaN or Inf among the keys")
    return out


def _animations(path, header, buffers):
    """``{glTF node index: {"times", "translation", "rotation", "step"}}`` of the file's
    first animation."""
    anims = header.get("animations") or []
    if not anims:
        return {}
    anim, out = anims[0], {}
    for c, ch in enumerate(anim.get("channels", [])):
        where = f"scene: {path}: animation 0, channel {c}"
        target = ch.get("target", {})
        prop, node = target.get("path"), target.get("node")
        if prop not in ("translation", "rotation"):
            raise ValueError(f"{where}: a {prop} channel is not a rigid motion; expected "
                             "translation or rotation")
        sampler = anim["samplers"][ch["sampler"]]
        interp = sampler.get("interpolation", "LINEAR")
        if interp not in ("LINEAR", "STEP"):
            raise ValueError(f"{where}: {interp} keys; expected LINEAR or STEP")
        times = _accessor(header, buffers, sampler["input"], where)[:, 0]
        values = _accessor(header, buffers, sampler["output"], where)
        if len(times) < 1 or (np.diff(times) <= 0).any() or len(values) != len(times):
            raise ValueError(f"{where}: expected increasing key times, one value each")
        rec = out.setdefault(node, {"times": times, "step": interp == "STEP"})
        if len(rec["times"]) != len(times) or not np.allclose(rec["times"], times):
            raise ValueError(f"{where}: node {node}'s channels have different key times")
        if prop == "rotation":
            values = values / np.linalg.norm(values, axis=-1, keepdims=True)
        rec[prop] = values
    return out


def _node_names(header):
    """glTF node index -> the frame name trimesh gives it."""
    from trimesh.util import unique_name  # lazy: the optional [mesh] extra
    index, counts = {}, {}
    for i, n in enumerate(header.get("nodes", [])):
        index[unique_name(n.get("name", str(i)), index, counts=counts)] = i
    return {v: k for k, v in index.items()}


def _keyframes(header, node, rec, parent, where):
    """The ``Keyframes`` motion of glTF node ``node`` under world transform ``parent``."""
    lin = parent[:3, :3]
    sv = np.linalg.svd(lin, compute_uv=False)
    if sv.max() - sv.min() > 1e-6 * max(sv.max(), 1e-12):
        raise ValueError(f"{where}: the animated node sits under a non-uniformly scaled "
                         "parent; its motion would not be rigid")
    n = header["nodes"][node]
    if "matrix" in n:
        raise ValueError(f"{where}: an animated node must be given by translation, rotation "
                         "and scale, not a matrix (glTF 2.0, 5.25)")
    t0 = np.asarray(n.get("translation", (0, 0, 0)), float)
    r0 = np.asarray(n.get("rotation", (0, 0, 0, 1)), float)
    rest = np.eye(4)
    rest[:3, :3], rest[:3, 3] = quat_matrix(r0 / np.linalg.norm(r0)), t0
    return Keyframes(times=rec["times"], translations=rec.get("translation"),
                     rotations=rec.get("rotation"), rest_t=t0, rest_r=r0 / np.linalg.norm(r0),
                     before=parent, after=np.linalg.inv(rest) @ np.linalg.inv(parent),
                     step=rec["step"])


def _geometry(scene, trimesh, mover):
    """``({moving node or None: triangle lists}, [Material])``: every mesh node's
    triangles in world space (its rest pose), grouped by the animated node that moves
    them (``mover``)."""
    groups, mats, seen = {}, [], {}
    for node in scene.graph.nodes_geometry:
        transform, geom = scene.graph[node]
        g = scene.geometry[geom]
        if not isinstance(g, trimesh.Trimesh) or not len(g.faces):
            continue
        v = trimesh.transform_points(g.vertices, transform)
        n = g.vertex_normals @ transform[:3, :3].T
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
        vis = g.visual
        uv = getattr(vis, "uv", None)
        uv = np.zeros((len(v), 2)) if uv is None else np.asarray(uv, np.float64)
        uv = np.stack([uv[:, 0], 1.0 - uv[:, 1]], -1)
        material = getattr(vis, "material", None)
        key = id(material)
        if key not in seen:
            seen[key] = len(mats)
            mats.append(_material(material, geom))
        grp = groups.setdefault(mover(node), {"p": [], "n": [], "uv": [], "f": [], "m": []})
        grp["f"].append(np.asarray(g.faces) + sum(len(x) for x in grp["p"]))
        grp["p"].append(v)
        grp["n"].append(n)
        grp["uv"].append(uv)
        grp["m"].append(np.full(len(g.faces), seen[key]))
    return groups, mats




def _mover(node, animated, parents, path):
    """The animated node that moves ``node`` (itself or an ancestor), or None."""
    found, cur = None, node
    while cur is not None:
        if cur in animated:
            if found is not None:
                raise ValueError(f"scene: {path}: node {found!r} is animated under the "
                                 f"animated node {cur!r}; nested animations are not read")
            found = cur
        cur = parents.get(cur)
    return found


def load(path, effects=None, name=None, sun=(-0.4, -1.0, -0.3)):
    """The mesh file ``path`` as a ``MeshScene`` declaring ``effects`` (default:
    ``camera_motion``, plus ``object_motion`` when the file is animated)."""
    try:
        import trimesh  # lazy: the optional [mesh] extra
    except ImportError as e:
        raise ImportError("mesh files are read with trimesh: pip install -e '.[mesh]'") from e

    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise ValueError(f"scene: expected a {'/'.join(SUFFIXES)} file, got {path}")
    if not path.is_file():
        raise FileNotFoundError(f"scene: {path} does not exist")
    try:
        scene = trimesh.load(str(path), force="scene")
    except Exception as e:  # trimesh raises many kinds for a broken file
        raise ValueError(f"scene: {path} could not be read as a mesh ({e})") from e
    header, buffers = _gltf(path) if path.suffix.lower() != ".obj" else ({}, [])
    anim = _animations(path, header, buffers)
    names = _node_names(header) if anim else {}
    animated = {names[i]: i for i in anim}
    if effects is None:
        effects = ("camera_motion",) + (("object_motion",) if anim else ())
    parents = scene.graph.transforms.parents
    groups, mats = _geometry(scene, trimesh, lambda node: _mover(node, animated, parents, path))
    if not groups:
        raise ValueError(f"scene: {path} holds no triangles")
    parts = []
    for key, grp in groups.items():
        pos = np.concatenate(grp["p"])
        if not np.isfinite(pos).all():
            raise ValueError(f"scene: {path} has NaN or Inf vertex positions")
        motion = Motion()
        if key is not None:
            parent = scene.graph.get(frame_to=parents[key], frame_from=scene.graph.base_frame)[0]
            motion = _keyframes(header, animated[key], anim[animated[key]], parent,
                                f"scene: {path}: node {key!r}")
        parts.append(Part(position=pos, faces=np.concatenate(grp["f"]).astype(np.int64),
                          uv=np.concatenate(grp["uv"]).astype(np.float32),
                          normal=np.concatenate(grp["n"]).astype(np.float32),
                          face_material=np.concatenate(grp["m"]).astype(np.int64),
                          light=np.ones((len(pos), 3), np.float32), motion=motion))
    pos = np.concatenate([p.position for p in parts])
    lo, hi = pos.min(0), pos.max(0)
    extent = hi - lo
    if not extent.max() > 0:
        raise ValueError(f"scene: {path} has no extent (all vertices at one point)")
    return MeshScene(name=name or path.stem, effects=tuple(effects), parts=parts,
                     materials=mats, spawns=_camera(scene) + _ring(lo, hi), sun=tuple(sun),
                     speed=max(0.02, 0.004 * float(extent.max())))
