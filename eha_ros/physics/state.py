"""The plant's state vector and record layout, its rest state and its operating condition.

Named ``state`` for what it holds: the index of every state entry (``S_*``), the fields of a
closed-loop record row, and what a state alone tells: the rest state and whether the jack is
at an end stop or a chamber cavitates.  The kernels (:mod:`.loop`) and the wrappers
(:mod:`.plant`) share it; the ROS plant reads the condition from here.
"""

from __future__ import annotations

import numpy as np

from .params import PlantParams
from .valve import steady_pressures

__all__ = ['STATE_NAMES', 'N_STATE', 'RECORD_FIELDS', 'N_REC', 'initial_state', 'OK',
           'END_STOP', 'CAVITATION', 'operating_condition']

STATE_NAMES = ('hysteresis_state_a', 'flapper_position_m', 'flapper_velocity_m_s',
               'spool_position_m', 'spool_velocity_m_s', 'p1_unclipped_pa', 'p2_unclipped_pa',
               'p1_pa', 'p2_pa', 'jack_position_m', 'jack_velocity_m_s', 'surface_position_m',
               'load_flow_m3_s', 'coil_current_a', 'torque_motor_force_n', 'q1l_m3_s',
               'q2l_m3_s')
(S_PLAY, S_XF, S_VF, S_XS, S_VS, S_P1T, S_P2T, S_P1, S_P2, S_XJ, S_VJ, S_SURF, S_QJ, S_ICOIL,
 S_FTM, S_Q1L, S_Q2L) = range(len(STATE_NAMES))
N_STATE = len(STATE_NAMES)

RECORD_FIELDS = ('time_s', 'command_m', 'current_command_a', 'coil_current_a',
                 'torque_motor_force_n', 'flapper_position_m', 'spool_position_m', 'p1_pa',
                 'p2_pa', 'p12_pa', 'load_flow_m3_s', 'jack_position_m', 'jack_velocity_m_s',
                 'surface_position_m', 'jack_position_measured_m')
N_REC = len(RECORD_FIELDS)

#: Operating conditions (:func:`operating_condition`), named as the ROS graph's status codes
#: (``eha_ros.graph.STATUS_NAMES``).
OK, END_STOP, CAVITATION = 'OK', 'END_STOP', 'CAVITATION'


def initial_state(p: PlantParams) -> np.ndarray:
    """Plant at rest at null: spool and flapper centred, chamber pressures at their steady
    values for a centred spool and no flow."""
    s = np.zeros(N_STATE)
    p1, p2 = steady_pressures(0.0, 0.0, p, 10.0 * p.supply_pressure_pa)
    s[S_P1T] = s[S_P1] = p1
    s[S_P2T] = s[S_P2] = p2
    return s


def operating_condition(s: np.ndarray, p: PlantParams) -> str:
    """:data:`END_STOP` with the jack at (or beyond) its stroke, else :data:`CAVITATION` with a
    chamber pressure clipped at the vapour pressure, else :data:`OK`."""
    if abs(s[S_XJ]) >= p.jack_stroke_m:
        return END_STOP
    if min(s[S_P1], s[S_P2]) <= p.vapour_pressure_pa:
        return CAVITATION
    return OK
