"""Studies on recorded data that answer design questions about the modelling (thesis Ch. 5).

* :mod:`daror_runtime.studies.data_efficiency`: how many stationary points a model needs
  (Sec. 5.3.1, Fig. 5.4); :mod:`daror_runtime.studies.data_efficiency_report` renders it.

Studies only read datasets and fit models through the model registry; like the models they never
see a simulation scenario, and they run outside the control loop.
"""
