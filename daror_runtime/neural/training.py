"""Training PENN and NNN networks: loss, Adam then L-BFGS, k-fold validation, several initialisations at once.

**The loss** (``settings.loss == "scaled"``, the default)::

    loss(theta) = mean over points n and joints j of ((tau_model_nj - tau_nj) / s_j)^2
                  + lambda * mean over parameters of |theta|

``s_j`` is the root mean square of joint ``j``'s training torque (Nm; floored at 5 % of the
largest joint's, so that no joint weighs more than 400 times another). The data term is
dimensionless: a model that outputs zero torque scores 1.0, a good one (validation RMSE ~0.41 Nm
on dataset B) ~0.015. The L1 term averages over the parameters, so ``lambda`` means the same for
any network size; with the weights a trained 2 x 32 PENN has, ``mean |theta| ~ 0.15``:

* ``lambda = 1e-6``: a penalty of ~1.5e-7, 1e-5 of the data term: no regularisation to speak of
  (the default; the networks are small and the training length is chosen by validation);
* ``lambda = 1e-2``: ~1.5e-3, a tenth of a good model's data term: weights shrink a little;
* ``lambda = 1e-1``: ~1.5e-2, as large as the data term: the weights shrink (mean 0.12);
* ``lambda = 1``: the penalty dominates and the fit suffers (validation RMSE ~0.5 Nm), yet zero
  torque would cost 1.0 in the data term, so even this penalty cannot erase the model.

(Measured numbers: docs/models.md, "PENN and NNN".)

The thesis's loss (``settings.loss == "thesis"``, Eq. 3.7) as a batch computes it: the mean
squared torque error in Nm^2 over the points and joints plus ``lambda * ||theta||_1`` (the sum over
all parameters), with no standardisation of the inputs and no output scale. On dataset B at the
thesis's ``lambda = 0.1`` the penalty wins: the torque of a network is a product of its layers'
weights, so near zero the data term's gradient vanishes while the penalty's stays ``lambda``, and
every weight is driven to zero (the collapse docs/models.md reports, "Why the thesis's networks lost to PLF+"). How close the two terms
are is an accident of units: with the squared error summed over the four joints instead of
averaged (four times the data term) the same network does not collapse.

**Training**: full batch (the data are ~1,300 points); ``adam_steps`` of Adam, then
``lbfgs_steps`` iterations of L-BFGS (``optax.lbfgs``'s direction; the step is checked by an
Armijo test and halved on the next iteration when it fails, one loss evaluation per iteration:
optax's own line searches run ``lax.cond`` and ``while_loop`` that, under ``jax.vmap``, evaluate
both branches, twice the cost). Each step evaluates the loss at the current parameters; its
index counts evaluations.

**Validation** (Sec. 4.2.5): the points, in time order, are split into ``folds`` contiguous blocks
(neighbouring points are correlated, so a random split would validate on near-copies of the
training points). For each of ``validation_folds`` held-out blocks a network is trained on the
others; the validation loss (the data term on the held-out block, no penalty) is tracked at every
step, averaged over the held-out blocks, and its minimum is the *minimal validation loss* (MVL);
the fold networks' parameters at it are kept.

**Final fit** (``final_fit``, default on): beside the fold networks, a network from the same
initial weights is trained on *all* the points in the same program. It is kept at the *stopping
step*: the last step, at or after the MVL's, whose validation loss is within ``stop_tolerance``
(10 %) of the MVL. So it trains as long as the held-out blocks do not argue against it, and stops
where they show overfitting (the validation loss risen 10 % above its minimum). Why not at the
MVL's step itself: on dataset B the held-out loss is flat within a few per cent after ~200 steps,
its minimum falls anywhere in that plateau (or on a transient dip), and a network stopped there is
worse on the validation trajectory (docs/models.md, "What fixed it: the loss and the training").

**Several initialisations** (Sec. 4.2.3): every ``(lambda, seed)`` of :func:`train_group` is
trained in one compiled program, ``jax.lax.scan`` over the steps; the caller keeps the one with the
best MVL. Within a ``(lambda, seed)`` its fold networks and its full-data network are one
``jax.vmap``; over the ``(lambda, seed)`` the program runs ``jax.lax.map``, not ``jax.vmap``: with
``vmap`` a network's result depended on which other networks were trained beside it (XLA's batched
reductions round differently for another batch size, and 300 steps of L-BFGS amplify the last
bit: weights 1e-2 apart, the validation RMSE in its fourth digit), while ``lax.map`` runs one
compiled step for each set in turn and gives, bit for bit, what training that network alone gives.
On this CPU ``vmap`` bought no speed (three networks cost 3.8 times one), so nothing is lost.

Everything is deterministic for given seeds, on one machine and thread count (XLA splits some
reductions by threads).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache, partial
from typing import Any, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from pydantic import BaseModel, ConfigDict, Field, model_validator

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import DataError, IdentifiabilityError
from daror_runtime.models.neural import Network, NetworkSpec
from daror_runtime.neural import networks
from daror_runtime.neural.networks import Scaling

__all__ = [
    "MIN_POINTS_PER_FOLD",
    "NetworkResult",
    "PreparedData",
    "TrainingSettings",
    "prepare_data",
    "train_group",
]

#: Fewest points a fold may have (a validation block smaller than this says little).
MIN_POINTS_PER_FOLD = 10
#: Smallest spread of a standardised input: a feature varying less than this (rad, or 1 for
#: sin/cos) is not magnified beyond it, so noise on a joint that hardly moved is not amplified.
MIN_FEATURE_SPREAD = 0.05
#: A joint's torque scale is at least this fraction of the largest joint's.
MIN_TORQUE_SCALE_FRACTION = 0.05
#: Armijo's sufficient-decrease constant of the L-BFGS step test.
ARMIJO = 1e-4


class TrainingSettings(BaseModel):
    """How networks are trained (frozen; unknown fields refused). Defaults: the default presets'.

    Raises (constructor): pydantic ``ValidationError`` for a value out of range, no step at all, or
    more validation folds than folds.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    loss: Literal["scaled", "thesis"] = Field(
        "scaled", description="scaled: errors divided by each joint's torque scale, L1 as a mean; thesis: Eq. 3.7, Nm^2"
    )
    folds: int = Field(4, ge=2, le=20, description="k: contiguous blocks of time")
    validation_folds: int = Field(1, ge=1, le=20, description="held-out blocks, one network each")
    adam_steps: int = Field(100, ge=0, le=1_000_000)
    learning_rate: float = Field(5e-3, gt=0.0, le=1.0, description="Adam's")
    lbfgs_steps: int = Field(200, ge=0, le=1_000_000, description="L-BFGS iterations after Adam (0: none)")
    lbfgs_memory: int = Field(10, ge=1, le=100)
    final_fit: bool = Field(True, description="also train on all the data, kept at the stopping step")
    stop_tolerance: float = Field(
        0.1, ge=0.0, le=1.0, description="stop at the last step whose validation loss is within this of the MVL"
    )

    @model_validator(mode="after")
    def _consistent(self) -> TrainingSettings:
        if self.validation_folds > self.folds:
            raise ValueError(f"validation_folds {self.validation_folds} is more than folds {self.folds}")
        if self.adam_steps + self.lbfgs_steps < 1:
            raise ValueError("no training step: adam_steps + lbfgs_steps must be at least 1")
        return self

    @property
    def steps(self) -> int:
        """Loss evaluations per network: Adam's, L-BFGS's, and one after the last Adam step when there is no L-BFGS."""
        return self.adam_steps + (self.lbfgs_steps if self.lbfgs_steps else 1)

    def held_out(self) -> tuple[int, ...]:
        """The held-out blocks, spread over the session from the last one (``folds=4``: 1 held out: (3,);
        2: (1, 3); 4: (0, 1, 2, 3))."""
        return tuple(
            sorted({self.folds - 1 - (i * self.folds) // self.validation_folds for i in range(self.validation_folds)})
        )


@dataclass(frozen=True, eq=False)
class PreparedData:
    """Training data in time order, cut into folds, with the scales the loss and the network use.

    Attributes:
        q: joint angles (rad, (N, 4)), time order.
        tau: torques (Nm, (N, 4)).
        fold: the block of each point, 0 .. folds - 1.
        torque_scale: ``s_j`` of the scaled loss (Nm, (4,)); ones for the thesis's loss.
        scaling: the network's input standardisation and output scale.
    """

    q: np.ndarray
    tau: np.ndarray
    fold: np.ndarray
    torque_scale: np.ndarray
    scaling: Scaling

    def masks(self, settings: TrainingSettings) -> tuple[np.ndarray, np.ndarray]:
        """Training and validation weights of every member network, (M, N) each: one member per held-out
        block, then (with ``final_fit``) the full-data member (all training, no validation)."""
        rows_train, rows_val = [], []
        for block in settings.held_out():
            rows_train.append((self.fold != block).astype(np.float64))
            rows_val.append((self.fold == block).astype(np.float64))
        if settings.final_fit:
            rows_train.append(np.ones(self.fold.size))
            rows_val.append(np.zeros(self.fold.size))
        return np.stack(rows_train), np.stack(rows_val)


def prepare_data(spec: NetworkSpec, data: StationaryDataset, settings: TrainingSettings) -> PreparedData:
    """Order ``data`` by time, cut it into ``settings.folds`` contiguous blocks, derive the scales.

    Without times (``t_s`` None) the rows' order is taken as the order of recording.

    Raises:
        DataError: a value that is not finite.
        IdentifiabilityError: too few points for ``settings.folds`` blocks of
            :data:`MIN_POINTS_PER_FOLD` points.
    """
    q = np.asarray(data.q_rad, dtype=np.float64)
    tau = np.asarray(data.tau_nm, dtype=np.float64)
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(tau))):
        raise DataError(f"{data.source}: a joint angle or torque is not a finite number")
    n = q.shape[0]
    if n < settings.folds * MIN_POINTS_PER_FOLD:
        raise IdentifiabilityError(
            f"{data.source}: {n} points cannot be cut into {settings.folds} validation blocks of at least "
            f"{MIN_POINTS_PER_FOLD} points; a neural model needs at least {settings.folds * MIN_POINTS_PER_FOLD}"
        )
    if data.t_s is not None:
        order = np.argsort(np.asarray(data.t_s), kind="stable")
        q, tau = q[order], tau[order]
    fold = np.empty(n, dtype=np.int64)
    for block, rows in enumerate(np.array_split(np.arange(n), settings.folds)):
        fold[rows] = block
    if settings.loss == "thesis":
        return PreparedData(q, tau, fold, np.ones(q.shape[1]), Scaling.identity(spec))
    rms = np.sqrt(np.mean(tau**2, axis=0))
    torque_scale = np.maximum(rms, max(MIN_TORQUE_SCALE_FRACTION * float(np.max(rms)), 1e-6))
    raw = np.concatenate([np.sin(q), np.cos(q)], axis=1) if spec.inputs == "sincos" else q
    offset = np.mean(raw, axis=0)
    spread = np.maximum(np.std(raw, axis=0), MIN_FEATURE_SPREAD)
    # PENN: V = s * y with s the torque's overall RMS, so O(1) slopes of y in the standardised
    # inputs give torques of the data's size; NNN: each torque scaled by its joint's scale.
    output = np.array([float(np.sqrt(np.mean(tau**2)))]) if spec.model == "penn" else torque_scale
    return PreparedData(q, tau, fold, torque_scale, Scaling(offset, spread, np.maximum(output, 1e-6)))


