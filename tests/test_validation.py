"""The shared checks of user-given values: one coercion of real numbers, one of integers, one of
known fields, one JSON reader; each refuses what cannot be trusted, naming it."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from reach.json_files import read_json
from reach.systems import Air3D
from reach.validation import (
    check_float,
    check_int,
    check_known_fields,
    is_positive_finite,
    positive_finite,
    real_number,
)
from reach_envs.spaces import check_action, check_state
from training import TrainConfig

REALS = [1, 2.5, np.float32(0.25), np.float64(0.5), np.int64(3), np.uint8(7), torch.tensor(0.75), torch.tensor(4)]
NOT_REALS = [
    True,
    False,
    np.bool_(True),
    "0.5",
    b"1",
    None,
    1j,
    [1.0],
    np.array([1.0, 2.0]),
    torch.ones(2),
    torch.tensor(True),
    torch.empty((), device="meta"),
]


@pytest.mark.parametrize("value", REALS, ids=repr)
def test_real_number_takes_python_numpy_and_0d_tensor_reals(value):
    out = real_number("x", value)
    assert type(out) is float
    assert out == pytest.approx(float(value))


@pytest.mark.parametrize("value", NOT_REALS, ids=repr)
def test_real_number_refuses_bools_strings_complex_and_arrays_naming_the_value(value):
    with pytest.raises(ValueError, match="x must be a real number, got"):
        real_number("x", value)


@given(st.floats(allow_nan=True, allow_infinity=True))
def test_positive_finite_agrees_with_its_definition(v):
    expected = math.isfinite(v) and v > 0
    assert is_positive_finite(v) is expected
    assert is_positive_finite(np.float64(v)) is expected
    assert is_positive_finite(torch.tensor(v, dtype=torch.float64)) is expected
    if expected:
        assert positive_finite("gain", v) == v
    else:
        with pytest.raises(ValueError, match="gain must be positive and finite"):
            positive_finite("gain", v)


def test_check_float_takes_numpy_scalars_and_refuses_strings():
    assert check_float("threshold", np.float32(0.5), 0) == 0.5
    with pytest.raises(ValueError, match=r"threshold must be a number, got '0\.5'"):
        check_float("threshold", "0.5", 0)


@pytest.mark.parametrize("value", [3, np.int64(3), np.uint16(3), torch.tensor(3), 3.0])
def test_check_int_takes_integers_of_every_kind(value):
    assert check_int("steps", value, 1) == 3


@pytest.mark.parametrize("value", [True, np.bool_(True), 2.5, "3", torch.tensor(3.0), torch.tensor(True), float("nan")])
def test_check_int_refuses_non_integers(value):
    with pytest.raises(ValueError, match="steps must be an integer"):
        check_int("steps", value, 1)


def test_check_known_fields_names_the_unknown_key_and_the_fields():
    with pytest.raises(ValueError, match=r"training config: unknown field\(s\) \['widht'\]; fields are \[.*'width'"):
        TrainConfig.from_dict({"widht": 64})
    with pytest.raises(ValueError, match="must be a mapping"):
        check_known_fields(TrainConfig, [("width", 64)], "training config")


def test_read_json_refuses_what_it_cannot_trust(tmp_path):
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"format": "x", "a": 1}))
    assert read_json(good, "a file", expect_format="x") == {"format": "x", "a": 1}
    with pytest.raises(ValueError, match=r"not a file \(format 'y' expected, got 'x'\)"):
        read_json(good, "a file", expect_format="y")
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match="a JSON object expected, got list"):
        read_json(tmp_path / "list.json", "a file")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ValueError, match=r"bad.json: a file is corrupt or unreadable .*; start over"):
        read_json(tmp_path / "bad.json", "a file", hint="; start over")
    with pytest.raises(ValueError, match="must be a regular file, not a directory"):
        read_json(tmp_path, "a file")
    with pytest.raises(ValueError, match="unreadable"):
        read_json(tmp_path / "missing.json", "a file")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_read_json_refuses_a_fifo_without_blocking(tmp_path):
    fifo = tmp_path / "x.json"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match="must be a regular file, not a FIFO"):
        read_json(fifo, "a file")


@pytest.mark.parametrize("action", [np.array([True]), ["0.5"], np.array(["1"]), [object()]], ids=repr)
def test_env_actions_must_be_real_numbers(action):
    with pytest.raises(ValueError, match="action must"):
        check_action(action, (1,))


def test_env_states_must_be_real_numbers():
    with pytest.raises(ValueError, match="must hold real numbers"):
        check_state(["0", "0", "0"], Air3D())
    assert check_state([0, 0, 1], Air3D()).dtype == np.float64


def test_table_cells_escape_pipes_so_tables_render():

    from studies import tables

    text = tables.render_markdown(["mean |u - u_nom|", "b"], [["1 | 2", "x"]])
    header, rule, row = text.splitlines()
    assert header == r"| mean \|u - u_nom\| | b |" and row == r"| 1 \| 2 | x |"
    assert header.replace("\\|", "").count("|") == 3  # three unescaped separators: two cells


def test_results_written_with_the_old_words_load_under_the_new_names(tmp_path):
    """A results file and a model card written before "certify" came to mean a proof only still load,
    their statistical columns read into the scenario names."""
    import json

    from reach.result_columns import current_names
    from studies.batch_verification import FORMAT, load_results

    old = {"source": "a", "certified_volume": 0.5, "certify_samples": 10, "robust_certified_volume": None}
    (tmp_path / "r.json").write_text(json.dumps({"format": FORMAT, "results": [old]}))
    (row,) = load_results(tmp_path / "r.json")
    assert row["scenario_volume"] == 0.5 and row["scenario_samples"] == 10 and "certified_volume" not in row
    assert "robust_scenario_volume" in row
    both = current_names({"certified_volume": 1.0, "scenario_volume": 2.0, "nested": [{"certify_error": "x"}]})
    assert both == {"scenario_volume": 2.0, "nested": [{"scenario_error": "x"}]}
