"""`gonio import rgl`: our own reader of the RGL tensor files (brdfdata.formats.rgl) against the
independent implementation — Mitsuba 3's ``measured`` plugin, C++ in float32 — on the four
published files shipped in data/rgl_brdf.

Tolerances. Mitsuba evaluates in float32 (relative rounding 6e-8 per operation) through a
chain of a few dozen operations (two CDF inversions, bilinear and parameter interpolation, a
quotient), so agreement near 1e-6 is expected; the acceptance bound is a median of 1e-3 where
f·cos θ_o exceeds 1 % of its maximum (below that the float32 cancellation in the interpolants
dominates a relative figure). A wrong reading — a transposed table, a wrong bit order, an
interpolation weight off by a cell — changes values by percents.

One known disagreement, at θ_i = 0 exactly: Mitsuba 3.9's ``measured`` leaves its
``m_reduction`` member uninitialised for isotropic files; when it happens to be ≥ 2 the plugin
mirrors ω_o through the z axis (``mulsign_neg``) but ``atan2(−0, −0)`` keeps φ_i = 0, so at
normal incidence it reads the table rotated by π (its value at θ_i = 1e-6 equals ours at 0).
We therefore also require every node with θ_i > 0 to agree to 1e-3, and the median over all.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import mitsuba as mi
import numpy as np
import pytest
from conftest import REPO, data_file

from brdfdata.directions import spherical_to_vector
from brdfdata.formats.common import FormatError, SigmaRule, parse_grid
from brdfdata.formats.rgl import RglImportOptions, import_rgl, load_rgl, measured_directions
from brdfdata.formats.tensor_file import read_tensor_file, tensor_file_bytes, write_tensor_file
from brdfdata.samples import Flags, read_samples, write_samples

NAMES = ("paper_white", "colodur_napoli_4f", "satin_rosaline", "vch_golden_yellow")


@pytest.fixture(scope="module", autouse=True)
def variant() -> str:
    from simulator.variant import ensure_variant

    return ensure_variant()


def _mitsuba_fcos(path, wi, wo) -> np.ndarray:
    """Mitsuba ``measured`` eval (f·cos θ_o) with the file's incidence ω_i as si.wi."""
    import drjit as dr

    bsdf = mi.load_dict({"type": "measured", "filename": str(path)})
    n = wi.shape[0]
    if mi.variant().startswith("scalar"):
        out = np.zeros((n, 3))
        si = mi.SurfaceInteraction3f()
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        for j in range(n):
            si.wi = mi.Vector3f(*wi[j])
            v = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*wo[j]))
            out[j] = [v[0], v[1], v[2]]
        return out
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.n = mi.Normal3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.wi = mi.Vector3f(wi[:, 0], wi[:, 1], wi[:, 2])
    v = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(wo[:, 0], wo[:, 1], wo[:, 2]))
    return np.stack([np.asarray(v[c], dtype=np.float64) for c in range(3)], axis=1)


def _by_channel(table):
    """(ω_i, ω_o, f (N, 3), flags (N, 3)) from an imported table (channel-major rows)."""
    n = len(table) // 3
    assert table.channel[:n].tolist() == ["R"] * n and table.channel[-n:].tolist() == ["B"] * n
    wi = spherical_to_vector(table.theta_i[:n], table.phi_i[:n])
    wo = spherical_to_vector(table.theta_o[:n], table.phi_o[:n])
    return wi, wo, table.f.reshape(3, n).T, table.flags.reshape(3, n).T


@pytest.mark.parametrize("name", NAMES)
def test_container_read_write_is_bitwise(name, tmp_path) -> None:
    src = data_file(f"rgl_brdf/{name}_rgb.bsdf")
    fields = read_tensor_file(src)
    assert list(fields)[:3] == ["version", "description", "phi_i"]
    assert tensor_file_bytes(fields) == src.read_bytes()
    out = write_tensor_file(tmp_path / "copy.bsdf", fields)
    assert out.read_bytes() == src.read_bytes()