@dataclass(frozen=True, eq=False)
class NetworkResult:
    """One trained ``(lambda, seed)`` network of :func:`train_group`.

    Attributes:
        spec, l1, seed, settings: what was trained, and how.
        mvl: minimal validation loss (mean over the held-out blocks; the loss's data term, no
            penalty: dimensionless for the scaled loss, Nm^2 for the thesis's).
        mvl_step: the step (loss evaluation, from 0) of the MVL.
        stop_step: the last step, at or after ``mvl_step``, whose validation loss is within
            ``settings.stop_tolerance`` of the MVL: where the selected network is taken.
        train_loss, validation_loss: at the last step, mean over the fold networks (training:
            with the penalty).
        parameters: the selected network (flat weights, the layout of
            :func:`daror_runtime.models.neural.weight_layout`): the full-data network at
            ``stop_step`` with ``final_fit``, else the first fold network at ``stop_step``.
        mvl_parameters: every fold network's weights at ``mvl_step``, (held-out blocks, P).
        final_train_loss: the full-data network's training loss at ``stop_step`` (None without
            final fit).
        train_curve, validation_curve: the mean fold training and validation losses at every step.
        scaling: the input standardisation and output scale the weights go with.
        wall_s, cpu_s, compile_s: of the whole group (its networks are trained together):
            wall-clock seconds, process CPU seconds (all threads), of which compiling (0 when the
            program for this shape was already compiled).
    """

    spec: NetworkSpec
    l1: float
    seed: int
    settings: TrainingSettings
    mvl: float
    mvl_step: int
    stop_step: int
    train_loss: float
    validation_loss: float
    parameters: np.ndarray
    mvl_parameters: np.ndarray
    final_train_loss: float | None
    train_curve: np.ndarray
    validation_curve: np.ndarray
    scaling: Scaling
    wall_s: float
    cpu_s: float
    compile_s: float

    def network(self) -> Network:
        """The selected network, runnable (:class:`daror_runtime.models.neural.Network`).

        Raises:
            ValueError: its weights are not finite (training diverged).
        """
        return self.scaling.network(self.spec, self.parameters)


