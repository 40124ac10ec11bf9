"""The FSM diagram's layout (daror_runtime.fsm.diagram.layout): complete, consistent with the transition
table, and readable (no overlapping boxes, labels or routes), on the repository's spec and on variants."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import pytest
import yaml

from daror_runtime.fsm.diagram import layout, mermaid
from daror_runtime.fsm.machine import Event, transition_table
from daror_runtime.fsm.spec import DEFAULT_SPEC_PATH, FsmSpec, load_fsm_spec

Box = tuple[float, float, float, float]  # x, y, w, h
TOL = 1.0  # units


def _base() -> dict[str, Any]:
    data = yaml.safe_load(DEFAULT_SPEC_PATH.read_text())
    assert isinstance(data, dict)
    return data


def _state(number: int, name: str, superstate: str, **extra: Any) -> dict[str, Any]:
    return {
        "number": number,
        "name": name,
        "superstate": superstate,
        "description": f"{name} (a test variant)",
        "mode": "torque_off",
        "limits": {"torque_nm": 0.0, "velocity_rad_s": 1.0},
        "fail_on_fault": True,
        **extra,
    }


def _extra_state() -> dict[str, Any]:
    """One more state at the end of operative, and guarded resets (the first state's own included)."""
    data = _base()
    data["states"].append(
        _state(
            len(data["states"]) + 1,
            "parking",
            "operative",
            guards={"revert": ["compensation_model_approved", "arm_inside_isb_limits"]},
        )
    )
    by_name = {s["name"]: s for s in data["states"]}
    for name, guards in {
        "startup": ["hal_connected"],
        "settings": ["robot_at_rest"],
        "identification": ["robot_at_rest"],
        "parking": ["robot_at_rest", "no_active_faults"],
    }.items():
        by_name[name].setdefault("guards", {})["reset"] = guards
    return data


def _extra_superstate() -> dict[str, Any]:
    """A fourth superstate holding one state, with a superstate name longer than any of the spec's."""
    data = _base()
    data["superstates"].append({"name": "shutdown_and_removal_of_the_pilot", "description": "after the session"})
    data["states"].append(
        _state(
            len(data["states"]) + 1,
            "pilot_removal_and_shutdown_of_drives",
            "shutdown_and_removal_of_the_pilot",
            guards={"revert": ["compensation_model_approved", "robot_at_rest", "arm_inside_isb_limits"]},
        )
    )
    return data


def _minimal() -> dict[str, Any]:
    """One superstate, one state."""
    data = _base()
    data["superstates"] = data["superstates"][:1]
    data["states"] = [_state(1, "only", data["superstates"][0]["name"])]
    return data


VARIANTS = {"extra_state": _extra_state, "extra_superstate": _extra_superstate, "minimal": _minimal}


@pytest.fixture(params=["default", *VARIANTS])
def spec(request: pytest.FixtureRequest, tmp_path: Path) -> FsmSpec:
    if request.param == "default":
        return load_fsm_spec()
    path = tmp_path / "fsm_spec.yaml"
    path.write_text(yaml.safe_dump(copy.deepcopy(VARIANTS[request.param]()), sort_keys=False))
    return load_fsm_spec(path)


def _box(item: dict[str, Any]) -> Box:
    return item["x"], item["y"], item["w"], item["h"]


def _label(edge: dict[str, Any]) -> Box:
    return edge["label_x"], edge["label_y"], edge["label_w"], edge["label_h"]


def _overlap(a: Box, b: Box) -> bool:
    """The interiors of ``a`` and ``b`` intersect."""
    return a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3]


def _inside(inner: Box, outer: Box, tol: float = 0.0) -> bool:
    return (
        inner[0] >= outer[0] - tol
        and inner[1] >= outer[1] - tol
        and inner[0] + inner[2] <= outer[0] + outer[2] + tol
        and inner[1] + inner[3] <= outer[1] + outer[3] + tol
    )


def _on_border(point: list[float], box: Box, tol: float = TOL) -> bool:
    x, y = point
    bx, by, bw, bh = box
    within_x = bx - tol <= x <= bx + bw + tol
    within_y = by - tol <= y <= by + bh + tol
    on_vertical = within_y and (abs(x - bx) <= tol or abs(x - (bx + bw)) <= tol)
    on_horizontal = within_x and (abs(y - by) <= tol or abs(y - (by + bh)) <= tol)
    return on_vertical or on_horizontal


