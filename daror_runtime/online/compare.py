"""A blind comparison of two approved models (issue 29, part 3): the schedule and the verdict.

The session alternates the two models in blocks of pairs; within each pair both models come once,
in an order drawn at random but balanced (as many pairs begin with one as with the other), and
neither the pilot nor the console says which model a block has until the end. After each block the
pilot rates it (0-10, the operator types it); each block's own online indicators are kept. The
verdict pairs the two ratings of each pair: the mean difference, a paired t-test and a Wilcoxon
signed-rank test (scipy), and the same for the pilot's effort at rest per block. Design time: no
tick runs any of it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: The verdict names a preferred model only at this two-sided p of the paired t-test on the ratings.
ALPHA = 0.05


def balanced_order(pairs: int, seed: int) -> list[int]:
    """Which model (0 or 1) each block has: ``pairs`` pairs, each both models once, half of them 0 first.

    With an odd number of pairs, the one left over begins with a model drawn at random.
    """
    rng = np.random.default_rng(seed)
    first = [0] * (pairs // 2) + [1] * (pairs // 2)
    if pairs % 2:
        first.append(int(rng.integers(2)))
    rng.shuffle(first)
    order = []
    for leader in first:
        order += [leader, 1 - leader]
    return order


@dataclass
class Block:
    """One block: its model (hidden until the end), its time, the pilot's rating, its indicators."""

    number: int
    model: int
    t_start_s: float | None = None
    t_end_s: float | None = None
    rating: float | None = None
    effort_at_rest_rms_nm: list[float] | None = None
    interaction_rms_nm: list[float | None] | None = None
    pilot_effort_nm: float | None = None  # the simulated pilot's mean effort (truth), where a simulation has one


@dataclass
class Comparison:
    """The state of one blind comparison (its verdict once every block is rated)."""

    labels: tuple[str, str]
    block_s: float
    seed: int
    blocks: list[Block] = field(default_factory=list)

    @classmethod
    def planned(cls, labels: tuple[str, str], pairs: int, block_s: float, seed: int) -> Comparison:
        order = balanced_order(pairs, seed)
        return cls(labels, block_s, seed, [Block(n + 1, model) for n, model in enumerate(order)])

    @property
    def rated(self) -> int:
        return sum(block.rating is not None for block in self.blocks)

    def verdict(self) -> dict[str, Any]:
        """Ratings and indicators per model, paired per pair, with their tests (JSON-ready)."""
        from scipy import stats

        pairs = [(self.blocks[i], self.blocks[i + 1]) for i in range(0, len(self.blocks) - 1, 2)]
        complete = [p for p in pairs if p[0].rating is not None and p[1].rating is not None]

        def by_model(pair: tuple[Block, Block], model: int) -> Block:
            return pair[0] if pair[0].model == model else pair[1]

        ratings = np.array([[by_model(p, m).rating for m in (0, 1)] for p in complete], dtype=float)
        document: dict[str, Any] = {
            "models": list(self.labels),
            "pairs": len(complete),
            "block_s": self.block_s,
            "seed": self.seed,
            "order": [self.labels[b.model] for b in self.blocks],
            "blocks": [
                {
                    "block": b.number,
                    "model": self.labels[b.model],
                    "rating": b.rating,
                    "t_start_s": b.t_start_s,
                    "t_end_s": b.t_end_s,
                    "effort_at_rest_rms_nm": b.effort_at_rest_rms_nm,
                    "interaction_rms_nm": b.interaction_rms_nm,
                    "pilot_effort_nm": b.pilot_effort_nm,
                }
                for b in self.blocks
            ],
        }
        if len(complete) < 2:
            document["ratings"] = None
            document["preferred"] = None
            return document
        difference = ratings[:, 0] - ratings[:, 1]
        t_test = stats.ttest_rel(ratings[:, 0], ratings[:, 1])
        p_t = float(t_test.pvalue) if np.isfinite(t_test.pvalue) else 1.0
        same = np.allclose(difference, 0.0)  # Wilcoxon is undefined then: no difference, no evidence
        p_w = 1.0 if same else float(stats.wilcoxon(ratings[:, 0], ratings[:, 1]).pvalue)
        document["ratings"] = {
            "mean": {self.labels[m]: float(ratings[:, m].mean()) for m in (0, 1)},
            "mean_difference": float(difference.mean()),  # model 0 minus model 1
            "p_paired_t": p_t,
            "p_wilcoxon": p_w,
        }
        efforts = [
            [float(np.sqrt(np.mean(np.square(by_model(p, m).effort_at_rest_rms_nm)))) for m in (0, 1)]
            for p in complete
            if all(by_model(p, m).effort_at_rest_rms_nm for m in (0, 1))
        ]
        if len(efforts) >= 2:
            effort = np.array(efforts)
            test = stats.ttest_rel(effort[:, 0], effort[:, 1])
            document["effort_at_rest"] = {
                "mean_nm": {self.labels[m]: float(effort[:, m].mean()) for m in (0, 1)},
                "p_paired_t": float(test.pvalue) if np.isfinite(test.pvalue) else 1.0,
            }
        better = 0 if difference.mean() > 0 else 1
        document["preferred"] = self.labels[better] if p_t < ALPHA and difference.mean() != 0 else None
        return document


def verdict_text(document: dict[str, Any]) -> str:
    """One paragraph for the operator: the preferred model, or none, with the figures."""
    ratings = document.get("ratings")
    if ratings is None:
        return f"blind comparison: {document['pairs']} complete pair(s): too few for a verdict"
    means = ", ".join(f"{name} {value:.2f}" for name, value in ratings["mean"].items())
    preferred = document["preferred"]
    head = f"the pilot preferred {preferred}" if preferred else f"no preference at p < {ALPHA:g}"
    effort = document.get("effort_at_rest")
    extra = (
        ""
        if effort is None
        else "; his effort at rest (RMS over joints) "
        + ", ".join(f"{name} {value:.2f} Nm" for name, value in effort["mean_nm"].items())
        + f" (paired t p = {effort['p_paired_t']:.3g})"
    )
    return (
        f"blind comparison over {document['pairs']} pairs: {head}; mean ratings {means} "
        f"(paired t p = {ratings['p_paired_t']:.3g}, Wilcoxon p = {ratings['p_wilcoxon']:.3g}){extra}"
    )


__all__ = ["ALPHA", "Block", "Comparison", "balanced_order", "verdict_text"]
