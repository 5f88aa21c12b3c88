"""The scene simulator: scenes that declare their effects, and a renderer that
computes only those."""

from jtus.sim.randomized import random_scene
from jtus.sim.scene import EFFECTS, Light, Material, Object, Path, Scene, from_json, to_json
from jtus.sim.suite import NAMES as SCENES
from jtus.sim.suite import get as get_scene
from jtus.sim.suite import with_effects
from jtus.sim.video import VideoRenderer, render_video

__all__ = ["EFFECTS", "Light", "Material", "Object", "Path", "SCENES", "Scene", "VideoRenderer",
           "from_json", "get_scene", "random_scene", "render_video", "to_json",
           "with_effects"]
