"""The exported safety filter: the ONNX graph decides as the torch filter does, the torch-free
runtime fails closed as it does, the exporter refuses what it cannot export, and the runtime runs in
a fresh virtual environment that has no torch."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

from reach_runtime import Filter
from safety import SafetyFilter, load_value_function
from safety.filters.export import export_filter
from safety.filters.settings import FilterSettings

ROOT = Path(__file__).resolve().parents[1]
DT = 0.05


@pytest.fixture(scope="module")
def air3d():
    return load_value_function("pretrained:air3d").value_function


class _Exports(dict):
    """Air3D filters exported once per kind, on first use (an export traces and converts for 10-30 s)."""

    def __init__(self, air3d, folder: Path) -> None:
        super().__init__()
        self.air3d, self.folder = air3d, folder

    def __missing__(self, kind: str):
        settings = {
            "switch": FilterSettings("switch"),
            "smooth": FilterSettings("smooth"),
            "lookahead": FilterSettings("lookahead", backup_horizon=0.0),
        }[kind]
        self[kind] = export_filter(self.air3d, self.folder / f"{kind}.onnx", settings, dt=DT, check_states=64)
        return self[kind]


@pytest.fixture(scope="module")
def exported(air3d, tmp_path_factory):
    """Air3D filters exported once per kind, as the tests ask for them. The lookahead checks its
    nominal step alone here (backup_horizon 0: each backup step adds about as much again); with
    backup steps: the slow test below and ``benchmarks/export_filter.py``."""
    return _Exports(air3d, tmp_path_factory.mktemp("exported"))


def _inputs(system, count: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    x = system.sample_states(count, generator=g)
    t = 1.1 * torch.rand(count, generator=g)
    u = 2 * torch.rand(count, system.control_dim, generator=g) - 1
    return x, t, u


# the lookahead's export is the slowest (about 20 s): run by name in .ci/run's slow step, which keeps
# the default suite under its 10 minutes on 2 cores
@pytest.mark.parametrize("kind", ["switch", "smooth", pytest.param("lookahead", marks=pytest.mark.slow)])
def test_the_exported_filter_decides_as_the_torch_filter(air3d, exported, kind):
    """On 2,000 random states, times and nominal inputs: the same decisions except within 1e-4 of
    the threshold, values and gradients within float32 rounding, and the same applied input where
    the decision agrees (a bang-bang input may flip where its switching function is ~0)."""
    _check_equivalence(air3d, exported[kind], kind)


@pytest.mark.slow
def test_the_exported_lookahead_with_backup_steps_decides_as_the_torch_filter(air3d, tmp_path):
    settings = FilterSettings("lookahead", backup_horizon=2 * DT)
    result = export_filter(air3d, tmp_path / "lookahead.onnx", settings, dt=DT, check_states=64)
    assert result.metadata["backup_steps"] == 2
    _check_equivalence(air3d, result, "lookahead")


def _check_equivalence(air3d, result, kind: str) -> None:
    meta = result.metadata
    assert meta["settings"]["kind"] == kind and meta["system_name"] == "air3d" and meta["dt"] == DT
    assert meta["fingerprint"].startswith("sha256:") and meta["settings"]["outside_domain"] == "backup"
    threshold = meta["settings"]["threshold"]
    torch_filter = SafetyFilter(air3d, threshold, settings=FilterSettings(**meta["settings"]), dt=DT)
    runtime = Filter.load(result.path)
    x, t, u = _inputs(air3d.system, 2000, 1)
    applied, info = torch_filter(x, t, u)
    got, got_info = runtime(x.numpy(), u.numpy(), t.numpy())
    np.testing.assert_allclose(got_info.value, info.value.numpy(), atol=2e-5, rtol=1e-5)
    np.testing.assert_allclose(got_info.gradient, info.gradient.numpy(), atol=2e-4, rtol=1e-4)
    differ = got_info.intervened != info.intervened.numpy()
    if kind != "lookahead":  # the lookahead's verdict is its rollout's minimum, not V here
        assert not (differ & (np.abs(info.value.numpy() - threshold) > 1e-4)).any()
    assert differ.mean() < 1e-3
    agree = ~differ
    same = np.isclose(got[agree], applied.numpy()[agree], atol=1e-5).all(-1)
    assert same.mean() > 0.995 and got_info.intervened.any() and (~got_info.intervened).any()


def test_the_runtime_takes_one_state_or_a_batch_and_defaults_the_time_to_go(exported, air3d):
    runtime = Filter.load(exported["switch"].path)
    x, _, u = _inputs(air3d.system, 5, 2)
    batch, info = runtime(x.numpy(), u.numpy())  # avoid: the horizon by default
    one, one_info = runtime(x[0].numpy(), u[0].numpy(), t=1.1)
    assert batch.shape == (5, 1) and one.shape == (1,) and one_info.value.shape == ()
    np.testing.assert_allclose(one, batch[0], atol=1e-6)
    np.testing.assert_allclose(one_info.value, info.value[0], atol=1e-6)
    assert "switch of air3d" in repr(runtime)


def test_the_runtime_fails_closed(exported, air3d):
    """Bad input raises before the graph runs; a state outside the domain keeps no nominal input."""
    runtime = Filter.load(exported["switch"].path)
    x, _, u = _inputs(air3d.system, 3, 3)
    xs, us = x.numpy(), u.numpy()
    bad = xs.copy()
    bad[1, 0] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        runtime(bad, us)
    with pytest.raises(ValueError, match="overflow float32"):
        runtime(xs.astype(np.float64) * np.array([1e300, 1, 1]), us)
    with pytest.raises(ValueError, match=r"t = 1.5 lies outside \[0, 1.1\]"):
        runtime(xs, us, t=1.5)
    with pytest.raises(ValueError, match=r"t = -0\.1"):
        runtime(xs, us, t=np.array([0.5, -0.1, 0.5]))
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 3\)"):
        runtime(xs[:, :2], us)
    with pytest.raises(ValueError, match="u_nominal must have shape"):
        runtime(xs, us[:2])
    with pytest.raises(ValueError, match="real numbers"):
        runtime(xs.astype(str), us)
    far = xs.copy()
    far[:, 0] = 5.0  # 5 m away: outside the 1 m box the network was trained on
    kept = np.zeros_like(us)
    applied, info = runtime(far, kept)
    assert info.outside_domain.all() and info.intervened.all()


def test_an_untrusted_value_raises_in_the_runtime(exported, air3d, tmp_path, nan_weights):
    """An exported file whose weight matrices are edited to NaN: the graph flags the batch and the
    runtime refuses it (it never passes the nominal input on a value it cannot trust)."""
    nan_weights(exported["smooth"].path, tmp_path / "nan.onnx")
    x, _, u = _inputs(air3d.system, 2, 4)
    with pytest.raises(ValueError, match="non-finite value"):
        Filter.load(tmp_path / "nan.onnx")(x.numpy(), u.numpy(), t=0.5)


def test_the_exporter_refuses_what_it_cannot_export(air3d, air3d_grid, tmp_path):
    with pytest.raises(ValueError, match="cannot be exported to ONNX"):
        export_filter(air3d_grid, tmp_path / "grid.onnx")
    with pytest.raises(ValueError, match=r"must end in \.onnx"):
        export_filter(air3d, tmp_path / "filter.pt")
    with pytest.raises(ValueError, match="is a directory"):
        export_filter(air3d, tmp_path)
    with pytest.raises(ValueError, match="needs a step dt"):
        export_filter(air3d, tmp_path / "f.onnx", kind="lookahead")
    with pytest.raises(ValueError, match="bfloat16"):
        export_filter(air3d.with_matmul_dtype(torch.bfloat16), tmp_path / "f.onnx")
    with pytest.raises(ValueError, match="filter kind must be one of"):
        export_filter(air3d, tmp_path / "f.onnx", kind="magic")
    assert not list(tmp_path.glob("*.onnx"))


class _RecordingBar:
    """Stands in for tqdm: keeps the stage names the export shows, and how it was built."""

    made: list[dict] = []

    def __init__(self, **kwargs) -> None:
        self.stages: list[str] = []
        _RecordingBar.made.append({"kwargs": kwargs, "stages": self.stages})

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None

    def set_description_str(self, text: str) -> None:
        self.stages.append(text)

    def update(self, n: int = 1) -> None:
        pass


def test_the_export_names_its_stage_on_a_progress_bar(air3d, tmp_path, monkeypatch):
    """A large network's conversion takes minutes (the quadrotor's 12 on 2 cores): the bar names each
    stage as it starts. Here the converter breaks: the bar had reached it, and no file is left."""
    import safety.filters.export as export

    def broken(graph, example, path):
        raise RuntimeError("the converter broke")

    _RecordingBar.made.clear()
    monkeypatch.setattr(export, "tqdm", _RecordingBar)
    monkeypatch.setattr(export, "_convert", broken)
    out = tmp_path / "f.onnx"
    with pytest.raises(RuntimeError, match="the converter broke"):
        export_filter(air3d, out, FilterSettings("switch"), dt=DT)
    (bar,) = _RecordingBar.made
    assert bar["stages"] == [f"export: {stage}" for stage in export.EXPORT_STAGES[:2]] and bar["kwargs"]["total"] == 3
    assert "disable" not in bar["kwargs"] and not out.exists()  # TQDM_DISABLE still decides, as everywhere
    with pytest.raises(RuntimeError, match="the converter broke"):
        export_filter(air3d, out, FilterSettings("switch"), dt=DT, check_states=0, progress=False)
    assert _RecordingBar.made[1]["kwargs"]["disable"] is True and _RecordingBar.made[1]["kwargs"]["total"] == 2


def test_the_runtime_refuses_a_file_that_is_not_an_exported_filter(tmp_path):
    with pytest.raises(ValueError, match="no such file"):
        Filter.load(tmp_path / "missing.onnx")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(ValueError, match="not a readable ONNX model"):
        Filter.load(junk)


def test_reach_export_command_writes_and_refuses_in_one_line(tmp_path, air3d_grid):
    out = tmp_path / "cli.onnx"
    run = [sys.executable, "-m", "reach", "export"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    bad = subprocess.run(
        [*run, "pretrained:air3d", "--out", str(tmp_path / "x.txt")], capture_output=True, text=True, env=env
    )
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1 and ".onnx" in bad.stderr
    bad = subprocess.run(
        [*run, "pretrained:air3d", "--out", str(out), "--kind", "lookahead"], capture_output=True, text=True, env=env
    )
    assert bad.returncode == 2 and "needs a step dt" in bad.stderr and not out.exists()
    bad = subprocess.run(
        [*run, "pretrained:air3d", "--out", str(out), "--c", str(tmp_path / "f.h")],
        capture_output=True,
        text=True,
        env=env,
    )
    assert bad.returncode == 2 and "--c must name a .c file, got" in bad.stderr and not out.exists()
    assert len(bad.stderr.strip().splitlines()) == 1


#: what the runtime imports: NumPy and ONNX Runtime, and what ONNX Runtime imports or declares
RUNTIME_PACKAGES = ("numpy", "onnxruntime", "packaging", "flatbuffers", "google.protobuf")

_SCRIPT = """
import importlib.util, sys
assert importlib.util.find_spec("torch") is None, "torch is importable"
assert importlib.util.find_spec("reach") is None, "reach is importable"
from reach_runtime import Filter
f = Filter.load(sys.argv[1])
u, info = f([0.1, 0.0, 0.0], [1.0])  # 0.1 m apart, head-on: the filter intervenes
print(bool(info.intervened), float(info.value), u.tolist())
try:
    f([float("nan"), 0.0, 0.0], [1.0])
