"""The HAL backends the runtime knows: one registry, looked up by name, imported lazily (python-can style).

A backend is one :class:`BackendEntry`: its name (``kind``: what ``--hal`` offers and a
configuration's ``backend:`` names), its :class:`hal.interface.Hal` class and its configuration
model (a :class:`hal.config.AnyHalConfig` subclass), both as ``"module:attribute"`` strings that
are imported only when the backend is asked for, and the function that builds it on a test bench
for the contract suite (:mod:`hal.testing`). Registering a backend is the one step that makes it
usable everywhere: ``--hal``, :func:`hal.config.load_hal_config`, :func:`hal.interface.open_hal`
and the contract suite (``tests/hal/test_hal_contract.py``) all ask here.

The three built-in backends (``sim``, ``can-sim``, ``can``) are registered in code
(:data:`BUILTIN_BACKENDS`). Other packages add backends through the entry point group
:data:`ENTRY_POINT_GROUP`; the entry point's value names a :class:`BackendEntry`, or a function
without arguments that returns one::

    [project.entry-points."daror_runtime.hal_backends"]
    my-drives = "my_package.daror:BACKEND"

The entry points are read once, the first time the backends are listed (:func:`backend_kinds`) or
a name is asked for that is not registered in code: importing this module or asking for a built-in
reads none (the start-up of ``daror hil`` pays nothing for it). A plug-in never replaces a built-in
backend nor one registered in code. A plug-in that cannot be loaded is named in one warning line
(its entry point, its package, what failed) and, when its name is asked for, in the error; every
other backend, the built-ins first, works on.

This module imports neither numpy nor pydantic (``hal.config`` and the command line's help ask it).
"""

from __future__ import annotations

import importlib
import re
import threading
from collections.abc import Callable, Iterable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

from hal.errors import BackendUnavailableError, HalConfigError, HalError

if TYPE_CHECKING:
    from importlib.metadata import EntryPoint

__all__ = [
    "BUILTIN_BACKENDS",
    "ENTRY_POINT_GROUP",
    "BackendEntry",
    "BackendRegistry",
    "backend_entry",
    "backend_kinds",
    "broken_backends",
    "forget_discovered_backends",
    "import_target",
    "register_backend",
    "registry_restored",
    "unregister_backend",
]

#: Entry point group through which another package registers HAL backends (its ``pyproject.toml``)::
#:
#:     [project.entry-points."daror_runtime.hal_backends"]
#:     my-drives = "my_package.daror:BACKEND"
ENTRY_POINT_GROUP = "daror_runtime.hal_backends"

#: Import name -> the package that provides it (what a message tells a person to install).
PACKAGES: dict[str, str] = {"can": "python-can", "canopen": "canopen"}
#: Import name -> the optional extra of daror-runtime that installs it (pyproject.toml).
EXTRAS: dict[str, str] = {"can": "can", "canopen": "can"}

#: What a backend may be called: lower case, as typed after ``--hal`` and ``backend:``.
_KIND = re.compile(r"[a-z][a-z0-9-]*")


def _check_target(kind: str, what: str, target: object, expected: str) -> None:
    """Refuse a target that is not a ``module:attribute`` string.

    Raises:
        HalConfigError: one line naming the backend, the field and what was expected.
    """
    module_name, _, attribute = target.partition(":") if isinstance(target, str) else ("", "", "")
    if not module_name or not attribute:
        raise HalConfigError(f"HAL backend {kind!r}: {what} {target!r}; expected {expected!r}")


