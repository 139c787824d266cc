"""Training: layouts, initialisation, parameterisations, checkpoints, resume after SIGKILL, DeepReach import."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from reach.systems import Air3D, MultiVehicle9D, ValueFunction
from reach_cli import main
from training import (
    Encoding,
    NeuralValueFunction,
    TrainConfig,
    Trainer,
    TrainingDivergedError,
    ValueNetwork,
    load_deepreach,
    load_network,
    parse_layout,
    save_checkpoint,
)

SHARED = Path(__file__).resolve().parents[2] / "shared" / "reference"
TINY = {"width": 16, "points": 256, "log_every": 5, "checkpoint_every_s": 0.0}


@pytest.mark.parametrize(
    ("layout", "message"),
    [("", "non-empty"), ("sss", "end with 'l'"), ("l", "at least one activated"), ("sxsl", "'x' at position 1")],
)
def test_bad_layouts_are_named(layout, message):
    with pytest.raises(ValueError, match=message):
        parse_layout(layout)
    with pytest.raises(ValueError, match=message):
        ValueNetwork(Air3D(), layout)


def test_layout_builds_matching_layers_and_init():
    torch.manual_seed(0)
    net = ValueNetwork(Air3D(), "srtsl", width=256, w0=30.0)
    kinds = [type(a).__name__ for a in net.activations]
    assert kinds == ["Sine", "ReLU", "Tanh", "Sine"] and len(net.layers) == 4
    first = net.layers[0].weight
    assert first.abs().max() <= 1 / first.shape[1]  # SIREN first layer
    relu = net.layers[1].weight
    assert relu.std().item() == pytest.approx(math.sqrt(2 / 256), rel=0.05)  # Kaiming
    sine_after_tanh = net.layers[3].weight
    assert sine_after_tanh.abs().max() <= math.sqrt(6 / 256) / 30
    assert torch.equal(net.layers[1].bias, torch.zeros(256))


@pytest.mark.parametrize("layout", ["ssssl", "ssrsl", "rrrrl", "srsrrl"])
def test_exact_parameterisation_meets_the_boundary_condition(layout):
    system = MultiVehicle9D()
    net = ValueNetwork(system, layout, width=32)
    x = system.sample_states(64)
    torch.testing.assert_close(net(x, torch.zeros(64)), system.failure_margin(x))
    vanilla = ValueNetwork(system, layout, width=32, parameterisation="vanilla")
    assert vanilla(x, torch.zeros(64)).shape == (64,)


@pytest.mark.parametrize("layout", ["ssssl", "ssrsl", "rrrrl", "ttsl"])
def test_inference_forward_applies_activations_in_place_with_the_same_bits(layout):
    """Without autograd each activation is written into its layer's output (faster where the layers
    are memory-bound); the values must be the autograd path's bit for bit, and the parameters and
    inputs untouched."""
    system = MultiVehicle9D()
    torch.manual_seed(3)
    net = ValueNetwork(system, layout, width=32)
    x, t = system.sample_states(257), torch.rand(257)
    before = [p.detach().clone() for p in net.parameters()]
    x_copy = x.clone()
    with torch.enable_grad():
        reference = net(x, t).detach()
    with torch.no_grad():
        fast = net(x, t)
    assert torch.equal(fast, reference)
    assert torch.equal(x, x_copy) and all(torch.equal(a, b) for a, b in zip(before, net.parameters()))


def test_neural_value_function_interface():
    net = ValueNetwork(Air3D(), "ssl", width=16)
    vf = NeuralValueFunction(net)
    assert isinstance(vf, ValueFunction)
    x = Air3D().sample_states(10, dtype=torch.float64)
    assert vf.value(x, 0.5).shape == (10,) and vf.value(x, 0.5).dtype == torch.float64
    g = vf.gradient(x, 0.5)
    eps = 1e-3
    e0 = torch.zeros_like(x)
    e0[:, 0] = eps
    fd = (vf.value(x + e0, 0.5) - vf.value(x - e0, 0.5)) / (2 * eps)
    torch.testing.assert_close(g[:, 0], fd, atol=2e-3, rtol=1e-2)
    with pytest.raises(ValueError, match="NaN"):
        vf.value(torch.full((1, 3), float("nan")), 0.5)


def test_sincos_encoding_is_periodic():
    system = Air3D()
    net = ValueNetwork(system, "ssl", width=16, encoding=Encoding.for_system(system, sincos=True))
    x = torch.tensor([[0.3, -0.2, 3.0]])
    shifted = x + torch.tensor([[0.0, 0.0, -2 * math.pi]])
    torch.testing.assert_close(net(x, torch.tensor([0.4])), net(shifted, torch.tensor([0.4])))


def test_checkpoint_round_trip_and_mismatches(tmp_path):
    net = ValueNetwork(Air3D(), "srsl", width=24)
    save_checkpoint(tmp_path / "c.pt", net, metadata={"steps": 0})
    loaded = load_network(tmp_path / "c.pt", system=Air3D(), layout="srsl")
    x = Air3D().sample_states(8)
    torch.testing.assert_close(loaded(x, torch.ones(8)), net(x, torch.ones(8)))
    meta = json.loads((tmp_path / "c.json").read_text())
    assert meta["layout"] == "srsl" and meta["system"]["name"] == "air3d" and "torch" in meta["versions"]
    with pytest.raises(ValueError, match="layout 'srsl', not 'ssssl'"):
        load_network(tmp_path / "c.pt", layout="ssssl")
    with pytest.raises(ValueError, match="multivehicle9d"):
        load_network(tmp_path / "c.pt", system=MultiVehicle9D())
    with pytest.raises(ValueError, match="collision_radius"):
        load_network(tmp_path / "c.pt", system=Air3D(collision_radius=0.3))
    with torch.no_grad():
        net.layers[1].weight[0, 0] = float("nan")
    save_checkpoint(tmp_path / "nan.pt", net)
    with pytest.raises(ValueError, match="NaN"):
        load_network(tmp_path / "nan.pt")
    (tmp_path / "bad.pt").write_bytes(b"\x00garbage")
    with pytest.raises(ValueError, match="corrupt"):
        load_network(tmp_path / "bad.pt")


def test_training_run_writes_config_checkpoint_and_metrics(tmp_path):
    config = TrainConfig(steps=20, **TINY)
    summary = Trainer(config, tmp_path / "run", progress=False).train()
    assert summary["steps"] == 20 and summary["stopped"] == "reached 20 steps"
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [5, 10, 15, 20]
    assert all(r["steps_per_s"] > 0 and math.isfinite(r["loss"]) for r in rows)
    meta = json.loads((tmp_path / "run" / "checkpoint.json").read_text())
    for key in (
        "system",
        "layout",
        "width",
        "parameterisation",
        "encoding",
        "steps",
        "wall_time_s",
        "seed",
        "versions",
    ):
        assert key in meta
    assert meta["steps"] == 20
    assert TrainConfig.from_dict(json.loads((tmp_path / "run" / "config.json").read_text())) == config


def test_resume_continues_steps_and_metrics(tmp_path):
    Trainer(TrainConfig(steps=10, **TINY), tmp_path / "run", progress=False).train()
    trainer = Trainer.resume(tmp_path / "run", progress=False, steps=20)
    assert trainer.step == 10
    trainer.train()
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [5, 10, 15, 20]


def test_vanilla_training_with_pretraining_runs(tmp_path):
    config = TrainConfig(parameterisation="vanilla", pretrain=0.5, steps=10, **TINY)
    trainer = Trainer(config, tmp_path / "run", progress=False)
    assert trainer.time_range(0.25) == 0.0 and trainer.time_range(1.0) == pytest.approx(1.1)
    trainer.train()
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert "pde" not in rows[0] and "boundary" in rows[0] and "pde" in rows[-1]


def test_diverging_run_stops_naming_the_step_and_keeps_the_checkpoint(tmp_path):
    config = TrainConfig(layout="rrrl", lr=1e12, lr_final=1e12, steps=300, **TINY)
    trainer = Trainer(config, tmp_path / "run", progress=False)
    with pytest.raises(TrainingDivergedError, match=r"at step \d+"):
        trainer.train()
    net = load_network(tmp_path / "run" / "checkpoint.pt")  # the last good one: finite weights
    assert all(torch.isfinite(p).all() for p in net.parameters())


def test_resume_on_another_kind_of_device_reseeds_and_moves_the_labels(tmp_path):
    """A run trained on a GPU resumes on the CPU (and back): the CUDA generator's 16-byte state cannot
    seed a CPU generator, so the stream restarts from the run's seed and step, with a warning; the
    lower-bound labels, loaded on the CPU, move to the run's device."""
    from training.checkpoint import network_from_payload, read_checkpoint, save_checkpoint
    from training.sampling import moved_run_seed

    run = tmp_path / "run"
    Trainer(TrainConfig(system="multivehicle9d", steps=4, seed=5, lower_bound="policy", lower_bound_points=8,
                        lower_bound_every=2, **TINY), run, progress=False).train()  # fmt: skip
    # what a GPU run leaves: config.json names cuda, the checkpoint holds a CUDA generator state
    config = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**config, "device": "cuda"}))
    payload = read_checkpoint(run / "checkpoint.pt")
    network = network_from_payload(run / "checkpoint.pt", payload)
    extra = {k: payload[k] for k in ("optimizer", "step", "wall", "loss_ema", "labels")}
    metadata = {k: payload["metadata"][k] for k in ("steps", "wall_time_s", "seed", "config")}
    save_checkpoint(run / "checkpoint.pt", network, {**extra, "generator": torch.zeros(16, dtype=torch.uint8)},
                    metadata)  # fmt: skip
    with pytest.warns(UserWarning, match="trained on cuda, resumed on cpu at step 4"):
        trainer = Trainer.resume(run, progress=False, steps=6, device="cpu")
    expected = torch.Generator().manual_seed(moved_run_seed(5, 4))
    assert torch.equal(trainer.generator.get_state(), expected.get_state())
    assert trainer.labels is not None and all(v.device.type == "cpu" for v in trainer.labels)
    assert trainer.train()["steps"] == 6
    # back on the device it was last trained on, the saved stream carries over exactly
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = Trainer.resume(run, progress=False, steps=7)
    assert torch.equal(again.generator.get_state(), trainer.generator.get_state())