@pytest.mark.parametrize("name", NAMES)
def test_measured_directions_agree_with_mitsuba(name) -> None:
    path = data_file(f"rgl_brdf/{name}_rgb.bsdf")
    table = import_rgl(path)
    wi, wo, f, _ = _by_channel(table)
    ref = _mitsuba_fcos(path, wi, wo) / wo[:, 2:3]  # f_r = eval / cos θ_o
    fcos = ref * wo[:, 2:3]
    big = fcos > 0.01 * fcos.max(axis=0)
    rel = np.abs(f - ref)[big] / np.abs(ref[big])
    assert big.sum() > 300  # a sharp lobe (satin, gold) leaves few nodes above 1 % of its peak
    assert np.median(rel) <= 1e-3, np.median(rel)
    off_normal = np.broadcast_to((wi[:, 2] < 1.0)[:, None], big.shape)[big]
    assert rel[off_normal].max() <= 1e-3, rel[off_normal].max()
    # Every direction is above the horizon and none repeats (the guards would refuse it).
    assert np.all(wo[:, 2] > 0) and len(np.unique(np.round(np.c_[wi, wo], 12), axis=0)) == len(wi)
    meta = json.loads(table.metadata["gonio.source.conversion"])
    assert table.metadata["gonio.source.file"] == path.name
    assert len(table.metadata["gonio.source.sha256"]) == 64
    assert meta["nodes_left_out"]["grazing_incidence"] == 1024  # the θ_i = 90° slice


def test_negative_values_are_kept_and_flagged(tmp_path) -> None:
    """vch_golden_yellow publishes slightly negative RGB (out-of-gamut spectra): they are
    imported with their value, flagged NEGATIVE, and Mitsuba returns the same negatives."""
    path = data_file("rgl_brdf/vch_golden_yellow_rgb.bsdf")
    table = import_rgl(path)
    wi, wo, f, flags = _by_channel(table)
    neg = f < 0
    assert neg.sum() > 500
    assert np.array_equal(flags == Flags.NEGATIVE, neg) and np.all(flags[~neg] == 0)
    ref = _mitsuba_fcos(path, wi, wo) / wo[:, 2:3]
    assert np.all(ref[neg & (wi[:, 2:3] < 1)] < 0)  # the same values are negative in Mitsuba
    meta = json.loads(table.metadata["gonio.source.conversion"])
    assert meta["negative_flagged"] == int(neg.sum())
    # The written table passes the guards and fits keep them as data (FLAG_ROLES: 16 keeps its
    # row): the σ rule's floor, the RMS of the channel's negatives, puts each within its noise.
    out = write_samples(tmp_path / "s.parquet", table)
    back = read_samples(out)
    assert len(back.good()) == len(table)
    blue = table.channel == "B"
    floor = np.sqrt(np.mean(np.square(table.f[blue & (table.f < 0)])))
    assert meta["sigma_floor"]["B"] == pytest.approx(floor, rel=1e-12)
    assert np.all(table.sigma[blue] >= floor) and np.min(table.f / table.sigma) > -3


def test_random_directions_agree_with_mitsuba() -> None:
    """Evaluation anywhere (the --grid path), not only at the nodes."""
    rng = np.random.default_rng(5)

    def dirs(n):
        ct = rng.uniform(0.05, 1.0, n)
        ph = rng.uniform(0, 2 * np.pi, n)
        st = np.sqrt(1 - ct**2)
        return np.stack([st * np.cos(ph), st * np.sin(ph), ct], axis=1)

    for name in NAMES:
        path = data_file(f"rgl_brdf/{name}_rgb.bsdf")
        wi, wo = dirs(5000), dirs(5000)
        ours = load_rgl(path).eval_cos(wi, wo)
        ref = _mitsuba_fcos(path, wi, wo)
        big = ref > 0.01 * ref.max(axis=0)
        rel = np.abs(ours - ref)[big] / np.abs(ref[big])
        assert np.median(rel) <= 1e-5 and np.percentile(rel, 99) <= 1e-4, name


