"""Electro-hydraulic servo actuator (EHA) with a flapper-nozzle servovalve, on ROS 2.

Subpackages: ``physics`` (plant models, numpy/numba only), ``tools`` (command-line tools),
``testing`` (helpers for tests that start ROS 2 processes) and ``msg`` (the ROS 2 message
classes, generated from ``msg/*.msg`` when the package is built).
"""

__version__ = '0.1.0'
