"""Architecture rules of docs/architecture.md, enforced on the source tree."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def sources(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


def test_hal_never_imports_the_runtime() -> None:
    offenders = {
        str(p.relative_to(ROOT)): sorted(m for m in imported_modules(p) if m.split(".")[0] == "daror_runtime")
        for p in sources("hal")
    }
    assert {k: v for k, v in offenders.items() if v} == {}


def test_only_hal_canopen_talks_can() -> None:
    offenders = []
    for package in ("hal", "daror_runtime"):
        for p in sources(package):
            if "canopen" in p.relative_to(ROOT).parts[1:2]:
                continue
            if any(m.split(".")[0] in {"can", "canopen"} for m in imported_modules(p)):
                offenders.append(str(p.relative_to(ROOT)))
    assert offenders == []


@pytest.mark.parametrize("package", ["daror_runtime/models", "daror_runtime/data"])
def test_modelling_code_never_reads_the_simulation(package: str) -> None:
    """Models learn only from measured data: no scenario, no simulator in the modelling code."""
    offenders = [
        str(p.relative_to(ROOT)) for p in sources(package) if any(m.startswith("hal.sim") for m in imported_modules(p))
    ]
    assert offenders == []


def test_no_print_in_library_code() -> None:
    offenders = []
    for package in ("hal", "daror_runtime"):
        for p in sources(package):
            for node in ast.walk(ast.parse(p.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "print":
                    offenders.append(f"{p.relative_to(ROOT)}:{node.lineno}")
    assert offenders == []


def test_no_bare_assert_in_library_code() -> None:
    offenders = [
        f"{p.relative_to(ROOT)}:{node.lineno}"
        for package in ("hal", "daror_runtime")
        for p in sources(package)
        for node in ast.walk(ast.parse(p.read_text(encoding="utf-8")))
        if isinstance(node, ast.Assert)
    ]
    assert offenders == []


# --- function length (acceptance rule: no function over 120 lines) -----------------------------

#: The most lines a function of daror_runtime/ or hal/ may have, from its ``def`` to its last line
#: (``ast``'s ``end_lineno - lineno + 1``: decorators not counted, its docstring and comments counted).
#: No data-table exception is needed today; one would be an explicit allow-list here, with its reason.
MAX_FUNCTION_LINES = 120


def long_functions(path: Path, limit: int = MAX_FUNCTION_LINES) -> list[str]:
    """Every function of ``path`` (methods and nested functions included) over ``limit`` lines, as
    ``file:line qualified.name: N lines`` (the file relative to the repository when in it)."""
    where = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
    found: list[str] = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = f"{prefix}{child.name}"
                lines = (child.end_lineno or child.lineno) - child.lineno + 1
                if lines > limit:
                    found.append(f"{where}:{child.lineno} {name}: {lines} lines")
                visit(child, f"{name}.<locals>.")
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")
            else:
                visit(child, prefix)

    visit(ast.parse(path.read_text(encoding="utf-8")), "")
    return found


def test_no_function_is_over_120_lines() -> None:
    """A function longer than a screenful or two does more than one job: split it into named steps."""
    offenders = [found for package in ("daror_runtime", "hal") for p in sources(package) for found in long_functions(p)]
    assert offenders == []


def test_the_length_check_finds_long_functions(tmp_path: Path) -> None:
    """The check above is not vacuous: a function of the limit passes and one line more is found (methods,
    nested and async functions too, by qualified name), counted from ``def`` (not its decorators) to its
    last line."""
    source = tmp_path / "probe.py"
    source.write_text(
        "@decorator\n"
        "def fits():\n"  # 4 lines
        "    a = 1\n"
        "    b = 2\n"
        "    return a + b\n"
        "\n"
        "def over():\n"  # 5 lines
        "    a = 1\n"
        "    b = 2\n"
        "    c = 3\n"
        "    return a + b + c\n"
        "\n"
        "class Holder:\n"
        "    def method(self):\n"  # 5 lines
        "        a = 1\n"
        "        b = 2\n"
        "        c = 3\n"
        "        return a + b + c\n"
        "\n"
        "def outer():\n"  # 7 lines, inner 5
        "    async def inner():\n"
        "        a = 1\n"
        "        b = 2\n"
        "        c = 3\n"
        "        return a + b + c\n"
        "    return inner\n",
        encoding="utf-8",
    )
    assert long_functions(source, limit=4) == [
        f"{source}:7 over: 5 lines",
        f"{source}:14 Holder.method: 5 lines",
        f"{source}:20 outer: 7 lines",
        f"{source}:21 outer.<locals>.inner: 5 lines",
    ]


# --- model kinds (issue 11, point 5) -----------------------------------------------------------


def model_class_names() -> set[str]:
    """``CompensationModel`` and every class of the source tree derived from it (by name, through the AST)."""
    bases: dict[str, set[str]] = {}
    for p in sources("daror_runtime"):
        for node in ast.walk(ast.parse(p.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef):
                bases.setdefault(node.name, set()).update(ast.unparse(b).split(".")[-1] for b in node.bases)
    models = {"CompensationModel"}
    while True:
        more = {name for name, parents in bases.items() if parents & models} - models
        if not more:
            return models
        models |= more


def _named(node: ast.expr) -> set[str]:
    """The class names an ``isinstance`` second argument refers to (a name, ``module.Name``, or a tuple)."""
    if isinstance(node, ast.Tuple):
        return set().union(*(_named(e) for e in node.elts)) if node.elts else set()
    if isinstance(node, ast.Name):
        return {node.id}
    if isinstance(node, ast.Attribute):
        return {node.attr}
    if isinstance(node, ast.BinOp):  # A | B
        return _named(node.left) | _named(node.right)
    return set()


def test_controllers_never_ask_a_models_class() -> None:
    """A controller asks the model (``tick_kernel()``), never ``isinstance(model, SomeModel)``."""
    models = model_class_names()
    assert {"LinearCompensationModel", "PLFPlusModel", "APModel", "AugmentedModel"} <= models
    offenders = []
    for p in [*sources("daror_runtime/control"), ROOT / "daror_runtime/session/controllers.py"]:
        for node in ast.walk(ast.parse(p.read_text(encoding="utf-8"))):
            if (
                isinstance(node, ast.Call)
                and getattr(node.func, "id", None) == "isinstance"
                and len(node.args) == 2
                and _named(node.args[1]) & models
            ):
                offenders.append(f"{p.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}")
    assert offenders == []


def test_the_models_package_never_names_the_residual_analysis() -> None:
    """residual/ depends on models/, not the other way round: no import, and no ``module[:attr]`` string either."""
    offenders = []
    for p in sources("daror_runtime/models"):
        tree = ast.parse(p.read_text(encoding="utf-8"))
        named = {m for m in imported_modules(p) if m.startswith("daror_runtime.residual")}
        named |= {
            node.value
            for node in ast.walk(tree)
            if isinstance(node, ast.Constant)
            and isinstance(node.value, str)
            and re.fullmatch(r"daror_runtime\.residual[\w.]*(:\w+)?", node.value.strip())
        }
        offenders += [f"{p.relative_to(ROOT)}: {n}" for n in sorted(named)]
    assert offenders == []


def test_a_clean_registry_lists_augmented_from_its_entry_point() -> None:
    """The residual analysis registers ``augmented`` through pyproject.toml's entry point (read lazily)."""
    from daror_runtime.models.registry import ENTRY_POINT_GROUP, KindRegistry

    pyproject = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    assert (
        f'[project.entry-points."{ENTRY_POINT_GROUP}"]\naugmented = "daror_runtime.residual.kind:MODEL_KIND"'
        in pyproject
    )
    clean = KindRegistry()
    assert "augmented" in clean.names()
    assert clean.entry("augmented").model == "daror_runtime.residual.model:AugmentedModel"