# --- the compiled program ----------------------------------------------------------------------


class _Track(NamedTuple):
    best: jax.Array  # the lowest mean validation loss so far (the MVL at the end)
    step: jax.Array  # its step
    params: jax.Array  # every member's weights at that step, (M, P)
    stop: jax.Array  # the last step so far whose mean validation loss is within the tolerance of ``best``
    stop_params: jax.Array  # every member's weights at ``stop``, (M, P)


class _Lbfgs(NamedTuple):
    good: jax.Array  # (M, P) the last accepted weights
    good_obj: jax.Array  # (M,) their training loss
    good_val: jax.Array  # (M,) their validation loss
    good_grad: jax.Array  # (M, P) their gradient
    direction: jax.Array  # (M, P) L-BFGS's step from there
    scale: jax.Array  # (M,) the fraction of the step tried next (halved after a failed test)
    state: Any  # optax's L-BFGS state, one per member
    candidate: jax.Array  # (M, P) the weights evaluated next


#: A network's training loss (with the penalty) and validation loss (data term on the held-out points), the
#: first with its gradient: ``(weights (P,), lambda, training weights (N,), validation weights (N,)) ->
#: ((loss, validation loss), gradient (P,))`` (``jax.value_and_grad`` with ``has_aux``).
_Gradient = Callable[[jax.Array, jax.Array, jax.Array, jax.Array], tuple[tuple[jax.Array, jax.Array], jax.Array]]
#: Every member's losses and gradients at once: ``weights (M, P) -> (loss (M,), validation loss (M,), gradient (M, P))``.
_Evaluate = Callable[[jax.Array], tuple[jax.Array, jax.Array, jax.Array]]
#: :func:`_track` with the program's constants bound: ``(track, step, weights (M, P), validation loss (M,)) -> track``.
_TrackStep = Callable[[_Track, Any, jax.Array, jax.Array], _Track]


