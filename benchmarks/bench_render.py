"""Benchmark: ms per simulated 64×64 capture (Mitsuba render + EMVA sensor), scene reused.

Target (issue 4): ≤ 10 ms per capture in llvm_ad_rgb. Run:
    .venv/bin/python benchmarks/bench_render.py [--n 200] [--variant scalar_rgb] [--bayer]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import random_positions

from simulator.frames import encode_dng, encode_exr
from simulator.planner import plan_effects
from simulator.render import Renderer
from simulator.scene import RoughPlasticMaterial, Scene, SensorSpec
from simulator.sensor import Sensor

__all__ = ["main", "bench"]


def bench(n: int = 200, variant: str | None = None, bayer: bool = False) -> dict:
    scene = Scene(
        material=RoughPlasticMaterial(alpha=0.2),
        sensor=SensorSpec(bayer="RGGB" if bayer else None, prnu=0.005),
    )
    t0 = time.perf_counter()
    r = Renderer(scene, variant=variant)
    load_ms = (time.perf_counter() - t0) * 1e3
    sensor = Sensor(scene.sensor, scene.camera.f_number, rng=0, intrinsics=r.intrinsics)
    lights, cams = random_positions(n, np.random.default_rng(0), 80)
    r.render(lights[0], cams[0])  # warm-up: kernel compilation / cache load
    t_render = t_sensor = t_encode = 0.0
    for k in range(n):
        a = time.perf_counter()
        img = r.render(lights[k], cams[k])
        b = time.perf_counter()
        dn = sensor.capture(img, 0.01)
        c = time.perf_counter()
        if bayer:
            encode_dng(dn, {"exposure_s": 0.01}, white_level=sensor.white_level)
        else:
            encode_exr(dn.astype(np.float32), {"exposure_s": 0.01})
        d = time.perf_counter()
        t_render += b - a
        t_sensor += c - b
        t_encode += d - c
    return {
        "variant": r.variant,
        "n": n,
        "load_ms": load_ms,
        "render_ms": t_render / n * 1e3,
        "sensor_ms": t_sensor / n * 1e3,
        "capture_ms": (t_render + t_sensor) / n * 1e3,
        "encode_ms": t_encode / n * 1e3,
        "plan": plan_effects(scene, variant=r.variant),
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--variant", default=None)
    ap.add_argument("--bayer", action="store_true")
    args = ap.parse_args(argv)
    res = bench(args.n, args.variant, args.bayer)
    print(f"variant {res['variant']}, {res['n']} poses, 64x64, scene reused")
    print(f"scene load      {res['load_ms']:8.1f} ms (once)")
    print(f"render          {res['render_ms']:8.3f} ms/capture")
    print(f"sensor          {res['sensor_ms']:8.3f} ms/capture")
    print(f"render+sensor   {res['capture_ms']:8.3f} ms/capture  (target <= 10 ms in llvm_ad_rgb)")
    print(f"encode ({'dng' if args.bayer else 'exr'})    {res['encode_ms']:8.3f} ms/capture")
    print()
    print("planner estimate:")
    print(res["plan"].describe())
    return res


if __name__ == "__main__":
    main()