# --- controllers and models do no I/O ---------------------------------------------------------------

#: The model-file layer (reads and writes model files) and the model-kind lookup (entry points,
#: logged warnings): the two places of the models package whose job is I/O.
IO_LAYER = {"daror_runtime/models/files.py", "daror_runtime/models/registry.py"}

#: Modules through which Python code reaches files, streams, the console, the log, the network or
#: other processes, and the project's own layers that do (a prefix bans its submodules too).
IO_MODULES = {
    # files, streams, the interpreter's own streams and exit
    "os", "io", "sys", "pathlib", "shutil", "tempfile", "glob", "mmap", "fileinput", "pickle", "shelve",
    "csv", "sqlite3", "yaml", "h5py", "matplotlib",
    # the console and the log (a handler writes, and may wait on a lock or a full pipe)
    "logging", "structlog", "rich.console", "rich.live", "rich.progress",
    # the network, other processes, other threads (work, and I/O, out of the loop's sight)
    "socket", "select", "selectors", "ssl", "urllib", "http", "can", "canopen",
    "subprocess", "multiprocessing", "threading", "concurrent", "asyncio", "signal",
    # dynamic imports would bring in any of the above past this check
    "importlib",
    # the project's file, log and backend layers
    "daror_runtime.logs", "daror_runtime.util", "daror_runtime.data.load", "daror_runtime.data.tables",
    "daror_runtime.data.recorder", "daror_runtime.data.recording_reader", "daror_runtime.models.files",
    "daror_runtime.models.registry", "hal.files", "hal.yamlfile", "hal.config", "hal.canopen",
}  # fmt: skip

