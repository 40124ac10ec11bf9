"""The robot description and scenario files: values, and errors that name the line and field."""

from __future__ import annotations

from importlib import resources

import pytest

from hal.errors import DescriptionError
from hal.robot import RobotDescription, load_description
from hal.sim.scenario import load_scenario, scenario_names


def test_packaged_description_holds_the_design_values(description: RobotDescription) -> None:
    masses = [link.mass_kg for link in description.links]
    assert masses == [1.20, 1.00, 1.40, 0.50]
    assert description.links[2].com_m == (0.150, 0.020, 0.030)
    assert description.geometry.elbow_offset_m == (0.275, 0.0, 0.0)
    assert description.sea.spring_stiffness_nm_per_rad == 289.0
    assert description.sea.torque_resolution_nm == pytest.approx(0.0289)
    assert description.dummy_arm.lower_arm_mass_kg == 1.053
    assert description.ap_elbow_stiffness.mu1_nm_per_rad == 1.14


def test_bad_description_names_line_and_field(tmp_path) -> None:
    original = (resources.files("hal") / "daror01.yaml").read_text()
    broken = original.replace("- {mass_kg: 1.40,", "- {mass_kg: -1.40,")
    path = tmp_path / "robot.yaml"
    path.write_text(broken)
    line = broken.splitlines().index(next(x for x in broken.splitlines() if "-1.40" in x)) + 1
    with pytest.raises(DescriptionError, match=rf"robot\.yaml: line {line}, field links\.2\.mass_kg: .*greater than 0"):
        load_description(path)


@pytest.mark.parametrize(
    ("text", "pattern"),
    [
        ("", "file is empty"),
        ("name: [unclosed", "not valid YAML"),
        ("links: []\njoint_limits: []\n", "field links: List should have at least 4 items"),
        ("nonsense_key: 1\n", "field nonsense_key: Extra inputs are not permitted"),
    ],
)
def test_malformed_descriptions(tmp_path, text: str, pattern: str) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    with pytest.raises(DescriptionError, match=pattern):
        load_description(path)


def test_shipped_scenarios_load() -> None:
    assert {"exo", "exo_dummy_arm"} <= set(scenario_names())
    assert load_scenario("exo").dummy_arm is None
    assert load_scenario("exo_dummy_arm").dummy_arm is not None


def test_unknown_scenario_lists_the_known_ones() -> None:
    with pytest.raises(DescriptionError, match=r"unknown scenario 'mars'; expected one of .*exo_dummy_arm"):
        load_scenario("mars")
