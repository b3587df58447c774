"""Checkpoint files: written atomically, loaded without unpickling arbitrary objects.

`last.pt` always holds the newest checkpoint (write to a temporary file, fsync, rename:
a run killed mid-write leaves the previous one intact); stage ends are also kept as
`stage_<name>.pt`. `last.json` says where the run stands, for people and scripts.
Payloads hold only tensors, numbers, strings, lists and dicts, so `torch.load` runs with
`weights_only=True`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch


def _plain(obj):
    """Dataclasses -> dicts, numpy -> tensors, tuples -> lists (weights_only-safe)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {"__dataclass__": type(obj).__name__, **{f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}}
    if isinstance(obj, np.ndarray):
        return {"__ndarray__": torch.from_numpy(obj.copy()), "dtype": str(obj.dtype)}
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return {"__tuple__": [_plain(v) for v in obj]} if isinstance(obj, tuple) else [_plain(v) for v in obj]
    if isinstance(obj, (np.integer, np.floating)):
        return obj.item()
    return obj


def _restore(obj, classes: dict):
    if isinstance(obj, dict):
        if "__ndarray__" in obj:
            return obj["__ndarray__"].numpy().astype(obj["dtype"])
        if "__tuple__" in obj:
            return tuple(_restore(v, classes) for v in obj["__tuple__"])
        if "__dataclass__" in obj:
            cls = classes[obj["__dataclass__"]]
            return cls(**{k: _restore(v, classes) for k, v in obj.items() if k != "__dataclass__"})
        return {k: _restore(v, classes) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_restore(v, classes) for v in obj]
    return obj


def save(folder: Path, payload: dict, tag: str | None = None) -> Path:
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".last", suffix=".tmp")
    with os.fdopen(fd, "wb") as f:
        torch.save(_plain(payload), f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, folder / "last.pt")
    if tag:
        shutil.copyfile(folder / "last.pt", folder / f".{tag}.tmp")
        os.replace(folder / f".{tag}.tmp", folder / f"{tag}.pt")
    rs = payload.get("run_state")
    info = {"stage": getattr(rs, "stage", None), "step": getattr(rs, "step", None), "tag": tag}
    with open(folder / ".last.json.tmp", "w") as f:
        json.dump(info, f)
    os.replace(folder / ".last.json.tmp", folder / "last.json")
    return folder / "last.pt"


def load(path: Path) -> dict:
    from cogs.train.trainer import RunState

    raw = torch.load(path, map_location="cpu", weights_only=True)
    return _restore(raw, {"RunState": RunState})


def load_last(folder: Path) -> dict | None:
    path = Path(folder) / "last.pt"
    return load(path) if path.exists() else None


def load_module(module: torch.nn.Module, state: dict) -> None:
    """Copy a state dict into a module whose per-Gaussian tensors may differ in length
    (call before creating optimizers: parameters are replaced by new objects)."""
    params = dict(module.named_parameters())
    buffers = dict(module.named_buffers())
    missing = (set(params) | set(buffers)) - set(state)
    unknown = set(state) - set(params) - set(buffers)
    assert not missing and not unknown, (sorted(missing), sorted(unknown))
    from cogs.train.density import replace_parameter

    for name, value in state.items():
        owner_name, _, attr = name.rpartition(".")
        owner = module.get_submodule(owner_name) if owner_name else module
        if name in params:
            replace_parameter(owner, attr, value)
        else:
            setattr(owner, attr, value.clone())