#: Builtins that read or write the console or files, or import or run code dynamically.
IO_BUILTINS = {"open", "print", "input", "breakpoint", "__import__", "exec", "eval", "compile"}
#: numpy's file functions (called on ``np`` / ``numpy``).
NUMPY_FILE_FUNCTIONS = {
    "load", "save", "savez", "savez_compressed", "loadtxt", "savetxt", "genfromtxt", "fromfile", "fromregex", "memmap",
}  # fmt: skip
#: Methods of files, streams, paths and HALs (``Path.open``, ``file.write``, ``hal.read``, ...).
IO_METHODS = {
    "open", "read", "write", "flush", "readline", "readlines", "writelines", "seek",
    "read_text", "write_text", "read_bytes", "write_bytes", "tofile", "savefig",
}  # fmt: skip
#: The project names every function that reads or writes a file so (``hal.robot.load_description``,
#: ``models.files.save_model``, ``data.load.write_dataset``, ``hal.yamlfile.read_yaml``, ...).
IO_FUNCTION_PREFIXES = ("load_", "read_", "write_", "save_")


def _imports(source: str, package: str) -> list[tuple[int, str]]:
    """(line, module) of every import anywhere in ``source``, a module of ``package`` (dotted).

    Relative imports are made absolute; ``from a import b`` gives both ``a`` and ``a.b`` (``b`` may
    be a module).
    """
    found: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parent, base] if base else parent)
            found.append((node.lineno, base))
            found += [(node.lineno, f"{base}.{alias.name}") for alias in node.names]
    return found


def _io_calls(source: str) -> list[tuple[int, str]]:
    """(line, call) of every call of an I/O builtin, numpy file function, I/O method or file function."""
    found: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        if isinstance(func, ast.Name):
            name = func.id
            if name in IO_BUILTINS or name.startswith(IO_FUNCTION_PREFIXES):
                found.append((node.lineno, name))
        elif isinstance(func, ast.Attribute):
            owner = func.value.id if isinstance(func.value, ast.Name) else None
            name = func.attr
            numpy_file = owner in {"np", "numpy"} and name in NUMPY_FILE_FUNCTIONS
            if numpy_file or name in IO_METHODS or name.startswith(IO_FUNCTION_PREFIXES):
                found.append((node.lineno, ast.unparse(func)))
    return found


def _is_io_module(module: str) -> bool:
    return any(module == banned or module.startswith(banned + ".") for banned in IO_MODULES)