@dataclass(frozen=True)
class BackendEntry:
    """One HAL backend: its name, its class, its configuration model and its contract benches.

    Attributes:
        kind: the backend's name (lower-case letters, digits and hyphens, starting with a letter):
            what ``--hal`` offers and a configuration file's ``backend:`` names.
        target: ``"module:Class"`` of its :class:`hal.interface.Hal` subclass.
        config: ``"module:Model"`` of its configuration model: a :class:`hal.config.AnyHalConfig`
            subclass whose ``backend`` field is ``Literal[kind]`` (checked when it is loaded).
        benches: ``"module:function"``: ``function() -> Sequence[hal.testing.BackendUnderTest]``,
            how the contract suite builds the backend without its hardware, with the test hooks;
            None: it cannot be built without hardware (a test rig of the suite must run its code:
            ``tests/hal/test_hal_contract.py`` checks every registered backend is covered).

    Raises:
        HalConfigError: a malformed name or target (one line).
    """

    kind: str
    target: str
    config: str
    benches: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.kind, str) or _KIND.fullmatch(self.kind) is None:
            raise HalConfigError(
                f"HAL backend {self.kind!r}: expected a name of lower-case letters, digits and hyphens, "
                "starting with a letter"
            )
        _check_target(self.kind, "target", self.target, "module:Class")
        _check_target(self.kind, "config", self.config, "module:Model")
        if self.benches is not None:
            _check_target(self.kind, "benches", self.benches, "module:function")


#: The backends of this package, in the order lists show them (plug-ins follow, by name).
BUILTIN_BACKENDS: tuple[BackendEntry, ...] = (
    BackendEntry("sim", "hal.sim.backend:SimHal", "hal.config:SimHalConfig", "hal.testing:sim_benches"),
    BackendEntry(
        "can-sim", "hal.canopen.backend:SimulatedCanHal", "hal.config:CanSimHalConfig", "hal.testing:can_sim_benches"
    ),
    # Real drives: no bench without them (the contract suite runs this class on its CAN rig).
    BackendEntry("can", "hal.canopen.backend:CanHal", "hal.config:CanHalConfig"),
)


def _group_entry_points() -> Iterable[EntryPoint]:
    import importlib.metadata  # here, not at the top: ~8-20 ms nobody pays who does not list the backends

    return importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)


def _origin(entry_point: EntryPoint) -> str:
    """``entry point NAME = VALUE of package DIST VERSION``: where a plug-in comes from, for messages."""
    dist = getattr(entry_point, "dist", None)
    package = "an unknown package" if dist is None else f"package {dist.name} {dist.version}"
    return f"entry point {entry_point.name} = {entry_point.value} of {package}"


def _one_line(exc: BaseException) -> str:
    """``Type: message`` on one line (a plug-in's exception may span several)."""
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}"


