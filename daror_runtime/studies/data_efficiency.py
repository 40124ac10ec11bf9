"""How many training points does a model need? The data-efficiency study of thesis Sec. 5.3.1.

For each training-set size ``n`` the study draws ``draws`` random subsets of ``n`` points (without
replacement) from the training set, fits the model on each through the model registry (the same
fitter ``daror fit`` uses), and validates every fit on the whole validation set. Per size it
records the distribution of the validation RMSE (Eq. 4.31, Nm) over the draws; the thesis plots
its mean and spread against ``n`` (Fig. 5.4).

Rules, chosen here because the thesis does not state them:

* **Random streams.** The draws of size ``n`` come from ``numpy.random.default_rng([seed, n])``,
  so a size's subsets depend only on the seed and ``n``: adding or removing other sizes does not
  change them, and a run is reproducible bit for bit.
* **Refused draws.** A subset that cannot identify the model (the fitter raises
  :class:`~daror_runtime.errors.IdentifiabilityError`: too few points, or too few distinct elbow
  angles for PLF+) is counted as *refused* and left out of the statistics; it does not stop the
  study. A size whose every draw is refused has ``None`` statistics.
* **Spread.** ``rmse_std`` is the population standard deviation (``ddof=0``) of the fitted draws'
  RMSE; ``rmse_p5``/``rmse_p95`` are linear-interpolated percentiles.
* **Enough points.** ``enough_points`` is the smallest ``n`` whose mean validation RMSE is at most
  ``(1 + tolerance)`` times the full-data RMSE (the model fitted on every training point), and
  *every larger size studied* also is, so a lucky dip of a noisy small size does not count. A mean
  below the full-data RMSE counts as within. ``None`` when no size qualifies.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import structlog

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import DataError, IdentifiabilityError, UsageError
from daror_runtime.models.metrics import ErrorMetrics, error_metrics
from daror_runtime.models.registry import ModelKind, fit_model, kind_entry, kind_names
from hal.robot import N_JOINTS, RobotDescription

log = structlog.get_logger(__name__)

#: Draws per size in the thesis (Sec. 5.3.1: "Per n datapoints, 100 models are trained").
DEFAULT_DRAWS = 100
#: Sizes in the default geometric ladder (the thesis's Fig. 5.4 shows about this many).
DEFAULT_LADDER_SIZES = 18
#: Relative excess over the full-data RMSE still counted as "enough points".
DEFAULT_TOLERANCE = 0.05
#: Fewest validation points accepted: with fewer, one noisy reading moves the RMSE of every draw.
MIN_VALIDATION_POINTS = 20

#: Called after each size with (fits done, fits in total); for a progress bar.
Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class SizeResult:
    """Validation errors of the ``draws`` models fitted on ``n`` random training points.

    RMSE figures are in Nm; ``nrmse_mean`` is unitless (Eq. 4.32). Every statistic is ``None``
    when no draw of this size could be fitted.
    """

    n: int
    fitted: int
    refused: int
    rmse_mean: float | None
    rmse_std: float | None
    rmse_min: float | None
    rmse_p5: float | None
    rmse_median: float | None
    rmse_p95: float | None
    rmse_max: float | None
    nrmse_mean: float | None

    @classmethod
    def from_draws(cls, n: int, refused: int, rmse_nm: Sequence[float], nrmse: Sequence[float]) -> SizeResult:
        """Summarise the fitted draws' validation RMSE (Nm) and nRMSE of size ``n``."""
        if not rmse_nm:
            return cls(n, 0, refused, None, None, None, None, None, None, None, None)
        rmse = np.asarray(rmse_nm, dtype=float)
        p5, median, p95 = (float(v) for v in np.percentile(rmse, [5.0, 50.0, 95.0]))
        lowest, highest = float(np.min(rmse)), float(np.max(rmse))
        # Clipped because summation rounding can put the mean of equal values an ulp above them
        # (every draw at n = N is the whole set), and readers rightly expect min <= mean <= max.
        mean = min(max(float(np.mean(rmse)), lowest), highest)
        return cls(
            n=n,
            fitted=int(rmse.size),
            refused=refused,
            rmse_mean=mean,
            rmse_std=float(np.std(rmse)),
            rmse_min=lowest,
            rmse_p5=p5,
            rmse_median=median,
            rmse_p95=p95,
            rmse_max=highest,
            nrmse_mean=float(np.mean(nrmse)),
        )

    def to_dict(self) -> dict[str, Any]:
        """The entry of ``sizes`` in ``data_efficiency.json``."""
        return {
            "n": self.n,
            "fitted": self.fitted,
            "refused": self.refused,
            "rmse_mean": self.rmse_mean,
            "rmse_std": self.rmse_std,
            "rmse_min": self.rmse_min,
            "rmse_p5": self.rmse_p5,
            "rmse_median": self.rmse_median,
            "rmse_p95": self.rmse_p95,
            "rmse_max": self.rmse_max,
            "nrmse_mean": self.nrmse_mean,
        }