def test_controllers_and_models_do_no_io() -> None:
    """Modules under ``daror_runtime/control`` and ``daror_runtime/models`` (but the model-file layer
    ``models/files.py`` and the kind lookup ``models/registry.py``) do no I/O.

    Why: the controllers' ``update`` and the models' ``torque`` run inside the 1 kHz tick, where a
    read, a write, a log line or a lock behind them can wait for an unbounded time (a slow disk, a
    full pipe on stderr, a logging handler's lock): the tick misses its deadline and the drives hold
    the last torque, the SEA torque loop running open. Their design-time code (gains, filters, fits)
    takes its inputs as arguments, so what a controller or model does depends on no file but the
    ones the audited file layers (``models/files.py``, ``data/``, ``hal/files.py``) read and check.

    What "no I/O" means, checked on the syntax tree of each module (imports and calls anywhere in
    it, inside functions too):

    * no import of a module through which code reaches files, streams, the console, the log, the
      network, other processes or threads (:data:`IO_MODULES`: ``os``, ``io``, ``sys``,
      ``pathlib``, ``logging``, ``structlog``, ``threading``, ``subprocess``, ...), of a dynamic
      importer (``importlib``), or of the project's own file, log and backend layers. Allowed:
      ``json`` (values to text and back; reading a file would need ``open``), ``time`` (a clock),
      ``rich.table`` (a table is a value; the CLI prints it);
    * no call of the builtins ``open``, ``print``, ``input``, ``breakpoint``, ``__import__``,
      ``exec``, ``eval``, ``compile``; of numpy's file functions (``np.load``, ``np.save``,
      ``np.fromfile``, ``np.memmap``, ...); of a method of files, streams, paths or HALs (``open``,
      ``read``, ``write``, ``flush``, ``read_text``, ``tofile``, ``savefig``, ...); of a function
      named as the project names its file functions (``load_*``, ``read_*``, ``write_*``,
      ``save_*``: ``hal.robot.load_description``, ``models.files.save_model``, ...).

    Not covered: numba's on-disk cache of compiled functions (``cache=True``), which numba reads or
    writes when a module is imported or a function first compiled, never in the tick.
    """
    offenders: list[str] = []
    for package in ("daror_runtime/control", "daror_runtime/models"):
        for path in sources(package):
            name = str(path.relative_to(ROOT))
            if name in IO_LAYER:
                continue
            source = path.read_text(encoding="utf-8")
            imports = _imports(source, package.replace("/", "."))
            offenders += [f"{name}:{line}: imports {module}" for line, module in imports if _is_io_module(module)]
            offenders += [f"{name}:{line}: calls {call}" for line, call in _io_calls(source)]
    assert offenders == []


def test_the_no_io_check_finds_io() -> None:
    """The check above is not vacuous: each kind of I/O it names is found, and plain code is not."""
    source = (
        "import os\n"
        "from pathlib import Path\n"
        "from hal.robot import load_description\n"
        "from . import tables\n"
        "import numpy as np\n"
        "from daror_runtime.data.schema import Q_COLUMNS\n"
        "def update(sample, hal):\n"
        "    import structlog\n"
        "    print(sample)\n"
        "    np.save('x.npy', sample)\n"
        "    Path('x').write_text('x')\n"
        "    hal.read()\n"
        "    load_description()\n"
        "    with open('f') as f:\n"
        "        return np.clip(sample, -1.0, 1.0)\n"
    )
    modules = {m for _, m in _imports(source, "daror_runtime.data") if _is_io_module(m)}
    assert modules == {"os", "pathlib", "pathlib.Path", "structlog", "daror_runtime.data.tables"}
    calls = {c for _, c in _io_calls(source)}
    assert calls == {"print", "np.save", "Path('x').write_text", "hal.read", "load_description", "open"}


# --- the backend owns its time and its abilities (issue 11, points 1-3) -----------------------------------

#: Where the simulator's own classes may be named in an isinstance check.
_SIM_PACKAGE = ROOT / "hal" / "sim"
#: Classes nobody outside hal/sim and the tests may ask about: ask the clock (``clock.virtual``) or
#: the backend (``hal.virtual_time``, ``hal.drives_hardware``, ``hal.world``) instead.
_NEVER_ASKED = {"LockStepClock", "SimHal"}


