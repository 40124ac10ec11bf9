"""The ``augmented`` model kind, registered with the model registry through an entry point.

``pyproject.toml`` names :data:`MODEL_KIND` in the group
:data:`daror_runtime.models.registry.ENTRY_POINT_GROUP`, so the models package never names the
residual analysis (which depends on it, not the other way round). This module is only the
declaration: it imports nothing but the registry, so listing the kinds (help texts, the settings
check) does not import the residual analysis; the model and its fitter are imported when used.
"""

from __future__ import annotations

from daror_runtime.models.registry import ModelKind, ModelOptions

#: The augmented kind: a base model plus the effects the training data support. It takes only a
#: name; a session may train it (it is validated like any other before it drives the arm). It is a
#: physical model: a PENN residual may sit on it (``daror residual --learned``).
MODEL_KIND = ModelKind(
    "augmented",
    "a base model plus the physical effects the data support (daror residual)",
    "daror_runtime.residual.model:AugmentedModel",
    "daror_runtime.residual.model:fit_augmented_kind",
    options=ModelOptions,
    session_training=True,
    physical=True,
)