def test_grid_import_uses_the_users_directions() -> None:
    path = data_file("rgl_brdf/paper_white_rgb.bsdf")
    # θ_i from 10°: at exactly 0 Mitsuba reads the table rotated (module docstring).
    grid = parse_grid("theta_i=10:70:30,theta_o=0:80:20,phi_o=0:180:90")
    table = import_rgl(path, RglImportOptions(grid=grid, sigma=SigmaRule("abs", 0.01)))
    # 3 θ_i × (1 pole + 4 θ_o × 3 φ_o) directions × 3 channels
    assert len(table) == 3 * 13 * 3
    assert set(np.round(np.degrees(table.theta_o))) == {0, 20, 40, 60, 80}
    assert np.all(table.sigma == 0.01)
    wi, wo, f, _ = _by_channel(table)
    ref = _mitsuba_fcos(path, wi, wo) / wo[:, 2:3]
    assert np.max(np.abs(f - ref) / ref) < 1e-4


def test_not_an_rgl_file_is_one_line(tmp_path) -> None:
    bad = tmp_path / "x.bsdf"
    bad.write_bytes(b"hello world, not a tensor")
    with pytest.raises(FormatError) as exc:
        import_rgl(bad)
    assert str(bad) in str(exc.value) and "\n" not in str(exc.value)
    fields = dict(read_tensor_file(data_file("rgl_brdf/paper_white_rgb.bsdf")))
    del fields["vndf"]
    write_tensor_file(tmp_path / "novndf.bsdf", fields)
    with pytest.raises(FormatError, match="missing field.*vndf"):
        import_rgl(tmp_path / "novndf.bsdf")