def _segments(edge: dict[str, Any]) -> list[tuple[list[float], list[float]]]:
    return list(zip(edge["points"], edge["points"][1:], strict=False))


def _segment_hits(a: list[float], b: list[float], box: Box) -> bool:
    """The axis-parallel segment a-b passes through the interior of ``box`` (shrunk by half a unit)."""
    x0, x1 = sorted((a[0], b[0]))
    y0, y1 = sorted((a[1], b[1]))
    interior = (box[0] + 0.5, box[1] + 0.5, box[2] - 1.0, box[3] - 1.0)
    return _overlap((x0, y0, max(x1 - x0, 1e-6), max(y1 - y0, 1e-6)), interior)


def _expected_edges(spec: FsmSpec) -> set[tuple[str, str, str, tuple[str, ...]]]:
    table = transition_table(spec)
    fail = spec.fail.name
    expected = set()
    for (source, event), t in table.items():
        drawn = event in (Event.ADVANCE, Event.REVERT) or (event == Event.RESET and (bool(t.guards) or source == fail))
        if drawn:
            expected.add((source, event.value, t.dest, t.guards))
    return expected


def test_every_state_once_and_fail_apart(spec: FsmSpec) -> None:
    drawn = layout(spec)
    names = [s["name"] for s in drawn["states"]]
    assert names == [s.name for s in spec.states] + [spec.fail.name]
    (fail,) = [s for s in drawn["states"] if s["fail"]]
    assert fail["name"] == spec.fail.name
    assert fail["superstate"] is None
    for node, state in zip(drawn["states"], spec.states, strict=False):
        assert (node["number"], node["superstate"], node["mode"]) == (state.number, state.superstate, state.mode)
        assert node["test"] is (not state.fail_on_fault)
        assert node["fail"] is False
    assert [b["name"] for b in drawn["superstates"]] == [s.name for s in spec.superstates]
    for band in drawn["superstates"]:  # FAIL is set apart: in no band
        assert not _overlap(_box(fail), _box(band))


def test_edges_are_those_of_the_transition_table(spec: FsmSpec) -> None:
    drawn = layout(spec)
    edges = [(e["source"], e["event"], e["dest"], tuple(e["guards"])) for e in drawn["edges"]]
    assert len(edges) == len(set(edges))
    assert set(edges) == _expected_edges(spec)
    assert Event.FAIL.value not in {e["event"] for e in drawn["edges"]}


def test_edges_match_the_mermaid_diagram_but_the_fault_edges(spec: FsmSpec) -> None:
    source = mermaid(spec)
    arrows = {line.strip().split(":")[0] for line in source.splitlines() if " --> " in line and "[*]" not in line}
    faults = {f"{s.name} --> {spec.fail.name}" for s in spec.states if s.fail_on_fault}
    assert {f"{e['source']} --> {e['dest']}" for e in layout(spec)["edges"]} == arrows - faults


def test_notes_say_what_is_not_drawn(spec: FsmSpec) -> None:
    notes = layout(spec)["notes"]
    tests = ", ".join(str(s.number) for s in spec.test_states) or "none"
    assert any(f"returns to {spec.first.number} {spec.first.name}" in n for n in notes)
    assert any(f"({tests})" in n and f"enters {spec.fail.name}" in n for n in notes)


def test_no_two_nodes_overlap_and_nodes_sit_in_their_band(spec: FsmSpec) -> None:
    drawn = layout(spec)
    boxes = [_box(s) for s in drawn["states"]]
    for i, a in enumerate(boxes):
        for b in boxes[i + 1 :]:
            assert not _overlap(a, b), (a, b)
    bands = {b["name"]: _box(b) for b in drawn["superstates"]}
    for node in drawn["states"]:
        if node["superstate"] is not None:
            assert _inside(_box(node), bands[node["superstate"]]), node["name"]
    band_boxes = list(bands.values())
    for i, a in enumerate(band_boxes):
        for b in band_boxes[i + 1 :]:
            assert not _overlap(a, b)


