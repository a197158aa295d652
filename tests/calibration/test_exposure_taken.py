"""The exposure a frame had, everywhere in calibration (issue 43 item 2).

A camera takes the nearest exposure it can (a DSLR's shutter-speed table, a sensor's line
period) and reports it; the plan's value is only what was asked. The simulated camera here
takes 1.96 ms when asked for 2 ms and 16.3 ms for 16 ms (a table 2.0 % and 1.9 % off, as a
1/3-stop table can be), records darks and the sample at those exposures, noise off. Calibration
must use what each frame had — the HDR merge, the darks' matching, the signal rate — so the
calibrated f equals that of a camera taking exactly what was asked (DN rounding aside, ≪ 0.1 %),
not f moved by the 2 %. The control reduces the same run with the commanded exposures in their
place: f then moves by about the difference (so the test can fail), and a fit of each run
gives the same kd, ks and m within a small fraction of their posterior sd.
"""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.config import CalibrationPhasesConfig, DarkPhaseConfig, PlanConfig
from acquisition.operator import AutoOperator
from acquisition.store import CalibrationRecord, CaptureRecord
from calibration.reduce import ReduceOptions, reduce_run
from fitting.fit import FitOptions, fit_samples
from gonio.pipeline import AcquireSpec, acquire
from simulator.scene import load_scene
from tests.support.effect_runs import paired_rows
from tests.support.paths import REPO

TABLE_S = (0.00196, 0.0163)  # what this camera takes for the plan's 0.002 s and 0.016 s
PLAN = PlanConfig(
    name="exposure",
    theta_i_deg=(30.0, 50.0),
    theta_o_deg=(0.0, 30.0, 50.0),
    delta_phi_deg=(180.0, 120.0),
    exposures_s=(0.002, 0.016),
    calibration=CalibrationPhasesConfig(dark=DarkPhaseConfig(count=4)),
)


def _run(out, table: tuple[float, ...]):
    scene = load_scene(REPO / "configs" / "scenes" / "demo.toml")
    scene = scene.model_copy(
        update={
            "sensor": scene.sensor.model_copy(update={"noise": False}),
            "camera": scene.camera.model_copy(update={"shutter_speeds_s": table}),
        }
    )
    spec = AcquireSpec(rig=REPO / "configs" / "rigs" / "sim.toml", plan=PLAN, scene=scene,
                       progress=False, announce=False, operator=AutoOperator())  # fmt: skip
    assert acquire(out, spec).outcome.complete
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("exposure")
    return _run(tmp / "exact", ()), _run(tmp / "table", TABLE_S)


def _reduce(run):
    return reduce_run(run, ReduceOptions(bin_px=4, radiometry="certified"), progress=False)


def test_the_camera_reports_the_exposure_it_took(runs) -> None:
    from acquisition.store import RunStore

    _, table_run = runs
    with RunStore.open(table_run) as store:
        recs = list(store.captures())
    taken = sorted({r.exposure_taken_s for r in recs})
    asked = sorted({r.exposure_s for r in recs})
    assert taken == list(TABLE_S) and asked == [0.002, 0.016]
    assert all(0.01 <= abs(t / a - 1.0) <= 0.03 for t, a in zip(taken, asked, strict=True))


def test_calibration_uses_the_exposure_each_frame_had(runs, monkeypatch) -> None:
    exact, quantised = (_reduce(r) for r in runs)
    a, b, good = paired_rows(exact, quantised)
    good &= exact.f[a] > 0.05 * np.max(exact.f[a])  # well above DN rounding
    ratio = quantised.f[b][good] / exact.f[a][good]
    # Noise off: what is left is DN rounding of frames 2 % apart in signal (< 1e-3 here).
    assert np.median(np.abs(ratio - 1.0)) < 1e-3, np.median(ratio)

    # The control: the same run reduced with the commanded exposures in place of the taken.
    for cls in (CaptureRecord, CalibrationRecord):
        monkeypatch.setattr(cls, "exposure_taken_s", property(lambda r: r.exposure_s))
    wrong = _reduce(runs[1])
    a2, b2, good2 = paired_rows(exact, wrong)
    good2 &= exact.f[a2] > 0.05 * np.max(exact.f[a2])
    moved = np.median(np.abs(wrong.f[b2][good2] / exact.f[a2][good2] - 1.0))
    assert 0.01 < moved < 0.03, moved  # the table's 1.9–2.0 %


def test_a_fit_of_the_quantised_run_equals_the_exact_runs(runs) -> None:
    """The estimates compared are the fits' maxima (least squares, the Laplace sd): the same
    data up to DN rounding give them to a tenth of their sd. Not the MCMC medians: two chains
    on data this close decorrelate, and their medians differed by 0.12 sd on kd (same seed;
    maxima 0.001 sd apart) — the chains' Monte Carlo error, not calibration's. The control's
    2 % in f would move kd by about 100 sd."""
    opt = FitOptions(model="torrance-sparrow", channels=["G"], n_starts=2, seed=3,
                     model_options={"fresnel": "none", "shadowing": "smith-rational"},
                     mcmc=None)  # fmt: skip
    exact, quantised = (fit_samples(_reduce(r), opt).parameters for r in runs)
    for name in ("kd_G", "ks_G", "m"):
        sd = (exact[name]["p84"] - exact[name]["p16"]) / 2
        # The same data up to DN rounding: the estimates agree to a tenth of their sd.
        assert abs(quantised[name]["map"] - exact[name]["map"]) < 0.1 * sd, name


def test_the_simulated_sensor_takes_whole_line_periods_or_the_nearest_shutter_speed() -> None:
    from simulator.scene import CameraSpec

    line = CameraSpec(exposure_step_s=15e-6)  # a 15 µs line period
    assert line.exposure_taken_s(0.002) == pytest.approx(133 * 15e-6)  # 1.995 ms, −0.25 %
    assert line.exposure_taken_s(1e-6) == pytest.approx(15e-6)  # never less than one line
    table = CameraSpec(shutter_speeds_s=(1 / 500, 1 / 400, 1 / 320))
    assert table.exposure_taken_s(0.0023) == pytest.approx(1 / 400)  # nearest in log
    assert CameraSpec().exposure_taken_s(0.00123) == 0.00123  # neither: what was asked