class BackendRegistry:
    """Backends registered in code plus those of the entry points (read once, on first need; thread-safe).

    Args:
        builtins: the backends known without reading any entry point.
        entry_points: where the plug-ins' entry points come from (default: the installed packages'
            :data:`ENTRY_POINT_GROUP`; tests pass their own).
    """

    def __init__(
        self,
        builtins: Iterable[BackendEntry] = BUILTIN_BACKENDS,
        entry_points: Callable[[], Iterable[EntryPoint]] = _group_entry_points,
    ) -> None:
        self._entries: dict[str, BackendEntry] = {e.kind: e for e in builtins}
        self._builtin = frozenset(self._entries)
        self._entry_points = entry_points
        self._discovered: set[str] = set()  # names that came from entry points (forgotten by forget_discovered)
        self._broken: dict[str, str] = {}
        self._read = False
        self._reading = False
        self._lock = threading.RLock()

    # --- registering in code ----------------------------------------------------------------------

    def register(self, entry: BackendEntry) -> BackendEntry | None:
        """Register (or replace) ``entry.kind``; the entry it replaced, if any. A plug-in of that name is ignored."""
        with self._lock:
            previous = self._entries.get(entry.kind)
            self._entries[entry.kind] = entry
            self._discovered.discard(entry.kind)
            self._broken.pop(entry.kind, None)
            return previous

    def unregister(self, kind: str) -> BackendEntry | None:
        """Remove backend ``kind`` (built-in or not); the entry removed, or None if there was none."""
        with self._lock:
            self._discovered.discard(kind)
            return self._entries.pop(kind, None)

    @contextmanager
    def restored(self) -> Iterator[None]:
        """Put the registry back as it was when the ``with`` block began (what a test registered or removed)."""
        with self._lock:
            saved = (dict(self._entries), set(self._discovered), dict(self._broken), self._read)
        try:
            yield
        finally:
            with self._lock:
                self._entries, self._discovered, self._broken, self._read = saved

    def forget_discovered(self) -> None:
        """Drop what the entry points gave; the next listing reads them again (a test that changed sys.path)."""
        with self._lock:
            for kind in self._discovered:
                self._entries.pop(kind, None)
            self._discovered.clear()
            self._broken.clear()
            self._read = False

    # --- the entry points ---------------------------------------------------------------------------

    def _read_plugins(self) -> None:
        """Read the entry points once. Other threads wait for the first read; a plug-in module that
        lists the backends while it is being loaded (same thread) sees those loaded so far."""
        with self._lock:
            if self._read or self._reading:
                return
            self._reading = True
            try:
                by_name: dict[str, list[EntryPoint]] = {}
                try:
                    for entry_point in self._entry_points():
                        by_name.setdefault(entry_point.name, []).append(entry_point)
                except Exception as exc:  # unreadable package metadata: the built-ins still work
                    self._warn("HAL backend plug-ins not read", group=ENTRY_POINT_GROUP, problem=_one_line(exc))
                for name in sorted(by_name):
                    entry, problem = self._load(name, by_name[name])
                    if entry is not None:
                        self._entries[name] = entry
                        self._discovered.add(name)
                    elif problem is not None:
                        self._broken[name] = problem
                        self._warn("HAL backend plug-in not loaded", backend=name, problem=problem)
            finally:
                self._reading = False
                self._read = True

    def _load(self, name: str, entry_points: list[EntryPoint]) -> tuple[BackendEntry | None, str | None]:
        """The entry of plug-in ``name``, or the problem that keeps it out ((None, None): ignored, with a warning)."""
        if name in self._entries:  # a built-in, or registered in code: those win
            self._warn(
                "a HAL backend plug-in cannot replace a backend already registered; ignored",
                backend=name,
                plugin="; ".join(_origin(e) for e in entry_points),
            )
            return None, None
        if len({(e.value, getattr(e.dist, "name", None)) for e in entry_points}) > 1:
            return None, f"registered more than once: {'; '.join(_origin(e) for e in entry_points)}"
        entry_point = entry_points[0]
        try:
            value = entry_point.load()
            entry = value() if callable(value) and not isinstance(value, BackendEntry) else value
        except Exception as exc:  # third-party code: any failure keeps only this backend out
            return None, f"{_origin(entry_point)} cannot be loaded: {_one_line(exc)}"
        if not isinstance(entry, BackendEntry):
            return None, (
                f"{_origin(entry_point)} gives a {type(entry).__name__}; expected a hal.registry.BackendEntry "
                "(or a function returning one)"
            )
        if entry.kind != name:
            return (
                None,
                f"{_origin(entry_point)} gives backend {entry.kind!r}; expected {name!r}, its entry point's name",
            )
        return entry, None

    @staticmethod
    def _warn(event: str, **fields: str) -> None:
        import structlog  # only on a broken plug-in: the registry itself stays free of it

        structlog.get_logger(__name__).warning(event, **fields)

    # --- asking -------------------------------------------------------------------------------------

    def entry(self, kind: str) -> BackendEntry:
        """The entry of backend ``kind``; the entry points are read if it is not registered in code.

        Raises:
            HalConfigError: ``kind`` is not registered (the registered backends are listed).
            BackendUnavailableError: ``kind`` is registered by a plug-in that cannot be loaded (one line
                naming its entry point, its package and what failed).
        """
        found = self._entries.get(kind)
        if found is not None:
            return found
        self._read_plugins()
        found = self._entries.get(kind)
        if found is not None:
            return found
        if kind in self._broken:
            raise BackendUnavailableError(f"HAL backend {kind!r} cannot be used: {self._broken[kind]}")
        raise HalConfigError(f"unknown HAL backend {kind!r}; expected one of {', '.join(self.kinds())}")

    def kinds(self) -> tuple[str, ...]:
        """Every usable backend's name: built-ins first, then those registered in code, then plug-ins by name."""
        self._read_plugins()
        return tuple(self._entries)

    def broken(self) -> dict[str, str]:
        """Plug-ins that cannot be loaded: name -> the problem (one line each); the entry points are read first."""
        self._read_plugins()
        return dict(self._broken)


