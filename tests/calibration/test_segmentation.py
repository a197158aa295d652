"""Sample segmentation from the image (calibration.segmentation) on simulated frames.

Scene: the RAW accuracy scene's material and sensor noise, an RGB camera of 96×96 pixels, and a
white holder rim (Lambertian 0.8, the sample is the blend of diffuse (0.6, 0.4, 0.2) and a
Beckmann lobe — a different reflectance) around the sample. The geometric prior is deliberately
wrong — the sample stated 8 % too large and the camera arm 0.25° off — so that the geometric
footprint covers part of the holder.

Ground truth is render-side and independent of calibration's code: the sample's corners projected
with the simulator's own camera (simulator.render.world_to_camera_cv and camera_intrinsics, the
transform Mitsuba renders with), and each pixel's covered fraction from 8×8 sub-pixel points in
that polygon. A pixel is "sample" when more than half covered; pixels with 0 < coverage < 1
straddle the edge and are the only ones a correct segmentation may get wrong.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from matplotlib.path import Path as PolygonPath

from acquisition.clock import VirtualClock
from acquisition.config import PlanConfig, RigConfig, load_rig
from acquisition.kinematics import Kinematics, Pose
from acquisition.store import RunStore
from brdfdata.samples import Flags
from calibration.decode import decode_frame
from calibration.geometry import Intrinsics, project_points
from calibration.reduce import ReduceOptions, reduce_run
from calibration.segmentation import iou, polygon_mask, segment_sample
from gonio.pipeline import AcquireSpec, acquire
from simulator.arms import ArmPose
from simulator.camera import SimCamera
from simulator.render import camera_frame, camera_intrinsics, world_to_camera_cv
from simulator.scene import Scene, load_scene
from tests.support.paths import REPO

DISTANCE_M = 0.5  # configs/rigs/sim.toml: light and camera arms
POSES_DEG = [
    (30, 0, 0, 180),
    (55, 0, 40, 180),
    (30, 0, 60, 60),
    (45, 90, 20, 300),
    (20, 0, 30, 180),
]
SIZE_ERROR = 1.08  # the stated sample side is 8 % too large
ARM_ERROR_RAD = np.radians(0.25)  # and the camera's θ is 0.25° off


def _scene() -> Scene:
    d = load_scene(REPO / "configs" / "scenes" / "raw.toml").model_dump()
    # The world states its camera (96 × 96, 8° across) and sample (50 mm) itself: the true
    # values, whatever a rig file believes.
    d["camera"].update(format="exr", resolution=(96, 96), fov_deg=8.0, f_number=4.0)
    d["sample"] = {"size_m": 0.05}
    d["sensor"].update(bayer=None, vignetting=False, prnu=0.0, dark_current_e_s=0.0, dsnu_e=0.0)
    # A thin rim (0.5 mm) so that it does not hide the sample's edge: occlusion would move the
    # visible edge away from the projected corners (the truth below has no occlusion).
    d["holder"] = {
        "rim_height_m": 0.0005,
        "wall_thickness_m": 0.006,
        "gap_m": 0.0,
        "reflectance": (0.8, 0.8, 0.8),
    }
    d["render"] = {"spp": 4}  # 2×2 points per pixel: edge pixels get their partial coverage
    return Scene.model_validate(d)


def true_coverage(scene: Scene, camera_pos_m, n: int = 8) -> np.ndarray:
    """Fraction of each pixel covered by the sample, from the simulator's own camera model."""
    k = camera_intrinsics(scene)
    r, t = world_to_camera_cv(camera_pos_m)
    h = scene.sample.size_m / 2.0
    corners = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    pc = corners @ r.T + t
    uv = np.stack(
        [k["fx"] * pc[:, 0] / pc[:, 2] + k["cx"], k["fy"] * pc[:, 1] / pc[:, 2] + k["cy"]], 1
    )
    sub = (np.arange(n) + 0.5) / n - 0.5
    su, sv = np.meshgrid(sub, sub)
    uu, vv = np.meshgrid(np.arange(k["width"]), np.arange(k["height"]))
    pts = np.stack([(uu[..., None] + su.ravel()).ravel(), (vv[..., None] + sv.ravel()).ravel()], 1)
    inside = PolygonPath(uv).contains_points(pts)
    return inside.reshape(k["height"], k["width"], n * n).mean(axis=-1)


