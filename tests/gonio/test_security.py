"""Security properties (issue 9 item 5).

1. Configs never execute code: no pickle/marshal/shelve, eval/exec/compile/__import__,
   yaml.load, numpy allow_pickle or shell=True anywhere in our packages (an AST walk over the
   source tree); Python-looking text in a TOML config is an inert string or a parse error; a
   config that is not .toml/.json is refused in one line.
2. Run names and paths cannot escape: `..` in `--out` / `RUN`, a bare run name that leaves the
   runs directory, and frame paths in a manifest that are absolute, contain `..`, or point
   outside the run through a symlink are all refused (rules in gonio/runs.py's docstring).
3. The HTML report escapes every user-supplied string: an HTML parser finds no injected
   element or attribute, and the strings appear as text.
"""

from __future__ import annotations

import ast
import json
import sqlite3
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from acquisition.config import load_plan, load_rig
from acquisition.store import CaptureStart, RunStore, RunStoreError
from plumbing.config import ConfigError
from tests.support.paths import REPO

PACKAGES = ("acquisition", "calibration", "fitting", "gonio", "simulator")
EVIL = "<script>alert(1)</script>"
QUOTES = "\"'&"
BAD = f"{EVIL} {QUOTES}"


# -- 1. configs never execute code -----------------------------------------------------------
FORBIDDEN_MODULES = {"pickle", "cPickle", "_pickle", "dill", "cloudpickle", "marshal", "shelve"}
FORBIDDEN_BUILTINS = {"eval", "exec", "compile", "__import__"}
FORBIDDEN_ATTRS = {
    ("yaml", "load"),
    ("yaml", "unsafe_load"),
    ("yaml", "full_load"),
    ("pickle", "load"),
    ("pickle", "loads"),
    ("pd", "read_pickle"),
    ("pandas", "read_pickle"),
    ("joblib", "load"),
    ("torch", "load"),
    ("os", "system"),
    ("os", "popen"),
}


def code_execution_findings(source: str, name: str = "<src>") -> list[str]:
    """Places in `source` that could turn data into running code."""
    found = []
    for node in ast.walk(ast.parse(source, name)):
        where = f"{name}:{getattr(node, 'lineno', 0)}"
        if isinstance(node, ast.Import):
            found += [
                f"{where}: import {a.name}" for a in node.names if a.name in FORBIDDEN_MODULES
            ]
        elif isinstance(node, ast.ImportFrom) and node.module in FORBIDDEN_MODULES:
            found.append(f"{where}: from {node.module} import")
        elif isinstance(node, ast.Call):
            f = node.func
            if isinstance(f, ast.Name) and f.id in FORBIDDEN_BUILTINS:
                found.append(f"{where}: {f.id}()")
            if (
                isinstance(f, ast.Attribute)
                and isinstance(f.value, ast.Name)
                and (f.value.id, f.attr) in FORBIDDEN_ATTRS
            ):
                found.append(f"{where}: {f.value.id}.{f.attr}()")
            for kw in node.keywords:
                if (
                    kw.arg in ("allow_pickle", "shell")
                    and isinstance(kw.value, ast.Constant)
                    and kw.value.value is True
                ):
                    found.append(f"{where}: {kw.arg}=True")
    return found


def test_scanner_finds_each_forbidden_construct() -> None:
    """The scanner itself can fail: each construct in a known-bad snippet is reported."""
    bad = (
        "import pickle\nfrom marshal import loads\nimport yaml\nimport numpy as np\n"
        "import subprocess, os\n"
        "eval('1')\nexec('x = 1')\n__import__('os')\nyaml.load(s)\npickle.loads(b)\n"
        "np.load(p, allow_pickle=True)\nsubprocess.run(c, shell=True)\nos.system('ls')\n"
    )
    found = code_execution_findings(bad)
    for needle in (
        "import pickle",
        "from marshal",
        "eval()",
        "exec()",
        "__import__()",
        "yaml.load()",
        "pickle.loads()",
        "allow_pickle=True",
        "shell=True",
        "os.system()",
    ):
        assert any(needle in f for f in found), needle
    # Method calls named like builtins (Mitsuba's bsdf.eval, re.compile) are not findings.
    assert code_execution_findings("bsdf.eval(ctx, si, w)\nre.compile('x')\n") == []


def test_no_code_execution_primitives_in_our_packages() -> None:
    files = [p for pkg in PACKAGES for p in sorted((REPO / pkg).rglob("*.py"))]
    assert len(files) > 50  # the walk really covers the source tree
    found = []
    for path in files:
        found += code_execution_findings(path.read_text(), str(path.relative_to(REPO)))
    assert found == []


