"""Regenerate the bad-input corpus used by tests/gonio/test_bad_inputs.py.

    .venv/bin/python tests/bad_inputs/make_corpus.py

Deterministic: the simulated runs are rendered with the scenes' fixed seeds, and every
timestamp, version string and random byte is replaced by a fixed value, so a rerun gives the
same content. Every file is kept below 50 kB (checked at the end). The cases themselves — which
command reads which file, and the words its one-line error must contain — are in cases.toml.
"""

from __future__ import annotations

import csv
import io
import json
import re
import shutil
import sqlite3
import sys
import tempfile
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent
FIXED_TIME = "2026-01-01T00:00:00.000+00:00"
MAX_BYTES = 50_000

# -- configs ---------------------------------------------------------------------------------
# A valid two-arm rig with no scene (so it is self-contained once copied); each bad rig below
# is this text with one mistake.
RIG_OK = """\
name = "corpus-rig"
clock = "sim"
[bus]
url = "dxlsim://corpus"
[light]
url = "lightsim://corpus"
[camera]
resolution = [64, 64]
pixel_pitch_m = 5e-6
focal_length_m = 0.0022881066
f_number = 4.0
gain_e_per_dn = 2.0
black_level_dn = 64.0
white_level_dn = 15055.0
color_filter = "rgb"
bit_depth = 14
[sample]
size_m = 0.05
[[axes]]
role = "light_theta"
id = 1
min_deg = 0.0
max_deg = 88.0
[[axes]]
role = "light_phi"
id = 2
min_deg = -180.0
max_deg = 179.9
[[axes]]
role = "camera_theta"
id = 3
min_deg = 0.0
max_deg = 88.0
[[axes]]
role = "camera_phi"
id = 4
min_deg = -180.0
max_deg = 179.9
"""

PLAN_OK = """\
name = "corpus-plan"
type = "isotropic"
theta_i_deg = [30.0]
theta_o_deg = [0.0, 30.0]
exposures_s = [0.002]
"""

SCENE_OK = (REPO / "configs" / "scenes" / "demo.toml").read_text()


def _edit(text: str, old: str, new: str) -> str:
    assert old in text, old
    return text.replace(old, new, 1)


