"""Issue 24, defect 9: the limits file has a page (docs/isb_limits.md), an example, and a session keeps its limits.

* the example file and the page's YAML are the same limits, and both load;
* the file a session writes (``isb_limits.yaml``, what ``rom load`` reads next time) holds exactly the
  limits the session used, whether recorded or loaded.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from daror_runtime.console.world import SimWorld
from daror_runtime.session.settings import RestSettings, SessionSettings
from hal.isb import AngleRange, IsbLimits, isb_limits_yaml, load_isb_limits
from tests.daror_runtime.session.test_session_safety import Session

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "isb_limits" / "pilot_isb.yaml"


def test_the_example_and_the_page_agree_and_load() -> None:
    example = load_isb_limits(EXAMPLE)
    page = (ROOT / "docs" / "isb_limits.md").read_text(encoding="utf-8")
    block = page.split("```yaml\n", 1)[1].split("```", 1)[0]
    assert IsbLimits.model_validate(yaml.safe_load(block)) == example
    assert example.elevation == AngleRange(lower_deg=10.0, upper_deg=70.0)
    for field in ("elevation", "horizontal_rotation", "axial_rotation", "elbow", "horizontal_free_below_deg"):
        assert f"| `{field}` |" in page


def test_the_written_file_reads_back_the_same_limits(tmp_path: Path) -> None:
    limits = IsbLimits(
        elevation=AngleRange(lower_deg=12.5, upper_deg=71.0),
        elbow=AngleRange(lower_deg=8.0, upper_deg=101.5),
        horizontal_free_below_deg=15.0,
    )
    path = tmp_path / "limits.yaml"
    path.write_text(isb_limits_yaml(limits, "pilot P-1\nrecorded by hand"), encoding="utf-8")
    assert load_isb_limits(path) == limits
    assert path.read_text(encoding="utf-8").startswith("# pilot P-1\n# recorded by hand\nelevation: ")


@pytest.fixture
def session(tmp_path: Path) -> Iterator[Session]:
    # the rest pose, where a fault's lowering ends, must lie inside the example's limits (issue 23)
    s = Session(tmp_path / "session", SessionSettings(dummy_arm=True, rest=RestSettings(pose_isb_deg=(15, 0, 0, 30))))
    yield s
    s.close()


@pytest.mark.slow
def test_a_session_keeps_the_limits_it_used_for_the_next_one(session: Session, tmp_path: Path) -> None:
    runtime = session.runtime
    session.walk_to("rom_limits")
    session.ok(runtime.set_isb_limits(load_isb_limits(EXAMPLE)))
    assert runtime.runner.run_until(lambda: not runtime.busy, 2.0)
    kept = runtime.session_dir / "isb_limits.yaml"
    assert load_isb_limits(kept) == load_isb_limits(EXAMPLE)
    assert "pilot simulated pilot (exo_dummy_arm)" in kept.read_text(encoding="utf-8").splitlines()[0]
    # recorded with rom start / rom stop: the recorded range is what the file holds
    world: SimWorld = session.world
    session.ok(runtime.rom_start())
    end = world.pilot_sweep(runtime.settings.identification)
    runtime.runner.pass_time(end - runtime.last_sample.t_s + 0.5)  # type: ignore[union-attr]
    session.ok(runtime.rom_stop())
    assert runtime.runner.run_until(lambda: not runtime.busy, 2.0)
    recorded = runtime.snapshot().isb_limits_deg
    assert recorded is not None
    again = load_isb_limits(kept)
    for name, (lo, hi) in recorded.items():
        angle = getattr(again, name)
        assert angle.lower_deg == pytest.approx(lo, abs=0.05)
        assert angle.upper_deg == pytest.approx(hi, abs=0.05)
