"""Commissioning a CAN bus of CiA 402 drives: ``daror can scan|check|zero|tare`` (docs/canopen.md, Commissioning).

The commands themselves (their flags, their output) are :mod:`daror_runtime.cli.can`; here:

* :mod:`~daror_runtime.commissioning.bus_session`: the backend, its clock, its ticks, torque off at the end;
* :mod:`~daror_runtime.commissioning.check`: the check's procedure and its table;
* :mod:`~daror_runtime.commissioning.calibration`: reading the drives still for a zero or a tare;
* :mod:`~daror_runtime.commissioning.robot_file`: each node's ``calibration:`` written into the robot file;
* :mod:`~daror_runtime.commissioning.expect`: what the check expects of each node.

The CAN side lives in ``hal``, reached through :mod:`hal.commissioning` only (the runtime names no
backend module, ``tests/test_boundaries.py``): the scan (:mod:`hal.canopen.scan`), the drives' own
words through the master (:mod:`hal.canopen.commissioning`), and a stored calibration applied to
the readings (:mod:`hal.canopen.calibration`).
"""
