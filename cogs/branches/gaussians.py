"""`GaussianSet`: raw parameters of N 3D Gaussians, their activations, and PLY I/O.

Parameters are stored raw, as 3DGS stores them, in a `torch.nn.ParameterDict`:

    means      [N, 3]      world (or branch-canonical) metres
    quats      [N, 4]      wxyz, any norm (normalised on activation)
    scales     [N, 3]      log of the standard deviations, metres
    opacities  [N]         logit
    sh0        [N, 1, 3]   SH DC coefficient  (rgb = SH_C0 * sh0 + 0.5)
    shN        [N, K-1, 3] higher SH bands, K = (sh_degree + 1)^2 (absent for degree 0)

Density control (cogs.train.density) edits this dict and the matching optimizer states
in place; everything else reads the activated views below. The PLY layout is the one
every 3DGS viewer opens: x, y, z, nx, ny, nz, f_dc_0..2, f_rest_0..44, opacity, scale_0..2,
rot_0..3 (binary little-endian floats, raw logit/log values, f_rest channel-major and
zero-padded to degree 3).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from cogs.geometry.rotations import quat_normalize
from cogs.render.sh import SH_C0, num_sh_bases

PARAM_NAMES = ("means", "quats", "scales", "opacities", "sh0", "shN")


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """[N, 3] colour in [0, 1] -> [N, 1, 3] DC coefficient."""
    return ((rgb - 0.5) / SH_C0)[:, None, :]


def sh0_to_rgb(sh0: Tensor) -> Tensor:
    return sh0[:, 0, :] * SH_C0 + 0.5


def inverse_sigmoid(x: Tensor) -> Tensor:
    x = x.clamp(1e-6, 1 - 1e-6)
    return torch.log(x / (1 - x))


class GaussianSet(torch.nn.Module):
    """N Gaussians' raw, trainable parameters (see module docstring for the layout)."""

    def __init__(self, params: dict[str, Tensor], sh_degree: int = 0):
        super().__init__()
        n = params["means"].shape[0]
        expected = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,), "sh0": (n, 1, 3)}
        for k, shape in expected.items():
            assert tuple(params[k].shape) == shape, (k, tuple(params[k].shape), shape)
        self.sh_degree = sh_degree
        K = num_sh_bases(sh_degree)
        if K > 1:
            assert tuple(params["shN"].shape) == (n, K - 1, 3), params["shN"].shape
        self.params = torch.nn.ParameterDict(
            {k: torch.nn.Parameter(v.detach().clone().float()) for k, v in params.items() if k in PARAM_NAMES and (k != "shN" or K > 1)}
        )

    # -- construction -----------------------------------------------------------------
    @classmethod
    def from_points(
        cls,
        xyz: Tensor,  # [N, 3]
        rgb: Tensor,  # [N, 3] in [0, 1]
        scales: Tensor,  # [N, 3] or [N] standard deviations, metres
        opacity: float | Tensor = 0.1,
        quats: Tensor | None = None,
        sh_degree: int = 0,
    ) -> "GaussianSet":
        n = xyz.shape[0]
        if scales.ndim == 1:
            scales = scales[:, None].expand(n, 3)
        if quats is None:
            quats = xyz.new_zeros(n, 4)
            quats[:, 0] = 1.0
        op = opacity if isinstance(opacity, Tensor) else xyz.new_full((n,), float(opacity))
        params = {
            "means": xyz.float(),
            "quats": quats.float(),
            "scales": torch.log(scales.float().clamp_min(1e-7)),
            "opacities": inverse_sigmoid(op.float()),
            "sh0": rgb_to_sh0(rgb.float()),
        }
        K = num_sh_bases(sh_degree)
        if K > 1:
            params["shN"] = xyz.new_zeros(n, K - 1, 3, dtype=torch.float32)
        return cls(params, sh_degree)

    @classmethod
    def from_state(cls, state: dict[str, Tensor], prefix: str = "params.") -> "GaussianSet":
        """A set rebuilt from a state dict's `params.*` entries (its size and SH degree read
        from their shapes)."""
        params = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
        degree = int(round((params["shN"].shape[1] + 1) ** 0.5)) - 1 if "shN" in params else 0
        return cls(params, degree)

    # -- views ------------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.params["means"].shape[0])

    @property
    def means(self) -> Tensor:
        return self.params["means"]

    @property
    def quats(self) -> Tensor:
        return quat_normalize(self.params["quats"])

    @property
    def scales(self) -> Tensor:
        return torch.exp(self.params["scales"])

    @property
    def opacities(self) -> Tensor:
        return torch.sigmoid(self.params["opacities"])

    @property
    def sh(self) -> Tensor:
        """[N, K, 3] all SH coefficients."""
        if "shN" in self.params:
            return torch.cat([self.params["sh0"], self.params["shN"]], dim=1)
        return self.params["sh0"]

    @property
    def rgb(self) -> Tensor:
        """View-independent colour (DC term only), [N, 3]."""
        return sh0_to_rgb(self.params["sh0"]).clamp_min(0.0)

    def select(self, index: Tensor) -> "GaussianSet":
        """A detached copy of the Gaussians at `index` (bool mask or indices)."""
        return GaussianSet({k: v.detach()[index] for k, v in self.params.items()}, self.sh_degree)

    @staticmethod
    def cat(sets: list["GaussianSet"]) -> "GaussianSet":
        degree = max(s.sh_degree for s in sets)
        K = num_sh_bases(degree)
        out: dict[str, list[Tensor]] = {k: [] for k in PARAM_NAMES}
        for s in sets:
            for k in ("means", "quats", "scales", "opacities", "sh0"):
                out[k].append(s.params[k].detach())
            if K > 1:
                sh0 = s.params["sh0"]
                rest = s.params["shN"].detach() if "shN" in s.params else sh0.new_zeros(len(s), 0, 3)
                pad = sh0.new_zeros(len(s), K - 1 - rest.shape[1], 3)
                out["shN"].append(torch.cat([rest, pad], dim=1))
        return GaussianSet({k: torch.cat(v) for k, v in out.items() if v}, degree)

    # -- PLY ----------------------------------------------------------------------------
    def save_ply(self, path: str | Path) -> None:
        """Write the standard 3DGS PLY (binary little-endian, raw values), always in the
        full degree-3 layout (62 floats, 248 bytes a vertex): viewers and engine plugins
        that expect `f_rest_0..44` reject anything shorter, so bands above the set's degree
        are written as zeros. The true degree is kept in a header comment
        (`comment sh_degree D`), so `load_ply` gives the same set back."""
        write_ply(path, {k: v.detach() for k, v in self.params.items()}, self.sh_degree)

    @classmethod
    def load_ply(cls, path: str | Path) -> "GaussianSet":
        from plyfile import PlyData

        ply = PlyData.read(str(path))
        v = ply["vertex"]
        names = v.data.dtype.names
        col = lambda *ks: np.stack([np.asarray(v[k], dtype=np.float32) for k in ks], axis=1)  # noqa: E731
        n_rest = len([k for k in names if k.startswith("f_rest_")])
        assert n_rest % 3 == 0, n_rest
        stored = int(round(np.sqrt(n_rest // 3 + 1))) - 1
        declared = [int(c.split()[1]) for c in ply.comments if c.startswith("sh_degree ")]
        degree = declared[0] if declared else stored
        assert degree <= stored, (degree, stored)
        params = {
            "means": torch.from_numpy(col("x", "y", "z")),
            "quats": torch.from_numpy(col("rot_0", "rot_1", "rot_2", "rot_3")),
            "scales": torch.from_numpy(col("scale_0", "scale_1", "scale_2")),
            "opacities": torch.from_numpy(np.asarray(v["opacity"], dtype=np.float32)),
            "sh0": torch.from_numpy(col("f_dc_0", "f_dc_1", "f_dc_2"))[:, None, :],
        }
        if degree > 0:
            per = n_rest // 3  # coefficients per channel in the file (channel-major)
            rest = col(*[f"f_rest_{i}" for i in range(n_rest)]).reshape(-1, 3, per)[:, :, : num_sh_bases(degree) - 1]
            params["shN"] = torch.from_numpy(rest.transpose(0, 2, 1).copy())
        return cls(params, degree)


PLY_PROPERTIES = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)
"""The reference 3DGS vertex layout, in order (all float32)."""


def write_ply(path: str | Path, params: dict[str, Tensor], sh_degree: int) -> None:
    """Write raw 3DGS parameters (the `GaussianSet` layout: means, wxyz quats, log scales,
    logit opacities, sh0 [N, 1, 3], optional shN [N, K-1, 3]) as a standard 3DGS PLY in
    the full layout of `PLY_PROPERTIES`; f_rest is channel-major (all of red's
    coefficients, then green's, then blue's) and zero above `sh_degree`."""
    from plyfile import PlyData, PlyElement

    p = {k: v.detach().cpu().float().numpy() for k, v in params.items()}
    n = p["means"].shape[0]
    rest = np.zeros((n, 15, 3), np.float32)
    if sh_degree > 0:
        rest[:, : p["shN"].shape[1]] = p["shN"]
    cols = np.concatenate(
        [p["means"], np.zeros((n, 3), np.float32), p["sh0"].reshape(n, 3), rest.transpose(0, 2, 1).reshape(n, 45),
         p["opacities"].reshape(n, 1), p["scales"], p["quats"]],
        axis=1,
    ).astype(np.float32)
    assert cols.shape[1] == len(PLY_PROPERTIES) and np.isfinite(cols).all(), "non-finite Gaussian parameters"
    data = np.empty(n, dtype=[(name, "<f4") for name in PLY_PROPERTIES])
    for i, name in enumerate(PLY_PROPERTIES):
        data[name] = cols[:, i]
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(data, "vertex")], text=False, byte_order="<",
            comments=[f"sh_degree {int(sh_degree)}"]).write(str(path))