@dataclass(frozen=True)
class DataEfficiencyResult:
    """Everything the study found; :meth:`to_dict` is the ``data_efficiency.json`` document."""

    kind: str
    display_name: str
    train_source: str
    train_points: int
    validate_source: str
    validate_points: int
    draws: int
    seed: int
    tolerance: float
    rank: int | None  # identifiable parameter combinations of the full-data fit (None: not linear)
    full_data: ErrorMetrics  # the model fitted on every training point, on the validation set
    sizes: tuple[SizeResult, ...]
    enough_points: int | None
    duration_s: float = field(default=0.0, compare=False)  # wall time; not in the JSON (not reproducible)

    @property
    def full_data_rmse(self) -> float:
        """Validation RMSE (Nm) of the model fitted on the whole training set."""
        return self.full_data.rmse_nm

    def to_dict(self) -> dict[str, Any]:
        """The ``data_efficiency.json`` document (docs/data_efficiency.md); JSON-ready, no NaN."""
        return {
            "kind": self.kind,
            "train": {"source": self.train_source, "n_points": self.train_points},
            "validate": {"source": self.validate_source, "n_points": self.validate_points},
            "draws": self.draws,
            "seed": self.seed,
            "full_data_rmse": self.full_data.rmse_nm,
            "full_data_nrmse": self.full_data.nrmse,
            "rank": self.rank,
            "tolerance": self.tolerance,
            "sizes": [s.to_dict() for s in self.sizes],
            "enough_points": self.enough_points,
        }


# --- inputs -------------------------------------------------------------------------------


def check_kind(kind: str) -> str:
    """The registry key of a model kind the study can fit (lower-cased): one that learns from data.

    Raises:
        UnknownModelKindError: ``kind`` is not registered.
        UsageError: ``kind`` is built without data (``ap``, capability ``needs_data`` False):
            there is nothing to learn; or it trains networks (an optional extra such as ``nn``):
            hundreds of fits of seconds each.
    """
    key = kind.lower()
    entry = kind_entry(key)
    studied = ", ".join(kind_names(_studied))
    if not entry.needs_data:
        raise UsageError(
            f"--kind {key}: this model is built from the robot description, not fitted, so it has nothing "
            f"to learn from more data; choose a fitted kind: {studied}"
        )
    if not _studied(entry):
        raise UsageError(
            f"--kind {key}: the study refits the model for every size and draw (hundreds of fits); a kind that "
            f"trains networks (extra {entry.extra!r}, seconds a fit) is compared by 'daror hpsearch' instead; "
            f"choose one of {studied}"
        )
    return key


def _studied(entry: ModelKind) -> bool:
    """A kind the study fits: learned from data by a closed-form fit (no optional extra: no network training)."""
    return entry.needs_data and entry.extra is None