CONFIGS: dict[str, str] = {
    # rigs
    "rig_unknown_key.toml": _edit(RIG_OK, "[light]", "baud = 57600\n[light]"),
    "rig_wrong_type.toml": _edit(RIG_OK, "id = 3", 'id = "three"'),
    "rig_unit_in_value.toml": _edit(
        RIG_OK,
        "max_deg = 88.0",
        'max_deg = "1.5 rad"',
    ),
    "rig_unit_in_key.toml": RIG_OK + "[geometry]\nlight_distance_mm = 500\n",
    "rig_mm_value.toml": RIG_OK + "[geometry]\nlight_distance_m = 500\n",
    "rig_angle_out_of_range.toml": _edit(RIG_OK, "max_deg = 179.9", "max_deg = 400.0"),
    "rig_duplicate_id.toml": _edit(RIG_OK, "id = 4", "id = 2"),
    "rig_negative_intensity.toml": _edit(
        RIG_OK,
        'url = "lightsim://corpus"',
        'url = "lightsim://corpus"\nintensity_W_sr = [-1.0, 1.0, 1.0]',
    ),
    "rig_gear_ratio_huge.toml": _edit(
        RIG_OK, "max_deg = 88.0", "max_deg = 88.0\ngear_ratio = 1e300"
    ),
    "rig_missing_port.toml": _edit(RIG_OK, 'url = "dxlsim://corpus"\n', ""),
    "rig_absent_port.toml": _edit(
        _edit(
            _edit(RIG_OK, 'url = "dxlsim://corpus"', 'url = "/dev/ttyUSB-gonio-corpus-absent"'),
            'url = "lightsim://corpus"',
            'url = "/dev/ttyUSB-gonio-corpus-light"',
        ),
        'clock = "sim"',
        'clock = "system"',
    )
    .replace('backend = "sim"', "")
    .replace("[camera]\n", '[camera]\nbackend = "gphoto2"\n'),
    "rig_unknown_camera_backend.toml": _edit(
        RIG_OK, "[camera]\n", '[camera]\nbackend = "genicam"\n'
    ),
    "rig_missing_intrinsics.toml": RIG_OK + '[calibration]\nintrinsics = "camera-absent.json"\n',
    "rig_python_code.toml": _edit(
        RIG_OK, 'name = "corpus-rig"', "name = __import__('os').system('touch PWNED')"
    ),
    "rig.yaml": "name: corpus-rig\nbus: {url: dxlsim://corpus}\n",
    # plans
    "plan_unknown_key.toml": PLAN_OK + "theta_step = 10\n",
    "plan_wrong_type.toml": _edit(PLAN_OK, "theta_i_deg = [30.0]", 'theta_i_deg = "30"'),
    "plan_unit_in_value.toml": _edit(PLAN_OK, "exposures_s = [0.002]", 'exposures_s = ["2 ms"]'),
    "plan_angle_out_of_range.toml": _edit(PLAN_OK, "theta_i_deg = [30.0]", "theta_i_deg = [95.0]"),
    # Light and camera at the same direction: inside the rig's minimum separation.
    "plan_unreachable_pose.toml": (
        'name = "corpus-unreachable"\ntype = "explicit"\n'
        "poses_deg = [[30.0, 0.0, 30.0, 0.0]]\nexposures_s = [0.002]\n"
    ),
    # scenes
    "scene_unknown_key.toml": _edit(SCENE_OK, "seed = ", "sede = 1\nseed = "),
    "scene_wrong_type.toml": SCENE_OK + '\n[camera]\nf_number = "four"\n',
    "scene_angle_out_of_range.toml": SCENE_OK + "\n[camera]\nfov_deg = 400.0\n",
    # Scene values only Mitsuba would have refused, at the first render (before: a run left
    # failing the same way on every resume); refused before a run directory exists.
    "scene_model_bad_option.toml": (
        '[material]\ntype = "model"\nmodel = "torrance-sparrow"\n'
        'options = {distribution = "nope"}\nparameters = {kd = 0.3, ks = 0.2, m = 0.2}\n'
    ),
    "scene_unknown_conductor.toml": (
        '[material]\ntype = "roughconductor"\nconductor = "Unobtainium"\n'
    ),
    # A plan whose steps ask for ~10¹¹ poses (before: 24 GB and the OOM killer, no output).
    "plan_too_many_poses.toml": (
        'name = "corpus-huge"\ntype = "hemisphere"\ntheta_step_deg = 0.5\n'
        "phi_step_deg = 0.5\nexposures_s = [0.002]\n"
    ),
    # priors (gonio fit --priors): bounds wider than the model's range [0, 1]
    "priors_outside_range.toml": "[parameters.kd_R]\nlower = -1\nupper = 5\n",
}
# Rich markup in a value, which the error line must show as written (an unknown URL scheme:
# no device is opened).
# An answers file whose answers are a string, not a table of steps.
CONFIGS["answers_not_a_table.toml"] = 'answers = "yes"\n'
# Nested 5000 deep (Python's parsers recurse per level: a RecursionError, not an error line).
CONFIGS["rig_deep_nesting.toml"] = "x = " + "[" * 5000 + "]" * 5000 + "\n"
CONFIGS["rig_markup_in_url.toml"] = _edit(
    CONFIGS["rig_absent_port.toml"],
    "/dev/ttyUSB-gonio-corpus-absent",
    "bogus://[bold]corpus[/bold]",
)


def write_configs() -> None:
    d = HERE / "configs"
    d.mkdir(exist_ok=True)
    for name, text in CONFIGS.items():
        (d / name).write_text(text)
    # A directory where a config file is expected; it holds a good rig, as git keeps no empty
    # directories.
    (d / "rig_dir.toml").mkdir(exist_ok=True)
    (d / "rig_dir.toml" / "rig.toml").write_text(RIG_OK)


# -- runs ------------------------------------------------------------------------------------
def _base_run(dest: Path, scene) -> Path:
    """A one-capture simulated run with fixed timestamps."""
    from acquisition.config import PlanConfig
    from gonio.pipeline import AcquireSpec, acquire

    plan = PlanConfig.model_validate(
        {
            "name": "corpus",
            "type": "isotropic",
            "theta_i_deg": [30.0],
            "theta_o_deg": [20.0],
            "exposures_s": [0.004],
        }
    )
    res = acquire(
        dest,
        AcquireSpec(
            rig=REPO / "configs" / "rigs" / "sim.toml",
            progress=False,
            plan=plan,
            scene=scene,
            announce=False,
        ),
    )
    assert res.outcome.complete, res.outcome
    _normalise(dest)
    return dest