@pytest.fixture(scope="module")
def frames():
    scene = _scene()
    where = {}
    cam = SimCamera(scene, VirtualClock(), lambda: where["p"], lambda: 1.0)
    s = scene.sensor
    exposure_s = 0.002  # no pixel saturates at this exposure (checked below)
    out = []
    for deg in POSES_DEG:
        pose = Pose.from_deg(*deg)
        light, camera = DISTANCE_M * pose.wi, DISTANCE_M * pose.wo
        where["p"] = ArmPose(light, camera_frame(camera))  # a camera looking at the centre
        frame = cam.capture(exposure_s)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / f"f{frame.suffix}"
            path.write_bytes(frame.data)
            dn = np.asarray(decode_frame(path).dn, dtype=np.float64)
        assert dn.max() < cam.clip_level_dn
        electrons = (dn - s.black_level_dn) * s.gain_e_per_dn
        flux = electrons.sum(axis=-1) / exposure_s
        # Shot + read noise of the three channels (EMVA 1288), in e/s.
        noise = np.sqrt(np.maximum(electrons.sum(axis=-1), 0) + 3 * s.read_noise_e**2)
        out.append((pose, camera, flux, noise / exposure_s, true_coverage(scene, camera)))
    return scene, out


def test_segmentation_recovers_the_true_footprint_from_a_wrong_prior(frames) -> None:
    scene, shots = frames
    k = camera_intrinsics(scene)
    intr = Intrinsics(k["width"], k["height"], k["fx"], k["fy"], k["cx"], k["cy"])
    h = SIZE_ERROR * scene.sample.size_m / 2.0
    stated = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    inter = union = holder_px = holder_kept = n_true = n_straddle = 0
    for pose, _camera, flux, noise, cov in shots:
        wrong_cam = (
            DISTANCE_M * Pose(pose.theta_i, pose.phi_i, pose.theta_o + ARM_ERROR_RAD, pose.phi_o).wo
        )
        # the (wrong) geometric prior: a camera at the wrong place looking at the centre
        corners = project_points(intr, wrong_cam, stated, world_to_camera_cv(wrong_cam)[0].T)
        prior = polygon_mask(flux.shape, corners)
        seg = segment_sample(flux, corners, noise_sd=noise, band_px=6)
        truth = cov > 0.5
        straddle = (cov > 0) & (cov < 1)
        # The prior really is wrong (else this test proves nothing) ...
        assert iou(prior, truth) < 0.9
        # ... and the segmentation errs only on pixels the edge passes through, up to a 1 %
        # allowance of the area for the rim's own 0.5 mm (≈ 0.7 px) inner wall at grazing views.
        wrong = (seg.mask != truth) & ~straddle
        assert wrong.sum() <= 0.01 * truth.sum(), (pose.deg(), wrong.sum())
        assert seg.sides_found == 4
        inter += np.sum(seg.mask & truth)
        union += np.sum(seg.mask | truth)
        n_true += truth.sum()
        n_straddle += straddle.sum()
        # Holder pixels (no sample in them) that the wrong footprint includes: excluded.
        on_holder = prior & (cov == 0)
        holder_px += on_holder.sum()
        holder_kept += np.sum(on_holder & seg.mask)
    # IoU bound from the boundary-pixel fraction: with the edge located to ±½ px, at most half
    # of the straddling pixels fall on the wrong side of the half-coverage line, so
    # IoU ≥ (A − n_s/2)/(A + n_s/2) with A the true area and n_s the straddling count (here
    # n_s/A ≈ 6.5 %, so the bound is ≈ 0.94).
    bound = (n_true - n_straddle / 2) / (n_true + n_straddle / 2)
    total_iou = inter / union
    assert total_iou >= bound, (total_iou, bound)
    assert total_iou >= 0.95, total_iou
    # The wrong footprint reached > 1000 holder pixels; ≥ 98 % are excluded (the rest sit where
    # the rim's inner wall is as bright as the sample's edge).
    assert holder_px > 1000
    assert holder_kept <= 0.02 * holder_px, (holder_kept, holder_px)


