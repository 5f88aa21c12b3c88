"""Mesh scenes: exact motion of moving parts, effects that gate surfaces, the Quake III
reader on a level written here, users' glTF/OBJ files, and datasets from them."""

import struct
import subprocess
import sys

import numpy as np
import pytest

from jtus.sim import bsp, meshfile
from jtus.sim.mesh import Material, MeshRenderer, MeshScene, Motion, Part, mip_pyramid, sample
from jtus.sim.paths import look_at
from jtus.sim.video import VideoRenderer
from jtus.sim import walk

pytest.importorskip("embreex")


def _quad(center, half, normal_axis=2, z_sign=1.0):
    cx, cy, cz = center
    hx, hy = half
    v = np.array([[cx - hx, cy - hy, cz], [cx + hx, cy - hy, cz], [cx + hx, cy + hy, cz],
                  [cx - hx, cy + hy, cz]], float)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    n = np.tile([0, 0, z_sign], (4, 1)).astype(np.float32)
    return v, uv, f, n


def _part(quads, mat_ids, motion=Motion()):
    pos, uvs, faces, ns, fm = [], [], [], [], []
    base = 0
    for (v, uv, f, n), m in zip(quads, mat_ids):
        pos.append(v)
        uvs.append(uv)
        faces.append(f + base)
        ns.append(n)
        fm.append(np.full(len(f), m))
        base += len(v)
    pos = np.concatenate(pos)
    return Part(position=pos, faces=np.concatenate(faces), uv=np.concatenate(uvs),
                normal=np.concatenate(ns), face_material=np.concatenate(fm),
                light=np.ones((len(pos), 3), np.float32), motion=motion)


def _gradient_material(n=64, alpha=None, **kw):
    """A smooth, unlit texture whose colour names its texture coordinate."""
    y, x = np.mgrid[0:n, 0:n] / (n - 1)
    img = np.stack([0.2 + 0.6 * x, 0.2 + 0.6 * y, 0.5 * np.ones_like(x),
                    np.ones_like(x) if alpha is None else alpha], -1).astype(np.float32)
    return Material(mip_pyramid(img), lit=False, **kw)


def _state(cam, prev, poses, prev_poses, seconds=0.0):
    return walk.FrameState(cam, prev, poses, prev_poses, seconds, np.zeros(3))


def _screen(h, w):
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([(x.ravel() + 0.5) / w, (y.ravel() + 0.5) / h], -1)


def _reprojected_error(sc, now_s, before_s):
    """Cast ``sc`` at ``now_s`` under a moving camera, then the frame at ``before_s``
    at p + motion: ``(largest motion, per-pixel colour error where p + motion stays
    inside)``."""
    r = MeshRenderer(sc)
    cam = look_at([0.1, 0.05, 1.0], [0.2, 0.1, -3.0], 0.9, 1.0)
    prev = look_at([0.0, 0.0, 1.0], [0.1, 0.0, -3.0], 0.9, 1.0)
    now = [p.motion.pose(now_s) for p in sc.parts]
    before = [p.motion.pose(before_s) for p in sc.parts]
    xy = _screen(48, 48)
    out = r.cast(_state(cam, prev, now, before), xy, 1e-5)
    moved = xy + out["motion"]
    inside = np.all((moved > 0.02) & (moved < 0.98), -1)
    back = r.cast(_state(prev, prev, before, before), moved[inside], 1e-5)
    return np.abs(out["motion"]).max(), np.abs(back["color"] - out["color"][inside]).max(-1)


def test_motion_vectors_of_a_moving_part_point_where_its_surface_was():
    """Backward motion of a rotating, sliding part under a moving camera: the previous
    frame, cast at p + motion, shows the same texel (an unlit smooth texture, so colour
    names the surface point)."""
    back = _part([_quad((0, 0, -4), (6, 6))], [0])
    spin = Motion("rotate", (0.0, 0.0, 1.0), period=3.0, pivot=(0.3, 0.2, -2.0))
    front = _part([_quad((0.3, 0.2, -2.0), (0.8, 0.6))], [1], spin)
    sc = MeshScene("t", ("camera_motion", "object_motion"), [back, front],
                   [_gradient_material(), _gradient_material(32)], [(np.zeros(3), 0.0)])
    most, err = _reprojected_error(sc, 0.5, 0.4)
    # the part turned by 12 degrees: pixels on it moved, and still match
    assert most > 0.02
    assert np.mean(err < 1e-3) > 0.97, np.mean(err < 1e-3)  # edges may disocclude
    assert np.median(err) < 1e-5