def _normalise(run: Path) -> None:
    """Fixed timestamps and version, so the corpus does not change when regenerated."""
    import tomllib

    import tomli_w

    doc = tomllib.loads((run / "run.toml").read_text())
    doc["gonio"]["started_at"] = FIXED_TIME
    doc["gonio"]["version"] = "0+corpus"
    doc.get("rig", {}).pop("scene", None)  # an absolute path of the machine that made it
    doc.get("rig", {}).get("calibration", {}).pop("intrinsics", None)  # the same
    if "intrinsics_source" in doc.get("camera", {}):
        source = doc["camera"]["intrinsics_source"]
        doc["camera"]["intrinsics_source"] = source.replace(f"{REPO}/", "")
    (run / "run.toml").write_text(tomli_w.dumps(doc))
    log = run / "log.jsonl"
    if log.exists():
        _fix_wall_times(log)
        log.write_text(re.sub(r'"ts": "[^"]*"', f'"ts": "{FIXED_TIME}"', log.read_text()))
    _sql(
        run, "UPDATE meta SET value = ? WHERE key IN ('created_at', 'completed_at')", (FIXED_TIME,)
    )
    _sql(run, "UPDATE captures SET started_at = ?, finished_at = ?", (FIXED_TIME, FIXED_TIME))
    _sql(run, "UPDATE events SET at = ?", (FIXED_TIME,))


def _fix_wall_times(path: Path) -> None:
    """Wall-clock durations differ on every run: fix them."""
    text = re.sub(r'("[a-z_]*wall[a-z_]*": )[-+0-9.eE]+', r"\g<1>0.0", path.read_text())
    path.write_text(text)


def _vacuum(db_path: Path) -> None:
    db = sqlite3.connect(db_path)
    db.execute("VACUUM")
    db.close()


def _sql(run: Path, statement: str, args: tuple = ()) -> None:
    db = sqlite3.connect(run / "manifest.sqlite")
    with db:
        db.execute(statement, args)
    db.close()
    _vacuum(run / "manifest.sqlite")


def _frame(run: Path) -> Path:
    (frame,) = sorted((run / "frames").iterdir())
    return frame


def _truncate(path: Path, fraction: float) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])


def _garbage(n: int, seed: int) -> bytes:
    return np.random.default_rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes()


