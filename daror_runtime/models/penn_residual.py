"""A PENN residual on top of a physical model: ``V = V_base + V_nn``, ``tau = tau_base + dV_nn/dq``.

The model kind ``penn-residual`` (issue 13): a physical base model (AP, PLF, PLF+, or the
augmented model of ``daror residual``) plus a PENN trained on what the base leaves in the training
data, ``tau - tau_base(q)``. The network adds a potential, so the sum stays the gradient of one
whenever the base is (Sec. 3.1.3); it has no physical parameters and is never presented as a
named effect. Training lives in ``daror_runtime.neural.residual_fit`` (the extra ``nn``); this
module only runs a trained model (numpy and numba, no JAX).

**Model file** ``parameters``::

    {"base": {"kind": "plf+", "name": "PLF+", "parameters": {...the base kind's parameters...}},
     "residual": {...a PENN's parameters (daror_runtime.models.neural.NetworkParameters)...}}

The model-file layer builds the base first, by its kind
(:func:`daror_runtime.models.files.model_from_parameters`: this kind is ``nested_base``), so this
module needs no kind lookup. The base must be a physical model: a neural one (a PENN, an NNN,
another ``penn-residual``) is refused.

**Tick**: when the base offers the compiled linear torque (AP, PLF, PLF+),
:func:`penn_residual_torque` runs both in one compiled call from one packed vector
``[LAYOUT_TAG, n_base, base's packed parameters (n_base), the packed network]``; a base without a
compiled torque (the augmented model) gives a model without one either (it runs through
:meth:`PennResidualModel.torque`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
from numba import njit

from daror_runtime.errors import ModelFileError
from daror_runtime.models.base import CompensationModel, ReadingErrorTracker, TickKernel
from daror_runtime.models.neural import NeuralModel, PennModel, _checked_scratch_size, network_torque_into
from daror_runtime.models.regressor import linear_torque
from hal.errors import ShapeError
from hal.robot import N_JOINTS, FloatArray, RobotDescription

__all__ = ["LAYOUT_TAG", "PennResidualModel", "pack_penn_residual", "penn_residual_torque"]

#: First number of the packed vector of :func:`penn_residual_torque` (layout 1).
LAYOUT_TAG = 9.130501
#: Numbers of :func:`~daror_runtime.models.regressor.linear_torque`'s vector before its polynomial
#: (up direction 3, cos and sin 60 deg, theta 12, the number of terms).
_LINEAR_HEADER = 18


def pack_penn_residual(base_parameters: np.ndarray, network_parameters: np.ndarray) -> np.ndarray:
    """The packed vector of :func:`penn_residual_torque` (read-only): tag, base length, base, network.

    Args:
        base_parameters: the packed parameters of :func:`daror_runtime.models.regressor.linear_torque`.
        network_parameters: a packed PENN (:func:`daror_runtime.models.neural.pack_network`).
    """
    packed = np.concatenate([[LAYOUT_TAG, float(base_parameters.size)], base_parameters, network_parameters])
    packed.flags.writeable = False
    return packed


@njit(cache=True)
def penn_residual_torque(q: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """The :class:`TickKernel` function of a PENN residual on a linear base: ``linear_torque + dV_nn/dq`` (Nm).

    Reads the packed vector of :func:`pack_penn_residual`; allocates one scratch array per call
    (as :func:`daror_runtime.models.neural.network_torque` does).

    Raises:
        ValueError: ``p`` is not a vector of this layout (the network's header is checked too).
    """
    if q.shape[0] != 4 or out.shape[0] != 4:
        raise ValueError("PENN residual kernel: q or out not of 4 values")
    if p.shape[0] < 2 or p[0] != LAYOUT_TAG or p[1] < _LINEAR_HEADER or p[1] > p.shape[0] - 2:
        raise ValueError("not a packed PENN residual vector (layout 1)")
    n_base = int(p[1])
    if p[1] != n_base or p[1 + _LINEAR_HEADER] != n_base - _LINEAR_HEADER:  # linear_torque's terms: 18 + n_mu
        raise ValueError("packed PENN residual vector: the base's length does not match its polynomial")
    network = p[2 + n_base :]
    scratch = np.empty(_checked_scratch_size(network) + 4)
    linear_torque(q, p[2 : 2 + n_base], out)
    learned = scratch[:4]
    network_torque_into(q, network, scratch[4:], learned)
    for j in range(4):
        out[j] += learned[j]


def _prefixed(exc: Exception, where: str) -> str:
    """A nested model's one-line error with its field moved under ``where`` (``parameters.x`` -> ``where.x``)."""
    message = str(exc)
    return where + message.removeprefix("parameters") if message.startswith("parameters") else f"{where}: {message}"


class PennResidualModel(CompensationModel):
    """A physical base model plus a PENN residual (the module docstring).

    Raises (constructor):
        ShapeError: the residual is not a PENN, or the base is a neural model (not a physical one).
    """

    kind: ClassVar[str] = "penn-residual"
    display_name: ClassVar[str] = "PENN residual"
    # The learned part is a gradient by construction; the whole is conservative when its base is
    # (AP, PLF, PLF+; an augmented base with a torque gain is not exactly): `daror cvf` measures it.
    conservative_by_construction: ClassVar[bool] = False
    nested_base: ClassVar[bool] = True

    def __init__(
        self, description: RobotDescription, base: CompensationModel, residual: PennModel, name: str | None = None
    ) -> None:
        if not isinstance(residual, PennModel):
            raise ShapeError(f"a PENN residual needs a PENN network, got a {type(residual).__name__}")
        if isinstance(base, NeuralModel | PennResidualModel):
            raise ShapeError(f"a PENN residual sits on a physical model, not on a neural one ({base.kind})")
        super().__init__(description, name or f"{base.name} + PENN residual")
        self.base = base
        self.residual = residual
        base_kernel = base.tick_kernel()
        self._kernel = (
            TickKernel(penn_residual_torque, pack_penn_residual(base_kernel.parameters, residual.packed_parameters))
            if base_kernel is not None and base_kernel.function is linear_torque
            else None
        )

    def torque(self, q: FloatArray) -> np.ndarray:
        """Torque (Nm, (4,)) at one ``q`` (rad, 4 values): the base's torque plus the network's gradient.

        Raises:
            ShapeError: ``q`` is not 4 numbers.
        """
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (N_JOINTS,):
            raise ShapeError(f"expected 4 joint angles, got shape {q.shape}")
        return self.base.torque(q) + self.residual.torque(q)

    def torque_batch(self, q: FloatArray) -> FloatArray:
        """Torque (Nm, (N, 4)) at N configurations (rad, (N, 4))."""
        return self.base.torque_batch(q) + self.residual.torque_batch(q)

    def predict(self, q: FloatArray, direction: FloatArray | None = None) -> FloatArray:
        """What the sensors would read (Nm, (N, 4)): the base's prediction (its sensor effects) plus the network."""
        return self.base.predict(q, direction) + self.residual.torque_batch(q)

    def path_travel_rad(self) -> FloatArray | None:
        """The base's (its sensor effects are the base's)."""
        return self.base.path_travel_rad()

    def reading_error_tracker(self) -> ReadingErrorTracker | None:
        """The base's: the network learns torque, not what the sensors read."""
        return self.base.reading_error_tracker()

    def potential_batch(self, q: FloatArray) -> FloatArray:
        """The learned part's potential ``V_nn`` (J, up to a constant; (N,)) at N configurations."""
        return self.residual.potential_batch(q)

    def tick_kernel(self) -> TickKernel | None:
        """:func:`penn_residual_torque` on a base with the compiled linear torque; None otherwise."""
        return self._kernel

    def parameters(self) -> dict[str, Any]:
        return {
            "base": {"kind": self.base.kind, "name": self.base.name, "parameters": self.base.parameters()},
            "residual": self.residual.parameters(),
        }

    @classmethod
    def from_parameters(
        cls, description: RobotDescription, parameters: Mapping[str, Any], name: str | None = None
    ) -> PennResidualModel:
        """Rebuild the model of a model file's ``parameters``, whose ``base`` the model-file layer has
        already built (:func:`daror_runtime.models.files.model_from_parameters`).

        Raises:
            ModelFileError: a field missing or unknown, a neural base, or network parameters that do
                not fit a PENN; one line naming the field.
        """
        unknown = sorted(set(parameters) - {"base", "residual"})
        if unknown:
            raise ModelFileError(f"parameters.{unknown[0]}: unknown field (model kind {cls.kind})")
        base = parameters.get("base")
        if not isinstance(base, CompensationModel):
            raise ModelFileError(
                f"parameters.base: expected the base model, built by the model-file layer (model kind {cls.kind})"
            )
        if isinstance(base, NeuralModel | PennResidualModel):
            raise ModelFileError(
                f"parameters.base.kind: {base.kind!r}; a PENN residual sits on a physical model, not a neural one"
            )
        residual = parameters.get("residual")
        if not isinstance(residual, Mapping):
            raise ModelFileError(f"parameters.residual: expected a PENN's parameters (model kind {cls.kind})")
        try:
            network = PennModel.from_parameters(description, residual)
        except ModelFileError as exc:
            raise ModelFileError(_prefixed(exc, "parameters.residual")) from None
        if not isinstance(network, PennModel):  # PennModel.from_parameters builds one; this narrows the type
            raise ModelFileError(f"parameters.residual: not a PENN (model kind {cls.kind})")
        return cls(description, base, network, name)
