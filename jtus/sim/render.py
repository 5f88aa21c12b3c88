"""A ray caster of analytic primitives, assembled from the effects a scene declares.

``make_renderer(scene)`` returns a jitted ``render(state, xy, pixel_angle)`` that casts
one ray per screen position ``xy [N,2]`` (normalized, x right and y down in [0,1]) and
returns linear RGB ``[N,3]``, device depth ``[N,1]`` and, with ``motion=True``, the
backward motion ``[N,2]`` in normalized screen units. Which code is traced is decided
by ``scene.effects`` at build time: no shadow rays without ``shadows``, no texture
filter without ``texture_detail``, no specular lobe without ``specular``, no per-object
previous poses without ``object_motion``, and so on. ``make_split_renderer(scene)``
gives the same work as two functions, colour and the hits first, depth and motion from
those hits second, so that the supersampled targets skip the second, and casts its
colour in bundles of ``BUNDLE`` rays: per bundle, objects whose bounding sphere no ray
can reach (``cone_keep``, ``capsule_keep``) and texture kinds no ray wears are skipped,
which changes no value (the ``intersect`` argument; docs/simulator.md, "Speed").

Camera: a pinhole looking along ``forward``; the ray through ``xy`` is
``forward + (2x-1) tan_x right + (1-2y) tan_y up``, so the ray parameter of a hit is
its view depth z, and device depth is D3D's ``far/(far-near) (1 - near/z)``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jtus.sim import textures
from jtus.sim.paths import FrameState, timeline
from jtus.sim.scene import TEXTURES, Scene

_EPS = 1e-4
_INF = jnp.inf
BUNDLE = 1024


def state_arrays(state: FrameState):
    """The jnp pytree the jitted renderer takes (everything but the cut flag)."""
    cam = lambda c: {k: jnp.asarray(v, jnp.float32) for k, v in c._asdict().items()}  # noqa: E731
    return {"camera": cam(state.camera), "prev_camera": cam(state.prev_camera),
            "obj_pos": jnp.asarray(state.obj_pos, jnp.float32),
            "obj_yaw": jnp.asarray(state.obj_yaw, jnp.float32),
            "prev_obj_pos": jnp.asarray(state.prev_obj_pos, jnp.float32),
            "prev_obj_yaw": jnp.asarray(state.prev_obj_yaw, jnp.float32),
            "light": jnp.asarray(state.light, jnp.float32),
            "emission": jnp.asarray(state.emission, jnp.float32)}


def _to_object(p, yaw):
    """World offset p [...,3] into object space for yaw [...]: R(yaw)^T p."""
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.stack([c * p[..., 0] - s * p[..., 2], p[..., 1], s * p[..., 0] + c * p[..., 2]], -1)


def _to_world(p, yaw):
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.stack([c * p[..., 0] + s * p[..., 2], p[..., 1], -s * p[..., 0] + c * p[..., 2]], -1)


def _safe(x):
    return jnp.where(jnp.abs(x) < 1e-12, 1e-12, x)


def _t_plane(o, d, size):
    t = -o[..., 1] / _safe(d[..., 1])
    x = o[..., 0] + t * d[..., 0]
    z = o[..., 2] + t * d[..., 2]
    ok = (t > _EPS) & (jnp.abs(x) <= size[..., 0]) & (jnp.abs(z) <= size[..., 2])
    return jnp.where(ok, t, _INF)


def _t_box(o, d, size):
    inv = 1.0 / _safe(d)
    t1, t2 = (-size - o) * inv, (size - o) * inv
    tmin = jnp.max(jnp.minimum(t1, t2), -1)
    tmax = jnp.min(jnp.maximum(t1, t2), -1)
    t = jnp.where(tmin > _EPS, tmin, tmax)
    return jnp.where((tmax >= tmin) & (t > _EPS), t, _INF)


def _quadratic(a, b, c):
    disc = b * b - a * c
    sq = jnp.sqrt(jnp.maximum(disc, 0.0))
    t0, t1 = (-b - sq) / _safe(a), (-b + sq) / _safe(a)
    t = jnp.where(t0 > _EPS, t0, t1)
    return jnp.where((disc >= 0) & (t > _EPS), t, _INF)


def _t_sphere(o, d, size):
    r = size[..., 0]
    return _quadratic((d * d).sum(-1), (o * d).sum(-1), (o * o).sum(-1) - r * r)


def _t_rod(o, d, size):
    r, hh = size[..., 0], size[..., 1]
    a = d[..., 0] ** 2 + d[..., 2] ** 2
    b = o[..., 0] * d[..., 0] + o[..., 2] * d[..., 2]
    c = o[..., 0] ** 2 + o[..., 2] ** 2 - r * r
    t = _quadratic(a, b, c)
    y = o[..., 1] + t * d[..., 1]
    return jnp.where(jnp.abs(y) <= hh, t, _INF)


_T_FNS = {"plane": _t_plane, "box": _t_box, "sphere": _t_sphere, "rod": _t_rod}


class _Static:
    """Per-object constants of the visible objects, grouped by kind."""

    def __init__(self, scene: Scene):
        vis = [(i, o) for i, o in enumerate(scene.objects)
               if o.kind != "rod" or scene.has("thin_geometry")]
        self.index = np.array([i for i, _ in vis], np.int32)
        objs = [o for _, o in vis]
        self.kinds = [k for k in ("plane", "box", "sphere", "rod")
                      if any(o.kind == k for o in objs)]
        order = [j for k in self.kinds for j, o in enumerate(objs) if o.kind == k]
        self.index = self.index[order]
        objs = [objs[j] for j in order]
        self.objs = objs
        self.groups = {}
        start = 0
        for k in self.kinds:
            n = sum(o.kind == k for o in objs)
            self.groups[k] = (start, start + n)
            start += n
        size = np.array([o.size for o in objs], np.float32).reshape(-1, 3)
        size[:, 0] = np.where([o.kind == "plane" and o.size[0] <= 0 for o in objs], 1e6, size[:, 0])
        size[:, 2] = np.where([o.kind == "plane" and o.size[2] <= 0 for o in objs], 1e6, size[:, 2])
        self.size = size
        self.kind_id = np.array([("plane", "box", "sphere", "rod").index(o.kind) for o in objs],
                                np.int32)
        m = [o.material for o in objs]
        self.color = np.array([x.color for x in m], np.float32).reshape(-1, 3)
        self.tex = np.array([TEXTURES.index(x.texture) for x in m], np.int32)
        self.tex_scale = np.array([x.texture_scale for x in m], np.float32)
        self.tex_seed = np.array([x.texture_seed for x in m], np.int32)
        self.tex_aspect = np.array([x.texture_aspect for x in m], np.float32)
        # albedo = lerp(dark, color, texture value); dark = color2 or color * (1 - contrast)
        self.dark = np.array([x.color2 if x.color2 else tuple(c * (1 - x.contrast)
                                                               for c in x.color) for x in m],
                             np.float32).reshape(-1, 3)
        self.spec = np.array([x.specular for x in m], np.float32)
        self.shine = np.array([x.shininess for x in m], np.float32)
        # each object's bounding sphere about its position (for culling; a plane
        # without a size is the 1e6 one above)
        self.radius = np.array([np.linalg.norm(size[i].astype(np.float64)[
            {"plane": [0, 2], "box": [0, 1, 2], "sphere": [0], "rod": [0, 1]}[o.kind]])
            for i, o in enumerate(objs)], np.float32).reshape(-1)


def _intersect(st: _Static, o, d, pos, yaw, any_hit_before=None, keep=None):
    """Nearest hit: ``(t [N], object [N])`` (t = inf where nothing is hit); or, with
    ``any_hit_before [N]``, a bool [N]: something is hit closer than that.

    ``keep [objects]`` (bool), when given, names the objects that may be hit (the
    others are proven missed by every ray, ``cone_keep`` / ``capsule_keep``): the
    objects are then tested one at a time in a loop, each under ``lax.cond``, and the
    culled ones cost nothing. The values are those of the test of every object."""
    if keep is None:
        ts = []
        for k in st.kinds:
            a, b = st.groups[k]
            po, yo = pos[a:b], yaw[a:b]
            oo = _to_object(o[:, None, :] - po[None], yo[None])
            do = _to_object(jnp.broadcast_to(d[:, None, :], oo.shape), yo[None])
            ts.append(_T_FNS[k](oo, do, jnp.asarray(st.size[a:b])[None]))
        t_all = jnp.concatenate(ts, -1)
        if any_hit_before is not None:
            return jnp.any(t_all < any_hit_before[:, None], -1)
        return jnp.min(t_all, -1), jnp.argmin(t_all, -1).astype(jnp.int32)
    size = jnp.asarray(st.size)
    n = o.shape[0]
    if any_hit_before is None:
        carry = (jnp.full((n,), _INF, o.dtype), jnp.zeros((n,), jnp.int32))
    else:
        carry = jnp.zeros((n,), bool)
    for k in st.kinds:
        fn = _T_FNS[k]

        def test(j, carry, fn=fn):
            t = fn(_to_object(o - pos[j], yaw[j]), _to_object(d, yaw[j]), size[j])
            if any_hit_before is not None:
                return carry | (t < any_hit_before)
            best, idx = carry
            closer = t < best  # strict: ties keep the first object, as argmin does
            return jnp.where(closer, t, best), jnp.where(closer, j, idx)

        def body(j, carry, test=test):
            return jax.lax.cond(keep[j], test, lambda j, c: c, j, carry)

        a, b = st.groups[k]
        carry = jax.lax.fori_loop(a, b, body, carry)
    return carry


def cone_keep(radius, pos, eye, d):
    """Which spheres (centres ``pos [K,3]``, ``radius [K]``) the rays from ``eye``
    along ``d [N,3]`` may meet: bool ``[K]``. The rays lie in the cone about their mean
    direction whose half-angle is their widest; a sphere is dropped only when its
    distance from the line of the cone's surface (at most its distance from the cone)
    exceeds its radius, with margins for float32 rounding. Rays wider than a
    half-space keep everything."""
    dn = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    axis = dn.mean(0)
    axis = axis / jnp.maximum(jnp.linalg.norm(axis), 1e-12)
    cos = jnp.min(dn @ axis) - 1e-5
    sin = jnp.sqrt(jnp.maximum(1.0 - cos * cos, 0.0))
    v = pos - eye
    along = v @ axis
    dist2 = (v * v).sum(-1)
    perp = jnp.sqrt(jnp.maximum(dist2 - along * along, 0.0))
    gap = cos * perp - sin * along
    margin = 1e-3 + 1e-4 * jnp.sqrt(dist2)
    return (gap <= radius + margin) | (cos <= 0.0)


def capsule_keep(radius, pos, x, hit, to, directional):
    """Which spheres (centres ``pos [K,3]``, ``radius [K]``) may block a shadow ray:
    bool ``[K]``. The rays start at ``x [N,3]`` where ``hit`` and run to the point
    ``to`` or, when ``directional``, along the unit direction ``to`` for ever; each lies
    within the bounding ball of the origins swept along that segment or half-line (a
    capsule), and a sphere is dropped only when it misses the capsule. Nothing is kept
    when no ray has an origin."""
    w = hit.astype(x.dtype)[:, None]
    count = jnp.maximum(w.sum(), 1.0)
    c = (x * w).sum(0) / count
    r = jnp.sqrt(jnp.max(((x - c) ** 2).sum(-1) * w[:, 0]))
    if directional:
        u, length = to, _INF
    else:
        seg = to - c
        length = jnp.linalg.norm(seg)
        u = seg / jnp.maximum(length, 1e-12)
    v = pos - c
    s = jnp.clip(v @ u, 0.0, length)
    dist = jnp.linalg.norm(v - s[:, None] * u, axis=-1)
    margin = 1e-3 + 1e-4 * jnp.linalg.norm(v, axis=-1)
    return (dist <= r + radius + margin) & jnp.any(hit)


def _normal_uv(st: _Static, p_obj, obj):
    """Object-space normal and texture coordinates at object-space points."""
    kind = jnp.asarray(st.kind_id)[obj]
    size = jnp.asarray(st.size)[obj]
    n_plane = jnp.broadcast_to(jnp.asarray([0.0, 1.0, 0.0]), p_obj.shape)
    rel = jnp.abs(p_obj) / jnp.maximum(size, 1e-6)
    axis = jnp.argmax(rel, -1)
    n_box = jax.nn.one_hot(axis, 3) * jnp.sign(jnp.take_along_axis(p_obj, axis[:, None], -1))
    n_sph = p_obj / jnp.maximum(jnp.linalg.norm(p_obj, axis=-1, keepdims=True), 1e-9)
    radial = p_obj * jnp.asarray([1.0, 0.0, 1.0])
    n_rod = radial / jnp.maximum(jnp.linalg.norm(radial, axis=-1, keepdims=True), 1e-9)
    n = jnp.select([kind[:, None] == i for i in range(4)], [n_plane, n_box, n_sph, n_rod])
    dom = jnp.argmax(jnp.abs(n), -1)
    u = jnp.where(dom == 0, p_obj[:, 2], p_obj[:, 0])
    v = jnp.where(dom == 1, p_obj[:, 2], p_obj[:, 1])
    return n, u, v


def _project(cam, x, direction=False):
    """Normalized screen position of world points (or directions) under a camera."""
    q = x if direction else x - cam["eye"]
    z = jnp.maximum((q * cam["forward"]).sum(-1), 1e-6)
    sx = (q * cam["right"]).sum(-1) / (z * cam["tan_half"][0])
    sy = (q * cam["up"]).sum(-1) / (z * cam["tan_half"][1])
    return jnp.stack([(sx + 1) / 2, (1 - sy) / 2], -1)


def _albedo(st, tex_kinds, obj, hit, u, v, n, dn, dist, pixel_angle, skip=True):
    """Each hit's base colour: the object's colour, through its prefiltered texture
    (``texture_detail``) with the filter width of its footprint.

    With ``skip``, each texture kind is evaluated only for the points of a call when
    one of them hits an object wearing it (``lax.cond`` on the whole call, a real
    branch on the CPU): ``VideoRenderer`` casts the targets tile by tile, whose points
    see one or two of a randomized scene's dozen kinds. ``skip=False`` evaluates every
    kind the scene has for every point (the form whose FLOPs XLA counts)."""
    albedo = jnp.asarray(st.color)[obj]
    if not tex_kinds:
        return albedo
    cos = jnp.maximum(jnp.abs((n * dn).sum(-1)), 0.25)
    scale = jnp.asarray(st.tex_scale)[obj]
    width = dist * pixel_angle / cos * scale
    tex_id = jnp.where(hit, jnp.asarray(st.tex)[obj], -1)  # the sky wears no texture
    tu, tv = u * scale, v * scale * jnp.asarray(st.tex_aspect)[obj]
    seed = jnp.asarray(st.tex_seed)[obj]
    value = jnp.ones_like(u)
    for name in tex_kinds:
        if name in textures.TEXTURE_FNS:
            fn = textures.TEXTURE_FNS[name]
            args = (tu, tv, width)
        else:
            fn = textures.SEEDED_FNS[name]
            args = (tu, tv, width, seed)
        worn = tex_id == TEXTURES.index(name)
        tval = (jax.lax.cond(jnp.any(worn), fn, lambda *a: jnp.ones_like(a[0]), *args)
                if skip else fn(*args))
        value = jnp.where(worn, tval, value)
    dark = jnp.asarray(st.dark)[obj]
    return dark + (albedo - dark) * value[:, None]


def _shade(scene, st, state, albedo, x, n, dn, obj, hit, pos, yaw, gain, keep_for):
    """Ambient, then each light's diffuse term (shadowed with ``shadows``) and its
    highlight (``specular``), then emission (``emissive_flicker``). ``keep_for(test,
    *args)``: the objects a shadow ray may hit (``_parts``)."""
    lights = (scene.light,) + tuple(scene.extra_lights)
    color = albedo * lights[0].ambient
    for i, light in enumerate(lights):
        lv = state["light"][i]
        if light.kind == "directional":
            ldir = jnp.broadcast_to(-lv / jnp.linalg.norm(lv), x.shape)
            ldist = jnp.full(x.shape[:1], _INF)
            intensity = 1.0
        else:
            to_l = lv - x
            ldist = jnp.linalg.norm(to_l, axis=-1)
            ldir = to_l / ldist[:, None]
            intensity = (20.0 / (1.0 + ldist * ldist))[:, None]
        lcol = jnp.asarray(light.color, jnp.float32) * intensity
        diffuse = jnp.maximum((n * ldir).sum(-1, keepdims=True), 0.0)
        vis = 1.0
        if scene.has("shadows"):
            origin = x + 1e-3 * n
            keep = keep_for(capsule_keep, pos, origin, hit,
                            ldir[0] if light.kind == "directional" else lv,
                            light.kind == "directional")
            occluded = _intersect(st, origin, ldir, pos, yaw, any_hit_before=ldist, keep=keep)
            vis = jnp.where(occluded, 0.0, 1.0)[:, None]
        color = color + albedo * lcol * diffuse * vis
        if scene.has("specular"):
            h = ldir - dn
            h = h / jnp.maximum(jnp.linalg.norm(h, axis=-1, keepdims=True), 1e-9)
            lobe = jnp.maximum((n * h).sum(-1), 0.0) ** jnp.asarray(st.shine)[obj]
            color = color + (gain * jnp.asarray(st.spec)[obj] * lobe)[:, None] * lcol * vis
    if scene.has("emissive_flicker"):
        glow = (gain * state["emission"][st.index][obj])[:, None]
        color = color + glow * jnp.asarray(st.color)[obj]
    return color


def _screen_motion(scene, st, state, x, p_obj, obj, dn, hit, xy):
    """Backward motion in normalized units: where each hit point (moved back with its
    object under ``object_motion``), or the sky's direction, was on the previous frame."""
    if scene.has("object_motion"):
        ppos = state["prev_obj_pos"][st.index][obj]
        pyaw = state["prev_obj_yaw"][st.index][obj]
        x_prev = _to_world(p_obj, pyaw) + ppos
    else:
        x_prev = x
    prev = state["prev_camera"]
    moved = _project(prev, x_prev)
    moved_sky = _project(prev, dn, direction=True)
    return jnp.where(hit[:, None], moved, moved_sky) - xy


