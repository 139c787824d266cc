"""Redraw the gallery's BRT slices (``docs/gallery/NAME.png``, :func:`studies.gallery.write_slices`).

Run: ``python benchmarks/gallery_slices.py`` (``--names dubins3d,air3d`` for some; ``--grid 51`` sets
the grid of the systems of at most three dimensions, solved here for the filled BRT). Each slice
is the system's own (``plot_slices``) at its horizon; systems with neither a shipped model nor a
grid (more than three dimensions, no model yet) are skipped and named.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from studies.gallery import GALLERY, SLICE_FOLDER, write_slices

DOCS = Path(__file__).resolve().parents[1] / "docs"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--names", default=None, help="comma-separated registered names (default: the whole gallery)")
    p.add_argument("--grid", type=int, default=51)
    args = p.parse_args(argv)
    names = args.names.split(",") if args.names else [n for n, _ in GALLERY]
    start = time.perf_counter()
    written = write_slices(DOCS / SLICE_FOLDER, names, grid=args.grid)
    for path in written:
        print(f"wrote {path.relative_to(DOCS.parent)}")
    skipped = sorted(set(names) - {p.stem for p in written})
    elapsed = time.perf_counter() - start
    print(f"{len(written)} slices in {elapsed:.1f} s; skipped (no model, > 3D): {', '.join(skipped)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
