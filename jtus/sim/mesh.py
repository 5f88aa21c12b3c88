"""Triangle-mesh scenes with image textures, ray cast with Embree (``embreex``).

A ``MeshScene`` holds parts (triangle meshes, each with a rigid motion), materials
(mip-mapped images with optional alpha test, blending, scrolling and flicker), baked
lighting (Quake lightmaps or vertex colours) or a sun, and the places a camera may
start. ``MeshRenderer`` gives what ``jtus.sim.render`` gives for analytic scenes:
``cast(state, xy, pixel_angle)`` returns colour, device depth and exact backward
motion for any screen points, so ``jtus.sim.video.VideoRenderer`` renders jittered
inputs and supersampled targets of mesh scenes the same way.

What is computed follows the scene's ``effects`` (``MESH_EFFECTS``): surfaces whose
material needs an undeclared effect are not there (an alpha-tested fence without
``alpha_cutout``, an additive glow without ``transparency``), scroll and flicker stand
still without ``scrolling_texture`` / ``emissive_flicker``, brush models stay at rest
without ``object_motion``, no light moves or casts shadow rays without
``moving_light``, no highlight is traced without ``specular``.

Why Embree through ``embreex`` rather than Mitsuba 3 (which renders the independent
clips): ``experiments/mesh_engine.py`` measures both on the same triangles; Mitsuba's
vectorized (LLVM) variant casts rays faster here but needs the system's LLVM library,
which no ``pip install`` brings, while its scalar variant casts one ray per Python call.
``embreex`` ships Embree inside its wheel. Either way only visibility comes from the
engine: shading, motion and depth are computed here from the hit's triangle and
barycentrics, so motion vectors are exact by construction (``tests/test_mesh.py``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jtus.data.conventions import FAR, NEAR, depth_to_device
from jtus.sim.paths import Camera

MESH_EFFECTS = ("camera_motion", "camera_cut", "object_motion", "alpha_cutout",
                "transparency", "scrolling_texture", "emissive_flicker", "moving_light",
                "specular", "hdr")
FPS = 30.0
_EPS = 1e-3  # metres a continued ray starts past the surface it went through


def srgb_to_linear(x):
    x = np.asarray(x, np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def mip_pyramid(rgba):
    """Box-filtered mip levels of a linear ``[H,W,C]`` image, down to 1x1 (odd sizes
    drop their last row or column before halving)."""
    levels = [np.asarray(rgba, np.float32)]
    while max(levels[-1].shape[:2]) > 1:
        a = levels[-1]
        h, w = max(a.shape[0] // 2, 1), max(a.shape[1] // 2, 1)
        a = a[:2 * h if a.shape[0] > 1 else 1, :2 * w if a.shape[1] > 1 else 1]
        a = a.reshape(h, a.shape[0] // h, w, a.shape[1] // w, -1).mean((1, 3))
        levels.append(a.astype(np.float32))
    return levels


def _bilinear(img, u, v):
    """Wrapped bilinear lookup of ``img [H,W,C]`` at texture coordinates (u right, v
    down, 1 = one image across; texel centres at (i + 0.5) / size)."""
    h, w = img.shape[:2]
    x = u * w - 0.5
    y = v * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0 = x0.astype(np.int64) % w
    y0 = y0.astype(np.int64) % h
    x1, y1 = (x0 + 1) % w, (y0 + 1) % h
    return ((img[y0, x0] * (1 - fx) + img[y0, x1] * fx) * (1 - fy)
            + (img[y1, x0] * (1 - fx) + img[y1, x1] * fx) * fy)


def sample(levels, u, v, lod):
    """Trilinear lookup in a mip pyramid at level ``lod`` (clamped to the pyramid)."""
    lod = np.clip(np.nan_to_num(lod, nan=0.0), 0, len(levels) - 1)
    lo = np.floor(lod).astype(np.int64)
    out = np.zeros((len(u), levels[0].shape[-1]), np.float32)
    for k in np.unique(lo):
        m = lo == k
        a = _bilinear(levels[k], u[m], v[m])
        if k + 1 < len(levels):
            f = (lod[m] - k)[:, None]
            a = a * (1 - f) + _bilinear(levels[k + 1], u[m], v[m]) * f
        out[m] = a
    return out


@dataclasses.dataclass
class Material:
    """``levels``: the mip pyramid of linear RGBA; ``blend``: opaque | add | blend |
    filter; ``alpha_test``: keep texels with alpha >= this (0: none); ``scroll``: texture
    units per second; ``wave``: (base, amplitude, phase, Hz) of a sine flicker;
    ``lit``: multiplied by the baked light (else shown as it is, as a light fixture)."""
    levels: list
    blend: str = "opaque"
    alpha_test: float = 0.0
    scroll: tuple = (0.0, 0.0)
    wave: tuple = ()
    lit: bool = True
    name: str = ""

    def needs(self):
        """The effect without which this material's surfaces are not drawn (or None)."""
        if self.blend != "opaque":
            return "transparency"
        if self.alpha_test > 0:
            return "alpha_cutout"
        return None