def test_undeclared_effects_leave_their_surfaces_out():
    """An alpha-tested quad is absent without alpha_cutout and cut per texel with it;
    an additive layer is absent without transparency and adds its colour with it,
    while depth and motion stay those of the surface behind."""
    alpha = np.zeros((16, 16), np.float32)
    alpha[:, :8] = 1.0  # left half kept
    mats = [_gradient_material(), _gradient_material(16, alpha, alpha_test=0.5),
            Material(mip_pyramid(np.full((2, 2, 4), 0.25, np.float32)), blend="add", lit=False)]
    back = _part([_quad((0, 0, -4), (6, 6))], [0])
    fence = _part([_quad((0, 0, -2), (0.5, 0.5))], [1])
    glow = _part([_quad((0, 0, -1), (0.2, 0.2))], [2])
    cam = look_at([0, 0, 1], [0, 0, -3], 0.9, 1.0)
    poses = [Motion().pose(0)] * 3
    pts = np.array([[0.5 - 0.08, 0.5], [0.5 + 0.08, 0.5], [0.5, 0.5]])
    res = {}
    for fx in [(), ("alpha_cutout",), ("transparency",)]:
        sc = MeshScene("t", fx, [back, fence, glow], mats, [(np.zeros(3), 0.0)])
        res[fx] = MeshRenderer(sc).cast(_state(cam, cam, poses, poses), pts, 1e-4)
    z_back, z_fence = res[()]["depth"][0, 0], res[("alpha_cutout",)]["depth"][0, 0]
    assert z_fence < z_back  # left half of the fence is there with the effect
    assert res[("alpha_cutout",)]["depth"][1, 0] == pytest.approx(z_back)  # right half cut
    np.testing.assert_allclose(res[("transparency",)]["color"][2],
                               res[()]["color"][2] + 0.25, atol=1e-6)
    assert res[("transparency",)]["depth"][2, 0] == res[()]["depth"][2, 0]


def test_trilinear_sampling_averages_levels():
    img = np.random.default_rng(0).random((8, 8, 3)).astype(np.float32)
    lv = mip_pyramid(img)
    assert [x.shape[0] for x in lv] == [8, 4, 2, 1]
    np.testing.assert_allclose(lv[-1][0, 0], img.mean((0, 1)), rtol=1e-6)
    u = np.array([0.3]), np.array([0.6])
    a = sample(lv, *u, np.array([1.0]))
    b = sample(lv, *u, np.array([2.0]))
    np.testing.assert_allclose(sample(lv, *u, np.array([1.25])), 0.75 * a + 0.25 * b, rtol=1e-6)
    # texel centres: level 0 at texel (2, 5) returns that texel exactly
    np.testing.assert_allclose(sample(lv, np.array([5.5 / 8]), np.array([2.5 / 8]),
                                      np.array([0.0]))[0], img[2, 5], rtol=1e-6)


SHADERS = """
// a comment { not a brace }
textures/x/fence
{
    surfaceparm alphashadow
    {
        map textures/x/fence.tga
        alphaFunc GE128
    }
    {
        map $lightmap
        blendFunc GL_DST_COLOR GL_ZERO
    }
}
textures/x/glow
{
    surfaceparm nolightmap
    {
        map textures/x/glow.jpg
        blendfunc add
        tcMod scroll 0.5 -0.25
        rgbGen wave sin 0.5 0.5 0 2
    }
}
textures/x/clip
{
    surfaceparm nodraw
}
textures/x/sky { skyparms - 512 - }
"""


