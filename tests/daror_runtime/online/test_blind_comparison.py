"""Issue 29, part 3: the blind comparison of two approved models, end to end on the simulated plant.

The session of ``session.txt``'s order (the A Priori model confirmed in rom_limits, PLF+ validated
later) compares PLF+ with the A Priori model; the simulated pilot moves between two poses in every
block and rates it by his own effort (with a person's scatter).
"""

from __future__ import annotations

import json
from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bench.online_harness import SimulatedSession, fitted_model
from daror_runtime.online.compare import Comparison, balanced_order


@given(st.integers(1, 30), st.integers(0, 2**31 - 1))
def test_the_order_is_balanced_pairs_of_both_models(pairs: int, seed: int) -> None:
    order = balanced_order(pairs, seed)
    assert len(order) == 2 * pairs
    assert all(sorted(order[i : i + 2]) == [0, 1] for i in range(0, len(order), 2))
    leaders = order[::2]
    assert abs(leaders.count(0) - leaders.count(1)) <= pairs % 2
    assert balanced_order(pairs, seed) == order  # the seed reproduces it


def test_the_verdict_pairs_the_ratings() -> None:
    comparison = Comparison.planned(("B", "A"), 6, 10.0, 3)
    for block in comparison.blocks:  # B always a point better, with a little scatter
        block.rating = (7.0 if block.model == 0 else 6.0) + 0.1 * (block.number % 3)
    verdict = comparison.verdict()
    assert verdict["pairs"] == 6
    assert verdict["ratings"]["mean_difference"] == pytest.approx(1.0, abs=0.2)
    assert verdict["ratings"]["p_paired_t"] < 0.001
    assert verdict["preferred"] == "B"
    for block in comparison.blocks:  # no difference at all: no preference
        block.rating = 5.0
    assert comparison.verdict()["preferred"] is None


@pytest.fixture(scope="module")
def compared(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[SimulatedSession, dict, float]]:
    folder = tmp_path_factory.mktemp("compare")
    model, validation = fitted_model("exo_dummy_arm", folder)
    session = SimulatedSession("exo_dummy_arm", folder / "session", model, validation, a_priori_first=True)
    start = session.runtime.last_sample.t_s
    verdict = session.blind_comparison(pairs=6, block_s=15.0, seed=11)
    yield session, verdict, session.runtime.last_sample.t_s - start
    session.close()


def test_a_blind_comparison_picks_plf_plus_over_a_priori(compared: tuple[SimulatedSession, dict, float]) -> None:
    session, verdict, robot_s = compared
    assert verdict["preferred"] == "PLF+ (model_plf_plus.json)"
    assert verdict["ratings"]["p_paired_t"] < 0.05
    assert robot_s < 600.0  # under 10 minutes of robot time
    assert verdict["pairs"] == 6
    # the simulated pilot's own effort (the truth) is what he rated: less of it under PLF+
    effort = {
        label: [b["pilot_effort_nm"] for b in verdict["blocks"] if b["model"] == label] for label in verdict["models"]
    }
    assert max(effort["PLF+ (model_plf_plus.json)"]) < min(effort["A Priori (the robot description)"])
    # the order was balanced and hidden until now: the status never named a block's model
    leaders = verdict["order"][::2]
    assert leaders.count(verdict["models"][0]) == leaders.count(verdict["models"][1]) == 3
    written = json.loads((session.runtime.session_dir / "comparison.json").read_text(encoding="utf-8"))
    assert written["ratings"] == verdict["ratings"]
    assert "the pilot preferred PLF+" in (session.runtime.session_dir / "comparison.md").read_text(encoding="utf-8")
    # afterwards the validated model supports him again
    assert session.core.modes.compensation.model is not session.core.a_priori


def test_every_switch_is_bumpless(tmp_path_factory: pytest.TempPathFactory) -> None:
    """As a state's entry (issue 9's test): a limp arm through a switch to the A Priori model, some Nm
    apart, stays within 1 deg, and the support never dips below what held it until he moves."""
    folder = tmp_path_factory.mktemp("switch")
    model, validation = fitted_model("exo_dummy_arm", folder)
    session = SimulatedSession("exo_dummy_arm", folder / "session", model, validation, a_priori_first=True)
    try:
        runtime, compensation = session.runtime, session.core.modes.compensation
        session.world.pilot_hold_here()
        session.run(1.0)
        session.world.pilot_carries(0.0)  # he relaxes completely: only the support holds his arm
        session.world.pilot_stiffness(0.0)
        session.run(1.0)
        held = session.hal.truth().tau_spring_nm.copy()
        seed = next(s for s in range(100) if balanced_order(2, s)[0] == 1)  # the A Priori model first: a switch at once
        response = runtime.wait(runtime.compare(2, 5.0, seed))
        assert response.accepted, response.reason
        assert compensation.model is session.core.a_priori
        poses, springs = [], []
        for _ in range(3000):  # 3 s
            runtime.runner.run_ticks(1)
            poses.append(runtime.last_sample.q_rad.copy())
            springs.append(session.hal.truth().tau_spring_nm.copy())
        target = np.asarray(session.core.a_priori.torque(poses[0]), dtype=float)
        assert np.abs(target - held).max() > 0.5  # the two models really differ here
        moved_deg = np.rad2deg(np.abs(np.array(poses) - poses[0]).max())
        assert moved_deg < 1.0, moved_deg
        dip = np.sign(held) * (held - np.array(springs))
        assert dip.max() < 0.1, dip.max(axis=0)  # never below what held his arm (issue 9: DIP_NM)
    finally:
        session.close()


def test_a_comparison_and_a_rating_are_refused_where_they_cannot_be(
    compared: tuple[SimulatedSession, dict, float],
) -> None:
    session, _, _ = compared
    runtime = session.runtime
    refused = runtime.wait(runtime.rate(7.0))
    assert not refused.accepted
    assert "no block of a blind comparison waits for a rating" in refused.reason
    runtime.wait(runtime.revert())
    session.run(0.3)
    outside = runtime.wait(runtime.compare(4, 10.0, 1))
    assert not outside.accepted
    assert "runs in state compensation" in outside.reason
