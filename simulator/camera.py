"""The simulated camera device: Mitsuba radiance → EMVA 1288 sensor → EXR or DNG bytes.

It implements `acquisition.protocols.Camera`. Where the arms *physically* are comes from the
servo emulator's true positions (which include any injected mounting offset), not from what
the driver commanded — so a calibration error in the rig shows up in the images as it would
on a real rig. What it faces follows the emulated world (`WorldView`): a capped lens gives a
dark frame, the flat source a uniform field, and the holder the sample, the reference target
or a calibration board — as the operator's (simulated) hands left them.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from acquisition.clock import Clock
from acquisition.protocols import Frame
from simulator.arms import ArmPose
from simulator.frames import encode_dng, encode_exr
from simulator.render import Renderer
from simulator.scene import Scene
from simulator.sensor import Sensor

__all__ = ["SimCamera", "WorldView"]


def _material_dict(material) -> dict:
    return material.model_dump() if hasattr(material, "model_dump") else dict(material)


@dataclass
class WorldView:
    """What the camera faces. `state` has `lens` ("open" | "capped" | "flat"), `holder`
    ("sample" | "reference" | "board") and `board` (the board's fields); the reference target's
    true material comes from `reference_material()`."""

    state: Any
    reference_material: Callable[[], Any] | None = None
    reference_size_m: float | None = None


class SimCamera:
    def __init__(
        self,
        scene: Scene,
        clock: Clock,
        pose_m: Callable[[], ArmPose],
        light_level: Callable[[], float],
        readout_s: float = 0.05,
        renderer: Renderer | None = None,
        world: WorldView | None = None,
    ) -> None:
        self.scene = scene
        self.clock = clock
        self._pose = pose_m  # the arms now (simulator.arms: lamp position, camera to_world)
        #: The world's own record of every lit capture: the pose it was rendered from.
        self.rendered: list[ArmPose] = []
        self._light_level = light_level
        self.readout_s = readout_s
        self.renderer = renderer or Renderer(scene)
        self.sensor = Sensor(
            scene.sensor,
            scene.camera.f_number,
            rng=np.random.default_rng(scene.seed),
            intrinsics=self.renderer.intrinsics,
        )
        self.captures = 0
        self._reference_renderers: dict[str, Renderer] = {}
        self.flat_falloff_runs = 0  # flat frames the source's non-uniformity was applied to
        self._boards: dict[str, Any] = {}
        self.world = world

    def supported_exposures(self) -> tuple[float, float]:
        return (1e-5, 30.0)

    @property
    def clip_level_dn(self) -> float:
        """Highest DN that is certainly not clipped: the full well sits below the ADC's white
        level, and read noise is added after the well clips, so stay 6σ_read below it
        (at 4σ one clipped value in ~30 000 would pass as unsaturated and get a long exposure's
        large HDR weight; 6σ makes that ~1e-9)."""
        s = self.scene.sensor
        well = s.black_level_dn + (s.full_well_e - 6.0 * s.read_noise_e) / s.gain_e_per_dn
        return float(math.floor(min(well, 2**s.adc_bits - 1)))

    def describe(self) -> dict[str, Any]:
        """What the device itself reports (a real camera's model and serial): identity and
        output format only — calibration uses the rig file's description, never this."""
        k = self.renderer.intrinsics
        return {
            "model": "gonio simulated camera (Mitsuba + EMVA 1288)",
            "serial": f"sim-{self.scene.seed}",
            "format": self.scene.camera.format,
            "resolution": [int(k["width"]), int(k["height"])],
        }

    def capture(self, exposure_s: float) -> Frame:
        """A frame of whatever the camera faces now (see WorldView)."""
        st = None if self.world is None else self.world.state
        if st is not None and st.lens == "capped":
            return self.capture_dark(exposure_s)
        if st is not None and st.lens == "flat":
            return self.capture_flat(exposure_s, self.scene.flat_source_radiance_W_m2_sr)
        pose = self._pose()
        level = float(self._light_level())
        if st is not None and st.holder == "reference":
            material = self.world.reference_material()
            renderer = self.reference_renderer(material, size_m=self.world.reference_size_m)
        elif st is not None and st.holder == "board":
            renderer = self._board_renderer(st.board)
        else:
            renderer = self.renderer
        self.rendered.append(pose)
        radiance = renderer.render(
            pose.light_m, pose.camera_m, intensity_scale=level, camera_to_world=pose.camera_to_world
        )
        return self._expose(radiance, exposure_s)

    def _board_renderer(self, board: Any) -> Renderer:
        """A calibration board printed on a Lambertian sheet in the sample's place, lit by the
        lamp (simulator.render.board_renderer), one renderer per board."""
        key = repr(sorted(vars(board).items()))
        if key not in self._boards:
            from simulator.render import board_renderer

            self._boards[key] = board_renderer(
                self.scene, board, variant=self.renderer.variant
            ).renderer
        return self._boards[key]

    # -- calibration frames (what a lab does with a lens cap and an integrating sphere) ----------
    def capture_dark(self, exposure_s: float) -> Frame:
        """A dark frame: lens capped, zero radiance, same sensor (dark current, DSNU, noise)."""
        k = self.renderer.intrinsics
        return self._expose(np.zeros((int(k["height"]), int(k["width"]), 3)), exposure_s)

    def flat_radiance(self, exposure_s: float, fill: float = 0.5) -> float:
        """Uniform radiance (W m⁻² sr⁻¹) that fills ``fill`` of the full well on axis in
        ``exposure_s`` (inverts the sensor's irradiance equation; a lab sets the sphere's level
        from the histogram instead)."""
        s = self.scene.sensor
        photon_j = 6.62607015e-34 * 299792458.0 / s.wavelength_m
        per_radiance = (
            math.pi
            / (4.0 * self.scene.camera.f_number**2)
            * s.pixel_pitch_m**2
            * exposure_s
            / photon_j
            * s.quantum_efficiency
        )
        return fill * s.full_well_e / per_radiance

    def capture_flat(self, exposure_s: float, radiance_W_m2_sr: float | None = None) -> Frame:
        """A flat frame: the camera facing a uniform (Lambertian, white) radiance field, such as
        an integrating sphere's port; vignetting, PRNU and noise act as on any frame."""
        k = self.renderer.intrinsics
        L = self.flat_radiance(exposure_s) if radiance_W_m2_sr is None else radiance_W_m2_sr
        field = np.full((int(k["height"]), int(k["width"]), 3), L)
        if self.scene.flat_source_falloff:  # a non-uniform source (scene flat_source_falloff)
            self.flat_falloff_runs += 1
            field *= (1.0 - self.scene.flat_source_falloff * flat_source_profile(k))[..., None]
        return self._expose(field, exposure_s)

    def capture_reference(
        self,
        exposure_s: float,
        light_pos_m,
        camera_pos_m,
        *,
        level: float = 1.0,
        material: object | None = None,
        reflectance: float = 0.99,
    ) -> Frame:
        """A capture of the reference target (``render.reference_target_scene``: Lambertian of
        albedo ``reflectance``, or ``material``) put in the sample's place, with the lamp at
        relative ``level``, at the given light and camera positions (a lab swaps the sample for
        the target and drives the arms to the reference poses). Same sensor, so the same fixed
        pattern, vignetting and noise as the measurement frames."""
        renderer = self.reference_renderer(material, reflectance)
        radiance = renderer.render(light_pos_m, camera_pos_m, intensity_scale=float(level))
        return self._expose(radiance, exposure_s)

    def reference_renderer(
        self,
        material: object | None = None,
        reflectance: float = 0.99,
        size_m: float | None = None,
    ) -> Renderer:
        """The renderer of the reference target (one per target, loaded once). Its
        ``truth_bsdf`` is Mitsuba's own f_r of the target — what a lab's calibration certificate
        tabulates (tests build their f_ref table from it). ``size_m``: the target's side
        (default: the sample's)."""
        key = json.dumps(None if material is None else _material_dict(material), sort_keys=True)
        key += f"/{reflectance!r}/{size_m!r}"
        if key not in self._reference_renderers:
            from simulator.render import reference_target_scene

            scene = reference_target_scene(self.scene, reflectance, material, size_m=size_m)
            self._reference_renderers[key] = Renderer(scene, variant=self.renderer.variant)
        return self._reference_renderers[key]

    def _expose(self, radiance: np.ndarray, asked_s: float) -> Frame:
        # The exposure the sensor can take (a whole number of line periods, or the nearest
        # shutter speed: simulator.scene.CameraSpec), reported in the frame as a camera does.
        exposure_s = self.scene.camera.exposure_taken_s(asked_s)
        dn = self.sensor.capture(radiance, exposure_s)
        self.captures += 1
        meta = {
            "exposure_s": float(exposure_s),
            "exposure_commanded_s": float(asked_s),
            "black_level_dn": self.scene.sensor.black_level_dn,
            "white_level": 2**self.scene.sensor.adc_bits - 1,
            "capture": self.captures,
        }
        if self.scene.camera.format == "dng":
            if dn.ndim != 2:
                raise ValueError('DNG output needs a Bayer sensor (set sensor.bayer = "RGGB")')
            data = encode_dng(
                dn,
                meta,
                cfa_pattern=self.scene.sensor.bayer,
                black_level=self.scene.sensor.black_level_dn,
                white_level=2**self.scene.sensor.adc_bits - 1,
                exposure_s=exposure_s,
            )
            suffix = ".dng"
        else:
            data = encode_exr(dn.astype(np.float32), meta)
            suffix = ".exr"
        # Lab time: the shutter is open for the exposure, then the sensor reads out.
        self.clock.sleep(exposure_s + self.readout_s)
        return Frame(data=data, suffix=suffix, metadata=meta)


def flat_source_profile(intrinsics: dict) -> np.ndarray:
    """ρ/ρ_corner per pixel (0 on the optical axis, 1 at the frame's farthest corner), ρ =
    ((u − cx)/fx)² + ((v − cy)/fy)²: the shape of the flat source's falloff."""
    h, w = int(intrinsics["height"]), int(intrinsics["width"])
    vv, uu = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    rho = ((uu - intrinsics["cx"]) / intrinsics["fx"]) ** 2 + (
        (vv - intrinsics["cy"]) / intrinsics["fy"]
    ) ** 2
    return rho / rho.max()