def test_shader_scripts_give_cutouts_layers_scroll_flicker_and_skips():
    sh = bsp.parse_shaders(SHADERS)
    assert set(sh) == {"textures/x/fence", "textures/x/glow", "textures/x/clip", "textures/x/sky"}
    fence, glow = sh["textures/x/fence"], sh["textures/x/glow"]
    assert fence.lightmapped and fence.stages[0].alpha_test == 0.5
    assert fence.stages[0].image == "textures/x/fence.tga" and len(fence.stages) == 1
    st = glow.stages[0]
    assert not glow.lightmapped and st.blend == "add" and st.scroll == (0.5, -0.25)
    assert st.wave == (0.5, 0.5, 0.0, 2.0)
    assert sh["textures/x/clip"].nodraw and sh["textures/x/sky"].sky


def _write_bsp(path_faces):
    """A minimal IBSP v46 file: one texture, a quad polygon, a 3x3 patch on brush model 1
    (a func_bobbing), a spawn point."""
    verts = []
    def vert(p, st):  # noqa: E306
        verts.append(struct.pack("<3f2f2f3f4B", *p, *st, 0.5, 0.5, 0, 0, 1, 200, 100, 50, 255))
    for p, st in [((0, 0, 0), (0, 0)), ((64, 0, 0), (1, 0)), ((64, 64, 0), (1, 1)),
                  ((0, 64, 0), (0, 1))]:
        vert(p, st)
    for j in range(3):
        for i in range(3):
            vert((100 + 32 * i, 32 * j, 16 * (i == 1 and j == 1)), (i / 2, j / 2))
    meshverts = struct.pack("<6i", 0, 1, 2, 0, 2, 3)
    face = lambda kind, v0, nv, m0, nm, size: struct.pack(  # noqa: E731
        "<7i1i2i2i3f6f3f2i", 0, -1, kind, v0, nv, m0, nm, 0, 0, 0, 128, 128,
        *([0.0] * 3), *([0.0] * 6), 0, 0, 1, *size)
    faces = face(1, 0, 4, 0, 6, (0, 0)) + face(2, 4, 9, 0, 0, (3, 3))
    models = (struct.pack("<3f3f4i", 0, 0, 0, 64, 64, 0, 0, 1, 0, 0)
              + struct.pack("<3f3f4i", 100, 0, 0, 164, 64, 16, 1, 1, 0, 0))
    ents = (b'{ "classname" "worldspawn" }\n{ "classname" "info_player_deathmatch" '
            b'"origin" "10 20 30" "angle" "90" }\n{ "classname" "func_bobbing" "model" "*1" '
            b'"height" "40" "speed" "2" }\0')
    tex = struct.pack("<64sii", b"textures/x/wall", 0, 1)
    lumps = [b""] * 17
    lumps[0], lumps[1], lumps[7] = ents, tex, models
    lumps[10], lumps[11], lumps[13] = b"".join(verts), meshverts, faces
    lumps[14] = bytes(128 * 128 * 3)
    head = 8 + 17 * 8
    out, dirs, off = b"", [], head
    for lump in lumps:
        dirs += [off, len(lump)]
        out += lump
        off += len(lump)
    return b"IBSP" + struct.pack("<i", 46) + struct.pack("<34i", *dirs) + out


def test_quake_level_reader_converts_axes_tessellates_patches_and_reads_entities():
    level = bsp.load_level(_write_bsp(None), "t", patch_level=4)
    assert len(level.faces) == 2 + 2 * 4 * 4  # the quad, a 3x3 patch at level 4
    # (x, y, z) quake -> (x, z, -y) * 0.0254
    np.testing.assert_allclose(level.position[1], [64 * 0.0254, 0, 0], atol=1e-9)
    np.testing.assert_allclose(level.position[3], [0, 0, -64 * 0.0254], atol=1e-9)
    # the patch's middle bulges by half its control point's height (quadratic Bezier)
    patch = level.position[4:]
    assert patch[:, 1].max() == pytest.approx(0.25 * 16 * 0.0254, rel=1e-6)
    (eye, yaw), = level.spawns
    np.testing.assert_allclose(eye, [10 * 0.0254, 56 * 0.0254, -20 * 0.0254], atol=1e-9)
    assert yaw == pytest.approx(np.pi / 2)
    assert list(level.movers) == [1] and level.movers[1]["height"] == "40"
    assert (level.face_model == 1).sum() == 32
    np.testing.assert_allclose(level.normal[0], [0, 1, 0], atol=1e-6)  # quake +z is up


