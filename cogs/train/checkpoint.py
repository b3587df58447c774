"""Checkpoint files: written atomically, read without unpickling arbitrary objects.

`last.pt` always holds the newest checkpoint (write to a temporary file, fsync, rename:
a run killed mid-write leaves the previous one intact); stage ends are also kept as
`stage_<name>.pt`. `last.json` says where the run stands, for people and scripts.
Payloads hold only tensors, numbers, strings, lists and dicts (dataclasses and arrays are
flattened to those), so they load with `weights_only=True`.

Payload: `run_state` (RunState), `body_model`, `branches` (the model's state dicts, see
`Model.payload`), `optimizers` and `optimizer_groups`, `density` (each branch's density
statistics), `rng` (every generator's state), `planes_assigned`.
"""

from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from cogs.data.io import atomic_writer, write_json
from cogs.errors import UserError
from cogs.model import read_checkpoint


@dataclass
class RunState:
    """Where the run stands; saved in every checkpoint."""

    stage: int = 0  # index into the run's stage list of the stage in progress
    step: int = 0  # completed steps of that stage
    history: list[dict] = field(default_factory=list)
    stage_seconds: dict[str, float] = field(default_factory=dict)
    stage_cpu_seconds: dict[str, float] = field(default_factory=dict)
    """Processor time per stage (all threads): beside stage_seconds, how busy the cores were."""
    density_events: list[dict] = field(default_factory=list)


def _plain(obj):
    """Dataclasses -> dicts, numpy -> tensors, tuples -> lists (weights_only-safe)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {"__dataclass__": type(obj).__name__, **{f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}}
    if isinstance(obj, np.ndarray):
        return {"__ndarray__": torch.from_numpy(obj.copy()), "dtype": str(obj.dtype)}
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return {"__tuple__": [_plain(v) for v in obj]} if isinstance(obj, tuple) else [_plain(v) for v in obj]
    if isinstance(obj, (np.integer, np.floating)):
        return obj.item()
    return obj


_CLASSES = {"RunState": RunState}


def _restore(obj):
    if isinstance(obj, dict):
        if "__ndarray__" in obj:
            return obj["__ndarray__"].numpy().astype(obj["dtype"])
        if "__tuple__" in obj:
            return tuple(_restore(v) for v in obj["__tuple__"])
        if "__dataclass__" in obj:
            cls = _CLASSES[obj["__dataclass__"]]
            return cls(**{k: _restore(v) for k, v in obj.items() if k != "__dataclass__"})
        return {k: _restore(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_restore(v) for v in obj]
    return obj


def save(folder: Path, payload: dict, tag: str | None = None) -> Path:
    folder = Path(folder)
    with atomic_writer(folder / "last.pt", "wb", fsync=True) as f:
        torch.save(_plain(payload), f)
    if tag:
        with atomic_writer(folder / f"{tag}.pt", "wb") as f, open(folder / "last.pt", "rb") as src:
            shutil.copyfileobj(src, f)
    rs = payload.get("run_state")
    write_json(folder / "last.json", {"stage": getattr(rs, "stage", None), "step": getattr(rs, "step", None), "tag": tag})
    return folder / "last.pt"


def load(path: Path) -> dict:
    return _restore(read_checkpoint(path))


def load_last(folder: Path, name: str | None = None) -> dict | None:
    """The newest checkpoint (`last.pt`), or the one named; None when there is none."""
    path = Path(folder) / (name or "last.pt")
    if name is not None and not path.is_file():
        have = ", ".join(sorted(p.name for p in Path(folder).glob("*.pt"))) or "none"
        raise UserError(f"--checkpoint {name}: no such file in {folder} (there: {have})")
    return load(path) if path.exists() else None
