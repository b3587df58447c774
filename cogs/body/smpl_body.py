"""SMPL behind the `BodyModel` interface, through smplx (optional extra `cogs[smpl]`).

SMPL's model file is licensed (https://smpl.is.tue.mpg.de): cogs never ships or downloads
it. Point cogs at your copy with the environment variable ``COGS_SMPL_MODEL`` (a
``SMPL_NEUTRAL.pkl``/``.npz`` file, or a folder holding one), ``--smpl-model PATH`` on the
command line, or `set_smpl_model_path()`.

Conventions, matching smplx's `lbs`: y up, metres, 24 joints, pose = per-joint axis-angle
relative to the parent ([B, 24, 3]; joint 0 is `global_orient`), `transl` added after
forward kinematics. Canonical space = the shaped template in the zero pose, so a canonical
point v is posed by sum_j w_j A_j v + transl with A_j = `bone_transforms(...)[0]` — smplx's
own `batch_rigid_transform` output. SMPL's pose-dependent corrective blend shapes
(`posedirs`) are not part of this interface and are not applied (the human branch learns
its own non-rigid detail); everything else equals smplx's forward pass.
"""

from __future__ import annotations

import contextlib
import io
import os
import zipfile
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from cogs.body.base import BodyModel, Canonical
from cogs.body.retarget import SMPL_JOINT_NAMES
from cogs.errors import UserError
from cogs.geometry.rotations import axis_angle_to_rotmat

ENV_VAR = "COGS_SMPL_MODEL"
N_BETAS = 10
_model_path: Path | None = None


def set_smpl_model_path(path: str | Path | None) -> None:
    """Use this SMPL model file (or folder holding SMPL_NEUTRAL.pkl/.npz) from now on;
    overrides ``COGS_SMPL_MODEL``. None clears the setting."""
    global _model_path
    _model_path = None if path is None else Path(path).expanduser()


def smpl_model_path() -> Path | None:
    """The configured model path (not checked), or None when nothing is configured."""
    if _model_path is not None:
        return _model_path
    env = os.environ.get(ENV_VAR, "").strip()
    return Path(env).expanduser() if env else None


_HOW_TO_SET = (
    f"set the environment variable {ENV_VAR}=/path/to/SMPL_NEUTRAL.pkl, pass --smpl-model PATH, "
    "or call cogs.body.smpl_body.set_smpl_model_path(PATH). The SMPL model is licensed: get it "
    "from https://smpl.is.tue.mpg.de. Without it, use the free Anny body model (`--body-model anny`)."
)


def resolve_smpl_model_file(path: str | Path | None = None) -> Path:
    """The SMPL model file to load; `UserError` saying what to set when there is none."""
    path = Path(path).expanduser() if path is not None else smpl_model_path()
    if path is None:
        raise UserError(f"the SMPL body model needs a licensed SMPL model file: {_HOW_TO_SET}")
    if path.is_dir():
        for name in ("SMPL_NEUTRAL.npz", "SMPL_NEUTRAL.pkl", "smpl/SMPL_NEUTRAL.npz", "smpl/SMPL_NEUTRAL.pkl"):
            if (path / name).is_file():
                return path / name
        raise UserError(f"{path}: no SMPL_NEUTRAL.pkl or SMPL_NEUTRAL.npz in this folder; {_HOW_TO_SET}")
    if not path.is_file():
        raise UserError(f"SMPL model file {path} does not exist; {_HOW_TO_SET}")
    return path


def _load_model_data(path: Path) -> dict:
    """The model file's arrays. A .pkl goes through the restricted unpickler
    (`cogs.data.safe_pickle.load_model_pickle`): the official releases' chumpy arrays come
    back as numpy arrays and the sparse regressor as a scipy matrix, and nothing in the file
    is run (a pickle can name any function). A .npz is read without pickle."""
    if path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
            raise UserError(f"{path}: not a readable SMPL .npz model ({e})") from None
    from cogs.data.safe_pickle import load_model_pickle

    data = load_model_pickle(path)
    if not isinstance(data, dict):
        raise UserError(f"{path}: not an SMPL model (the pickle holds a {type(data).__name__}, not a dict of arrays)")
    return dict(data)


