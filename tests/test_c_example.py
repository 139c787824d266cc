"""The C example (examples/c): an Air3D filter exported as one C file (``reach export --c``), built
into a program with the system's C compiler, decides as ``reach_runtime.Filter`` does on the same
export, makes the runtime's input checks, and refuses a value function it cannot trust.

Slow (an export, about 25 s, and two builds): CI runs it in a step of its own."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow
pytest.importorskip("onnx")

from reach_runtime import Filter  # noqa: E402
from reach_runtime.native import c_source  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "c"
FLAGS = ["-O3", "-march=native", "-fno-math-errno", "-fno-trapping-math"]


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    compiler = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        pytest.skip("the C example needs a C compiler")
    build = tmp_path_factory.mktemp("c-build")
    env = {**os.environ, "REACH_C_BUILD": str(build), "OMP_NUM_THREADS": "1"}
    result = subprocess.run(
        ["bash", str(EXAMPLE / "build_and_run.sh")], capture_output=True, text=True, env=env, timeout=600
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return build, result.stdout, compiler


def _run(binary: Path, *args: float | str) -> subprocess.CompletedProcess:
    return subprocess.run([str(binary), *map(str, args)], capture_output=True, text=True, timeout=60)


def _fields(stdout: str) -> dict[str, str]:
    return dict(line.split(": ", 1) for line in stdout.splitlines() if ": " in line)


def test_the_c_program_decides_as_the_python_runtime(built):
    build, stdout, _ = built
    lines = stdout.splitlines()
    assert "flags: intervened=1 infeasible=0 outside_domain=0" in lines  # head-on, 0.1 m apart
    assert "flags: intervened=0 infeasible=0 outside_domain=0" in lines  # far apart
    assert "flags: intervened=1 infeasible=0 outside_domain=1" in lines  # outside the domain
    runtime = Filter.load(build / "air3d-switch.onnx")
    rng = np.random.default_rng(0)
    low, high = np.array(runtime.metadata.domain).T
    for _ in range(12):
        x = rng.uniform(low, high).astype(np.float32)
        u = rng.uniform(-1, 1, 1).astype(np.float32)
        t = float(rng.uniform(0, 1.1))
        applied, info = runtime(x, u, t)
        done = _run(build / "filter_one_state", f"{t!r}", *(f"{v!r}" for v in x.tolist()), f"{float(u[0])!r}")
        assert done.returncode == 0, done.stdout + done.stderr
        fields = _fields(done.stdout)
        assert abs(float(fields["value"]) - float(info.value)) < 1e-5
        if abs(float(info.value) - runtime.metadata.threshold) > 1e-4:
            assert fields["flags"].startswith(f"intervened={int(info.intervened)} ")
            assert abs(float(fields["control"]) - float(applied[0])) < 1e-5


def test_the_c_program_fails_closed(built, tmp_path, nan_weights):
    build, stdout, compiler = built
    assert "refused: a state, time or nominal input is NaN or inf (status 1)" in stdout
    assert "refused: the time-to-go lies outside the range the value function covers (status 3)" in stdout
    bad = _run(build / "filter_one_state", 1.1, 0.1, 0, 0, "inf")
    assert bad.returncode == 3 and "status 1" in bad.stdout
    # a value function it cannot trust: the same export with NaN weights, compiled the same way
    nan_weights(build / "air3d-switch.onnx", tmp_path / "nan.onnx")
    (tmp_path / "filter.c").write_text(c_source(tmp_path / "nan.onnx"))
    binary = tmp_path / "filter_one_state"
    subprocess.run(
        [compiler, *FLAGS, "-I", str(tmp_path), "-o", str(binary), str(EXAMPLE / "filter_one_state.c"), "-lm"],
        check=True,
        timeout=300,
    )
    untrusted = _run(binary, 1.1, 0.5, 0.5, 0, 1)
    assert untrusted.returncode == 3 and "refused: the value function returned a non-finite value" in untrusted.stdout