def test_everything_inside_the_canvas(spec: FsmSpec) -> None:
    drawn = layout(spec)
    canvas = (0.0, 0.0, drawn["width"], drawn["height"])
    assert 420 <= drawn["width"] <= 500 or spec.first.guards.reset  # compact unless many reset lanes
    for item in drawn["states"] + drawn["superstates"]:
        assert _inside(_box(item), canvas), item["name"]
    for edge in drawn["edges"]:
        assert _inside(_label(edge), canvas)
        for x, y in edge["points"]:
            assert 0 <= x <= drawn["width"]
            assert 0 <= y <= drawn["height"]
    for line in drawn["note_lines"]:
        assert line["x"] >= 0
        assert line["y"] <= drawn["height"]
        assert line["x"] + 0.6 * 7 * len(line["text"]) <= drawn["width"]


def test_edges_run_from_border_to_border(spec: FsmSpec) -> None:
    drawn = layout(spec)
    boxes = {s["name"]: _box(s) for s in drawn["states"]}
    for edge in drawn["edges"]:
        points = edge["points"]
        assert len(points) >= 2
        assert _on_border(points[0], boxes[edge["source"]]), edge
        assert _on_border(points[-1], boxes[edge["dest"]]), edge
        for a, b in _segments(edge):  # axis-parallel routes
            assert a[0] == b[0] or a[1] == b[1], edge


def test_routes_avoid_the_other_nodes_and_every_label(spec: FsmSpec) -> None:
    drawn = layout(spec)
    boxes = {s["name"]: _box(s) for s in drawn["states"]}
    for edge in drawn["edges"]:
        for a, b in _segments(edge):
            for name, box in boxes.items():
                assert not _segment_hits(a, b, box), (edge["source"], edge["dest"], name)
            for other in drawn["edges"]:
                assert not _segment_hits(a, b, _label(other)), (edge["source"], edge["dest"], other["source"])


def test_labels_overlap_neither_nodes_nor_each_other(spec: FsmSpec) -> None:
    drawn = layout(spec)
    labels = [_label(e) for e in drawn["edges"]]
    for label in labels:
        assert label[2] > 0
        assert label[3] >= 9  # room for a line of text
        for node in drawn["states"]:
            assert not _overlap(label, _box(node))
    for i, a in enumerate(labels):
        for b in labels[i + 1 :]:
            assert not _overlap(a, b), (a, b)


def test_advance_goes_down_and_revert_routes_apart(spec: FsmSpec) -> None:
    drawn = layout(spec)
    boxes = {s["name"]: _box(s) for s in drawn["states"]}
    advances = [e for e in drawn["edges"] if e["event"] == "advance"]
    reverts = [e for e in drawn["edges"] if e["event"] == "revert"]
    for edge in advances:
        assert edge["points"][-1][1] > edge["points"][0][1]  # forward is down
    right = max(b[0] + b[2] for b in boxes.values())
    advance_xs = {p[0] for e in advances for p in e["points"]}
    for edge in reverts:
        assert edge["points"][-1][1] < edge["points"][0][1]  # back is up
        assert max(p[0] for p in edge["points"]) > right  # on the other side, beside the column
        assert not advance_xs & {p[0] for p in edge["points"][1:-1]}
    # No two routes share a stretch of line.
    segments = [(e["source"], e["event"], a, b) for e in drawn["edges"] for a, b in _segments(e)]
    for i, (s1, e1, a1, b1) in enumerate(segments):
        for s2, e2, a2, b2 in segments[i + 1 :]:
            if (s1, e1) == (s2, e2):
                continue
            if a1[0] == b1[0] == a2[0] == b2[0]:
                lo1, hi1 = sorted((a1[1], b1[1]))
                lo2, hi2 = sorted((a2[1], b2[1]))
                assert min(hi1, hi2) <= max(lo1, lo2), (s1, e1, s2, e2)
            if a1[1] == b1[1] == a2[1] == b2[1]:
                lo1, hi1 = sorted((a1[0], b1[0]))
                lo2, hi2 = sorted((a2[0], b2[0]))
                assert min(hi1, hi2) <= max(lo1, lo2), (s1, e1, s2, e2)


def test_json_ready_and_deterministic(spec: FsmSpec) -> None:
    drawn = layout(spec)
    assert json.loads(json.dumps(drawn)) == drawn
    assert layout(spec) == drawn