class SmplBody(BodyModel):
    """SMPL (24 joints, 10 shape coefficients) via smplx, without pose blend shapes."""

    name = "smpl"

    def __init__(self, model_path: str | Path | None = None) -> None:
        super().__init__()
        try:
            import smplx
            from smplx.utils import Struct
        except ImportError:
            raise UserError(
                "the SMPL body model needs the optional dependency smplx: pip install 'cogs[smpl]'"
            ) from None
        self.model_file = resolve_smpl_model_file(model_path)
        data = _load_model_data(self.model_file)
        missing = [k for k in ("v_template", "shapedirs", "J_regressor", "weights", "kintree_table", "f") if k not in data]
        if missing:
            raise UserError(f"{self.model_file}: not an SMPL model (missing {', '.join(missing)})")
        data.setdefault("posedirs", np.zeros((len(np.asarray(data["v_template"])), 3, 207)))
        try:
            # smplx prints a warning for 10-coefficient models on stdout; cogs' stdout stays clean.
            with contextlib.redirect_stdout(io.StringIO()):
                self._smpl = smplx.SMPL(
                    model_path=str(self.model_file),
                    data_struct=Struct(**data),
                    num_betas=N_BETAS,
                    create_betas=False, create_global_orient=False, create_body_pose=False, create_transl=False,
                )
        except (ValueError, TypeError, IndexError, KeyError, AttributeError, RuntimeError) as e:
            raise UserError(f"{self.model_file}: smplx could not build SMPL from it ({type(e).__name__}: {e})") from None
        self._smpl.requires_grad_(False)
        parents = self._smpl.parents.long()
        if len(parents) != len(SMPL_JOINT_NAMES):
            raise UserError(f"{self.model_file}: has {len(parents)} joints, SMPL has {len(SMPL_JOINT_NAMES)}")
        self.bone_names = list(SMPL_JOINT_NAMES)
        self.bone_parents = [-1] + [int(p) for p in parents[1:]]
        self._parents = parents
        self.shape_names = [f"beta{i}" for i in range(N_BETAS)]
        self.default_shape = torch.zeros(N_BETAS)
        self._faces = self._smpl.faces_tensor.long()
        self._weights = self._smpl.lbs_weights.float()
        self._cache: dict[tuple, Canonical] = {}

    def _betas(self, shape: Tensor | None) -> Tensor:
        betas = torch.zeros(N_BETAS) if shape is None else shape.detach().cpu().float().reshape(-1)
        n = self._smpl.shapedirs.shape[-1]
        if len(betas) < n:
            betas = torch.cat([betas, betas.new_zeros(n - len(betas))])
        return betas[:n]

    def canonical(self, shape: Tensor | None = None) -> Canonical:
        from smplx.lbs import blend_shapes, vertices2joints

        betas = self._betas(shape)
        key = tuple(round(float(b), 6) for b in betas)
        if key not in self._cache:
            with torch.no_grad():
                v = self._smpl.v_template[None] + blend_shapes(betas[None], self._smpl.shapedirs)
                j = vertices2joints(self._smpl.J_regressor, v)
            self._cache[key] = Canonical(vertices=v[0].float(), joints=j[0].float(), faces=self._faces, weights=self._weights)
        return self._cache[key]

    def bone_transforms(
        self, pose: Tensor, transl: Tensor, shape: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        from smplx.lbs import batch_rigid_transform

        B = pose.shape[0]
        assert pose.shape[1:] == (24, 3), pose.shape
        J = self.canonical(shape).joints.to(pose.dtype)
        rot = axis_angle_to_rotmat(pose)
        posed, A = batch_rigid_transform(rot, J.expand(B, -1, -1), self._parents, dtype=pose.dtype)
        shift = torch.zeros_like(A)
        shift[:, :, :3, 3] = transl.to(pose.dtype)[:, None, :]
        return A + shift, posed + transl.to(pose.dtype)[:, None, :]

    def betas_from_rest_joints(self, joints: Tensor) -> Tensor:
        """Shape coefficients [10] whose zero-pose joints best match `joints` [24, 3].

        SMPL's rest joints are linear in the betas (J = R (T + S b)), so least squares
        recovers the betas exactly from joints the same model produced (HumanNeRF's
        canonical_joints.pkl), up to a translation, which is solved for too.
        """
        from smplx.lbs import vertices2joints

        with torch.no_grad():
            Jr = self._smpl.J_regressor.double()
            base = vertices2joints(Jr, self._smpl.v_template[None].double())[0]  # [24, 3]
            dirs = self._smpl.shapedirs.double()[:, :, :N_BETAS]  # [V, 3, 10]
            basis = torch.einsum("jv,vcb->jcb", Jr, dirs).reshape(-1, N_BETAS)  # [72, 10]
            shift = torch.eye(3, dtype=torch.float64).repeat(24, 1)  # [72, 3]: a free translation
            A = torch.cat([basis, shift], 1)
            b = (joints.double().reshape(24, 3) - base).reshape(-1, 1)
            sol = torch.linalg.lstsq(A, b).solution[:, 0]
        return sol[:N_BETAS].float()
