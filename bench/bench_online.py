"""The online indicators against the simulated pilot's truth (issue 29; the figures of docs/online.md).

For each simulated pilot (the Dummy Arm, the heavier arm of ``exo_heavy_arm``) a lock-step session
reaches compensation with a PLF+ model fitted on his simulated identification data; he holds four
poses at support levels 1.0, 0.7 and 0.4 carrying what the robot does not, then again at 1.0 under
the same model with a known error added (``bench/online_harness.py``). Figures, over every rest:
the largest error of the effort at rest against his true effort per joint, what the estimate adds
to the model's own error there, the support delivered against the level asked; while moving, the
interaction torque's RMS against his true torque's; and the cost of one observation between ticks.

Run alone: ``python bench/bench_online.py`` prints the table of docs/online.md.
"""

from __future__ import annotations

import statistics
import sys
import time

import numpy as np

from bench.online_harness import SimulatedSession, fitted_model, temporary_folder
from daror_runtime.bench import BenchFigure
from daror_runtime.session.online import observe_online

PILOTS = ("exo_dummy_arm", "exo_heavy_arm")
KNOWN_ERROR_NM = np.array([0.3, -0.5, 0.2, 0.4])


def measure(scenario: str) -> dict[str, object]:
    """One pilot's session: the rows of docs/online.md and the cost of an observation."""
    folder = temporary_folder()
    model, validation = fitted_model(scenario, folder)
    session = SimulatedSession(scenario, folder / "session", model, validation)
    try:
        started = time.perf_counter()
        session.hold_poses()
        plain_name = str(session.core.modes.compensation.model.name)
        offset_name = session.use_offset(KNOWN_ERROR_NM)
        session.hold_poses(levels=(1.0,))
        wall_s = time.perf_counter() - started
        checks = session.rest_checks()
        online = {entry["model"]: entry for entry in session.runtime.status()["online"]}
        moving = {}
        for name in (plain_name, offset_name):
            truth_rms, samples = session.moving_truth(name)
            label = next(label for label in online if label.startswith(name + " ("))
            moving[name] = (truth_rms, np.array(online[label]["interaction_rms_nm"], dtype=float), samples)
        # one observation's cost: the service's call on a compensating session, the loop not ticking
        core = session.core
        calls = 2000
        started = time.perf_counter()
        for _ in range(calls):
            core.online.next_t_s = -np.inf
            observe_online(core)
        per_call_us = (time.perf_counter() - started) / calls * 1e6
    finally:
        session.close()
    drifting = SimulatedSession(scenario, folder / "drift", model, validation)
    try:
        drifting.run(0.5)
        plain = drifting.drift_tests()
        drifting.hold_poses()  # then the rests at the same poses, corrected by those drift tests
        corrected = [c for c in drifting.rest_checks() if c.corrected_nm is not None]
        drifting.use_offset(KNOWN_ERROR_NM)
        drift = [*plain, *drifting.drift_tests()]
    finally:
        drifting.close()
    compared = SimulatedSession(scenario, folder / "compare", model, validation, a_priori_first=True)
    try:
        start_t = compared.runtime.last_sample.t_s
        started = time.perf_counter()
        verdict = compared.blind_comparison(pairs=8, block_s=20.0, seed=29)
        comparison = {
            "verdict": verdict,
            "robot_s": compared.runtime.last_sample.t_s - start_t,
            "wall_s": time.perf_counter() - started,
        }
    finally:
        compared.close()
    return {
        "checks": checks,
        "moving": moving,
        "wall_s": wall_s,
        "observe_us": per_call_us,
        "drift": drift,
        "corrected": corrected,
        "comparison": comparison,
    }