def _classes_named(node: ast.expr) -> set[str]:
    """Class names in an ``isinstance`` second argument: a name, ``module.Name``, a tuple or ``A | B``."""
    if isinstance(node, ast.Tuple):
        return set().union(*(_classes_named(e) for e in node.elts)) if node.elts else set()
    if isinstance(node, ast.Name):
        return {node.id}
    if isinstance(node, ast.Attribute):
        return {node.attr}
    if isinstance(node, ast.BinOp):
        return _classes_named(node.left) | _classes_named(node.right)
    return set()


def _asks_which(path: Path) -> list[str]:
    """``isinstance(x, LockStepClock)`` / ``isinstance(x, SimHal)`` calls in ``path`` (also via tuples and ``|``)."""
    found = []
    name = path.relative_to(ROOT) if ROOT in path.parents else path.name
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if (
            isinstance(node, ast.Call)
            and getattr(node.func, "id", None) in {"isinstance", "issubclass"}
            and len(node.args) == 2
            and _classes_named(node.args[1]) & _NEVER_ASKED
        ):
            found.append(f"{name}:{node.lineno}: {ast.unparse(node)}")
    return found


def test_nobody_asks_which_clock_or_backend_it_has() -> None:
    """Lock-step is the clock's property and the backend's ability, never an isinstance check (outside hal/sim)."""
    offenders = []
    for package in ("hal", "daror_runtime", "bench", "examples"):
        for p in sources(package):
            if _SIM_PACKAGE not in p.parents:
                offenders += _asks_which(p)
    assert offenders == []


def test_the_which_check_finds_what_it_forbids(tmp_path: Path) -> None:
    """The check above is not vacuous: every spelling it forbids is found, an allowed check is not."""
    source = tmp_path / "probe.py"
    source.write_text(
        "isinstance(clock, LockStepClock)\n"
        "isinstance(hal, backend.SimHal)\n"
        "isinstance(hal, (Hal, SimHal))\n"
        "isinstance(clock, RealTimeClock | LockStepClock)\n"
        "isinstance(hal, Hal)\n",
        encoding="utf-8",
    )
    assert [line.split(":")[1] for line in _asks_which(source)] == ["1", "2", "3", "4"]


def test_the_console_never_imports_the_simulator() -> None:
    """The console (and the rehearsal it drives) reach the simulated world through ``hal.world`` only."""
    offenders = [
        f"{p.relative_to(ROOT)}: {m}"
        for p in [*sources("daror_runtime/console"), ROOT / "daror_runtime/demo/rehearsal.py"]
        for m in sorted(imported_modules(p))
        if m == "hal.sim" or m.startswith("hal.sim.")
    ]
    assert offenders == []


def test_backends_are_imported_only_through_the_registry() -> None:
    """Outside its own package a backend's module is named only in the registry (hal/registry.py), lazily."""
    offenders = []
    for p in sources("daror_runtime"):
        for m in imported_modules(p):
            if m.startswith(("hal.canopen", "hal.sim.backend")):
                offenders.append(f"{p.relative_to(ROOT)}: {m}")
    assert offenders == []


