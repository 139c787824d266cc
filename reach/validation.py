"""Checks of user-given values, shared by the library and the command line.

Every check raises :class:`ValueError` naming the bad value, so that the CLI's error boundary turns
it into one line, and every check is cheap, so that it runs before any expensive work (a grid solve,
a training run, a rollout). The ``*_arg`` helpers are ``argparse`` types built from the same checks.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import numbers
import os
import stat
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

#: largest seed NumPy's and torch's generators take
MAX_SEED = 2**32 - 1


def check_int(name: str, value: Any, low: int | None = None, high: int | None = None) -> int:
    """``value`` as an int within ``[low, high]``: a Python or NumPy integer, a 0-d integer tensor, or
    a float with no fractional part; bools and non-integers are refused."""
    if isinstance(value, torch.Tensor) and value.ndim == 0 and not value.is_meta and not value.dtype.is_floating_point:
        value = value.item() if value.dtype != torch.bool else True  # a bool tensor is refused below
    integral = isinstance(value, numbers.Integral) or (isinstance(value, float) and value.is_integer())
    if isinstance(value, bool) or not integral:  # np.bool_ is not a numbers.Integral
        raise ValueError(f"{name} must be an integer, got {value!r}")
    value = int(value)
    if (low is not None and value < low) or (high is not None and value > high):
        bounds = f">= {low}" if high is None else (f"<= {high}" if low is None else f"in [{low}, {high}]")
        raise ValueError(f"{name} must be {bounds}, got {value}")
    return value


def real_number(name: str, value: Any) -> float:
    """``value`` as a float, whatever real it arrives as: a Python ``int``/``float``, a NumPy real
    scalar (``np.float32(0.05)``, ``np.int64(2)``) or a 0-d real tensor.

    Bools (Python, NumPy or tensor), strings, complex numbers and arrays of more than one element are
    refused with ``ValueError`` naming the value: ``"0.5"`` or ``True`` given as a number is a caller's
    mistake, not a number. Finiteness is not checked here (see :func:`check_float`).
    """
    if isinstance(value, torch.Tensor):
        if value.ndim != 0 or value.dtype == torch.bool or value.is_complex() or value.is_meta:
            where = " on the meta device" if value.is_meta else ""
            kind = f"a tensor of shape {tuple(value.shape)} ({value.dtype}{where})"
            raise ValueError(f"{name} must be a real number, got {kind}")
        return float(value.item())
    if isinstance(value, bool) or not isinstance(value, numbers.Real):  # np.bool_ is not a numbers.Real
        raise ValueError(f"{name} must be a real number, got {value!r}")
    return float(value)


def positive_finite(name: str, value: Any) -> float:
    """``value`` as a float that is finite and above zero (a real, as :func:`real_number` takes)."""
    out = real_number(name, value)
    if not (math.isfinite(out) and out > 0):
        raise ValueError(f"{name} must be positive and finite, got {value!r}")
    return out


def finite_point(name: str, value: Any, dim: int) -> tuple[float, ...]:
    """``value`` as a tuple of ``dim`` finite floats (a point: a goal, an obstacle's centre), from any
    sequence of reals (tuple, list, 1-d array or tensor). A string, a wrong length or a non-finite or
    non-real coordinate is refused with ``ValueError`` naming ``name`` and the value: a 3-tuple for a
    2-D point would otherwise lose its third value, and a NaN would make every comparison with it false."""
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or not hasattr(value, "__getitem__"):
        raise ValueError(f"{name} must be a sequence of {dim} real numbers, got {value!r}")
    if len(value) != dim:
        raise ValueError(f"{name} must have {dim} coordinates, got {len(value)}: {value!r}")
    out = tuple(real_number(f"{name}[{i}]", value[i]) for i in range(dim))
    if not all(math.isfinite(c) for c in out):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return out


def check_float(
    name: str,
    value: Any,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
) -> float:
    """``value`` as a finite float within the given bounds (open where ``*_open``); NaN and inf are refused."""
    try:
        out = real_number(name, value)
    except ValueError:
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(out):
        raise ValueError(f"{name} must be finite, got {value!r}")
    too_low = low is not None and (out <= low if low_open else out < low)
    too_high = high is not None and (out >= high if high_open else out > high)
    if too_low or too_high:
        lo = "" if low is None else ("(" if low_open else "[") + f"{low:g}"
        hi = "" if high is None else f"{high:g}" + (")" if high_open else "]")
        if low is not None and high is not None:
            rule = f"in {lo}, {hi}"
        elif low is not None:
            rule = f"{'>' if low_open else '>='} {low:g}"
        else:
            rule = f"{'<' if high_open else '<='} {high:g}"
        raise ValueError(f"{name} must be {rule}, got {value!r}")
    return out


def is_positive_finite(value: Any) -> bool:
    """Whether ``value`` is a real number (see :func:`real_number`) that is finite and above zero."""
    try:
        positive_finite("value", value)
    except ValueError:
        return False
    return True


def check_known_fields(cls: type, data: Any, what: str) -> None:
    """Refuse a mapping with keys that are not fields of the dataclass ``cls``, naming them and the
    fields there are (a misspelt key would otherwise be dropped or fail deep inside ``cls(**data)``)."""
    if not isinstance(data, dict):
        raise ValueError(f"{what} must be a mapping of field names to values, got {type(data).__name__}")
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(str(key) for key in set(data) - set(names))
    if unknown:
        raise ValueError(f"{what}: unknown field(s) {unknown}; fields are {names}")


def settings_from(cls: type, settings: Any, keywords: dict[str, Any], what: str) -> Any:
    """The frozen dataclass ``cls`` from ``settings`` (an instance, or None for the defaults) with
    ``keywords`` (field names) replacing its fields: the one way a function that takes a settings
    object also takes its fields as keywords. Unknown keywords raise ``ValueError`` naming them."""
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(keywords) - set(names))
    if unknown:
        raise ValueError(f"unknown {what} setting(s) {unknown}; settings are {sorted(names)}")
    if settings is None:
        return cls(**keywords)
    if not isinstance(settings, cls):
        raise ValueError(f"{what} settings must be a {cls.__name__}, got {type(settings).__name__}")
    return dataclasses.replace(settings, **keywords) if keywords else settings


def check_seed(name: str, value: Any) -> int:
    """A seed for NumPy and torch generators: an integer in ``[0, 2**32 - 1]``."""
    return check_int(name, value, 0, MAX_SEED)


def check_device(device: str | torch.device) -> torch.device:
    """A torch device that exists on this machine (``cpu``, ``cuda``, ``cuda:1``, ``mps``)."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise ValueError(f"unknown device {str(device)!r} (expected cpu, cuda, cuda:N or mps)") from None
    if dev.type == "cpu":
        return dev
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {str(device)!r}: this torch build sees no CUDA GPU (torch {torch.__version__})")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"device {str(device)!r}: only {torch.cuda.device_count()} CUDA device(s) here")
        return dev
    if dev.type == "mps":
        if not torch.backends.mps.is_available():
            raise ValueError(f"device {str(device)!r}: MPS is not available on this machine")
        return dev
    raise ValueError(f"device {str(device)!r} is not supported (expected cpu, cuda, cuda:N or mps)")


def check_output_path(path: str | os.PathLike, what: str = "output") -> Path:
    """A file path that can be written: not a directory, and its folder exists or can be created
    and is writable. Checked before the work whose result goes there."""
    p = Path(path)
    if str(path) == "" or p.name in ("", ".", ".."):
        raise ValueError(f"{what} path {str(path)!r} is not a file name")
    if p.is_dir():
        raise ValueError(f"{what} path {str(p)!r} is a directory, not a file")
    check_not_special(p, f"{what} path")
    _check_creatable(p.parent, f"{what} path {str(p)!r}")
    return p


def check_not_special(path: str | os.PathLike, what: str = "file") -> None:
    """Refuse a path that exists as something other than a regular file or a directory: a FIFO
    (reading it blocks), a device (replacing ``/dev/null`` with a file would break the system) or a
    socket. Nothing is opened; a missing path passes (it may be created)."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise ValueError(f"{what} {str(path)!r} is a {file_kind(mode)}, not a regular file")


def check_input_file(path: str | os.PathLike, what: str = "input") -> Path:
    """An existing regular file to read: a missing path, a directory, a FIFO, a device or a socket
    is refused naming it, before anything opens it (opening a FIFO would block forever)."""
    p = Path(path)
    try:
        mode = p.stat().st_mode
    except OSError as err:
        reason = "a broken symbolic link or a link loop" if p.is_symlink() else (err.strerror or str(err)).lower()
        raise ValueError(f"{what} {str(p)!r}: {reason}") from None
    if not stat.S_ISREG(mode):
        raise ValueError(f"{what} {str(p)!r} is a {file_kind(mode)}, not a regular file")
    return p


def file_kind(mode: int) -> str:
    """What a file of this ``st_mode`` is, in words (``"FIFO"``, ``"character device"``, ...)."""
    for test, name in (
        (stat.S_ISREG, "regular file"),
        (stat.S_ISDIR, "directory"),
        (stat.S_ISFIFO, "FIFO"),
        (stat.S_ISCHR, "character device"),
        (stat.S_ISBLK, "block device"),
        (stat.S_ISSOCK, "socket"),
    ):
        if test(mode):
            return name
    return "special file"


def check_output_dir(path: str | os.PathLike, what: str = "output") -> Path:
    """A directory that exists and is writable, or can be created."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ValueError(f"{what} directory {str(p)!r} is a file")
    _check_creatable(p, f"{what} directory {str(p)!r}")
    return p


def _check_creatable(folder: Path, label: str) -> None:
    """``folder`` exists and is writable, or its nearest existing ancestor is a writable folder."""
    existing = folder
    while not existing.exists() and existing.parent != existing:
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(f"{label}: {str(existing)!r} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ValueError(f"{label}: folder {str(existing)!r} is not writable")
    try:  # permissions do not tell everything (root, read-only mounts, /proc): try it
        probe = tempfile.mkdtemp(prefix=".reach-write-check-", dir=existing)
    except OSError as err:
        raise ValueError(f"{label}: folder {str(existing)!r} is not writable ({err.strerror or err})") from None
    os.rmdir(probe)


# ---------------------------------------------------------------------- argparse types
def _arg_type(check: Callable[[str, Any], Any], parse: Callable[[str], Any], label: str) -> Callable[[str], Any]:
    def convert(text: str) -> Any:
        try:
            value = parse(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {label}, got {text!r}") from None
        try:
            return check("value", value)
        except ValueError as err:  # argparse names the option: "argument --seed: must be ..."
            raise argparse.ArgumentTypeError(str(err).removeprefix("value ")) from None

    convert.__name__ = label.replace(" ", "_")
    return convert


positive_int_arg = _arg_type(lambda n, v: check_int(n, v, 1), int, "a positive integer")
nonnegative_int_arg = _arg_type(lambda n, v: check_int(n, v, 0), int, "an integer >= 0")
seed_arg = _arg_type(check_seed, int, "a seed (an integer in [0, 2**32 - 1])")
positive_float_arg = _arg_type(lambda n, v: check_float(n, v, 0, low_open=True), float, "a positive number")
nonnegative_float_arg = _arg_type(lambda n, v: check_float(n, v, 0), float, "a number >= 0")
finite_float_arg = _arg_type(check_float, float, "a finite number")
unit_interval_arg = _arg_type(lambda n, v: check_float(n, v, 0, 1), float, "a number in [0, 1]")
probability_arg = _arg_type(
    lambda n, v: check_float(n, v, 0, 1, low_open=True, high_open=True), float, "a number in (0, 1)"
)


def device_arg(text: str) -> str:
    """argparse type: a device that exists here (see :func:`check_device`)."""
    try:
        check_device(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def csv_items(name: str, text: str) -> list[str]:
    """The comma-separated items of ``text``, stripped; an empty list or an empty item (``"a,,b"``,
    a trailing comma) is refused naming ``name``, since dropping it would hide a typo."""
    items = [v.strip() for v in str(text).split(",")]
    if not any(items):
        raise ValueError(f"{name} must list at least one item, got {text!r}")
    if not all(items):
        raise ValueError(f"{name} has an empty item in {text!r}; separate items by single commas")
    return items


def csv_floats(name: str, text: str, check: Callable[[str, Any], float] = check_float) -> list[float]:
    """Comma-separated finite numbers (``"0,0.03,0.1"``), each checked by ``check``.

    An arithmetic progression may be written with an ellipsis, as in the docs' commands:
    ``"0,0.05,...,1.1"`` is 0, 0.05, 0.1, ..., 1.1 (23 numbers). The ellipsis must stand between the
    first two terms, which fix the step, and the last; a last term that the step does not reach
    exactly is refused rather than rounded to the nearest term.
    """
    items = csv_items(name, text)
    if "..." in items:
        return [check(name, value) for value in _progression(name, text, items)]
    out = []
    for item in items:
        out.append(check(name, _number(name, item, text)))
    return out


def _number(name: str, item: str, text: str) -> float:
    try:
        return float(item)
    except ValueError:
        raise ValueError(f"{name} must be comma-separated numbers, got {item!r} in {text!r}") from None


#: the most terms an ellipsis may stand for (a typo such as "0,1e-9,...,1" fails instead of allocating)
MAX_PROGRESSION_TERMS = 100_000


def _progression(name: str, text: str, items: list[str]) -> list[float]:
    """The terms of ``"a,b,...,c"``: from a in steps of b - a (> 0) up to c, which a whole number of
    steps must reach (to a relative 1e-9 of the step)."""
    if len(items) != 4 or items[2] != "...":
        raise ValueError(f"{name}: an ellipsis must read FIRST,SECOND,...,LAST, got {text!r}")
    first, second, last = (_number(name, items[i], text) for i in (0, 1, 3))
    for value in (first, second, last):
        check_float(name, value)
    step = second - first
    if step <= 0:
        raise ValueError(f"{name}: the step {second!r} - {first!r} of {text!r} must be positive")
    count = (last - first) / step
    whole = round(count)
    if whole < 1 or abs(count - whole) > 1e-9 * max(1.0, whole):
        raise ValueError(f"{name}: {last!r} is not a whole number of steps of {step:g} from {first!r} in {text!r}")
    if whole + 1 > MAX_PROGRESSION_TERMS:
        raise ValueError(f"{name}: {text!r} stands for {whole + 1} numbers (at most {MAX_PROGRESSION_TERMS})")
    # each term from the first and its index (no accumulated error); the last is the one written
    # rounded well below the step, so 0.05 * 3 reads 0.15, not 0.15000000000000002
    decimals = 12 + max(0, math.ceil(-math.log10(step)))
    return [round(first + k * step, decimals) for k in range(whole)] + [last]
