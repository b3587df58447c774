"""NeuMan (Jiang et al., ECCV 2022) sequences -> native scene.

Layout read (one sequence folder):

    images/<name>.png                 frames (only those COLMAP registered are imported)
    segmentations/<name>.png|.npy     person masks, Detectron2 style: 0 = person, 255 = rest
    sparse/cameras.txt                COLMAP text model (PINHOLE in the release; distorted
    sparse/images.txt                 models are undistorted, fisheye ones refused)
    sparse/points3D.txt
    smpl_output_optimized.pkl         joblib pickle {person_id: {"pose": [N][72], "betas":
                                      [N][10], ...}} indexed by the frame number in <name>
    alignments.npy                    {<name>: 4x3}: world = [x_smpl, 1] @ A (scale included)
    4d_humans/smpl_optimized_aligned_scale.npz   (HUGS' variant) global_orient [T, 3],
                                      body_pose [T, 69], betas, transl [T, 3], scale [T]:
                                      world = scale * SMPL(...) + transl, in video order
    train_split.txt / val_split.txt / test_split.txt   (optional) image names per part

The world is COLMAP's divided by the median SMPL scale, so the person is metric; per-frame
scale differences are folded into depth along each frame's view ray (see
`common.fold_scale`), which keeps every frame's image of the body unchanged.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from cogs.data.outdir import check_out_folder
from cogs.data.safe_pickle import load_npy, load_pickle
from cogs.data.scene import CameraTrack
from cogs.errors import UserError
from cogs.preprocess.importers.common import (
    FrameSelection,
    ImportedFrames,
    SmplFits,
    Undistorter,
    as_array,
    camera_centres,
    colmap_intrinsics,
    select_frames,
    fold_scale,
    neuman_split,
    read_colmap_cameras,
    read_colmap_images,
    read_colmap_points,
    read_gray,
    read_rgb,
    require,
    similarity_parts,
    write_scene,
)

log = logging.getLogger(__name__)

OPTIMIZED = "smpl_output_optimized.pkl"
ALIGNMENTS = "alignments.npy"
FOUR_D = "4d_humans/smpl_optimized_aligned_scale.npz"
_JOINT_KEYS = ("joints", "smpl_joints", "joints3d", "joints_3d")


def _joints_from(d: dict, n: int, where: str) -> np.ndarray | None:
    """The first 24 SMPL joints per frame when the fits carry them (any of _JOINT_KEYS)."""
    for key in _JOINT_KEYS:
        if key in d and d[key] is not None:
            arr = np.asarray(np.stack([np.asarray(j, dtype=np.float64) for j in d[key]]) if isinstance(d[key], list)
                             else d[key], dtype=np.float64)
            if arr.ndim != 3 or arr.shape[1] < 24 or arr.shape[2] != 3 or len(arr) < n:
                raise UserError(f"{where}: `{key}` has shape {list(arr.shape)}, expected [frames, >=24, 3]")
            return arr[:, :24]
    return None


def _read_optimized(root: Path, names: list[str]) -> SmplFits:
    path, apath = root / OPTIMIZED, root / ALIGNMENTS
    require(apath, f"NeuMan's SMPL-to-COLMAP alignments, needed with {OPTIMIZED}")
    raw = load_pickle(path)
    if not isinstance(raw, dict) or len(raw) != 1:
        raise UserError(f"{path}: expected a dict with one tracked person, got {type(raw).__name__} of {len(raw) if hasattr(raw, '__len__') else '?'}")
    person = next(iter(raw.values()))
    if not isinstance(person, dict) or "pose" not in person or "betas" not in person:
        raise UserError(f"{path}: the person's entry needs `pose` and `betas`")
    align = load_npy(apath)
    if not isinstance(align, dict):
        raise UserError(f"{apath}: expected a dict {{image name: 4x3 array}}")
    idx = []
    for name in names:
        try:
            idx.append(int(Path(name).stem))
        except ValueError:
            raise UserError(f"{path}: fits are indexed by frame number but image {name!r} has no numeric name") from None
    n_fits = len(person["pose"])
    if max(idx) >= n_fits:
        raise UserError(f"{path}: {n_fits} fits but image {names[int(np.argmax(idx))]} needs index {max(idx)}")
    poses = np.stack([as_array(person["pose"][i], (-1,), "pose", f"{path} (frame {i})").reshape(-1)[:72] for i in idx])
    betas = np.stack([as_array(person["betas"][i], (-1,), "betas", f"{path} (frame {i})").reshape(-1)[:10] for i in idx])
    scale, rot, trans = [], [], []
    for name in names:
        if name not in align:
            raise UserError(f"{apath}: no alignment for image {name}")
        A = as_array(align[name], (4, 3), "alignment", f"{apath} ({name})")
        s, R = similarity_parts(A[:3].T, f"{apath} ({name})")
        scale.append(s)
        rot.append(R)
        trans.append(A[3])
    joints = _joints_from(person, n_fits, str(path))
    return SmplFits(
        global_orient=poses[:, :3], body_pose=poses[:, 3:72], betas=betas.mean(0),
        scale=np.array(scale), rotation=np.stack(rot), translation=np.stack(trans),
        joints=None if joints is None else joints[idx], source=f"{path} + {apath.name}",
    )


def _read_4d_humans(root: Path, n: int) -> SmplFits:
    path = root / FOUR_D
    try:
        with np.load(require(path, "HUGS' SMPL fits"), allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except (OSError, ValueError) as e:
        raise UserError(f"{path}: unreadable npz ({e})") from None
    if "thetas" in d:
        d.setdefault("global_orient", d["thetas"][:, :3])
        d.setdefault("body_pose", d["thetas"][:, 3:])
    missing = [k for k in ("global_orient", "body_pose", "betas", "transl", "scale") if k not in d]
    if missing:
        raise UserError(f"{path}: missing arrays {', '.join(missing)}")
    if len(d["transl"]) != n:
        raise UserError(f"{path}: {len(d['transl'])} frames of fits but COLMAP registered {n} images")
    bp = as_array(d["body_pose"], (n, -1), "body_pose", str(path))
    bp = bp[:, 3:72] if bp.shape[1] == 72 else bp[:, :69]
    betas = as_array(d["betas"], (-1,) * np.ndim(d["betas"]), "betas", str(path)).reshape(-1, np.shape(d["betas"])[-1])[:, :10]
    scale = as_array(d["scale"], (-1,) * np.ndim(d["scale"]), "scale", str(path)).reshape(n, -1)[:, 0]
    if (scale <= 0).any():
        raise UserError(f"{path}: non-positive `scale`")
    return SmplFits(
        global_orient=as_array(d["global_orient"], (n, 3), "global_orient", str(path)),
        body_pose=bp, betas=betas.mean(0), scale=scale,
        rotation=np.tile(np.eye(3), (n, 1, 1)), translation=as_array(d["transl"], (n, 3), "transl", str(path)),
        joints=_joints_from(d, n, str(path)), source=str(path),
    )


def _split_from_files(root: Path, names: list[str]) -> dict[str, list[int]] | None:
    files = {p: root / f"{p}_split.txt" for p in ("train", "val", "test")}
    if not all(f.is_file() for f in files.values()):
        return None
    pos = {n: i for i, n in enumerate(names)}
    out = {}
    for part, f in files.items():
        listed = [ln.strip() for ln in f.read_text().splitlines() if ln.strip()]
        unknown = [n for n in listed if n not in pos]
        if unknown:
            raise UserError(f"{f}: lists images COLMAP did not register: {unknown[:3]}")
        out[part] = sorted(pos[n] for n in listed)
    return out


def import_neuman(
    src: str | Path,
    out: str | Path,
    body_model: str = "anny",
    smpl_model: Path | None = None,
    smpl_source: str = "auto",
    overwrite: bool = False,
    select: FrameSelection = FrameSelection(),
) -> Path:
    """Import one NeuMan sequence folder `src` as a native scene in `out` (an existing `out`
    is replaced only with `overwrite`, once the new scene is complete).

    smpl_source: "optimized" (smpl_output_optimized.pkl + alignments.npy), "4d_humans"
    (HUGS' npz) or "auto": the one whose fits carry joints when only one does (needed for
    the licence-free Anny body), else "optimized" when present.
    """
    check_out_folder(Path(out), overwrite=overwrite)
    root = Path(src)
    if not root.is_dir():
        raise UserError(f"{root}: not a folder (expected a NeuMan sequence)")
    sparse = require(root / "sparse", "COLMAP text model: cameras.txt, images.txt, points3D.txt")
    cams = read_colmap_cameras(sparse / "cameras.txt")
    regs = sorted(read_colmap_images(sparse / "images.txt"), key=lambda im: im.name)  # video order
    xyz, rgb = read_colmap_points(require(sparse / "points3D.txt", "COLMAP sparse points"))
    if len(xyz) == 0:
        raise UserError(f"{sparse / 'points3D.txt'}: no points")
    names = [im.name for im in regs]
    n = len(names)
    require(root / "images", "the video frames")
    seg = require(root / "segmentations", "person masks (0 = person)")

    fits = _choose_fits(root, names, smpl_source, body_model)

    # Cameras (world still COLMAP's here).
    K_all, w2c_all, images, masks = [], [], [], []
    undistorters: dict[int, Undistorter] = {}
    for im in regs:
        if im.camera_id not in cams:
            raise UserError(f"{sparse / 'images.txt'}: image {im.name} uses unknown camera {im.camera_id}")
        cam = cams[im.camera_id]
        K, dist = colmap_intrinsics(cam, f"{sparse / 'cameras.txt'} (camera {im.camera_id})")
        rgb_img = read_rgb(root / "images" / im.name)
        if rgb_img.shape[:2] != (cam.height, cam.width):
            raise UserError(f"{root / 'images' / im.name}: image is {rgb_img.shape[1]}x{rgb_img.shape[0]}, "
                            f"camera {im.camera_id} says {cam.width}x{cam.height}")
        mpath = seg / (im.name + ".npy") if (seg / (im.name + ".npy")).is_file() else seg / im.name
        m = read_gray(mpath)
        if m.shape != rgb_img.shape[:2]:
            raise UserError(f"{mpath}: mask is {m.shape[1]}x{m.shape[0]}, image is {rgb_img.shape[1]}x{rgb_img.shape[0]}")
        human = m < 128  # Detectron2 convention of the release: the person is black
        if dist is not None:
            if im.camera_id not in undistorters:
                log.info("undistorting camera %d (%s)", im.camera_id, cam.model)
                undistorters[im.camera_id] = Undistorter(K, dist, cam.width, cam.height)
            u = undistorters[im.camera_id]
            rgb_img, human = u.image(rgb_img), u.mask(human)
        K_all.append(K)
        w2c_all.append(im.world_to_camera())
        images.append(rgb_img)
        masks.append(human)
    sizes = {im.shape for im in images}
    if len(sizes) != 1:
        raise UserError(f"{root / 'images'}: frames differ in size ({sorted(sizes)}); one size is needed")

    # Metric world: divide COLMAP's by the median SMPL scale.
    k = float(np.median(fits.scale))
    w2c = np.stack(w2c_all)
    w2c[:, :3, 3] /= k
    cameras = CameraTrack(K=np.stack(K_all), world_to_camera=w2c)
    R, c = fold_scale(fits, camera_centres(cameras), k)

    split_files = _split_from_files(root, names)
    train, val, test = neuman_split(n)
    rule = "NeuMan create_split_files: every (n // 5)-th-spaced frame from half that spacing held out; first half test, rest val"
    if split_files is not None:
        if (split_files["train"], split_files["val"], split_files["test"]) != (train, val, test):
            log.warning("%s: split files differ from NeuMan's rule; using the files", root)
            rule = "train/val/test_split.txt of the sequence (they differ from the rule)"
        else:
            rule = "train/val/test_split.txt of the sequence (identical to NeuMan's rule)"
        train, val, test = split_files["train"], split_files["val"], split_files["test"]

    scale_spread = float(fits.scale.max() / fits.scale.min()) if len(fits.scale) else 1.0
    frames = ImportedFrames(
        name=root.name,
        frame_ids=[Path(nm).stem for nm in names],
        images=np.stack(images),
        human_masks=np.stack(masks),
        object_masks=None,
        cameras=cameras,
        fits=fits,
        body_R=R,
        body_c=c,
        split={"train": train, "test": test},
        points_xyz=xyz / k,
        points_rgb=rgb,
        source={
            "dataset": "neuman",
            "path": str(root.resolve()),
            "images": names,
            "protocol": "neuman",
            "split_rule": rule,
            "val": val,
            "smpl_fits": fits.source,
            "world_from_colmap": {"scale": 1.0 / k, "note": "x_cogs = x_colmap / median SMPL scale"},
            "smpl_scale_range": [float(fits.scale.min()), float(fits.scale.max())],
            "scale_folding": ("per-frame SMPL scale differences (max/min %.3f) folded into depth along each "
                              "frame's view ray; images of the body are unchanged" % scale_spread),
        },
    )
    frames = select_frames(frames, select, _neuman_split, str(root))
    return write_scene(frames, Path(out), body_model, smpl_model, overwrite=overwrite)


def _neuman_split(n: int) -> dict[str, list[int]]:
    train, _, test = neuman_split(n)
    return {"train": train, "test": test}


def _choose_fits(root: Path, names: list[str], smpl_source: str, body_model: str) -> SmplFits:
    have_opt = (root / OPTIMIZED).is_file()
    have_4d = (root / FOUR_D).is_file()
    if smpl_source == "optimized" or (smpl_source == "auto" and have_opt and not have_4d):
        return _read_optimized(root, names)
    if smpl_source == "4d_humans" or (smpl_source == "auto" and have_4d and not have_opt):
        return _read_4d_humans(root, len(names))
    if smpl_source != "auto":
        raise UserError(f"unknown SMPL source {smpl_source!r} (auto, optimized, 4d_humans)")
    if not (have_opt or have_4d):
        raise UserError(f"{root}: no SMPL fits: expected {OPTIMIZED} (with {ALIGNMENTS}) or {FOUR_D}")
    opt = _read_optimized(root, names)
    if body_model == "anny" and opt.joints is None:
        four = _read_4d_humans(root, len(names))
        if four.joints is not None:
            return four
    return opt