def parse_sizes(text: str) -> list[int]:
    """Training-set sizes from ``--sizes`` text such as ``"10,50,200"``; range checks come later.

    Raises:
        UsageError: a part is empty or not a whole number.
    """
    sizes: list[int] = []
    for part in text.split(","):
        token = part.strip()
        try:
            sizes.append(int(token))
        except ValueError:
            raise UsageError(
                f"--sizes: {token!r} is not a whole number; expected comma-separated point counts such as 10,50,200"
            ) from None
    return sizes


def minimum_identifiable_size(rank: int | None) -> int:
    """Smallest training-set size (points) that can identify a model of ``rank`` combinations.

    A linear fit needs at least as many spare equations as unknowns (4 equations per point, see
    ``fit_linear``): ``n >= ceil(2 rank / 4)``. This is necessary, not sufficient: a random subset
    of that size may still be refused (e.g. repeated elbow angles), which the study counts.
    ``rank=None`` (a kind without a rank) gives 1 and leaves the refusals to the fitter.
    """
    if rank is None:
        return 1
    return max(1, math.ceil(2 * rank / N_JOINTS))


def default_sizes(n_min: int, n_total: int, count: int = DEFAULT_LADDER_SIZES) -> list[int]:
    """A geometric ladder of about ``count`` sizes from ``n_min`` to ``n_total`` points, both included.

    Geometric because the RMSE changes by orders of magnitude over the first few sizes and hardly
    at all over the last ones (Fig. 5.4 uses a log axis for the same reason). Rounding may merge
    neighbouring sizes at the small end, so fewer than ``count`` may come back.

    Raises:
        UsageError: ``n_min`` is not in ``1..n_total`` or ``count < 2``.
    """
    if not 1 <= n_min <= n_total:
        raise UsageError(f"the smallest size {n_min} must be between 1 and the {n_total} training points")
    if count < 2:
        raise UsageError(f"a ladder needs at least 2 sizes, got {count}")
    ladder = np.rint(np.geomspace(n_min, n_total, count)).astype(int)
    return sorted({int(v) for v in ladder} | {n_min, n_total})


def _check_settings(draws: int, seed: int, tolerance: float) -> None:
    if draws < 1:
        raise UsageError(f"--draws {draws}: out of range; expected at least 1 model per size")
    if seed < 0:
        raise UsageError(f"--seed {seed}: out of range; expected a whole number from 0 up")
    if not (math.isfinite(tolerance) and tolerance > 0.0):
        raise UsageError(f"tolerance {tolerance}: expected a positive fraction such as 0.05")


def _check_sizes(sizes: Sequence[int], n_total: int, source: str) -> None:
    if not sizes:
        raise UsageError("--sizes: no sizes given; expected comma-separated point counts such as 10,50,200")
    for n in sizes:
        if not 1 <= n <= n_total:
            raise UsageError(
                f"--sizes: {n} is out of range; expected sizes from 1 to {n_total} (the stationary points in {source})"
            )


# --- the study ------------------------------------------------------------------------------


def _validate(model_torque: Callable[[np.ndarray], np.ndarray], validate: StationaryDataset) -> ErrorMetrics:
    return error_metrics(validate.tau_nm, model_torque(validate.q_rad))


def enough_points(sizes: Sequence[SizeResult], full_data_rmse_nm: float, tolerance: float) -> int | None:
    """The smallest size from which on every mean RMSE is within ``tolerance`` of the full-data RMSE.

    ``sizes`` must be in increasing ``n``. A size with no fitted draw breaks the run of
    qualifying sizes, like a size whose mean is too high. Returns ``None`` when the largest size
    does not qualify (then no size does).
    """
    limit = (1.0 + tolerance) * full_data_rmse_nm
    answer: int | None = None
    for size in reversed(sizes):
        if size.rmse_mean is None or size.rmse_mean > limit:
            break
        answer = size.n
    return answer