def test_resume_survives_sigkill(tmp_path):
    run = tmp_path / "run"
    cmd = [
        sys.executable,
        "-m",
        "reach",
        "train",
        "--width",
        "16",
        "--points",
        "256",
        "--steps",
        "400",
        "--log-every",
        "5",
        "--checkpoint-every",
        "0.2",
        "--out",
        str(run),
    ]
    env = {**os.environ, "TQDM_DISABLE": "1"}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + 120
    steps = 0
    while time.time() < deadline and proc.poll() is None:
        meta = run / "checkpoint.json"
        if meta.exists():
            try:
                steps = json.loads(meta.read_text())["steps"]
            except (json.JSONDecodeError, KeyError):
                steps = 0
            if steps >= 60:
                break
        time.sleep(0.05)
    assert proc.poll() is None, "training finished before it could be killed"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed_at = json.loads((run / "checkpoint.json").read_text())["steps"]
    assert 60 <= killed_at < 400
    load_network(run / "checkpoint.pt")  # not corrupt
    done = subprocess.run(
        [sys.executable, "-m", "reach", "train", "--resume", str(run)], env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    assert json.loads((run / "checkpoint.json").read_text())["steps"] == 400
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == list(range(5, 401, 5))  # continuous, no duplicates, no torn lines


def test_cli_train_and_refuses_to_overwrite(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["train", "--layout", "srl", "--width", "8", "--points", "64", "--steps", "6", "--out", str(out)]
    assert main(args) == 0
    assert main(args) == 2 and "already holds a run" in capsys.readouterr().err
    assert main(["train", "--layout", "sxl", "--steps", "2", "--out", str(tmp_path / "x")]) == 2


def test_deepreach_checkpoint_import_matches_the_toolbox_slice():
    path = SHARED / "air3d_deepreach_ssssl_3x512.pth"
    if not path.exists():
        pytest.skip("../shared/reference is absent")
    net = load_deepreach(path, Air3D(), "ssssl")
    with np.load(SHARED / "air3d_levelset_slice.npz") as ref:
        x1, x2 = np.meshgrid(ref["x1"], ref["x2"], indexing="ij")
        x = torch.tensor(np.stack([x1, x2, np.full_like(x1, float(ref["x3"]))], -1), dtype=torch.float32)
        ls = ref["LS"]
    v = NeuralValueFunction(net).value(x, 1.0).numpy()
    inside, truth = v <= 0.001, ls <= 0.001
    iou = (inside & truth).sum() / (inside | truth).sum()
    assert iou >= 0.95, iou
    with pytest.raises(ValueError, match="needs 4"):
        load_deepreach(path, Air3D(), "sssl")
    with pytest.raises(ValueError, match="shape"):
        load_deepreach(path, MultiVehicle9D(), "ssssl")


def test_network_initialisation_follows_the_seed_not_the_global_rng():
    from training.trainer import build_network

    cfg = TrainConfig(layout="srsl", width=8, steps=1, seed=3)
    a = build_network(cfg).state_dict()
    torch.rand(100)  # whatever the process did before must not matter
    b = build_network(cfg).state_dict()
    c = build_network(TrainConfig(layout="srsl", width=8, steps=1, seed=4)).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)


def test_tensorboard_logging_writes_the_metrics_and_resumes(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    cfg = TrainConfig(layout="srsl", width=8, points=64, steps=10, log_every=5, tensorboard=True)
    Trainer(cfg, tmp_path / "run", progress=False).train()
    Trainer.resume(tmp_path / "run", progress=False, steps=20).train()
    events = EventAccumulator(str(tmp_path / "run" / "tensorboard"))
    events.Reload()
    assert {"loss", "lr", "steps_per_s"} <= set(events.Tags()["scalars"])
    assert [e.step for e in events.Scalars("loss")] == [5, 10, 15, 20]
    logged = [json.loads(line)["loss"] for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [e.value for e in events.Scalars("loss")] == pytest.approx(logged, rel=1e-6)


def _loss_and_grads(network: ValueNetwork, x: torch.Tensor, t: torch.Tensor, residual_fn=None):
    from training.loss import LossSettings, training_loss

    network.zero_grad(set_to_none=True)
    loss, _ = training_loss(network, x.clone(), t.clone(), settings=LossSettings(residual_fn=residual_fn))
    loss.backward()
    return float(loss.detach()), [p.grad.clone() for p in network.parameters()]


@pytest.mark.parametrize(
    ("system", "layout", "parameterisation", "sincos"),
    [
        (Air3D(), "srtl", "exact", False),
        (Air3D(), "ssssl", "vanilla", False),
        (Air3D(), "rsl", "exact", True),
        (MultiVehicle9D(), "ssrsl", "exact", True),
        (MultiVehicle9D(), "tsl", "vanilla", False),
    ],
)
def test_fused_input_gradients_match_autograd_double_backward(system, layout, parameterisation, sincos):
    """The hand-carried input gradient gives autograd's residual, loss and parameter gradients."""
    from training.loss import hji_residual, residual_function

    torch.manual_seed(3)
    enc = Encoding.for_system(system, sincos=sincos, value_scale=0.7, sincos_radius=0.4)
    network = ValueNetwork(system, layout, width=24, parameterisation=parameterisation, encoding=enc)
    box = system.domain_tensor(torch.float32, "cpu")
    x = box[:, 0] + torch.rand(300, system.state_dim) * (box[:, 1] - box[:, 0])
    t = torch.rand(300) * system.horizon
    r_auto, v_auto, p_auto = hji_residual(network, x.clone(), t.clone(), "autograd")
    r_fused, v_fused, p_fused = hji_residual(network, x.clone(), t.clone(), "fused")
    torch.testing.assert_close(v_fused, v_auto)
    torch.testing.assert_close(p_fused, p_auto, atol=2e-5, rtol=1e-4)
    torch.testing.assert_close(r_fused, r_auto, atol=2e-5, rtol=1e-4)
    loss_auto, grads_auto = _loss_and_grads(network, x, t)
    loss_fused, grads_fused = _loss_and_grads(network, x, t, residual_function(network, "fused", compile=False))
    assert loss_fused == pytest.approx(loss_auto, rel=1e-5)
    for a, b in zip(grads_auto, grads_fused):
        torch.testing.assert_close(b, a, atol=1e-5 * float(a.abs().max()) + 1e-8, rtol=1e-3)


def test_compiled_training_step_matches_eager():
    """torch.compile of the fused residual (where a compiler works) gives the eager loss and gradients."""
    from training.loss import residual_function

    torch.manual_seed(0)
    network = ValueNetwork(Air3D(), "ssrsl", width=16)
    x = torch.rand(256, 3) * 2 - 1
    t = torch.rand(256)
    eager = _loss_and_grads(network, x, t, residual_function(network, "fused", compile=False))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        compiled = _loss_and_grads(network, x, t, residual_function(network, "fused", compile=None))
    failed = [w for w in caught if "torch.compile failed" in str(w.message)]
    if failed:
        pytest.skip(f"no working torch.compile here: {failed[0].message}")
    assert compiled[0] == pytest.approx(eager[0], rel=1e-5)
    for a, b in zip(eager[1], compiled[1]):
        torch.testing.assert_close(b, a, atol=1e-5 * float(a.abs().max()) + 1e-8, rtol=1e-3)


def test_each_network_gets_its_own_compiled_residual(request):
    """A process that trains many networks compiles each one: none falls back to eager mode because
    dynamo's recompile limit counted the earlier networks' residuals (a sweep worker's ninth run did).
    The limit is lowered to 1 so that the second network would already hit it."""
    import torch._dynamo
    from torch._dynamo.utils import counters

    from training.loss import residual_function

    # config.patch, not monkeypatch.setattr: undoing a setattr deletes the config entry (dynamo's config
    # module keeps no attribute in __dict__), and every later compile in the process then failed
    limit = torch._dynamo.config.patch(recompile_limit=1)
    limit.__enter__()
    request.addfinalizer(lambda: limit.__exit__(None, None, None))
    x = torch.rand(64, 3) * 2 - 1
    t = torch.rand(64)
    compiled_before = counters["frames"]["ok"]
    for seed in range(3):
        torch.manual_seed(seed)
        network = ValueNetwork(Air3D(), "ssrsl", width=8)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            residual_function(network, "fused", compile=None)(x, t)
        failed = [w for w in caught if "torch.compile failed" in str(w.message)]
        if failed:
            pytest.skip(f"no working torch.compile here: {failed[0].message}")
        assert counters["frames"]["ok"] == compiled_before + seed + 1, f"network {seed} was not compiled"


def test_gradient_and_compile_settings():
    with pytest.raises(ValueError, match="gradients must be"):
        TrainConfig(steps=1, gradients="forward").validate()
    with pytest.raises(ValueError, match="compile needs gradients='fused'"):
        TrainConfig(steps=1, gradients="autograd", compile=True).validate()
    assert TrainConfig(steps=10).compile_resolved() is False  # short runs stay eager
    assert TrainConfig(budget_s=600).compile_resolved() is None  # long runs compile, eager if that fails
    assert TrainConfig(steps=5000).compile_resolved() is None
    assert TrainConfig(steps=10, compile=True).compile_resolved() is True
    assert TrainConfig(budget_s=600, gradients="autograd").compile_resolved() is False


def test_margin_slope_is_the_failure_margins_steepest_normalised_slope():
    assert ValueNetwork(Air3D(), "sl", 8).margin_slope() == pytest.approx(1.0, abs=1e-5)  # |grad hypot| = 1
    assert ValueNetwork(MultiVehicle9D(), "sl", 8).margin_slope() == pytest.approx(math.sqrt(2), abs=1e-5)


def test_gradient_bound_penalises_only_slopes_above_it(tmp_path):
    """A cliff (a steep wall in V) is charged by the gradient-bound term; a gentle network is not."""
    from training.loss import LossSettings, LossWeights, residual_function, training_loss

    torch.manual_seed(0)
    network = ValueNetwork(Air3D(), "ssl", width=32)
    x = torch.rand(512, 3) * 2 - 1
    t = torch.rand(512)
    fn = residual_function(network, "fused", compile=False)
    _, v, dv_dx = fn(x, t)
    slope = torch.linalg.vector_norm(dv_dx * network._scale, dim=-1).detach()
    loose, terms = training_loss(
        network, x, t, settings=LossSettings(residual_fn=fn, gradient_bound=float(slope.max()) + 1)
    )
    assert terms["gradient"] == 0.0
    bound = float(slope.median())
    settings = LossSettings(residual_fn=fn, gradient_bound=bound, weights=LossWeights(gradient=2.0))
    loss, terms = training_loss(network, x, t, settings=settings)
    expected = torch.relu(slope - bound).mean()
    assert terms["gradient"] == pytest.approx(float(expected), rel=1e-5)
    assert float(loss.detach()) == pytest.approx(terms["pde"] + 2.0 * terms["gradient"], rel=1e-5)
    trainer = Trainer(TrainConfig(steps=5, gradient_bound=0.5, **TINY), tmp_path / "run", progress=False)
    assert trainer.gradient_bound == pytest.approx(0.5, abs=1e-5)  # x Air3D's margin slope of 1
    trainer.train()
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert all("gradient" in row for row in rows)
    with pytest.raises(ValueError, match="gradient_bound"):
        TrainConfig(steps=1, gradient_bound=-1.0).validate()


def test_upper_bound_term_charges_only_values_above_a_known_bound(tmp_path, pair_grid, air3d_grid):
    """The union-of-pairs penalty: mean(relu(V - bound)) where the bound is known, nothing where it
    is +inf; a 9D run with a pair solution file logs it; misuse is refused before training."""
    from training.loss import Anchors, LossSettings, LossWeights, training_loss

    torch.manual_seed(0)
    network = ValueNetwork(Air3D(), "ssl", width=32)
    x, t = torch.rand(256, 3) * 2 - 1, torch.rand(256)
    v = network(x, t).detach()
    bound = torch.where(torch.arange(256) % 2 == 0, v - 0.1, torch.inf)  # half the points: V is 0.1 too high
    weights = LossWeights(upper_bound=3.0)
    loss, terms = training_loss(
        network, x, t, pde=False, anchors=Anchors(upper_bound=bound), settings=LossSettings(weights=weights)
    )
    assert terms["upper_bound"] == pytest.approx(0.05, rel=1e-4)
    assert float(loss.detach()) == pytest.approx(0.15, rel=1e-4)
    loss.backward()  # the penalty's gradient lowers V at the charged points only
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in network.parameters())
    _, terms = training_loss(network, x, t, pde=False, anchors=Anchors(upper_bound=v + 0.1))
    assert terms["upper_bound"] == 0.0
    path = pair_grid.save(tmp_path / "pair.npz")
    config = TrainConfig(system="multivehicle9d", steps=3, upper_bound=str(path), **TINY)
    Trainer(config, tmp_path / "run", progress=False).train()
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert rows and all(row["upper_bound"] >= 0 for row in rows)
    with pytest.raises(ValueError, match="multi-vehicle systems only, not air3d"):
        Trainer(TrainConfig(steps=1, upper_bound=str(path), **TINY), tmp_path / "a", progress=False)
    with pytest.raises(ValueError, match=r"no such file 'missing\.npz'"):
        Trainer(TrainConfig(system="multivehicle9d", steps=1, upper_bound="missing.npz"), tmp_path / "b")
    with pytest.raises(ValueError, match="no pretrained model 'pairs'"):
        Trainer(TrainConfig(system="multivehicle9d", steps=1, upper_bound="pretrained:pairs"), tmp_path / "e")
    foreign = air3d_grid.save(tmp_path / "air3d.npz")  # a two-player grid, but not this system's pair problem
    with pytest.raises(ValueError, match="no pair solution for cars"):
        Trainer(TrainConfig(system="multivehicle9d", steps=1, upper_bound=str(foreign)), tmp_path / "c")
    with pytest.raises(ValueError, match="upper_bound_weight"):
        TrainConfig(steps=1, upper_bound_weight=-1.0).validate()
    # the shipped compact pair grid bounds the larger fleets too, by name
    shipped = TrainConfig(system="multivehicle12d", steps=1, upper_bound="pretrained:relativepair", **TINY)
    union = Trainer(shipped, tmp_path / "d", progress=False).upper_bound
    assert union is not None and len(union.system.failure_pairs) == 6
    assert not (tmp_path / "a").exists() or not any((tmp_path / "a").iterdir())


def test_runs_from_before_new_defaults_resume_as_they_were_trained(tmp_path):
    """A config.json without the later keys resumes without the gradient bound and with radius-1 (sin, cos)."""
    run = tmp_path / "old"
    old = TrainConfig(steps=3, sincos=True, sincos_radius=1.0, gradient_bound=None, **TINY)
    Trainer(old, run, progress=False).train()
    config = json.loads((run / "config.json").read_text())
    for key in ("gradient_bound", "sincos_radius", "gradients", "compile", "gradient_weight"):
        del config[key]
    (run / "config.json").write_text(json.dumps(config))
    trainer = Trainer.resume(run, progress=False, steps=5)
    assert trainer.gradient_bound is None and trainer.network.encoding.sincos_radius == 1.0
    trainer.train()
    config["sincos_radius"] = 0.5  # a config that no longer builds the stored network is refused
    (run / "config.json").write_text(json.dumps(config))
    with pytest.raises(ValueError, match="does not match the run's config"):
        Trainer.resume(run, progress=False, steps=6)


def _assert_resumes_like_one_run(tmp_path: Path, **lower_bound: object) -> None:
    """A 9D run with a lower-bound term, stopped after 3 steps and resumed to 5, ends with the same
    weights as one run of 5 steps (its labels travel in the checkpoint)."""
    options = dict(
        system="multivehicle9d",
        lower_bound_every=2,
        curriculum=0.0,
        schedule="constant",  # the cosine schedule depends on the step count the run was started with
        compile=False,
        **lower_bound,
        **TINY,
    )
    Trainer(TrainConfig(steps=5, **options), tmp_path / "straight", progress=False).train()
    Trainer(TrainConfig(steps=3, **options), tmp_path / "resumed", progress=False).train()
    Trainer.resume(tmp_path / "resumed", progress=False, steps=5).train()
    straight = load_network(tmp_path / "straight" / "checkpoint.pt").state_dict()
    resumed = load_network(tmp_path / "resumed" / "checkpoint.pt").state_dict()
    assert all(torch.equal(straight[k], resumed[k]) for k in straight)


def test_policy_labels_bound_the_value_from_below(pair_grid):
    """What the network's own policy achieves is a lower bound: J <= l (the start counts), J = l at
    t = 0, and J never exceeds the union of pairwise values, which bounds the 9D value from above
    (J <= V <= union), here for an untrained network's arbitrary policy; and the rollout says more
    than the any-input floor of l alone."""
    from groundtruth.pairwise import PairwiseUnion
    from training.policy_lower_bounds import policy_lower_bound

    system = MultiVehicle9D()
    torch.manual_seed(0)
    network = ValueNetwork(system, "ssl", width=32)
    g = torch.Generator().manual_seed(1)
    x = system.sample_states(400, generator=g)
    t = torch.rand(400, generator=g) * system.horizon
    t[:50] = 0.0
    bound = policy_lower_bound(network, x, t, dt=0.01)
    margin = system.failure_margin(x)
    assert torch.equal(bound[:50], margin[:50])
    assert bool((bound <= margin).all())
    union = PairwiseUnion(system, pair_grid).value_where_known(x, t)
    known = torch.isfinite(union)
    assert int(known.sum()) > 200
    # 45^3 pair grid: its nodes are 2/44 apart in relative position, and |grad V| <= 1 there
    assert float((bound - union)[known].max()) <= 2.0 / 44
    floor = system.margin_floor(x, t)  # per-row time: a lower bound of l under any inputs
    assert float((bound - floor)[50:].mean()) > 0.05


def test_lower_bound_term_trains_resumes_exactly_and_refuses_misuse(tmp_path, capsys):
    """A 9D run logs the term; stopped and resumed it ends with the same weights as one run straight
    through (the labels travel in the checkpoint); a system with a disturbance is refused."""
    from training.loss import Anchors, training_loss

    system = MultiVehicle9D()
    torch.manual_seed(0)
    network = ValueNetwork(system, "ssl", width=16)
    x, t = system.sample_states(64), torch.rand(64)
    v = network(x, t).detach()
    _, terms = training_loss(network, x, t, pde=False, anchors=Anchors(lower_bound=(x, t, v + 0.2)))
    assert terms["lower_bound"] == pytest.approx(0.2, rel=1e-4)
    _, terms = training_loss(network, x, t, pde=False, anchors=Anchors(lower_bound=(x, t, v - 0.2)))
    assert terms["lower_bound"] == 0.0

    _assert_resumes_like_one_run(tmp_path, lower_bound="policy", lower_bound_points=32)
    rows = [json.loads(line) for line in (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]
    assert rows and all(row["lower_bound"] >= 0 for row in rows)

    with pytest.raises(ValueError, match="air3d has a disturbance"):
        Trainer(TrainConfig(steps=1, lower_bound="policy", **TINY), tmp_path / "a", progress=False)
    assert main(["train", "--lower-bound", "policy", "--steps", "1", "--out", str(tmp_path / "cli")]) == 2
    err = capsys.readouterr().err
    assert "air3d has a disturbance" in err and "Traceback" not in err
    with pytest.raises(ValueError, match="lower_bound must be one of"):
        TrainConfig(steps=1, lower_bound="labels").validate()
    for name in ("lower_bound_weight", "lower_bound_dt", "lower_bound_points", "lower_bound_every"):
        with pytest.raises(ValueError, match=name):
            TrainConfig(steps=1, **{name: -1}).validate()


def test_mpc_labels_take_the_best_sampled_sequence(pair_grid):
    """The MPC labels include the network's own policy: where the whole time-to-go fits in the MPC
    horizon no network value enters, so they are at least the policy labels and, being the best of
    real control sequences, still at most the union of pairwise values. Beyond it they bootstrap
    from the network; a 9D run with them trains and logs the term."""
    from groundtruth.pairwise import PairwiseUnion
    from training.policy_lower_bounds import mpc_lower_bound, policy_lower_bound

    system = MultiVehicle9D()
    torch.manual_seed(0)
    network = ValueNetwork(system, "ssl", width=32)
    g = torch.Generator().manual_seed(2)
    x = system.sample_states(300, generator=g)
    t = torch.rand(300, generator=g) * 0.1
    policy = policy_lower_bound(network, x, t, dt=0.01)
    mpc = mpc_lower_bound(network, x, t, 0.01, horizon=0.1, samples=8, noise=0.5, generator=g)
    assert bool((mpc >= policy).all()) and bool((mpc > policy).any())
    union = PairwiseUnion(system, pair_grid).value_where_known(x, t)
    known = torch.isfinite(union)
    assert float((mpc - union)[known].max()) <= 2.0 / 44
    later = mpc_lower_bound(network, x, t + 0.5, 0.01, horizon=0.1, samples=4, noise=0.5, generator=g)
    assert bool(torch.isfinite(later).all()) and bool((later <= system.failure_margin(x)).all())
    with pytest.raises(ValueError, match="samples"):
        mpc_lower_bound(network, x, t, 0.01, horizon=0.1, samples=0, noise=0.5, generator=g)
    with pytest.raises(ValueError, match="dt must be positive"):
        mpc_lower_bound(network, x, t, 0.0, horizon=0.1, samples=2, noise=0.5, generator=g)


def test_mpc_lower_bound_term_trains_and_resumes_exactly(tmp_path):
    _assert_resumes_like_one_run(
        tmp_path, lower_bound="mpc", lower_bound_points=16, lower_bound_samples=3, lower_bound_horizon=0.05
    )
    for name in ("lower_bound_samples", "lower_bound_horizon", "lower_bound_noise"):
        with pytest.raises(ValueError, match=name):
            TrainConfig(steps=1, **{name: -1}).validate()


def test_zero_level_sampling_draws_near_the_networks_boundary_and_resumes_exactly(tmp_path):
    """The zero-level points are the smallest |V| of a larger uniform draw (so far below a uniform
    draw's typical |V|), take the last share of each step's points, keep resumes exact, and nonsense
    fractions are refused."""
    trainer = Trainer(
        TrainConfig(
            steps=1, system="multivehicle9d", zero_level_fraction=0.25, zero_level_candidates=8, compile=False, **TINY
        ),
        tmp_path / "sample",
        progress=False,
    )
    x, t, _ = trainer._sample(1.0)
    n = len(x)
    near = n - int(0.25 * n)
    with torch.no_grad():
        v = trainer.network(x, t).abs()
    # the smallest eighth of 8x as many draws: all below the uniform points' lower quartile
    assert float(v[near:].max()) < float(v[:near].quantile(0.25))
    _assert_resumes_like_one_run(tmp_path, zero_level_fraction=0.25, zero_level_candidates=3)
    for bad in ({"zero_level_fraction": 1.0}, {"zero_level_fraction": -0.1}, {"zero_level_candidates": 1}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            TrainConfig(steps=1, **bad).validate()
    with pytest.raises(ValueError, match="boundary_fraction \\+ zero_level_fraction"):
        TrainConfig(steps=1, parameterisation="vanilla", boundary_fraction=0.5, zero_level_fraction=0.5).validate()
