"""A formal certificate and its file: the certified set's boxes with their backup inputs, and what was proven.

A :class:`Certificate` is what the closure (:func:`safety.formal.closure.certified_set`) keeps: the
set ``S``, the union of the ``kept`` boxes, each with the backup input under which all its next
states land in ``S`` (or in the escape set ``E``, where there is one); the boxes proven ``outside``
``S_c``; the proof's settings; the system; and the value function's fingerprint. The checker
(:func:`safety.formal.checker.check_certificate`) re-verifies one from its file alone, and the
certified filter (:mod:`safety.formal.certified_filter`) keeps a system inside its set.

The **certificate file** (``.npz``, read with ``allow_pickle=False``: loading runs no code) holds the
kept boxes with their backup inputs, the boxes proven outside ``S_c``, the escape and excluded boxes
(where there is an escape set), and one JSON header: the format, the settings, the system, the
fingerprint and the cell grid's resolution. Files written before there was an escape set lack its
boxes, and load with none.
"""

from __future__ import annotations

import json
import zipfile
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from reach.atomic import atomic_path
from reach.validation import check_input_file
from safety.formal.settings import CertifySettings

__all__ = [
    "FORMAT",
    "Boxes",
    "Certificate",
    "Provenance",
    "check_fields",
    "load_certificate",
    "save_certificate",
    "volume_share",
]

#: the ``format`` a certificate file's header names
FORMAT = "reach-certificate/1"


@dataclass(frozen=True, eq=False)
class Boxes:
    """Boxes by their corners: ``lo`` and ``hi``, ``(B, n)`` float64 tensors (``lo <= hi``)."""

    lo: torch.Tensor
    hi: torch.Tensor

    def __len__(self) -> int:
        return len(self.lo)

    @staticmethod
    def cat(*parts: Boxes) -> Boxes:
        """The boxes of ``parts``, in order."""
        return Boxes(torch.cat([p.lo for p in parts]), torch.cat([p.hi for p in parts]))


@dataclass(frozen=True)
class Provenance:
    """What a certificate was made for: the system's configuration (``system.config()``) and the value
    function's ``fingerprint`` (:func:`training.checkpoint.network_digest`). A certificate holds for
    that system and that network only."""

    system: dict
    fingerprint: str


@dataclass(frozen=True, eq=False)
class Certificate:
    """A certified set: the ``kept`` boxes (``S`` is their union) with their backup ``inputs`` (one row
    each), the ``outside`` boxes (``V < c`` on each), the grid ``resolution`` per dimension, the
    proof's ``settings`` and its ``provenance``. With an escape set (``settings.escape_margin``): the
    ``escape`` boxes (all in ``E``) and the ``excluded`` rest of the cover, so that the file's boxes
    tile the state box and the checker can see that every box meeting the band below ``E`` is kept;
    without one, both are empty."""

    settings: CertifySettings
    provenance: Provenance
    kept: Boxes
    inputs: torch.Tensor
    outside: Boxes
    resolution: int
    escape: Boxes
    excluded: Boxes

    def allowed_boxes(self) -> Boxes:
        """The boxes a kept box's next states may land in: kept first, then outside, then escape."""
        return Boxes.cat(self.kept, self.outside, self.escape)

    def every_box(self) -> Boxes:
        """Every box the file holds: kept, outside, escape and excluded."""
        return Boxes.cat(self.kept, self.outside, self.escape, self.excluded)

    def member_boxes(self) -> Boxes:
        """The boxes of the set: kept, then escape (all in ``E``)."""
        return Boxes.cat(self.kept, self.escape)

    def kept_volume_share(self, domain: torch.Tensor) -> float:
        """The kept boxes' share of the state box ``domain`` (the certified set ``S`` in it, less the
        escape set); boxes kept beyond it (``closure_scale``) count only where they meet it."""
        return volume_share(self.kept.lo, self.kept.hi, domain)

    def kept_beyond(self, domain: torch.Tensor) -> int:
        """How many kept boxes lie beyond the state box ``domain`` (a closure over a wider box)."""
        domain = domain.to(self.kept.lo)
        return int(((self.kept.lo < domain[:, 0]) | (self.kept.hi > domain[:, 1])).any(-1).sum())


def volume_share(lo: torch.Tensor, hi: torch.Tensor, domain: torch.Tensor) -> float:
    """The boxes' share of the box ``domain`` (``(n, 2)``): each box counts where it meets it (boxes
    that do not overlap; a closure's wide cover has boxes beyond the state box)."""
    domain = domain.to(lo)
    inside = (torch.minimum(hi, domain[:, 1]) - torch.maximum(lo, domain[:, 0])).clamp(min=0)
    return float((inside / (domain[:, 1] - domain[:, 0])).prod(-1).sum())


def save_certificate(path: str | Path, certificate: Certificate) -> Path:
    """Write ``certificate`` atomically (``.npz``; arrays and one JSON header, nothing executable)."""
    path = Path(path)
    if path.suffix != ".npz":
        raise ValueError(f"a certificate file ends in .npz, got {str(path)!r}")
    header = {
        "format": FORMAT,
        "settings": asdict(certificate.settings),
        "system": certificate.provenance.system,
        "fingerprint": certificate.provenance.fingerprint,
        "resolution": certificate.resolution,
    }
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(  # dyadic box corners compress well, and a certificate may hold millions of boxes
            f,
            header=np.array(json.dumps(header)),
            kept_lo=certificate.kept.lo.numpy(),
            kept_hi=certificate.kept.hi.numpy(),
            inputs=certificate.inputs.numpy(),
            outside_lo=certificate.outside.lo.numpy(),
            outside_hi=certificate.outside.hi.numpy(),
            escape_lo=certificate.escape.lo.numpy(),
            escape_hi=certificate.escape.hi.numpy(),
            excluded_lo=certificate.excluded.lo.numpy(),
            excluded_hi=certificate.excluded.hi.numpy(),
        )
    return path


