"""What ``daror can check`` expects of each node, from the robot file: its identity, and its stored calibration.

The identity a node must report (0x1018 sub 1 vendor, sub 2 product): the robot file's
``identity:`` of the node where it gives one, else the ``[DeviceInfo]`` of the node's EDS
(``VendorNumber``, ``ProductNumber``), which the scan matches nodes with too.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from daror_runtime.commissioning.robot_file import CALIBRATION_KEYS, read_calibrations
from hal.errors import HalConfigError

__all__ = ["calibration_rows", "expected_identity"]


def expected_identity(config: Any) -> Callable[[int], dict[str, int | None]]:
    """Node id -> ``{"vendor_id": ..., "product_code": ...}`` it must report (None: not compared).

    Raises:
        HalConfigError: an EDS the file names cannot be read or has no identity in ``[DeviceInfo]``.
    """
    from hal.commissioning import eds_identities

    nodes = {node.node_id: node for node in getattr(config, "nodes", None) or []}
    expected: dict[int, dict[str, int | None]] = {}
    for node_id, (vendor, product) in eds_identities(config).items():
        identity = getattr(nodes.get(node_id), "identity", None)
        if identity is not None:  # the robot file's own, over the EDS's
            vendor, product = identity.vendor_id, identity.product_code
        expected[node_id] = {"vendor_id": vendor, "product_code": product}
    return lambda node_id: expected[node_id]


def calibration_rows(path: Path) -> Callable[[int], list[tuple[str, str]]]:
    """Node id -> ``(item, value)`` rows of its stored calibration (none for a file without ``nodes:``)."""
    try:
        stored = read_calibrations(path)
    except HalConfigError:
        stored = {}  # the short form (node_ids, eds): no calibration to show

    def rows(node_id: int) -> list[tuple[str, str]]:
        calibration = stored.get(node_id, {})
        if not calibration:
            return [("calibration", "none stored (daror can zero, daror can tare)")]
        return [(f"calibration {key}", str(calibration[key])) for key in CALIBRATION_KEYS if key in calibration]

    return rows
