"""High-fidelity physics of the electro-hydraulic servo actuator (numpy + numba only).

Blocks: :mod:`.commands`, :mod:`.servovalve` (torque motor, first and second stage),
:mod:`.friction` (Borello), :mod:`.valve` (fluid-dynamic block), :mod:`.jack`; the closed loop
and the steppable plant in :mod:`.plant`, built on :mod:`.state` (state layout), :mod:`.loop`
(the kernel, and the :class:`FluidBlock` a surrogate provides) and :mod:`.stability`;
characteristic maps in :mod:`.maps`; parameters in :mod:`.params`; parameter changes during a
run in :mod:`.events`.  Nothing here imports rclpy or torch.
"""

from eha_ros.jit_cache import defer_blas_probe, share_inline_copies

share_inline_copies()  # before any kernel compiles: a third of numba's compile time
defer_blas_probe()  # before the first kernel loads: numba's probe imported scipy.linalg

# (the imports below follow it: E402)
from .commands import Scenario, get_scenario, load_scenarios  # noqa: E402
from .events import (CONTROLLER_RUNTIME, PLANT_RUNTIME, Event, EventSchedule,  # noqa: E402
                     format_event, parse_event)
from .loop import CHAMBER_FLOWS, P12, FluidBlock, SimulationDiverged  # noqa: E402
from .params import (ParameterError, PlantParams, default_params, load_params,  # noqa: E402
                     params_hash, params_to_dict)
from .plant import Plant, SimResult, simulate  # noqa: E402
from .stability import stability_limit  # noqa: E402

__all__ = ['Scenario', 'get_scenario', 'load_scenarios', 'ParameterError', 'PlantParams',
           'default_params', 'load_params', 'params_hash', 'params_to_dict', 'Plant',
           'SimResult', 'SimulationDiverged', 'simulate', 'stability_limit', 'PLANT_RUNTIME',
           'CONTROLLER_RUNTIME', 'Event', 'EventSchedule', 'parse_event', 'format_event',
           'FluidBlock', 'P12', 'CHAMBER_FLOWS']