def _primary(state, xy):
    """Each screen point's camera ray: origin and (unnormalized) direction ``[N,3]``."""
    cam = state["camera"]
    sx = 2 * xy[:, 0:1] - 1
    sy = 1 - 2 * xy[:, 1:2]
    d = (cam["forward"] + sx * cam["tan_half"][0] * cam["right"]
         + sy * cam["tan_half"][1] * cam["up"])
    return jnp.broadcast_to(cam["eye"], d.shape), d


INTERSECT = ("culled", "every", "unrolled")


def _keep_rule(st: _Static, intersect):
    """``keep_for(test, pos, *args)``: the objects ``_intersect`` tests for some rays.
    ``intersect``: ``"culled"`` keeps those whose bounding sphere a ray can reach
    (``test`` is ``cone_keep`` for the camera rays, ``capsule_keep`` for each light's
    shadow rays), each then tested under a ``lax.cond``; ``"every"`` runs the same
    loop with every object kept (the same values, bit for bit: the culling's
    reference); ``"unrolled"`` tests every object in one expression, the form whose
    FLOPs XLA counts (it counts a loop's body once), which rounds a few grazing rays
    differently from the loop."""
    if intersect not in INTERSECT:
        raise ValueError(f"intersect: expected one of {INTERSECT}, got {intersect!r}")

    def keep_for(test, pos, *args):
        if intersect == "unrolled":
            return None
        if intersect == "every":
            return jnp.ones(pos.shape[:1], bool)
        return test(jnp.asarray(st.radius), pos, *args)

    return keep_for


