"""Per-frame scene state, computed on the host: camera, object poses, light, emission.

A video is a scene, a split and an index; its seed fixes the camera path's start,
speed, holds and cuts, so train, validation and test videos differ. Effects that a
scene does not declare leave their part of the state constant (a static camera
without ``camera_motion``, objects at their first pose without ``object_motion``...).
"""

from __future__ import annotations

import hashlib
from typing import NamedTuple

import numpy as np

from jtus.sim.scene import Scene

SPLITS = ("train", "val", "test")
FPS = 30.0


class Camera(NamedTuple):
    eye: np.ndarray      # [3]
    forward: np.ndarray  # [3] unit view axis
    right: np.ndarray    # [3] unit, screen x
    up: np.ndarray       # [3] unit, screen -y
    tan_half: np.ndarray  # [2] tan of the half field of view in x and y


class FrameState(NamedTuple):
    camera: Camera
    prev_camera: Camera
    obj_pos: np.ndarray       # [K,3]
    obj_yaw: np.ndarray       # [K]
    prev_obj_pos: np.ndarray
    prev_obj_yaw: np.ndarray
    light: np.ndarray         # [L,3] per light: direction of travel or position
    emission: np.ndarray      # [K]
    cut: bool                 # a camera cut at this frame
    exposure: float = 1.0     # pre-exposure of the frame's HDR colour (hdr), else 1


def video_seed(scene_name, split, index):
    if split not in SPLITS:
        raise ValueError(f"split: expected one of {SPLITS}, got {split!r}")
    digest = hashlib.sha256(f"{scene_name}/{split}/{index}".encode()).digest()
    return int.from_bytes(digest[:8], "little")


def look_at(eye, target, fov_y, aspect):
    f = np.asarray(target, float) - np.asarray(eye, float)
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 1.0, 0.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    ty = np.tan(fov_y / 2)
    return Camera(np.asarray(eye, float), f, r, u, np.array([ty * aspect, ty]))


