"""How a value network reads ``(t, x)`` and how its output becomes ``V``: the :class:`Encoding`.

Why a module of its own: the encoding is plain data, stored in checkpoints and built for a system or
for DeepReach's convention (checkpoint import) without any layer.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from reach.systems import ControlAffineSystem


@dataclass(frozen=True)
class Encoding:
    """How ``(t, x)`` becomes network input and the output becomes ``V``.

    Input: ``((t - time_offset) / time_scale, (x - state_offset) / state_scale)``; periodic
    dimensions listed in ``sincos_dims`` are replaced by ``r (sin x_i, cos x_i)`` instead (a heading
    encoding with no seam at +-pi), ``r = sincos_radius``. With ``r = 1/pi`` a full turn is a circle
    of circumference 2 in input space, the same length as the [-1, 1] span of the plain encoding, so
    a sine network's first layer sees the heading at the same spatial frequency either way (with
    ``r = 1`` it sees it pi times faster). Output: ``value_scale * o + value_offset`` (vanilla) or
    ``l(x) + (t / horizon) * value_scale * o`` (exact).
    """

    state_offset: tuple[float, ...]
    state_scale: tuple[float, ...]
    time_offset: float = 0.0
    time_scale: float = 1.0
    value_scale: float = 1.0
    value_offset: float = 0.0
    horizon: float = 1.0
    sincos_dims: tuple[int, ...] = field(default_factory=tuple)
    sincos_radius: float = 1.0

    @classmethod
    def for_system(
        cls, system: ControlAffineSystem, sincos: bool = False, value_scale: float = 1.0, sincos_radius: float = 1.0
    ) -> Encoding:
        """Domain box mapped to [-1, 1], time-to-go [0, T] to [-1, 1]."""
        lo = [a for a, _ in system.domain]
        hi = [b for _, b in system.domain]
        return cls(
            state_offset=tuple(0.5 * (a + b) for a, b in zip(lo, hi)),
            state_scale=tuple(0.5 * (b - a) for a, b in zip(lo, hi)),
            time_offset=0.5 * system.horizon,
            time_scale=0.5 * system.horizon,
            value_scale=value_scale,
            value_offset=0.0,
            horizon=system.horizon,
            sincos_dims=tuple(system.periodic_dims) if sincos else (),
            sincos_radius=sincos_radius,
        )

    @classmethod
    def deepreach(cls, system: ControlAffineSystem) -> Encoding:
        """DeepReach's convention: raw t, headings / 1.2 pi, ``V = 25 o + 0.25`` (checkpoint import)."""
        n = system.deepreach
        if n is None:
            raise ValueError(
                f"{system.reference()} declares no DeepReach normalisation (attribute 'deepreach'), which "
                "importing a DeepReach checkpoint needs"
            )
        return cls(
            state_offset=n.state_offset,
            state_scale=n.state_scale,
            value_scale=n.value_scale,
            value_offset=n.value_offset,
            horizon=system.horizon,
        )

    def input_dim(self, state_dim: int) -> int:
        return 1 + state_dim + len(self.sincos_dims)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Encoding:
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})
