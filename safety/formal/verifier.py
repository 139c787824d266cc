"""Formal certification of a learned safe set by branch and bound over boxes of states.

For a neural value function ``V``, a level ``c`` and a time-to-go ``T``, the set is
``S_c = {x : V(x, T) >= c}``. The verifier covers the state box with boxes and tries to prove, on each:

* **(a) inclusion**: every state of ``S_c`` in the box is outside the failure set, ``l(x) > 0``;
* **(b) one-step robust invariance**: one backup input ``u`` (a vertex or the centre of the control
  box, the same for the whole box) such that for *every* state of the box and *every* disturbance of
  the disturbance box, the next state ``step(x, u, d)`` (the env's integrator and ``dt``) lies in
  ``S_c`` again, and inside the value function's domain (a heading, which the network's sin/cos
  encoding makes periodic, may wrap).

A box on which ``V < c`` everywhere holds no state of ``S_c`` and needs nothing more. Every other
box is **proven** (both hold, with its backup input), **refuted** (a concrete counterexample at its
centre, checked by evaluation: a state of ``S_c`` with ``l <= 0``, or one from which every candidate
input has a disturbance leading out of ``S_c``), or **split** in two along its relatively widest
dimension, until it reaches ``min_relative_width`` (then **unknown**).

If every box is outside or proven, then from any state of ``S_c`` a filter that applies the box's
backup input keeps the state in ``S_c`` for all time, under the model's dynamics, the integrator's
discrete time and any disturbance in its box, and ``S_c`` never meets the failure set: the
certificate. Bounds: :mod:`safety.formal.linear_bounds` for the network, :mod:`safety.formal.intervals` for the
margins and the step. This first version certifies avoid problems with the ``exact``, ``diff`` and
``vanilla`` output parameterisations.

**The escape set.** A next state may leave the domain, where the network is not trusted. With
``escape_margin = m`` and a system that declares two lemmas (:func:`escape_rule`), the states with
``l(x) >= m`` form an escape set ``E`` that is certified without the network: every state beyond the
domain is in ``E``, and one step from ``E``, under any input and disturbance, lowers ``l`` by at most
``delta``, so it lands in ``E`` or in the band ``m - delta <= l < m`` inside the domain. Then (b) also
accepts next states in ``E``; a box all in ``E`` needs nothing (status **escape**); and a box meeting
the band must hold only states of ``S_c`` (``V >= c`` on all of it) and be proven (split until it
is, down to ``band_min_relative_width``). The set
proven is ``S_c ∪ E``: from ``E`` any admissible input keeps the state in it, or in the band, where
(b) takes over. No bound of the network is ever computed beyond the domain.
"""

from __future__ import annotations

import copy
import itertools
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict

import torch

from reach.integrators import make_stepper
from reach.systems import ControlAffineSystem
from reach.systems.arrays import TORCH
from safety.formal.intervals import INTERVAL, Interval, IntervalBackend, box_columns
from safety.formal.linear_bounds import linear_bounds
from safety.formal.progress import SAVE_EVERY_S, VerifierProgress, load_progress, save_progress
from safety.formal.settings import (
    ESCAPE,
    OUTSIDE,
    PROVEN,
    REFUTED,
    UNKNOWN,
    CertificationResult,
    CertifySettings,
    closure_domain,
    escape_rule,
)
from safety.formal.sizing import check_size
from training.checkpoint import network_digest
from training.network import NeuralValueFunction, ValueNetwork

__all__ = [
    "Verifier",
    "candidate_inputs",
    "certify",
    "margin_bounds",
    "network_of",
    "value_bounds",
]


class _Unwrapped(IntervalBackend):
    """Interval columns whose headings are left unwrapped by the step: the verifier wraps the next-state
    box itself, exactly, by cutting it at the seam (:func:`_wrap_boxes`)."""

    @staticmethod
    def wrap_angle(a: Interval) -> Interval:
        return a