class _Timeline:
    def __init__(self, scene: Scene, seed, length):
        rng = np.random.default_rng(seed)
        p = scene.path
        self.scene = scene
        self.start = rng.uniform(0, 2 * np.pi)
        self.radius = p.radius * rng.uniform(0.85, 1.15)
        self.height = p.height * rng.uniform(0.7, 1.3)
        speed = p.speed * rng.uniform(0.6, 1.4) * rng.choice([-1.0, 1.0])
        t = np.arange(-1, length)
        period = rng.uniform(30, 60)
        s = speed * (1 + p.speed_variation * np.sin(2 * np.pi * t / period + rng.uniform(0, 6)))
        for _ in range(p.holds):
            if length > p.hold_frames + 2:
                h0 = rng.integers(1, length - p.hold_frames)
                s[h0 + 1:h0 + 1 + p.hold_frames] = 0.0
        if not scene.has("camera_motion"):
            s[:] = 0.0
        self.phase = np.cumsum(s)  # phase[t + 1] is frame t's, phase[0] is frame -1's
        self.offset = np.zeros(length)
        self.cuts = np.zeros(length, bool)
        if scene.has("camera_cut") and p.cut_every > 0:
            for c in range(p.cut_every, length, p.cut_every):
                self.offset[c:] += rng.uniform(1.5, 4.5)
                self.cuts[c] = True
        self.aspect = 1.0
        self.flicker_phase = rng.uniform(0, 2 * np.pi, size=len(scene.objects))
        self.noise = rng.normal(size=(length + 1, len(scene.objects)))
        # drawn last and from its own stream: scenes without hdr keep their timelines
        erng = np.random.default_rng([seed, 0xE4905E])
        self.exposure_period = erng.uniform(48, 120)
        self.exposure_phase = erng.uniform(0, 2 * np.pi)

    def exposure(self, t):
        """An auto-exposure-like curve: ``2^(stops * sin(2 pi t / period + phase))``,
        periods of 48 to 120 frames (1 when the scene has no ``hdr``)."""
        if not self.scene.has("hdr"):
            return 1.0
        a = 2 * np.pi * t / self.exposure_period + self.exposure_phase
        return float(2.0 ** (self.scene.exposure_stops * np.sin(a)))

    def camera(self, phi):
        p = self.scene.path
        c = np.asarray(p.center, float)
        a = self.start + phi
        if p.kind == "orbit":
            eye = c + [self.radius * np.cos(a), self.height, self.radius * np.sin(a)]
            target = c
        elif p.kind == "dolly":
            r = self.radius * (1 - 0.35 * np.sin(phi / max(self.radius, 1e-6) * 4))
            eye = c + [r * np.cos(self.start), self.height, r * np.sin(self.start)]
            target = c
        elif p.kind == "fly":
            # a figure-of-eight through the scene above its centre, looking along the way
            def at(b):
                return c + [self.radius * np.sin(b), self.height + 0.25 * np.sin(3 * b),
                            0.6 * self.radius * np.sin(2 * b)]
            eye = at(a)
            # look at a point between the path ahead and the centre (the objects)
            target = 0.4 * at(a + 0.8) + 0.6 * c
            target[1] = c[1]
        else:  # pan: fixed eye, the view swings
            eye = c + [self.radius * np.cos(self.start), self.height,
                       self.radius * np.sin(self.start)]
            yaw = np.arctan2(c[2] - eye[2], c[0] - eye[0]) + 0.6 * np.sin(phi * 8)
            target = eye + [np.cos(yaw), -0.25, np.sin(yaw)]
        return look_at(eye, target, p.fov_y, self.aspect)

    def objects(self, t):
        k = len(self.scene.objects)
        pos = np.array([o.position for o in self.scene.objects], float).reshape(k, 3)
        yaw = np.array([o.yaw for o in self.scene.objects], float)
        if self.scene.has("object_motion"):
            period = 40.0
            for i, o in enumerate(self.scene.objects):
                phase = np.sin(2 * np.pi * t / period)
                pos[i] += np.asarray(o.velocity) * period / (2 * np.pi) * phase
                pos[i, 1] += o.bob * np.sin(2 * np.pi * t / 30.0)
                yaw[i] += o.spin * t
        return pos, yaw

    def light(self, t):
        out = []
        for L in (self.scene.light,) + tuple(self.scene.extra_lights):
            v = np.asarray(L.vector, float)
            if self.scene.has("moving_light"):
                a = L.orbit_speed * t
                ca, sa = np.cos(a), np.sin(a)
                v = np.array([ca * v[0] - sa * v[2], v[1], sa * v[0] + ca * v[2]])
            if L.kind == "directional":
                v = v / np.linalg.norm(v)
            out.append(v)
        return np.stack(out)

    def emission(self, t):
        objs = self.scene.objects
        if not self.scene.has("emissive_flicker"):
            return np.zeros(len(objs))
        e = np.array([o.material.emission for o in objs], float)
        hz = np.array([o.material.flicker_hz for o in objs], float)
        wave = 0.6 + 0.3 * np.sin(2 * np.pi * hz * t / FPS + self.flicker_phase)
        return e * np.clip(wave + 0.25 * self.noise[t + 1], 0.0, 1.0)

    def state(self, t) -> FrameState:
        cam = self.camera(self.phase[t + 1] + self.offset[t])
        prev = self.camera(self.phase[t] + self.offset[t])  # same shot: a cut has no motion
        pos, yaw = self.objects(t)
        ppos, pyaw = self.objects(t - 1)
        return FrameState(cam, prev, pos, yaw, ppos, pyaw, self.light(t), self.emission(t),
                          bool(self.cuts[t]), self.exposure(t))


def timeline(scene: Scene, split: str, index: int, length: int, aspect: float):
    """The ``FrameState`` of each frame of one video."""
    tl = _Timeline(scene, video_seed(scene.name, split, index), length)
    tl.aspect = aspect
    return [tl.state(t) for t in range(length)]