_REGISTRY = BackendRegistry()


def register_backend(
    kind: str | BackendEntry, target: str | None = None, config: str | None = None, benches: str | None = None
) -> BackendEntry | None:
    """Register (or replace) a backend in code; returns the entry it replaced, if any.

    Either ``register_backend(entry)`` or ``register_backend(kind, target, config, benches)``
    (see :class:`BackendEntry`). Nothing is imported now: the class and the configuration model
    are imported when the backend is asked for (:func:`hal.interface.hal_class`,
    :func:`hal.config.config_model`).

    Raises:
        HalConfigError: a malformed name, ``target`` not of the form ``module:Class`` or ``config``
            not of the form ``module:Model``; or an entry given together with targets.
    """
    if isinstance(kind, BackendEntry):
        if (target, config, benches) != (None, None, None):
            raise HalConfigError(f"HAL backend {kind.kind!r}: give an entry or its targets, not both")
        return _REGISTRY.register(kind)
    if target is None or config is None:
        shown = "target" if target is None else "config"
        raise HalConfigError(f"HAL backend {kind!r}: {shown} missing; expected 'module:Class' and 'module:Model'")
    return _REGISTRY.register(BackendEntry(kind, target, config, benches))


def unregister_backend(kind: str) -> BackendEntry | None:
    """Remove backend ``kind`` (what a test registered); the entry removed, or None if there was none."""
    return _REGISTRY.unregister(kind)


def backend_entry(kind: str) -> BackendEntry:
    """The registry entry of backend ``kind``.

    Raises:
        HalConfigError: ``kind`` is not registered (the registered backends are listed).
        BackendUnavailableError: ``kind`` is registered by a plug-in that cannot be loaded.
    """
    return _REGISTRY.entry(kind)


def backend_kinds() -> tuple[str, ...]:
    """The names of every usable HAL backend (what ``--hal`` offers): built-ins first, plug-ins after, by name.

    The first call reads the entry points (:data:`ENTRY_POINT_GROUP`); a plug-in that cannot be
    loaded is left out, with a warning.
    """
    return _REGISTRY.kinds()


def broken_backends() -> dict[str, str]:
    """Plug-ins that cannot be loaded: backend name -> what is wrong (one line each)."""
    return _REGISTRY.broken()


def registry_restored() -> AbstractContextManager[None]:
    """A ``with`` block after which the registry is as it was before it (for tests that register backends)."""
    return _REGISTRY.restored()


def forget_discovered_backends() -> None:
    """Forget what the entry points gave: the next listing reads them again (for tests that change ``sys.path``)."""
    _REGISTRY.forget_discovered()


def import_target(kind: str, target: str) -> object | None:
    """The object ``target`` (``"module:attribute"``) of backend ``kind``, its module imported now; None if it has none.

    Raises:
        BackendUnavailableError: the module does not exist (the backend is not built yet), or it
            needs a Python package that is not installed (the message names it, and the extra of
            daror-runtime that installs it).
        HalError: the module failed to import for another reason (a bug; one line, the cause chained).
    """
    module_name, _, attribute = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        missing = exc.name or ""
        if missing and (module_name == missing or module_name.startswith(missing + ".")):
            raise BackendUnavailableError(
                f"HAL backend {kind!r} is not built yet: this installation has no module {module_name}"
            ) from None
        if missing:
            top = missing.split(".")[0]
            package = PACKAGES.get(top, top)
            extra = EXTRAS.get(top)
            how = f"pip install 'daror-runtime[{extra}]'" if extra is not None else f"pip install {package}"
            raise BackendUnavailableError(
                f"HAL backend {kind!r} needs the Python package {package!r}, which is not installed ({how})"
            ) from None
        raise HalError(f"HAL backend {kind!r} cannot be loaded: {exc}") from None
    except ImportError as exc:
        raise HalError(f"HAL backend {kind!r} cannot be loaded: {exc}") from None
    except Exception as exc:  # a plug-in's module that fails as it runs: one line, not its traceback
        raise HalError(f"HAL backend {kind!r} cannot be loaded: module {module_name}: {_one_line(exc)}") from exc
    return getattr(module, attribute, None)