def _program(spec: NetworkSpec, settings: TrainingSettings, n_fold_members: int) -> Any:
    """The function trained by :func:`train_group` (to be jitted): ``G`` groups of ``M`` members.

    Its arguments, as :func:`_compiled` declares them: the initial weights (G, P), lambda (G,), q and
    tau (N, 4), the torque scale (4,), the input offset and scale, the output scale, the members'
    training and validation weights of the points (M, N). Its result: :func:`_fit`'s, stacked over G.
    """
    adam = optax.adam(settings.learning_rate)
    lbfgs = optax.lbfgs(learning_rate=1.0, memory_size=settings.lbfgs_memory, linesearch=None)
    track = partial(_track, n_fold_members=n_fold_members, stop_tolerance=settings.stop_tolerance)

    def train(init, lam, q, tau, torque_scale, offset, spread, output, train_mask, val_mask):  # type: ignore[no-untyped-def]
        objective = _objective(spec, settings.loss, (offset, spread, output), q, tau, torque_scale)
        gradient: _Gradient = jax.value_and_grad(objective, has_aux=True)

        def one_group(theta0: jax.Array, lam_: jax.Array) -> dict[str, jax.Array]:
            members = train_mask.shape[0]
            theta = jnp.broadcast_to(theta0, (members, theta0.shape[0]))
            evaluate = partial(_evaluate, gradient=gradient, lam=lam_, train_mask=train_mask, val_mask=val_mask)
            return _fit(theta, evaluate, track, adam, lbfgs, settings)

        # lax.map, not vmap: each (lambda, seed) bit for bit as if trained alone (module docstring)
        return jax.lax.map(lambda args: one_group(*args), (init, lam))

    return train


