"""Backend wiring: the front door is the only place that knows the simulator exists.

A rig config that names simulated devices (`dxlsim://`, `lightsim://`, camera backend "sim",
clock "sim") gets a simulated world built here, which registers those names; the acquisition
code then opens them exactly as it would open real devices.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from acquisition.config import RigConfig

__all__ = ["needs_simulator", "prepare_backends"]


def needs_simulator(rig: RigConfig) -> bool:
    return (
        rig.bus.url.startswith("dxlsim://")
        or rig.light.url.startswith("lightsim://")
        or rig.camera.backend == "sim"
        or rig.clock == "sim"
    )


def prepare_backends(rig: RigConfig, scene: Any | None = None) -> Any | None:
    """Build the simulated world when the rig asks for one; return it (or None)."""
    if not needs_simulator(rig):
        return None
    from simulator.scene import Scene, load_scene
    from simulator.world import SimWorld

    if scene is None:
        if rig.scene is None:
            from gonio.errors import UserError

            raise UserError("the rig uses simulated devices but names no scene (key `scene`)")
        scene = load_scene(Path(rig.scene))
    elif isinstance(scene, dict):
        scene = Scene.model_validate(scene)
    return SimWorld(rig, scene)
