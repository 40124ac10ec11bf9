"""The networks ``daror fit penn|nnn`` trains by default, and the thesis's (Tables I and II, Eq. 3.7).

A :class:`Preset` is everything a fit needs besides the data: the network shape, the L1 rate,
how many initialisations to try and how to train them. The registry's options
(``daror_runtime.models.registry.NetworkOptions``) override single fields of a preset
(:func:`with_options`); ``--thesis`` picks the thesis's preset as the starting point.

* **Default PENN** (D206): 2 x 32 tanh on the joint angles ``q``, the scaled loss with
  ``lambda = 1e-6``, 100 Adam steps then 850 L-BFGS iterations (memory 30), one initialisation,
  4 folds (the last held out), final fit. Why: docs/models.md, "Generalising between paths". On
  low-noise data with training and validation on different paths, the former default (sin/cos
  inputs, 200 L-BFGS iterations, 2 initialisations) validated at 7.7x PLF+; ``q`` inputs and the
  longer L-BFGS bring it to 1.6-1.8x, and no worse on datasets A and B. One initialisation: the MVL
  hardly predicts which of two validates better, and each costs two networks' training (its fold
  network and its final fit). 2 x 32 tanh and not the prototype's 2 x 64 softplus: tanh converges
  in a few hundred full-batch steps where softplus needs thousands.
* **Default NNN**: the same shape and training with four outputs.
* **Residual PENN and NNN** (:func:`residual_preset`: ``penn-residual`` and ``daror residual
  --learned``): 2 x 16 tanh, ``q`` inputs, 4 initialisations, otherwise the default. What remains
  after a physical model is small and smooth (tens of mNm over the workspace, against sensor noise
  of the same size), and the joints stay far from +-pi, so ``[sin q, cos q]`` adds only redundant
  inputs. The model is the *mean* of the four initialisations' networks (one 2 x 64 network,
  block-diagonal): a single network's error varies with its start, and the best minimal validation
  loss hardly predicts which start validates best. On the ``residual_*`` scenarios (PLF+ base, 16
  initialisations each) a single 2 x 16 network on ``q`` ended 1.08 +- 0.02 x the noise floor on
  the tilt (up to 1.11 x), the 2 x 32 sin/cos default 1.13 +- 0.02 x, the mean of four 1.04-1.06 x
  (docs/residual.md).
* **Thesis PENN** (Table I's best): 2 x 10 sigmoid, sin/cos inputs, ``lambda = 0.1``; **thesis NNN**
  (Table II's best): 2 x 5 tanh, sin/cos inputs, ``lambda = 1e-5``. Both with the thesis's loss
  (Eq. 3.7: Nm^2 plus ``lambda ||theta||_1``, no scaling), Adam only, 5 initialisations (Sec.
  4.2.3), 4 folds (75 % training, 25 % validation, Sec. 4.2.5).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from daror_runtime.models.neural import NetworkSpec
from daror_runtime.neural.training import TrainingSettings

__all__ = ["MAX_INITS", "RESIDUAL_PRESETS", "Preset", "init_seeds", "preset", "residual_preset", "with_options"]

#: Most initialisations one fit trains (each costs a network's training).
MAX_INITS = 100


@dataclass(frozen=True)
class Preset:
    """A network to train and how: shape, L1 rate, initialisations, training settings.

    ``ensemble``: the model is the mean of every initialisation's network, as one network of
    ``inits x width`` units (:func:`daror_runtime.neural.ensemble.mean_network`), instead of the
    one with the best minimal validation loss.
    """

    name: str
    spec: NetworkSpec
    l1: float
    inits: int
    settings: TrainingSettings
    ensemble: bool = False

    def describe(self) -> str:
        s = self.settings
        optimiser = f"Adam {s.adam_steps} steps" + (f" + L-BFGS {s.lbfgs_steps}" if s.lbfgs_steps else "")
        return (
            f"{self.name}: {self.spec.describe()}, {s.loss} loss, lambda {self.l1:g}, {optimiser}, "
            f"{self.inits} inits, {s.folds} folds ({s.validation_folds} held out)"
            + (", final fit on all data" if s.final_fit else "")
            + (
                f"; the model is their mean, one network of {self.inits * self.spec.width} units"
                if self.ensemble
                else ""
            )
        )


_DEFAULT_SETTINGS = TrainingSettings()
#: The default PENN's and NNN's training (D206): L-BFGS run four times longer, with three times the
#: memory. On low-noise data (a tenth of dataset B's sensor noise and direction error, training and
#: validation on different paths) 300 steps left the PENN at twice PLF+'s training error and 7.7x its
#: validation error; dataset B's 0.42 Nm of direction error had hidden that the fit stopped short.
_NETWORK_SETTINGS = TrainingSettings(lbfgs_steps=850, lbfgs_memory=30)

PRESETS: dict[tuple[str, bool], Preset] = {
    ("penn", False): Preset(
        "default PENN",
        NetworkSpec(model="penn", layers=2, width=32, activation="tanh", inputs="q"),
        l1=1e-6,
        inits=1,
        settings=_NETWORK_SETTINGS,
    ),
    ("nnn", False): Preset(
        "default NNN",
        NetworkSpec(model="nnn", layers=2, width=32, activation="tanh", inputs="q"),
        l1=1e-6,
        inits=1,
        settings=_NETWORK_SETTINGS,
    ),
    ("penn", True): Preset(
        "thesis PENN (Table I)",
        NetworkSpec(model="penn", layers=2, width=10, activation="sigmoid", inputs="sincos"),
        l1=0.1,
        inits=5,
        settings=TrainingSettings(loss="thesis", adam_steps=2000, learning_rate=1e-3, lbfgs_steps=0),
    ),
    ("nnn", True): Preset(
        "thesis NNN (Table II)",
        NetworkSpec(model="nnn", layers=2, width=5, activation="tanh", inputs="sincos"),
        l1=1e-5,
        inits=5,
        settings=TrainingSettings(loss="thesis", adam_steps=2000, learning_rate=1e-3, lbfgs_steps=0),
    ),
}


RESIDUAL_PRESETS: dict[str, Preset] = {
    "penn": Preset(
        "residual PENN",
        NetworkSpec(model="penn", layers=2, width=16, activation="tanh", inputs="q"),
        l1=1e-6,
        inits=4,
        settings=_DEFAULT_SETTINGS,
        ensemble=True,
    ),
    "nnn": Preset(
        "residual NNN",
        NetworkSpec(model="nnn", layers=2, width=16, activation="tanh", inputs="q"),
        l1=1e-6,
        inits=4,
        settings=_DEFAULT_SETTINGS,
        ensemble=True,
    ),
}


def residual_preset(model: str, thesis: bool = False) -> Preset:
    """The preset of a network learned on a physical model's residual (``penn`` or ``nnn``); with ``thesis``
    the thesis's network (:func:`preset`), which has no residual form of its own.

    Raises:
        KeyError: another model.
    """
    return PRESETS[(model, True)] if thesis else RESIDUAL_PRESETS[model]


def preset(model: str, thesis: bool = False) -> Preset:
    """The default (or, with ``thesis``, the thesis's) preset of ``model`` (``penn`` or ``nnn``).

    Raises:
        KeyError: another model.
    """
    return PRESETS[(model, thesis)]


def with_options(base: Preset, options: Any) -> Preset:
    """``base`` with the fields the registry's options set (None: keep the preset's).

    ``options`` has the fields of ``NetworkOptions``: ``layers``, ``width``, ``activation``,
    ``inputs``, ``l1``, ``inits``, ``folds``, ``adam_steps``, ``lbfgs`` (True: the preset's L-BFGS
    iterations, or the default's when the preset has none; False: none). The name says which
    fields were changed.

    Raises:
        pydantic ValidationError: a combination the spec or the settings refuse (a network of too
            many weights, no training step at all).
    """
    changed: dict[str, Any] = {
        k: getattr(options, k)
        for k in ("layers", "width", "activation", "inputs", "l1", "inits", "folds", "adam_steps", "lbfgs")
        if getattr(options, k) is not None
    }
    spec_fields = {k: v for k, v in changed.items() if k in ("layers", "width", "activation", "inputs")}
    spec = NetworkSpec(**(base.spec.model_dump() | spec_fields)) if spec_fields else base.spec
    settings: dict[str, Any] = {}
    if "folds" in changed:
        settings["folds"] = changed["folds"]
        settings["validation_folds"] = min(base.settings.validation_folds, changed["folds"])
    if "adam_steps" in changed:
        settings["adam_steps"] = changed["adam_steps"]
    if "lbfgs" in changed:
        on = base.settings.lbfgs_steps or _DEFAULT_SETTINGS.lbfgs_steps
        settings["lbfgs_steps"] = on if changed["lbfgs"] else 0
    return replace(
        base,
        name=base.name + (", with " + ", ".join(f"{k}={v}" for k, v in changed.items()) if changed else ""),
        spec=spec,
        l1=float(changed.get("l1", base.l1)),
        inits=int(changed.get("inits", base.inits)),
        settings=TrainingSettings.model_validate(base.settings.model_dump() | settings) if settings else base.settings,
    )


def init_seeds(seed: int, inits: int) -> list[int]:
    """The initialisation seeds of a fit with ``seed``: ``1000 * seed + i`` for ``i < inits``.

    So fits with different seeds never share an initialisation (``inits`` <= :data:`MAX_INITS`).

    Raises:
        ValueError: ``seed`` negative or too large, ``inits`` out of 1 .. MAX_INITS.
    """
    if not 1 <= inits <= MAX_INITS:
        raise ValueError(f"inits {inits}: expected 1 to {MAX_INITS}")
    if not 0 <= seed < 2**53 // 1000:
        raise ValueError(f"seed {seed}: expected 0 <= seed < {2**53 // 1000}")
    return [1000 * seed + i for i in range(inits)]