def _objective(
    spec: NetworkSpec,
    loss: Literal["scaled", "thesis"],
    scaling: tuple[jax.Array, jax.Array, jax.Array],
    q: jax.Array,
    tau: jax.Array,
    torque_scale: jax.Array,
) -> Callable[[jax.Array, jax.Array, jax.Array, jax.Array], tuple[jax.Array, jax.Array]]:
    """The loss of one network on ``q`` (rad, (N, 4)) and ``tau`` (Nm, (N, 4)), as the module docstring defines it.

    Returns:
        ``(weights (P,), lambda, training weights (N,), validation weights (N,)) -> (training loss with
        the penalty, validation loss)``: the points' weighted means (``loss`` "scaled": dimensionless;
        "thesis": Nm^2).
    """

    def objective(theta, lam_, train_w, val_w):  # type: ignore[no-untyped-def]
        error = networks.torque(spec, scaling, theta, q) - tau
        if loss == "scaled":
            per_point = jnp.mean((error / torque_scale) ** 2, axis=1)
            penalty = lam_ * jnp.mean(jnp.abs(theta))
        else:  # Eq. 3.7: the squared error in Nm^2 (its mean), L1 summed over the parameters
            per_point = jnp.mean(error**2, axis=1)
            penalty = lam_ * jnp.sum(jnp.abs(theta))
        data = jnp.sum(train_w * per_point) / jnp.sum(train_w)
        val = jnp.sum(val_w * per_point) / jnp.maximum(jnp.sum(val_w), 1.0)
        return data + penalty, val

    return objective


