"""LPIPS (Zhang et al., CVPR 2018), AlexNet variant v0.1, in plain torch, weights found locally.

The ``lpips`` PyPI package imports torchvision (which does not import beside the CPU torch
used here), so the network is rebuilt from its description:

1. images in [0, 1] are mapped to [-1, 1], then shifted by [-.030, -.088, -.188] and divided
   by [.458, .448, .450] per channel (LPIPS's scaling layer);
2. torchvision's AlexNet ``features`` (conv 64 k11 s4 p2, relu, maxpool 3/2, conv 192 k5 p2,
   relu, maxpool 3/2, conv 384 k3 p1, relu, conv 256 k3 p1, relu, conv 256 k3 p1, relu) is
   tapped after each of the five ReLUs;
3. each tap is unit-normalised over channels (``x / (||x|| + 1e-10)``), the two images'
   taps are subtracted and squared, weighted per channel by a 1x1 convolution without bias
   (the "lin" layers), averaged over space, and the five layers are summed.

Weights are only ever read from local files, never downloaded:

- backbone (ImageNet AlexNet, torchvision layout ``features.{0,3,6,8,10}.{weight,bias}``;
  a bare ``features`` dict ``{0,3,...}.weight`` or the lpips model layout
  ``net.slice{k}.{i}.weight`` is accepted too): the explicit ``backbone_path`` argument,
  else ``$COGS_ALEXNET_WEIGHTS``, else the torch hub cache
  ``torch.hub.get_dir()/checkpoints/alexnet-owt-7be5be79.pth`` (``$TORCH_HOME/hub`` or
  ``~/.cache/torch/hub``);
- linear layers (lpips layout ``lin{0..4}.model.1.weight``, shapes [1, C, 1, 1]): the explicit
  ``linear_path`` argument, else ``$COGS_LPIPS_WEIGHTS``, else ``weights/v0.1/alex.pth`` inside
  an installed ``lpips`` package, located with ``importlib.util.find_spec`` (not imported).

An explicitly named file (argument or environment variable) that does not exist is reported
as such; the search does not silently fall through to another location. When anything is
missing or unreadable, ``lpips_alex`` returns ``None`` and ``lpips_status`` says why.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn
from torch import Tensor

ENV_BACKBONE = "COGS_ALEXNET_WEIGHTS"
ENV_LINEAR = "COGS_LPIPS_WEIGHTS"
ALEXNET_CHECKPOINT = "alexnet-owt-7be5be79.pth"
CHANNELS = (64, 192, 384, 256, 256)
_CONV_INDICES = (0, 3, 6, 8, 10)  # conv layers inside torchvision's alexnet.features
_TAP_INDICES = (1, 4, 7, 9, 11)  # the ReLUs after them
# AlexNet's first two max-pools need at least 3x3 inputs: side >= 31 pixels.
LPIPS_MIN_SIDE = 31

# Indirection so tests can fake an installed lpips package without patching importlib.
_find_spec = importlib.util.find_spec

_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)


class AlexFeatures(nn.Module):
    """torchvision ``alexnet().features`` up to the last ReLU, same module indices."""

    def __init__(self) -> None:
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2),
            nn.ReLU(),
            nn.MaxPool2d(kernel_size=3, stride=2),
            nn.Conv2d(64, 192, kernel_size=5, padding=2),
            nn.ReLU(),
            nn.MaxPool2d(kernel_size=3, stride=2),
            nn.Conv2d(192, 384, kernel_size=3, padding=1),
            nn.ReLU(),
            nn.Conv2d(384, 256, kernel_size=3, padding=1),
            nn.ReLU(),
            nn.Conv2d(256, 256, kernel_size=3, padding=1),
            nn.ReLU(),
        )

    def forward(self, x: Tensor) -> list[Tensor]:
        taps = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in _TAP_INDICES:
                taps.append(x)
        return taps


class LPIPSAlex(nn.Module):
    """LPIPS-AlexNet v0.1 as a differentiable module (parameters frozen).

    forward(pred, gt): [H, W, 3] -> 0-dim tensor, or [B, 3, H, W] -> [B]; inputs in [0, 1];
    sides at least ``LPIPS_MIN_SIDE`` pixels. Lower is more similar; 0 for identical images.
    """

    def __init__(self) -> None:
        super().__init__()
        self.backbone = AlexFeatures()
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in CHANNELS)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def forward(self, pred: Tensor, gt: Tensor) -> Tensor:
        if pred.shape != gt.shape:
            raise ValueError(f"pred and gt differ in shape: {tuple(pred.shape)} vs {tuple(gt.shape)}")
        single = pred.ndim == 3
        if single:
            pred, gt = pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None]
        if pred.ndim != 4 or pred.shape[1] != 3:
            raise ValueError(f"expected [H, W, 3] or [B, 3, H, W], got shape {tuple(pred.shape)}")
        h, w = pred.shape[-2:]
        if min(h, w) < LPIPS_MIN_SIDE:
            raise ValueError(f"lpips needs images at least {LPIPS_MIN_SIDE}x{LPIPS_MIN_SIDE}, got {h}x{w}")
        dtype = self.shift.dtype
        feats = []
        for img in (pred, gt):
            x = (2.0 * img.to(dtype) - 1.0 - self.shift) / self.scale
            feats.append(self.backbone(x))
        total = pred.new_zeros(pred.shape[0], dtype=dtype)
        for lin, f0, f1 in zip(self.lins, *feats):
            n0 = f0 / (f0.pow(2).sum(dim=1, keepdim=True).sqrt() + 1e-10)
            n1 = f1 / (f1.pow(2).sum(dim=1, keepdim=True).sqrt() + 1e-10)
            total = total + lin((n0 - n1) ** 2).mean(dim=(1, 2, 3))
        return total[0] if single else total


# --------------------------------------------------------------------------------------
# Locating the weight files


def _find_backbone(explicit: str | os.PathLike | None) -> tuple[Path | None, str]:
    if explicit is not None:
        p = Path(explicit)
        return (p, "") if p.is_file() else (None, f"AlexNet backbone weights not found at {p} (explicit path)")
    env = os.environ.get(ENV_BACKBONE)
    if env:
        p = Path(env)
        return (p, "") if p.is_file() else (None, f"AlexNet backbone weights not found at {p} (${ENV_BACKBONE})")
    try:
        hub_dir = Path(torch.hub.get_dir())
    except Exception as exc:  # a broken environment must not break evaluation
        return None, f"AlexNet backbone weights: torch hub directory unknown ({exc})"
    p = hub_dir / "checkpoints" / ALEXNET_CHECKPOINT
    if p.is_file():
        return p, ""
    return None, (
        f"AlexNet backbone weights not found: looked for {p} (torch hub cache; set "
        f"${ENV_BACKBONE} to a torchvision alexnet state dict to use another file)"
    )


def _find_linear(explicit: str | os.PathLike | None) -> tuple[Path | None, str]:
    if explicit is not None:
        p = Path(explicit)
        return (p, "") if p.is_file() else (None, f"LPIPS linear weights not found at {p} (explicit path)")
    env = os.environ.get(ENV_LINEAR)
    if env:
        p = Path(env)
        return (p, "") if p.is_file() else (None, f"LPIPS linear weights not found at {p} (${ENV_LINEAR})")
    try:
        # find_spec on a top-level name locates the package without executing it (importing
        # lpips would import torchvision, which fails here).
        spec = _find_spec("lpips")
    except (ImportError, ValueError) as exc:
        spec = None
        why = f"locating the lpips package failed ({exc})"
    else:
        why = "the lpips package is not installed"
    if spec is not None and spec.submodule_search_locations:
        for root in spec.submodule_search_locations:
            p = Path(root) / "weights" / "v0.1" / "alex.pth"
            if p.is_file():
                return p, ""
        where = list(spec.submodule_search_locations)
        why = f"the installed lpips package at {where} has no weights/v0.1/alex.pth"
    return None, f"LPIPS linear weights not found: {why} and ${ENV_LINEAR} is not set"


# --------------------------------------------------------------------------------------
# Loading


def _read_state_dict(path: Path) -> dict[str, Tensor]:
    sd = torch.load(path, map_location="cpu", weights_only=True)
    if isinstance(sd, dict) and "state_dict" in sd and isinstance(sd["state_dict"], dict):
        sd = sd["state_dict"]
    if not isinstance(sd, dict):
        raise ValueError(f"{path} does not hold a state dict")
    return sd


def _backbone_state(sd: dict[str, Tensor], path: Path) -> dict[str, Tensor]:
    """Map any accepted layout to ``features.{i}.{weight,bias}``."""
    out = {}
    for key, value in sd.items():
        m = re.fullmatch(r"(?:.*\.)?(?:features|slice\d)\.(\d+)\.(weight|bias)", key) or re.fullmatch(
            r"(\d+)\.(weight|bias)", key
        )
        if m and int(m.group(1)) in _CONV_INDICES:
            out[f"features.{m.group(1)}.{m.group(2)}"] = value
    wanted = [f"features.{i}.{k}" for i in _CONV_INDICES for k in ("weight", "bias")]
    missing = [k for k in wanted if k not in out]
    if missing:
        raise ValueError(f"{path} lacks AlexNet keys {missing[:3]}{'...' if len(missing) > 3 else ''}")
    return out


def _linear_state(sd: dict[str, Tensor], path: Path) -> dict[str, Tensor]:
    out = {}
    for i in range(len(CHANNELS)):
        cands = [k for k in sd if re.fullmatch(rf"(?:.*\.)?lin{i}\.model\.1\.weight", k)]
        if not cands:
            raise ValueError(f"{path} lacks key lin{i}.model.1.weight")
        out[f"{i}.weight"] = sd[cands[0]]
    return out


@functools.lru_cache(maxsize=4)
def _load_cached(
    backbone: str, b_stamp: tuple, linear: str, l_stamp: tuple
) -> tuple[LPIPSAlex | None, str]:
    # The stamps (mtime, size) are part of the key so a replaced file is reloaded.
    del b_stamp, l_stamp
    model = LPIPSAlex()
    try:
        model.backbone.load_state_dict(_backbone_state(_read_state_dict(Path(backbone)), Path(backbone)))
        model.lins.load_state_dict(_linear_state(_read_state_dict(Path(linear)), Path(linear)))
    except Exception as exc:  # corrupt or foreign files: report, never crash
        return None, f"LPIPS weights could not be loaded ({type(exc).__name__}: {exc})"
    model.requires_grad_(False)
    return model, f"LPIPS-AlexNet available (backbone {backbone}, linear layers {linear})"


def _stamp(p: Path) -> tuple:
    st = p.stat()
    return (st.st_mtime_ns, st.st_size)


def _load(backbone_path, linear_path) -> tuple[LPIPSAlex | None, str]:
    b, b_why = _find_backbone(backbone_path)
    l, l_why = _find_linear(linear_path)
    reasons = [r for r in (b_why, l_why) if r]
    if reasons:
        return None, "; ".join(reasons)
    try:
        return _load_cached(str(b), _stamp(b), str(l), _stamp(l))
    except OSError as exc:
        return None, f"LPIPS weights could not be read ({exc})"


def load_lpips_alex(
    backbone_path: str | os.PathLike | None = None, linear_path: str | os.PathLike | None = None
) -> LPIPSAlex | None:
    """The LPIPS module (CPU, float32, frozen, cached per file), or None when unavailable.

    The returned module is shared between callers: move a copy (``copy.deepcopy``) if you
    need it on another device.
    """
    return _load(backbone_path, linear_path)[0]


def lpips_status(
    backbone_path: str | os.PathLike | None = None, linear_path: str | os.PathLike | None = None
) -> str:
    """A sentence saying whether LPIPS is available, and if not, which file was looked for where."""
    return _load(backbone_path, linear_path)[1]


def lpips_alex(
    pred: Any,
    gt: Any,
    backbone_path: str | os.PathLike | None = None,
    linear_path: str | os.PathLike | None = None,
) -> float | None:
    """LPIPS-AlexNet distance of two [H, W, 3] images in [0, 1]; None when weights are missing.

    Raises ValueError for images smaller than ``LPIPS_MIN_SIDE`` on a side (a caller error,
    which ``image_metrics`` turns into null with a note).
    """
    model = load_lpips_alex(backbone_path, linear_path)
    if model is None:
        return None
    p = pred if isinstance(pred, Tensor) else torch.as_tensor(np.asarray(pred))
    g = gt if isinstance(gt, Tensor) else torch.as_tensor(np.asarray(gt))
    with torch.no_grad():
        value = model(p.detach().cpu().float(), g.detach().cpu().float())
    return float(value)
