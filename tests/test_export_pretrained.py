"""Every shipped value network exports (``reach export pretrained:NAME``'s defaults) and passes the
export's own self-check: the written file loads as a robot loads it (digest, interface, a free
batch dimension, the graph following its metadata) and decides as the torch filter on 512 sampled
states. The batch is free: the runtime decides batches of 1, 3 and 7.

Grid models (``relativepair``) are not exported: the export takes networks and minimums of them,
not a grid's interpolation (``tests/test_export.py`` checks the refusal). Slow (an export each):
CI runs it in a step of its own, for the models that export in under a minute on 2 cores (every
kind, box and disc inputs, 3D to 10D). The others (Air3D, whose export ``tests/test_export.py``
checks too, the car fleets and the quadrotor: 2 to 12 minutes each) are ``release`` checks:
``python -m pytest -m release``."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.slow
pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

from reach_runtime import Filter  # noqa: E402
from safety.filters.export import CHECK_STATES, export_filter  # noqa: E402
from training.pretrained import card, names  # noqa: E402

NETWORKS = [name for name in names() if card(name).format == "network"]

#: exports of 2 to 12 minutes each on 2 cores (measured 2026-11-29, docs/results/benchmarks.md: air3d 1.8,
#: multivehicle6d 2.2, multivehicle9d 4.2, multivehicle12d 6.4, multivehicle15d 10.1, quadrotor 12.4);
#: run with -m release
RELEASE_ONLY = {"air3d", "multivehicle6d", "multivehicle9d", "multivehicle12d", "multivehicle15d", "quadrotor"}


def test_the_shipped_grids_are_the_only_models_left_out():
    assert sorted(set(names()) - set(NETWORKS)) == ["relativepair"]


def test_the_release_only_exports_name_shipped_networks():
    assert set(NETWORKS) >= RELEASE_ONLY and set(NETWORKS) - RELEASE_ONLY


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.release) if n in RELEASE_ONLY else n for n in NETWORKS]
)
def test_every_shipped_network_exports_and_passes_its_self_check(name, tmp_path):
    result = export_filter(f"pretrained:{name}", tmp_path / f"{name}.onnx")
    assert result.checked == CHECK_STATES
    assert result.metadata["source_verdict"]["passes"] is card(name).verdict.passes
    runtime = Filter.load(result.path)
    meta = runtime.metadata
    low, high = np.array(meta.domain).T
    rng = np.random.default_rng(0)
    t = 0.5 * sum(meta.time_range)
    for batch in (1, 3, 7):
        x = rng.uniform(low, high, size=(batch, meta.state_dim)).astype(np.float32)
        u = np.zeros((batch, meta.control_dim), np.float32)
        applied, info = runtime(x, u, t)
        assert applied.shape == (batch, meta.control_dim) and info.value.shape == (batch,)
