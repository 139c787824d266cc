"""One source for every default: CLI options that mirror a library setting carry no literal of their own."""

from __future__ import annotations

import dataclasses

import pytest

from reach_cli import build_parser
from reach_cli import evaluate as evaluate_command
from reach_cli import sweep as sweep_command
from reach_cli import train as train_command
from safety.verification.verify import VerifySettings
from studies.sweeps.spec import SweepSpec
from training import TrainConfig


def _subparser(name):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return sub.choices[name]


@pytest.mark.parametrize(
    ("command", "table", "cls"),
    [
        ("train", train_command.TRAIN_OPTIONS, TrainConfig),
        ("evaluate", evaluate_command.VERIFY_OPTIONS, VerifySettings),
        ("sweep", sweep_command.SPEC_OPTIONS, SweepSpec),
    ],
)
def test_options_default_to_none_and_help_shows_the_dataclass_default(command, table, cls):
    parser = _subparser(command)
    actions = {a.dest: a for a in parser._actions}
    fields = {f.name: f for f in dataclasses.fields(cls)}
    help_text = parser.format_help().replace("\n", " ")
    help_text = " ".join(help_text.split())
    for option, field, _, _ in table:
        assert field in fields, f"{option} sets no {cls.__name__} field"
        assert actions[field].default is None, f"{option} carries its own default {actions[field].default!r}"
        expected = fields[field].default
        assert f"(default: {expected})" in help_text, f"{option}: help lacks the default {expected!r}"


def test_parsed_defaults_reach_the_library_unchanged(tmp_path):
    from reach_cli.train import _config_fields

    args = build_parser().parse_args(["train", "--out", str(tmp_path / "r")])
    assert _config_fields(args) == {}  # nothing given: TrainConfig's own defaults apply
    config = TrainConfig(**_config_fields(args))
    assert config == TrainConfig()


@pytest.mark.parametrize(
    ("argv", "threads"),
    [
        (["--threads", "2", "sweep", "--out", "s"], 2),
        (["sweep", "--threads", "3", "--out", "s"], 3),
        (["sweep", "--out", "s"], None),
    ],
)
def test_threads_given_before_or_after_the_subcommand_are_kept(argv, threads):
    from reach_cli.options import finish_namespace

    assert finish_namespace(build_parser().parse_args(argv)).threads == threads


def test_library_entry_points_keep_a_chosen_thread_count_and_restore_it(monkeypatch):
    """thread_policy replaces only torch's blind default, and gives the caller's count back."""
    import torch

    from reach import threads

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    before = torch.get_num_threads()
    monkeypatch.setattr(threads, "free_cores", lambda: 1)  # a busy machine
    monkeypatch.setattr(threads, "_applied", None)
    monkeypatch.setattr(threads, "_default_counts", lambda: {before})
    try:
        with threads.thread_policy() as n:  # nobody chose: the free cores
            assert n == 1 and torch.get_num_threads() == 1
        assert torch.get_num_threads() == before
        threads.apply_thread_policy(before)  # reach --threads N chose this count
        with threads.thread_policy() as n:
            assert n == before and torch.get_num_threads() == before
        monkeypatch.setattr(threads, "_applied", None)
        monkeypatch.setenv("OMP_NUM_THREADS", str(before))  # the environment chose
        with threads.thread_policy() as n:
            assert n == before
        with threads.thread_policy(1) as n:  # an explicit count always wins
            assert n == 1 and torch.get_num_threads() == 1
        assert torch.get_num_threads() == before
    finally:
        torch.set_num_threads(before)


def test_free_cores_counts_what_runs_now_not_the_lagging_load_average(monkeypatch):
    """The busy count is the median of three reads of the threads other processes have runnable;
    where /proc cannot say, the 1-minute load average; a CPU-bound child process counts as busy."""
    import os
    import subprocess
    import sys
    import time

    from reach import threads

    monkeypatch.setattr(threads, "usable_cores", lambda: 4)
    monkeypatch.setattr(threads, "_READ_PAUSE", 0.0)
    reads = iter([5, 0, 1])  # one burst among the reads: the median ignores it
    monkeypatch.setattr(threads, "runnable_elsewhere", lambda: next(reads))
    assert threads.free_cores() == 3
    monkeypatch.setattr(threads, "runnable_elsewhere", lambda: None)
    monkeypatch.setattr(os, "getloadavg", lambda: (1.2, 1.0, 0.9))
    assert threads.free_cores() == 3
    monkeypatch.setattr(os, "getloadavg", lambda: (9.0, 9.0, 9.0))
    assert threads.free_cores() == 1  # never below one
    monkeypatch.undo()
    assert 1 <= threads.usable_cores() <= (os.cpu_count() or 1)

    if threads.runnable_elsewhere() is None:
        pytest.skip("no /proc/loadavg on this platform")
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        deadline, seen = time.monotonic() + 5.0, 0
        while time.monotonic() < deadline and seen < 1:
            seen = threads.runnable_elsewhere()
            time.sleep(0.05)
        assert seen >= 1  # the spinning child is runnable now
    finally:
        busy.kill()
        busy.wait()


