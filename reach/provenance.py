"""What produced a file: package versions recorded in every result the library writes."""

from __future__ import annotations

import platform

import numpy as np
import torch

import reach


def package_versions() -> dict[str, str]:
    """Versions of reach, torch, numpy and Python, for file metadata."""
    return {
        "reach": reach.__version__,
        "torch": str(torch.__version__),  # a plain str: TorchVersion would need an unpickling allowance
        "numpy": np.__version__,
        "python": platform.python_version(),
    }
