"""Body models: the `BodyModel` interface, LBS, and the registry of implementations.

Anny is the default (free, ships its assets). A second implementation (SMPL via smplx)
registers itself in `MODELS` with its bone count, so scene validation can check pose
arrays without building the model.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from cogs.body.base import BodyModel, Canonical
from cogs.body.lbs import blend_transforms, lbs_gaussians, lbs_points


@dataclass(frozen=True)
class ModelInfo:
    n_bones: int
    n_shape: int
    factory: Callable[[], BodyModel]
    source: Callable[[], str] = lambda: ""
    """What the model is built from (a licensed model file, say): a model built from
    another source is never reused."""


def _anny() -> BodyModel:
    from cogs.body.anny_body import AnnyBody

    return AnnyBody()


def _smpl() -> BodyModel:
    # smplx is imported lazily and the licensed model file is looked up only here
    # (COGS_SMPL_MODEL or cogs.body.smpl_body.set_smpl_model_path); a missing file is a
    # UserError that says what to set.
    from cogs.body.smpl_body import SmplBody

    return SmplBody()


def _smpl_source() -> str:
    from cogs.body.smpl_body import smpl_model_path

    return str(smpl_model_path())


MODELS: dict[str, ModelInfo] = {
    "anny": ModelInfo(n_bones=104, n_shape=6, factory=_anny),
    "smpl": ModelInfo(n_bones=24, n_shape=10, factory=_smpl, source=_smpl_source),
}

_instances: dict[tuple[str, str, str], BodyModel] = {}


def load_body_model(name: str = "anny", device=None) -> BodyModel:
    """The named body model on `device` (default the host), built once per process and
    device (another device gets a copy of the host's)."""
    if name not in MODELS:
        raise KeyError(f"unknown body model {name!r}; known: {', '.join(sorted(MODELS))}")
    import copy

    import torch

    dev = torch.device("cpu" if device is None else device)
    info = MODELS[name]
    key = (name, str(dev), info.source())
    if key not in _instances:
        if dev.type == "cpu":
            _instances[key] = info.factory()
        else:
            _instances[key] = copy.deepcopy(load_body_model(name)).to(dev)
    return _instances[key]


__all__ = [
    "BodyModel",
    "Canonical",
    "MODELS",
    "ModelInfo",
    "blend_transforms",
    "lbs_gaussians",
    "lbs_points",
    "load_body_model",
]
