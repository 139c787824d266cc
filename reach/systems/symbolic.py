"""A system's equations as mathematics: its own physics code run on SymPy symbols.

A system writes its physics once, on columns (:mod:`reach.systems.arrays`); :data:`SYMPY` is one more
backend whose columns are SymPy expressions, so the drift, the input matrices and the margins that
envs, solvers and training evaluate are the ones printed. Nothing is restated by hand: the docs'
gallery of systems (``docs/gallery.md``) and :func:`equations` for a system of your own come from
the same code path::

    from reach.systems import make_system
    from reach.systems.symbolic import equations

    eq = equations(make_system("dubins3d"))
    print(eq.dynamics_latex())   # \\dot{x} = ..., one line per state

Display only: ``wrap_angle`` leaves an angle as it is, and ``where`` becomes a piecewise expression.
SymPy is imported on first use (it ships with torch).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import sympy

from reach.systems.base import ControlAffineSystem


class SympyBackend:
    """Columns are SymPy expressions (or Python numbers, which SymPy absorbs)."""

    name = "sympy"
    cos = staticmethod(sympy.cos)
    sin = staticmethod(sympy.sin)
    sqrt = staticmethod(sympy.sqrt)
    atan2 = staticmethod(sympy.atan2)
    abs = staticmethod(sympy.Abs)
    sign = staticmethod(sympy.sign)

    @staticmethod
    def unbind(x: Sequence[Any]) -> Sequence[Any]:
        return x

    @staticmethod
    def stack(columns: Sequence[Any], like: Any = None) -> list[Any]:
        return [sympy.sympify(c) for c in columns]

    @staticmethod
    def minimum(a: Any, b: Any) -> Any:
        return sympy.Min(a, b)

    @staticmethod
    def where(condition: Any, a: Any, b: Any) -> Any:
        return sympy.Piecewise((a, condition), (b, True))

    @staticmethod
    def clip(a: Any, lo: float, hi: float) -> Any:
        return sympy.Min(sympy.Max(a, lo), hi)

    @staticmethod
    def hypot(dx: Any, dy: Any) -> Any:
        return sympy.sqrt(dx**2 + dy**2)

    @staticmethod
    def norm(columns: Sequence[Any]) -> Any:
        return sympy.sqrt(sum(c**2 for c in columns))

    @staticmethod
    def wrap_angle(a: Any) -> Any:
        return a  # display: the angle as written; the numeric backends wrap it to [-pi, pi)

    @staticmethod
    def axpy(x: Sequence[Any], h: float, k: Sequence[Any]) -> list[Any]:
        return [a + h * b for a, b in zip(x, k)]


SYMPY = SympyBackend()


#: state-name stems that read as a Greek letter
_GREEK = {"th": "theta", "heading": "theta", "phi": "phi", "psi": "psi", "w": "omega", "omega": "omega"}


def _symbol(name: str) -> sympy.Symbol:
    """A state name as it reads in the docs: ``x1`` -> x_1, ``th3`` and ``heading3`` -> theta_3,
    ``px`` -> p_x, ``wy`` -> omega_y; other names stay as they are."""
    stem = name.rstrip("0123456789")
    index = name[len(stem) :]
    if not index and len(stem) == 2 and stem[1] in "xyzw" and stem[0] in "pvqw":
        stem, index = stem[0], stem[1]  # a vector's component: p_x, v_y, q_w, omega_z
    stem = _GREEK.get(stem, stem)
    if stem in _GREEK.values():
        stem = "\\" + stem
    return sympy.Symbol(f"{stem}_{{{index}}}" if index else stem, real=True)


@dataclass(frozen=True)
class Equations:
    """A system's state, inputs, dynamics and margins as SymPy expressions (see the module docstring)."""

    system: ControlAffineSystem
    states: tuple[sympy.Symbol, ...]
    controls: tuple[sympy.Symbol, ...]
    disturbances: tuple[sympy.Symbol, ...]
    dynamics: tuple[Any, ...]
    margins: dict[str, Any]

    def dynamics_latex(self) -> str:
        """``\\dot{x}_i = ...`` per state, one LaTeX ``aligned`` block."""
        rows = [
            rf"\dot{{{sympy.latex(s)}}} &= {sympy.latex(f)}" for s, f in zip(self.states, self.dynamics, strict=True)
        ]
        return "\\begin{aligned}\n" + " \\\\\n".join(rows) + "\n\\end{aligned}"

    def margins_latex(self) -> dict[str, str]:
        """Each margin the kind uses (``failure``, ``target``, ``constraint``) in LaTeX."""
        return {name: sympy.latex(expr) for name, expr in self.margins.items()}


def _tidy_number(value: sympy.Float) -> Any:
    """A float as it reads best: an integer, a simple multiple of pi, else six significant digits."""
    f = float(value)
    if abs(f - round(f)) < 1e-12:
        return sympy.Integer(round(f))
    ratio = sympy.Rational(f / sympy.pi.evalf(30)).limit_denominator(12)
    if abs(float(ratio * sympy.pi) - f) < 1e-12 * max(1.0, abs(f)):
        return ratio * sympy.pi
    return sympy.Float(f, 6)


def tidy(expr: Any) -> Any:
    """``expr`` with its floats tidied (:func:`_tidy_number`) and 1.0 factors gone, for display."""
    expr = sympy.sympify(expr)
    return expr.xreplace({f: _tidy_number(f) for f in expr.atoms(sympy.Float)})


def _entries(matrix: dict[tuple[int, int], Any], n: int, inputs: Sequence[sympy.Symbol]) -> list[Any]:
    out: list[Any] = [sympy.Integer(0)] * n
    for (i, j), g in matrix.items():
        out[i] = out[i] + sympy.sympify(g) * inputs[j]
    return out


def equations(system: ControlAffineSystem, display: bool = True) -> Equations:
    """The equations of ``system``, derived by running its own physics on symbols.

    ``display`` tidies each expression for reading: floats to six significant digits or a multiple
    of pi (:func:`tidy`), terms simplified (``sympy.simplify``). ``display=False`` keeps the exact
    floats and the terms as the system's code builds them."""
    states = tuple(_symbol(n) for n in system.state_names)
    controls = tuple(sympy.Symbol(f"u_{{{j + 1}}}", real=True) for j in range(system.control_dim))
    disturbances = tuple(sympy.Symbol(f"d_{{{j + 1}}}", real=True) for j in range(system.disturbance_dim))
    x = list(states)
    drift = [sympy.sympify(f) for f in system.drift(x, SYMPY)]
    control = _entries(system.control_matrix(x, SYMPY), len(x), controls)
    disturbance = (
        _entries(system.disturbance_matrix(x, SYMPY), len(x), disturbances) if system.disturbance_dim else [0] * len(x)
    )
    shown = (lambda e: tidy(sympy.simplify(tidy(e)))) if display else sympy.sympify
    dynamics = tuple(shown(f + g + h) for f, g, h in zip(drift, control, disturbance))
    margins: dict[str, Any] = {}
    if system.kind == "avoid":
        margins["failure"] = system.failure_margin_columns(x, SYMPY)
    else:
        margins["target"] = system.target_margin_columns(x, SYMPY)
        if system.kind == "reach-avoid":
            margins["constraint"] = system.constraint_margin_columns(x, SYMPY)
    margins = {name: (tidy if display else sympy.sympify)(expr) for name, expr in margins.items()}
    return Equations(system, states, controls, disturbances, dynamics, margins)


__all__ = ["SYMPY", "Equations", "SympyBackend", "equations"]
