"""The operator console: one line per request, scripted (``--script FILE``) or typed.

The console talks only to :class:`daror_runtime.runtime.Runtime` (requests, status). On the
simulated plant it also plays the world around the robot (:mod:`~daror_runtime.console.world`):
the pilot who holds, moves or relaxes the arm, the e-stop buttons, injected faults.
"""
