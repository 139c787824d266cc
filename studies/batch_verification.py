"""Batch evaluation of many value functions on the same sampled states, resumable.

:func:`evaluate_many` verifies each source (run directory, checkpoint, DeepReach file, grid
solution) with :func:`~safety.verification.verify.verify` on states drawn once from the seed, optionally scores
it against a grid ground truth (value MSE and BRT IoU over the volume and one slice) and, for
multi-vehicle systems, against the union of pairwise BRTs (the containment metric), and after
every source rewrites ``<out>.csv``, ``<out>.json`` and ``<out>.md`` atomically. A second call with
the same settings skips sources already evaluated (same path, size and modification time); a source
that fails to load or evaluate becomes a row with its error, and the others go on.

Within a source, the rollouts are kept block by block in ``<out>.rollouts/`` (a
:class:`~safety.verification.rollout_store.RolloutStore` per source, keyed by its fingerprint and the settings)
until its row is written: a run killed in the middle of a million-state verification resumes
where it stopped when the same command runs again (``rollout_blocks_resumed`` counts the blocks it
loaded; ``rollout_seconds`` is the blocks' own simulation time, whichever run did it).
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import os
import shutil
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm.auto import tqdm

from groundtruth.solution import GridSolution
from reach.exit_codes import EXIT_PARTIAL
from reach.json_files import read_json, restore_nan
from reach.locking import exclusive_lock
from reach.result_columns import current_names
from reach.systems import ControlAffineSystem, make_system
from reach.validation import check_float, check_output_path, settings_from
from safety.value_loading import (
    FORMATS,
    composition_kind,
    is_composition,
    load_value_function,
    min_sources,
    resolve_checkpoint,
)
from safety.verification.metrics import containment_statistics
from safety.verification.rollout_store import RolloutStore
from safety.verification.verify import VerifySettings, check_for_system, sample_states, values_at, verify
from studies.tables import columns_table, merge_rows, write_results
from training.accuracy import ReferenceEvaluator

FORMAT = "reach.evaluation.v1"
GLOB_CHARS = set("*?[")

#: (column, header, format) of the printed table
TABLE_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("label", "model", "{}"),
    ("layout", "layout", "{}"),
    ("violation_rate", "violation %", "pct"),
    ("false_safe_rate", "false safe %", "pct"),
    ("false_unsafe_rate", "false unsafe %", "pct"),
    ("collision_rate", "collision %", "pct"),
    ("false_reachable_rate", "false reachable %", "pct"),
    ("false_unreachable_rate", "false unreachable %", "pct"),
    ("failure_rate", "failure %", "pct"),
    ("delta", "delta", "{:.3g}"),  # 3 significant digits: small deltas are the point
    ("eps", "eps", "{:.2e}"),
    ("scenario_volume", "scenario vol.", "{:.3f}"),
    ("robust_eps", "robust eps", "{:.2e}"),
    ("robust_scenario_volume", "robust vol.", "{:.3f}"),
    ("iou_volume", "IoU vol.", "{:.3f}"),
    ("mse_volume", "MSE vol.", "{:.2e}"),
    ("iou_slice", "IoU slice", "{:.3f}"),
    ("mse_slice", "MSE slice", "{:.2e}"),
    ("containment_miss_rate", "misses union %", "pct"),
    ("wall_time", "time (s)", "{:.1f}"),
)


def expand_sources(patterns: Sequence[str]) -> list[str]:
    """Paths from arguments; unexpanded glob patterns are expanded here. Empty results raise."""
    if not patterns:
        raise ValueError("no value functions given (expected run directories, checkpoints or .npz files)")
    out: list[str] = []
    for pattern in patterns:
        if not os.path.exists(pattern) and GLOB_CHARS & set(pattern):
            matches = sorted(glob.glob(pattern))
            if not matches:
                raise ValueError(f"pattern {pattern!r} matched no file or directory")
            out.extend(matches)
        else:
            out.append(pattern)
    return list(dict.fromkeys(p if is_composition(p) else os.path.normpath(p) for p in out))


def fingerprint(path: str) -> dict[str, Any]:
    """What identifies one version of a source: resolved file, size, modification time (of every
    member of a ``min:A,B`` source; a ``cap:A,B`` source, whose policy differs, says so)."""
    if is_composition(path):
        members = {"members": [fingerprint(p) for p in min_sources(path)]}
        return {"kind": "cap", **members} if composition_kind(path) == "cap" else members
    try:
        p = resolve_checkpoint(path)
    except ValueError:
        return {"file": os.path.abspath(path), "size": None, "mtime_ns": None}
    st = p.stat()
    return {"file": str(p.resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def markdown_table(rows: Sequence[dict[str, Any]]) -> str:
    """The paper-style table; columns nobody has (e.g. ground truth for 9D) are left out.

    Each kind of problem has its own columns (:data:`~safety.verification.metrics.KIND_COLUMNS`): an avoid row
    counts false *safe* claims and collisions, a reach row false *reachable* claims and failures, and
    its delta bounds ``{V < -delta}``. Rows of several kinds get a ``problem`` column and a first
    line that says the table mixes kinds."""
    kinds = sorted({str(r["problem"]) for r in rows if r.get("problem")})
    if len(kinds) < 2:
        return columns_table(rows, TABLE_COLUMNS, drop_empty=True)
    columns = (TABLE_COLUMNS[0], ("problem", "problem", "{}"), *TABLE_COLUMNS[1:])
    note = (
        f"This table mixes kinds of problem ({', '.join(kinds)}): each row fills its own kind's columns, and "
        "delta bounds {V > delta} for avoid rows, {V < -delta} for reach rows.\n\n"
    )
    return note + columns_table(rows, columns, drop_empty=True)


def _write_outputs(out: Path, header: dict[str, Any], rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Merge ``rows`` into the table on disk and rewrite it; returns the merged rows.

    Rows of other sources already in the table are kept (a rerun with fewer sources, or another
    process evaluating other sources into the same ``out``, loses nothing); a row for the same
    source replaces the old one. The read-merge-write runs under a lock on ``out.lock``, so
    concurrent writers serialise instead of overwriting each other's rows."""
    with exclusive_lock(out.with_suffix(".lock"), f"results {out}", wait=True):
        merged = merge_rows(_previous(out, header, keep_errors=True).values(), rows, key="source")
        write_results(out, header, merged, markdown_table(merged))
    return merged