def set_param_groups(g: GaussianSet, lr, prefix: str, means_scale: float) -> list[dict]:
    """Optimizer groups of a plain set, named as its parameters, with the learning rates
    `lr.<prefix>_<name>` (the means' times `means_scale`; higher SH bands `lr.scene_shN`)."""
    p = g.params
    groups = [
        {"params": [p["means"]], "lr": getattr(lr, f"{prefix}_means") * means_scale, "name": "means"},
        {"params": [p["sh0"]], "lr": getattr(lr, f"{prefix}_sh0"), "name": "sh0"},
        {"params": [p["opacities"]], "lr": getattr(lr, f"{prefix}_opacities"), "name": "opacities"},
        {"params": [p["scales"]], "lr": getattr(lr, f"{prefix}_scales"), "name": "scales"},
        {"params": [p["quats"]], "lr": getattr(lr, f"{prefix}_quats"), "name": "quats"},
    ]
    if "shN" in p:
        groups.append({"params": [p["shN"]], "lr": lr.scene_shN, "name": "shN"})
    return groups


@torch.no_grad()
def guard_set(g: GaussianSet, extent: float) -> None:
    """After an optimizer step: log-scales clamped to [1e-5 m, half the extent], zero
    quaternions (no rotation) repaired to the identity, without a device sync."""
    p = g.params
    p["scales"].clamp_(max=float(np.log(0.5 * extent + 1e-6)), min=float(np.log(1e-5)))
    q = p["quats"]
    bad = q.norm(dim=1, keepdim=True) < 1e-8
    q.copy_(torch.where(bad, q.new_tensor([1.0, 0.0, 0.0, 0.0]), q))