def run_data_efficiency(
    train: StationaryDataset,
    validate: StationaryDataset,
    description: RobotDescription,
    kind: str = "plf+",
    sizes: Sequence[int] | None = None,
    draws: int = DEFAULT_DRAWS,
    seed: int = 0,
    tolerance: float = DEFAULT_TOLERANCE,
    progress: Progress | None = None,
) -> DataEfficiencyResult:
    """Validation RMSE of ``kind`` fitted on random subsets of ``train``, per subset size.

    Args:
        train: stationary training points (only ``q_rad`` and ``tau_nm`` are used).
        validate: stationary validation points; every fit is scored on all of them.
        description: the robot description the models are fitted for.
        kind: a fitted model kind of the registry (``plf``, ``plf+``).
        sizes: training-set sizes in points, each in ``1..len(train)``; sorted and de-duplicated
            here. Default: :func:`default_sizes` from the smallest identifiable size to all points.
        draws: models fitted per size (the thesis: 100).
        seed: seeds the random subsets (see the module docstring for the streams).
        tolerance: relative excess over the full-data RMSE that still counts as enough points.
        progress: called after each size with (fits done, fits in total).

    Raises:
        UnknownModelKindError: ``kind`` is not registered.
        UsageError: ``kind`` is not fitted (``ap``); ``draws < 1``; ``seed < 0``; a size outside
            ``1..len(train)``; no sizes.
        DataError: fewer than :data:`MIN_VALIDATION_POINTS` validation points.
        IdentifiabilityError: the whole training set cannot identify the model.
    """
    start = time.perf_counter()
    key = check_kind(kind)
    n_total = len(train)
    _check_settings(draws, seed, tolerance)
    if sizes is not None:
        _check_sizes(sizes, n_total, train.source)
    if len(validate) < MIN_VALIDATION_POINTS:
        raise DataError(
            f"{validate.source}: {len(validate)} stationary points; expected at least {MIN_VALIDATION_POINTS} "
            "to validate on"
        )
    options = kind_entry(key).options()  # the kind's defaults: the study varies only the data
    # The full-data fit is the reference every size is compared with; if even all the training
    # points cannot identify the model the study is meaningless, so its refusal is bad input.
    full = fit_model(key, train, description, options)
    full_metrics = _validate(full.model.torque_batch, validate)
    rank = full.report.rank
    ladder = sorted(set(sizes)) if sizes is not None else default_sizes(minimum_identifiable_size(rank), n_total)
    total_fits = len(ladder) * draws
    results: list[SizeResult] = []
    for done_sizes, n in enumerate(ladder):
        rng = np.random.default_rng([seed, n])
        rmse: list[float] = []
        nrmse: list[float] = []
        refused = 0
        for _ in range(draws):
            # Sorted so a subset keeps the recording order; the fit does not depend on row order.
            index = np.sort(rng.choice(n_total, size=n, replace=False))
            try:
                fitted = fit_model(key, train.subset(index), description, options)
            except IdentifiabilityError:
                refused += 1
                continue
            metrics = _validate(fitted.model.torque_batch, validate)
            rmse.append(metrics.rmse_nm)
            nrmse.append(metrics.nrmse)
        results.append(SizeResult.from_draws(n, refused, rmse, nrmse))
        if progress is not None:
            progress((done_sizes + 1) * draws, total_fits)
    enough = enough_points(results, full_metrics.rmse_nm, tolerance)
    duration = time.perf_counter() - start
    log.info(
        "data-efficiency study done",
        kind=key,
        train=train.source,
        validate=validate.source,
        sizes=len(ladder),
        draws=draws,
        refused=sum(r.refused for r in results),
        full_data_rmse_nm=round(full_metrics.rmse_nm, 6),
        enough_points=enough,
        duration_s=round(duration, 3),
    )
    return DataEfficiencyResult(
        kind=key,
        display_name=full.model.display_name,
        train_source=train.source,
        train_points=n_total,
        validate_source=validate.source,
        validate_points=len(validate),
        draws=draws,
        seed=seed,
        tolerance=tolerance,
        rank=rank,
        full_data=full_metrics,
        sizes=tuple(results),
        enough_points=enough,
        duration_s=duration,
    )