def _claim(out: Path, header: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The rows already in ``out`` (see :func:`_previous`); a new table is written at once, empty,
    with this run's header, so that a second run with other settings into the same ``out`` is
    refused before it simulates anything, not after."""
    with exclusive_lock(out.with_suffix(".lock"), f"results {out}", wait=True):
        done = _previous(out, header)
        if not out.with_suffix(".json").exists():
            write_results(out, header, [], markdown_table([]))
    return done


def _previous(out: Path, header: dict[str, Any], keep_errors: bool = False) -> dict[str, dict[str, Any]]:
    """Rows already in ``out`` by source (error rows only with ``keep_errors``); a table written with
    other settings raises, since its rows would not be comparable."""
    path = out.with_suffix(".json")
    if not path.exists():
        return {}
    data = current_names(read_json(path, "existing results", hint="; move the file away to start over"))
    if isinstance(data.get("settings"), dict):  # files from before these settings existed used these values
        data["settings"] = _resolved(
            {
                "matmul_precision": "float32",
                "policy": "gradient",
                "share_samples": False,
                "control_period": None,
                **data["settings"],
            }
        )
    if any(
        data.get(key) != header[key]
        for key in ("format", "settings", "system", "ground_truth", "ground_truth_time", "pairwise")
    ):
        raise ValueError(
            f"{path} holds results for other settings ({data.get('settings')}, system {data.get('system')}); "
            "use another --out or delete it"
        )
    return {r["source"]: r for r in restore_nan(data.get("results", [])) if keep_errors or not r.get("error")}


def _resolved(settings: dict[str, Any]) -> dict[str, Any]:
    """Settings with the sample counts that default to another count written out (by
    :class:`VerifySettings`' own rule), so that ``--robust-samples`` left out and given as the value
    it defaults to compare equal; tables written before the counts were resolved are read the same
    way. Settings of another version, which :class:`VerifySettings` does not take, stay as written."""
    try:
        parsed = VerifySettings(**settings)
    except (TypeError, ValueError):
        return settings
    return {**settings, "scenario_samples": parsed.fresh_samples, "robust_samples": parsed.robust_sample_count}


def pairwise_union_values(pairwise: str | os.PathLike, system: ControlAffineSystem, states: Any, horizon: float) -> Any:
    """Values of the union of pairwise BRTs (a two-car ``relativepair`` solution) at ``states``."""
    union = load_value_function(pairwise, format="grid", system=system)
    if union.kind != "pairwise":
        raise ValueError(f"{pairwise}: not a two-car (relativepair) solution for {system.name}")
    return values_at(union.value_function, states, horizon)


@dataclass(frozen=True)
class References:
    """What each source is scored against besides its own rollouts.

    Attributes:
        ground_truth: a grid ``.npz`` of the same system: volume IoU and MSE against it.
        gt_time: the time-to-go of that comparison (None: the grid's last stored time).
        gt_slice: score on the slice of the last state dimension at this value instead of the volume.
        pairwise: a two-car grid ``.npz`` (``reach groundtruth relativepair``): containment in the
            union of pairwise BRTs, for a multi-vehicle system.
    """

    ground_truth: str | os.PathLike | None = None
    gt_time: float | None = None
    gt_slice: float | None = None
    pairwise: str | os.PathLike | None = None

    def __post_init__(self) -> None:
        for name in ("gt_time", "gt_slice"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, check_float(name, value))


@dataclass(frozen=True)
class SourceLoading:
    """How :func:`evaluate_many` loads its sources (:func:`~safety.value_loading.load_value_function`).

    Attributes:
        system: the sources' system (an instance, a registered name or an import path), which the
            states are drawn for; ``None``: the first source that loads decides.
        format: ``"auto"`` (from each source's suffix), ``"reach"``, ``"deepreach"`` or ``"grid"``.
        layout: the expected network layout (required for DeepReach files).
    """

    system: ControlAffineSystem | str | None = None
    format: str = "auto"
    layout: str | None = None

    def __post_init__(self) -> None:
        if self.system is not None and not isinstance(self.system, (str, ControlAffineSystem)):
            raise ValueError(f"system must be a system, its name or an import path, got {self.system!r}")
        if self.format not in FORMATS:
            raise ValueError(f"format must be one of {FORMATS}, got {self.format!r}")
        if self.layout is not None and not isinstance(self.layout, str):
            raise ValueError(f"layout must be a layout string such as 'ssssl', got {self.layout!r}")


def evaluate_many(
    sources: Sequence[str],
    out: str | os.PathLike,
    settings: VerifySettings,
    loading: SourceLoading | None = None,
    references: References | None = None,
    device: str = "cpu",
    progress: bool = True,
    backend: Any = None,
    **reference_fields: Any,
) -> list[dict[str, Any]]:
    """Evaluate every source on the same states; returns the rows (also written to ``out``).

    ``references`` (:class:`References`; its fields may also be given as keywords, e.g.
    ``ground_truth="gt.npz"``) adds the comparison columns; ``loading`` (:class:`SourceLoading`:
    system, format and layout) says how to load the sources. ``backend``
    (:class:`~safety.verification.sharding.RayBlocks`) runs the rollout blocks on its workers, with the same rows."""
    refs = settings_from(References, references, reference_fields, "reference")
    ground_truth, gt_time, gt_slice, pairwise = refs.ground_truth, refs.gt_time, refs.gt_slice, refs.pairwise
    if loading is None:
        loading = SourceLoading()
    elif not isinstance(loading, SourceLoading):
        raise ValueError(f"loading must be a SourceLoading, got {type(loading).__name__}")
    system, format, layout = loading.system, loading.format, loading.layout
    paths = expand_sources(sources)
    out = check_output_path(out, "results")
    out.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(system, str):
        system = make_system(system)
    if system is None:  # the first source that loads decides, so every row shares the states
        errors = []
        for p in paths:
            try:
                system = load_value_function(p, format=format, layout=layout).value_function.system
                break
            except ValueError as err:
                errors.append(str(err))
        if system is None:
            if len(errors) == 1:
                raise ValueError(errors[0])
            raise ValueError(
                f"none of {len(paths)} sources could be loaded (first: {errors[0]}); "
                "give --system to see each error in the table"
            )
    check_for_system(system, settings)  # before the table is claimed: a refused run leaves nothing behind
    reference = None
    if ground_truth is not None:
        gt = GridSolution.load(ground_truth, outside="clamp")
        system.require_same_physics(gt.system, f"ground truth {ground_truth}")
        t_ref = float(gt.times[-1]) if gt_time is None else gt_time
        reference = ReferenceEvaluator(gt, t_ref, slice_value=gt_slice)
    header = {
        "format": FORMAT,
        "system": system.config(),
        "settings": _resolved(settings.to_dict()),
        "ground_truth": str(Path(ground_truth).resolve()) if ground_truth else None,
        "ground_truth_time": gt_time,
        "pairwise": str(Path(pairwise).resolve()) if pairwise else None,
    }
    done = _claim(out, header)
    states = sample_states(system, settings.samples, settings.seed)
    horizon = system.horizon if settings.horizon is None else settings.horizon
    union_values = None if pairwise is None else pairwise_union_values(pairwise, system, states, horizon)
    rows: list[dict[str, Any]] = []
    for path in tqdm(paths, desc="value functions", unit="vf", **({} if progress else {"disable": True})):
        fp = fingerprint(path)
        old = done.get(path)
        if old is not None and old.get("fingerprint") == fp:
            rows.append(old)
            continue
        row: dict[str, Any] = {"source": path, "fingerprint": fp, "label": Path(path).name or path}
        try:
            loaded = load_value_function(path, format=format, system=system, layout=layout, device=device)
            if isinstance(loaded.value_function, GridSolution):
                loaded.value_function.outside = "clamp"  # rollouts may leave the grid; documented
            row.update(label=loaded.label, layout=loaded.layout, kind=loaded.kind)
            # what the rollouts depend on: sharing samples reuses outcomes and changes no rollout, so a
            # shared run loads the blocks of an unshared one (and the reverse) and older stores stay valid;
            # a policy deciding at every step keys as stores did before the control period existed
            settings_now = header["settings"].items()
            rolled = {
                k: v for k, v in settings_now if k != "share_samples" and not (k == "control_period" and v is None)
            }
            key = {"source": path, "fingerprint": fp, "device": device, **header, "settings": rolled}
            with RolloutStore(_store_directory(out, path), key) as store:
                vf = loaded.value_function
                row.update(verify(vf, states, settings, device=device, progress=progress, store=store, backend=backend))
                row["rollout_blocks_resumed"] = store.loaded_blocks
            if reference is not None:
                row.update(reference(loaded.value_function))
            if union_values is not None:
                learned = values_at(loaded.value_function, states, horizon, device=device)
                row.update(containment_statistics(union_values, learned))
        except (ValueError, RuntimeError, OSError, KeyError, TypeError, EOFError) as err:
            # a corrupt or foreign source is one error row; the others go on
            row["error"] = f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"[:300]
        rows.append(row)
        _write_outputs(out, header, rows)
        shutil.rmtree(_store_directory(out, path), ignore_errors=True)  # the row holds it now
    _write_outputs(out, header, rows)
    with contextlib.suppress(OSError):
        _store_directory(out, None).rmdir()  # only if no other source's store is left in it
    return rows


def report_failures(rows: Sequence[dict[str, Any]], command: str, what: str = "sources") -> int:
    """Name each failed row on stderr, as ``command``, and say how many of ``rows`` failed; returns
    :data:`~reach.exit_codes.EXIT_PARTIAL` if any did (their rows say why), else 0."""
    failed = [row for row in rows if row.get("error")]
    for row in failed:
        print(f"{command}: {row.get('source')}: {row['error']}", file=sys.stderr)
    if not failed:
        return 0
    print(f"{command}: {len(failed)} of {len(rows)} {what} failed (their rows say why)", file=sys.stderr)
    return EXIT_PARTIAL


def _store_directory(out: Path, source: str | None) -> Path:
    """Where the rollouts of ``source`` are kept until its row is written (None: the parent of all)."""
    parent = out.parent / f"{out.name}.rollouts"
    return parent if source is None else parent / hashlib.sha256(source.encode()).hexdigest()[:16]


#: the suffixes a results path may carry (the empty one: the path without a suffix)
RESULT_SUFFIXES = ("", ".json", ".csv", ".md")


def load_results(path: str | os.PathLike) -> list[dict[str, Any]]:
    """Rows of the results :func:`evaluate_many` wrote at ``path`` (its ``.json``, ``.csv`` or
    ``.md``, or the path without a suffix: the rows are read from the ``.json`` beside it)."""
    given = Path(path)
    if given.suffix not in RESULT_SUFFIXES:
        raise ValueError(
            f"{given} is not a results file of reach evaluate (expected one of {', '.join(RESULT_SUFFIXES[1:])})"
        )
    p = given.with_suffix(".json")
    return current_names(restore_nan(read_json(p, "a reach evaluation file", expect_format=FORMAT)["results"]))


__all__ = [
    "References",
    "SourceLoading",
    "evaluate_many",
    "expand_sources",
    "load_results",
    "markdown_table",
    "report_failures",
]
