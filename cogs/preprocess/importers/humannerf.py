"""HumanNeRF (Weng et al., CVPR 2022) / HOSNeRF (Liu et al., ICCV 2023) sequences -> native scene.

Layout read (one subject folder, as HumanNeRF's `prepare_dataset.py` writes it):

    images/<frame>.png          frames; their sorted names are the frame order
    masks/<frame>.png           person masks (non-zero = person; 3-channel is fine)
    object_masks/<frame>.png    (or masks_object/) HOSNeRF-style object masks, optional:
                                with them the scene gets an object (initial pose guessed)
    cameras.pkl                 {frame: {"intrinsics": 3x3, "extrinsics": 4x4 world->camera,
                                "distortions": (5,) optional}}; HOSNeRF's
                                cameras_scaleworld.pkl is read when cameras.pkl is absent
    mesh_infos.pkl              {frame: {"Rh": (3,), "Th": (3,), "poses": (72,), "joints":
                                (24, 3), "tpose_joints": (24, 3)}}: world = R(Rh) x_body + Th
    canonical_joints.pkl        {"joints": (24, 3)} zero-pose joints of the mean shape

All pickles go through `cogs.data.safe_pickle`. HumanNeRF's rays pass through integer
pixel coordinates; cogs puts pixel centres at +0.5, so the principal point is shifted by
half a pixel (the geometry of every pixel is unchanged). The layout has no SfM points: a
ground plane under the feet is guessed (`common.ground_plane_points`). The split is the
hosnerf-16 protocol (`common.hosnerf16_split`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from cogs.data.io import mask_from_values
from cogs.data.outdir import check_out_folder
from cogs.data.safe_pickle import load_pickle
from cogs.data.scene import CameraTrack
from cogs.errors import UserError
from cogs.geometry.rotations import axis_angle_to_rotmat
from cogs.preprocess.importers.common import (
    FrameSelection,
    ImportedFrames,
    SmplFits,
    Undistorter,
    as_array,
    hosnerf16_split,
    read_gray,
    select_frames,
    read_rgb,
    require,
    write_scene,
)

log = logging.getLogger(__name__)

OBJECT_MASK_DIRS = ("object_masks", "masks_object")
_IMAGE_EXTS = (".png", ".jpg", ".jpeg")


def _entry(table: dict, frame: str, path: Path) -> dict:
    if frame not in table:
        raise UserError(f"{path}: no entry for frame {frame}")
    e = table[frame]
    if not isinstance(e, dict):
        raise UserError(f"{path}: the entry of frame {frame} is a {type(e).__name__}, expected a dict")
    return e


def _mask_path(folder: Path, frame: str) -> Path:
    for ext in _IMAGE_EXTS:
        if (folder / f"{frame}{ext}").is_file():
            return folder / f"{frame}{ext}"
    return folder / f"{frame}.png"  # missing: read_gray names it


def import_humannerf(
    src: str | Path,
    out: str | Path,
    body_model: str = "anny",
    smpl_model: Path | None = None,
    overwrite: bool = False,
    select: FrameSelection = FrameSelection(),
) -> Path:
    """Import one HumanNeRF/HOSNeRF subject folder `src` as a native scene in `out` (an
    existing `out` is replaced only with `overwrite`, once the new scene is complete);
    `select` keeps some of its frames, at a reduced size."""
    check_out_folder(Path(out), overwrite=overwrite)
    root = Path(src)
    if not root.is_dir():
        raise UserError(f"{root}: not a folder (expected a HumanNeRF-layout subject)")
    img_dir = require(root / "images", "the video frames")
    mask_dir = require(root / "masks", "person masks")
    cam_path = root / "cameras.pkl"
    if not cam_path.is_file() and (root / "cameras_scaleworld.pkl").is_file():
        cam_path = root / "cameras_scaleworld.pkl"
    cameras_raw = load_pickle(require(cam_path, "per-frame intrinsics/extrinsics"))
    mesh_path = require(root / "mesh_infos.pkl", "per-frame SMPL Rh, Th, poses, joints")
    mesh = load_pickle(mesh_path)
    canon_path = root / "canonical_joints.pkl"
    rest_joints = None
    if canon_path.is_file():
        cj = load_pickle(canon_path)
        if not isinstance(cj, dict) or "joints" not in cj:
            raise UserError(f"{canon_path}: expected {{'joints': (24, 3)}}")
        rest_joints = as_array(cj["joints"], (24, 3), "joints", str(canon_path))
    else:
        log.warning("%s: missing; SMPL shape will come from mesh_infos only", canon_path)
    for p, obj in ((cam_path, cameras_raw), (mesh_path, mesh)):
        if not isinstance(obj, dict):
            raise UserError(f"{p}: expected a dict keyed by frame name, got {type(obj).__name__}")

    frames = sorted(p.stem for p in img_dir.iterdir() if p.suffix.lower() in _IMAGE_EXTS)
    if not frames:
        raise UserError(f"{img_dir}: no images")
    kept = None if select.identity else select.indices(len(frames), str(img_dir))
    if kept is not None:  # read only the frames kept; resized below
        frames = [frames[i] for i in kept]
    obj_dir = next((root / d for d in OBJECT_MASK_DIRS if (root / d).is_dir()), None)

    Ks, w2cs, images, humans, objects = [], [], [], [], []
    go, bp, Rh, Th, joints, pelvis, betas = [], [], [], [], [], [], []
    for f in frames:
        cam = _entry(cameras_raw, f, cam_path)
        where = f"{cam_path} (frame {f})"
        K = as_array(cam.get("intrinsics"), (-1, -1), "intrinsics", where)[:3, :3].copy()
        E = as_array(cam.get("extrinsics"), (4, 4), "extrinsics", where)
        R = E[:3, :3]
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
            raise UserError(f"{where}: `extrinsics` rotation is not a rotation (a scaled world is not supported)")
        dist = cam.get("distortions")
        rgb = read_rgb(next((img_dir / f"{f}{e}" for e in _IMAGE_EXTS if (img_dir / f"{f}{e}").is_file())))
        human = mask_from_values(read_gray(_mask_path(mask_dir, f)))
        obj = mask_from_values(read_gray(_mask_path(obj_dir, f))) if obj_dir is not None else None
        for m, what in ((human, mask_dir), (obj, obj_dir)):
            if m is not None and m.shape != rgb.shape[:2]:
                raise UserError(f"{what}/{f}: mask is {m.shape[1]}x{m.shape[0]}, image is {rgb.shape[1]}x{rgb.shape[0]}")
        if dist is not None:
            dist = as_array(dist, (-1,), "distortions", where).reshape(-1)
            if np.any(dist):
                # HumanNeRF undistorts with cv2 and this K: integer pixel centres, so the
                # remap is done before the half-pixel shift below.
                Kc = K.copy()
                Kc[:2, 2] += 0.5
                u = Undistorter(Kc, dist, rgb.shape[1], rgb.shape[0])
                rgb, human = u.image(rgb), u.mask(human)
                obj = u.mask(obj) if obj is not None else None
        K[0, 2] += 0.5  # integer pixel centres (HumanNeRF) -> +0.5 centres (cogs)
        K[1, 2] += 0.5
        Ks.append(K)
        w2cs.append(E)
        images.append(rgb)
        humans.append(human)
        objects.append(obj)

        info = _entry(mesh, f, mesh_path)
        where = f"{mesh_path} (frame {f})"
        poses = as_array(info.get("poses"), (-1,), "poses", where)
        if len(poses) < 72:
            raise UserError(f"{where}: `poses` has {len(poses)} values, expected 72")
        go.append(poses[:3])
        bp.append(poses[3:72])
        Rh.append(as_array(info.get("Rh"), (-1,) * np.ndim(info.get("Rh")), "Rh", where).reshape(3)
                  if np.size(info.get("Rh")) == 3 else _rh_from_matrix(info.get("Rh"), where))
        Th.append(as_array(info.get("Th"), (-1,), "Th", where).reshape(3))
        if info.get("joints") is not None:
            joints.append(as_array(info["joints"], (-1, 3), "joints", where)[:24])
        if info.get("tpose_joints") is not None:
            pelvis.append(as_array(info["tpose_joints"], (-1, 3), "tpose_joints", where)[0])
        if info.get("betas") is not None:
            betas.append(as_array(info["betas"], (-1,), "betas", where).reshape(-1)[:10])
    sizes = {im.shape for im in images}
    if len(sizes) != 1:
        raise UserError(f"{img_dir}: frames differ in size ({sorted(sizes)}); one size is needed")
    T = len(frames)
    if joints and len(joints) != T:
        raise UserError(f"{mesh_path}: `joints` present for {len(joints)} of {T} frames")
    J = np.stack(joints) if joints else None
    # Body coordinates are SMPL's output shifted so the rest pelvis sits at the body's own
    # pelvis joint (0 for HumanNeRF's in-the-wild preparation, J0 for ZJU-MoCap's).
    if J is not None:
        pelvis_in_body = J[:, 0].copy()
    elif len(pelvis) == T:
        pelvis_in_body = np.stack(pelvis)
    else:
        pelvis_in_body = None
    R = axis_angle_to_rotmat(torch.from_numpy(np.stack(Rh))).numpy()
    fits = SmplFits(
        global_orient=np.stack(go), body_pose=np.stack(bp),
        betas=np.stack(betas).mean(0) if len(betas) == T else None,
        scale=np.ones(T), rotation=R, translation=np.stack(Th),
        joints=J, pelvis_in_body=pelvis_in_body, rest_joints=rest_joints, source=str(mesh_path),
    )
    train, test = hosnerf16_split(T)
    object_masks = np.stack(objects) if obj_dir is not None else None
    data = ImportedFrames(
        name=root.name,
        frame_ids=frames,
        images=np.stack(images),
        human_masks=np.stack(humans),
        object_masks=object_masks,
        cameras=CameraTrack(K=np.stack(Ks), world_to_camera=np.stack(w2cs)),
        fits=fits,
        body_R=R,
        body_c=np.stack(Th),
        split={"train": train, "test": test},
        points_xyz=None,
        points_rgb=None,
        source={
            "dataset": "humannerf",
            "path": str(root.resolve()),
            "cameras": cam_path.name,
            "object_masks": obj_dir.name if obj_dir is not None else None,
            "protocol": "hosnerf-16",
            "split_rule": "every (n // 16)-th frame from 0, first 16, is test (every other frame under 32 frames)",
            "principal_point_shift_px": 0.5,
        },
    )
    if kept is not None:
        data = select_frames(data, FrameSelection(max_side=select.max_side), _hosnerf_split, str(img_dir))
        # The frames were picked as they were read: record the selection as the user gave it.
        data.source["selection"].update(start=select.start, stride=select.stride, limit=select.limit,
                                        frames_of_the_sequence=kept)
    return write_scene(data, Path(out), body_model, smpl_model, overwrite=overwrite)


def _hosnerf_split(n: int) -> dict[str, list[int]]:
    train, test = hosnerf16_split(n)
    return {"train": train, "test": test}


def _rh_from_matrix(value, where: str) -> np.ndarray:
    """Rh stored as a 3x3 matrix (some preparations do) -> axis-angle."""
    from cogs.geometry.rotations import rotmat_to_axis_angle

    M = as_array(value, (3, 3), "Rh", where)
    return rotmat_to_axis_angle(torch.from_numpy(M)).numpy()
