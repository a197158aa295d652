"""Benchmark: render-side cost of each optional simulator effect, ms per 64×64 capture.

Each row renders the same random poses with the scene reused (one load, poses updated in place)
at 1 spp and at 16 spp (``render.spp`` override) and reports the median ms per render, the extra
over the point-lamp baseline at 1 spp, and the extra per additional sample per pixel — the two
numbers `simulator.planner.EFFECT_MS_64` holds. The sensor stages are timed by switching each
off in turn. Run:
    .venv/bin/python benchmarks/bench_effects.py [--n 30] [--variant scalar_rgb]
The table in docs/simulator.md is this script's output.
"""

from __future__ import annotations

import argparse
import gc
import time
from pathlib import Path

import numpy as np
from _common import random_positions

from brdfdata.data_paths import find_data
from simulator.planner import plan_effects
from simulator.render import Renderer
from simulator.scene import Scene, SensorSpec, load_scene
from simulator.sensor import Sensor

__all__ = ["main", "effect_scenes", "bench_effects", "bench_stages"]

# The repository's own copy, found by the data resolver (data/README.md; $GONIO_DATA first).
PAPER = "rgl_brdf/paper_white_rgb.bsdf"
SCENES = Path(__file__).resolve().parent.parent / "configs" / "scenes"


def effect_scenes() -> dict[str, dict]:
    """Scene overrides, one per effect, over a Lambertian 64×64 baseline with a point lamp."""
    return {
        "baseline (point, direct)": {},
        "light_spot": {"light": {"type": "spot"}},
        "light_area": {"light": {"type": "area"}},
        "holder (black: shadows)": {"holder": {"rim_height_m": 0.005}},
        "stray_light": {"stray_light": {"radiance_W_m2_sr": [0.05, 0.05, 0.05]}},
        "path_integrator (rim ρ=0.5, 1 spp)": {
            "holder": {"rim_height_m": 0.005, "reflectance": [0.5, 0.5, 0.5]},
        },
        "material: measured paper": {
            "material": {"type": "measured", "filename": str(find_data(PAPER))}
        },
        "material: model torrance-sparrow": {
            "material": {
                "type": "model",
                "parameters": {"kd": 0.3, "ks": 0.5, "m": 0.2, "ior": 1.5},
            }
        },
    }


def _renderer(overrides: dict, variant: str | None, spp: int) -> Renderer:
    ov = dict(overrides)
    ov["render"] = {**ov.get("render", {}), "spp": spp}
    scene = Scene.model_validate({"camera": {"resolution": [64, 64], "fov_deg": 8.0}, **ov})
    return Renderer(scene, variant=variant)


def bench_effects(n: int, variant: str | None, spps=(1, 16)) -> dict[tuple[str, int], float]:
    """ms per render (minimum over n poses) for every effect scene and spp.

    One renderer alive at a time, as in the simulated camera: drjit's symbolic calls trace every
    live BSDF/emitter instance, so keeping many scenes alive would slow them all down. Each is
    warmed first (the first render compiles kernels); the minimum drops the stalls a
    shared machine causes.
    """
    lights, cams = random_positions(n, np.random.default_rng(0), 70)
    out = {}
    for name, ov in effect_scenes().items():
        for spp in spps:
            r = _renderer(ov, variant, spp)
            r.render(lights[0], cams[0])
            r.render(lights[1], cams[1])
            times = []
            for k in range(n):
                t0 = time.perf_counter()
                r.render(lights[k], cams[k])
                times.append(time.perf_counter() - t0)
            out[(name, spp)] = float(np.min(times)) * 1e3
            del r
            gc.collect()
    return out


def render_capture_ms(scene: Scene, n: int, variant: str | None) -> float:
    """minimum ms of render + sensor capture for a whole scene at its planned settings."""
    r = Renderer(scene, variant=variant)
    sensor = Sensor(scene.sensor, scene.camera.f_number, rng=0, intrinsics=r.intrinsics)
    lights, cams = random_positions(n, np.random.default_rng(0), 70)
    sensor.capture(r.render(lights[0], cams[0]), 0.01)
    times = []
    for k in range(n):
        t0 = time.perf_counter()
        sensor.capture(r.render(lights[k], cams[k]), 0.01)
        times.append(time.perf_counter() - t0)
    del r
    gc.collect()
    return float(np.min(times)) * 1e3


