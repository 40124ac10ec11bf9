"""The networks of :mod:`daror_runtime.models.neural` in JAX: initialisation, forward pass, torque.

The weights are the same flat float64 vector (layout of
:func:`daror_runtime.models.neural.weight_layout`: ``W1, b1, ..., Wout, bout``, each ``W``
row-major ``(inputs, units)``), so what training produces is what the model file stores and the
numba kernel runs. The standardisation of the inputs and the output scale are a
:class:`Scaling` (the :class:`~daror_runtime.models.neural.Network` fields other than the weights).

A PENN's torque here is ``jax.grad`` of its potential with respect to ``q`` (Eq. 3.17), vmapped
over the points: automatic differentiation through the sin/cos features (Eq. 4.29) and the
standardisation, independent of the kernel's hand-written backpropagation (tests compare the two).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from daror_runtime.models.neural import Network, NetworkSpec, weight_layout

__all__ = [
    "Scaling",
    "activation_function",
    "init_weights",
    "network_output",
    "penn_potential",
    "torque",
]

Array = jax.Array


@dataclass(frozen=True, eq=False)
class Scaling:
    """How the network's inputs are standardised and its output scaled (float64 numpy arrays).

    ``x = (f(q) - input_offset) / input_scale``; a PENN's ``V = output_scale[0] * y`` (J), an NNN's
    ``tau_j = output_scale[j] * y_j`` (Nm).
    """

    input_offset: np.ndarray
    input_scale: np.ndarray
    output_scale: np.ndarray

    @classmethod
    def identity(cls, spec: NetworkSpec) -> Scaling:
        """No standardisation and no output scale (the thesis's networks)."""
        return cls(np.zeros(spec.n_inputs), np.ones(spec.n_inputs), np.ones(spec.n_outputs))

    def network(self, spec: NetworkSpec, weights: np.ndarray) -> Network:
        """The runnable :class:`~daror_runtime.models.neural.Network` of these weights (checked).

        Raises:
            ShapeError: the weights do not fit ``spec``.
            ValueError: a number that is not finite.
        """
        return Network.checked(spec, self.input_offset, self.input_scale, self.output_scale, weights)


def activation_function(name: str) -> Callable[[Array], Array]:
    """The hidden layers' activation, as JAX defines it (its derivatives are JAX's automatic ones)."""
    return {
        "tanh": jnp.tanh,
        "sigmoid": jax.nn.sigmoid,
        "relu": jax.nn.relu,
        "softplus": jax.nn.softplus,
    }[name]


def init_weights(spec: NetworkSpec, seed: int) -> np.ndarray:
    """Initial weights of ``spec`` from ``seed`` (an integer, 0 <= seed < 2**63): the same seed, the same weights.

    Weights normal with zero mean, standard deviation by Glorot (``sqrt(2 / (n_in + n_out))``) for
    tanh, sigmoid and softplus layers and for the linear output layer, by He (``sqrt(2 / n_in)``)
    for ReLU layers; biases zero. Drawn with numpy's PCG64 generator seeded with ``seed``, layer
    by layer in the order of the layout (numpy, not ``jax.random``: no program to compile for each
    shape, which cost 0.6 s a network shape).

    Raises:
        ValueError: a seed out of range.
    """
    if not 0 <= seed < 2**63:
        raise ValueError(f"seed {seed}: expected 0 <= seed < 2**63")
    generator = np.random.Generator(np.random.PCG64(seed))
    weights = np.zeros(spec.n_weights)
    layout = weight_layout(spec)
    for i, layer in enumerate(layout):
        hidden = i < len(layout) - 1
        if hidden and spec.activation == "relu":
            std = np.sqrt(2.0 / layer.n_in)  # He: keeps the variance through half-active units
        else:
            std = np.sqrt(2.0 / (layer.n_in + layer.n_out))  # Glorot
        weights[layer.weights] = std * generator.standard_normal(layer.n_in * layer.n_out)
    return weights


def _features(spec: NetworkSpec, scaling: Scaling | tuple[Array, Array, Array], q: Array) -> Array:
    offset, scale, _ = _arrays(scaling)
    raw = jnp.concatenate([jnp.sin(q), jnp.cos(q)], axis=-1) if spec.inputs == "sincos" else q
    return (raw - offset) / scale


def _arrays(scaling: Scaling | tuple[Array, Array, Array]) -> tuple[Array, Array, Array]:
    if isinstance(scaling, Scaling):
        return (
            jnp.asarray(scaling.input_offset),
            jnp.asarray(scaling.input_scale),
            jnp.asarray(scaling.output_scale),
        )
    return scaling


def network_output(spec: NetworkSpec, weights: Array, x: Array) -> Array:
    """The network's raw output ``y`` (before the output scale) for standardised inputs ``x`` (..., n_inputs)."""
    act = activation_function(spec.activation)
    layout = weight_layout(spec)
    h = x
    for layer in layout[:-1]:
        h = act(h @ weights[layer.weights].reshape(layer.n_in, layer.n_out) + weights[layer.bias])
    out = layout[-1]
    return h @ weights[out.weights].reshape(out.n_in, out.n_out) + weights[out.bias]


def penn_potential(spec: NetworkSpec, scaling: Scaling | tuple[Array, Array, Array], weights: Array, q: Array) -> Array:
    """A PENN's potential ``V`` (J) at one configuration ``q`` (rad, (4,)): a scalar."""
    _, _, output_scale = _arrays(scaling)
    return output_scale[0] * network_output(spec, weights, _features(spec, scaling, q))[0]


def torque(spec: NetworkSpec, scaling: Scaling | tuple[Array, Array, Array], weights: Array, q: Array) -> Array:
    """Torque (Nm, (N, 4)) at N configurations ``q`` (rad, (N, 4)).

    PENN: ``jax.grad`` of :func:`penn_potential` with respect to ``q``, vmapped over the points
    (Eq. 3.17, 4.29). NNN: the scaled outputs.
    """
    if spec.model == "penn":
        arrays = _arrays(scaling)
        gradient = jax.grad(lambda one: penn_potential(spec, arrays, weights, one))
        return jax.vmap(gradient)(q)
    _, _, output_scale = _arrays(scaling)
    return network_output(spec, weights, _features(spec, scaling, q)) * output_scale