def table(results: dict[str, dict[str, object]]) -> list[str]:
    lines = [
        "| pilot | model | level | rests | largest error vs his true effort (Nm, per joint) | "
        "what the estimate adds (Nm) | support delivered |",
        "|---|---|---|---|---|---|---|",
    ]
    for scenario, result in results.items():
        checks = result["checks"]
        assert isinstance(checks, list)
        keys = sorted({(c.model, c.level_asked) for c in checks}, key=lambda k: (k[0], -k[1]))
        for model, level in keys:
            rows = [c for c in checks if c.model == model and c.level_asked == level]
            error = np.max(np.abs([c.error_nm for c in rows]), axis=0)
            added = np.max(np.abs([c.estimator_error_nm for c in rows]), axis=0)
            delivered = [c.level_delivered for c in rows if c.level_delivered is not None]
            lines.append(
                f"| {scenario} | {model} | {level:.1f} | {len(rows)} | {' '.join(f'{v:.3f}' for v in error)} | "
                f"{' '.join(f'{v:.3f}' for v in added)} | {min(delivered):.3f}-{max(delivered):.3f} |"
            )
    lines += ["", "| pilot | model | his true torque while moving, RMS (Nm) | the indicator's (Nm) | samples |",
              "|---|---|---|---|---|"]  # fmt: skip
    for scenario, result in results.items():
        moving = result["moving"]
        assert isinstance(moving, dict)
        for name, (truth, estimate, samples) in moving.items():
            lines.append(
                f"| {scenario} | {name} | {' '.join(f'{v:.2f}' for v in truth)} | "
                f"{' '.join(f'{v:.2f}' for v in estimate)} | {' '.join(str(int(n)) for n in samples)} |"
            )
    lines += [
        "",
        "| pilot | model | caught | drift (deg) | unsupported torque (Nm) | the model's true error there (Nm) | "
        "moved once held (deg) |",
        "|---|---|---|---|---|---|---|",
    ]
    for scenario, result in results.items():
        for check in result["drift"]:  # type: ignore[attr-defined]
            r = check.result
            lines.append(
                f"| {scenario} | {r.model.split(' (')[0]} | {r.why_caught}, {r.drift_s:.2f} s | "
                f"{' '.join(f'{v:.2f}' for v in r.drift_deg)} | {' '.join(f'{v:.3f}' for v in r.unsupported_nm)} | "
                f"{' '.join(f'{v:.3f}' for v in check.model_error_nm)} | {check.held_drift_deg:.3f} |"
            )
    lines += [
        "",
        "| pilot | level | rests | his effort corrected by the drift test there: largest error (Nm, per joint) |",
        "|---|---|---|---|",
    ]
    for scenario, result in results.items():
        corrected = result["corrected"]
        for level in (1.0, 0.7, 0.4):
            rows = [c for c in corrected if c.level_asked == level]  # type: ignore[attr-defined]
            if rows:
                worst = np.max(np.abs([c.corrected_error_nm for c in rows]), axis=0)
                lines.append(f"| {scenario} | {level:.1f} | {len(rows)} | {' '.join(f'{v:.3f}' for v in worst)} |")
    lines += [
        "",
        "| pilot | pairs of 20 s blocks | preferred | mean ratings | paired t p | Wilcoxon p | robot time (s) | wall (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for scenario, result in results.items():
        c = result["comparison"]
        v = c["verdict"]  # type: ignore[index]
        means = ", ".join(f"{name.split(' (')[0]} {value:.2f}" for name, value in v["ratings"]["mean"].items())
        lines.append(
            f"| {scenario} | {v['pairs']} | {(v['preferred'] or 'none').split(' (')[0]} | {means} | "
            f"{v['ratings']['p_paired_t']:.2g} | {v['ratings']['p_wilcoxon']:.2g} | {c['robot_s']:.1f} | "  # type: ignore[index]
            f"{c['wall_s']:.1f} |"  # type: ignore[index]
        )
    return lines


def bench_online_indicators(quick: bool) -> list[BenchFigure]:
    results = {scenario: measure(scenario) for scenario in (PILOTS[:1] if quick else PILOTS)}
    added, errors, delivered, observe, walls = [], [], [], [], []
    for result in results.values():
        checks = result["checks"]
        assert isinstance(checks, list)
        added.append(float(np.max(np.abs([c.estimator_error_nm for c in checks]))))
        errors.append(float(np.max(np.abs([c.error_nm for c in checks if "known error" not in c.model]))))
        delivered.append(float(max(abs(c.level_delivered - c.level_asked) for c in checks if c.level_delivered)))
        observe.append(float(result["observe_us"]))  # type: ignore[arg-type]
        walls.append(float(result["wall_s"]))  # type: ignore[arg-type]
    drift_errors = [
        float(np.max(np.abs(check.error_nm)))
        for result in results.values()
        for check in result["drift"]  # type: ignore[attr-defined]
    ]
    held = [check.held_drift_deg for result in results.values() for check in result["drift"]]  # type: ignore[attr-defined]
    robot = [float(r["comparison"]["robot_s"]) for r in results.values()]  # type: ignore[index]
    p_values = [float(r["comparison"]["verdict"]["ratings"]["p_paired_t"]) for r in results.values()]  # type: ignore[index]
    corrected_errors = [
        float(np.max(np.abs(c.corrected_error_nm)))
        for r in results.values()
        for c in r["corrected"]  # type: ignore[attr-defined]
    ]
    n = len(results)
    return [
        BenchFigure(
            "effort at rest with PLF+, corrected by a drift test there: error (largest, any joint)",
            float(np.median(corrected_errors)),
            max(corrected_errors),
            "Nm",
            len(corrected_errors),
            target=0.05,
        ),
        BenchFigure(
            "blind comparison PLF+ against A Priori: robot time to the verdict",
            statistics.median(robot),
            max(robot),
            "s",
            n,
            target=600.0,
        ),
        BenchFigure(
            "blind comparison: paired t p (the pilot preferred PLF+)",
            statistics.median(p_values),
            max(p_values),
            "",
            n,
            target=0.05,
        ),
        BenchFigure(
            "drift test: unsupported torque against the model's true error (largest, any joint)",
            float(np.median(drift_errors)),
            max(drift_errors),
            "Nm",
            len(drift_errors),
        ),
        BenchFigure(
            "drift test: the arm moved once caught (largest)",
            float(np.median(held)),
            max(held),
            "deg",
            len(held),
            target=1.0,
        ),
        BenchFigure(
            "effort at rest: what the estimate adds to the model's error (largest, any joint)",
            float(np.median(added)),
            max(added),
            "Nm",
            n,
            target=0.05,
        ),
        BenchFigure(
            "effort at rest with PLF+: error against his true effort (largest, any joint)",
            float(np.median(errors)),
            max(errors),
            "Nm",
            n,
        ),
        BenchFigure("support delivered against asked (largest)", float(np.median(delivered)), max(delivered), "", n),
        BenchFigure("one observation between ticks", float(np.median(observe)), max(observe), "us", n),
        BenchFigure("the session's 78 s of compensation, lock-step", float(np.median(walls)), max(walls), "s", n),
    ]


BENCHMARKS = [bench_online_indicators]


if __name__ == "__main__":
    measured = {scenario: measure(scenario) for scenario in PILOTS}
    sys.stdout.write("\n".join(table(measured)) + "\n")
    for scenario, result in measured.items():
        sys.stdout.write(f"{scenario}: {result['wall_s']:.2f} s wall, {result['observe_us']:.1f} us per observation\n")
