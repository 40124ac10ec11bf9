"""The neural compensation models PENN and NNN (thesis Sec. 3.1.1, 3.2.2, 4.2.3-4.2.4): running a trained network.

This module runs a trained network; it never trains one and imports no JAX (training lives in
``daror_runtime.neural``, the optional extra ``nn``), so a model file of a neural model loads and
runs on the base install.

**The network** (Eq. 3.5-3.6, :class:`NetworkSpec`): the features of ``q`` (rad), either ``q``
itself (4 inputs) or ``[sin q, cos q]`` (Eq. 4.28, 8 inputs), are standardised,
``x = (f(q) - input_offset) / input_scale``; then ``layers`` hidden layers of ``width`` units,
``h_l = act(h_{l-1} W_l + b_l)``, and a linear output layer ``y = h_L W_out + b_out``.

* **PENN** (Sec. 3.2.2): one output, the potential ``V(q) = output_scale * y`` (J); the torque is
  its gradient, ``tau = dV/dq`` (Nm, Eq. 3.17), by backpropagation through the layers and, for the
  sin/cos features, the chain rule of Eq. 4.29 (``d sin q / dq = cos q``, ``d cos q / dq = -sin
  q``). Conservative by construction.
* **NNN** (Sec. 3.1.1, 4.2.4): four outputs, the torques ``tau_j = output_scale_j * y_j`` (Nm).
  Nothing makes it conservative (Table IV).

The offsets and scales are what training used to condition the problem; they are part of the
model, so ``torque(q)`` is exactly what was trained.

**Weights layout** (:func:`weight_layout`): one flat float64 vector, layer by layer from the
input, each layer's weight matrix then its bias: ``W1, b1, W2, b2, ..., Wout, bout``. ``W_l`` has
shape ``(inputs of the layer, units of the layer)`` stored row-major, so that ``a = h W + b``:
entry ``W_l[i, j]`` (input ``i`` to unit ``j``) is at ``offset_l + i * units + j``. The same layout
is used by the training code (``daror_runtime.neural.networks``) and by the model files.

**Packed vector** (:func:`pack_network`): what the compiled kernel reads, a header of
:data:`HEADER_SIZE` numbers (:data:`LAYOUT_TAG`, model, activation, inputs, layers, width, number
of inputs, number of outputs, scratch size, total length; see the ``H_*`` indices), then
``input_offset``, ``input_scale``, ``output_scale`` and the weights.

**Kernels**: :func:`network_torque_into` (one ``q``, writes the torque into ``out``, uses a scratch
array the caller owns, allocates nothing) is what :meth:`NeuralModel.torque` runs;
:func:`network_torque` (``function(q, parameters, out)``) is the :class:`TickKernel` form, which
any compiled caller can run from the packed vector alone. It allocates its scratch (one array of
``parameters[H_SCRATCH]`` floats) on every call, since the :class:`TickKernel` signature has no
place for one. :func:`network_torque_batch` is numpy, for N configurations.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from numba import njit, types
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from daror_runtime.errors import ModelFileError
from daror_runtime.models.base import CompensationModel, TickKernel
from hal.errors import ShapeError
from hal.kernels import SAMPLE_VECTOR, entry_point
from hal.robot import N_JOINTS, FloatArray, RobotDescription, as_configurations

__all__ = [
    "ACTIVATIONS",
    "HEADER_SIZE",
    "INPUT_KINDS",
    "MAX_NETWORK_WEIGHTS",
    "Network",
    "NetworkParameters",
    "NetworkSpec",
    "NeuralModel",
    "NnnModel",
    "PennModel",
    "network_torque",
    "network_torque_batch",
    "network_torque_into",
    "pack_network",
    "penn_potential_batch",
    "weight_layout",
]

#: Activation functions of the hidden layers, in the order of their codes in the packed vector.
ACTIVATIONS: tuple[str, ...] = ("tanh", "sigmoid", "relu", "softplus")
#: Network inputs: ``q`` (4 features) or ``sincos`` (``[sin q, cos q]``, Eq. 4.28, 8 features).
INPUT_KINDS: tuple[str, ...] = ("q", "sincos")
#: The models, in the order of their codes in the packed vector.
NETWORK_MODELS: tuple[str, ...] = ("penn", "nnn")

MAX_LAYERS = 32
MAX_WIDTH = 256
#: Most weights (and biases) a network may have. A million is ~30 MB of model file (half of
#: ``hal.files.MODEL_MAX_BYTES``) and about a millisecond a torque, the whole tick; the thesis's
#: largest networks (21 x 25) have 13,251 (PENN) and 13,329 (NNN), the default PENN 1,377. Above
#: this a network is refused as absurd.
MAX_NETWORK_WEIGHTS = 1_000_000
#: Smallest input scale a model may hold: a smaller one would turn rounding noise into large inputs
#: (the fitter floors a feature's spread at 0.05, ``daror_runtime.neural.training``).
MIN_INPUT_SCALE = 1e-6

# --- the packed vector's header ---------------------------------------------------------------

#: First number of every packed vector: identifies this layout (version 1) to the kernel.
LAYOUT_TAG = 7.140601
H_TAG, H_MODEL, H_ACTIVATION, H_INPUTS, H_LAYERS, H_WIDTH, H_N_IN, H_N_OUT, H_SCRATCH, H_LENGTH = range(10)
HEADER_SIZE = 10

_PENN, _NNN = 0, 1
_TANH, _SIGMOID, _RELU, _SOFTPLUS = 0, 1, 2, 3
_Q, _SINCOS = 0, 1


class NetworkSpec(BaseModel):
    """The shape of a network: what it computes, how deep and wide, which activation and inputs.

    Frozen; every field strict (``"2"`` is not a number of layers). Raises a pydantic
    ``ValidationError`` for a value out of range or a network of more than
    :data:`MAX_NETWORK_WEIGHTS` weights.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    model: Literal["penn", "nnn"] = Field(description="penn: output V (J), torque dV/dq; nnn: output the 4 torques")
    layers: int = Field(ge=1, le=MAX_LAYERS, description="hidden layers")
    width: int = Field(ge=1, le=MAX_WIDTH, description="units per hidden layer")
    activation: Literal["tanh", "sigmoid", "relu", "softplus"] = Field(description="of the hidden layers")
    inputs: Literal["q", "sincos"] = Field(description="q, or [sin q, cos q] (Eq. 4.28)")

    @model_validator(mode="after")
    def _not_absurd(self) -> NetworkSpec:
        if self.n_weights > MAX_NETWORK_WEIGHTS:
            raise ValueError(
                f"{self.layers} layers of {self.width} units make {self.n_weights:,} weights; "
                f"expected at most {MAX_NETWORK_WEIGHTS:,}"
            )
        return self

    @property
    def n_inputs(self) -> int:
        return 2 * N_JOINTS if self.inputs == "sincos" else N_JOINTS

    @property
    def n_outputs(self) -> int:
        return 1 if self.model == "penn" else N_JOINTS

    @property
    def layer_sizes(self) -> tuple[int, ...]:
        """Units of every layer, input first, output last: ``(8, 32, 32, 1)`` for a 2 x 32 sincos PENN."""
        return (self.n_inputs, *([self.width] * self.layers), self.n_outputs)

    @property
    def n_weights(self) -> int:
        """Length of the flat weight vector (weights and biases of every layer)."""
        sizes = self.layer_sizes
        return sum(m * n + n for m, n in itertools.pairwise(sizes))

    @property
    def scratch_size(self) -> int:
        """Floats of scratch :func:`network_torque_into` needs: the features, two layer buffers, the
        activation derivatives of every hidden layer."""
        return self.n_inputs + 2 * max(self.width, self.n_inputs) + self.layers * self.width

    def describe(self) -> str:
        """``PENN 2 x 32 tanh, sin/cos inputs``."""
        inputs = "sin/cos inputs" if self.inputs == "sincos" else "q inputs"
        return f"{self.model.upper()} {self.layers} x {self.width} {self.activation}, {inputs}"