def bench_stages(n: int) -> dict[str, float]:
    """ms per 64×64 capture of each optional sensor stage: the full pipeline minus the pipeline
    with that stage switched off (interleaved captures, minimum over n). Bayer comes out
    negative: after it the later stages work on one plane instead of three."""
    rad = np.full((64, 64, 3), 0.1, np.float32)
    intr = {"fx": 400.0, "fy": 400.0, "cx": 31.5, "cy": 31.5}
    on = {
        "vignetting": True,
        "bayer": "RGGB",
        "prnu": 0.01,
        "dark_current_e_s": 10.0,
        "dsnu_e": 1.0,
        "noise": True,
        "read_noise_e": 3.0,
    }
    # stage -> spec keys that switch it off (shot noise: noise=False also drops read noise,
    # so it is measured against a pipeline that already has no read noise).
    variants = {
        "all stages": {},
        "vignetting": {"vignetting": False},
        "bayer": {"bayer": None},
        "prnu": {"prnu": 0.0},
        "dark_current": {"dark_current_e_s": 0.0},
        "dsnu": {"dsnu_e": 0.0},
        "read_noise": {"read_noise_e": 0.0},
        "shot_noise": {"noise": False, "read_noise_e": 0.0},
    }
    sensors = {
        k: Sensor(SensorSpec(**{**on, **v}), 4.0, rng=0, intrinsics=intr)
        for k, v in variants.items()
    }
    times: dict[str, list[float]] = {k: [] for k in sensors}
    for _ in range(n):
        for k, sensor in sensors.items():
            t0 = time.perf_counter()
            sensor.capture(rad, 0.01)
            times[k].append(time.perf_counter() - t0)
    p25 = {k: float(np.min(v)) * 1e3 for k, v in times.items()}
    out = {"all stages": p25["all stages"]}
    for k in variants:
        if k == "all stages":
            continue
        ref = p25["read_noise"] if k == "shot_noise" else p25["all stages"]
        out[k] = ref - p25[k]
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=60)
    ap.add_argument("--variant", default=None)
    args = ap.parse_args(argv)
    names = list(effect_scenes())
    t = bench_effects(args.n, args.variant)
    base = names[0]
    print(f"variant: {Renderer(Scene()).variant}; minimum over {args.n} poses, 64×64")
    hdr = f"{'effect':<36}{'ms @1spp':>10}{'ms @16spp':>11}{'extra @1':>10}{'extra/spp':>11}"
    print(hdr)
    rows = {}
    for name in names:
        ms1, ms16 = t[(name, 1)], t[(name, 16)]
        extra1 = ms1 - t[(base, 1)]
        per_spp = ((ms16 - t[(base, 16)]) - extra1) / 15.0
        rows[name] = (ms1, ms16, extra1, per_spp)
        print(f"{name:<36}{ms1:>10.2f}{ms16:>11.2f}{extra1:>10.2f}{per_spp:>11.3f}")
    base_per_spp = (t[(base, 16)] - t[(base, 1)]) / 15.0
    print(f"{'(baseline, per extra spp)':<36}{'':>31}{base_per_spp:>11.3f}")
    print()
    # Effects combined, at the planned spp/depth: the planner's estimate against the measurement.
    for path in sorted(SCENES.glob("*.toml")):
        scene = load_scene(path)
        plan = plan_effects(scene, variant=args.variant)
        ms = render_capture_ms(scene, args.n, args.variant)
        print(
            f"{path.name:<22} {plan.integrator:>6} depth {plan.max_depth:<2} spp {plan.spp:<4}"
            f" planned {plan.total_ms:7.2f} ms   measured {ms:7.2f} ms (render + sensor)"
        )
    print()
    print(f"{'sensor stage (64×64, 3 planes)':<38}{'ms':>10}")
    for stage, ms in bench_stages(max(args.n, 200)).items():
        print(f"{stage:<38}{ms:>10.3f}")
    return rows


if __name__ == "__main__":
    main()
