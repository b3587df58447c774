"""The trained model: the branches and their body model, apart from any trainer.

`Model.load(run, device=...)` rebuilds it from a run folder alone — the run's config.yaml
and a checkpoint — with no scene image read: every tensor a branch needs (the human's
seed and input poses, the object's trajectory, size and rest frames, the scene's planes)
is in its state dict. It then poses and renders any frame, body pose, object pose and
camera (`render`), which is what evaluation, the pose refit, rendering and export use.

    model = Model.load("demo_out", device="cpu")
    out = model.render(viewmat, K, width, height, frame=12)               # a training frame
    out = model.render(viewmat, K, width, height, frame=0, poses={"human": (pose, transl)})

Device: the model's tensors live on one device (`model.to(device)`); every tensor it
creates takes that device. The rasterizer backend "auto" picks gsplat for CUDA tensors.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

import cogs.branches  # noqa: F401  (registers the branches)
from cogs.body import load_body_model
from cogs.branches.base import REGISTRY, Branch, Splats
from cogs.branches.compositor import CompositeRender, composite
from cogs.errors import UserError

log = logging.getLogger(__name__)


class Model(torch.nn.Module):
    """The branches of one reconstruction, rendered together."""

    def __init__(self, branches: dict[str, Branch] | None = None, backend: str = "auto",
                 near: float = 0.05, far: float = 100.0):
        super().__init__()
        self.branches = torch.nn.ModuleDict()
        self.backend, self.near, self.far = backend, near, far
        for b in (branches or {}).values():
            self.add(b)

    # -- structure ------------------------------------------------------------------------
    def add(self, branch: Branch) -> None:
        """Add (or replace) a branch, keeping the registry's order."""
        have = {**dict(self.branches.items()), branch.name: branch}
        self.branches = torch.nn.ModuleDict({n: have[n] for n in REGISTRY if n in have})

    def get(self, name: str) -> Branch | None:
        return self.branches[name] if name in self.branches else None

    @property
    def human(self):
        return self.get("human")

    @property
    def object(self):
        return self.get("object")

    @property
    def scene(self):
        return self.get("scene")

    def available(self) -> tuple[str, ...]:
        """The branches present with at least one Gaussian, in registry order."""
        return tuple(n for n, b in self.branches.items() if len(b) > 0)

    @property
    def device(self) -> torch.device:
        return next(iter(self.branches.values())).device

    @property
    def n_frames(self) -> int:
        for b in self.branches.values():
            if hasattr(b, "n_frames"):
                return int(b.n_frames)
        return 0

    def counts(self) -> dict[str, int]:
        return {n: (len(self.branches[n]) if n in self.branches else 0) for n in REGISTRY}

    # -- rendering ------------------------------------------------------------------------
    def prepare(self, branches: tuple[str, ...] | None = None) -> dict[str, Any]:
        """Each branch's per-step shared work (the human's decoded field)."""
        names = self.available() if branches is None else branches
        return {n: self.branches[n].prepare() for n in names if n in self.branches}

    def splats(self, frame: int, viewmat: Tensor, branches: tuple[str, ...] | None = None,
               poses: dict[str, Any] | None = None, prepared: dict[str, Any] | None = None) -> dict[str, Splats]:
        """World-space splats of `branches` (default: every available one) at `frame`, or
        in `poses[name]` where given (human: (pose [1, J, 3], transl [1, 3]); object:
        (translation [3], quat [4]))."""
        have = self.available()
        names = have if branches is None else tuple(b for b in branches if b in have)
        campos = -(viewmat[:3, :3].T @ viewmat[:3, 3])
        poses, prepared = poses or {}, prepared or {}
        return {n: self.branches[n].splats(frame, campos, poses.get(n), prepared.get(n)) for n in names}

    def render(self, viewmat: Tensor, K: Tensor, width: int, height: int, frame: int, *,
               branches: tuple[str, ...] | None = None, background: Tensor | None = None,
               poses: dict[str, Any] | None = None, prepared: dict[str, Any] | None = None,
               splats: dict[str, Splats] | None = None) -> CompositeRender:
        """Render `branches` (default all) at `frame` from a camera (viewmat [4, 4]
        world->camera, OpenCV; K [3, 3]): RGB, alpha, depth and per-branch alpha."""
        if splats is None:
            splats = self.splats(frame, viewmat, branches, poses, prepared)
        return composite(splats, viewmat, K, width, height, background, self.backend, self.near, self.far)

    # -- persistence ----------------------------------------------------------------------
    def payload(self) -> dict:
        """What a checkpoint stores of the model: the body model's name and each
        registered branch's state dict (None where absent)."""
        h = self.human
        return {
            "body_model": h.body.name if h is not None else None,
            "branches": {n: (self.branches[n].state_dict() if n in self.branches else None) for n in REGISTRY},
        }

    @classmethod
    def from_payload(cls, branches: dict[str, dict | None], body_model: str | None, cfg, device="cpu") -> "Model":
        """Rebuild from a checkpoint's branch state dicts and the run's `TrainConfig`."""
        body = load_body_model(body_model) if body_model else None
        model = cls(backend=cfg.backend)
        for name, state in branches.items():
            if state is None:
                continue
            if name not in REGISTRY:
                raise UserError(f"the checkpoint holds a branch {name!r} this cogs does not know ({', '.join(REGISTRY)})")
            model.add(REGISTRY[name].from_state(state, cfg.branches, body))
        return model.to(device)

    @classmethod
    def load(cls, run: str | Path, device: str | torch.device = "cpu", checkpoint: str | Path | None = None) -> "Model":
        """The model of a run folder (its last checkpoint, or `checkpoint`) on `device`.
        Reads config.yaml and the checkpoint only; no scene image."""
        from cogs.config import load_config

        run = Path(run)
        path = Path(checkpoint) if checkpoint else run / "checkpoints" / "last.pt"
        if not (run / "config.yaml").exists() or not path.exists():
            raise UserError(f"{run} is not a training run (no config.yaml or {path.relative_to(run) if path.is_relative_to(run) else path})")
        cfg = load_config(run / "config.yaml")
        payload = read_checkpoint(path)
        body = payload.get("body_model")
        branches = payload["branches"]
        if _legacy(branches):
            branches, body = upgrade_legacy(run, cfg, branches)
        return cls.from_payload(branches, body, cfg, device)

    def export(self, folder: Path, n_frames: int | None = None) -> list[Path]:
        """Each branch's files (PLYs, body poses, trajectory) into `folder`."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        n = self.n_frames if n_frames is None else n_frames
        return [p for b in self.branches.values() for p in b.export(folder, n)]


def read_checkpoint(path: str | Path) -> dict:
    """A checkpoint file's payload, read without unpickling code (`weights_only`). A
    damaged or foreign file is a `UserError` naming it and the newest readable checkpoint
    beside it, if any."""
    path = Path(path)
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # a truncated zip, garbage, or a pickle of arbitrary objects
        msg = f"{path}: not a readable cogs checkpoint ({type(e).__name__}: {str(e).splitlines()[0][:160]})"
        alt = _newest_readable(path)
        if alt is not None:
            msg += (f". The newest readable checkpoint beside it is {alt.name}: `cogs train --resume --checkpoint "
                    f"{alt.name}` continues from it, `cogs eval --checkpoint {alt.name}` evaluates it")
        raise UserError(msg) from None


def _newest_readable(bad: Path) -> Path | None:
    others = sorted((p for p in bad.parent.glob("*.pt") if p != bad), key=lambda p: p.stat().st_mtime, reverse=True)
    for p in others:
        try:
            torch.load(p, map_location="cpu", weights_only=True)
            return p
        except Exception:
            continue
    return None


# -- runs trained before the model was saved whole ----------------------------------------

_LEGACY_KEYS = {"human": ("trained",), "object": ("size", "rest"), "scene": ("planes64",)}


def _legacy(branches: dict) -> bool:
    return any(branches.get(b) is not None and any(k not in branches[b] for k in keys) for b, keys in _LEGACY_KEYS.items())


def upgrade_legacy(run: Path, cfg, branches: dict) -> tuple[dict, str]:
    """Checkpoints written before the model was saved whole lack a few tensors its
    branches were rebuilt with from the scene (which frames were trained, the object's
    size and rest frames, the planes at full precision): rebuild those from the run's
    scene once, as the old loader did."""
    from cogs.branches.build import build_object, build_scene
    from cogs.data.io import read_json
    from cogs.data.scene import load_scene

    info_path = run / "run.json"
    scene_dir = read_json(info_path).get("scene") if info_path.exists() else None
    if not scene_dir or not Path(scene_dir).exists():
        raise UserError(f"{run} was trained by an older cogs and its checkpoint lacks what a model needs without its "
                        f"scene; the scene it names ({scene_dir!r}) is not there to rebuild it from. Retrain the run.")
    log.info("upgrading %s, trained by an older cogs, from its scene %s", run, scene_dir)
    scene = load_scene(scene_dir)
    out = {k: (dict(v) if v is not None else None) for k, v in branches.items()}
    if out.get("human") is not None:
        trained = torch.zeros(scene.n_frames, dtype=torch.bool, device="cpu")
        trained[list(scene.split["train"])] = True
        out["human"]["trained"] = trained
    if out.get("object") is not None:
        obj = build_object(scene, cfg.branches, cfg.backend)
        out["object"]["size"], out["object"]["rest"] = obj.size, obj.rest
    if out.get("scene") is not None:
        out["scene"]["planes64"] = build_scene(scene, cfg.branches).planes64
    return out, scene.body.model