def test_python_looking_text_in_a_toml_config_stays_a_string(tmp_path: Path) -> None:
    code = "__import__('os').system('touch PWNED')"
    plan = tmp_path / "plan.toml"
    plan.write_text(
        tomli_w.dumps(
            {
                "name": code,
                "type": "isotropic",
                "theta_i_deg": [30.0],
                "theta_o_deg": [0.0],
                "exposures_s": [0.002],
            }
        )
    )
    cfg = load_plan(plan)
    assert cfg.name == code  # inert data
    assert not (tmp_path / "PWNED").exists() and not Path("PWNED").exists()
    # Unquoted, the same text is not TOML at all: a one-line refusal naming the file.
    bare = tmp_path / "bare.toml"
    bare.write_text(f"name = {code}\n")
    with pytest.raises(ConfigError) as info:
        load_plan(bare)
    msg = str(info.value)
    assert "\n" not in msg and "bare.toml" in msg and "not valid TOML" in msg
    assert not (tmp_path / "PWNED").exists()


@pytest.mark.parametrize("suffix", [".yaml", ".yml", ".py", ".pkl", ".pickle", ".ini", ""])
def test_configs_other_than_toml_or_json_are_refused(tmp_path: Path, suffix: str) -> None:
    src = (REPO / "configs" / "rigs" / "sim.toml").read_text()
    path = tmp_path / f"rig{suffix}"
    path.write_text(src)  # valid TOML inside: the suffix alone decides
    for loader in (load_rig, load_plan):
        with pytest.raises(ConfigError) as info:
            loader(path)
        msg = str(info.value)
        assert "\n" not in msg and str(path) in msg and "must be TOML (.toml) or JSON" in msg


def test_a_json_config_is_read_like_the_same_toml(tmp_path: Path) -> None:
    import tomllib

    toml_path = REPO / "configs" / "plans" / "demo.toml"
    data = tomllib.loads(toml_path.read_text())
    json_path = tmp_path / "demo.json"
    json_path.write_text(json.dumps(data))
    assert load_plan(json_path) == load_plan(toml_path)


# -- 2. run names and paths cannot escape ----------------------------------------------------
def _cli(args: list[str], monkeypatch: pytest.MonkeyPatch, capsys) -> tuple[int, str]:
    """Run `gonio ARGS` in-process; return (exit code, stderr)."""
    from gonio import cli

    monkeypatch.setattr("sys.argv", ["gonio", *args])
    monkeypatch.delenv("GONIO_DEBUG", raising=False)
    code = 0
    try:
        cli.main()
    except SystemExit as exc:
        code = int(exc.code or 0)
    return code, capsys.readouterr().err


def _tiny_run(root: Path, frame_name: str | None = None) -> Path:
    """A complete one-capture run written through the store; optionally a tampered path."""
    store = RunStore.create(root, 'name = "t"\n')
    cid = store.begin_capture(
        CaptureStart(
            pose_index=0,
            bracket_index=0,
            exposure_s=0.01,
            pose=(0.3, 0.0, 0.3, np.pi),
            axes_commanded={},
            axes_measured={},
            light_dir=[0.0, 0.0, 1.0],
            camera_dir=[0.0, 0.0, 1.0],
            suffix=".exr",
            devices={},
            lab_time_s=0.0,
        )
    )
    store.finish_capture(cid, b"frame bytes", {})
    store.mark_complete()
    store.close()
    if frame_name is not None:
        with sqlite3.connect(root / "manifest.sqlite") as db:
            db.execute("UPDATE captures SET frame_path = ?", (frame_name,))
        db.close()
    return root