def write_runs(work: Path) -> None:
    from calibration.reduce import ReduceOptions, reduce_run
    from fitting.fit import FitOptions, fit_samples
    from fitting.mcmc import McmcOptions
    from simulator.scene import load_scene

    runs = HERE / "run_dirs"
    if runs.exists():
        shutil.rmtree(runs)
    runs.mkdir()
    exr = _base_run(work / "exr", load_scene(REPO / "configs" / "scenes" / "demo.toml"))
    raw = load_scene(REPO / "configs" / "scenes" / "raw.toml")
    # No dark current, DSNU, PRNU or vignetting: the run then needs no dark/flat frames, which
    # keeps it to one small frame.
    raw = raw.model_copy(
        update={
            "sensor": raw.sensor.model_copy(
                update={"dark_current_e_s": 0.0, "dsnu_e": 0.0, "prnu": 0.0, "vignetting": False}
            )
        }
    )
    dng = _base_run(work / "dng", raw)

    def variant(name: str, base: Path) -> Path:
        dst = runs / name
        shutil.copytree(base, dst)
        return dst

    _truncate(_frame(variant("dng_truncated", dng)), 0.5)
    _frame(variant("dng_garbage", dng)).write_bytes(b"II*\x00" + _garbage(6000, 1))
    _truncate(_frame(variant("exr_truncated", exr)), 0.6)
    r = variant("exr_corrupt_header", exr)
    data = bytearray(_frame(r).read_bytes())
    data[8:200] = _garbage(192, 2)  # the attribute list: names, types and sizes scrambled
    _frame(r).write_bytes(bytes(data))

    r = variant("manifest_garbage", exr)
    (r / "manifest.sqlite").write_bytes(_garbage(8192, 3))
    r = variant("manifest_truncated", exr)
    _truncate(r / "manifest.sqlite", 0.3)
    r = variant("manifest_newer", exr)
    _sql(r, "UPDATE meta SET value = '99' WHERE key = 'schema_version'")
    r = variant("manifest_schema_superscript", exr)
    _sql(r, "UPDATE meta SET value = '²' WHERE key = 'schema_version'")
    r = variant("runtoml_newer", exr)
    text = (r / "run.toml").read_text()
    (r / "run.toml").write_text(_edit(text, "schema_version = 2", "schema_version = 99"))
    r = variant("runtoml_section_not_table", exr)
    text = (r / "run.toml").read_text()
    start, end = text.index("[gonio]"), text.index("[rig]")
    (r / "run.toml").write_text(text[:start] + 'gonio = "0+corpus"\n\n' + text[end:])
    r = variant("frame_path_escape", exr)
    _sql(r, "UPDATE captures SET frame_path = '../../etc/passwd'")
    r = variant("frame_path_nul", exr)  # open() raised ValueError: embedded null byte
    _sql(r, "UPDATE captures SET frame_path = 'frames/p00000' || char(0) || '_b00.exr'")
    r = variant("frame_path_absolute", exr)
    _sql(r, "UPDATE captures SET frame_path = '/etc/passwd'")
    r = variant("manifest_exposure_zero", exr)
    _sql(r, "UPDATE captures SET exposure_s = 0")
    variant("bin_px_huge", exr)  # a good run: the bad input is calibrate's --bin-px
    r = variant("frame_sha256_differs", exr)  # a frame changed or swapped since capture
    _sql(r, "UPDATE captures SET sha256 = '00' || substr(sha256, 3)")

    # An empty run: a manifest and a frozen config, zero captures (a run that never started).
    r = runs / "empty"
    from acquisition.store import RunStore

    RunStore.create(r, (exr / "run.toml").read_text()).close()
    _normalise(r)
    (r / "frames").rmdir()  # git keeps no empty directories; a run without frames/ is the same
    # A run whose frozen rig runs a command: resuming it with another rig file must refuse.
    r = variant("runtoml_trigger_command", r)
    text = (r / "run.toml").read_text()
    (r / "run.toml").write_text(
        _edit(
            text,
            '[rig.camera]\nbackend = "sim"\n',
            '[rig.camera]\nbackend = "folder"\nfolder = "incoming"\n'
            'trigger_command = ["sh", "-c", "touch PWNED"]\n',
        )
    )

    # Runs with samples and a fit, for `gonio report` and a resumed `gonio fit`.
    fitted = work / "fitted"
    shutil.copytree(exr, fitted)
    table = reduce_run(fitted, ReduceOptions(bin_px=8, mode="center"))
    fit_samples(
        table,
        FitOptions(model="lambert", mcmc=McmcOptions(walkers=8, max_steps=40), n_starts=1, seed=0),
        out_dir=fitted,
    )
    _fix_wall_times(fitted / "fit-lambert.json")
    (fitted / "samples.parquet").write_bytes(_strip_parquet_meta(fitted / "samples.parquet"))

    r = variant("fit_json_truncated", fitted)
    (r / "fit-lambert.h5").unlink()
    _truncate(r / "fit-lambert.json", 0.5)
    r = variant("fit_json_newer", fitted)
    (r / "fit-lambert.h5").unlink()
    text = (r / "fit-lambert.json").read_text()
    (r / "fit-lambert.json").write_text(_edit(text, '"schema_version": 1', '"schema_version": 99'))
    r = variant("fit_json_deep", fitted)
    (r / "fit-lambert.h5").unlink()
    (r / "fit-lambert.json").write_text('{"parameters": ' + "[" * 5000 + "]" * 5000 + "}")
    r = variant("fit_json_huge", fitted)
    (r / "fit-lambert.h5").unlink()
    doc = json.loads((r / "fit-lambert.json").read_text())
    doc["parameters"]["kd_R"]["median"] = 1e308  # exported as a MERL file of inf before
    (r / "fit-lambert.json").write_text(json.dumps(doc, indent=2))
    r = variant("fit_json_nan", fitted)
    (r / "fit-lambert.h5").unlink()
    doc = json.loads((r / "fit-lambert.json").read_text())
    doc["parameters"]["kd_R"]["map"] = float("nan")  # json writes the bare token NaN
    (r / "fit-lambert.json").write_text(json.dumps(doc, indent=2))
    r = variant("chain_h5_truncated", fitted)
    (r / "fit-lambert.json").unlink()
    # The first 20 kB: a valid HDF5 signature and superblock, then nothing.
    (r / "fit-lambert.h5").write_bytes((r / "fit-lambert.h5").read_bytes()[:20_000])
    r = variant("chain_h5_garbage", fitted)
    (r / "fit-lambert.json").unlink()
    (r / "fit-lambert.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + _garbage(4000, 4))

    # A samples table from the same run, for the samples cases.
    shutil.copy(fitted / "samples.parquet", work / "samples.parquet")


def _strip_parquet_meta(path: Path) -> bytes:
    """The samples table with the machine-specific provenance fields fixed."""
    t = pq.read_table(path)
    meta = dict(t.schema.metadata)
    cal = json.loads(meta[b"gonio.calibration"])
    cal["run"] = "corpus"
    meta[b"gonio.calibration"] = json.dumps(cal).encode()
    buf = io.BytesIO()
    pq.write_table(t.replace_schema_metadata(meta), buf)
    return buf.getvalue()


# -- samples ---------------------------------------------------------------------------------
def _table(n: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "theta_i": np.full(n, 0.4),
        "phi_i": np.zeros(n),
        "theta_o": rng.uniform(0.05, 1.2, n),
        "phi_o": np.full(n, np.pi),
        "channel": ["R"] * n,
        "f": rng.uniform(0.05, 0.2, n),
        "sigma": np.full(n, 0.01),
    }


def write_samples(work: Path) -> None:
    d = HERE / "samples"
    if d.exists():
        shutil.rmtree(d)
    d.mkdir()
    good = work / "samples.parquet"
    data = good.read_bytes()
    (d / "truncated.parquet").write_bytes(data[: len(data) // 2])
    (d / "not_parquet.parquet").write_text("theta_i,phi_i\n0.1,0.2\n")
    cols = _table(60, 5)
    cols["f"][[7, 19, 40]] = np.nan
    cols["sigma"][23] = np.inf
    pq.write_table(pa.table(cols), d / "partial_nan.parquet")
    cols = _table(60, 6)
    cols["theta_o"][11] = -np.inf
    pq.write_table(pa.table(cols), d / "partial_inf_angle.parquet")
    t = pa.table(_table(40, 7)).replace_schema_metadata({"gonio.schema_version": "99"})
    pq.write_table(t, d / "newer_schema.parquet")
    for name, version in (("schema_superscript", "²"), ("schema_not_whole", "2.0")):
        t = pa.table(_table(40, 7)).replace_schema_metadata({"gonio.schema_version": version})
        pq.write_table(t, d / f"{name}.parquet")
    t = pa.table(_table(40, 7)).replace_schema_metadata({b"gonio.note": b"\xff\xfe latin-1"})
    pq.write_table(t, d / "metadata_not_utf8.parquet")
    t = pa.table(_table(40, 7))
    pq.write_table(t.append_column("f", t.column("f")), d / "duplicate_column.parquet")
    cols = _table(40, 11)
    cols["f"][5] = 1e308  # fitted before: f² overflows
    pq.write_table(pa.table(cols), d / "f_huge.parquet")
    cols = _table(40, 12)
    cols["f"] = cols["f"] > 0.1  # True/False, read as 1/0 sr⁻¹ before
    pq.write_table(pa.table(cols), d / "f_boolean.parquet")
    cols = _table(40, 10)
    cols["flags"] = np.full(40, 8, dtype=np.int32)  # every row MASKED
    pq.write_table(pa.table(cols), d / "all_masked.parquet")
    cols = _table(40, 8)
    del cols["sigma"]
    pq.write_table(pa.table(cols), d / "missing_column.parquet")
    cols = _table(40, 9)
    cols["theta_i"] = [f"{v} rad" for v in cols["theta_i"]]
    pq.write_table(pa.table(cols), d / "angle_as_text.parquet")
    # A good table: the bad input is the command's --fix.
    shutil.copy(good, d / "fix_outside_range.parquet")
    shutil.copy(good, d / "time_budget_negative.parquet")  # the bad input: --time-budget
    shutil.copy(good, d / "out_under_a_file.parquet")  # the bad input: --out under this file


# -- study CSVs ------------------------------------------------------------------------------
def write_studies() -> None:
    d = HERE / "studies"
    if d.exists():
        shutil.rmtree(d)
    d.mkdir()
    # The first rows of the accuracy-vs-time study, one cell made infinite.
    with open(REPO / "docs" / "accuracy-vs-time.csv", newline="") as fh:
        rows = list(csv.reader(fh))[:4]
    rows[2][rows[0].index("lab_time_s")] = "inf"
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(rows)
    (d / "results_inf.csv").write_text(buf.getvalue())


def main() -> int:
    sys.path.insert(0, str(REPO))
    write_configs()
    with tempfile.TemporaryDirectory() as tmp:
        write_runs(Path(tmp))
        write_samples(Path(tmp))
    write_studies()
    big = [p for p in HERE.rglob("*") if p.is_file() and p.stat().st_size > MAX_BYTES]
    for p in big:
        print(f"too big: {p} ({p.stat().st_size} bytes)", file=sys.stderr)
    return 1 if big else 0


if __name__ == "__main__":
    raise SystemExit(main())