def test_quake_reader_refuses_other_files():
    with pytest.raises(ValueError, match="bsp: expected the magic"):
        bsp.load_level(b"PK\x03\x04" + bytes(200))
    data = bytearray(_write_bsp(None))
    data[4:8] = struct.pack("<i", 47)
    with pytest.raises(ValueError, match="version 46"):
        bsp.load_level(bytes(data))


@pytest.fixture(scope="module")
def gltf_file(tmp_path_factory):
    trimesh = pytest.importorskip("trimesh")
    from PIL import Image

    d = tmp_path_factory.mktemp("gltf")
    checker = (np.indices((32, 32)).sum(0) // 4 % 2 * 200 + 30).astype(np.uint8)
    img = Image.fromarray(np.stack([checker] * 3, -1))
    floor = trimesh.creation.box([8, 0.1, 8])
    floor.visual = trimesh.visual.TextureVisuals(
        uv=(floor.vertices[:, [0, 2]] / 8 + 0.5), image=img)
    block = trimesh.creation.box([1, 1, 1])
    block.apply_translation([0.5, 0.55, -1.0])
    scene = trimesh.Scene([floor, block])
    scene.camera_transform = trimesh.transformations.translation_matrix([0.2, 1.0, 3.0])
    path = d / "room.glb"
    scene.export(str(path))
    return path


def test_gltf_file_loads_with_its_texture_and_renders(gltf_file):
    sc = meshfile.load(gltf_file)
    assert sum(len(p.faces) for p in sc.parts) == 24 and len(sc.materials) == 2
    eye, yaw = sc.spawns[0]  # the file's camera: at (0.2, 1, 3), looking along -z
    np.testing.assert_allclose(eye, [0.2, 1.0, 3.0], atol=1e-9)
    assert yaw == pytest.approx(np.pi / 2)
    tex, = [m.levels[0] for m in sc.materials if m.levels[0].shape[0] > 2]
    assert tex.shape[:2] == (32, 32) and tex[..., :3].max() > 20 * tex[..., :3].min()
    r = VideoRenderer(sc, (32, 32), (2, 4), spp=4)
    v = r.video("train", 0, 4)
    assert v["target"].shape == (4, 32, 32, 3) and np.isfinite(v["target"]).all()
    assert v["x4"]["motion"].shape == (4, 8, 8, 2)
    assert v["target"].std() > 0.02  # a picture, not a flat colour


def test_render_cli_writes_a_dataset_from_a_mesh_file(gltf_file, tmp_path):
    out = tmp_path / "m.h5"
    cmd = [sys.executable, "-m", "jtus.sim", "render", "--scene", str(gltf_file), "--out",
           str(out), "--frames", "3", "--size", "32", "--spp", "4", "--workers", "1",
           "--quiet"]
    assert subprocess.run(cmd, capture_output=True, text=True).returncode == 0
    from jtus.data.dataset import Dataset
    with Dataset(str(out)) as ds:
        assert ds.size == (32, 32)
    bad = tmp_path / "broken.obj"
    bad.write_text("this is not a mesh\n")
    res = subprocess.run(cmd[:5] + [str(bad), "--out", str(tmp_path / "b.h5")],
                         capture_output=True, text=True)
    assert res.returncode == 2 and "error: scene:" in res.stderr
    assert not (tmp_path / "b.h5").exists()
    res = subprocess.run(cmd[:5] + [str(gltf_file), "--effects", "texture_detail", "--out",
                                    str(tmp_path / "c.h5")], capture_output=True, text=True)
    assert res.returncode == 2 and "mesh scene takes" in res.stderr


def test_walks_keep_off_walls_and_hold_still():
    """In a closed box room the walking camera never leaves the room, and its hold
    frames do not move."""
    room = []
    for v, uv, f, n in [_quad((0, 1.5, -5), (5, 1.5)), _quad((0, 1.5, 5), (5, 1.5))]:
        room.append((v, uv, f, n))
    # side walls and floor as rotated quads
    def rot(q, m):  # noqa: E306
        v, uv, f, n = q
        return v @ m.T, uv, f, n @ m.T
    ry = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]], float)
    room += [rot(_quad((0, 1.5, -5), (5, 1.5)), ry), rot(_quad((0, 1.5, 5), (5, 1.5)), ry)]
    rx = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)
    room += [rot(_quad((0, 0, 0), (5, 5)), rx)]
    part = _part(room, [0] * 5)
    sc = MeshScene("room", ("camera_motion",), [part], [_gradient_material()],
                   [(np.array([0.0, 1.3, 0.0]), 0.0)], speed=0.3)
    states = walk.timeline(MeshRenderer(sc), "train", 3, 60, 1.0)
    eyes = np.array([s.camera.eye for s in states])
    assert np.abs(eyes[:, [0, 2]]).max() < 5.0 - 0.2  # walls at 5
    steps = np.linalg.norm(np.diff(eyes, axis=0), axis=-1)
    assert (steps == 0).sum() >= walk.HOLD - 1 and steps.max() > 0.1