except ValueError as error:
    print("refused:", error)
assert "torch" not in sys.modules
"""


def _run_in_fresh_venv(venv: Path, app: Path, onnx_file: Path) -> None:
    python = venv / "bin" / "python"
    shutil.copytree(ROOT / "reach_runtime", app / "reach_runtime")
    done = subprocess.run(
        [str(python), "-c", _SCRIPT, str(onnx_file)], cwd=app, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    intervened, value, _ = done.stdout.splitlines()[0].split(" ", 2)
    assert intervened == "True" and float(value) < 0
    assert "refused: states contain NaN or inf" in done.stdout


def test_the_runtime_runs_in_a_fresh_venv_without_torch(exported, tmp_path):
    """A new virtual environment that sees only the runtime's folder, NumPy and ONNX Runtime (with
    what ONNX Runtime needs), linked from this one so that the default suite downloads nothing:
    no torch, no reach. (The same with the documented ``pip install`` line, both engines: the slow
    test at the end.)"""
    import importlib.util
    import sysconfig

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    linked = tmp_path / "linked"
    for name in RUNTIME_PACKAGES:
        spec = importlib.util.find_spec(name)
        assert spec is not None and spec.origin is not None, name
        top = name.split(".")[0]
        source = Path(spec.origin).parent
        for _ in name.split(".")[1:]:
            source = source.parent
        (linked / top).parent.mkdir(parents=True, exist_ok=True)
        if not (linked / top).exists():
            (linked / top).symlink_to(source)
    libs = Path(sysconfig.get_paths()["purelib"]) / "numpy.libs"
    if libs.exists():
        (linked / "numpy.libs").symlink_to(libs)
    site = next((venv / "lib").glob("python*/site-packages"))
    (site / "runtime_packages.pth").write_text(str(linked) + "\n")
    _run_in_fresh_venv(venv, tmp_path / "app", exported["switch"].path)


# ---------------------------------------------------------------------------------------------
# the native engine: the same filter compiled to C (reach_runtime.native), behind the same checks
needs_compiler = pytest.mark.skipif(
    not any(shutil.which(c) for c in ("cc", "gcc", "clang")), reason="the native engine needs a C compiler"
)


@pytest.fixture(scope="module")
def native_cache(tmp_path_factory):
    """One build cache for this module (a build takes several seconds): XDG_CACHE_HOME, restored after."""
    before = os.environ.get("XDG_CACHE_HOME")
    os.environ["XDG_CACHE_HOME"] = str(tmp_path_factory.mktemp("native-cache"))
    yield
    if before is None:
        os.environ.pop("XDG_CACHE_HOME", None)
    else:
        os.environ["XDG_CACHE_HOME"] = before


@needs_compiler
def test_the_native_engine_decides_as_onnx_runtime_and_fails_closed(exported, air3d, native_cache):
    """On 2,000 random states, the compiled switch decides as ONNX Runtime runs the same file: values
    within float32 rounding, the same decisions and applied inputs; and its bad input is refused,
    its states outside the domain overridden, exactly as with ONNX Runtime."""
    path = exported["switch"].path
    reference, native = Filter.load(path), Filter.load(path, engine="native")
    assert native.engine == "native" and reference.engine == "onnxruntime"
    x, t, u = _inputs(air3d.system, 2000, 5)
    expected, expected_info = reference(x.numpy(), u.numpy(), t.numpy())
    got, got_info = native(x.numpy(), u.numpy(), t.numpy())
    np.testing.assert_allclose(got_info.value, expected_info.value, atol=2e-6, rtol=1e-6)
    np.testing.assert_allclose(got_info.gradient, expected_info.gradient, atol=2e-5, rtol=1e-5)
    differ = got_info.intervened != expected_info.intervened
    assert not (differ & (np.abs(expected_info.value - native.metadata.threshold) > 1e-4)).any()
    assert np.isclose(got[~differ], expected[~differ], atol=1e-5).all(-1).mean() > 0.999
    one, _ = native(x[0].numpy(), u[0].numpy(), t=float(t[0]))
    assert one.shape == (1,) and np.allclose(one, got[0], atol=1e-6)
    bad = x.numpy()[:3].copy()
    bad[1, 0] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        native(bad, u.numpy()[:3])
    with pytest.raises(ValueError, match=r"t = 1.5 lies outside"):
        native(x.numpy()[:3], u.numpy()[:3], t=1.5)
    far = x.numpy()[:3].copy()
    far[:, 0] = 5.0
    _, info = native(far, np.zeros((3, 1), np.float32))
    assert info.outside_domain.all() and info.intervened.all()
    with pytest.raises(ValueError, match="engine must be one of onnxruntime, native"):
        Filter.load(path, engine="tvm")


@needs_compiler
def test_a_compiled_filter_that_disagrees_with_onnx_runtime_is_refused(exported, native_cache, monkeypatch):
    """The load-time check: a compiled graph whose values are off (here: shifted by 1e-3 after the
    C call) is refused before it decides anything."""
    from reach_runtime import native

    real = native.NativeGraph.run

    def shifted(self, feeds):
        out = real(self, feeds)
        out[1] = out[1] + 1e-3  # the value output
        return out

    monkeypatch.setattr(native.NativeGraph, "run", shifted)
    with pytest.raises(ValueError, match="disagrees with ONNX Runtime on values"):
        Filter.load(exported["switch"].path, engine="native")


@needs_compiler
@pytest.mark.slow
def test_an_untrusted_value_raises_in_the_native_engine(exported, air3d, tmp_path, nan_weights, native_cache):
    nan_weights(exported["switch"].path, tmp_path / "nan.onnx")
    x, _, u = _inputs(air3d.system, 2, 4)
    with pytest.raises(ValueError, match="non-finite value"):
        Filter.load(tmp_path / "nan.onnx", engine="native")(x.numpy(), u.numpy(), t=0.5)


@needs_compiler
def test_one_float32_state_on_the_native_engine_decides_as_the_general_path(exported, air3d, native_cache, monkeypatch):
    """The control loop's call (one float32 state, a number for t) takes the C file's checked entry:
    the same outputs, shapes and dtypes as the general path, on both sides of the switch; its
    refusals name the bad value as the general path does; and a state the C checks refuse is never
    decided, even should the general path accept it."""
    native = Filter.load(exported["switch"].path, engine="native")
    assert native._row_ok is not None
    x, t, u = _inputs(air3d.system, 64, 6)
    xs, us = x.numpy(), u.numpy()
    sides = set()
    for k in range(64):
        for cast in (np.float32, np.float64):  # float64 is cast on the way in, as the general path casts it
            state, nominal = xs[k].astype(cast), us[k].astype(cast)
            got, got_info = native(state, nominal, float(t[k]))
            expected, expected_info = native._decide(state, nominal, float(t[k]))
            pairs = [(got, expected)] + [(getattr(got_info, f), getattr(expected_info, f)) for f in vars(got_info)]
            for a, b in pairs:
                assert a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b)
        sides.add(bool(got_info.intervened))
    assert sides == {True, False}
    bad = xs[0].copy()
    bad[1] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        native(bad, us[0], 0.5)
    huge = xs[0].astype(np.float64)
    huge[0] = 1e300  # finite in float64, inf in float32
    with pytest.raises(ValueError, match=r"overflow float32\), e\.g\. \[1e\+300"):  # the value as given
        native(huge, us[0], 0.5)
    with pytest.raises(ValueError, match=r"t = 1.5 lies outside"):
        native(xs[0], us[0], 1.5)
    from reach_runtime import native as native_module

    monkeypatch.setattr(native_module.NativeGraph, "checked_row", lambda self, *a: (4, []))
    with pytest.raises(ValueError, match=r"refused this state \(status 4\)"):
        native(xs[0], us[0], 0.5)


#: the native engine in the fresh environment: compiled there, checked against ONNX Runtime, deciding
_NATIVE_SCRIPT = """
import importlib.util, sys
assert importlib.util.find_spec("torch") is None, "torch is importable"
from reach_runtime import Filter
f = Filter.load(sys.argv[1], engine="native")
u, info = f([0.1, 0.0, 0.0], [1.0])
print(f.engine, bool(info.intervened), float(info.value))
"""


def documented_install_line() -> list[str]:
    """The packages of the robot's install line in docs/export.md (``python -m pip install ...``)."""
    for line in (ROOT / "docs" / "export.md").read_text().splitlines():
        if "# the robot's install line" in line:
            command = line.split("#")[0].split()
            assert command[:4] == ["python", "-m", "pip", "install"], line
            return command[4:]
    raise AssertionError("docs/export.md has no line marked '# the robot's install line'")