@dataclass(frozen=True)
class LayerSlice:
    """Where one layer's weights and bias are in the flat weight vector (``W`` row-major, ``(n_in, n_out)``)."""

    weights: slice
    bias: slice
    n_in: int
    n_out: int


def weight_layout(spec: NetworkSpec) -> tuple[LayerSlice, ...]:
    """The layers of ``spec`` in the flat weight vector, input layer first, the output layer last."""
    out = []
    offset = 0
    sizes = spec.layer_sizes
    for m, n in itertools.pairwise(sizes):
        out.append(LayerSlice(slice(offset, offset + m * n), slice(offset + m * n, offset + m * n + n), m, n))
        offset += m * n + n
    return tuple(out)


@dataclass(frozen=True, eq=False)
class Network:
    """A trained network: its spec, the input standardisation, the output scale and the weights.

    Arrays are float64, read-only. Use :meth:`checked` to build one from untrusted numbers.
    """

    spec: NetworkSpec
    input_offset: np.ndarray  # (n_inputs,), units of the features (rad, or 1 for sin/cos)
    input_scale: np.ndarray  # (n_inputs,), > 0, same units
    output_scale: np.ndarray  # (n_outputs,): J for a PENN's V, Nm for an NNN's torques
    weights: np.ndarray  # (n_weights,), the layout of weight_layout()

    @classmethod
    def checked(
        cls,
        spec: NetworkSpec,
        input_offset: FloatArray,
        input_scale: FloatArray,
        output_scale: FloatArray,
        weights: FloatArray,
    ) -> Network:
        """A network from arrays, checked: shapes that fit ``spec``, finite numbers, positive scales.

        Raises:
            ShapeError: an array of the wrong length (the message names it).
            ValueError: a number that is not finite, or a scale that is not positive enough.
        """
        arrays = {}
        expected = {
            "input_offset": spec.n_inputs,
            "input_scale": spec.n_inputs,
            "output_scale": spec.n_outputs,
            "weights": spec.n_weights,
        }
        given = {
            "input_offset": input_offset,
            "input_scale": input_scale,
            "output_scale": output_scale,
            "weights": weights,
        }
        for name, length in expected.items():
            array = np.array(given[name], dtype=np.float64).reshape(-1)  # a copy: nobody else holds it
            if array.shape != (length,):
                raise ShapeError(f"{name}: {array.size} values; the network {spec.describe()} has {length}")
            if not np.all(np.isfinite(array)):
                raise ValueError(f"{name}: not every value is a finite number")
            array.flags.writeable = False
            arrays[name] = array
        if np.any(arrays["input_scale"] < MIN_INPUT_SCALE):
            raise ValueError(f"input_scale: every scale must be at least {MIN_INPUT_SCALE:g}")
        if np.any(arrays["output_scale"] <= 0.0):
            raise ValueError("output_scale: every scale must be positive")
        return cls(spec, **arrays)


