"""How much memory this machine can still give: checked before any large allocation.

A grid solve or a verification of a billion states that cannot fit is refused up front, with an
estimate and what to change, instead of dying half-way with an out-of-memory error.
"""

from __future__ import annotations

import os


def available_memory() -> int | None:
    """Bytes this machine can still give (MemAvailable on Linux, physical memory elsewhere), or None."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def require_memory(need: int, what: str, advice: str) -> int:
    """Refuse ``what`` (e.g. "a 101x101x101 grid with 12 stored times") when its ``need`` in bytes
    exceeds what the machine can give, saying both and ``advice``; returns ``need``."""
    have = available_memory()
    if have is not None and need > have:
        raise ValueError(
            f"{what} needs about {need / 2**30:.1f} GiB, but {have / 2**30:.1f} GiB is available; {advice}"
        )
    return need
