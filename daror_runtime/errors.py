"""The runtime's errors: one tree, rooted in :class:`hal.errors.DarorError`.

::

    DarorError                         root (hal.errors)
    +-- InputError                     a person's input is wrong -> exit 2, nothing written
    |   +-- DescriptionError           robot description / scenario YAML (hal.errors)
    |   +-- HalConfigError             a HAL configuration file or flag (hal.errors)
    |   +-- BackendUnavailableError    a HAL backend not built or not installed (hal.errors)
    |   +-- DataError                  dataset file (names file, line/row, column)
    |   +-- ModelFileError             model JSON (not JSON, wrong version, checksum mismatch, ...)
    |   +-- UnknownModelKindError      a model kind that is not registered
    |   +-- IdentifiabilityError       the data cannot identify the model (rank too low)
    |   +-- UsageError                 a command-line value that makes no sense
    |       +-- LockStepRefusedError   lock-step (virtual time) on a backend that drives hardware
    |       +-- ModelOptionError       an option the model kind does not take
    +-- ShapeError (also ValueError)   an array of the wrong shape reached an API: a bug (hal.errors)
    +-- ConfigurationError             the runtime was wired inconsistently (a bug or a bad configuration)
    +-- HalError                       the hardware or its simulation failed (hal.errors)
    |   +-- HalNotOpenError            read or write before open or after close
    |   +-- HalFaultError              a backend fault latched outside the tick (hal.interface)
    |       +-- HalBusFaultError       the field bus failed: bus-off, error-passive (hal.interface)
    +-- ModelKindPluginError           a registered model-kind plugin that cannot be loaded
    +-- ExtraMissingError              an optional extra (nn) is needed but not installed
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