@dataclasses.dataclass
class Motion:
    """A rigid motion over time: ``kind`` static | slide | bob | rotate | swing.
    ``axis``: unit vector (direction of travel, or rotation axis); ``amount``: metres
    (slide, bob) or radians (swing amplitude); ``period``: seconds of one cycle (rotate:
    one turn); ``pivot``: a point on the rotation axis."""
    kind: str = "static"
    axis: tuple = (0.0, 1.0, 0.0)
    amount: float = 0.0
    period: float = 4.0
    pivot: tuple = (0.0, 0.0, 0.0)

    def pose(self, seconds):
        """``(R [3,3], t [3])``: a rest-space point p is at ``R (p - pivot) + pivot + t``."""
        a = np.asarray(self.axis, float)
        w = 2 * np.pi * seconds / self.period
        if self.kind == "slide":   # opens, holds, closes: a door's cycle
            s = np.clip(1.5 * (0.5 - 0.5 * np.cos(w)) - 0.25, 0, 1)
            return np.eye(3), a * self.amount * s
        if self.kind == "bob":
            return np.eye(3), a * self.amount * np.sin(w)
        if self.kind in ("rotate", "swing"):
            ang = w if self.kind == "rotate" else self.amount * np.sin(w)
            k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
            r = np.eye(3) + np.sin(ang) * k + (1 - np.cos(ang)) * (k @ k)
            return r, np.zeros(3)
        return np.eye(3), np.zeros(3)


def _slerp(q0, q1, u):
    """Unit quaternions (x, y, z, w) interpolated along the shorter arc."""
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + u * (q1 - q0)
    else:
        a = np.arccos(d)
        q = (np.sin((1 - u) * a) * q0 + np.sin(u * a) * q1) / np.sin(a)
    return q / np.linalg.norm(q)


