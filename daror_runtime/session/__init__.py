"""What a session needs beyond the FSM: its settings, the controllers of the modes, the pilot's
range of motion, the identification runs and model training done outside the tick.

:class:`daror_runtime.runtime.Runtime` wires them together; the console talks only to it.
"""