def pack_network(network: Network) -> np.ndarray:
    """The packed vector the kernels read: header, input offset and scale, output scale, weights (read-only)."""
    spec = network.spec
    header = np.zeros(HEADER_SIZE)
    header[H_TAG] = LAYOUT_TAG
    header[H_MODEL] = NETWORK_MODELS.index(spec.model)
    header[H_ACTIVATION] = ACTIVATIONS.index(spec.activation)
    header[H_INPUTS] = INPUT_KINDS.index(spec.inputs)
    header[H_LAYERS] = spec.layers
    header[H_WIDTH] = spec.width
    header[H_N_IN] = spec.n_inputs
    header[H_N_OUT] = spec.n_outputs
    header[H_SCRATCH] = spec.scratch_size
    packed = np.concatenate([header, network.input_offset, network.input_scale, network.output_scale, network.weights])
    packed[H_LENGTH] = packed.size
    packed.flags.writeable = False
    return packed


# --- compiled kernels --------------------------------------------------------------------------


@njit(cache=True)
def _activate(code: int, a: np.ndarray, derivative: np.ndarray) -> None:  # pragma: no cover - compiled
    """``a <- act(a)`` in place and ``derivative <- act'(a)``, elementwise (the hidden layers' activation).

    The formulas are the stable ones (no overflow for any finite ``a``), and the derivatives those
    JAX's automatic differentiation gives (ReLU: 0 at 0).
    """
    n = a.shape[0]
    if code == _TANH:
        for j in range(n):
            t = math.tanh(a[j])
            a[j] = t
            derivative[j] = 1.0 - t * t
    elif code == _SIGMOID:
        for j in range(n):
            v = a[j]
            if v >= 0.0:
                s = 1.0 / (1.0 + math.exp(-v))
            else:
                e = math.exp(v)
                s = e / (1.0 + e)
            a[j] = s
            derivative[j] = s * (1.0 - s)
    elif code == _RELU:
        for j in range(n):
            if a[j] > 0.0:
                derivative[j] = 1.0
            else:
                a[j] = 0.0
                derivative[j] = 0.0
    else:  # softplus: log(1 + e^a), derivative the sigmoid
        for j in range(n):
            v = a[j]
            e = math.exp(-abs(v))
            s = 1.0 / (1.0 + e) if v >= 0.0 else e / (1.0 + e)
            a[j] = max(v, 0.0) + math.log1p(e)
            derivative[j] = s