def quat_matrix(q):
    """The rotation matrix of a unit quaternion (x, y, z, w), glTF's order."""
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@dataclasses.dataclass
class Keyframes:
    """A rigid motion from keyframes (a glTF node's animation), looping over its last
    key time. The node's translation ``T(s)`` and rotation ``R(s)`` (linear and slerp
    between keys, or held with ``step``) act between two fixed transforms: a rest-space
    point p is at ``before @ [T(s) R(s)] @ after @ p`` (4x4, homogeneous), where
    ``after`` takes the rest pose back into the node's frame and ``before`` is the
    node's parent frame. ``translations`` / ``rotations``: ``[K,3]`` / ``[K,4]``
    (x, y, z, w), or None where the node keeps its rest value (``rest_t``, ``rest_r``)."""
    times: np.ndarray
    translations: np.ndarray | None
    rotations: np.ndarray | None
    rest_t: np.ndarray
    rest_r: np.ndarray
    before: np.ndarray
    after: np.ndarray
    step: bool = False
    kind: str = "keyframes"
    pivot: tuple = (0.0, 0.0, 0.0)

    def _at(self, seconds):
        """Index of the key before ``seconds`` (looped) and the fraction past it."""
        t = np.asarray(self.times, float)
        span = t[-1]
        s = (seconds % span) if span > 0 else 0.0
        i = int(np.clip(np.searchsorted(t, s, side="right") - 1, 0, len(t) - 1))
        if i == len(t) - 1 or self.step:
            return i, 0.0
        return i, float((s - t[i]) / (t[i + 1] - t[i]))

    def pose(self, seconds):
        i, u = self._at(seconds)
        j = min(i + 1, len(self.times) - 1)
        tr = self.rest_t if self.translations is None else \
            (1 - u) * self.translations[i] + u * self.translations[j]
        q = self.rest_r if self.rotations is None else \
            _slerp(np.asarray(self.rotations[i], float), np.asarray(self.rotations[j], float), u)
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = quat_matrix(q), tr
        g = self.before @ m @ self.after
        return g[:3, :3], g[:3, 3]


@dataclasses.dataclass
class Part:
    """One rigidly moving triangle mesh (rest-space positions)."""
    position: np.ndarray      # [V,3]
    faces: np.ndarray         # [F,3]
    uv: np.ndarray            # [V,2]
    normal: np.ndarray        # [V,3]
    face_material: np.ndarray  # [F]
    light: np.ndarray         # [V,3] baked light per vertex (used where no lightmap)
    lm_uv: np.ndarray = None  # [V,2]
    face_lightmap: np.ndarray = None  # [F], -1 where none
    motion: Motion = dataclasses.field(default_factory=Motion)


@dataclasses.dataclass
class MeshScene:
    """A scene of triangle meshes; see the module docstring. ``spawns``: camera
    starts ``[(eye [3], yaw radians about +y, 0 = looking along +x)]``."""
    name: str
    effects: tuple
    parts: list
    materials: list
    spawns: list
    lightmaps: np.ndarray = None     # [K,h,w,3] linear light
    sun: tuple = ()                  # direction light travels, when lit by a sun
    ambient: float = 0.3
    sky: tuple = ((0.6, 0.65, 0.75), (0.25, 0.35, 0.6))  # horizon, zenith
    near: float = NEAR
    far: float = FAR
    fov_y: float = 1.2
    speed: float = 0.08              # metres per frame of a walk (x3 in flight)
    highlight_gain: float = 8.0
    exposure_stops: float = 0.0

    def __post_init__(self):
        bad = [e for e in self.effects if e not in MESH_EFFECTS]
        if bad:
            raise ValueError(f"effects: unknown {bad}; expected a subset of {MESH_EFFECTS}")
        if not self.parts or not any(len(p.faces) for p in self.parts):
            raise ValueError(f"{self.name}: expected at least one triangle")
        if not self.spawns:
            raise ValueError(f"{self.name}: expected at least one camera start (spawn)")
        for i, p in enumerate(self.parts):
            if not np.isfinite(p.position).all():
                raise ValueError(f"{self.name}: parts[{i}].position holds NaN or Inf")
            if len(p.faces) and (p.faces.min() < 0 or p.faces.max() >= len(p.position)):
                raise ValueError(f"{self.name}: parts[{i}].faces index past its vertices")

    def has(self, effect):
        return effect in self.effects


@dataclasses.dataclass
class FrameState:
    """One frame of a mesh video: cameras, part poses now and one frame before,
    the time in seconds, the moving light, whether a cut starts here."""
    camera: Camera
    prev_camera: Camera
    poses: list
    prev_poses: list
    seconds: float
    light: np.ndarray
    cut: bool = False
    exposure: float = 1.0


