"""The diagram of a spec, generated (Appendix A's lost Fig. A.1, regenerated from ``fsm_spec.yaml``).

Mermaid ``stateDiagram-v2``: it renders in the Markdown viewers of GitHub and GitLab and in most
editors without another tool, and it is text, so a change of the spec shows in a review as a
change of the diagram. Superstates are composite states; every edge is labelled with its event
and guards. Reset edges are drawn only where a state has reset guards (every state may reset to
the first state; a note says so instead of ten unlabelled arrows).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from daror_runtime.fsm.machine import Event, Transition, transition_table
from daror_runtime.fsm.spec import FsmSpec, StateSpec


def _state_text(state: StateSpec) -> str:
    test = ", e-stop test" if not state.fail_on_fault else ""
    isb = ", ISB limits" if state.enforce_isb else ""
    limits = f"{state.limits.torque_nm:g} Nm, {state.limits.velocity_rad_s:g} rad/s"
    return f"{state.number} {state.name}{test}<br/>{state.mode}, {limits}{isb}"


def _edge_text(event: Event, guards: tuple[str, ...]) -> str:
    return event.value if not guards else f"{event.value} [{', '.join(guards)}]"


def mermaid(spec: FsmSpec) -> str:
    """The Mermaid source of ``spec``'s diagram (ends with a newline)."""
    lines = ["stateDiagram-v2", "    direction TB", f"    [*] --> {spec.first.name}"]
    for superstate in spec.superstates:
        members = [s for s in spec.states if s.superstate == superstate.name]
        lines.append(f'    state "{superstate.name}" as {superstate.name} {{')
        lines.extend(f"        {s.name}: {_state_text(s)}" for s in members)
        lines.append("    }")
    fail = spec.fail
    lines.append(f"    {fail.name}: {fail.name}<br/>{fail.mode}")
    table = transition_table(spec)
    for (source, event), t in table.items():
        if source == fail.name:
            continue  # drawn last, below the fault edges
        if event in (Event.ADVANCE, Event.REVERT) or (event == Event.RESET and t.guards):
            lines.append(f"    {source} --> {t.dest}: {_edge_text(event, t.guards)}")
    for state in spec.states:
        if (state.name, Event.FAIL) in table:
            lines.append(f"    {state.name} --> {fail.name}: fault")
    reset = table[(fail.name, Event.RESET)]
    lines.append(f"    {fail.name} --> {spec.first.name}: {_edge_text(Event.RESET, reset.guards)}")
    tests = ", ".join(str(s.number) for s in spec.test_states) or "none"
    lines += [
        f"    note right of {spec.first.name}",
        f"        reset from every state returns to {spec.first.number} {spec.first.name}",
        f"        e-stop test states ({tests}): a fault is met by its reaction and recorded, no {fail.name}",
        "    end note",
    ]
    return "\n".join(lines) + "\n"


# --- The layout the web console draws as SVG (static/fsm.js) -----------------------------------
#
# All lengths are abstract pixel units (the SVG's user units; the browser scales the drawing to the
# width of its card). The superstates are horizontal bands stacked top to bottom in spec order, each
# holding its states in one column, so the states read top to bottom in advance order:
#
#   left lanes | state boxes (one column) | revert lane | labels of revert and reset edges
#
# Advance edges are short vertical arrows between consecutive boxes (label in the gap, right of the
# arrow); revert edges leave the right border, run up the revert lane and enter the previous box's
# right border; reset edges (those with guards, and FAIL's) leave the left border, run up a lane of
# their own on the left and enter the first state's left border. FAIL sits below the bands, the
# notes to its right. Every edge has a label area (label_x, label_y: its top-left corner; label_w,
# label_h: its size) that no node, other label or edge route overlaps.

#: Canvas margin, units.
MARGIN = 6.0
#: Smallest canvas width, units (the card is about 420 px wide).
MIN_WIDTH = 460.0
#: State box size, units.
BOX_W = 200.0
BOX_H = 20.0
#: Vertical gap between consecutive boxes of a band (holds the advance label), units.
GAP = 18.0
#: Band padding above its first box (holds its title), below its last box, and between bands, units.
BAND_TOP = 18.0
BAND_BOTTOM = 6.0
BAND_SPACING = 8.0
#: Gap between the last band and FAIL (holds FAIL's reset label), units.
FAIL_GAP = 24.0
#: FAIL's box width, units (the notes are written to its right).
FAIL_W = 80.0
#: Distance between neighbouring left lanes, units.
LANE_STEP = 8.0
#: Horizontal offset of the advance arrows from the boxes' left border, units.
ADVANCE_X = 14.0
#: Distance of the revert lane from the boxes' right border, units.
REVERT_LANE = 14.0
#: Vertical offset from a box's centre at which revert edges leave (above) and enter (below), units.
REVERT_DY = 5.0
#: Padding between a label area and the route it belongs to, units.
LABEL_PAD = 5.0
#: Narrowest label column right of the revert lane, units (the canvas widens to keep it).
MIN_LABEL_W = 170.0
#: The notes' font size, line height and estimated character width (0.6 em, a monospace advance), units.
NOTE_FONT = 7.0
NOTE_LINE = 8.5
NOTE_CHAR_W = 0.6 * NOTE_FONT


