"""The commissioning commands' door into the CANopen backend (``daror can scan|check|zero|tare``).

The runtime names a backend's module nowhere but through the registry (:mod:`hal.interface`,
``tests/test_boundaries.py``): the CANopen package needs python-can and canopen, which a core
install does not have. This facade imports :mod:`hal.canopen` when a function is called, and says
which extra is missing when it is not installed (one line, exit 2), as the registry does.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

from hal.errors import BackendUnavailableError
from hal.interface import Hal

__all__ = ["bus_probe", "eds_identities", "scan"]


def _canopen(module: str) -> Any:
    """``hal.canopen.<module>``, imported now.

    Raises:
        BackendUnavailableError: python-can or canopen is not installed (``pip install daror-runtime[can]``).
    """
    try:
        return importlib.import_module(f"hal.canopen.{module}")
    except ModuleNotFoundError as exc:
        if exc.name in ("can", "canopen"):
            raise BackendUnavailableError(
                f"the CAN commissioning commands need the Python package {exc.name!r}: pip install daror-runtime[can]"
            ) from None
        raise


def bus_probe(hal: Hal) -> Any:
    """The drives' own words through the master of ``hal``, an open CANopen backend (:class:`hal.canopen.commissioning.BusProbe`).

    Raises:
        HalError: ``hal`` is not a CANopen backend, or not open.
    """
    return _canopen("commissioning").BusProbe(hal)


def eds_identities(config: Any) -> dict[int, tuple[int, int]]:
    """Node id -> ``(vendor id, product code)`` the EDS of that node declares in ``[DeviceInfo]``.

    Raises:
        HalConfigError: an EDS cannot be read or declares no identity.
    """
    commissioning = _canopen("commissioning")
    return {node: commissioning.identity_of(path) for node, path in commissioning.eds_of(config).items()}


def scan(
    config: Any,
    interface: str,
    channel: str,
    bitrate: int,
    listen_s: float,
    eds_sources: list[Path],
) -> Any:
    """Scan a bus (:func:`hal.canopen.scan.scan_bus`): a ``can-sim`` ``config`` scans its simulated drives.

    ``eds_sources`` empty and a ``config`` given: the folders of the EDS files it names. Returns the
    :class:`hal.canopen.scan.ScanResult`, its ``eds_problems`` filled.

    Raises:
        HalConfigError: an EDS folder that does not exist.
        HalError: the interface cannot be opened, or the bus refused a frame.
    """
    import dataclasses

    found = _canopen("scan")
    commissioning = _canopen("commissioning")
    if not eds_sources and config is not None:
        eds_sources = sorted({path.parent for path in commissioning.eds_of(config).values()})
    catalogue, problems = found.eds_catalogue(eds_sources)
    timeout_s = found.sdo_probe_timeout_s(bitrate)

    def run(bus: Any) -> Any:
        try:
            return found.scan_bus(bus, catalogue, listen_s, timeout_s)
        finally:
            bus.shutdown()

    if config is not None and config.backend == "can-sim":
        with found.simulated_drives(config) as sim_channel:
            result = run(found.open_bus("virtual", sim_channel, bitrate))
    else:
        result = run(found.open_bus(interface, channel, bitrate))
    return dataclasses.replace(result, eds_problems=tuple(problems))
