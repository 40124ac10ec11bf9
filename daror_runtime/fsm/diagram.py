"""The diagram of a spec, generated (Appendix A's lost Fig. A.1, regenerated from ``fsm_spec.yaml``).

Mermaid ``stateDiagram-v2``: it renders in the Markdown viewers of GitHub and GitLab and in most
editors without another tool, and it is text, so a change of the spec shows in a review as a
change of the diagram. Superstates are composite states; every edge is labelled with its event
and guards. Reset edges are drawn only where a state has reset guards (every state may reset to
the first state; a note says so instead of ten unlabelled arrows).
"""

from __future__ import annotations

from typing import Any

from daror_runtime.fsm.machine import Event, transition_table
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
    states = spec.states
    first = spec.first
    fail = spec.fail
    index = {s.name: i for i, s in enumerate(states)}

    # Left lanes, innermost first: the guarded resets of states 2..N (top to bottom), FAIL's reset,
    # then the first state's own guarded reset (a loop over its top). Outer lanes enter the first
    # state higher up, so no two reset routes cross.
    guarded_resets = [s for s in states[1:] if table[(s.name, Event.RESET)].guards]
    first_resets_itself = bool(table[(first.name, Event.RESET)].guards)
    n_lanes = len(guarded_resets) + 1 + int(first_resets_itself)
    box_x = MARGIN + 8.0 + LANE_STEP * n_lanes + 2.0

    def lane_x(k: int) -> float:
        return box_x - 10.0 - LANE_STEP * k

    revert_x = box_x + BOX_W + REVERT_LANE
    right_x = revert_x + LABEL_PAD
    width = max(MIN_WIDTH, right_x + MIN_LABEL_W + 4.0 + MARGIN)
    right_w = width - MARGIN - 4.0 - right_x

    # Bands and boxes, top to bottom.
    band_boxes: list[dict[str, Any]] = []
    boxes: dict[str, dict[str, float]] = {}
    y = MARGIN
    for superstate in spec.superstates:
        members = [s for s in states if s.superstate == superstate.name]
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
    bands_bottom = y - BAND_SPACING
    fail_y = bands_bottom + FAIL_GAP
    boxes[fail.name] = _box(box_x, fail_y, FAIL_W, BOX_H)

    def centre_y(name: str) -> float:
        return boxes[name]["y"] + boxes[name]["h"] / 2

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
        for s in states
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

    # The right label column beside a source box: shared by its revert label (top) and reset label (bottom).
    def right_label(name: str, event: Event) -> dict[str, float]:
        box = boxes[name]
        both = (name, Event.REVERT) in table and bool(table[(name, Event.RESET)].guards)
        if not both:
            return _label(right_x, box["y"], right_w, box["h"])
        half = box["h"] / 2
        return _label(right_x, box["y"] + (half if event == Event.RESET else 0.0), right_w, half)

    # Where the left lanes enter the first state, the outermost highest.
    first_box = boxes[first.name]
    step = min(5.0, (first_box["h"] - 6.0) / (n_lanes - 1)) if n_lanes > 1 else 0.0
    entry_mid = centre_y(first.name)

    def entry_y(k: int) -> float:
        return entry_mid + step * ((n_lanes - 1) / 2 - k)

    edges: list[dict[str, Any]] = []
    lane_of = {s.name: k for k, s in enumerate(guarded_resets)}
    for (source, event), t in table.items():
        if source == fail.name:
            continue
        src = boxes[source]
        if event == Event.ADVANCE:
            x = box_x + ADVANCE_X
            points = _points((x, src["y"] + src["h"]), (x, boxes[t.dest]["y"]))
            gap_top = src["y"] + src["h"]
            gap_bottom = boxes[t.dest]["y"]
            if states[index[t.dest]].superstate != states[index[source]].superstate:
                gap_top = next(b["y"] for b in band_boxes if b["name"] == states[index[t.dest]].superstate)
            label = _label(
                x + LABEL_PAD, gap_top + 1.0, revert_x - LABEL_PAD - (x + LABEL_PAD), gap_bottom - gap_top - 2.0
            )
        elif event == Event.REVERT:
            y0 = centre_y(source) - REVERT_DY
            y1 = centre_y(t.dest) + REVERT_DY
            right = src["x"] + src["w"]
            points = _points((right, y0), (revert_x, y0), (revert_x, y1), (right, y1))
            label = right_label(source, event)
        elif event == Event.RESET and t.guards:
            if source == first.name:
                k = n_lanes - 1
                x0 = box_x + 6.0
                above = src["y"] - 5.0
                points = _points(
                    (x0, src["y"]), (x0, above), (lane_x(k), above), (lane_x(k), entry_y(k)), (box_x, entry_y(k))
                )
            else:
                k = lane_of[source]
                y0 = centre_y(source)
                points = _points((box_x, y0), (lane_x(k), y0), (lane_x(k), entry_y(k)), (box_x, entry_y(k)))
            label = right_label(source, event)
        else:
            continue
        edges.append(
            {
                "source": source,
                "dest": t.dest,
                "event": event.value,
                "guards": list(t.guards),
                "points": points,
                **label,
            }
        )
    reset = table[(fail.name, Event.RESET)]
    k = len(guarded_resets)
    y0 = centre_y(fail.name)
    edges.append(
        {
            "source": fail.name,
            "dest": reset.dest,
            "event": Event.RESET.value,
            "guards": list(reset.guards),
            "points": _points((box_x, y0), (lane_x(k), y0), (lane_x(k), entry_y(k)), (box_x, entry_y(k))),
            **_label(box_x, bands_bottom + 1.0, width - MARGIN - 4.0 - box_x, FAIL_GAP - 2.0),
        }
    )

    # The notes, wrapped to the right of FAIL.
    notes_x = box_x + FAIL_W + 12.0
    note_lines: list[dict[str, Any]] = []
    baseline = fail_y + NOTE_FONT
    for note in _notes(spec):
        for line in _wrap(note, width - MARGIN - 4.0 - notes_x, NOTE_CHAR_W):
            note_lines.append({"text": line, "x": round(notes_x, 2), "y": round(baseline, 2)})
            baseline += NOTE_LINE
    notes_bottom = baseline - NOTE_LINE + 2.0
    height = max(fail_y + BOX_H, notes_bottom) + MARGIN
    return {
        "width": round(width, 2),
        "height": round(height, 2),
        "superstates": band_boxes,
        "states": node_list,
        "edges": edges,
        "notes": _notes(spec),
        "note_lines": note_lines,
    }
