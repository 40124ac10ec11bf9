"""The runtime's errors: one tree, rooted in :class:`hal.errors.DarorError`.

::

    DarorError                      root (hal.errors)
    +-- InputError                  bad input from a person -> CLI exit code 2, nothing written
    |   +-- DescriptionError        robot description / scenario file (hal.errors)
    |   +-- DataError               a dataset file: missing column, NaN, degrees, empty, ...
    |   +-- ModelFileError          a model JSON file: unreadable, corrupted, wrong version
    |   +-- UnknownModelKindError   a model kind that is not registered
    |   +-- IdentifiabilityError    data too poor for the model (rank below the model's rank)
    |   +-- UsageError              a command-line value that makes no sense
    +-- ShapeError                  an array of the wrong shape reached an API (a bug; hal.errors)
    +-- ConfigurationError          the runtime was wired inconsistently (a bug or a bad configuration)
    +-- HalError                    the hardware or its simulation failed (hal.errors)
    |   +-- HalFaultError           a backend fault latched outside the tick (hal.interface)
    +-- ExtraMissingError           an optional extra (e.g. ``nn``) is needed but not installed
"""

from __future__ import annotations

from hal.errors import DarorError, DescriptionError, HalError, InputError, ShapeError

__all__ = [
    "ConfigurationError",
    "DarorError",
    "DataError",
    "DescriptionError",
    "ExtraMissingError",
    "HalError",
    "IdentifiabilityError",
    "InputError",
    "ModelFileError",
    "ShapeError",
    "UnknownModelKindError",
    "UsageError",
]


class DataError(InputError):
    """A dataset file does not hold what was expected; the message names file, line and column."""


class ModelFileError(InputError):
    """A model file cannot be read, is corrupted, or is of an unsupported format version."""


class UnknownModelKindError(InputError):
    """A model kind that is not in the registry."""


class IdentifiabilityError(InputError):
    """The data cannot identify the model: the regressor rank is below the model's structural rank."""


class UsageError(InputError):
    """A command-line value that is well-formed but makes no sense (e.g. a negative point count)."""


class ExtraMissingError(DarorError):
    """An optional extra (``pip install daror-runtime[nn]``) is needed for this and is not installed."""


class ConfigurationError(DarorError):
    """The runtime was wired inconsistently: a bug, or a configuration that cannot work."""
