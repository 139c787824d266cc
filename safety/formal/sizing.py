"""Size before work: a proof whose settings cannot fit is refused before any box is bounded.

:func:`check_size` estimates what the verifier and the closure will hold at their peak from the
settings and the network's size alone, and refuses with the estimate and what to change, as
``reach evaluate`` and the grid solver do (:func:`reach.memory_check.require_memory`), instead of
an out-of-memory error, a negative range or an overflowing index half-way through.
"""

from __future__ import annotations

from reach.memory_check import require_memory
from safety.formal.settings import CertifySettings
from training.network import ValueNetwork

__all__ = ["BYTES_PER_CLOSURE_BOX", "BYTES_PER_PIECE_UNIT", "MAX_CELLS", "check_size"]

#: bytes one (box, disturbance piece) costs while the verifier bounds a batch, per unit of
#: ``(network inputs + 1) x (hidden units)``: the linear bounds of every layer of every piece-box
#: (calibrated on the CPU, measured: docs/results/certificates.md; rounded up)
BYTES_PER_PIECE_UNIT = 64
#: bytes per box of the closure's cover (corners, inputs, owners and next-state pieces; rounded up)
BYTES_PER_CLOSURE_BOX = 1024
#: the largest cell index a 64-bit integer holds with room for the sums over cells
MAX_CELLS = 2**62


def check_size(network: ValueNetwork, settings: CertifySettings) -> None:
    """Refuse, before any box is bounded, settings whose work cannot fit, with the estimate and what to
    change: a batch of boxes times the disturbance pieces beyond the memory available, a cell grid
    whose index overflows 64 bits, and a closure cover cut so fine it cannot be held."""
    system = network.system
    n = system.state_dim
    pieces = settings.disturbance_splits**system.disturbance_dim
    hidden = sum(layer.out_features for layer in network.layers)
    per_piece = BYTES_PER_PIECE_UNIT * (network.layers[0].in_features + 1) * hidden
    require_memory(
        settings.batch * pieces * per_piece,
        f"bounding {settings.batch} boxes at once, each in {pieces:,} disturbance pieces "
        f"({settings.disturbance_splits} per dimension over {system.disturbance_dim})",
        "lower --batch or --disturbance-splits",
    )
    widths = [settings.min_relative_width, settings.band_min_relative_width, settings.closure_relative_width]
    finest = min(w for w in widths if w is not None) / 2**settings.closure_refinements
    per_dim = settings.closure_scale / finest
    if per_dim**n >= MAX_CELLS:
        raise ValueError(
            f"the finest box, {finest:.3g} of the span (the widths given, halved {settings.closure_refinements} "
            f"times by the refinements) over a box {settings.closure_scale} times wider, makes a cell grid of "
            f"{per_dim:.3g}^{n} cells, beyond what a 64-bit index holds: give a wider --min-width, "
            "--band-min-width or --closure-width, or fewer --closure-refinements"
        )
    if settings.closure_relative_width is not None:
        cut = (settings.closure_scale / settings.closure_relative_width) ** n
        require_memory(
            int(min(cut * BYTES_PER_CLOSURE_BOX, 2**80)),
            f"a closure cover cut down to {settings.closure_relative_width:.3g} of the span ({cut:.3g} boxes at most)",
            "give a wider --closure-width or a smaller --closure-scale",
        )