def test_without_an_edge_the_prediction_is_kept() -> None:
    """A uniform image has no edge: the segmentation must not invent one."""
    rng = np.random.default_rng(0)
    flux = 1e4 + rng.normal(0.0, 100.0, (64, 64))
    corners = np.array([[10.0, 12.0], [50.0, 11.0], [52.0, 50.0], [11.0, 49.0]])
    seg = segment_sample(flux, corners, noise_sd=100.0)
    assert seg.sides_found == 0
    assert np.array_equal(seg.mask, polygon_mask(flux.shape, corners))


def test_a_sharp_step_is_located_to_a_tenth_of_a_pixel() -> None:
    """A bright square on a dark field, predicted 2 px too large: every side comes back to the
    true edge, half a pixel outside the outermost bright pixel centres (noise 1e-4 relative:
    the location error is set by the 0.25 px search grid and the centroid, ≪ 0.1 px)."""
    rng = np.random.default_rng(1)
    flux = np.full((48, 48), 20.0)
    flux[10:38, 12:40] = 2e4  # rows 10..37, columns 12..39
    flux += rng.normal(0.0, 2.0, flux.shape)
    true_edges = np.array([[11.5, 9.5], [39.5, 9.5], [39.5, 37.5], [11.5, 37.5]])
    centre = true_edges.mean(axis=0)
    predicted = centre + (true_edges - centre) * (1 + 2.0 / 14.0)  # sides 2 px further out
    seg = segment_sample(flux, predicted, noise_sd=2.0)
    assert seg.sides_found == 4
    assert np.allclose(np.sort(seg.corners_px, axis=0), np.sort(true_edges, axis=0), atol=0.1)
    expected = np.zeros(flux.shape, bool)
    expected[10:38, 12:40] = True
    assert np.array_equal(seg.mask, expected)


def _rig(size_m: float):
    """The sim rig file describing this test's camera (96 × 96 px of 5 µm, 8° across: focal
    length 48 px·5 µm / tan 4°) and a sample of side `size_m`."""
    rig = load_rig(REPO / "configs" / "rigs" / "sim.toml")
    focal = 48 * 5e-6 / np.tan(np.radians(4.0))
    cam = rig.camera.model_copy(update={"resolution": (96, 96), "focal_length_m": focal})
    sample = rig.sample.model_copy(update={"size_m": size_m})
    cal = rig.calibration.model_copy(update={"intrinsics": None})  # sim-camera.json is 64 px
    return rig.model_copy(update={"camera": cam, "sample": sample, "calibration": cal})


def _holder_acquire(out: Path, size_m: float, scene: Scene) -> Path:
    plan = PlanConfig.model_validate(
        {
            "name": "segmentation",
            "type": "isotropic",
            "theta_i_deg": [30.0, 50.0],
            "theta_o_deg": [10.0, 40.0],
            "delta_phi_deg": [180.0, 90.0],
            "exposures_s": [0.002],
            "order": "nearest",
        }
    )
    res = acquire(out, AcquireSpec(scene=scene, progress=False, rig=_rig(size_m), plan=plan))
    assert res.outcome.complete
    return out


@pytest.fixture(scope="module")
def holder_run(tmp_path_factory: pytest.TempPathFactory):
    """The same world measured twice: by a rig file stating the sample's true size, and by one
    overstating it by 8 % (the frames are the same; only what the lab believes differs)."""
    root = tmp_path_factory.mktemp("seg")
    scene = _scene()
    right = _holder_acquire(root / "right", scene.sample.size_m, scene)
    wrong = _holder_acquire(root / "wrong", SIZE_ERROR * scene.sample.size_m, scene)
    return right, wrong, scene


def _coverage_of_rows(run_dir: Path, scene: Scene, table) -> np.ndarray:
    store = RunStore.open(run_dir)
    kin = Kinematics(RigConfig.model_validate(store.run_config()["rig"]))
    cams = {r.id: kin.camera_position_m(r.axes_measured) for r in store.captures("done")}
    cov = np.empty(len(table.f))
    ids = table.extra["capture_id"]
    for cid in np.unique(ids):
        m = ids == cid
        c = true_coverage(scene, cams[int(cid)])
        cov[m] = c[table.extra["pixel_y"][m], table.extra["pixel_x"][m]]
    return cov