def _box(x: float, y: float, w: float, h: float) -> dict[str, float]:
    return {"x": round(x, 2), "y": round(y, 2), "w": round(w, 2), "h": round(h, 2)}


def _points(*points: tuple[float, float]) -> list[list[float]]:
    return [[round(x, 2), round(y, 2)] for x, y in points]


def _label(x: float, y: float, w: float, h: float) -> dict[str, float]:
    return {"label_x": round(x, 2), "label_y": round(y, 2), "label_w": round(w, 2), "label_h": round(h, 2)}


def _wrap(text: str, width: float, char_w: float) -> list[str]:
    """``text`` wrapped at spaces into lines of at most ``width`` units (``char_w`` units a character)."""
    limit = max(1, int(width // char_w))
    lines: list[str] = []
    line = ""
    for word in text.split():
        candidate = f"{line} {word}" if line else word
        if len(candidate) <= limit or not line:
            line = candidate
        else:
            lines.append(line)
            line = word
    if line:
        lines.append(line)
    return lines


def _notes(spec: FsmSpec) -> list[str]:
    """What the layout does not draw as edges, in words (the fault edges and the unguarded resets)."""
    first = spec.first
    fail = spec.fail.name
    tests = ", ".join(str(s.number) for s in spec.test_states) or "none"
    return [
        f"a fault in any state but the e-stop test states ({tests}) enters {fail}",
        f"e-stop test states ({tests}): a fault is met by its reaction and recorded, no {fail}",
        f"reset from every state returns to {first.number} {first.name}",
    ]


@dataclass(frozen=True)
class _Frame:
    """Where one layout's edges run: the columns, the boxes and the lanes, units (see the sketch above)."""

    table: dict[tuple[str, Event], Transition]
    #: Left border of the state boxes; the revert lane; the label column right of it, and its width.
    box_x: float
    revert_x: float
    right_x: float
    right_w: float
    #: The canvas width.
    width: float
    #: How many left lanes (reset routes) there are.
    n_lanes: int
    #: Every node's box (``_box``) by name, FAIL's included.
    boxes: dict[str, dict[str, float]]

    def lane_x(self, k: int) -> float:
        """The x of left lane ``k`` (0 the innermost)."""
        return self.box_x - 10.0 - LANE_STEP * k

    def centre_y(self, name: str) -> float:
        """The y of the centre of node ``name``'s box."""
        return self.boxes[name]["y"] + self.boxes[name]["h"] / 2

    def entry_y(self, k: int, first: str) -> float:
        """Where left lane ``k`` enters the first state (``first``), the outermost highest."""
        first_box = self.boxes[first]
        step = min(5.0, (first_box["h"] - 6.0) / (self.n_lanes - 1)) if self.n_lanes > 1 else 0.0
        return self.centre_y(first) + step * ((self.n_lanes - 1) / 2 - k)

    def right_label(self, name: str, event: Event) -> dict[str, float]:
        """The right label column beside a source box: shared by its revert label (top) and reset label (bottom)."""
        box = self.boxes[name]
        both = (name, Event.REVERT) in self.table and bool(self.table[(name, Event.RESET)].guards)
        if not both:
            return _label(self.right_x, box["y"], self.right_w, box["h"])
        half = box["h"] / 2
        return _label(self.right_x, box["y"] + (half if event == Event.RESET else 0.0), self.right_w, half)


def layout(spec: FsmSpec) -> dict[str, Any]:
    """The diagram of ``spec`` laid out for drawing (JSON-ready: dicts, lists, str, float, int, bool, None).

    Lengths are abstract pixel units with the origin top left, y down. Keys:

    * ``width``, ``height``: the canvas;
    * ``superstates``: one band per superstate in spec order, ``{name, description, x, y, w, h}``;
    * ``states``: every state of the spec in advance order, then FAIL (below the bands, ``number``
      and ``superstate`` None), ``{name, number, superstate, mode, description, x, y, w, h, test,
      fail}``; ``test`` marks the e-stop test states (a fault does not enter FAIL);
    * ``edges``: the edges :func:`mermaid` draws except the fault edges: advance, revert, reset
      where it has guards, and FAIL's reset; ``{source, dest, event, guards, points, label_x,
      label_y, label_w, label_h}``, ``points`` an axis-parallel polyline from the source box's
      border to the dest box's border, the label area's top-left corner and size;
    * ``notes``: what is not drawn, in words; ``note_lines``: the notes wrapped to the right of FAIL,
      ``{text, x, y}`` with ``y`` the baseline, at a :data:`NOTE_FONT` unit font.
    """
    table = transition_table(spec)
    guarded_resets = _guarded_resets(spec, table)
    n_lanes = len(guarded_resets) + 1 + int(bool(table[(spec.first.name, Event.RESET)].guards))
    box_x = MARGIN + 8.0 + LANE_STEP * n_lanes + 2.0
    revert_x = box_x + BOX_W + REVERT_LANE
    right_x = revert_x + LABEL_PAD
    width = max(MIN_WIDTH, right_x + MIN_LABEL_W + 4.0 + MARGIN)
    band_boxes, boxes, bands_bottom = _bands(spec, box_x, width)
    fail_y = bands_bottom + FAIL_GAP
    boxes[spec.fail.name] = _box(box_x, fail_y, FAIL_W, BOX_H)
    frame = _Frame(table, box_x, revert_x, right_x, width - MARGIN - 4.0 - right_x, width, n_lanes, boxes)
    edges = _state_edges(spec, frame, guarded_resets, band_boxes)
    edges.append(_fail_reset_edge(spec, frame, len(guarded_resets), bands_bottom))
    note_lines, notes_bottom = _note_lines(spec, box_x + FAIL_W + 12.0, fail_y + NOTE_FONT, width)
    height = max(fail_y + BOX_H, notes_bottom) + MARGIN
    return {
        "width": round(width, 2),
        "height": round(height, 2),
        "superstates": band_boxes,
        "states": _nodes(spec, boxes),
        "edges": edges,
        "notes": _notes(spec),
        "note_lines": note_lines,
    }


def _guarded_resets(spec: FsmSpec, table: dict[tuple[str, Event], Transition]) -> list[StateSpec]:
    """The states 2..N whose reset has guards, top to bottom: the innermost left lanes, in this order.

    The left lanes, innermost first: these states' resets, FAIL's reset, then the first state's own
    guarded reset (a loop over its top). Outer lanes enter the first state higher up, so no two
    reset routes cross.
    """
    return [s for s in spec.states[1:] if table[(s.name, Event.RESET)].guards]


def _bands(
    spec: FsmSpec, box_x: float, width: float
) -> tuple[list[dict[str, Any]], dict[str, dict[str, float]], float]:
    """The superstates' bands and their states' boxes, top to bottom from the top margin.

    Returns:
        The bands (``{name, description, x, y, w, h}``), the state boxes by name, and the y of the
        last band's bottom, units.
    """
    band_boxes: list[dict[str, Any]] = []
    boxes: dict[str, dict[str, float]] = {}
    y = MARGIN
    for superstate in spec.superstates:
        members = [s for s in spec.states if s.superstate == superstate.name]
        top = y
        y += BAND_TOP
        for k, state in enumerate(members):
            if k:
                y += GAP
            boxes[state.name] = _box(box_x, y, BOX_W, BOX_H)
            y += BOX_H
        y += BAND_BOTTOM
        band_boxes.append(
            {
                "name": superstate.name,
                "description": superstate.description,
                **_box(MARGIN, top, width - 2 * MARGIN, y - top),
            }
        )
        y += BAND_SPACING
    return band_boxes, boxes, y - BAND_SPACING


def _nodes(spec: FsmSpec, boxes: dict[str, dict[str, float]]) -> list[dict[str, Any]]:
    """The layout's ``states``: every state in advance order, then FAIL, each with its box."""
    fail = spec.fail
    node_list: list[dict[str, Any]] = [
        {
            "name": s.name,
            "number": s.number,
            "superstate": s.superstate,
            "mode": s.mode,
            "description": s.description,
            **boxes[s.name],
            "test": not s.fail_on_fault,
            "fail": False,
        }
        for s in spec.states
    ]
    node_list.append(
        {
            "name": fail.name,
            "number": None,
            "superstate": None,
            "mode": fail.mode,
            "description": fail.description,
            **boxes[fail.name],
            "test": False,
            "fail": True,
        }
    )
    return node_list


def _edge(transition: Transition, event: Event, points: list[list[float]], label: dict[str, float]) -> dict[str, Any]:
    """One edge of the layout: its ends, event, guards, route and label area."""
    return {
        "source": transition.source,
        "dest": transition.dest,
        "event": event.value,
        "guards": list(transition.guards),
        "points": points,
        **label,
    }


def _state_edges(
    spec: FsmSpec, frame: _Frame, guarded_resets: list[StateSpec], band_boxes: list[dict[str, Any]]
) -> list[dict[str, Any]]:
    """The edges leaving the states, in the transition table's order: advance, revert, and reset where guarded."""
    edges: list[dict[str, Any]] = []
    lane_of = {s.name: k for k, s in enumerate(guarded_resets)}
    for (source, event), t in frame.table.items():
        if source == spec.fail.name:
            continue  # FAIL's reset is routed by _fail_reset_edge
        if event == Event.ADVANCE:
            edges.append(_advance_edge(spec, frame, t, band_boxes))
        elif event == Event.REVERT:
            edges.append(_revert_edge(frame, t))
        elif event == Event.RESET and t.guards:
            edges.append(_reset_edge(spec, frame, t, lane_of))
    return edges


def _advance_edge(spec: FsmSpec, frame: _Frame, t: Transition, band_boxes: list[dict[str, Any]]) -> dict[str, Any]:
    """An advance: a vertical arrow between consecutive boxes, its label in the gap right of it (the
    gap reaching up to the band's top when the advance enters another superstate)."""
    states = spec.states
    index = {s.name: i for i, s in enumerate(states)}
    src = frame.boxes[t.source]
    x = frame.box_x + ADVANCE_X
    points = _points((x, src["y"] + src["h"]), (x, frame.boxes[t.dest]["y"]))
    gap_top = src["y"] + src["h"]
    gap_bottom = frame.boxes[t.dest]["y"]
    if states[index[t.dest]].superstate != states[index[t.source]].superstate:
        gap_top = next(b["y"] for b in band_boxes if b["name"] == states[index[t.dest]].superstate)
    label = _label(
        x + LABEL_PAD, gap_top + 1.0, frame.revert_x - LABEL_PAD - (x + LABEL_PAD), gap_bottom - gap_top - 2.0
    )
    return _edge(t, Event.ADVANCE, points, label)


def _revert_edge(frame: _Frame, t: Transition) -> dict[str, Any]:
    """A revert: out of the right border above the centre, up the revert lane, into the previous box below its centre."""
    src = frame.boxes[t.source]
    y0 = frame.centre_y(t.source) - REVERT_DY
    y1 = frame.centre_y(t.dest) + REVERT_DY
    right = src["x"] + src["w"]
    points = _points((right, y0), (frame.revert_x, y0), (frame.revert_x, y1), (right, y1))
    return _edge(t, Event.REVERT, points, frame.right_label(t.source, Event.REVERT))


def _reset_edge(spec: FsmSpec, frame: _Frame, t: Transition, lane_of: dict[str, int]) -> dict[str, Any]:
    """A guarded reset: out of the left border, up its own left lane, into the first state's left border
    (the first state's own: out of its top, into the outermost lane)."""
    first = spec.first.name
    src = frame.boxes[t.source]
    box_x = frame.box_x
    if t.source == first:
        k = frame.n_lanes - 1
        x0 = box_x + 6.0
        above = src["y"] - 5.0
        lane, entry = frame.lane_x(k), frame.entry_y(k, first)
        points = _points((x0, src["y"]), (x0, above), (lane, above), (lane, entry), (box_x, entry))
    else:
        k = lane_of[t.source]
        y0 = frame.centre_y(t.source)
        lane, entry = frame.lane_x(k), frame.entry_y(k, first)
        points = _points((box_x, y0), (lane, y0), (lane, entry), (box_x, entry))
    return _edge(t, Event.RESET, points, frame.right_label(t.source, Event.RESET))


def _fail_reset_edge(spec: FsmSpec, frame: _Frame, k: int, bands_bottom: float) -> dict[str, Any]:
    """FAIL's reset: out of FAIL's left border, up left lane ``k``, into the first state; its label in
    the gap above FAIL."""
    reset = frame.table[(spec.fail.name, Event.RESET)]
    box_x = frame.box_x
    y0 = frame.centre_y(spec.fail.name)
    lane, entry = frame.lane_x(k), frame.entry_y(k, spec.first.name)
    points = _points((box_x, y0), (lane, y0), (lane, entry), (box_x, entry))
    label = _label(box_x, bands_bottom + 1.0, frame.width - MARGIN - 4.0 - box_x, FAIL_GAP - 2.0)
    return _edge(reset, Event.RESET, points, label)


def _note_lines(spec: FsmSpec, notes_x: float, baseline: float, width: float) -> tuple[list[dict[str, Any]], float]:
    """The notes wrapped into the column from ``notes_x`` to the canvas's right margin, the first
    baseline at ``baseline``.

    Returns:
        The lines (``{text, x, y}``, ``y`` the baseline), and the y of the last line's bottom, units.
    """
    note_lines: list[dict[str, Any]] = []
    for note in _notes(spec):
        for line in _wrap(note, width - MARGIN - 4.0 - notes_x, NOTE_CHAR_W):
            note_lines.append({"text": line, "x": round(notes_x, 2), "y": round(baseline, 2)})
            baseline += NOTE_LINE
    return note_lines, baseline - NOTE_LINE + 2.0