@needs_compiler
@pytest.mark.slow
def test_the_documented_install_line_runs_both_engines_in_a_fresh_venv(exported, tmp_path):
    """A plain new virtual environment (no system site packages), the docs' install line with
    ``pip`` and nothing else, the runtime's folder copied beside: both engines load the export and
    decide there, torch and reach not importable."""
    assert "onnx" in documented_install_line()  # the native engine reads the graph with it
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    python = str(venv / "bin" / "python")
    pip = [python, "-m", "pip", "install", "-q", "--disable-pip-version-check"]
    subprocess.run([*pip, *documented_install_line()], check=True, timeout=600)
    app = tmp_path / "app"
    _run_in_fresh_venv(venv, app, exported["switch"].path)
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    done = subprocess.run(
        [python, "-c", _NATIVE_SCRIPT, str(exported["switch"].path)],
        cwd=app,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert done.returncode == 0, done.stderr
    engine, intervened, value = done.stdout.split()
    assert engine == "native" and intervened == "True" and float(value) < 0


def test_the_export_time_benchmark_refuses_a_model_it_cannot_export_in_one_line():
    """``benchmarks/export_filter.py export-time`` takes shipped networks only: a grid model stops in
    argparse's one line, before any export or table."""
    script = ROOT / "benchmarks" / "export_filter.py"
    done = subprocess.run(
        [sys.executable, str(script), "export-time", "relativepair"], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "argument NAME: invalid choice: 'relativepair'" in done.stderr.strip().splitlines()[-1]
    assert "| model |" not in done.stdout