def _wrap_boxes(lo: torch.Tensor, hi: torch.Tensor, periodic: list[int]) -> tuple[torch.Tensor, ...]:
    """Boxes with their periodic dimensions wrapped into ``[-pi, pi]``, a box that crosses the seam cut
    in two there: ``(lo, hi, owner)`` with ``owner`` the row each piece came from. A box that spans
    a whole turn or more keeps ``[-pi, pi]`` whole."""
    owner = torch.arange(len(lo), device=lo.device)
    for i in periodic:
        width = hi[:, i] - lo[:, i]
        turns = torch.floor((lo[:, i] + math.pi) / (2 * math.pi))
        a = lo[:, i] - turns * 2 * math.pi
        b = a + width
        whole = width >= 2 * math.pi
        b = torch.where(turns == 0, hi[:, i], b)  # unshifted: the bound itself, not lo + (hi - lo) rounded
        a, b = torch.where(whole, -math.pi, a), torch.where(whole, math.pi, b)
        crosses = b > math.pi
        lo, hi = lo.clone(), hi.clone()
        lo[:, i], hi[:, i] = a, torch.where(crosses, math.pi, b)
        extra = crosses.nonzero().squeeze(-1)
        if len(extra):
            lo2, hi2 = lo[extra].clone(), hi[extra].clone()
            lo2[:, i], hi2[:, i] = -math.pi, b[extra] - 2 * math.pi
            lo, hi = torch.cat([lo, lo2]), torch.cat([hi, hi2])
            owner = torch.cat([owner, owner[extra]])
    return lo, hi, owner


def network_of(value_function: NeuralValueFunction | ValueNetwork) -> ValueNetwork:
    """The network of ``value_function`` (or the network itself), refused unless a proof covers it:
    an avoid problem, with the ``exact``, ``diff`` or ``vanilla`` output parameterisation."""
    network = getattr(value_function, "network", value_function)
    if not isinstance(network, ValueNetwork):
        raise ValueError(
            "certify takes a neural value function (a run, a .pt checkpoint or pretrained:NAME), not a "
            f"{type(value_function).__name__}: a proof bounds a network's layers"
        )
    system = network.system
    if system.kind != "avoid":
        raise ValueError(f"certify proves avoid problems for now; {system.name} is a {system.kind} problem")
    if network.parameterisation not in ("exact", "diff", "vanilla"):
        raise ValueError(
            f"certify takes the exact, diff and vanilla parameterisations, not {network.parameterisation!r}"
        )
    return network


def margin_bounds(system: ControlAffineSystem, x_lo: torch.Tensor, x_hi: torch.Tensor) -> Interval:
    """Sound bounds of the failure margin ``l(x)`` over each box (the system's own code, on intervals)."""
    return Interval.of(system.failure_margin_columns(box_columns(x_lo, x_hi), INTERVAL))


def value_bounds(network: ValueNetwork, x_lo: torch.Tensor, x_hi: torch.Tensor, t: float) -> Interval:
    """Sound bounds of ``V(x, t)`` over each box (``(B, n)`` corners) at one time-to-go ``t``: the
    raw output's linear bounds through the output map, the boundary value's by interval arithmetic."""
    o_lo, o_hi = linear_bounds(network, x_lo, x_hi, t, t)
    enc = network.encoding
    if network.parameterisation == "vanilla":
        offset: Interval | float = enc.value_offset
        scale = enc.value_scale
    else:
        offset = margin_bounds(network.system, x_lo, x_hi)
        scale = enc.value_scale * (t / enc.horizon if network.parameterisation == "exact" else 1.0)
    return offset + scale * Interval(o_lo, o_hi)


def candidate_inputs(network: ValueNetwork) -> torch.Tensor:
    """The backup inputs tried on every box: the control box's vertices, then its centre."""
    box = network.system.control_bounds
    vertices = [list(v) for v in itertools.product(*zip(box.low, box.high))]
    return torch.tensor([*vertices, list(box.center)], dtype=torch.float64)