def _face_frames(part: Part, mats):
    """Per face: texels per metre of its material's base image (for the mip level)."""
    v = part.position[part.faces]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=-1)
    t = part.uv[part.faces].astype(np.float64)
    uva = 0.5 * np.abs((t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1])
                       - (t[:, 2, 0] - t[:, 0, 0]) * (t[:, 1, 1] - t[:, 0, 1]))
    texels = np.array([m.levels[0].shape[0] * m.levels[0].shape[1] for m in mats], float)
    return np.sqrt(uva * texels[part.face_material] / np.maximum(area, 1e-12))


class MeshRenderer:
    """Casts screen points through a ``MeshScene`` (one Embree scene per part)."""

    def __init__(self, scene: MeshScene):
        try:
            from embreex import rtcore_scene as rtcs  # lazy: the optional [mesh] extra
            from embreex.mesh_construction import TriangleMesh  # lazy: likewise
        except ImportError as e:
            raise ImportError("mesh scenes are ray cast with Embree: pip install -e "
                              "'.[mesh]' (embreex, trimesh)") from e

        self.scene = scene
        drawn = np.array([m.needs() is None or scene.has(m.needs()) for m in scene.materials])
        self.parts, self.bvh, self.density = [], [], []
        for p in scene.parts:
            keep = drawn[p.face_material]
            if not keep.any():
                continue
            q = dataclasses.replace(p, faces=p.faces[keep], face_material=p.face_material[keep],
                                    face_lightmap=None if p.face_lightmap is None
                                    else p.face_lightmap[keep])
            s = rtcs.EmbreeScene()
            TriangleMesh(s, q.position[q.faces].astype(np.float32))
            self.parts.append(q)
            self.bvh.append(s)
            self.density.append(_face_frames(q, scene.materials))
        codes = {"opaque": 0, "add": 1, "blend": 2, "filter": 3}
        mats = scene.materials
        self.mat_blend = np.array([codes[m.blend] for m in mats], np.int64)
        self.mat_test = np.array([m.alpha_test for m in mats], np.float32)
        self.mat_pass = (self.mat_blend != 0) | (self.mat_test > 0)
        self.mat_lit = np.array([m.lit for m in mats], bool)

    def _face_material(self, part, face):
        out = np.zeros(len(face), np.int64)
        for k in np.unique(part):
            m = part == k
            out[m] = self.parts[k].face_material[face[m]]
        return out

    # -- visibility -----------------------------------------------------------------
    def _into_rest(self, k, o, d, pose):
        """Rays ``(o, d)`` in part ``k``'s rest space under ``pose`` (float32, as Embree
        takes them): ``R^T (o - pivot - t) + pivot``, ``R^T d``."""
        r, tr = pose
        pv = np.asarray(self.parts[k].motion.pivot, float)
        return ((o - pv - tr) @ r + pv).astype(np.float32), (d @ r).astype(np.float32)

    def _from_rest(self, k, p, pose):
        """Rest-space points ``p`` of part ``k`` in the world under ``pose``."""
        r, tr = pose
        pv = np.asarray(self.parts[k].motion.pivot, float)
        return (p - pv) @ r.T + pv + tr

    def nearest(self, o, d, poses):
        """Nearest hit over all parts: t [N] (inf: none), part [N], face [N], bary [N,2]."""
        n = len(o)
        best = np.full(n, np.inf)
        part = np.zeros(n, np.int64)
        face = np.zeros(n, np.int64)
        bary = np.zeros((n, 2), np.float32)
        for k, (bvh, pose) in enumerate(zip(self.bvh, poses)):
            res = bvh.run(*self._into_rest(k, o, d, pose), output=1)
            hit = res["primID"] >= 0
            t = np.where(hit, res["tfar"], np.inf)
            better = t < best
            best = np.where(better, t, best)
            part[better] = k
            face[better] = res["primID"][better]
            bary[better] = np.stack([res["u"], res["v"]], -1)[better]
        return best, part, face, bary

    def _occluded(self, o, d, dist, poses):
        out = np.zeros(len(o), bool)
        for k, (bvh, pose) in enumerate(zip(self.bvh, poses)):
            res = bvh.run(*self._into_rest(k, o, d, pose), dists=dist.astype(np.float32))
            out |= np.asarray(res) != -1
        return out

    def _attributes(self, part, face, bary, poses):
        """Interpolated attributes of hits (rest space) and their world normals."""
        out = {"p_rest": np.zeros((len(face), 3)), "uv": np.zeros((len(face), 2)),
               "n": np.zeros((len(face), 3)), "light": np.zeros((len(face), 3)),
               "lm_uv": np.zeros((len(face), 2)), "lm": np.full(len(face), -1),
               "mat": np.zeros(len(face), np.int64), "density": np.zeros(len(face))}
        w = np.stack([1 - bary[:, 0] - bary[:, 1], bary[:, 0], bary[:, 1]], -1)[..., None]
        for k in np.unique(part):
            m = part == k
            p, f = self.parts[k], face[m]
            tri = p.faces[f]
            out["p_rest"][m] = (p.position[tri] * w[m]).sum(1)
            out["uv"][m] = (p.uv[tri] * w[m]).sum(1)
            n = (p.normal[tri] * w[m]).sum(1)
            out["n"][m] = n @ poses[k][0].T
            out["light"][m] = (p.light[tri] * w[m]).sum(1)
            if p.lm_uv is not None:
                out["lm_uv"][m] = (p.lm_uv[tri] * w[m]).sum(1)
                out["lm"][m] = p.face_lightmap[f]
            out["mat"][m] = p.face_material[f]
            out["density"][m] = self.density[k][f]
        nn = np.linalg.norm(out["n"], axis=-1, keepdims=True)
        out["n"] = out["n"] / np.maximum(nn, 1e-9)
        return out

    def _texture(self, a, lod, seconds):
        """RGBA of each hit's material at its footprint's mip level."""
        rgba = np.zeros((len(lod), 4), np.float32)
        scroll = self.scene.has("scrolling_texture")
        for mi in np.unique(a["mat"]):
            m = a["mat"] == mi
            mat = self.scene.materials[mi]
            u, v = a["uv"][m, 0], a["uv"][m, 1]
            if scroll and mat.scroll != (0.0, 0.0):
                u = u + mat.scroll[0] * seconds
                v = v + mat.scroll[1] * seconds
            rgba[m] = sample(mat.levels, u, v, lod[m])
            if self.scene.has("emissive_flicker") and mat.wave:
                base, amp, phase, hz = mat.wave
                rgba[m, :3] *= np.clip(base + amp * np.sin(2 * np.pi * (phase + hz * seconds)),
                                       0, None)
        return rgba

    def _light(self, a, x, n, dn, state):
        """Light arriving at each hit: baked (lightmap or vertex light) or sun, plus the
        moving point light (shadowed) under ``moving_light``."""
        sc = self.scene
        light = a["light"].copy()
        if sc.lightmaps is not None:
            for li in np.unique(a["lm"][a["lm"] >= 0]):
                m = a["lm"] == li
                light[m] = _clamped_bilinear(sc.lightmaps[li], a["lm_uv"][m])
        if sc.sun:
            s = -np.asarray(sc.sun, float) / np.linalg.norm(sc.sun)
            light = light * (sc.ambient + np.maximum((n * s).sum(-1, keepdims=True), 0)
                             * (1 - sc.ambient))
        if sc.has("moving_light"):
            to_l = state.light[None] - x
            dist = np.linalg.norm(to_l, axis=-1)
            ldir = to_l / np.maximum(dist, 1e-9)[:, None]
            vis = ~self._occluded(x + 1e-3 * n, ldir, dist, state.poses)
            lamb = np.maximum((n * ldir).sum(-1), 0) * vis / (1 + dist * dist) * 6.0
            light = light + lamb[:, None] * np.array([1.0, 0.85, 0.6])
        return light

    def cast(self, state: FrameState, xy, pixel_angle):
        """Colour ``[N,3]``, device depth ``[N,1]``, backward motion ``[N,2]``
        (normalized units) of normalized screen points ``xy [N,2]``."""
        cam = state.camera
        xy = np.asarray(xy, np.float64)
        sx, sy = 2 * xy[:, 0:1] - 1, 1 - 2 * xy[:, 1:2]
        d = cam.forward + sx * cam.tan_half[0] * cam.right + sy * cam.tan_half[1] * cam.up
        dlen = np.linalg.norm(d, axis=-1)
        dn = d / dlen[:, None]
        n_pts = len(xy)
        o = np.broadcast_to(cam.eye, d.shape).astype(np.float64)
        t_total = np.zeros(n_pts)
        front = np.zeros((n_pts, 3))         # what transparent layers add in front
        trans = np.ones((n_pts, 3))          # and how much they let through
        active = np.arange(n_pts)
        final = {"t": np.full(n_pts, np.inf), "part": np.zeros(n_pts, np.int64),
                 "face": np.zeros(n_pts, np.int64), "bary": np.zeros((n_pts, 2), np.float32)}
        for _ in range(8):  # cutouts and layers a ray may pass through
            t, part, face, bary = self.nearest(o[active], d[active], state.poses)
            hit = np.isfinite(t)
            idx, t, part, face, bary = active[hit], t[hit], part[hit], face[hit], bary[hit]
            tt = t_total[idx] + t
            stop = np.ones(len(idx), bool)
            mat = self._face_material(part, face)
            sel = np.flatnonzero(self.mat_pass[mat])
            if len(sel):  # surfaces that may let the ray through: look at their texels
                rows = idx[sel]
                sub = self._attributes(part[sel], face[sel], bary[sel], state.poses)
                lod = _lod(tt[sel] * dlen[rows], sub["n"], dn[rows], sub["density"],
                           pixel_angle)
                rgba = self._texture(sub, lod, state.seconds)
                blend, test = self.mat_blend[mat[sel]], self.mat_test[mat[sel]]
                cut = (test > 0) & (rgba[:, 3] < test)
                add, bl, fi = (blend == 1) & ~cut, (blend == 2) & ~cut, (blend == 3) & ~cut
                front[rows[add]] += trans[rows[add]] * rgba[add, :3]
                al = rgba[bl, 3:4]
                front[rows[bl]] += trans[rows[bl]] * al * rgba[bl, :3]
                trans[rows[bl]] *= 1 - al
                trans[rows[fi]] *= rgba[fi, :3]
                stop[sel[cut | (blend != 0)]] = False
            done = idx[stop]
            final["t"][done] = tt[stop]
            final["part"][done] = part[stop]
            final["face"][done] = face[stop]
            final["bary"][done] = bary[stop]
            active = idx[~stop]
            t_cont = tt[~stop] + _EPS / dlen[active]
            o[active] = cam.eye + t_cont[:, None] * d[active]
            t_total[active] = t_cont
            if not len(active):
                break
        return self._shade(state, final, d, dn, dlen, xy, front, trans, pixel_angle)

    def _shade(self, state, final, d, dn, dlen, xy, front, trans, pixel_angle):
        sc = self.scene
        n_pts = len(xy)
        hit = np.isfinite(final["t"])
        horizon, zenith = (np.asarray(c, np.float32) for c in sc.sky)
        color = horizon + (zenith - horizon) * np.clip(dn[:, 1:2], 0.0, 1.0)
        depth = np.ones((n_pts, 1), np.float32)
        cam, prev = state.camera, state.prev_camera
        motion = _project(prev, dn, direction=True) - xy
        idx = np.flatnonzero(hit)
        if len(idx):
            a = self._attributes(final["part"][idx], final["face"][idx], final["bary"][idx],
                                 state.poses)
            t = final["t"][idx]
            x = cam.eye + t[:, None] * d[idx]
            n = a["n"]
            n = np.where((n * dn[idx]).sum(-1, keepdims=True) > 0, -n, n)
            lod = _lod(t * dlen[idx], n, dn[idx], a["density"], pixel_angle)
            rgba = self._texture(a, lod, state.seconds)
            lit = self.mat_lit[a["mat"]]
            light = self._light(a, x, n, dn[idx], state)
            c = rgba[:, :3] * np.where(lit[:, None], light, 1.0)
            if sc.has("specular"):
                c = c + self._highlight(rgba, x, n, dn[idx], state)
            color[idx] = c
            depth[idx, 0] = np.clip(depth_to_device(np.maximum(t, sc.near), "view", sc.near,
                                                    sc.far), 0, 1)
            # where the surface point was: move it back with its part, then project
            part = final["part"][idx]
            x_prev = np.empty_like(x)
            for k in np.unique(part):
                m = part == k
                x_prev[m] = self._from_rest(k, a["p_rest"][m], state.prev_poses[k])
            motion[idx] = _project(prev, x_prev) - xy[idx]
        color = front + trans * color
        hdr = sc.has("hdr")
        color = np.maximum(color, 0.0) if hdr else np.clip(color, 0.0, 1.0)
        return {"color": color.astype(np.float32), "depth": depth,
                "motion": motion.astype(np.float32)}

    def _highlight(self, rgba, x, n, dn, state):
        """A glossy Blinn-Phong highlight of the scene's light (the moving light, else
        a light at the camera) on a normal perturbed by the texture's luminance, a
        stand-in for a normal map: bright texels bulge out."""
        sc = self.scene
        lpos = state.light if sc.has("moving_light") else state.camera.eye
        ldir = lpos[None] - x
        ldir /= np.maximum(np.linalg.norm(ldir, axis=-1, keepdims=True), 1e-9)
        lum = rgba[:, :3] @ np.array([0.2126, 0.7152, 0.0722], np.float32)
        h = ldir - dn
        h /= np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-9)
        bump = n + 0.35 * (lum[:, None] - 0.3) * (h - (h * n).sum(-1, keepdims=True) * n)
        bump /= np.maximum(np.linalg.norm(bump, axis=-1, keepdims=True), 1e-9)
        lobe = np.maximum((bump * h).sum(-1), 0) ** 48 * np.clip(2 * lum, 0, 1)
        gain = sc.highlight_gain if sc.has("hdr") else 1.0
        return (0.6 * gain * lobe)[:, None] * np.array([1.0, 0.95, 0.9])