def _parts(scene: Scene, intersect="culled"):
    """The renderer in two pieces: ``shade(state, xy, pixel_angle) -> (color, t, obj)``,
    the costly one (intersection, texture, lighting), and ``geometry(state, xy, t,
    obj, motion) -> dict`` of ``depth`` and ``motion`` from the hits it found (a few
    dozen FLOPs a point). ``intersect``: how rays meet objects (``_keep_rule``)."""
    st = _Static(scene)
    keep_for = _keep_rule(st, intersect)
    tex_kinds = (sorted({TEXTURES[t] for t in st.tex if t != 0})
                 if scene.has("texture_detail") else [])
    near, far = scene.near, scene.far
    horizon, zenith = (jnp.asarray(c, jnp.float32) for c in scene.sky)
    hdr = scene.has("hdr")
    gain = scene.highlight_gain if hdr else 1.0

    def poses(state):
        """The visible objects' positions and yaws, in ``st``'s order."""
        return state["obj_pos"][st.index], state["obj_yaw"][st.index]

    def hit_point(pos, yaw, o, d, t, obj):
        hit = jnp.isfinite(t)
        t_safe = jnp.where(hit, t, 1.0)
        x = o + t_safe[:, None] * d
        p_obj = _to_object(x - pos[obj], yaw[obj])
        return hit, t_safe, x, p_obj

    def shade(state, xy, pixel_angle):
        pos, yaw = poses(state)
        o, d = _primary(state, xy)
        t, obj = _intersect(st, o, d, pos, yaw,
                            keep=keep_for(cone_keep, pos, state["camera"]["eye"], d))
        hit, t_safe, x, p_obj = hit_point(pos, yaw, o, d, t, obj)
        n_obj, u, v = _normal_uv(st, p_obj, obj)
        n = _to_world(n_obj, yaw[obj])
        dn = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
        n = jnp.where((n * dn).sum(-1, keepdims=True) > 0, -n, n)
        albedo = _albedo(st, tex_kinds, obj, hit, u, v, n, dn,
                         t_safe * jnp.linalg.norm(d, axis=-1), pixel_angle,
                         skip=intersect != "unrolled")
        color = _shade(scene, st, state, albedo, x, n, dn, obj, hit, pos, yaw, gain, keep_for)
        sky = horizon + (zenith - horizon) * jnp.clip(dn[:, 1:2], 0.0, 1.0)
        color = jnp.where(hit[:, None], color, sky)
        # LDR scenes clamp to display range; hdr keeps linear radiance (>= 0)
        return (jnp.maximum(color, 0.0) if hdr else jnp.clip(color, 0.0, 1.0)), t, obj

    def geometry(state, xy, t, obj, motion=True):
        o, d = _primary(state, xy)
        hit, t_safe, x, p_obj = hit_point(*poses(state), o, d, t, obj)
        z = jnp.maximum(t_safe, near)
        ndc = jnp.clip(far / (far - near) * (1 - near / z), 0, 1)
        out = {"depth": jnp.where(hit, ndc, 1.0)[:, None]}
        if motion:
            dn = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
            out["motion"] = _screen_motion(scene, st, state, x, p_obj, obj, dn, hit, xy)
        return out

    return shade, geometry


