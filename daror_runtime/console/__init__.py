"""The operator console: one line per request, scripted (``--script FILE``) or typed.

The console talks only to :class:`daror_runtime.runtime.Runtime` (requests, status). On a backend
that simulates the robot it also plays the world around it (:mod:`~daror_runtime.console.world`,
through the backend's :class:`hal.capabilities.SimulatedWorld`): the pilot who holds, moves or
relaxes the arm, the e-stop buttons, injected faults. It never imports a backend nor asks which
one it has; on a backend without a world, ``sim`` lines are refused.
"""
