"""Every shipped value network exports (``reach export pretrained:NAME``'s defaults) and passes the
export's own self-check: the written file loads as a robot loads it (digest, interface, a free
batch dimension, the graph following its metadata) and decides as the torch filter on 512 sampled
states. The batch is free: the runtime decides batches of 1, 3 and 7.

Grid models (``relativepair``) are not exported: the export takes networks and minimums of them,
not a grid's interpolation (``tests/test_export.py`` checks the refusal). Slow (an export each):
CI runs it in a step of its own."""

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


def test_the_shipped_grids_are_the_only_models_left_out():
    assert sorted(set(names()) - set(NETWORKS)) == ["relativepair"]


@pytest.mark.parametrize("name", NETWORKS)
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
