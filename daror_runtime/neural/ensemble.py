"""The mean of several trained networks, as one network (the residual presets' model).

``k`` networks of the same spec and the same standardisation (trained on the same data), each
``L`` hidden layers of ``w`` units, average to one network of ``L`` layers of ``k w`` units: the
first layer's units side by side, every later hidden layer block-diagonal (member ``i``'s units
see only member ``i``'s), the output weights stacked and divided by ``k``, the output bias the
mean. Its output is exactly the mean of the members' outputs, so a mean of PENNs is the PENN of
the mean potential (still conservative), and the numba kernel runs it unchanged. The price: ``k``
times the units in the tick (``k^2`` times the weights between hidden layers, mostly zeros).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from daror_runtime.models.neural import MAX_WIDTH, Network, NetworkSpec, weight_layout

__all__ = ["mean_network"]


def mean_network(members: Sequence[Network]) -> Network:
    """One network whose output is the mean of ``members``' outputs (the module docstring).

    Raises:
        ValueError: no member, members of different specs or standardisations, or ``k w`` above
            :data:`~daror_runtime.models.neural.MAX_WIDTH` units.
    """
    if not members:
        raise ValueError("mean_network needs at least one network")
    first = members[0]
    if len(members) == 1:
        return first
    spec, k = first.spec, len(members)
    for m in members[1:]:
        same_scaling = all(
            np.array_equal(getattr(m, a), getattr(first, a)) for a in ("input_offset", "input_scale", "output_scale")
        )
        if m.spec != spec or not same_scaling:
            raise ValueError("mean_network: the networks differ in spec or standardisation")
    width = k * spec.width
    if width > MAX_WIDTH:
        raise ValueError(
            f"the mean of {k} networks of {spec.width} units needs {width} units per layer; at most {MAX_WIDTH}"
        )
    merged = NetworkSpec(**(spec.model_dump() | {"width": width}))
    source, target = weight_layout(spec), weight_layout(merged)
    weights = np.zeros(merged.n_weights)
    for i, member in enumerate(members):
        units = slice(i * spec.width, (i + 1) * spec.width)
        for layer, (src, dst) in enumerate(zip(source, target, strict=True)):
            w = member.weights[src.weights].reshape(src.n_in, src.n_out)
            b = member.weights[src.bias]
            block = weights[dst.weights].reshape(dst.n_in, dst.n_out)  # a view: writes go into ``weights``
            bias = weights[dst.bias]
            if layer == 0:  # inputs to this member's units
                block[:, units] = w
                bias[units] = b
            elif layer < len(source) - 1:  # this member's units to its own units
                block[units, units] = w
                bias[units] = b
            else:  # this member's units to the outputs, averaged
                block[units, :] = w / k
                bias += b / k
    return Network.checked(merged, first.input_offset, first.input_scale, first.output_scale, weights)