def _disturbance_pieces(network: ValueNetwork, splits: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The disturbance box cut into ``splits`` pieces per dimension (its bounding box for a ball)."""
    system = network.system
    if not system.disturbance_dim:
        return torch.zeros(1, 0, dtype=torch.float64), torch.zeros(1, 0, dtype=torch.float64)
    low = torch.tensor(system.disturbance_bounds.low, dtype=torch.float64)
    high = torch.tensor(system.disturbance_bounds.high, dtype=torch.float64)
    cuts = [torch.linspace(float(a), float(b), splits + 1, dtype=torch.float64) for a, b in zip(low, high)]
    pieces = list(itertools.product(*[range(splits)] * len(cuts)))
    lo = torch.tensor([[float(cuts[j][i]) for j, i in enumerate(p)] for p in pieces], dtype=torch.float64)
    hi = torch.tensor([[float(cuts[j][i + 1]) for j, i in enumerate(p)] for p in pieces], dtype=torch.float64)
    return lo, hi


class Verifier:
    """The bounds a proof needs, for one network and one proof's ``settings``, on ``device``: ``V``
    over boxes (:meth:`value`), where each box's next states land (:meth:`next_boxes`,
    :meth:`landing`), whether an input keeps a box in ``S_c`` (:meth:`keeps`, :meth:`invariant`), the
    escape set's flags, and the branch and bound itself (:meth:`run`, what :func:`certify` runs). The
    closure (:mod:`safety.formal.closure`), the checker (:mod:`safety.formal.checker`) and the
    certified filter ask it the same questions, so all of them bound alike.

    ``closure=True``: the closure's view, over the state box widened ``closure_scale`` times
    (``domain``) with the escape set beyond it, the network bounded only inside its own box
    (``network_domain``). The verifier's own view (``closure=False``) is the network's box, with the
    escape set only where the closure's box is that box."""

    def __init__(
        self, network: ValueNetwork, settings: CertifySettings, device: torch.device, closure: bool = False
    ) -> None:
        # a float64 copy on the device: the caller's network stays as it is
        self.network, self.settings = copy.deepcopy(network).double().eval().to(device), settings
        system = network.system
        self.system = system
        self.periodic_dims = list(system.periodic_dims)
        self.periodic = torch.tensor([i in self.periodic_dims for i in range(system.state_dim)])
        self.network_domain = system.domain_tensor(torch.float64, device)
        scale = settings.closure_scale if closure else 1
        self.domain = closure_domain(system, scale, device)
        self.span = self.domain[:, 1] - self.domain[:, 0]
        self.step = make_stepper(system, settings.dt, settings.integrator, _Unwrapped())
        self.point_step = make_stepper(system, settings.dt, settings.integrator, TORCH)
        self.candidates = candidate_inputs(network)
        self.d_lo, self.d_hi = _disturbance_pieces(network, settings.disturbance_splits)
        self.escape = escape_rule(system, settings, scale) if closure or settings.closure_scale == 1 else None

    def in_network_domain(self, n_lo: torch.Tensor, n_hi: torch.Tensor) -> torch.Tensor:
        """Whether each box lies inside the network's box, where its bounds may be taken."""
        box = self.network_domain
        return (((n_lo >= box[:, 0]) & (n_hi <= box[:, 1])) | self.periodic.to(n_lo.device)).all(-1)

    def value(self, x_lo: torch.Tensor, x_hi: torch.Tensor) -> Interval:
        """Sound bounds of ``V(x, T)`` over each box (:func:`value_bounds`)."""
        return value_bounds(self.network, x_lo, x_hi, self.settings.time_to_go)

    def point_value(self, x: torch.Tensor) -> torch.Tensor:
        """``V(x, T)`` at states ``x`` (float64 evaluation, no bound)."""
        t = torch.full(x.shape[:-1], self.settings.time_to_go, dtype=torch.float64)
        with torch.no_grad():
            return self.network(x, t)

    def next_boxes(self, lo: torch.Tensor, hi: torch.Tensor, inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The next-state boxes of each box under its input (``inputs`` ``(B, m)``) and each disturbance
        piece, wrapped as the env wraps states (cut at the seam): ``(n_lo, n_hi, piece)``, ``piece`` the
        row of (box, disturbance piece), box-major, that each came from."""
        b, p = lo.shape[0], len(self.d_lo)
        x_lo, x_hi = lo.repeat_interleave(p, 0), hi.repeat_interleave(p, 0)
        u = inputs.repeat_interleave(p, 0)
        d_lo, d_hi = self.d_lo.repeat(b, 1), self.d_hi.repeat(b, 1)
        nxt = self.step(box_columns(x_lo, x_hi), [Interval(c, c) for c in u.unbind(-1)], box_columns(d_lo, d_hi))
        return _wrap_boxes(
            torch.stack([c.lo for c in nxt], -1), torch.stack([c.hi for c in nxt], -1), self.periodic_dims
        )

    def in_domain(self, n_lo: torch.Tensor, n_hi: torch.Tensor) -> torch.Tensor:
        """Whether each box lies inside the domain (periodic dimensions wrap, so they always do)."""
        return (((n_lo >= self.domain[:, 0]) & (n_hi <= self.domain[:, 1])) | self.periodic).all(-1)

    def escape_flags(self, margin: Interval) -> tuple[torch.Tensor, torch.Tensor]:
        """From bounds of ``l`` over boxes: whether every state of each box is in the escape set ``E``,
        and whether the box meets the band ``m - delta <= l < m`` where a step from ``E`` may land
        (every state of it must be in the certified set); both ``False`` without an escape set."""
        if self.escape is None:
            none = torch.zeros(margin.lo.shape, dtype=torch.bool, device=margin.lo.device)
            return none, none
        m, delta = self.escape
        return margin.lo >= m, (margin.hi >= m - delta) & (margin.lo < m)

    def in_escape(self, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
        """``(B,)``: whether every state of each box (inside the domain) is in ``E`` (:meth:`escape_flags`)."""
        return self.escape_flags(margin_bounds(self.system, lo, hi))[0]

    def in_band(self, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
        """``(B,)``: whether each box meets the band below ``E`` (:meth:`escape_flags`)."""
        return self.escape_flags(margin_bounds(self.system, lo, hi))[1]

    def landing(self, lo: torch.Tensor, hi: torch.Tensor, inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Where each box's next states land (:meth:`next_boxes`), cut to the domain where there is an
        escape set (what lies beyond is in ``E``): ``(n_lo, n_hi, piece, escaped, needs_escape)``.
        ``escaped``: the piece is all in ``E``; ``needs_escape``: some of its states are in ``E`` only
        (outside the domain, or all of it)."""
        n_lo, n_hi, piece = self.next_boxes(lo, hi, inputs)
        if self.escape is None:
            none = torch.zeros(len(n_lo), dtype=torch.bool)
            return n_lo, n_hi, piece, none, none
        c_lo, c_hi = torch.maximum(n_lo, self.domain[:, 0]), torch.minimum(n_hi, self.domain[:, 1])
        left = ((c_lo != n_lo) | (c_hi != n_hi)).any(-1)
        gone = (c_lo > c_hi).any(-1)  # wholly outside the domain
        point = torch.maximum(torch.minimum(n_lo, self.domain[:, 1]), self.domain[:, 0])
        c_lo, c_hi = torch.where(gone[:, None], point, c_lo), torch.where(gone[:, None], point, c_hi)
        escaped = gone | self.in_escape(c_lo, c_hi)
        return c_lo, c_hi, piece, escaped, escaped | left

    def keeps(
        self,
        lo: torch.Tensor,
        hi: torch.Tensor,
        inputs: torch.Tensor,
        also: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """``(B,)``: whether each box's input (``inputs`` ``(B, m)``) keeps every next state, under every
        disturbance piece, inside the domain and in ``S_c``, and (``also``, given the next-state boxes
        that passed) wherever else the caller requires. With an escape set, a next state may instead
        be in ``E`` (every state beyond the domain is)."""
        b, p = lo.shape[0], len(self.d_lo)
        n_lo, n_hi, piece, escaped, _ = self.landing(lo, hi, inputs)
        ok = self.in_network_domain(n_lo, n_hi) & ~escaped
        check = ok.nonzero().squeeze(-1)
        ok |= escaped
        if len(check):
            ok[check] = self.value(n_lo[check], n_hi[check]).lo >= self.settings.level
            if also is not None:
                ok[check] &= also(n_lo[check], n_hi[check])
        # a (box, piece) holds when all its wrapped parts do; a box when all its pieces do
        held = torch.ones(b * p, dtype=torch.long)
        held.scatter_reduce_(0, piece, ok.long(), reduce="amin")
        return held.reshape(b, p).bool().all(-1)

    def invariant(self, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
        """``(B,)`` the first candidate input that keeps each box in ``S_c`` (:meth:`keeps`), or -1.
        Candidates are tried in turn, each only on the boxes no earlier one kept."""
        chosen = torch.full((len(lo),), -1, dtype=torch.long)
        for k, u in enumerate(self.candidates):
            open_ = (chosen < 0).nonzero().squeeze(-1)
            if not len(open_):
                break
            kept = self.keeps(lo[open_], hi[open_], u.expand(len(open_), -1))
            chosen[open_[kept]] = k
        return chosen

    def refute(self, lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, list[dict]]:
        """Counterexamples at the boxes' centres (float64 evaluation): a state of ``S_c`` with ``l <= 0``,
        or one from which every candidate input has a disturbance vertex that leaves ``S_c`` (and the
        escape set ``E``, where there is one)."""
        x = 0.5 * (lo + hi)
        c = self.settings.level
        v = self.point_value(x)
        in_set = v >= c
        failing = self.system.failure_margin(x) <= 0
        escapes = torch.ones(len(x), dtype=torch.bool)
        d_vertices = [list(v) for v in itertools.product(*zip(self.d_lo.amin(0).tolist(), self.d_hi.amax(0).tolist()))]
        for u in self.candidates:
            some_d_escapes = torch.zeros(len(x), dtype=torch.bool)
            for d in d_vertices or [[]]:
                u_cols = [torch.full((len(x),), float(a), dtype=torch.float64) for a in u]
                d_cols = [torch.full((len(x),), float(a), dtype=torch.float64) for a in d]
                nxt = TORCH.stack(self.point_step(TORCH.unbind(x), u_cols, d_cols))
                out = self.point_value(nxt) < c
                if self.escape is not None:
                    out &= self.in_domain(nxt, nxt) & (self.system.failure_margin(nxt) < self.escape[0])
                some_d_escapes |= out
            escapes &= some_d_escapes
        refuted = in_set & (failing | escapes)
        found = [
            {"state": x[i].tolist(), "value": float(v[i]), "reason": "l <= 0" if failing[i] else "every input escapes"}
            for i in refuted.nonzero().squeeze(-1).tolist()
        ]
        return refuted, found

    def first_cover(self) -> VerifierProgress:
        """The state before any box is handled: the first cover queued, nothing decided."""
        s, n = self.settings, self.system.state_dim
        grid = torch.linspace(0, 1, s.initial_splits + 1, dtype=torch.float64)
        cells = torch.cartesian_prod(*[torch.arange(s.initial_splits)] * n).reshape(-1, n)
        empty = torch.empty(0, n, dtype=torch.float64)
        none = torch.empty(0, dtype=torch.long)
        return VerifierProgress(
            self.domain[:, 0] + grid[cells] * self.span,
            self.domain[:, 0] + grid[cells + 1] * self.span,
            empty, empty, none, none,
        )  # fmt: skip

    def run(
        self,
        progress: bool = False,
        state: VerifierProgress | None = None,
        save: Callable[[VerifierProgress], None] | None = None,
    ) -> CertificationResult:
        """Handle boxes from ``state`` (default: the first cover) until every box is decided or the
        budget is spent; ``save`` is given the state every :data:`SAVE_EVERY_S` seconds and at the end."""
        s, start = self.settings, time.perf_counter()
        state = self.first_cover() if state is None else state
        device = self.domain.device
        queue_lo, queue_hi = state.queue_lo.to(device), state.queue_hi.to(device)
        done_lo, done_hi = [state.done_lo.to(device)], [state.done_hi.to(device)]
        done_status, done_backup = [state.done_status.to(device)], [state.done_backup.to(device)]
        counterexamples: list[dict] = list(state.counterexamples)
        handled, last_save = state.handled, start

        def snapshot() -> VerifierProgress:
            return VerifierProgress(
                queue_lo, queue_hi, torch.cat(done_lo), torch.cat(done_hi), torch.cat(done_status),
                torch.cat(done_backup), counterexamples, handled, state.seconds + time.perf_counter() - start,
            )  # fmt: skip

        while len(queue_lo) and handled < s.max_boxes:
            if s.max_seconds is not None and time.perf_counter() - start > s.max_seconds:
                break
            if save is not None and time.perf_counter() - last_save > SAVE_EVERY_S:
                save(snapshot())
                last_save = time.perf_counter()
            lo, hi = queue_lo[: s.batch], queue_hi[: s.batch]
            queue_lo, queue_hi = queue_lo[s.batch :], queue_hi[s.batch :]
            handled += len(lo)
            status = torch.full((len(lo),), UNKNOWN, dtype=torch.long)
            backup = torch.full((len(lo),), -1, dtype=torch.long)
            v = self.value(lo, hi)
            margin = margin_bounds(self.system, lo, hi)
            escaping, band = self.escape_flags(margin)
            status[escaping] = ESCAPE
            outside = (v.hi < s.level) & ~escaping
            status[outside] = OUTSIDE
            # a box of the band must hold only states of S_c: one where that is not proven is split
            short = band & (v.lo < s.level)
            width = (hi - lo) / self.span
            finest = s.min_relative_width if s.band_min_relative_width is None else s.band_min_relative_width
            short_split = short & (width.amax(-1) > finest)  # split whatever (b) says: not tried
            rest = (~outside & ~escaping & ~short_split).nonzero().squeeze(-1)
            undecided = torch.zeros_like(short)
            if len(rest):
                included = (margin.lo[rest] > 0).nonzero().squeeze(-1)
                chosen = torch.full((len(rest),), -1, dtype=torch.long)
                if len(included):
                    chosen[included] = self.invariant(lo[rest[included]], hi[rest[included]])
                proven = chosen >= 0
                status[rest[proven]] = PROVEN
                backup[rest[proven]] = chosen[proven]
                open_ = rest[~proven]
                if len(open_):
                    refuted, found = self.refute(lo[open_], hi[open_])
                    status[open_[refuted]] = REFUTED
                    counterexamples += found
                    undecided[open_[~refuted]] = True
            # the band's boxes must all be kept, so an undecided one is split finer, as far as the band goes
            finer = torch.where(band, finest, s.min_relative_width)
            split = (undecided & (width.amax(-1) > finer)) | short_split
            split = split.nonzero().squeeze(-1)
            if len(split):
                dim = width[split].argmax(-1)
                mid = 0.5 * (lo[split, dim] + hi[split, dim])
                left_hi, right_lo = hi[split].clone(), lo[split].clone()
                rows = torch.arange(len(split))
                left_hi[rows, dim], right_lo[rows, dim] = mid, mid
                # breadth first: every box is tried at each size before any is split further
                queue_lo = torch.cat([queue_lo, lo[split], right_lo])
                queue_hi = torch.cat([queue_hi, left_hi, hi[split]])
                status[split] = -1  # replaced by its halves
            keep = status >= 0
            done_lo.append(lo[keep]), done_hi.append(hi[keep])
            done_status.append(status[keep]), done_backup.append(backup[keep])
            if progress:
                print(f"{handled} boxes handled, {len(queue_lo)} queued", flush=True)
        final = snapshot()
        if save is not None:
            save(final)
        finished = len(queue_lo) == 0
        lo, hi, status, backup = final.done_lo, final.done_hi, final.done_status, final.done_backup
        if not finished:  # what is left counts as unknown: never reported as proven
            lo, hi = torch.cat([lo, queue_lo]), torch.cat([hi, queue_hi])
            status = torch.cat([status, torch.full((len(queue_lo),), UNKNOWN, dtype=torch.long)])
            backup = torch.cat([backup, torch.full((len(queue_lo),), -1, dtype=torch.long)])
        band_open = 0
        if self.escape is not None:
            band = (self.in_band(lo, hi) & (status != ESCAPE)).nonzero().squeeze(-1)
            band_open = int((self.value(lo[band], hi[band]).lo < s.level).sum()) if len(band) else 0
        return CertificationResult(
            s,
            lo.cpu(),
            hi.cpu(),
            status.cpu(),
            backup.cpu(),
            self.candidates.cpu(),
            counterexamples,
            finished,
            final.seconds,
            handled,
            band_open,
        )


def certify(
    value_function: NeuralValueFunction | ValueNetwork,
    settings: CertifySettings,
    progress: bool = False,
    device: str | torch.device = "cpu",
    resume: str | os.PathLike | None = None,
) -> CertificationResult:
    """Prove (or refute) that ``{V(x, T) >= c}`` is a safe, robustly invariant set (module docstring),
    bounding boxes on ``device`` (a GPU bounds many more boxes a second; float64 throughout).

    ``resume``: a progress file (``.npz``, :mod:`safety.formal.progress`). The run saves its state
    there as it goes and when it stops, and a run started again with the same file continues from
    it; a file made for another value function, system or proof is refused, naming the difference.
    The result's ``wall_time`` and ``boxes_handled`` then count every run."""
    network = network_of(value_function)
    escape_rule(network.system, settings, settings.closure_scale)  # refused before any box is bounded
    check_size(network, settings)
    if settings.time_to_go > network.system.horizon:
        raise ValueError(
            f"time_to_go {settings.time_to_go:g} is beyond the value function's horizon {network.system.horizon:g}"
        )
    save, state = None, None
    if resume is not None:
        if not str(resume).endswith(".npz"):
            raise ValueError(f"a verifier progress file ends in .npz, got {str(resume)!r}")
        provenance = (asdict(settings), network.system.config(), network_digest(network))
        state = load_progress(resume, *provenance)

        def save(snapshot: VerifierProgress) -> None:
            save_progress(resume, snapshot, *provenance)

    with torch.device(device):
        return Verifier(network, settings, torch.device(device)).run(progress, state, save)