@njit(cache=True)
def _checked_scratch_size(p: np.ndarray) -> int:  # pragma: no cover - compiled
    """The scratch size the packed network ``p`` needs, after checking its header against its length.

    Every offset the kernel computes comes from the header; a vector whose header does not
    describe exactly its own length (or is not of this layout) is refused before anything past the
    header is read.

    Raises:
        ValueError: not a packed network vector of this layout, or a header inconsistent with it.
    """
    if p.shape[0] < HEADER_SIZE or p[H_TAG] != LAYOUT_TAG:
        raise ValueError("not a packed neural network vector (layout 1)")
    model, activation, inputs = p[H_MODEL], p[H_ACTIVATION], p[H_INPUTS]
    n_layers, width, n_in, n_out = p[H_LAYERS], p[H_WIDTH], p[H_N_IN], p[H_N_OUT]
    ok = model in (0.0, 1.0) and activation in (0.0, 1.0, 2.0, 3.0) and inputs in (0.0, 1.0)
    ok = ok and 1.0 <= n_layers <= MAX_LAYERS and 1.0 <= width <= MAX_WIDTH
    ok = ok and n_in == (8.0 if inputs == 1.0 else 4.0) and n_out == (1.0 if model == 0.0 else 4.0)
    if not ok:
        raise ValueError("packed neural network vector: header out of range")
    n_layers_i, width_i, n_in_i, n_out_i = int(n_layers), int(width), int(n_in), int(n_out)
    n_weights = (
        n_in_i * width_i + width_i + (n_layers_i - 1) * (width_i * width_i + width_i) + width_i * n_out_i + n_out_i
    )
    scratch = n_in_i + 2 * max(width_i, n_in_i) + n_layers_i * width_i
    if (
        p[H_LENGTH] != p.shape[0]
        or p.shape[0] != HEADER_SIZE + 2 * n_in_i + n_out_i + n_weights
        or p[H_SCRATCH] != scratch
    ):
        raise ValueError("packed neural network vector: header does not match its length")
    return scratch


# The two layer kernels take their weights as a slice of the packed vector and index it only with
# loop counters: numba then knows every index is non-negative and leaves out its negative-index
# wrap-around, which is what lets LLVM vectorise the inner loops (an index ``offset + j`` with a
# run-time ``offset`` made a 2 x 64 network 4x slower).


@njit(cache=True)
def _layer_forward(
    w: np.ndarray, b: np.ndarray, h: np.ndarray, n_in: int, width: int, a: np.ndarray
) -> None:  # pragma: no cover - compiled
    """``a = h W + b`` of a layer with ``W`` (``n_in`` x ``width``, row-major) in ``w`` and ``b`` in ``b``.

    Row by row (``a += h_i W[i, :]``): the inner loop runs along contiguous memory and vectorises.
    """
    for j in range(width):
        a[j] = b[j]
    for i in range(n_in):
        hi = h[i]
        row = i * width
        for j in range(width):
            a[j] += hi * w[row + j]


# ``reassoc``: the dot products may be summed in vector lanes (several times faster for 64 units);
# the sum then differs from a sequential one in its last bits only, the same way on every call.
@njit(cache=True, fastmath={"reassoc"})
def _layer_backward(
    w: np.ndarray, g: np.ndarray, n_in: int, width: int, d: np.ndarray
) -> None:  # pragma: no cover - compiled
    """``d = W g`` (``d_i = sum_j W[i, j] g_j``) of a layer with ``W`` (``n_in`` x ``width``, row-major) in ``w``."""
    for i in range(n_in):
        acc = 0.0
        row = i * width
        for j in range(width):
            acc += w[row + j] * g[j]
        d[i] = acc