#: What the console may import from the project: the facade, the types it hands out, and the words
#: an operator types (checklists, model kinds, guard descriptions, the spec's states), plus the
#: readers of the files an operator names. Nothing of the loop, the safety monitor, the controllers,
#: the session's internals or the simulator.
CONSOLE_MAY_IMPORT = {
    "daror_runtime.runtime",  # the facade
    "daror_runtime.session.status",  # the typed status it returns
    "daror_runtime.session.events",  # its announcements
    "daror_runtime.session.settings",  # its settings (Runtime.settings)
    "daror_runtime.fsm.supervisor",  # Ticket and Response, what a request returns
    "daror_runtime.errors",
    "daror_runtime.fsm.signals",  # the checklists' names
    "daror_runtime.records.codes",  # what a pilot's code is (the grammar's pilot CODE)
    # the lab's records, read between lines, never in the tick: a returning pilot's limits and model
    "daror_runtime.records.index",
    "daror_runtime.records.returning",
    "daror_runtime.records.store",
    "daror_runtime.fsm.guards",  # the guards' descriptions (the guide)
    "daror_runtime.fsm.spec",  # the states' names and modes (the grammar)
    "daror_runtime.fsm.diagram",  # the spec's diagram, laid out for the web console
    "daror_runtime.models.registry",  # the model kinds' names
    "daror_runtime.identification.settings",  # the sweep's waypoint settings
    "daror_runtime.identification.waypoints",  # the sweep's waypoints
    "hal.capabilities",  # the simulated world's protocol, through Runtime.world
    "hal.files",  # files the operator names: regular, bounded
    "hal.isb",  # an ISB limits file the operator names
    "daror_runtime.models.files",  # a model file the operator names, checked before a script runs
    "hal.robot",  # types
}


def test_the_console_imports_only_the_facade_and_its_own_modules() -> None:
    offenders = [
        f"{p.relative_to(ROOT)}: {m}"
        for p in sources("daror_runtime/console")
        for m in sorted(imported_modules(p))
        if m.split(".")[0] in {"daror_runtime", "hal"}
        and not m.startswith("daror_runtime.console")
        and m not in CONSOLE_MAY_IMPORT
    ]
    assert offenders == []


def test_the_session_never_imports_the_console_or_the_runtime() -> None:
    """``session/`` is what the runtime is made of; the facade and the console sit above it (the demo owns the rehearsal)."""
    offenders = [
        f"{p.relative_to(ROOT)}: {m}"
        for p in sources("daror_runtime/session")
        for m in sorted(imported_modules(p))
        if m.startswith(("daror_runtime.console", "daror_runtime.runtime", "daror_runtime.demo"))
    ]
    assert offenders == []


#: The facade: the operator's requests, the typed status, the session's lifecycle, read-only facts.
FACADE = {
    # what the session is
    "session_id", "session_dir", "operator", "drift_test", "compare", "rate", "settings", "spec", "description", "shoulder", "rate_hz", "lock_step", "world",
    "state_name", "last_sample", "torque_reference_nm", "model_in_use", "drain_announcements", "on_transition",
    # lifecycle; who drives the loop (lock-step ticks or its own thread: daror_runtime/runner.py)
    "open", "shutdown", "close", "runner", "busy", "jobs_pending", "at_rest", "arm_held", "wait",
    # the operator's requests
    "request", "advance", "revert", "reset", "acknowledge", "confirm", "name_pilot", "set_support", "rom_start",
    "rom_stop", "set_isb_limits", "identify", "stop_identification", "train", "select_model",
    "lower_arm", "release_arm",  # a fault's reaction holds the arm (docs/safety.md)
    # what the operator sees
    "status", "snapshot",
}  # fmt: skip


def test_the_runtime_exposes_only_its_facade(tmp_path: Path) -> None:
    """Everything else (supervisor, monitor, loop, controllers, jobs) is private to the session."""
    from daror_runtime.runtime import Runtime
    from hal.config import SimHalConfig
    from hal.interface import open_hal

    public_class = {n for n in vars(Runtime) if not n.startswith("_")}
    runtime = Runtime(open_hal(SimHalConfig()), tmp_path / "session")
    public_instance = {n for n in vars(runtime) if not n.startswith("_")}
    assert public_class == FACADE
    assert public_instance == {"ended", "ended_utc"}  # how and when the session ended (None while it runs)


def test_the_tick_side_trajectory_never_imports_its_planner() -> None:
    """Issue 26: trajectory.py (what the tick evaluates) and trajectory_planning.py (design time) were an import
    circle; the settings and kinds they share live in trajectory_settings.py, and the approach is prepended by
    the planner's prepend_approach, not by a method that called back into it."""
    planner = "daror_runtime.identification.trajectory_planning"
    tick_side = ROOT / "daror_runtime/identification/trajectory.py"
    assert planner not in imported_modules(tick_side)
    shared = ROOT / "daror_runtime/identification/trajectory_settings.py"
    assert not {m for m in imported_modules(shared) if m.startswith("daror_runtime.identification")}


