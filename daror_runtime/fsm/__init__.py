"""The safety FSM: what the robot may do at any moment follows from ``fsm_spec.yaml``.

* :mod:`~daror_runtime.fsm.spec`: the spec's schema (pydantic), its loader and its checks.
* :mod:`~daror_runtime.fsm.guards`: the named conditions a spec may use, and the session signals
  they read.
* :mod:`~daror_runtime.fsm.modes`: the control modes a spec may name.
* :mod:`~daror_runtime.fsm.machine`: the machine built from a spec with ``transitions``.
* :mod:`~daror_runtime.fsm.supervisor`: the machine inside the tick (requests, faults, e-stops,
  controllers and limits per state).
* :mod:`~daror_runtime.fsm.diagram`: the Mermaid diagram of a spec (docs/fsm.md).
"""
