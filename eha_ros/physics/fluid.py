"""The fluid-dynamic block as the plant sees it: :class:`FluidBlock`, what a surrogate
provides in place of the high-fidelity block, and the kernels it hands to :func:`.loop.run`.

Named ``fluid`` for that block; the high-fidelity equations themselves are in :mod:`.valve`.
"""

from __future__ import annotations

from typing import Callable, Protocol, runtime_checkable

from .loop import Kernel
from .params import ParameterError, PlantParams

__all__ = ['P12', 'CHAMBER_FLOWS', 'FluidBlock', 'fluid_kernels']

#: ``kernel_output`` of an algebraic surrogate:
#: ``kernel(data, xs_m, q_m3_s, overlap_m, clearance_m) -> P12 [Pa]``.
P12 = 'p12'
#: ``kernel_output`` of a dynamic surrogate:
#: ``kernel(data, xs_m, p1_pa, p2_pa, lap_supply_m, lap_return_m) -> (Q1L, Q2L) [m^3/s]``.
CHAMBER_FLOWS = 'chamber_flows'


@runtime_checkable
class FluidBlock(Protocol):
    """A surrogate of the fluid-dynamic block, as the plant calls it."""

    name: str
    #: the numba kernel, called inside the plant's loop (signature after ``kernel_output``)
    kernel: Callable
    #: :data:`P12` or :data:`CHAMBER_FLOWS`
    kernel_output: str

    def prepare(self, p: PlantParams) -> tuple:
        """The kernel's data for the parameters ``p``; ValueError if it refuses them."""

    def stability_limit(self, p: PlantParams) -> tuple[float, str]:
        """``(dt_s, reason)``: the largest stable step under this block's feedback, in place
        of the high-fidelity chamber bound."""

    def check_params(self, p: PlantParams) -> None:
        """Refuse parameters the block was not built for (ValueError)."""


def fluid_kernels(fluid: FluidBlock | None, p: PlantParams) -> tuple:
    """``(p12_kernel, flows_kernel)`` of :func:`.loop.run` for ``fluid`` at the parameters
    ``p``: ``(None, None)`` for the high-fidelity block (``fluid`` ``None``)."""
    if fluid is None:
        return None, None
    if not isinstance(fluid, FluidBlock) or fluid.kernel_output not in (P12, CHAMBER_FLOWS):
        raise ParameterError(f'fluid must be a FluidBlock with kernel_output {P12!r} or '
                             f'{CHAMBER_FLOWS!r}')
    try:
        kernel = Kernel(fluid.kernel, tuple(fluid.prepare(p)))
    except ValueError as exc:  # a surrogate refusing these parameters
        raise ParameterError(str(exc)) from None
    return (kernel, None) if fluid.kernel_output == P12 else (None, kernel)
