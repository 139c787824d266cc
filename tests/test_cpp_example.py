"""The C++ example (examples/cpp): built against a prebuilt ONNX Runtime from the npm registry, it
filters one state with an exported filter, makes the Python runtime's input checks, refuses an
untrusted batch, and decides as ``reach_runtime.Filter`` does on the same file.

Slow (about 50 s cold, 40 s with npm's cache: the Air3D export alone takes 20-35 s); CI runs it in a
step of its own. It skips where the build cannot run: no npm, g++ or tar, or not Linux x86-64."""

from __future__ import annotations

import os
import platform
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "examples" / "cpp" / "build_and_run.sh"


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """Run build_and_run.sh once, in a fresh build folder: fetch, build, export Air3D, check."""
    missing = [tool for tool in ("npm", "g++", "tar", "sha256sum") if shutil.which(tool) is None]
    if missing:
        pytest.skip(f"the C++ example needs {', '.join(missing)}")
    if (platform.system(), platform.machine()) != ("Linux", "x86_64"):
        pytest.skip("the npm package ships ONNX Runtime's Linux library for x86-64 only")
    build = tmp_path_factory.mktemp("cpp-build")
    env = {**os.environ, "REACH_CPP_BUILD": str(build)}
    result = subprocess.run(["bash", str(SCRIPT)], capture_output=True, text=True, env=env, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return build, result.stdout


def _run(binary: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(binary), *args], capture_output=True, text=True, timeout=60)


def _fields(stdout: str) -> dict[str, str]:
    return dict(line.split(": ", 1) for line in stdout.splitlines() if ": " in line)


def test_the_script_builds_the_example_and_its_checks_pass(built):
    _, stdout = built
    assert stdout.rstrip().endswith("build_and_run.sh: 8 checks passed")
    assert "filter: switch of air3d (avoid problem), state_dim 3, control_dim 1, time_to_go in [0, 1.1]" in stdout
    for line in (
        "flags: intervened=1 infeasible=0 outside_domain=0",  # collision
        "flags: intervened=0 infeasible=0 outside_domain=0",  # clear
        "flags: intervened=1 infeasible=0 outside_domain=1",  # outside the domain: the backup input
        "refused: states contain NaN or inf (or overflow float32), e.g. [nan,0,0]",
        "refused: time-to-go t = 2 lies outside [0, 1.1], the times this value function covers",
    ):
        assert line in stdout.splitlines()


def test_the_cpp_example_decides_as_the_python_runtime(built):
    """On 16 random states, times and nominal inputs (some outside the domain): the same flags,
    control, value and gradient as ``reach_runtime.Filter`` on the same file."""
    from reach_runtime import Filter

    build, _ = built
    path = build / "air3d-switch.onnx"
    runtime = Filter.load(path)
    rng = np.random.default_rng(0)
    states = rng.uniform([-1.2, -1.2, -np.pi], [1.2, 1.2, np.pi], size=(16, 3)).astype(np.float32)
    times = rng.uniform(0.0, 1.1, size=16).astype(np.float32)
    nominal = rng.uniform(-3, 3, size=(16, 1)).astype(np.float32)
    applied, info = runtime(states, nominal, t=times)
    decisions = set()
    for i in range(16):
        result = _run(
            build / "filter_one_state",
            str(path),
            "--state", ",".join(f"{v:.9g}" for v in states[i]),
            "--u", f"{nominal[i, 0]:.9g}",
            "--t", f"{times[i]:.9g}",
        )  # fmt: skip
        assert result.returncode == 0, result.stdout + result.stderr
        fields = _fields(result.stdout)
        flags = f"intervened={int(info.intervened[i])} infeasible={int(info.infeasible[i])} "
        flags += f"outside_domain={int(info.outside_domain[i])}"
        assert fields["flags"] == flags
        decisions.add(flags)
        np.testing.assert_allclose(float(fields["control"]), applied[i, 0], atol=1e-5)
        np.testing.assert_allclose(float(fields["value"]), info.value[i], atol=1e-5)
        gradient = [float(v) for v in fields["gradient"].split(",")]
        np.testing.assert_allclose(gradient, info.gradient[i], atol=1e-4)
    assert len(decisions) >= 2  # the states are not all decided alike


def test_the_cpp_example_refuses_an_untrusted_batch(built, tmp_path, nan_weights):
    """The exported file with its weight matrices set to NaN: the graph sets `untrusted` and the
    example refuses to decide, as the Python runtime does (tests/test_export.py)."""
    build, _ = built
    nan_weights(build / "air3d-switch.onnx", tmp_path / "nan.onnx")
    result = _run(
        build / "filter_one_state", str(tmp_path / "nan.onnx"), "--state", "0.5,0.2,0", "--u", "1", "--t", "0.5"
    )
    assert result.returncode == 3
    assert "refused: the value function returned a non-finite value, gradient or optimal input" in result.stdout
    assert "control:" not in result.stdout


def test_the_cpp_example_refuses_a_file_that_is_not_a_reach_filter(built, tmp_path):
    onnx = pytest.importorskip("onnx")

    build, _ = built
    model = onnx.load(build / "air3d-switch.onnx")
    del model.metadata_props[:]
    onnx.save(model, tmp_path / "bare.onnx")
    result = _run(build / "filter_one_state", str(tmp_path / "bare.onnx"), "--state", "0,0,0", "--u", "1")
    assert result.returncode == 2
    assert "not a reach filter of format reach-filter/1" in result.stderr
    missing = _run(build / "filter_one_state", str(tmp_path / "none.onnx"), "--state", "0,0,0", "--u", "1")
    assert missing.returncode == 2 and "error: ONNX Runtime:" in missing.stderr