_SPECTRAL_CHECK = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    import mitsuba as mi
    mi.set_variant("scalar_spectral")
    path, wl = sys.argv[1], [float(x) for x in sys.argv[2].split(",")]
    pairs = json.loads(sys.argv[3])
    bsdf = mi.load_dict({"type": "measured", "filename": path})
    si = mi.SurfaceInteraction3f()
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.wavelengths = mi.Spectrum(wl)
    out = []
    for wi, wo in pairs:
        si.wi = mi.Vector3f(*wi)
        v = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*wo))
        out.append([float(v[i]) for i in range(4)])
    print(json.dumps(out))
    """
)


def test_spectral_file_agrees_with_mitsuba_spectral(tmp_path) -> None:
    """No spectral file is published in a fetchable place, so one is made from paper_white with
    our container writer: ``spectra`` at 400 and 700 nm = the file's R and B tables (values
    linear in λ in between, as both readers interpolate). Mitsuba's scalar_spectral variant, in
    a child process (the variant is global), evaluates it at four wavelengths."""
    fields = dict(read_tensor_file(data_file("rgl_brdf/paper_white_rgb.bsdf")))
    rgb = fields.pop("rgb")
    fields["spectra"] = np.ascontiguousarray(rgb[:, :, [0, 2]])
    fields["wavelengths"] = np.array([400.0, 700.0], np.float32)
    spec = write_tensor_file(tmp_path / "paper_spec.bsdf", fields)
    wl = (450.0, 520.0, 610.0, 690.0)
    table = import_rgl(spec, RglImportOptions(wavelengths_nm=wl))
    assert table.channels == ["450nm", "520nm", "610nm", "690nm"]
    n = len(table) // 4
    pick = np.random.default_rng(0).choice(n, 60, replace=False)
    wi = spherical_to_vector(table.theta_i[pick], table.phi_i[pick])
    wo = spherical_to_vector(table.theta_o[pick], table.phi_o[pick])
    pairs = json.dumps([[a.tolist(), b.tolist()] for a, b in zip(wi, wo, strict=True)])
    proc = subprocess.run(
        [sys.executable, "-c", _SPECTRAL_CHECK, str(spec), ",".join(map(str, wl)), pairs],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    ref = np.asarray(json.loads(proc.stdout.strip().splitlines()[-1])) / wo[:, 2:3]
    ours = table.f.reshape(4, n).T[pick]
    keep = np.all(wi[:, 2:3] < 1.0, axis=1)  # θ_i = 0: Mitsuba's rotation (module docstring)
    np.testing.assert_allclose(ours[keep], ref[keep], rtol=1e-4)
    # Default: the file's own wavelengths.
    assert import_rgl(spec).channels == ["400nm", "700nm"]


def test_measured_directions_reproduce_the_table_nodes() -> None:
    """At a node the imported value is the table entry itself times D/(4σ)/cos θ_o: the
    forward warp and its inverse meet (an internal consistency check of sample/invert)."""
    path = data_file("rgl_brdf/satin_rosaline_rgb.bsdf")
    brdf = load_rgl(path)
    wi, wo, _ = measured_directions(brdf)
    from brdfdata.formats.rgl import _elevation, phi2u, theta2u  # the plugin's conventions

    wm = (wi + wo) / np.linalg.norm(wi + wo, axis=1, keepdims=True)
    phi_i = np.arctan2(wi[:, 1], wi[:, 0])
    u = np.stack([theta2u(_elevation(wm)), phi2u(np.arctan2(wm[:, 1], wm[:, 0]) - phi_i)], 1)
    u[:, 1] -= np.floor(u[:, 1])
    s, _ = brdf.vndf.invert(u, [phi_i, _elevation(wi)])
    # The nodes, with the reference's clamp of the sample square to [ε, 1 − ε], ε = 2^-24.
    eps = 1 - float(np.float32(0.999999940395355225))
    node = np.clip(np.round(s * (brdf.grid_size - 1)) / (brdf.grid_size - 1), eps, 1 - eps)
    off = np.abs(s - node)
    # Float64 round trip through two quadratic CDF solves: exact to ~1e-15 except where a
    # row's density nearly vanishes (dx/dCDF = 1/density amplifies rounding there).
    assert np.median(off) < 1e-14 and np.percentile(off, 99) < 1e-10 and off.max() < 1e-6


@pytest.mark.parametrize(
    "grid",
    [
        "theta_i=0:60:1e-5,theta_o=0:80:5,phi_o=0:180:30",  # 6·10⁶ × 17 × 7 pairs
        "theta_i=0:1e300:1,theta_o=0:80:5,phi_o=0:180:30",  # one axis alone too long
    ],
)
def test_a_grid_too_fine_to_hold_is_refused_before_any_allocation(grid) -> None:
    """Issue 47: `import merl --grid` with a 1e-5° step asked for ~10¹⁹ cells and died inside
    numpy. A grid holds at most GRID_MAX_PAIRS pairs (2·10⁷ rows per channel: ~1.2 GB of
    samples; MERL's own table is 1.46 M cells): beyond, one line before anything is built."""
    with pytest.raises(FormatError, match="a grid holds at most 20,000,000"):
        parse_grid(grid)


def test_an_rgl_file_whose_vndf_is_all_zero_is_refused_in_one_line(tmp_path) -> None:
    """Issue 47: an RGL file whose VNDF is all zero (every value then 0/0) became an empty
    table and exit 0. Refused now: a file with no measured value is not a measurement."""
    from brdfdata.formats.convert import ImportOptions, import_samples

    fields = dict(read_tensor_file(data_file("rgl_brdf/paper_white_rgb.bsdf")))
    fields["vndf"] = np.zeros_like(np.asarray(fields["vndf"]))
    write_tensor_file(tmp_path / "zero.bsdf", fields)
    with pytest.raises(FormatError, match="no measured value in it") as exc:
        import_samples("rgl", tmp_path / "zero.bsdf", ImportOptions(grid="measured"))
    assert "\n" not in str(exc.value) and "zero.bsdf" in str(exc.value)


def test_a_declared_shape_that_overflows_is_refused_in_one_line(tmp_path) -> None:
    """Issue 47: an RGL field declaring shape (2⁶², 4) made numpy's int64 product wrap to 0 and
    the reshape fail inside numpy (an internal error). The size is counted in Python integers."""
    import struct

    data = bytearray(tensor_file_bytes({"x": np.zeros((2, 3), np.float32)}))
    struct.pack_into("<2Q", data, 32, 2**62, 4)  # the shape, after magic, version, count, name
    (tmp_path / "overflow.bsdf").write_bytes(bytes(data))
    with pytest.raises(FormatError, match="field 'x' runs past the end"):
        read_tensor_file(tmp_path / "overflow.bsdf")