def make_renderer(scene: Scene, motion: bool = True, intersect: str = "culled"):
    """The jitted ``render(state, xy [N,2], pixel_angle) -> dict`` for this scene.

    ``pixel_angle`` is the texture filter's footprint in radians per sample (the
    mip bias is folded into it). The dict holds ``color [N,3]`` (clamped to [0,1]; with
    ``hdr`` linear radiance >= 0, highlights scaled by ``scene.highlight_gain``),
    ``depth [N,1]`` and, with ``motion``, ``motion [N,2]`` (normalized units). Only
    the effects the scene declares are traced.
    """
    shade, geometry = _parts(scene, intersect)

    def render(state, xy, pixel_angle):
        color, t, obj = shade(state, xy, pixel_angle)
        return {"color": color, **geometry(state, xy, t, obj, motion)}

    return jax.jit(render)


def make_split_renderer(scene: Scene, intersect: str = "culled"):
    """``make_renderer``'s work as two jitted functions, for callers that need depth
    and motion for only some of their points (``jtus.sim.video``: the inputs, not the
    supersampled targets): ``shade(state, xy, pixel_angle) -> (color, t, obj)`` and
    ``geometry(state, xy, t, obj) -> {"depth", "motion"}``. Their outputs are
    ``make_renderer``'s (to 1e-6, ``tests/test_sim.py``). The colour alone counts
    0.85-0.94x the whole's FLOPs per point on the hand-made scenes measured, 0.98-0.99x
    on randomized ones, and the two compile in about the whole's time
    (``experiments/renderer_split.py``). ``shade`` takes its points ``BUNDLE`` at a
    time (``lax.map``) when their number is a multiple of it, so that culling works on
    bundles of nearby rays (``VideoRenderer`` orders the targets' rays so)."""
    shade, geometry = _parts(scene, intersect)
    if intersect == "unrolled":
        return jax.jit(shade), jax.jit(geometry)

    def bundled(state, xy, pixel_angle):
        n = xy.shape[0]
        if n % BUNDLE:
            return shade(state, xy, pixel_angle)
        color, t, obj = jax.lax.map(lambda p: shade(state, p, pixel_angle),
                                    xy.reshape(n // BUNDLE, BUNDLE, 2))
        return color.reshape(n, -1), t.reshape(n), obj.reshape(n)

    return jax.jit(bundled), jax.jit(geometry)


def pixel_angle(camera_tan_half_y, height_hr, spp_match=1):
    """Texture footprint per sample: one HR pixel's angle over sqrt(spp_match); the
    input's mip bias of eq. 47 and the target's level both reduce to this."""
    return 2.0 * float(camera_tan_half_y) / height_hr / np.sqrt(spp_match)


def flops_per_point(scene: Scene, points=256):
    """The FLOPs XLA counts (``cost_analysis``) for rendering one screen point of
    ``scene`` with its declared effects: the compiled renderer over ``points`` points,
    divided by their number. Unlike a wall time it does not move with the machine's
    load, so it shows that an undeclared effect costs nothing."""
    state = state_arrays(timeline(scene, "train", 0, 1, 1.0)[0])
    cost = compiled_cost(make_renderer(scene, motion=True, intersect="unrolled"), state,
                         jnp.zeros((points, 2), jnp.float32), 0.01)
    return float(cost["flops"]) / points


def compiled_cost(fn, *args):
    """XLA's ``cost_analysis`` of the jitted ``fn`` compiled for ``args``: a dict with
    ``flops`` and ``bytes accessed`` among its keys."""
    cost = fn.lower(*args).compile().cost_analysis()
    return cost[0] if isinstance(cost, (list, tuple)) else cost