#: What decides whether another thread can stall a tick (docs/safety.md H7); only the loop runner touches it.
_INTERPRETER_SETTINGS = re.compile(
    r"\b(threading\.Thread|sys\.setswitchinterval|gc\.(disable|enable|freeze|unfreeze))\b"
)


def test_the_runtime_owns_no_thread(tmp_path: Path) -> None:
    """Threads, the garbage collector's policy and the switch interval belong to the loop runner, not to the facade."""
    import threading

    from daror_runtime.clocks import PacedClock
    from daror_runtime.runner import LoopRunner
    from daror_runtime.runtime import Runtime
    from hal.config import SimHalConfig
    from hal.interface import open_hal

    source = (ROOT / "daror_runtime" / "runtime.py").read_text()
    assert "threading" not in imported_modules(ROOT / "daror_runtime" / "runtime.py")
    assert _INTERPRETER_SETTINGS.findall(source) == []
    hal = open_hal(SimHalConfig())
    runtime = Runtime(hal, tmp_path / "session", clock=PacedClock(1.0 / hal.rate_hz))
    runtime.open()
    try:
        runtime.runner.start()
        loop_threads = [t for t in threading.enumerate() if t.name in {"daror-loop", "daror-service"}]
        assert len(loop_threads) == 2
        owned = [name for name, value in vars(runtime).items() if isinstance(value, threading.Thread)]
        assert owned == []  # the runtime holds none of them
        assert isinstance(runtime.runner, LoopRunner)
        assert runtime.runner.running
    finally:
        runtime.shutdown("test")
        runtime.close()
    assert not any(t.is_alive() for t in loop_threads)


#: Who else may set the collector or the switch interval, and why (none of them runs a session's loop).
_MAY_SET_THE_INTERPRETER = {
    "daror_runtime/runner.py": "the loop runner: a session's loop on its own thread",
    "daror_runtime/loop.py": "a batch of ticks in the caller's thread pauses the collector for its own length",
    "daror_runtime/rt_check.py": "the design-time rate check runs a bare loop with the runner's settings",
    "daror_runtime/cli": "a command about to exit freezes what exists (spares the collections at exit)",
}


def test_only_the_loop_runner_sets_what_can_stall_a_tick() -> None:
    """Outside the declared places, no module sets the collector's policy or the switch interval."""
    offenders = [
        f"{p.relative_to(ROOT)}: {match.group(0)}"
        for package in ("daror_runtime", "hal")
        for p in sources(package)
        if not p.relative_to(ROOT).as_posix().startswith(tuple(_MAY_SET_THE_INTERPRETER))
        for match in re.finditer(r"\bsys\.setswitchinterval\b|\bgc\.(disable|freeze)\b", p.read_text())
    ]
    assert offenders == []


def test_nothing_but_tests_and_benches_reach_past_the_runtimes_door() -> None:
    """``Runtime._core`` is read only by the declared test hook (daror_runtime/testing.py), which library code never imports."""
    reaching = [
        str(p.relative_to(ROOT))
        for root in ("daror_runtime", "hal", "tests", "bench")
        for p in sorted((ROOT / root).rglob("*.py"))
        if re.search(r"\._core\b", p.read_text())
        and p.relative_to(ROOT).as_posix()
        not in {"daror_runtime/runtime.py", "daror_runtime/testing.py", "tests/test_boundaries.py"}
    ]
    assert reaching == []
    importing_the_hook = [
        str(p.relative_to(ROOT))
        for package in ("daror_runtime", "hal")
        for p in sources(package)
        if "daror_runtime.testing" in imported_modules(p)
    ]
    assert importing_the_hook == []


# --- HAL backends plug in (issue 26, point 4) ------------------------------------------------------

#: The tests' stand-in drives as a third-party package: a module and its dist-info, whose entry point
#: (group daror_runtime.hal_backends) registers the HAL backend ``stand-in`` (tests/outside.py).
OUTSIDE_BACKEND = ROOT / "tests" / "data" / "outside_backend"