@njit(cache=True)
def network_torque_into(
    q: np.ndarray, p: np.ndarray, scratch: np.ndarray, out: np.ndarray
) -> None:  # pragma: no cover - compiled
    """Torque (Nm, 4) at one ``q`` (rad, 4) of the network packed in ``p`` (:func:`pack_network`), into ``out``.

    ``scratch``: at least ``p[H_SCRATCH]`` floats the kernel may overwrite (the caller's; nothing is
    allocated). A PENN's torque is ``dV/dq`` by backpropagation through the hidden layers, then
    the chain rule through the standardisation and the sin/cos features (Eq. 4.29).

    Raises:
        ValueError: ``p`` is not a packed network vector of this layout, or ``scratch`` is too small
            (checked before anything is read past the header).
    """
    if scratch.shape[0] < _checked_scratch_size(p) or q.shape[0] != 4 or out.shape[0] != 4:
        raise ValueError("network kernel: scratch too small, or q or out not of 4 values")
    model = int(p[H_MODEL])
    activation = int(p[H_ACTIVATION])
    n_layers = int(p[H_LAYERS])
    width = int(p[H_WIDTH])
    n_in = int(p[H_N_IN])
    n_out = int(p[H_N_OUT])
    in_offset = HEADER_SIZE
    in_scale = in_offset + n_in
    out_scale = in_scale + n_in
    first = out_scale + n_out  # the first hidden layer's weights
    hidden = n_in * width + width  # the first hidden layer's weights and bias
    square = width * width + width  # every further hidden layer's
    buffer = max(width, n_in)
    x = scratch[0:n_in]
    even = scratch[n_in : n_in + buffer]  # hidden layers 0, 2, 4, ... write here
    odd = scratch[n_in + buffer : n_in + 2 * buffer]  # and 1, 3, 5, ... here
    slopes = scratch[n_in + 2 * buffer : n_in + 2 * buffer + n_layers * width]

    # features, standardised
    if int(p[H_INPUTS]) == _SINCOS:
        for j in range(4):
            x[j] = (math.sin(q[j]) - p[in_offset + j]) / p[in_scale + j]
            x[4 + j] = (math.cos(q[j]) - p[in_offset + 4 + j]) / p[in_scale + 4 + j]
    else:
        for j in range(4):
            x[j] = (q[j] - p[in_offset + j]) / p[in_scale + j]

    # forward through the hidden layers, keeping every act'(a)
    _layer_forward(p[first : first + n_in * width], p[first + n_in * width : first + hidden], x, n_in, width, even)
    _activate(activation, even[:width], slopes[0:width])
    for layer in range(1, n_layers):
        offset = first + hidden + (layer - 1) * square
        w = p[offset : offset + width * width]
        b = p[offset + width * width : offset + square]
        if layer % 2 == 1:
            _layer_forward(w, b, even, width, width, odd)
            _activate(activation, odd[:width], slopes[layer * width : (layer + 1) * width])
        else:
            _layer_forward(w, b, odd, width, width, even)
            _activate(activation, even[:width], slopes[layer * width : (layer + 1) * width])
    top = n_layers - 1
    last = even if top % 2 == 0 else odd  # the last hidden layer's output
    output = first + hidden + top * square  # the output layer's weights (width x n_out)

    w_out = p[output : output + width * n_out]
    if model == _NNN:
        b_out = p[output + width * n_out : output + width * n_out + n_out]
        for k in range(n_out):
            acc = b_out[k]
            for i in range(width):
                acc += last[i] * w_out[i * n_out + k]
            out[k] = p[out_scale + k] * acc
        return

    # PENN: g_l = dy/da_l, from the last hidden layer down: g_{l-1} = (W_l g_l) * act'(a_{l-1}).
    # g_l is kept in the buffer layer l + 1 would use (h_l is no longer needed once act' is kept),
    # so g_0 always ends in ``odd``.
    g = odd if top % 2 == 0 else even
    for j in range(width):
        g[j] = w_out[j] * slopes[top * width + j]  # Wout[j, 0] * act'(a_j)
    for layer in range(top, 0, -1):
        offset = first + hidden + (layer - 1) * square
        source = odd if layer % 2 == 0 else even
        target = even if layer % 2 == 0 else odd
        _layer_backward(p[offset : offset + width * width], source, width, width, target)
        below = slopes[(layer - 1) * width : layer * width]
        for i in range(width):
            target[i] *= below[i]
    # dy/dx = W1 g_0 (into the even buffer, free now), then dV/dq through the standardisation and
    # the features
    dx = even
    _layer_backward(p[first : first + n_in * width], odd, n_in, width, dx)
    scale = p[out_scale]
    if int(p[H_INPUTS]) == _SINCOS:
        for j in range(4):
            out[j] = scale * (
                dx[j] * math.cos(q[j]) / p[in_scale + j] - dx[4 + j] * math.sin(q[j]) / p[in_scale + 4 + j]
            )
    else:
        for j in range(4):
            out[j] = scale * dx[j] / p[in_scale + j]


