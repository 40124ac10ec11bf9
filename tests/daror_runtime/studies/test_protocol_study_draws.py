"""The protocol study's scoring of random draws: the numbers and refusals of the plain PLF+ fit."""

from __future__ import annotations

import numpy as np
import pytest

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import IdentifiabilityError
from daror_runtime.studies.protocol_study import _DrawScorer, _score
from hal.robot import RobotDescription

Datasets = tuple[StationaryDataset, StationaryDataset]

#: Draw sizes from too few points to identify PLF+ (refused) to plenty.
SIZES = (1, 4, 7, 8, 9, 10, 12, 16, 24, 60, 250)


def _draws(train: StationaryDataset) -> list[np.ndarray]:
    """Random draws of every size, and draws that see a single elbow angle or a single stop."""
    rng = np.random.default_rng(7)
    draws = [np.sort(rng.choice(len(train), size=n, replace=False)) for n in SIZES for _ in range(3)]
    elbow = np.round(train.q_rad[:, 3], 2)
    draws.append(np.flatnonzero(elbow == elbow[0]))
    draws.append(np.zeros(40, dtype=int))
    draws.append(np.zeros(0, dtype=int))
    return draws


def test_draw_scores_are_the_plain_fits_to_the_last_bit(dataset_b: Datasets, description: RobotDescription) -> None:
    train, validation = dataset_b
    scorer = _DrawScorer(validation, description)
    refused = fitted = 0
    for index in _draws(train):
        draw = train.subset(index)
        try:
            expected = _score(draw, validation, description)
        except IdentifiabilityError:
            expected = None
        got = scorer.metrics(draw)
        assert got == expected, f"draw of {index.size} points"
        refused += expected is None
        fitted += expected is not None
    assert refused >= 3, "the draws should exercise the refusals"
    assert fitted >= 3, "the draws should exercise the fits"


@pytest.mark.parametrize("size", [12, 60])
def test_a_scorer_is_reusable(dataset_b: Datasets, description: RobotDescription, size: int) -> None:
    """One scorer serves every draw of a budget: a second use gives the first's numbers."""
    train, validation = dataset_b
    scorer = _DrawScorer(validation, description)
    draw = train.subset(np.arange(size))
    first = scorer.metrics(train.subset(np.arange(0, len(train), 3)))
    assert scorer.metrics(draw) == scorer.metrics(draw)
    assert scorer.metrics(train.subset(np.arange(0, len(train), 3))) == first