def test_the_cli_starts_without_the_env_stack():
    """`reach` (every subcommand's parser) loads neither Gymnasium nor PettingZoo nor Matplotlib at
    start-up: a grid solve or a training run should not pay for them (about 0.2 s of each start),
    and `safety`'s lazy names still resolve to the objects, not to their modules."""
    import subprocess
    import sys

    code = (
        "import sys; from reach_cli import main; "
        "print(sorted(m for m in ('gymnasium', 'pettingzoo', 'matplotlib') if m in sys.modules)); "
        "import safety, safety.verification.rollout, safety.filters.wrappers; "
        "from safety import rollout, SafetyFilterWrapper; "
        "print(callable(rollout) and isinstance(SafetyFilterWrapper, type) and set(safety.__all__) <= set(dir(safety)))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split("\n")
    assert out[0] == "[]" and out[1] == "True"


def test_the_console_script_freezes_the_collector_after_the_command_not_main(monkeypatch, capsys):
    """`reach` (console_main) skips Python's shutdown garbage pass by freezing the collector once the
    command has returned and its output is flushed; main() called in-process never touches it."""
    import gc

    import reach_cli as cli

    events = []
    real_main = cli.main

    def recording_main(argv=None):
        code = real_main(argv)
        events.append(("main", code))
        return code

    monkeypatch.setattr(gc, "freeze", lambda: events.append(("freeze", None)))
    assert real_main(["envs"]) == 0 and events == []  # in-process: the caller's collector is left alone
    monkeypatch.setattr(cli, "main", recording_main)
    monkeypatch.setattr("sys.argv", ["reach", "envs"])
    with pytest.raises(SystemExit) as exited:
        cli.console_main()
    assert exited.value.code == 0
    assert events == [("main", 0), ("freeze", None)]
    assert "Air3D-v0" in capsys.readouterr().out


def test_a_closed_pipe_ends_the_command_quietly():
    """`reach envs | head -1`: when the reader goes away the command stops with 141 (128 + SIGPIPE),
    as a shell pipeline expects, instead of printing an error about the pipe."""
    import subprocess
    import sys

    proc = subprocess.Popen(
        [sys.executable, "-m", "reach", "envs"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    proc.stdout.close()  # before the command has written anything: its first write meets a closed pipe
    err = proc.stderr.read()
    assert proc.wait(timeout=60) == 141
    assert err == ""


def test_work_at_a_lower_priority_does_not_count_as_busy():
    """A ``nice -n 19`` job yields its core: its runnable threads do not compete with ours, and the
    same job at our own priority does (read from the children's own /proc entries)."""
    import os
    import subprocess
    import sys
    import time

    from reach import threads

    if threads.competing_runnable() is None:
        pytest.skip("no per-thread states in /proc on this platform")
    own = os.getpriority(os.PRIO_PROCESS, 0)
    spin = [sys.executable, "-c", "while True: pass"]
    seen = {}
    for label, argv in (("niced", ["nice", "-n", "19", *spin]), ("same", spin)):
        child = subprocess.Popen(argv)
        try:
            deadline, verdict = time.monotonic() + 5.0, None
            while time.monotonic() < deadline and verdict is None:
                fields = threads._stat_fields(f"/proc/{child.pid}/stat")
                if fields is not None and fields[0] == "R" and (label == "same" or int(fields[16]) > own):
                    verdict = threads.competes(fields, own)
                time.sleep(0.02)
        finally:
            child.kill()
            child.wait()
        seen[label] = verdict
    assert seen == {"niced": own >= 19, "same": True}, seen
    # the rule itself, on stat fields: runnable, nice, SCHED_IDLE
    fields = ["R"] + ["0"] * 40
    assert threads.competes(fields, 0)
    fields[16] = "19"
    assert not threads.competes(fields, 0) and threads.competes(fields, 19)
    fields[16], fields[38] = "0", "5"
    assert not threads.competes(fields, 0)
    fields[38], fields[0] = "0", "S"
    assert not threads.competes(fields, 0)