def _evaluate(
    weights: jax.Array, gradient: _Gradient, lam: jax.Array, train_mask: jax.Array, val_mask: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Every member's training loss (M,), validation loss (M,) and gradient (M, P) at ``weights`` (M, P)."""
    (obj, val), grad = jax.vmap(gradient, in_axes=(0, None, 0, 0))(weights, lam, train_mask, val_mask)
    return obj, val, grad


def _track(
    t: _Track, step: Any, weights: jax.Array, val: jax.Array, n_fold_members: int, stop_tolerance: float
) -> _Track:
    """``t`` after a step whose members' validation losses are ``val`` (M,) at ``weights`` (M, P): the
    MVL (the mean over the first ``n_fold_members``, the fold networks) and the stopping step."""
    mean_val = jnp.mean(val[:n_fold_members])
    better = mean_val < t.best  # NaN never is
    best = jnp.where(better, mean_val, t.best)
    # ``best`` only falls, so the last step within the tolerance of the running best is,
    # at the end, the last step at or after the MVL within the tolerance of the MVL
    near = mean_val <= best * (1.0 + stop_tolerance)
    return _Track(
        best,
        jnp.where(better, step, t.step),
        jnp.where(better, weights, t.params),
        jnp.where(near, step, t.stop),
        jnp.where(near, weights, t.stop_params),
    )


def _fit(
    theta: jax.Array,
    evaluate: _Evaluate,
    track: _TrackStep,
    adam: optax.GradientTransformation,
    lbfgs: optax.GradientTransformation,
    settings: TrainingSettings,
) -> dict[str, jax.Array]:
    """One group's members trained from ``theta`` (M, P): Adam, then L-BFGS (or one more evaluation
    without it).

    Returns:
        The MVL (``best``), its step and the members' weights there (``params``), the stopping step
        and the weights there (``stop``, ``stop_params``), the last weights (``last``), and the
        training and validation loss of every member at every step (``train_curve``,
        ``validation_curve``, (steps, M)).
    """
    theta, t, objs, vals = _adam_phase(theta, evaluate, track, adam, settings.adam_steps)
    curves_obj, curves_val = [objs], [vals]
    if settings.lbfgs_steps:
        last, t, objs, vals = _lbfgs_phase(theta, t, evaluate, track, lbfgs, settings)
        curves_obj.append(objs)
        curves_val.append(vals)
    else:  # evaluate the last Adam step's weights too
        obj, val, _ = evaluate(theta)
        t = track(t, settings.adam_steps, theta, val)
        curves_obj.append(obj[None])
        curves_val.append(val[None])
        last = theta
    return {
        "best": t.best,
        "step": t.step,
        "params": t.params,
        "stop": t.stop,
        "stop_params": t.stop_params,
        "last": last,
        "train_curve": jnp.concatenate(curves_obj),
        "validation_curve": jnp.concatenate(curves_val),
    }


def _adam_phase(
    theta: jax.Array, evaluate: _Evaluate, track: _TrackStep, adam: optax.GradientTransformation, steps: int
) -> tuple[jax.Array, _Track, jax.Array, jax.Array]:
    """``steps`` of Adam from ``theta`` (M, P), tracked from the start.

    Returns:
        The weights after the last step, the track, and every step's training and validation losses (steps, M).
    """

    def adam_step(carry, step):  # type: ignore[no-untyped-def]
        weights, state, t = carry
        obj, val, grad = evaluate(weights)
        t = track(t, step, weights, val)
        updates, state = adam.update(grad, state, weights)
        return (optax.apply_updates(weights, updates), state, t), (obj, val)

    t0 = _Track(jnp.asarray(jnp.inf), jnp.asarray(0), theta, jnp.asarray(0), theta)
    (theta, _, t), (objs, vals) = jax.lax.scan(adam_step, (theta, adam.init(theta), t0), jnp.arange(steps))
    return theta, t, objs, vals


def _lbfgs_phase(
    theta: jax.Array,
    t: _Track,
    evaluate: _Evaluate,
    track: _TrackStep,
    lbfgs: optax.GradientTransformation,
    settings: TrainingSettings,
) -> tuple[jax.Array, _Track, jax.Array, jax.Array]:
    """``settings.lbfgs_steps`` of L-BFGS from ``theta`` (M, P), Adam's weights, continuing the track ``t``.

    Returns:
        The last accepted weights, the track, and every step's training and validation losses of
        the accepted weights (steps, M).
    """

    def lbfgs_step(carry, step):  # type: ignore[no-untyped-def]
        s, t = carry
        return _lbfgs_step(s, t, step, evaluate, track, lbfgs)

    m = theta.shape[0]
    start = _Lbfgs(
        theta,
        jnp.full(m, jnp.inf),
        jnp.full(m, jnp.inf),
        jnp.zeros_like(theta),
        jnp.zeros_like(theta),
        jnp.ones(m),
        jax.vmap(lbfgs.init)(theta),
        theta,
    )
    steps = jnp.arange(settings.adam_steps, settings.adam_steps + settings.lbfgs_steps)
    (s, t), (objs, vals) = jax.lax.scan(lbfgs_step, (start, t), steps)
    return s.good, t, objs, vals


def _lbfgs_step(
    s: _Lbfgs, t: _Track, step: Any, evaluate: _Evaluate, track: _TrackStep, lbfgs: optax.GradientTransformation
) -> tuple[tuple[_Lbfgs, _Track], tuple[jax.Array, jax.Array]]:
    """One L-BFGS iteration: the candidate evaluated, accepted or not by the Armijo test (a refused
    step is halved next time), the next direction and candidate from the accepted weights.

    Returns:
        The next (L-BFGS state, track), and the accepted weights' training and validation losses (M,).
    """
    obj, val, grad = evaluate(s.candidate)
    slope = jnp.sum(s.good_grad * s.direction, axis=1)
    accept = jnp.isfinite(obj) & (obj <= s.good_obj + ARMIJO * s.scale * slope)
    a1 = accept[:, None]
    good = jnp.where(a1, s.candidate, s.good)
    good_grad = jnp.where(a1, grad, s.good_grad)
    new_dir, new_state = jax.vmap(lbfgs.update)(grad, s.state, s.candidate)
    state = jax.tree.map(
        lambda new, old: jnp.where(accept.reshape((-1,) + (1,) * (new.ndim - 1)), new, old),
        new_state,
        s.state,
    )
    direction = jnp.where(a1, new_dir, s.direction)
    # L-BFGS may give an ascent direction where the curvature is negative: then steepest descent
    descent = jnp.sum(good_grad * direction, axis=1) < 0.0
    direction = jnp.where(descent[:, None], direction, -good_grad)
    scale = jnp.where(accept, 1.0, 0.5 * s.scale)
    good_obj = jnp.where(accept, obj, s.good_obj)
    good_val = jnp.where(accept, val, s.good_val)
    t = track(t, step, good, good_val)
    nxt = _Lbfgs(good, good_obj, good_val, good_grad, direction, scale, state, good + scale[:, None] * direction)
    return (nxt, t), (good_obj, good_val)


@lru_cache(maxsize=16)
def _compiled(
    spec: NetworkSpec, settings: TrainingSettings, n_groups: int, n_points: int, n_fold_members: int, n_members: int
) -> Any:
    """The compiled program for one shape (kept: the hyper-parameter search calls each shape again)."""
    f64 = jnp.float64
    shapes = (
        jax.ShapeDtypeStruct((n_groups, spec.n_weights), f64),  # init
        jax.ShapeDtypeStruct((n_groups,), f64),  # lambda
        jax.ShapeDtypeStruct((n_points, 4), f64),  # q
        jax.ShapeDtypeStruct((n_points, 4), f64),  # tau
        jax.ShapeDtypeStruct((4,), f64),  # torque scale
        jax.ShapeDtypeStruct((spec.n_inputs,), f64),  # input offset
        jax.ShapeDtypeStruct((spec.n_inputs,), f64),  # input scale
        jax.ShapeDtypeStruct((spec.n_outputs,), f64),  # output scale
        jax.ShapeDtypeStruct((n_members, n_points), f64),  # training weights
        jax.ShapeDtypeStruct((n_members, n_points), f64),  # validation weights
    )
    return jax.jit(_program(spec, settings, n_fold_members)).lower(*shapes).compile()


def train_group(
    spec: NetworkSpec,
    data: StationaryDataset,
    lambdas: Sequence[float],
    seeds: Sequence[int],
    settings: TrainingSettings,
) -> list[NetworkResult]:
    """Train every ``(lambda, seed)`` network of one shape together; one result each, lambdas outer, seeds inner.

    All networks run in one compiled program (``jax.lax.map`` over the parameter sets,
    ``jax.lax.scan`` over the steps), compiled once per shape, number of networks and settings,
    and kept.
    Each ``(lambda, seed)`` starts from :func:`daror_runtime.neural.networks.init_weights` of its
    seed; its fold networks (and the full-data network) share those initial weights. The result
    is, bit for bit, that of training each ``(lambda, seed)`` alone.

    Args:
        spec: the network shape.
        data: the training data (all of it; the folds are cut here).
        lambdas: L1 rates (>= 0; their meaning depends on ``settings.loss``, see the module).
        seeds: initialisation seeds (0 <= seed < 2**63).
        settings: how to train.

    Raises:
        ValueError: no lambda or no seed, a negative or non-finite lambda, a seed out of range.
        DataError, IdentifiabilityError: see :func:`prepare_data`.
    """
    if not lambdas or not seeds:
        raise ValueError("train_group needs at least one lambda and one seed")
    if any(not np.isfinite(v) or v < 0 for v in lambdas):
        raise ValueError(f"L1 rates must be finite and >= 0; got {list(lambdas)}")
    prepared = prepare_data(spec, data, settings)
    pairs = [(float(lam), int(seed)) for lam in lambdas for seed in seeds]
    init = np.stack([networks.init_weights(spec, seed) for _, seed in pairs])
    lam = np.array([p[0] for p in pairs])
    train_mask, val_mask = prepared.masks(settings)
    n_fold = len(settings.held_out())

    wall0, cpu0 = time.perf_counter(), time.process_time()
    known = _compiled.cache_info().misses
    program = _compiled(spec, settings, len(pairs), prepared.q.shape[0], n_fold, train_mask.shape[0])
    compile_s = time.perf_counter() - wall0 if _compiled.cache_info().misses > known else 0.0
    s = prepared.scaling
    out = program(
        init, lam, prepared.q, prepared.tau, prepared.torque_scale,
        s.input_offset, s.input_scale, s.output_scale, train_mask, val_mask,
    )  # fmt: skip
    out = {k: np.asarray(v) for k, v in out.items()}  # waits for the result
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0

    results = []
    for g, (lam_g, seed) in enumerate(pairs):
        stop = int(out["stop"][g])
        train_curve = out["train_curve"][g]  # (S, M)
        val_curve = out["validation_curve"][g]
        at_stop = out["stop_params"][g]  # (M, P)
        final = settings.final_fit
        results.append(
            NetworkResult(
                spec=spec,
                l1=lam_g,
                seed=seed,
                settings=settings,
                mvl=float(out["best"][g]),
                mvl_step=int(out["step"][g]),
                stop_step=stop,
                train_loss=float(np.mean(train_curve[-1, :n_fold])),
                validation_loss=float(np.mean(val_curve[-1, :n_fold])),
                parameters=np.array(at_stop[n_fold] if final else at_stop[0]),
                mvl_parameters=np.array(out["params"][g][:n_fold]),
                final_train_loss=float(train_curve[stop, n_fold]) if final else None,
                train_curve=np.mean(train_curve[:, :n_fold], axis=1),
                validation_curve=np.mean(val_curve[:, :n_fold], axis=1),
                scaling=prepared.scaling,
                wall_s=wall,
                cpu_s=cpu,
                compile_s=compile_s,
            )
        )
    return results
