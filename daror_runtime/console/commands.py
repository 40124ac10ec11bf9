"""Executing console lines: one checked line, one request to the runtime (or one act of the simulated world).

The words of a line are checked first (:mod:`daror_runtime.console.grammar`); then an operator
request is posted to the runtime and takes effect at the next tick boundary, and the answer is
printed (accepted, or refused with the reason). ``help`` lists the commands in plain words;
``status`` shows what the robot is doing and the next steps (:mod:`daror_runtime.console.view`).
Whatever the runtime announces (a transition, a fault, finished work) is printed as it is drained,
on its own line.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from rich.console import Console
from rich.markup import escape

from daror_runtime.console.grammar import CommandError, ParseContext, Parsed, help_text, parse_line, split
from daror_runtime.console.guide import next_steps
from daror_runtime.console.view import announcement_line, render_status, stamp
from daror_runtime.console.world import SimWorld
from daror_runtime.errors import DarorError
from daror_runtime.fsm.spec import FsmSpec
from daror_runtime.fsm.supervisor import Response, Ticket
from daror_runtime.runtime import Runtime
from daror_runtime.session.events import Announcement
from hal.isb import UnreachablePoseError

if TYPE_CHECKING:
    from daror_runtime.records.returning import PilotHistory
from hal.robot import RobotDescription

__all__ = ["CommandError", "ConsoleSession", "QuitRequested", "ScriptCheckError", "parse_context"]


class ScriptCheckError(DarorError):
    """An ``expect`` line of a script did not hold, or a ``wait until`` timed out."""


class QuitRequested(Exception):  # noqa: N818 - a request, not an error
    """The operator typed quit: the session ends (torque off first)."""


@dataclass
class _Tally:
    response: Response | None = None  # the last answered request
    response_counted: bool = False  # its refusal was counted as a failure
    failed: int = 0  # requests refused, checks that did not hold, commands that failed
    bad_lines: int = 0  # lines that were not commands
    failures: list[str] = field(default_factory=list)


def parse_context(spec: FsmSpec, description: RobotDescription, fault_kinds: tuple[str, ...] | None) -> ParseContext:
    """What lines are checked against in a session on ``spec`` and a robot ``description``.

    ``fault_kinds``: the faults the backend's simulated world injects; None: no simulated world
    (hardware: ``sim`` lines are refused).
    """
    return ParseContext(
        state_names=(*(s.name for s in spec.states), spec.fail.name),
        has_world=fault_kinds is not None,
        description=description,
        fault_kinds=fault_kinds or (),
    )


class ConsoleSession:
    """Executes console lines against a runtime (and the simulated world, if any).

    Args:
        runtime: an opened runtime.
        out: where answers are printed.
        world: the simulated world (None on hardware: ``sim`` commands are refused).
        request_timeout_s: how long a request may wait for its tick (robot time in lock-step).
        announcements: what this console drains its announcements from (default: the runtime's
            feed; the web console's hub when a browser shares the session, so both show them).
    """

    def __init__(
        self,
        runtime: Runtime,
        out: Console,
        world: SimWorld | None = None,
        request_timeout_s: float = 5.0,
        announcements: Callable[[], list[Announcement]] | None = None,
        records_url: str | None = None,
    ) -> None:
        self.runtime = runtime
        self.records_url = records_url  # the lab's records (a returning pilot's limits and model); None: none
        self.announcements = announcements if announcements is not None else runtime.drain_announcements
        self.out = out
        self.world = world
        self.timeout_s = request_timeout_s
        self.context = parse_context(
            runtime.spec, runtime.description, world.fault_kinds if world is not None else None
        )
        self.tally = _Tally()
        self._announcing = threading.Lock()  # a printer thread drains too: one drain-and-print at a time, in order
        self._line = ""  # the line being run (echoed by world acts)
        self._run: dict[str, Callable[[tuple], None]] = {  # type: ignore[type-arg]
            "advance": lambda a: self._answer(runtime.advance()),
            "revert": lambda a: self._answer(runtime.revert()),
            "reset": lambda a: self._answer(runtime.reset()),
            "ack": lambda a: self._answer(runtime.acknowledge()),
            "lower": lambda a: self._answer(runtime.lower_arm()),
            "release": lambda a: self._answer(runtime.release_arm()),
            "confirm": lambda a: self._answer(runtime.confirm(a[0])),
            "pilot": self._name_pilot,
            "support": lambda a: self._answer(runtime.set_support(a[0])),
            "drift": lambda a: self._answer(runtime.drift_test()),
            "compare": lambda a: self._answer(runtime.compare(a[0], a[1])),
            "rate": lambda a: self._answer(runtime.rate(a[0])),
            "rom": self._rom,
            "identify": self._identify,
            "train": self._train,
            "model": self._model,
            "status": self._status,
            "settings": self._settings,
            "help": lambda a: self.say(help_text(a[0])),
            "wait": self._wait,
            "expect": self._expect,
            "sim": self._sim,
            "quit": self._quit,
        }

    # --- entry ----------------------------------------------------------------------------

    def parse(self, line: str) -> Parsed | None:
        """Check a line (None: empty or a comment).

        Raises:
            CommandError: not a command, or bad words.
        """
        return parse_line(line, self.context)

    def execute(self, line: str) -> None:
        """Check and run one line, then print what the runtime announced meanwhile.

        Raises:
            CommandError: not a command, or bad words (nothing was done).
            ScriptCheckError: an ``expect`` or ``wait until`` did not hold.
            QuitRequested: the line was quit.
            InputError, DarorError: the runtime refused the request before queueing it.
        """
        parsed = self.parse(line)
        if parsed is not None:
            self.run(parsed)

    def run(self, parsed: Parsed) -> None:
        """Run a checked line (see :meth:`execute`)."""
        self._line = parsed.line
        try:
            self._run[parsed.command](parsed.args)
        finally:
            self.show_announcements()

    def show_announcements(self) -> None:
        """Print what the runtime announced since the last call, one line each (any thread)."""
        with self._announcing:
            for item in self.announcements():
                self.say(announcement_line(item))

    def say(self, text: str) -> None:
        self.out.print(escape(text), soft_wrap=True)

    def record_failure(self, text: str) -> None:
        self.tally.failed += 1
        self.tally.failures.append(text)

    # --- operator requests ----------------------------------------------------------------

    def _name_pilot(self, args: tuple) -> None:  # type: ignore[type-arg]
        self._answer(self.runtime.name_pilot(args[0]))
        if self.tally.response is not None and self.tally.response.accepted and self.records_url is not None:
            for line in self._history().offer(self.runtime.settings.limits_max_age_days):
                self.say(line)

    def _history(self) -> PilotHistory:
        """What the lab's records hold of this session's pilot (read now, outside the tick).

        Raises:
            CommandError: no records, no pilot named, or the records cannot be read (why, in one line).
        """
        from daror_runtime.records.returning import PilotHistory, pilot_history
        from daror_runtime.records.store import NoRecordsError, open_store

        pilot = self.runtime.snapshot().pilot
        if self.records_url is None:
            raise CommandError("no lab's records in this session (--db none)")
        if pilot is None:
            raise CommandError("no pilot named: pilot CODE first")
        try:
            store = open_store(self.records_url, create=False)
        except NoRecordsError:
            return PilotHistory(pilot_code_of(pilot), 0, None, None, None)  # no records yet: new to them
        except DarorError as exc:
            raise CommandError(f"the lab's records: {exc}") from None
        with store:
            try:
                return pilot_history(store, pilot)
            except DarorError as exc:
                raise CommandError(f"the lab's records: {exc}") from None

    def _rom(self, args: tuple) -> None:  # type: ignore[type-arg]
        if args[0] == "start":
            self._answer(self.runtime.rom_start())
        elif args[0] == "stop":
            self._answer(self.runtime.rom_stop())
        elif args[0] == "last":
            last = self._history().last_limits
            if last is None:
                raise CommandError("rom last: the records hold no range of motion of this pilot; record it (rom start)")
            age, allowed = last.age_days(), self.runtime.settings.limits_max_age_days
            if age > allowed:
                raise CommandError(
                    f"rom last: his last range of motion is {age:.0f} days old, the settings allow {allowed:g} "
                    "(limits_max_age_days): record it anew (rom start)"
                )
            source = f"the lab's records: session {last.session_id}, {last.recorded_utc.date().isoformat()}"
            self._answer(self.runtime.set_isb_limits(last.limits, source=source))
        else:
            self._answer(self.runtime.set_isb_limits(args[1], source=args[2]))

    def _identify(self, args: tuple) -> None:  # type: ignore[type-arg]
        if args[0] == "stop":
            self._answer(self.runtime.stop_identification())
        else:
            self._answer(self.runtime.identify(args[0]))

    def _train(self, args: tuple) -> None:  # type: ignore[type-arg]
        self.runtime.train(args[0])
        self.say("training queued (outside the loop); 'wait until idle' waits for it")

    def _model(self, args: tuple) -> None:  # type: ignore[type-arg]
        path, validation = args[0], args[1]
        if path == "last":
            last = self._history().last_model
            if last is None:
                raise CommandError("model last: the records hold no validated model of this pilot; identify and train")
            path = last.path
            if "validation" in self.runtime.snapshot().identification_saved:
                where = "this session's validation run"
            elif last.validation_file is not None:
                # before this session has a run of its own: his last session's, where it was validated
                # (a recording of this pilot on this robot, as the gate requires); re-validated after identify
                validation, where = last.validation_file, f"his validation run of session {last.session_id}"
            else:
                raise CommandError("model last: no validation run in this session yet (identify validation first)")
            self.say(f"his last model: {path} ({last.kind}, session {last.session_id}), validated on {where}")
        self._check_against_the_records(path)
        self.runtime.select_model(path, validation, accept_nonconservative=args[2])
        self.say("model validation queued (outside the loop); 'wait until idle' waits for it")

    def _check_against_the_records(self, path: object) -> None:
        """A model file the records hold with another hash is refused (issue 28: never used for compensation)."""
        if self.records_url is None:
            return
        from daror_runtime.records.returning import check_model_file
        from daror_runtime.records.store import NoRecordsError, open_store

        try:
            store = open_store(self.records_url, create=False)
        except NoRecordsError:
            return  # no records yet: nothing to compare with
        except DarorError as exc:
            raise CommandError(f"the lab's records: {exc}") from None
        with store:
            try:
                check_model_file(store, str(path))
            except DarorError as exc:
                raise CommandError(f"model: {exc}") from None

    def _status(self, args: tuple) -> None:  # type: ignore[type-arg]
        status = self.runtime.snapshot()
        if args[0]:
            self.out.print_json(json.dumps(status.as_dict(), default=str))
            return
        world = self.world
        notes = world.notes(self.runtime.settings) if world is not None else []
        self.say(render_status(status, next_steps(status, world is not None), notes))

    def _settings(self, args: tuple) -> None:  # type: ignore[type-arg]
        settings = self.runtime.settings
        self.say("session settings (daror console --settings FILE changes them):")
        for key, value in settings.model_dump(mode="json").items():
            if isinstance(value, dict):
                for sub, subvalue in value.items():
                    self.say(f"  {key}.{sub}: {subvalue}")
            else:
                self.say(f"  {key}: {value}")

    def _quit(self, args: tuple) -> None:  # type: ignore[type-arg]
        # torque off drops an arm a fault's reaction holds: the operator hands it on first, or says he means it
        if not args[0] and self.runtime.arm_held:
            raise CommandError(
                "a fault's reaction holds the pilot's arm: 'lower' it to its rest, or 'release' it once someone "
                "holds it; 'quit now' ends the session anyway and the torque off drops the arm"
            )
        raise QuitRequested

    # --- time -----------------------------------------------------------------------------

    def _wait(self, args: tuple) -> None:  # type: ignore[type-arg]
        """``wait SECONDS`` / ``wait until ...``; a wait begun outside FAIL ends at the tick the robot enters FAIL.

        Raises:
            ScriptCheckError: ``wait until`` timed out, or ended early in FAIL without its condition.
        """
        runtime = self.runtime
        fail = runtime.spec.fail.name
        # Waiting on in FAIL would only pass robot time while the reaction holds the arm; a wait begun
        # in FAIL is the operator's own (for the reaction, the release) and runs its course.
        watch = runtime.state_name != fail

        def failed() -> bool:
            return watch and runtime.state_name == fail

        def shown() -> float | None:
            """Print what happened meanwhile (before the wait's own line: robot time's order); its latest time."""
            items = self.announcements()
            for item in items:
                self.say(announcement_line(item))
            return max((item.t_s for item in items if item.t_s is not None), default=None)

        def ended_early(latest_s: float | None) -> None:  # a tick whose reading failed has no sample of its own
            t_s = self._t()
            self.say(f"{stamp(t_s if t_s is not None else latest_s)} wait ended early: the robot is in {fail}")

        if args[0] == "seconds":
            if watch and args[1] > 0:
                runtime.runner.run_until(failed, args[1])
            else:
                runtime.runner.pass_time(args[1])
            latest = shown()
            if failed():
                ended_early(latest)
            return
        _, what, name, timeout_s = args
        awaited = f"{what}{' ' + name if name else ''}"
        condition = self._condition(what, name)
        runtime.runner.run_until(lambda: condition() or failed(), timeout_s)
        latest = shown()
        if not condition():
            if failed():
                ended_early(latest)
                raise ScriptCheckError(f"'wait until {awaited}' ended early: the robot entered {fail}")
            raise ScriptCheckError(f"'wait until {awaited}' did not happen within {timeout_s:g} s")
        self.say(f"{stamp(self._t())} {awaited}")

    def _condition(self, what: str, name: str | None) -> Callable[[], bool]:
        runtime = self.runtime
        if what == "idle":
            return lambda: not runtime.busy
        if what == "still":
            world = self.world

            def still() -> bool:
                return not (world is not None and world.pilot_moving) and runtime.at_rest

            return still
        if what == "model":
            return lambda: runtime.model_in_use is not None and not runtime.jobs_pending
        return lambda: runtime.state_name == name

    # --- checks ---------------------------------------------------------------------------

    def _expect(self, args: tuple) -> None:  # type: ignore[type-arg]
        if args[0] == "state":
            state = self.runtime.state_name
            if state != args[1]:
                raise ScriptCheckError(f"expected state {args[1]}, the robot is in {state}")
        else:
            response = self.tally.response
            if response is None:
                raise ScriptCheckError("expect accepted/refused: no request was answered yet")
            if response.accepted != (args[0] == "accepted"):
                raise ScriptCheckError(
                    f"expected {response.request!r} to be {args[0]}; it was "
                    + ("accepted" if response.accepted else f"refused ({response.reason})")
                )
            if self.tally.response_counted:  # a refusal that was expected is no failure
                self.tally.failed -= 1
                self.tally.failures.pop()
                self.tally.response_counted = False
        self.say(f"  ok: {' '.join(str(a) for a in args)}")

    # --- the simulated world --------------------------------------------------------------

    def _sim(self, args: tuple) -> None:  # type: ignore[type-arg]
        world = self.world
        if world is None:  # the grammar refuses these on hardware; a session without a world too
            raise CommandError("'sim' commands act on the simulated plant; this session runs on hardware")
        what = args[0]
        if what == "estop":
            world.estop(args[1], args[2])
        elif what == "fault":
            world.fault(args[1], args[2], args[3])
        elif what == "clear":
            world.clear_faults()
        elif what == "rest":
            if args[1] == "here":
                world.rest_here()
            else:
                world.rest_off()
        else:
            self._pilot(world, args[1:])
        self.say(f"{stamp(self._t())} world: {' '.join(split(self._line)[1:])}")

    def _pilot(self, world: SimWorld, args: tuple) -> None:  # type: ignore[type-arg]
        what = args[0]
        if what == "carry":
            world.pilot_carries(args[1])
        elif what == "stiffness":
            world.pilot_stiffness(args[1])
        elif what == "hold":
            world.pilot_hold_here()
        elif what == "stop":
            world.pilot_stop()
        elif what == "move":
            try:
                sample = self.runtime.last_sample
                seed = sample.q_rad if sample is not None else None
                q_rad = self.runtime.shoulder.q_from_isb(np.deg2rad(args[1]), seed=seed)
            except UnreachablePoseError as exc:
                raise CommandError(f"sim pilot move: {exc}") from None
            end = world.pilot_move(q_rad, args[2])
            self.say(f"  the pilot moves the arm to that pose until t = {end:.1f} s")
        else:
            end = world.pilot_sweep(self.runtime.settings.identification, args[1])
            self.say(f"  the pilot moves through the session's waypoints until t = {end:.1f} s")

    # --- internals ------------------------------------------------------------------------

    def _t(self) -> float | None:
        sample = self.runtime.last_sample
        return sample.t_s if sample is not None else None

    def _answer(self, ticket: Ticket) -> None:
        response = self.runtime.wait(ticket, self.timeout_s)
        self.tally.response = response
        self.tally.response_counted = not response.accepted
        if response.accepted:
            self.say(f"{stamp(self._t())} {response.request}: accepted, state {response.state}")
        else:
            self.record_failure(f"{response.request}: refused ({response.reason})")
            self.say(f"{stamp(self._t())} {response.request}: refused ({response.reason})")


def pilot_code_of(pilot: str) -> str:
    """The records' code of a session's pilot (a simulated scenario's pilot is ``sim-SCENARIO``)."""
    from daror_runtime.records.index import pilot_code

    return pilot_code(pilot)[0]