def _names_the_stand_in(path: Path) -> list[str]:
    """Where ``path``'s code (not its prose) names the stand-in backend: an import of it, or its name or target as a value."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = [m for m in imported_modules(path) if m.startswith(("tests.standin_drives", "daror_standin"))]
    found += [
        f"line {node.lineno}: {node.value!r}"
        for node in ast.walk(tree)
        if isinstance(node, ast.Constant)
        and isinstance(node.value, str)
        and (node.value == "stand-in" or node.value.startswith(("tests.standin_drives", "daror_standin")))
    ]
    return found


@pytest.mark.subprocess
@pytest.mark.slow
def test_a_new_backend_registered_from_outside_appears_in_hal_and_in_the_contract_suite() -> None:
    """A new backend registered from outside the packages appears in --hal and in the contract suite without edits elsewhere.

    The stand-in drives' package is put on the path of fresh processes, as pip would install it;
    no module of the packages, the command line or the contract suite names it.
    """
    import os
    import subprocess
    import sys

    nowhere = [
        *sources("hal"),
        *sources("daror_runtime"),
        ROOT / "tests/hal_contract.py",
        ROOT / "tests/hal/test_hal_contract.py",
    ]
    assert {str(p.relative_to(ROOT)): found for p in nowhere if (found := _names_the_stand_in(p))} == {}
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(OUTSIDE_BACKEND), str(ROOT)])}

    def run(*argv: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)

    listed = run(sys.executable, "-c", "from hal.interface import backend_kinds; print(*backend_kinds())")
    assert (listed.returncode, listed.stdout.split(), listed.stderr) == (0, ["sim", "can-sim", "can", "stand-in"], "")
    helped = run(str(Path(sys.executable).with_name("daror")), "console", "--help")
    assert helped.returncode == 0, helped.stderr
    assert "--hal {sim,can-sim,can,stand-in}" in helped.stdout
    contract = run(
        sys.executable, "-m", "pytest", "tests/hal/test_hal_contract.py", "-k", "stand-in",
        "-p", "no:cacheprovider", "-o", "addopts=", "-q", "-rs",
    )  # fmt: skip
    assert contract.returncode == 0, contract.stdout[-3000:]
    summary = contract.stdout.strip().splitlines()[-1]
    passed = re.search(r"(\d+) passed", summary)
    assert passed is not None, summary
    assert int(passed.group(1)) >= 20, summary  # the contract's checks, run on the stand-in
    assert "failed" not in summary
    assert "error" not in summary


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _runtime_imports(path: Path, modules: set[str]) -> set[str]:
    """The project modules ``path`` imports when it runs (in functions too; not those only a type checker reads)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = _module_name(path) if path.name == "__init__.py" else _module_name(path).rpartition(".")[0]
    type_only = {
        id(node)
        for branch in ast.walk(tree)
        if isinstance(branch, ast.If) and "TYPE_CHECKING" in ast.unparse(branch.test)
        for statement in branch.body
        for node in ast.walk(statement)
    }
    found: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in type_only:
            continue
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return {name for name in found if name in modules and name != _module_name(path)}


def _import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        on_stack.add(module)
        for imported in sorted(graph[module]):
            if imported not in index:
                visit(imported)
                low[module] = min(low[module], low[imported])
            elif imported in on_stack:
                low[module] = min(low[module], index[imported])
        if low[module] == index[module]:
            component = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                component.append(top)
                if top == module:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return cycles


def test_no_import_cycle_between_the_projects_modules() -> None:
    """Module A imports B which imports A, even inside a function: a tangle the next engineer has to learn.

    Imports only a type checker reads (``if TYPE_CHECKING:``) do not count: they never run.
    """
    paths = [p for package in ("daror_runtime", "hal") for p in sources(package)]
    modules = {_module_name(p) for p in paths}
    graph = {_module_name(p): _runtime_imports(p, modules) for p in paths}
    assert _import_cycles(graph) == []
    assert _import_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]  # the finder finds