def _lod(dist, n, dn, density, pixel_angle):
    """Mip level of hits at distance ``dist`` along ``dn`` on surfaces with normal ``n``
    and ``density`` texels per metre: log2 of the footprint (the sample's angle times
    the distance, over the cosine, at most 4x stretched) in texels."""
    cos = np.maximum(np.abs((n * dn).sum(-1)), 0.25)
    return np.log2(np.maximum(dist * pixel_angle / cos * density, 1e-9))


def _clamped_bilinear(img, uv):
    h, w = img.shape[:2]
    x = np.clip(uv[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip(uv[:, 1] * h - 0.5, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 2 if w > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(np.int64), h - 2 if h > 1 else 0)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    return ((img[y0, x0] * (1 - fx) + img[y0, x1] * fx) * (1 - fy)
            + (img[y1, x0] * (1 - fx) + img[y1, x1] * fx) * fy)


def _project(cam: Camera, x, direction=False):
    """Normalized screen position of world points (or directions) under a camera."""
    q = x if direction else x - cam.eye
    z = np.maximum(q @ cam.forward, 1e-6)
    sx = (q @ cam.right) / (z * cam.tan_half[0])
    sy = (q @ cam.up) / (z * cam.tan_half[1])
    return np.stack([(sx + 1) / 2, (1 - sy) / 2], -1)

