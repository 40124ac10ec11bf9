"""Which parameter combinations a regressor identifies (thesis Sec. 4.2.1, "Regressor Rank").

The DAROR-01's PLF regressor has rank 8 of 12: four directions of the parameter space do not
change the torque, so only eight linear combinations ("base parameters") are identifiable. The
first moment of a link along its own joint axis (``z``) does not move when that joint turns, so
it is indistinguishable from a component of the previous link; link 1's never moves at all.

Base columns are chosen greedily in a physically readable order (x and y components first, link
by link), so each base parameter reads ``theta1x + 0.866 theta2z``. Values are invariant: every
least-squares solution gives the same base-parameter values. Standard errors assume independent
residuals; repeated samples per stop and the direction error make them optimistic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from daror_runtime.models.least_squares import LeastSquaresFit

#: A column is independent of those already chosen when the sine of its angle to their span
#: exceeds this (column-scaled Gram matrix, so the test is scale-free).
_INDEPENDENCE_SINE = 1e-6


@dataclass(frozen=True)
class BaseParameter:
    """One identifiable combination ``lead + sum_k coefficient_k * other_k`` and its estimate."""

    lead: str
    combination: dict[str, float]  # parameter name -> coefficient (lead has 1.0)
    value: float
    std_error: float

    def expression(self) -> str:
        """Readable form, e.g. ``theta1x + 0.866 theta2z``."""
        parts = [self.lead]
        for name, coefficient in self.combination.items():
            if name == self.lead:
                continue
            sign = "-" if coefficient < 0 else "+"
            parts.append(f"{sign} {abs(coefficient):.4g} {name}")
        return " ".join(parts)

    def to_dict(self) -> dict[str, object]:
        return {
            "expression": self.expression(),
            "combination": self.combination,
            "value": self.value,
            "std_error": self.std_error,
        }


def readable_order(names: tuple[str, ...]) -> list[int]:
    """Indices of ``names`` with x/y components first, then z components, then the rest."""
    first = [i for i, n in enumerate(names) if n.startswith("theta") and n[-1] in "xy"]
    second = [i for i, n in enumerate(names) if n.startswith("theta") and n[-1] == "z"]
    rest = [i for i in range(len(names)) if i not in first and i not in second]
    return first + second + rest


def base_parameters(fit: LeastSquaresFit, names: tuple[str, ...]) -> list[BaseParameter]:
    """The identifiable combinations of ``fit`` with values and standard errors."""
    gram = fit.gram
    norms = np.sqrt(np.diag(gram))
    usable = norms > 0
    scaled = gram / np.outer(np.where(usable, norms, 1.0), np.where(usable, norms, 1.0))
    chosen: list[int] = []
    for index in readable_order(names):
        if not usable[index] or len(chosen) == fit.rank:
            continue
        if not chosen:
            chosen.append(index)
            continue
        g = scaled[np.ix_(chosen, [index])]
        projection = g.T @ np.linalg.solve(scaled[np.ix_(chosen, chosen)], g)
        if 1.0 - float(projection[0, 0]) > _INDEPENDENCE_SINE**2:
            chosen.append(index)
    dependent = [i for i in range(len(names)) if i not in chosen]
    g_bb = gram[np.ix_(chosen, chosen)]
    coefficients = np.linalg.solve(g_bb, gram[np.ix_(chosen, dependent)]) if dependent else np.zeros((len(chosen), 0))
    values = fit.theta[chosen] + coefficients @ fit.theta[dependent]
    covariance = fit.residual_variance * np.linalg.inv(g_bb)
    result = []
    for row, lead in enumerate(chosen):
        combination = {names[lead]: 1.0}
        for col, other in enumerate(dependent):
            if abs(coefficients[row, col]) > 1e-9:
                combination[names[other]] = float(coefficients[row, col])
        result.append(
            BaseParameter(
                lead=names[lead],
                combination=combination,
                value=float(values[row]),
                std_error=float(np.sqrt(max(covariance[row, row], 0.0))),
            )
        )
    return result


def unidentifiable_parameters(fit: LeastSquaresFit, names: tuple[str, ...], tol: float = 1e-9) -> list[str]:
    """Parameters with no effect on the torque at all (a zero regressor column), e.g. ``theta1z``."""
    return [n for n, g in zip(names, np.diag(fit.gram), strict=True) if g <= tol * max(np.max(np.diag(fit.gram)), 1.0)]
