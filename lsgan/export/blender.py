"""The Blender scene settings that play an exported motion at its own length and speed.

Blender's importers leave the scene at its defaults, 24 fps and frames 1-250, unless told otherwise (measured
with Blender 5.0, ``pip install bpy``): a 20 fps BVH then plays 1.2x too fast (unless the importer's "Update
Scene FPS" is ticked) over frames 1-250, and a GLB keeps its speed (glTF keys are in seconds) over frames 1-250.
The BVH importer's "Update Scene Duration" only lengthens the scene, never shortens it: a 131-frame BVH still
plays 250 frames, so the scene's end frame has to be set to the motion's length by hand, for BVH and GLB alike.
The settings below are what ``lsgan export`` prints and ``tests/test_blender.py`` applies in Blender.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SceneSettings:
    """Blender's ``scene.render.fps`` / ``fps_base`` (the rate is fps / fps_base) and the frame range."""

    fps: int
    fps_base: float
    frame_start: int
    frame_end: int


def scene_settings(fmt: str, fps: float, frames: int) -> SceneSettings:
    """For a ``fmt`` ("bvh" or "glb") file of ``frames`` frames at ``fps``: the BVH importer keys frames 1..T,
    played at fps through a fractional base; the glTF importer puts the key at t seconds on frame t x (fps x
    fps_base), so a GLB wants a whole rate with base 1 (measured: at 12 / base 0.96 a 12.5 fps motion played 8%
    fast) and ends on the frame of its last key."""
    rate = max(1, round(fps))
    if fmt == "bvh":
        return SceneSettings(rate, rate / fps, 1, frames)
    return SceneSettings(rate, 1.0, 0, round((frames - 1) * rate / fps))


def blender_hint(fmt: str, fps: float, frames: int, scale: float = 0.01) -> str:
    """One line for the user: the import options and scene settings that keep length and speed (``scale``: the
    BVH's metres per unit, 0.01 for ours in centimetres, a rig's own otherwise)."""
    s = scene_settings(fmt, fps, frames)
    rate = f"{s.fps} fps" + ("" if s.fps_base == 1 else f" / base {s.fps_base:.4f}")
    scene = (f"Output > Frame Range: Start {s.frame_start}, End {s.frame_end} "
             f"(scene.frame_start, scene.frame_end = {s.frame_start}, {s.frame_end})")
    if fmt == "bvh":
        return (f"Blender: File > Import > Motion Capture (.bvh) with Scale {scale:g} and 'Update Scene FPS' ticked "
                f"(or Output > Frame Rate {rate}), then {scene}: 'Update Scene Duration' never shortens the "
                "250-frame default; otherwise it plays at 24 fps over frames 1-250")
    return (f"Blender: set Output > Frame Rate to {rate} before File > Import > glTF 2.0, then {scene}; "
            "otherwise it plays over frames 1-250")
