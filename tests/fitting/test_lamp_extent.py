"""The lamp's extent in the likelihood (fitting.likelihood.Likelihood._freeze_lamp): a disk lamp
of radius r at distance d lights each point from a cone of half-angle a = r/d, and the measured
f is the disk average of f(ω', ω_o) cos θ' over the centre's f cos θ_c.

Checked here against a dense quadrature of the same average written out independently (a polar
midpoint grid, 400 radii × 720 angles, of the disk in the plane perpendicular to ω_c): the
7-point rule is exact for degree 5, so on a lobe of width m its error is of order (a/m)⁶ of the
correction — 1e-8 at a/m = 0.05 — and the bound below, 1e-6 of f, is loose for it and a
hundred times below the correction itself (c − 1 ≈ 1e-3 near the peak). Whether the
correction is the right physics is the realistic coverage test's question: there Mitsuba renders
the disk (its `area` emitter) and m's error/half-width must lose its bias.
"""

from __future__ import annotations

import json

import numpy as np

from brdfdata.directions import spherical_to_vector, vector_to_spherical
from brdfdata.samples import SampleTable
from fitting import models
from fitting.likelihood import Likelihood
from fitting.priors import ParameterSpace

RADIUS_M, DISTANCE_M = 0.005, 0.5
OPTIONS = {"fresnel": "none", "shadowing": "smith-rational"}
PARAMS = {"kd": 0.3, "ks": 0.25, "m": 0.2}


def _table(lamp: bool) -> SampleTable:
    ti = np.radians([20.0, 20.0, 40.0, 40.0, 60.0, 5.0])
    to = np.radians([20.0, 30.0, 40.0, 10.0, 58.0, 0.0])
    po = np.radians([180.0, 180.0, 175.0, 180.0, 150.0, 90.0])
    n = ti.size
    meta = {"gonio.lamp": json.dumps({"radius_m": RADIUS_M, "distance_m": DISTANCE_M})}
    return SampleTable(
        theta_i=ti,
        phi_i=np.zeros(n),
        theta_o=to,
        phi_o=po,
        channel=np.full(n, "G"),
        f=np.ones(n),
        sigma=np.full(n, 0.01),
        flags=np.zeros(n, np.int32),
        metadata=meta if lamp else {},
    )


def _dense_average(model, wi, wo) -> np.ndarray:
    a = RADIUS_M / DISTANCE_M
    nr, nt = 400, 720
    r = (np.arange(nr) + 0.5) / nr  # midpoints in radius (fraction of the disk's)
    t = (np.arange(nt) + 0.5) / nt * 2 * np.pi
    weight = np.repeat(r, nt) / np.sum(np.repeat(r, nt))  # area element r dr dθ, normalised
    u, v = np.outer(r, np.cos(t)).ravel(), np.outer(r, np.sin(t)).ravel()
    out = []
    for c, o in zip(wi, wo, strict=True):
        # a basis of the plane perpendicular to ω_c, built from ω_c's own spherical angles
        th, ph = vector_to_spherical(c[None, :])
        e1 = np.array(
            [np.cos(th[0]) * np.cos(ph[0]), np.cos(th[0]) * np.sin(ph[0]), -np.sin(th[0])]
        )
        e2 = np.cross(c, e1)
        w = c[None, :] + a * (u[:, None] * e1 + v[:, None] * e2)
        w /= np.linalg.norm(w, axis=1, keepdims=True)
        f = model.evaluate(PARAMS, w, np.repeat(o[None, :], w.shape[0], axis=0))
        f0 = model.evaluate(PARAMS, c[None, :], o[None, :])
        out.append(np.sum(weight * f * w[:, 2]) / (f0[0] * c[2]))
    return np.array(out)


def test_lamp_factor_is_the_disk_average_of_the_model() -> None:
    model = models.get("torrance-sparrow", **OPTIONS)
    space = ParameterSpace.build(model, ["G"], discrepancy=False)
    natural = {"kd_G": PARAMS["kd"], "ks_G": PARAMS["ks"], "m": PARAMS["m"]}
    theta = space.to_internal(np.array([natural[n] for n in space.names]))
    table = _table(lamp=True)
    frozen = Likelihood(model, table, space, channels=["G"]).frozen_at(theta)
    (factor,) = frozen._lamp
    wi = spherical_to_vector(table.theta_i, table.phi_i)
    wo = spherical_to_vector(table.theta_o, table.phi_o)
    dense = _dense_average(model, wi, wo)
    np.testing.assert_allclose(factor, dense, rtol=1e-6, atol=0)
    assert np.max(np.abs(factor - 1)) > 1e-4  # the correction is there, and far above the bound
    # the prediction carries it; a table without the metadata gets none
    (with_lamp,) = frozen.predict(theta[None, :])
    plain = Likelihood(model, _table(lamp=False), space, channels=["G"]).frozen_at(theta)
    (without,) = plain.predict(theta[None, :])
    np.testing.assert_allclose(with_lamp[0] / without[0], factor, rtol=1e-12)
    assert plain._lamp is None


def test_calibration_hands_the_rig_files_lamp_to_the_fit(tmp_path) -> None:
    """The rig file's `[light] radius_m` reaches the samples' metadata (`gonio.lamp`) through a
    real simulated run and calibration, and a rig without it writes none (a point lamp)."""
    from acquisition.config import PlanConfig, load_rig
    from calibration.reduce import ReduceOptions, reduce_run
    from gonio.pipeline import AcquireSpec, acquire
    from tests.support.paths import REPO

    plan = PlanConfig(
        name="lamp", theta_i_deg=(25.0,), theta_o_deg=(0.0, 20.0, 40.0), delta_phi_deg=(180.0,),
        exposures_s=(0.002, 0.016),
    )  # fmt: skip
    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    stated = rig.model_copy(update={"light": rig.light.model_copy(update={"radius_m": 0.005})})
    for label, r, expect in (("disk", stated, 0.005), ("point", rig, None)):
        run = tmp_path / label
        acquire(run, AcquireSpec(rig=r, plan=plan, progress=False, announce=False))
        meta = reduce_run(run, ReduceOptions(bin_px=4, mode="center")).metadata
        if expect is None:
            assert "gonio.lamp" not in meta
        else:
            lamp = json.loads(meta["gonio.lamp"])
            assert lamp == {"radius_m": expect, "distance_m": rig.geometry.light_distance_m}
