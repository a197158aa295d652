"""Bad rig and plan configs give one clear line naming the key and the allowed range."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from acquisition.config import load_plan, load_rig
from acquisition.kinematics import Unreachable
from acquisition.plans import build_plan
from plumbing.config import ConfigError


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def _rig_text(configs: Path) -> str:
    """sim.toml with its relative file paths made absolute, so a copy elsewhere loads."""
    text = (configs / "rigs" / "sim.toml").read_text()
    return text.replace('"sim-camera.json"', f'"{configs / "rigs" / "sim-camera.json"}"')


def test_shipped_configs_load(configs: Path) -> None:
    rig = load_rig(configs / "rigs" / "sim.toml")
    plan = load_plan(configs / "plans" / "demo.toml")
    built = build_plan(rig, plan)
    # "about 60 poses" (issue #2): the demo plan is 3 θi × 7 θo × 3 Δφ, all reachable.
    assert 50 <= len(built.poses) <= 80
    assert Path(rig.scene).exists()


def test_unknown_key_names_the_key(tmp_path: Path, configs: Path) -> None:
    text = _rig_text(configs).replace("settle_s = 0.2", "settle_s = 0.2\nsetle_time = 3")
    with pytest.raises(ConfigError) as exc:
        load_rig(_write(tmp_path, "rig.toml", text))
    msg = str(exc.value)
    assert "\n" not in msg
    assert "setle_time" in msg and "unknown key" in msg


def test_angle_out_of_range_names_key_and_range(tmp_path: Path, configs: Path) -> None:
    text = (
        (configs / "plans" / "demo.toml")
        .read_text()
        .replace("theta_i_deg = [20.0", "theta_i_deg = [95.0")
    )
    with pytest.raises(ConfigError) as exc:
        load_plan(_write(tmp_path, "plan.toml", text))
    msg = str(exc.value)
    assert "\n" not in msg
    assert "theta_i_deg" in msg and "[0, 90)" in msg


def test_duplicate_servo_id(tmp_path: Path, configs: Path) -> None:
    text = _rig_text(configs).replace("id = 4", "id = 3")
    with pytest.raises(ConfigError) as exc:
        load_rig(_write(tmp_path, "rig.toml", text))
    assert re.search(r"duplicate servo id 3", str(exc.value))


def test_wrong_type(tmp_path: Path, configs: Path) -> None:
    text = _rig_text(configs).replace("baudrate = 57600", 'baudrate = "fast"')
    with pytest.raises(ConfigError) as exc:
        load_rig(_write(tmp_path, "rig.toml", text))
    assert "bus.baudrate" in str(exc.value)


def test_unreachable_explicit_pose(tmp_path: Path, configs: Path) -> None:
    rig = load_rig(configs / "rigs" / "sim.toml")
    # Light and camera 2° apart: closer than min_separation_deg = 5, the light occludes.
    plan = _write(
        tmp_path,
        "plan.toml",
        'type = "explicit"\nposes_deg = [[30.0, 0.0, 32.0, 0.0]]\n',
    )
    with pytest.raises(Unreachable) as exc:
        build_plan(rig, load_plan(plan))
    assert "min_separation_deg" in str(exc.value)