def check_fields(certificate: Certificate, where: str = "the certificate") -> Certificate:
    """``certificate`` if every field is well formed, else ``ValueError`` naming ``where`` and the field.

    A certificate is data from outside: each box array is ``(B, n)`` with one ``n`` for all, every
    corner finite with ``lo <= hi``, one finite backup input row per kept box, a resolution that is a
    positive integer, and a provenance of a system configuration and a fingerprint. The comparisons
    are written so that NaN fails them (``~(lo <= hi)``, not ``lo > hi``). The settings were checked
    when they were made (:class:`~safety.formal.settings.CertifySettings`); what depends on the
    system (inputs inside its control box, boxes inside its domain) the checker adds."""
    if not isinstance(certificate.settings, CertifySettings):
        raise ValueError(f"{where}: its settings are not a verifier's ({type(certificate.settings).__name__})")
    provenance = certificate.provenance
    if not isinstance(provenance.system, dict) or not isinstance(provenance.fingerprint, str):
        raise ValueError(f"{where}: its provenance is not a system configuration and a fingerprint")
    resolution = certificate.resolution
    if isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 1:
        raise ValueError(f"{where}: its resolution {resolution!r} is not a positive integer")
    n = certificate.kept.lo.shape[-1] if certificate.kept.lo.ndim == 2 else None
    parts = (("kept", certificate.kept), ("outside", certificate.outside),
             ("escape", certificate.escape), ("excluded", certificate.excluded))  # fmt: skip
    for name, boxes in parts:
        lo, hi = boxes.lo, boxes.hi
        if lo.ndim != 2 or lo.shape != hi.shape or lo.shape[-1] != n:
            shapes = f"{tuple(lo.shape)} and {tuple(hi.shape)}"
            raise ValueError(f"{where}: its {name} boxes have corners of shapes {shapes}")
        if not bool((torch.isfinite(lo) & torch.isfinite(hi)).all()):
            raise ValueError(f"{where}: a {name} box has a corner that is not finite (NaN or inf)")
        if not bool((lo <= hi).all()):
            raise ValueError(f"{where}: a {name} box has a lower corner above its upper one")
    inputs = certificate.inputs
    if inputs.ndim != 2 or len(inputs) != len(certificate.kept):
        raise ValueError(
            f"{where}: its backup inputs have shape {tuple(inputs.shape)}, not one row per kept box "
            f"({len(certificate.kept)})"
        )
    if not bool(torch.isfinite(inputs).all()):
        raise ValueError(f"{where}: a backup input is not finite (NaN or inf)")
    return certificate


def load_certificate(path: str | Path) -> Certificate:
    """Read a certificate file (no pickles: nothing in it runs); refuses junk naming the problem: a
    truncated or damaged file, a foreign one, and any field :func:`check_fields` refuses."""
    check_input_file(path, "certificate")
    try:
        with np.load(path, allow_pickle=False) as data:
            header = json.loads(str(data["header"]))
            arrays = {k: torch.from_numpy(np.array(data[k], dtype=np.float64)) for k in
                      ("kept_lo", "kept_hi", "inputs", "outside_lo", "outside_hi")}  # fmt: skip
            # files without an escape set may lack these (written before there was one)
            arrays |= {k: torch.from_numpy(np.array(data[k], dtype=np.float64)) for k in
                       ("escape_lo", "escape_hi", "excluded_lo", "excluded_hi") if k in data.files}  # fmt: skip
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile, zlib.error) as err:
        # a truncated or bit-flipped file fails inside the zip reader or the inflater: name the file
        why = f"{type(err).__name__}: {err}"
        raise ValueError(f"{path}: not a reach certificate file, or a damaged one ({why})") from None
    found = header.get("format") if isinstance(header, dict) else None
    if found != FORMAT:
        raise ValueError(f"{path}: not a reach certificate file (format {found!r})")
    try:
        settings = CertifySettings(**header["settings"])
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: its settings are not a verifier's ({err})") from None
    try:
        resolution = header["resolution"]
        provenance = Provenance(header["system"], header["fingerprint"])
    except KeyError as err:
        raise ValueError(f"{path}: its header is not a certificate's (no {err})") from None
    kept_lo = arrays["kept_lo"]
    none = kept_lo.new_zeros((0, kept_lo.shape[-1] if kept_lo.ndim == 2 else 0))

    def boxes(name: str) -> Boxes:
        return Boxes(arrays.get(f"{name}_lo", none), arrays.get(f"{name}_hi", none))

    certificate = Certificate(
        settings,
        provenance,
        Boxes(kept_lo, arrays["kept_hi"]),
        arrays["inputs"],
        boxes("outside"),
        resolution,
        boxes("escape"),
        boxes("excluded"),
    )
    return check_fields(certificate, str(path))
