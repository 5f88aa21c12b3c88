"""Camera paths through mesh scenes: walks and flights that do not go through walls.

A video starts at one of the scene's spawn points (its seed picks which, and whether
it walks at eye height over the floor or flies). Each frame the camera moves along its
heading at a slowly changing speed and turns with a slowly changing rate; rays cast
ahead keep it off walls (it turns toward the side with more room), rays cast down keep
a walker at eye height. Holds stop it for some frames (the static case), and with
``camera_cut`` it jumps to another spawn point every ``CUT_EVERY`` frames. Without
``camera_motion`` it stays where it starts.
"""

from __future__ import annotations

import numpy as np

from jtus.sim.mesh import FPS, FrameState, MeshRenderer
from jtus.sim.paths import look_at, video_seed

EYE = 1.3        # metres above the floor a walker's eye keeps
ROOM = 1.2       # metres kept free ahead
OPEN = 5.0       # closer than this ahead, the heading drifts toward open space
CUT_EVERY = 24
HOLD = 8


def _heading(yaw, pitch):
    """Unit view direction: yaw about +y (0 looks along +x), pitch up."""
    return np.array([np.cos(pitch) * np.cos(yaw), np.sin(pitch), -np.cos(pitch) * np.sin(yaw)])


def _free(r: MeshRenderer, eye, direction, poses):
    """Distance to the nearest surface from ``eye`` along ``direction`` (inf: none)."""
    t, *_ = r.nearest(eye[None], direction[None], poses)
    return float(t[0])


def _step(r, eye, yaw, pitch, speed, fly, pose):
    """One frame's move: ``(eye, yaw)`` after stepping ``speed`` metres along the
    heading, turned away from walls (toward open space), a walker eased onto eye height
    over the floor."""
    ahead = _heading(yaw, pitch if fly else 0.0)
    turn = 0.0
    if _free(r, eye, ahead, pose) < OPEN:  # drift toward the side with more room
        left = _free(r, eye, _heading(yaw + 0.5, 0.0), pose)
        right = _free(r, eye, _heading(yaw - 0.5, 0.0), pose)
        turn = 0.05 * np.clip((min(left, 50) - min(right, 50)) / OPEN, -1, 1)
    for _ in range(12):
        if _free(r, eye, ahead, pose) > ROOM + speed:
            break
        left = _free(r, eye, _heading(yaw + 0.5, 0.0), pose)
        right = _free(r, eye, _heading(yaw - 0.5, 0.0), pose)
        yaw += 0.25 if left >= right else -0.25
        ahead = _heading(yaw, pitch if fly else 0.0)
    else:
        speed = 0.0
    nxt = eye + speed * ahead
    if not fly:
        down = _free(r, nxt + np.array([0, 0.5, 0]), np.array([0.0, -1.0, 0.0]), pose)
        if not np.isfinite(down):
            return eye, yaw + turn  # no floor ahead: stay
        nxt[1] += 0.3 * (EYE - (down - 0.5))  # ease onto eye height
    return nxt, yaw + turn


def _start(sc, rng):
    eye, yaw = sc.spawns[int(rng.integers(len(sc.spawns)))]
    return np.array(eye, float), float(yaw) + rng.uniform(-0.6, 0.6)


def timeline(r: MeshRenderer, split, index, length, aspect):
    """The ``FrameState`` of each frame of one video of ``r.scene``."""
    sc = r.scene
    rng = np.random.default_rng(video_seed(sc.name, split, index))
    fly = rng.random() < 0.3
    eye, yaw = _start(sc, rng)
    t0 = rng.uniform(0, 20)  # seconds into the movers' and flicker's cycles
    speed = sc.speed * rng.uniform(0.6, 1.4) * (2.0 if fly else 1.0)
    f_turn, p_turn = rng.uniform(0.02, 0.08), rng.uniform(0, 6)
    f_pitch, p_pitch = rng.uniform(0.02, 0.06), rng.uniform(0, 6)
    pitch_amp = 0.35 if fly else 0.12
    still = np.zeros(length + 1, bool)
    if length > HOLD + 4:
        h0 = int(rng.integers(2, length - HOLD))
        still[h0:h0 + HOLD] = True
    light_center = eye + np.array([0.0, 0.6, 0.0])
    light_phase = rng.uniform(0, 2 * np.pi)
    rest = [p.motion.pose(0.0) for p in r.parts]

    def poses(frame):
        if not sc.has("object_motion"):
            return rest
        return [p.motion.pose(t0 + frame / FPS) for p in r.parts]

    cams, cuts = [], np.zeros(length, bool)
    pitch = 0.0
    for f in range(-1, length):
        if sc.has("camera_cut") and f > 0 and f % CUT_EVERY == 0:
            eye, yaw = _start(sc, rng)
            cuts[f] = True
        elif sc.has("camera_motion") and f >= 0 and not still[f]:
            pitch = pitch_amp * np.sin(2 * np.pi * f_pitch * f + p_pitch)
            step = speed * (1 + 0.3 * np.sin(0.1 * f + p_turn))
            eye, yaw = _step(r, eye, yaw, pitch, step, fly, poses(f))
            yaw += 0.03 * np.sin(2 * np.pi * f_turn * f + p_turn)
        cams.append(look_at(eye, eye + _heading(yaw, pitch), sc.fov_y, aspect))
    states = []
    for f in range(length):
        prev = cams[f + 1] if cuts[f] else cams[f]  # a cut's first frame has no history
        a = light_phase + (0.05 * f if sc.has("moving_light") else 0.0)
        light = light_center + np.array([2.0 * np.cos(a), 0.3 * np.sin(2 * a), 2.0 * np.sin(a)])
        states.append(FrameState(cams[f + 1], prev, poses(f), poses(f - 1), t0 + f / FPS,
                                 light, bool(cuts[f]), 1.0))
    return states