def test_game_levels_are_held_out_whole():
    """No level is in two splits, and variants of one level share their split; the game
    preset draws each split from its own levels."""
    from jtus.sim import game
    from jtus.sim.generate import preset

    splits = {"train": game.TRAIN_LEVELS, "val": game.VAL_LEVELS, "test": game.TEST_LEVELS}
    seen = [m for ms in splits.values() for m in ms]
    assert len(seen) == len(set(seen))
    for family in game.VARIANTS:
        assert len({s for s, ms in splits.items() for m in family if m in ms}) == 1, family
    p = preset("game")
    for split, maps in splits.items():
        assert p.splits[split][0] == tuple(game.PREFIX + m for m in maps)
    assert len(p.splits["train"][0]) * p.splits["train"][1] >= 200


@pytest.mark.skipif(not __import__("jtus.sim.game").sim.game.pk3_files(),
                    reason="game assets not fetched (bash data/fetch_game_assets.sh)")
def test_an_openarena_level_renders_with_the_effects_its_content_has():
    from jtus.sim import game

    sc = game.scene_of("oa:oa_dm1")
    assert {"object_motion", "transparency", "camera_cut"} <= set(sc.effects)
    v = VideoRenderer(sc, (32, 32), (4,), 4).video("test", 0, 3)
    assert np.isfinite(v["target"]).all() and v["target"].std() > 0.01
    assert np.isfinite(v["x4"]["motion"]).all()


