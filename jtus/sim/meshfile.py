"""A user's own mesh files (glTF 2.0 ``.gltf``/``.glb``, Wavefront ``.obj``) as mesh
scenes, read with trimesh.

Every mesh node becomes triangles in world space with its UVs, normals and material:
the base-colour image (or factor, or an OBJ material's diffuse image or colour), glTF's
``alphaMode`` ``MASK`` (an alpha-tested cutout at ``alphaCutoff``) or ``BLEND`` (an
alpha-blended layer). The scene is lit by a sun and ambient light. Cameras start at
the file's camera, if it has one, and on a ring inside the scene's bounds at eye
height, looking across it. Not read yet: glTF animations, normal and roughness maps.

Conventions converted here: glTF and OBJ are y-up and right-handed like jtus (metres
assumed for OBJ); trimesh gives texture coordinates with v up from the image's bottom
row, jtus samples with v down from the top (``v -> 1 - v``); images are sRGB-encoded
and decoded to linear.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jtus.sim.mesh import Material, MeshScene, Part, mip_pyramid, srgb_to_linear

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


def load(path, effects=("camera_motion",), name=None, sun=(-0.4, -1.0, -0.3)):
    """The mesh file ``path`` as a ``MeshScene`` declaring ``effects``."""
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
    positions, normals, uvs, faces, fmat, mats, seen = [], [], [], [], [], [], {}
    base = 0
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
        positions.append(v)
        normals.append(n)
        uvs.append(uv)
        faces.append(np.asarray(g.faces) + base)
        fmat.append(np.full(len(g.faces), seen[key]))
        base += len(v)
    if not positions:
        raise ValueError(f"scene: {path} holds no triangles")
    pos = np.concatenate(positions)
    if not np.isfinite(pos).all():
        raise ValueError(f"scene: {path} has NaN or Inf vertex positions")
    part = Part(position=pos, faces=np.concatenate(faces).astype(np.int64),
                uv=np.concatenate(uvs).astype(np.float32),
                normal=np.concatenate(normals).astype(np.float32),
                face_material=np.concatenate(fmat).astype(np.int64),
                light=np.ones((len(pos), 3), np.float32))
    lo, hi = pos.min(0), pos.max(0)
    extent = hi - lo
    if not extent.max() > 0:
        raise ValueError(f"scene: {path} has no extent (all vertices at one point)")
    return MeshScene(name=name or path.stem, effects=tuple(effects), parts=[part],
                     materials=mats, spawns=_camera(scene) + _ring(lo, hi), sun=tuple(sun),
                     speed=max(0.02, 0.004 * float(extent.max())))
