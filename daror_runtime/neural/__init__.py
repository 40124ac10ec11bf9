"""Training the neural compensation models PENN and NNN with JAX (the optional extra ``nn``).

* :mod:`.networks`: the networks of :mod:`daror_runtime.models.neural` in JAX: initialisation,
  forward pass, a PENN's torque as ``jax.grad`` of its potential;
* :mod:`.training`: the loss, Adam then L-BFGS, k-fold validation by blocks of time, the minimal
  validation loss, several initialisations trained together (:func:`.training.train_group`,
  the entry point of the hyper-parameter search too);
* :mod:`.presets`: the default networks and the thesis's (Tables I and II, Eq. 3.7);
* :mod:`.fit`: the registry's fitters ``fit_penn`` and ``fit_nnn``.

A trained model runs without this package: :mod:`daror_runtime.models.neural` (numpy and numba).

**Float64.** Importing this package switches JAX to 64-bit floats for the whole process
(``jax_enable_x64``): the trained weights must reproduce the torque to the last digits the numba
kernel computes (tests compare them to 1e-9 Nm), and float32 training would leave the model's
weights rounded at 1e-7. Nothing else in the runtime uses JAX, so the switch affects only this
package's computations (and anything a caller runs with JAX after importing it).
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)