def _animated_gltf(d, channels):
    """A glTF written here: a textured back wall and a textured quad ``spinner`` at
    (0.3, 0.2, -2) whose first animation has ``channels`` ({path: [K, width] values})
    at key times 0, 1, 2 s. Returns the file's path."""
    import base64
    import json

    trimesh = pytest.importorskip("trimesh")
    from PIL import Image

    y, x = np.mgrid[0:64, 0:64] / 63
    img = Image.fromarray((np.stack([0.2 + 0.6 * x, 0.2 + 0.6 * y, 0.5 + 0 * x], -1)
                           * 255).astype(np.uint8))
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)

    def quad(half):
        m = trimesh.Trimesh(np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]) * half,
                            [[0, 1, 2], [0, 2, 3]], process=False)
        m.visual = trimesh.visual.TextureVisuals(uv=uv, image=img)
        return m

    sc = trimesh.Scene()
    sc.add_geometry(quad(6.0), node_name="back", geom_name="back",
                    transform=trimesh.transformations.translation_matrix([0, 0, -4]))
    sc.add_geometry(quad(0.7), node_name="spinner", geom_name="spin",
                    transform=trimesh.transformations.translation_matrix([0.3, 0.2, -2]))
    files = sc.export(file_type="gltf")
    h = json.loads(files.pop("model.gltf"))
    node = next(i for i, n in enumerate(h["nodes"]) if n["name"] == "spinner")
    del h["nodes"][node]["matrix"]
    h["nodes"][node]["translation"] = [0.3, 0.2, -2.0]
    arrays = [np.array([0.0, 1.0, 2.0], np.float32)] + [np.asarray(v, np.float32)
                                                       for v in channels.values()]
    blob = b"".join(a.tobytes() for a in arrays)
    h["buffers"].append({"uri": "data:application/octet-stream;base64,"
                         + base64.b64encode(blob).decode(), "byteLength": len(blob)})
    samplers, chans, offset = [], [], 0
    for k, a in enumerate(arrays):
        h["bufferViews"].append({"buffer": len(h["buffers"]) - 1, "byteOffset": offset,
                                 "byteLength": a.nbytes})
        offset += a.nbytes
        h["accessors"].append({"bufferView": len(h["bufferViews"]) - 1, "componentType": 5126,
                               "count": len(a), "type": {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[
                                   1 if a.ndim == 1 else a.shape[1]]})
        if k:
            samplers.append({"input": len(h["accessors"]) - 1 - k, "output":
                             len(h["accessors"]) - 1, "interpolation": "LINEAR"})
    for k, path in enumerate(channels):
        chans.append({"sampler": k, "target": {"node": node, "path": path}})
    first_time = len(h["accessors"]) - len(arrays)
    for smp in samplers:
        smp["input"] = first_time
    h["animations"] = [{"samplers": samplers, "channels": chans}]
    for name, data in files.items():
        (d / name).write_bytes(data)
    path = d / "anim.gltf"
    path.write_text(json.dumps(h))
    return path


def _quat_z(deg):
    a = np.radians(deg) / 2
    return [0.0, 0.0, np.sin(a), np.cos(a)]


def test_gltf_animation_moves_its_node_rigidly_with_exact_motion(tmp_path):
    """A glTF node's keyframed translation and rotation become its part's motion: at a
    key time its triangles are where the key puts them (checked against trimesh's own
    matrices), between keys rotation is slerped, and the previous frame cast at
    p + motion shows the same texel. Scale channels are refused (not rigid)."""
    trimesh = pytest.importorskip("trimesh")
    tf = trimesh.transformations
    keys_t = [[0.3, 0.2, -2.0], [0.5, 0.2, -2.0], [0.5, 0.4, -2.2]]
    path = _animated_gltf(tmp_path, {"translation": keys_t,
                                     "rotation": [_quat_z(0), _quat_z(40), _quat_z(80)]})
    sc = meshfile.load(path)
    assert "object_motion" in sc.effects and len(sc.parts) == 2
    spin, = [p for p in sc.parts if p.motion.kind == "keyframes"]
    rest = spin.position  # the node's own translation, no rotation
    # keys at 0, 1, 2 s; the animation loops, so 2.25 s is 0.25 s
    for t, (tr, deg) in [(1.0, (keys_t[1], 40)), (1.5, (np.mean(keys_t[1:], 0), 60)),
                         (2.25, (np.average(keys_t[:2], 0, [3, 1]), 10))]:
        r, d = spin.motion.pose(t)
        local = rest - np.array([0.3, 0.2, -2.0])
        want = tf.transform_points(local, tf.translation_matrix(tr)
                                   @ tf.rotation_matrix(np.radians(deg), [0, 0, 1]))
        np.testing.assert_allclose(rest @ r.T + d, want, atol=1e-6)
    most, err = _reprojected_error(sc, 0.8, 0.7)
    assert most > 0.01
    assert np.mean(err < 1e-3) > 0.97 and np.median(err) < 1e-5, np.mean(err < 1e-3)
    still = meshfile.load(path, effects=("camera_motion",))  # undeclared: held at rest
    assert "object_motion" not in still.effects
    (tmp_path / "s").mkdir()
    bad = _animated_gltf(tmp_path / "s", {"scale": [[1, 1, 1], [2, 2, 2], [1, 1, 1]]})
    with pytest.raises(ValueError, match="scale channel is not a rigid motion"):
        meshfile.load(bad)
