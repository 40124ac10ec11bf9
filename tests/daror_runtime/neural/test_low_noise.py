"""Issue 27, part 2 (D206): PENN and NNN generalise between paths on low-noise data.

Dataset B's 0.42 Nm of direction error hides model error: a network that stopped short of the data
still validated within 5 % of PLF+ there. Here the simulator's sensor noise and direction error are
a tenth of dataset B's (``encoder_noise_rad`` 5e-6 without quantisation, the direction error
0.025 / 0.075 / 0.035 / 0.015 Nm), and training and validation come from different seeds, so the
validation stops lie on other random paths through the workspace than every training stop. The
former defaults validated at 7.7x PLF+ (PENN) and 5.2x (NNN) on this pair; the defaults now,
1.76x and 2.55x (docs/models.md, "Generalising between paths").
"""

from __future__ import annotations

from pathlib import Path

import pytest

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.models.compare import evaluate_models
from daror_runtime.models.files import training_summary
from daror_runtime.models.registry import NetworkOptions, fit_model
from hal.robot import RobotDescription
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import generate_stationary
from tests.conftest import as_dataset

pytestmark = pytest.mark.slow

#: The low-noise plant: dataset B's robot and Dummy Arm with a tenth of its noise and direction error.
LOW_NOISE = """extends: exo_dummy_arm
name: {name}
summary: dataset B with a tenth of its sensor noise and direction error
seed: {seed}
sensors:
  encoder_noise_rad: 0.5e-5
  quantise: false
  direction_error_nm: [0.025, 0.075, 0.035, 0.015]
"""


def _generated(folder: Path, seed: int, trajectory: str) -> StationaryDataset:
    path = folder / f"low_noise_{seed}.yaml"
    path.write_text(LOW_NOISE.format(name=f"low_noise_{seed}", seed=seed), encoding="utf-8")
    return as_dataset(generate_stationary(load_scenario(path), trajectory), f"low_noise_{seed}_{trajectory}")  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def low_noise(tmp_path_factory: pytest.TempPathFactory) -> tuple[StationaryDataset, StationaryDataset]:
    folder = tmp_path_factory.mktemp("low_noise")
    return _generated(folder, 7101, "training"), _generated(folder, 7202, "validation")


def test_penn_and_nnn_generalise_between_paths_on_low_noise_data(
    low_noise: tuple[StationaryDataset, StationaryDataset], description: RobotDescription
) -> None:
    train, validation = low_noise
    models = [fit_model("plf+", train, description).model]
    models += [fit_model(kind, train, description, NetworkOptions()).model for kind in ("penn", "nnn")]
    plf, penn, nnn = evaluate_models(models, validation, training=[training_summary(train, None)] * 3)
    assert plf.metrics.rmse_nm < 0.05  # the floor of these data: PLF+ 0.0418 Nm measured
    # the acceptance (measured 1.76x and 2.55x; the former defaults 7.7x and 5.2x)
    assert penn.metrics.rmse_nm <= 2.0 * plf.metrics.rmse_nm, (penn.metrics.rmse_nm, plf.metrics.rmse_nm)
    assert nnn.metrics.rmse_nm <= 3.0 * plf.metrics.rmse_nm, (nnn.metrics.rmse_nm, plf.metrics.rmse_nm)
    # the paths differ: some validation stops lie beyond the training range, and every evaluation
    # says how a model does inside and outside it (PENN measured 0.068 Nm inside, 0.115 outside)
    for evaluation in (penn, nnn):
        extrapolation = evaluation.extrapolation
        assert extrapolation is not None
        assert 0 < extrapolation.n_outside < extrapolation.n_points
        assert extrapolation.rmse_inside_nm is not None
        assert extrapolation.rmse_outside_nm is not None
    assert penn.extrapolation is not None
    assert penn.extrapolation.rmse_inside_nm is not None
    assert penn.extrapolation.rmse_inside_nm <= 2.0 * plf.metrics.rmse_nm
