"""A safety filter that is safe for all time by proof: it keeps a certificate's set invariant.

:mod:`safety.formal.closure` certifies a set ``S``, the union of a certificate's kept boxes (and the
escape set ``E`` where it has one): from every state of ``S`` its box's backup input keeps the next
state in ``S``, under every disturbance, and ``S`` never meets the failure set. :class:`CertifiedFilter` is
the least restrictive filter that keeps ``S``:

* at a state of ``S`` it keeps the nominal input when it is proven, for this state and every
  disturbance of its box, to lead to ``S`` again (the same rule as the certificate's: each next-state
  box inside the kept boxes, or with ``V >= c`` on it and inside the kept and outside boxes);
  otherwise it applies the box's certified backup input;
* with an escape set ``E`` (the certificate's ``escape_margin``), at a state of ``E`` every
  admissible input keeps the set: the nominal input is kept; one that is not admissible is replaced
  by the box's backup input, or, beyond the kept boxes, by the centre of the control box;
* at a state outside ``S`` nothing is proven: it applies the value function's optimal input ``u*`` and
  says so in ``certified`` (a start outside ``S`` has no guarantee);
* a nominal input outside the control box is never kept (it is not an admissible input); a state that
  is not finite is refused with an error.

Each decision bounds a few boxes (measured: docs/results/certificates.md): a filter for a Python control
loop, not for the 1 kHz exported path of :mod:`safety.filters.export`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from safety.formal.certificate import Certificate, check_fields, load_certificate
from safety.formal.checker import CertificateCells, check_provenance, landing_verdicts, verify_certificate
from safety.formal.cover import CellGrid
from safety.formal.verifier import Verifier, network_of
from training.network import NeuralValueFunction, ValueNetwork

__all__ = ["CertifiedFilter", "CertifiedInfo"]


@dataclass
class CertifiedInfo:
    """Per state: ``V(x, T)``, whether the state lies in the certified set (``certified``: the guarantee
    holds from here), whether the filter replaced the nominal input, and the input it applied."""

    value: torch.Tensor
    certified: torch.Tensor
    intervened: torch.Tensor
    applied: torch.Tensor


class CertifiedFilter:
    """The filter of a certificate (a :class:`~safety.formal.certificate.Certificate` or its ``.npz`` path) for
    ``value_function``. ``verify=True`` (the default) re-verifies the certificate first
    (:func:`~safety.formal.checker.verify_certificate`); ``False`` checks only that it was made for this
    value function and system."""

    def __init__(
        self,
        certificate: Certificate | str,
        value_function: NeuralValueFunction | ValueNetwork,
        verify: bool = True,
    ) -> None:
        label = str(certificate) if not isinstance(certificate, Certificate) else "the certificate"
        if not isinstance(certificate, Certificate):
            certificate = load_certificate(certificate)
        check_fields(certificate, label)  # a non-finite stored input is refused here, never applied
        network = network_of(value_function)
        if verify:
            verify_certificate(certificate, network, label)
        else:
            check_provenance(certificate, network, label)
        self.certificate = certificate
        self.system = network.system
        self._verifier = Verifier(network, certificate.settings, torch.device("cpu"), closure=True)
        self._network64 = self._verifier.network
        every = certificate.every_box()
        # its allowed boxes: the kept boxes first, then the outside ones: a state's box below its
        # number of kept boxes is the kept box that holds it, whose backup input applies
        self._cells = CertificateCells.of(
            certificate, CellGrid(self._verifier.domain, certificate.resolution, every.lo, every.hi)
        )

    def __call__(self, x: torch.Tensor, u_nominal: torch.Tensor) -> tuple[torch.Tensor, CertifiedInfo]:
        """The applied inputs for states ``(B, n)`` (or ``(n,)``) and nominal inputs ``(B, m)`` (or ``(m,)``)."""
        single = x.ndim == 1
        x = torch.as_tensor(x).reshape(-1, self.system.state_dim).to(torch.float64)
        u = torch.as_tensor(u_nominal).reshape(-1, self.system.control_dim).to(torch.float64)
        if len(u) != len(x):
            raise ValueError(f"{len(x)} states but {len(u)} nominal inputs")
        if not bool(torch.isfinite(x).all()):
            raise ValueError("a state is not finite (NaN or inf): the certified filter decides nothing there")
        s = self.certificate.settings
        x = self.system.wrap(x)
        with torch.no_grad():
            value = self._network64(x, torch.full((len(x),), s.time_to_go, dtype=torch.float64))
        domain = self._verifier.domain
        inside = ((x >= domain[:, 0]) & (x <= domain[:, 1])).all(-1)
        box = torch.full((len(x),), -1, dtype=torch.long)
        if bool(inside.any()):
            grid = self._cells.grid
            a, _ = grid.cells(x[inside], x[inside], exact=False)
            owner = self._cells.allowed.owner(a.clamp(max=grid.resolution - 1))
            box[inside] = torch.where(owner < len(self.certificate.kept), owner, -1)
        in_box = inside & (box >= 0)
        escape = self._verifier.escape
        # in E (beyond the domain, or l >= m) every admissible input keeps the set
        in_e = torch.zeros_like(in_box) if escape is None else ~inside | (self.system.failure_margin(x) >= escape[0])
        admissible = self._admissible(u)
        keep = admissible & ((in_box & self._keeps_set(x, u)) | in_e)
        applied = u.clone()
        backup = in_box & ~keep
        applied[backup] = self.certificate.inputs[box[backup]]
        applied[in_e & ~keep & ~in_box] = u.new_tensor(self.system.control_bounds.center)
        certified = in_box | in_e
        elsewhere = ~certified
        if bool(elsewhere.any()):
            applied[elsewhere] = self._optimal(x[elsewhere])
        if not bool(torch.isfinite(applied).all()):  # the filter's own input (u* of a NaN gradient): never applied
            raise ValueError(
                "the certified filter computed a non-finite input (NaN or inf) from the value function's gradient "
                "outside the certified set; the nominal input was not the cause"
            )
        info = CertifiedInfo(value, certified, ~keep, applied)
        return (applied[0] if single else applied), info

    def _admissible(self, u: torch.Tensor) -> torch.Tensor:
        box = self.system.control_bounds
        low, high = u.new_tensor(box.low), u.new_tensor(box.high)
        return ((u >= low) & (u <= high)).all(-1)

    def _keeps_set(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Whether ``u`` is proven to lead each state ``x`` back into the certified set: the certificate's
        rule (module docstring) on the point box of each state, under every disturbance piece."""
        verifier = self._verifier
        land = landing_verdicts(
            verifier, self._cells, self.certificate.settings.level, x, x, u,
            lambda n_lo, n_hi: verifier.value(n_lo, n_hi).lo,
        )  # fmt: skip
        held = torch.ones(len(x) * len(verifier.d_lo), dtype=torch.long)
        held.scatter_reduce_(0, land.piece, land.ok().long(), reduce="amin")
        return held.reshape(len(x), -1).bool().all(-1)

    def _optimal(self, x: torch.Tensor) -> torch.Tensor:
        """``u*`` of ``grad V`` where nothing is certified (the best the value function offers)."""
        network = self._network64
        t = torch.full((len(x),), self.certificate.settings.time_to_go, dtype=torch.float64)
        _, grad = network.value_and_gradient(x, t)
        return self.system.optimal_control(x, grad)
