"""The repository stands on its own (issue 16, item 5): real data shipped in data/ with their
SHA-256, one resolver (brdfdata.data_paths) honouring $GONIO_DATA, the `data:` scheme of the
scene files, and a checked fetch for the data not shipped."""

from __future__ import annotations

import subprocess

import pytest
from conftest import REPO

from brdfdata import data_paths
from brdfdata.data_paths import DataNotFound, fetch, find_data, manifest, resolve_data_uri, verify


def test_every_shipped_file_is_in_the_repository_with_its_hash() -> None:
    shipped = {k: v for k, v in manifest().items() if v.shipped}
    assert len(shipped) == 4 + 7 + 14  # rgl_brdf, brdf_fits, calibration_chessboard
    for rel in shipped:
        path, ok = verify(rel)
        assert ok, f"{rel}: SHA-256 differs from data/SHA256SUMS"
        assert path == REPO / "data" / rel
    readme = (REPO / "data" / "README.md").read_text()
    for entry in shipped.values():  # the provenance page lists every hash
        assert entry.sha256 in readme, entry.path
    for entry in data_paths.FETCHED.values():
        assert entry.sha256 in readme and entry.url.startswith("https://")


def test_gonio_data_comes_first_and_the_cache_last(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("GONIO_DATA", str(tmp_path / "mine"))
    monkeypatch.setenv("GONIO_CACHE", str(tmp_path / "cache"))
    roots = data_paths.data_roots()
    assert roots[0] == tmp_path / "mine" and roots[1] == REPO / "data"
    assert roots[-1] == tmp_path / "cache" / "data"
    (tmp_path / "mine" / "rgl_brdf").mkdir(parents=True)
    (tmp_path / "mine" / "rgl_brdf" / "paper_white_rgb.bsdf").write_bytes(b"mine")
    assert find_data("rgl_brdf/paper_white_rgb.bsdf").read_bytes() == b"mine"
    assert resolve_data_uri("data:rgl_brdf/paper_white_rgb.bsdf").endswith(
        "mine/rgl_brdf/paper_white_rgb.bsdf"
    )
    assert resolve_data_uri("relative/file.bsdf") == "relative/file.bsdf"
    with pytest.raises(DataNotFound, match="without '..'"):
        find_data("../etc/passwd")


def test_missing_fetchable_data_names_the_command(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("GONIO_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("GONIO_DATA", raising=False)
    with pytest.raises(DataNotFound) as exc:
        find_data("camera_raw/Blackmagic.dng")
    msg = str(exc.value)
    assert "\n" not in msg and "gonio data fetch camera_raw" in msg and "GONIO_DATA" in msg


def test_fetch_from_a_folder_checks_the_hash(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("GONIO_CACHE", str(tmp_path / "cache"))
    src = tmp_path / "src"
    src.mkdir()
    (src / "Blackmagic.dng").write_bytes(b"not the published file")
    (src / "Nikon_uncompressed.nef").write_bytes(b"nor this")
    with pytest.raises(DataNotFound, match="SHA-256 .* does not match"):
        fetch("camera_raw", src)
    assert not list((tmp_path / "cache").rglob("*.dng"))  # nothing unverified is kept
    with pytest.raises(DataNotFound, match="no fetchable data group 'rgl_brdf'"):
        fetch("rgl_brdf")


def test_shipped_scenes_resolve_their_data(configs) -> None:
    from simulator.scene import load_scene

    for name in ("paper", "rgl_paper_white", "rgl_vch_golden_yellow"):
        text = (configs / "scenes" / f"{name}.toml").read_text()
        assert 'filename = "data:rgl_brdf/' in text
        scene = load_scene(configs / "scenes" / f"{name}.toml")
        assert scene.material.filename.startswith(str(REPO / "data" / "rgl_brdf"))


def test_no_code_or_document_points_outside_the_repository() -> None:
    """No tracked file but scene comments (left to the engineer editing those files) refers to
    the shared folder beside the checkout."""
    files = subprocess.run(
        ["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True
    ).stdout.split()
    offenders = []
    for rel in files:
        if rel.startswith("data/") or rel == "tests/brdfdata/test_data_paths.py":
            continue
        path = REPO / rel
        if path.suffix not in (".py", ".md", ".toml", ".cfg", ".txt", "") or not path.is_file():
            continue
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if rel.endswith(".toml") and line.lstrip().startswith("#"):
                continue
            if any(
                s in line
                for s in ("shared/data", "/work/shared", "GONIO_SHARED_DATA", "../shared/")
            ):
                offenders.append(f"{rel}:{n}")
    assert not offenders, offenders