@njit(cache=True)
def network_torque(q: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """The :class:`TickKernel` function of the neural models: :func:`network_torque_into` with its own scratch.

    Reads everything from the packed vector ``p``; allocates one scratch array of ``p[H_SCRATCH]``
    floats per call (the :class:`TickKernel` signature has no place for a caller's scratch).

    Raises:
        ValueError: ``p`` is not a packed network vector of this layout.
    """
    scratch = np.empty(_checked_scratch_size(p))
    network_torque_into(q, p, scratch, out)


#: The types :meth:`NeuralModel.torque` resolves its entry point for: any float64 vector ``q``,
#: the model's own read-only packed vector, its scratch and a fresh ``out``.
_TORQUE_SIGNATURE = (
    SAMPLE_VECTOR,
    types.Array(types.float64, 1, "C", readonly=True),
    types.Array(types.float64, 1, "C"),
    types.Array(types.float64, 1, "C"),
)


# --- numpy, N configurations -------------------------------------------------------------------


def _activation_and_slope(name: str, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``act(a)`` and ``act'(a)`` elementwise (the formulas of :func:`_activate`)."""
    if name == "tanh":
        h = np.tanh(a)
        return h, 1.0 - h * h
    if name == "relu":
        positive = a > 0.0
        return np.where(positive, a, 0.0), positive.astype(np.float64)
    e = np.exp(-np.abs(a))
    sigmoid = np.where(a >= 0.0, 1.0 / (1.0 + e), e / (1.0 + e))
    if name == "sigmoid":
        return sigmoid, sigmoid * (1.0 - sigmoid)
    return np.maximum(a, 0.0) + np.log1p(e), sigmoid  # softplus


def _features(network: Network, q: FloatArray) -> np.ndarray:
    """Standardised inputs ``x`` (N, n_inputs) of configurations ``q`` (N, 4)."""
    raw = np.concatenate([np.sin(q), np.cos(q)], axis=1) if network.spec.inputs == "sincos" else q
    return (raw - network.input_offset) / network.input_scale


def _forward(network: Network, x: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Output ``y`` (N, n_outputs) before the output scale, and every hidden layer's ``act'`` (N, width)."""
    layout = weight_layout(network.spec)
    w = network.weights
    h = x
    slopes = []
    for layer in layout[:-1]:
        a = h @ w[layer.weights].reshape(layer.n_in, layer.n_out) + w[layer.bias]
        h, slope = _activation_and_slope(network.spec.activation, a)
        slopes.append(slope)
    out = layout[-1]
    return h @ w[out.weights].reshape(out.n_in, out.n_out) + w[out.bias], slopes


def network_torque_batch(network: Network, q: FloatArray) -> np.ndarray:
    """Torque (Nm, (N, 4)) at N configurations ``q`` (rad, (N, 4)); the same arithmetic as the kernel, vectorised.

    Raises:
        ShapeError: ``q`` is not (N, 4) (or (4,)).
    """
    q = as_configurations(q)
    x = _features(network, q)
    y, slopes = _forward(network, x)
    if network.spec.model == "nnn":
        return y * network.output_scale
    layout = weight_layout(network.spec)
    w = network.weights
    out = layout[-1]
    g = w[out.weights].reshape(1, -1) * slopes[-1]  # dy/da of the last hidden layer
    for layer, slope in zip(reversed(layout[1:-1]), reversed(slopes[:-1]), strict=True):
        g = (g @ w[layer.weights].reshape(layer.n_in, layer.n_out).T) * slope
    first = layout[0]
    dx = (g @ w[first.weights].reshape(first.n_in, first.n_out).T) / network.input_scale
    dq = dx[:, :N_JOINTS] * np.cos(q) - dx[:, N_JOINTS:] * np.sin(q) if network.spec.inputs == "sincos" else dx
    return network.output_scale[0] * dq


def penn_potential_batch(network: Network, q: FloatArray) -> np.ndarray:
    """A PENN's potential ``V`` (J, (N,)) at N configurations; its gradient is :func:`network_torque_batch`.

    Raises:
        ShapeError: ``q`` is not (N, 4), or the network is not a PENN.
    """
    if network.spec.model != "penn":
        raise ShapeError(f"{network.spec.describe()} has no potential: it outputs torques")
    q = as_configurations(q)
    y, _ = _forward(network, _features(network, q))
    return network.output_scale[0] * y[:, 0]


# --- model files -------------------------------------------------------------------------------

FiniteFloat = Annotated[float, Field(strict=False, allow_inf_nan=False)]


class NetworkParameters(BaseModel):
    """The parameters of a neural model as stored in a model file (``parameters`` of docs/data.md).

    ``layout_version`` 1 is the weights layout of this module's docstring. Numbers are finite,
    lengths fit the spec, scales positive (checked again when the :class:`Network` is built).
    """

    model_config = ConfigDict(extra="forbid")

    network: NetworkSpec
    layout_version: Literal[1]
    input_offset: list[FiniteFloat]
    input_scale: list[FiniteFloat]
    output_scale: list[FiniteFloat]
    weights: list[FiniteFloat]

    @model_validator(mode="before")
    @classmethod
    def _numbers_are_numbers(cls, data: Any) -> Any:
        """Refuse text or yes/no where numbers are meant (pydantic would read ``"0.5"`` or ``true`` as numbers)."""
        if isinstance(data, Mapping):
            for key in ("input_offset", "input_scale", "output_scale", "weights"):
                values = data.get(key)
                if isinstance(values, list):
                    for i, v in enumerate(values):
                        if isinstance(v, bool) or not isinstance(v, int | float):
                            raise ValueError(f"{key}.{i}: expected a number; got {type(v).__name__} {str(v)[:20]!r}")
        return data

    @model_validator(mode="after")
    def _fits_the_spec(self) -> NetworkParameters:
        spec = self.network
        for name, length in (
            ("input_offset", spec.n_inputs),
            ("input_scale", spec.n_inputs),
            ("output_scale", spec.n_outputs),
            ("weights", spec.n_weights),
        ):
            got = len(getattr(self, name))
            if got != length:
                raise ValueError(f"{name}: {got:,} values; the network {spec.describe()} (layout 1) has {length:,}")
        if min(self.input_scale) < MIN_INPUT_SCALE:
            raise ValueError(f"input_scale: every scale must be at least {MIN_INPUT_SCALE:g}")
        if min(self.output_scale) <= 0.0:
            raise ValueError("output_scale: every scale must be positive")
        return self


# --- the models --------------------------------------------------------------------------------


class NeuralModel(CompensationModel):
    """A trained network as a compensation model (shared by :class:`PennModel` and :class:`NnnModel`).

    :meth:`torque` runs the compiled kernel with the model's own scratch: the kernel holds the
    GIL (not ``nogil``), so two threads never run it on the same model at once.

    Raises (constructor):
        ShapeError: the network is not of this kind (a PENN's weights given to an NNN), or its
            arrays do not fit its spec.
        ValueError: a number that is not finite, a scale that is not positive.
    """

    network_model: ClassVar[str]

    def __init__(self, description: RobotDescription, network: Network, name: str | None = None) -> None:
        if network.spec.model != self.network_model:
            raise ShapeError(
                f"a {self.display_name} model needs a {self.network_model} network, got {network.spec.model}"
            )
        super().__init__(description, name)
        # checked again (a copy): a Network built without Network.checked reaches no kernel unchecked
        self.network = Network.checked(
            network.spec, network.input_offset, network.input_scale, network.output_scale, network.weights
        )
        self._packed = pack_network(self.network)
        self._scratch = np.zeros(self.network.spec.scratch_size)
        # Resolved once here (loaded from numba's cache, or compiled), never in the tick.
        self._torque_entry = entry_point(network_torque_into, _TORQUE_SIGNATURE)

    @property
    def spec(self) -> NetworkSpec:
        return self.network.spec

    @property
    def packed_parameters(self) -> np.ndarray:
        """The read-only vector :func:`network_torque` reads (header and weights)."""
        return self._packed

    def torque(self, q: FloatArray) -> np.ndarray:
        """Torque (Nm, (4,)) at one configuration ``q`` (rad, 4 values), by the compiled kernel.

        The returned array is new (the caller may keep it); the kernel itself allocates nothing.

        Raises:
            ShapeError: ``q`` is not 4 numbers.
        """
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (N_JOINTS,):  # the entry point checks no shape: a short q would be read past its end
            raise ShapeError(f"expected 4 joint angles, got shape {q.shape}")
        out = np.empty(N_JOINTS)
        self._torque_entry(q, self._packed, self._scratch, out)
        return out

    def torque_batch(self, q: FloatArray) -> FloatArray:
        """Torque (Nm, (N, 4)) at N configurations (rad, (N, 4)), numpy."""
        return network_torque_batch(self.network, q)

    def tick_kernel(self) -> TickKernel:
        """:func:`network_torque` with this model's packed vector."""
        return TickKernel(network_torque, self._packed)

    def parameters(self) -> dict[str, Any]:
        n = self.network
        return {
            "network": n.spec.model_dump(),
            "layout_version": 1,
            "input_offset": [float(v) for v in n.input_offset],
            "input_scale": [float(v) for v in n.input_scale],
            "output_scale": [float(v) for v in n.output_scale],
            "weights": [float(v) for v in n.weights],
        }

    @classmethod
    def from_parameters(
        cls, description: RobotDescription, parameters: Mapping[str, Any], name: str | None = None
    ) -> NeuralModel:
        """Rebuild the model of a model file's ``parameters``.

        Raises:
            ModelFileError: a field missing or unknown, a spec out of range, weights that do not fit
                the spec's layout, a number that is not a finite number, a scale that is not
                positive, or the network of another kind; one line naming the field.
        """
        try:
            p = NetworkParameters.model_validate(parameters)
        except ValidationError as exc:
            problem = exc.errors()[0]
            field = ".".join(str(x) for x in problem["loc"])
            where = f"parameters.{field}: " if field else "parameters: "
            message = problem["msg"].removeprefix("Value error, ")
            raise ModelFileError(f"{where}{message} (model kind {cls.kind})") from None
        if p.network.model != cls.network_model:
            raise ModelFileError(
                f"parameters.network.model: {p.network.model!r} in a model of kind {cls.kind}; expected {cls.network_model!r}"
            )
        network = Network.checked(p.network, p.input_offset, p.input_scale, p.output_scale, p.weights)
        return cls(description, network, name)


class PennModel(NeuralModel):
    """Potential Energy Neural Network (Sec. 3.2.2): ``tau = dV/dq`` of a network ``V(q)``."""

    kind: ClassVar[str] = "penn"
    display_name: ClassVar[str] = "PENN"
    conservative_by_construction: ClassVar[bool] = True
    network_model: ClassVar[str] = "penn"

    def potential_batch(self, q: FloatArray) -> FloatArray:
        """Potential energy (J, up to a constant; (N,)) whose gradient is the torque."""
        return penn_potential_batch(self.network, q)


class NnnModel(NeuralModel):
    """Naive Neural Network (Sec. 3.1.1, 4.2.4): the network outputs the four torques."""

    kind: ClassVar[str] = "nnn"
    display_name: ClassVar[str] = "NNN"
    conservative_by_construction: ClassVar[bool] = False
    network_model: ClassVar[str] = "nnn"