@pytest.mark.parametrize(
    "args",
    [
        ["acquire", "--out", "runs/../../escaped", "--rig", "r.toml", "--plan", "p.toml"],
        ["acquire", "--out", "../escaped", "--rig", "r.toml", "--plan", "p.toml"],
        ["demo", "--quick", "--out", "../escaped"],
        ["runs", "show", "../../etc"],
        ["runs", "show", "x/../../etc", "--root", "runs"],
    ],
    ids=["acquire-nested", "acquire", "demo", "runs-show", "runs-show-nested"],
)
def test_dotdot_in_run_paths_is_refused(
    args: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    monkeypatch.chdir(tmp_path)
    code, err = _cli(args, monkeypatch, capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert "'..' is not allowed in run paths" in lines[0]
    assert list(tmp_path.iterdir()) == []  # nothing was created, anywhere under cwd
    assert not (tmp_path.parent / "escaped").exists()


def test_a_bare_run_name_stays_inside_the_runs_directory(tmp_path: Path) -> None:
    from gonio.runs import RunPathError, resolve_run

    root = tmp_path / "runs"
    root.mkdir()
    outside = _tiny_run(tmp_path / "elsewhere")
    (root / "sneaky").symlink_to(outside, target_is_directory=True)
    _tiny_run(root / "fine")
    assert resolve_run("fine", root) == root / "fine"
    with pytest.raises(RunPathError, match="outside the runs directory"):
        resolve_run("sneaky", root)
    with pytest.raises(RunPathError, match="'..' is not allowed"):
        resolve_run("..", root)


def test_explicit_normal_run_paths_keep_working(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    run = _tiny_run(tmp_path / "runs" / "r1")
    monkeypatch.chdir(tmp_path)
    for arg in (str(run), "runs/r1"):  # absolute, and relative without '..'
        code, err = _cli(["runs", "show", arg, "--no-verify"], monkeypatch, capsys)
        assert code == 0, err
    code, err = _cli(["runs", "show", "r1", "--root", "runs", "--no-verify"], monkeypatch, capsys)
    assert code == 0, err


@pytest.mark.parametrize("frame", ["../../etc/passwd", "/etc/passwd", "frames/../../outside"])
def test_manifest_frame_paths_must_stay_inside_the_run(tmp_path: Path, frame: str) -> None:
    run = _tiny_run(tmp_path / "run", frame_name=frame)
    store = RunStore.open(run)
    try:
        for read in (lambda: list(store.captures()), store.verify):
            with pytest.raises(RunStoreError, match="not a path inside the run directory"):
                read()
    finally:
        store.close()
    # The same row left pending by a "crash": resume would adopt the file at that path.
    with sqlite3.connect(run / "manifest.sqlite") as db:
        db.execute("UPDATE captures SET status = 'pending', sha256 = NULL")
        db.execute("UPDATE meta SET value = 'incomplete' WHERE key = 'status'")
    db.close()
    store = RunStore.open(run, writable=True)
    try:
        with pytest.raises(RunStoreError, match="not a path inside the run directory"):
            store.adopt_orphans()
        assert store.count("done") == 0
    finally:
        store.close()


def test_a_symlinked_frame_leaving_the_run_is_refused(tmp_path: Path) -> None:
    run = _tiny_run(tmp_path / "run")
    secret = tmp_path / "secret.txt"
    secret.write_text("not yours")
    (frame,) = (run / "frames").iterdir()
    frame.unlink()
    frame.symlink_to(secret)
    store = RunStore.open(run)
    try:
        with pytest.raises(RunStoreError, match="resolves outside the run directory"):
            store.verify()
    finally:
        store.close()


def test_calibrate_refuses_a_tampered_manifest_without_reading_outside(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    """A valid frame placed *outside* the run, named by the manifest: were the path followed,
    calibration would succeed and write samples.parquet."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(REPO / "tests" / "bad_inputs" / "run_dirs" / "frame_path_escape", run)
    (frame,) = (run / "frames").iterdir()
    shutil.move(frame, tmp_path / "outside.exr")
    with sqlite3.connect(run / "manifest.sqlite") as db:
        db.execute("UPDATE captures SET frame_path = '../outside.exr'")
    db.close()
    code, err = _cli(["calibrate", str(run)], monkeypatch, capsys)
    assert code == 2 and "not a path inside the run directory" in err, err
    assert not (run / "samples.parquet").exists()


def test_pending_row_with_escaping_path_is_never_written(tmp_path: Path) -> None:
    """finish_capture writes to the row's frame path: a tampered one is refused, not written."""
    store = RunStore.create(tmp_path / "run", "")
    cid = store.begin_capture(
        CaptureStart(
            pose_index=0,
            bracket_index=0,
            exposure_s=0.01,
            pose=(0.3, 0.0, 0.3, np.pi),
            axes_commanded={},
            axes_measured={},
            light_dir=[0.0, 0.0, 1.0],
            camera_dir=[0.0, 0.0, 1.0],
            suffix=".exr",
            devices={},
            lab_time_s=0.0,
        )
    )
    with store._db:
        store._db.execute("UPDATE captures SET frame_path = '../planted.exr' WHERE id = ?", (cid,))
    with pytest.raises(RunStoreError, match="not a path inside the run directory"):
        store.finish_capture(cid, b"data", {})
    store.close()
    assert not (tmp_path / "planted.exr").exists()


# -- 3. the HTML report escapes user strings -------------------------------------------------
class _Collect(HTMLParser):
    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.tags: list[tuple[str, list[tuple[str, str | None]]]] = []
        self.text: list[str] = []

    def handle_starttag(self, tag, attrs) -> None:
        self.tags.append((tag, attrs))

    def handle_startendtag(self, tag, attrs) -> None:
        self.tags.append((tag, attrs))

    def handle_data(self, data) -> None:
        self.text.append(data)


def _no_nulls(d: dict) -> dict:
    return {k: v for k, v in d.items() if v is not None}


def _evil_run(root: Path) -> Path:
    """A run, samples and two fits whose every free-text field carries BAD."""
    from brdfdata.samples import SampleTable, write_samples
    from fitting.result import FitResult
    from simulator.scene import load_scene

    scene = load_scene(REPO / "configs" / "scenes" / "demo.toml").model_dump(mode="json")
    scene["name"] = BAD
    scene = json.loads(
        json.dumps(scene), object_hook=lambda d: {k: v for k, v in d.items() if v is not None}
    )
    doc = {
        "gonio": {"version": BAD, "started_at": BAD},
        "notes": BAD,
        "rig": {"name": BAD},
        "plan": {"name": BAD, "notes": BAD},
        "scene": scene,
    }
    store = RunStore.create(root, tomli_w.dumps(doc))
    cid = store.begin_capture(
        CaptureStart(
            pose_index=0,
            bracket_index=0,
            exposure_s=0.01,
            pose=(0.3, 0.0, 0.3, np.pi),
            axes_commanded={},
            axes_measured={},
            light_dir=[0.0, 0.0, 1.0],
            camera_dir=[0.0, 0.0, 1.0],
            suffix=".exr",
            devices={},
            lab_time_s=0.0,
        )
    )
    store.finish_capture(cid, b"frame", {})
    store.close()
    rng = np.random.default_rng(0)
    n = 60
    theta_o = rng.uniform(0.05, 1.3, n)
    write_samples(
        root / "samples.parquet",
        SampleTable(
            theta_i=np.full(n, 0.4),
            phi_i=np.zeros(n),
            theta_o=theta_o,
            phi_o=np.full(n, np.pi),
            channel=np.array(["R"] * n),
            f=np.full(n, 0.2),
            sigma=np.full(n, 0.01),
            flags=np.zeros(n, np.int32),
        ),
    )
    q = {"map": 0.6, "median": 0.6, "p16": 0.59, "p84": 0.61, "p2.5": 0.58, "p97.5": 0.62}
    common = dict(
        channels=["R"],
        diagnostics={
            "tau": {},
            "ess": {},
            "acceptance": 0.3,
            "converged": True,
            "stop_reason": BAD,
        },
        goodness={BAD: 1.0},
        n_samples=n,
        wall_time_s=1.0,
    )
    # A known model whose unit, stop reason and goodness key are hostile...
    FitResult(model="lambert", options={}, parameters={"kd_R": {"unit": BAD, **q}}, **common).write(
        root / "fit-lambert.json"
    )
    # ...and a foreign fit whose model name, options and parameter name are.
    FitResult(model=BAD, options={BAD: BAD}, parameters={BAD: {"unit": BAD, **q}}, **common).write(
        root / "fit-foreign.json"
    )
    return root


def test_report_escapes_every_user_string(tmp_path: Path) -> None:
    from gonio.report import write_report

    # A run directory name may hold any character but '/': quotes, ampersand and brackets.
    run = _evil_run(tmp_path / "run <b onclick=x>'\"&")
    html = write_report(run).read_text(encoding="utf-8")
    parser = _Collect()
    parser.feed(html)
    parser.close()
    tags = [t for t, _ in parser.tags]
    assert "script" not in tags and "b" not in tags
    for tag, attrs in parser.tags:
        for name, value in attrs:
            assert not name.startswith("on"), (tag, name)
            if name == "src":
                assert value.startswith("data:image/png;base64,"), value[:60]
    # Only the page's own elements exist.
    allowed = {
        "html",
        "head",
        "meta",
        "title",
        "style",
        "body",
        "h1",
        "h2",
        "h3",
        "p",
        "img",
        "table",
        "tr",
        "th",
        "td",
        "code",
        "span",
        "br",
        "details",
        "summary",
        "pre",
        "div",  # the verdict box
        "strong",  # its title
        "ul",  # the model's coverage list
        "li",
    }
    assert set(tags) <= allowed, set(tags) - allowed
    text = "".join(parser.text)
    # Each hostile field shows up as text, verbatim: rig, plan, notes, version, stop reason,
    # unit, goodness key, foreign model name, run directory name.
    assert text.count(EVIL) >= 8, text.count(EVIL)
    assert QUOTES in text
    assert "run <b onclick=x>'\"&" in text
    # And in the source every '<' of them is an entity.
    assert EVIL not in html and "&lt;script&gt;" in html


def test_a_frame_symlinked_to_itself_is_refused_in_one_line(tmp_path: Path) -> None:
    """Issue 47: a frame that is a symbolic link to itself made Path.resolve raise RuntimeError
    (Python 3.11: "Symlink loop"), an internal error of `calibrate` and `runs show`."""
    run = _tiny_run(tmp_path / "run")
    (frame,) = (run / "frames").iterdir()
    frame.unlink()
    frame.symlink_to(frame.name)
    store = RunStore.open(run)
    try:
        with pytest.raises(RunStoreError, match="is a symbolic link that loops"):
            store.verify()
    finally:
        store.close()