def test_reduce_flags_the_holder_when_the_sample_size_is_overstated(holder_run, tmp_path) -> None:
    run_dir, wrong_dir, scene = holder_run
    store_a, store_b = RunStore.open(run_dir), RunStore.open(wrong_dir)
    # The same world, so the same frames: only the rig file's belief differs.
    assert [c.sha256 for c in store_a.captures()] == [c.sha256 for c in store_b.captures()]
    assert store_b.run_config()["sample"]["size_m"] == SIZE_ERROR * scene.sample.size_m
    # The right size first: the image agrees with the geometry, (almost) nothing is masked.
    good = reduce_run(run_dir, ReduceOptions(bin_px=1), out=tmp_path / "good.parquet")
    masked = (good.flags & Flags.MASKED) != 0
    assert masked.mean() < 0.005, masked.mean()

    # The rig file overstated the sample (`sample.size_m`): the footprint grows onto the white
    # holder. The reduction must flag those pixels MASKED and keep the sample's.
    table = reduce_run(wrong_dir, ReduceOptions(bin_px=1), out=tmp_path / "w.parquet")
    cov = _coverage_of_rows(wrong_dir, scene, table)
    masked = (table.flags & Flags.MASKED) != 0
    off = cov == 0
    assert off.sum() > 300  # the wrong footprint does reach the holder
    assert masked[off].mean() >= 0.95, masked[off].mean()
    assert masked[cov == 1].mean() <= 0.01, masked[cov == 1].mean()

    # Without segmentation the holder pixels pass as sample data: the check above can fail.
    plain = reduce_run(
        wrong_dir, ReduceOptions(bin_px=1, segment=False), out=tmp_path / "p.parquet"
    )
    assert not np.any(plain.flags & Flags.MASKED)


def test_the_edge_search_samples_the_image_as_scipy_does() -> None:
    """The compiled bilinear samples of the edge search (segmentation._steps_across) against
    scipy.ndimage.map_coordinates (order 1, edge values beyond the image), at offsets inside
    and outside the image. Tolerance: each sample is 4 products and 3 sums of image values,
    so the two differ by a few ulps of the largest value; asserted at 8ε·max|image|."""
    from scipy.ndimage import map_coordinates

    from calibration.segmentation import _steps_across

    rng = np.random.default_rng(0)
    ell = rng.normal(size=(60, 80))
    var_ell = rng.uniform(size=(60, 80))
    p_out = rng.uniform(-3.0, 83.0, (33, 200, 2))
    p_in = p_out - rng.uniform(0.0, 2.0, (33, 200, 2))

    def sample(img: np.ndarray, p: np.ndarray) -> np.ndarray:
        return map_coordinates(img, [p[..., 1], p[..., 0]], order=1, mode="nearest")

    diff, var = _steps_across(ell, var_ell, p_out, p_in)
    eps = np.finfo(float).eps
    np.testing.assert_allclose(
        diff, sample(ell, p_out) - sample(ell, p_in), rtol=0, atol=8 * eps * np.abs(ell).max()
    )
    np.testing.assert_allclose(
        var, sample(var_ell, p_out) + sample(var_ell, p_in), rtol=0, atol=8 * eps * var_ell.max()
    )


def test_polygon_mask_is_the_pixel_centres_inside_the_polygon() -> None:
    """`polygon_mask` against matplotlib's point-in-polygon test of every pixel centre, for
    random convex quadrilaterals given in any corner order (non-integer corners: no centre lies
    on an edge, where the two tests may differ by convention)."""
    rng = np.random.default_rng(3)
    shape = (37, 53)
    for _ in range(20):
        centre = rng.uniform([10.0, 8.0], [43.0, 29.0])
        angles = np.sort(rng.uniform(0.0, 2 * np.pi, 4))
        # points on an ellipse: a convex quadrilateral, as a square's image is
        on_circle = np.column_stack([np.cos(angles), np.sin(angles)])
        corners = centre + on_circle @ rng.uniform(-12.0, 12.0, (2, 2))
        corners = corners[rng.permutation(4)]
        vv, uu = np.mgrid[0 : shape[0], 0 : shape[1]]
        ordered = corners[np.argsort(np.arctan2(*(corners - corners.mean(0)).T[::-1]))]
        want = PolygonPath(ordered).contains_points(np.column_stack([uu.ravel(), vv.ravel()]))
        got = polygon_mask(shape, corners)
        assert got.any() and not got.all()
        np.testing.assert_array_equal(got, want.reshape(shape))
