"""The compiled library: built with the system's C compiler, cached, and checked before it is used.

:func:`compile_filter` builds an exported filter's C file into a shared library under a cache
folder, keyed by the hash of the source, the flags and the compiler. A cached library is loaded
into the process as machine code, and a damaged one does not fail politely: a truncated library
kills the process with SIGBUS when it is loaded. So each build records the library's size and
SHA-256 beside it (``filter-<key>.json``, written atomically after the library), and a cached
library is used only where both match its record. A library that is truncated, overwritten,
replaced by another, or has no record (an interrupted build) is built again; where it cannot be
(the cache cannot be written), the build is refused with one ``ValueError`` naming the file.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import stat
import subprocess
import tempfile
from pathlib import Path

from reach_runtime.native.emission import c_source

__all__ = ["CFLAGS", "build", "cache_folder", "compile_filter", "compiler", "file_record", "is_recorded"]

#: flags of the build: optimised and vectorised for this machine (-O3 -march=native; no FP traps and
#: no errno, so that loops with comparisons and square roots vectorise), with IEEE values kept: no
#: -ffast-math, so NaN and inf propagate and the graph's own non-finite checks still see them
CFLAGS = ("-O3", "-march=native", "-fno-math-errno", "-fno-trapping-math", "-fPIC", "-shared")

#: the largest record file read (a record is a few lines of JSON; anything larger is not one)
_RECORD_LIMIT = 4096


def compiler() -> str:
    """The C compiler: ``$CC`` where set, else the first of ``cc``, ``gcc``, ``clang`` on PATH."""
    chosen = os.environ.get("CC")
    if chosen:
        if not shutil.which(chosen):
            raise ValueError(f"$CC is {chosen!r}, which is not a program on PATH")
        return chosen
    for name in ("cc", "gcc", "clang"):
        if shutil.which(name):
            return name
    raise ValueError("the native engine needs a C compiler (cc, gcc or clang on PATH, or $CC)")


def cache_folder(cache: str | os.PathLike | None) -> Path:
    """``cache``, or by default ``$XDG_CACHE_HOME/reach_runtime`` (``~/.cache/reach_runtime``)."""
    if cache is not None:
        return Path(cache)
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "reach_runtime"


def compile_filter(path: str | os.PathLike, cache: str | os.PathLike | None = None) -> Path:
    """Build the filter at ``path`` into a shared library (cached under ``cache``, default
    ``$XDG_CACHE_HOME/reach_runtime`` or ``~/.cache/reach_runtime``, by the hash of its source and
    flags) and return the library's path. ``ValueError`` if the graph or the compiler refuses, or
    where a damaged cached library cannot be rebuilt."""
    return build(c_source(path), path, cache)


def file_record(path: Path) -> dict[str, int | str]:
    """``{"bytes": size, "sha256": digest}`` of the regular file at ``path``, read without
    loading it (the record a cached library must match)."""
    digest = hashlib.sha256()
    size = 0
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
            size += len(block)
    return {"bytes": size, "sha256": digest.hexdigest()}


def _record_path(library: Path) -> Path:
    return library.with_suffix(".json")


def _regular(path: Path) -> bool:
    """Whether ``path`` is a regular file itself (not a link, FIFO, device or folder)."""
    try:
        return stat.S_ISREG(os.lstat(path).st_mode)
    except OSError:
        return False


def is_recorded(library: Path) -> bool:
    """Whether ``library`` is a regular file whose size and SHA-256 are those its build recorded.
    False for a missing, unreadable or malformed record: such a library is not trusted."""
    record_path = _record_path(library)
    if not _regular(library) or not _regular(record_path):
        return False
    try:
        with open(record_path, "rb") as handle:
            data = handle.read(_RECORD_LIMIT + 1)
        record = json.loads(data) if len(data) <= _RECORD_LIMIT else None
        if not isinstance(record, dict) or record.get("library") != library.name:
            return False
        size = record.get("bytes")
        if not isinstance(size, int) or isinstance(size, bool) or os.lstat(library).st_size != size:
            return False  # the cheap check first: a truncated library is not read through
        return file_record(library) == {"bytes": size, "sha256": record.get("sha256")}
    except (OSError, ValueError):  # unreadable, or not JSON
        return False


def build(source: str, path: str | os.PathLike, cache: str | os.PathLike | None) -> Path:
    """The shared library of ``source`` (the C file of the filter at ``path``): the cached one
    where it matches its record (:func:`is_recorded`), else built now, recorded, and put in place
    by renames (a process that has the old file loaded keeps it; none sees a partial file)."""
    chosen = compiler()
    key = hashlib.sha256((source + " ".join(CFLAGS) + chosen).encode()).hexdigest()[:24]
    folder = cache_folder(cache)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ValueError(f"{folder}: cannot create the native engine's cache folder ({error})") from None
    library = folder / f"filter-{key}.so"
    if is_recorded(library):
        return library
    damaged = os.path.lexists(library)
    try:
        with tempfile.TemporaryDirectory(dir=folder) as work:
            c_file = Path(work) / "filter.c"
            c_file.write_text(source)
            built = Path(work) / "filter.so"
            result = subprocess.run(
                [chosen, *CFLAGS, "-o", str(built), str(c_file), "-lm"], capture_output=True, text=True
            )
            if result.returncode != 0:
                raise ValueError(
                    f"{os.fspath(path)}: the C compiler refused the generated source: {result.stderr.strip()[-400:]}"
                )
            record = Path(work) / "record.json"
            record.write_text(json.dumps({"library": library.name, **file_record(built)}) + "\n")
            # the library first, then its record: an interruption between leaves a library without
            # a matching record, which the next build replaces. A concurrent build of the same key
            # writes the same bytes.
            os.replace(built, library)
            os.replace(record, _record_path(library))
    except OSError as error:
        if damaged:
            raise ValueError(
                f"{library}: the cached library does not match its record ({_record_path(library).name}: size and "
                f"SHA-256) and cannot be rebuilt ({error})"
            ) from None
        raise ValueError(f"{library}: cannot write the compiled library into its cache ({error})") from None
    return library
