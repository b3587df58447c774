"""`cogs eval`: the evaluation protocols on a trained run, writing metrics.json and renders.

Protocols (the split itself lives in the scene, see `cogs.eval.protocols`):
    hosnerf-16  full frame, human tight-bbox crop, object tight-bbox crop; PSNR/SSIM/LPIPS
    neuman      full frame and human tight-bbox crop
Synthetic scenes (ground truth present) add novel views off the training path, branch
decomposition IoU against the ground-truth masks, and object pose error.

metrics.json schema (DESIGN.md): protocol, n_test_frames, full, human_crop, object_crop,
novel_view, decomposition, object_pose_error, train_seconds, stage_seconds, n_gaussians,
notes; and per_frame, each held-out frame's full, human_crop and object_crop (the means
above are over these). A value that cannot be computed is null with a note saying why.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import torch

from cogs.data.io import read_json, write_image, write_json
from cogs.errors import UserError
from cogs.eval.metrics import crop_to_mask, image_metrics, iou
from cogs.geometry.camera import project_points
from cogs.geometry.rotations import quat_to_rotmat, rotmat_geodesic_angle
from cogs.log import track

log = logging.getLogger(__name__)

EVAL_ENTRIES = ("metrics.json", "renders", "novel")
"""What an evaluation writes into its folder (RUN/eval by default); re-evaluating replaces them."""


def _mean_metrics(rows: list[dict], notes: list[str], what: str) -> dict:
    out = {}
    for k in ("psnr", "ssim", "lpips"):
        vals = [r[k] for r in rows if r.get(k) is not None and math.isfinite(r[k])]
        out[k] = float(np.mean(vals)) if vals else None
        if not vals and rows:
            notes.append(f"{what}.{k}: not computable (unavailable for every frame)")
    return out


def _error_map(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    import matplotlib

    err = np.abs(pred - gt).mean(-1)
    return matplotlib.colormaps["inferno"](np.clip(err / 0.25, 0, 1))[..., :3]


def _branch_iou(r, branch: str, mask: np.ndarray) -> float:
    """IoU of a branch's rendered silhouette (its alpha share > 0.5) with a true mask."""
    return iou(r.branch_alpha[branch][..., 0].cpu().numpy() > 0.5, mask)


def _camera(model, scene, t: int, viewmat=None, K=None, pose=None):
    dev = model.device
    vm = torch.as_tensor(scene.cameras.world_to_camera[t] if viewmat is None else viewmat, dtype=torch.float32, device=dev)
    KK = torch.as_tensor(scene.cameras.K[t] if K is None else K, dtype=torch.float32, device=dev)
    return vm, KK


def render_frame(model, scene, t: int, branches=None, viewmat=None, K=None, human_pose=None):
    """Composite render of frame t (training camera unless viewmat/K given), no grad."""
    vm, KK = _camera(model, scene, t, viewmat, K)
    poses = {"human": human_pose} if human_pose is not None else None
    with torch.no_grad():
        return model.render(vm, KK, scene.width, scene.height, t, branches=branches,
                            background=vm.new_zeros(3), poses=poses)


def _numpy(x: torch.Tensor) -> np.ndarray:
    """A rendered image on the host, checked: a non-finite pixel is a bug, never a metric."""
    a = x.detach().clamp(0, 1).cpu().numpy() if x.is_floating_point() else x.cpu().numpy()
    assert np.isfinite(a).all(), "a render holds non-finite values"
    return a


def load_run(run: Path, device: str = "cpu", scene_dir: Path | None = None, checkpoint: str | None = None,
             full_resolution: bool = False):
    """(model, config, scene) of a run folder: the model from its last checkpoint (no
    images read), the scene its run.json names (or `scene_dir`) at the resolution the run
    trained at (or in full), checked against the fingerprint the run recorded."""
    from cogs.config import load_config
    from cogs.data.scene import load_scene
    from cogs.model import Model
    from cogs.train.run_folder import check_fingerprint

    run = Path(run)
    if checkpoint is not None and not (run / "checkpoints" / checkpoint).is_file():
        have = ", ".join(sorted(p.name for p in (run / "checkpoints").glob("*.pt"))) or "none"
        raise UserError(f"--checkpoint {checkpoint}: no such file in {run / 'checkpoints'} (there: {have})")
    model = Model.load(run, device=device, checkpoint=run / "checkpoints" / checkpoint if checkpoint else None)
    info_path = run / "run.json"
    info = read_json(info_path) if info_path.is_file() else {}
    if scene_dir is None:
        named = info.get("scene")
        if not info_path.is_file():
            raise UserError(f"{run} has no run.json naming its scene; pass the scene it was trained on with --scene")
        if not named or not Path(named).exists():
            raise UserError(f"{info_path} names scene {named!r}, which does not exist (moved?); pass it with --scene")
        scene_dir = Path(named)
    scene = load_scene(scene_dir, max_side=None if full_resolution else info.get("max_side"))
    check_fingerprint(run, info.get("fingerprint"), scene)
    return model, load_config(run / "config.yaml"), scene


def _progress(run: Path, names: list[str], model, checkpoint: str | None) -> tuple[dict, dict]:
    """({"stage", "step"}, summary) of the checkpoint evaluated: the newest from
    last.json and train_summary.json where they describe it, else from its run state."""
    if checkpoint is None and (run / "checkpoints" / "last.json").is_file() and (run / "train_summary.json").is_file():
        return read_json(run / "checkpoints" / "last.json"), read_json(run / "train_summary.json")
    from cogs.train import checkpoint as ckpt

    state = ckpt.load(run / "checkpoints" / (checkpoint or "last.pt"))["run_state"]
    summary = {"stages": names[: state.stage], "train_seconds": sum(state.stage_seconds.values()),
               "stage_seconds": dict(state.stage_seconds), "n_gaussians": model.counts()}
    return {"stage": state.stage, "step": state.step}, summary


def evaluate(run: Path, out: Path | None = None, save_renders: bool = True, pose_fit_steps: int = 40,
             show_progress: bool = True, device: str = "cpu", scene_dir: Path | None = None,
             checkpoint: str | None = None, full_resolution: bool = False) -> dict:
    from cogs.train.stages import stage_names

    run = Path(run)
    out = Path(out) if out else run / "eval"
    model, cfg, scene = load_run(run, device, scene_dir, checkpoint, full_resolution)
    gt = scene.gt
    notes: list[str] = []
    names = stage_names(cfg)
    where, summary = _progress(run, names, model, checkpoint)
    if where["stage"] < len(names):
        msg = (f"{run} is unfinished: it stopped in stage {names[where['stage']]} after {where['step']} "
               f"steps; these numbers are of that state (`cogs train --resume --out {run}` finishes it)")
        log.warning(msg)
        notes.append(msg)
    protocol = scene.source.get("protocol", "hosnerf-16")
    test = list(scene.split["test"])
    if not test:
        notes.append("the scene's split has no test frames: nothing to evaluate")
    human_masks = gt.human_masks if gt is not None else scene.human_masks
    object_masks = (gt.object_masks if gt is not None else scene.object_masks) if scene.has_object else None
    if gt is None:
        notes.append("no ground truth: crops use the input masks; novel views, decomposition and object pose error are null")

    rdir = out / "renders" if save_renders else None
    strict = _frame_metrics(model, scene, test, human_masks, object_masks, protocol, notes, rdir,
                            show_progress=show_progress)
    fitted = None
    if pose_fit_steps > 0 and model.human is not None and model.human.cfg.refine_pose:
        poses = _test_time_poses(model, cfg, scene, test, pose_fit_steps, show_progress)
        fitted = _frame_metrics(model, scene, test, human_masks, object_masks, protocol, notes, None, poses,
                                "eval: frames with fitted poses", show_progress)
    full, hcrop, ocrop, h_iou, o_iou, per_frame = strict

    metrics: dict = {
        "protocol": protocol,
        "n_test_frames": len(test),
        "resolution": [scene.width, scene.height],
        "full": _mean_metrics(full, notes, "full"),
        "human_crop": _mean_metrics(hcrop, notes, "human_crop"),
        "object_crop": _mean_metrics(ocrop, notes, "object_crop") if protocol != "neuman" and scene.has_object else None,
        "novel_view": None,
        "decomposition": None,
        "object_pose_error": None,
    }
    if protocol == "neuman":
        notes.append("neuman protocol: no object crop")
    elif not scene.has_object:
        notes.append("object_crop: the scene has no object")
    if gt is not None:
        metrics["decomposition"] = {
            "human_iou": float(np.mean(h_iou)) if h_iou else None,
            "object_iou": float(np.mean(o_iou)) if o_iou else None,
        }
        metrics["novel_view"] = _novel_views(model, scene, notes, out if save_renders else None, show_progress)
        if scene.has_object and model.object is not None:
            metrics["object_pose_error"] = _object_pose_error(model.object, gt.object, test, list(scene.split["train"]))
        if model.human is not None and test:
            metrics["body_pose_error"] = _body_pose_error(model.human, scene, list(scene.split["train"]), test)
    if fitted is not None:
        f_full, f_h, f_o, f_hi, f_oi, _ = fitted
        metrics["test_time_pose_fit"] = {
            "steps": pose_fit_steps,
            "full": _mean_metrics(f_full, notes, "test_time_pose_fit.full"),
            "human_crop": _mean_metrics(f_h, notes, "test_time_pose_fit.human_crop"),
            "object_crop": _mean_metrics(f_o, notes, "test_time_pose_fit.object_crop") if metrics["object_crop"] is not None else None,
            "decomposition": {"human_iou": float(np.mean(f_hi)) if f_hi else None,
                              "object_iou": float(np.mean(f_oi)) if f_oi else None} if gt is not None else None,
        }
        notes.append("test_time_pose_fit: the body pose of each held-out frame fitted to that frame (appearance, "
                     "object and scene frozen), the Anim-NeRF/InstantAvatar protocol; the top-level numbers use no test image")
    metrics.update(summary)
    metrics["per_frame"] = per_frame
    metrics["notes"] = _summarise_notes(notes)
    write_json(out / "metrics.json", metrics)
    return metrics


def _test_time_poses(model, cfg, scene, test: list[int], steps: int, show_progress: bool) -> dict:
    """Each held-out frame's body pose fitted to its own image (the training's pose refit,
    `cogs.train.posefit`, with `steps` Adam steps): the Anim-NeRF / InstantAvatar protocol."""
    from dataclasses import replace

    from cogs.train.posefit import fit_frame_pose, posed

    opts = replace(cfg.refit, steps=steps)
    out = {}
    for t in track(test, "eval: test-time pose fit", show_progress):
        vm, K = _camera(model, scene, t)
        img = torch.from_numpy(np.ascontiguousarray(scene.images[t])).to(model.device).float() / 255.0
        fit = fit_frame_pose(model, img, vm, K, t, opts)
        with torch.no_grad():
            out[t] = posed(model.human, t, fit)
    return out


def _frame_metrics(model, scene, test, human_masks, object_masks, protocol, notes, rdir, poses=None,
                   label: str = "eval: held-out frames", show_progress: bool = True):
    """Per-frame metric rows over the held-out frames: (full, human crop, object crop,
    human IoU, object IoU, per frame). `poses` optionally overrides the human pose per
    frame. The crop lists hold the frames with a non-empty mask only; "per frame" is one
    row per held-out frame ({"frame": its id, "full", "human_crop", "object_crop"}, a crop
    None where its mask is empty or the protocol has none)."""
    gt = scene.gt
    h_iou, o_iou, rows = [], [], []
    for t in track(test, label, show_progress):
        r = render_frame(model, scene, t, human_pose=poses.get(t) if poses else None)
        pred = _numpy(r.rgb)
        img = scene.images[t].astype(np.float32) / 255.0
        row = {"frame": scene.frame_ids[t], "full": image_metrics(pred, img, notes=notes), "human_crop": None, "object_crop": None}
        c = crop_to_mask(pred, img, human_masks[t])
        if c is not None:
            row["human_crop"] = image_metrics(*c, notes=notes)
        if object_masks is not None and protocol != "neuman":
            c = crop_to_mask(pred, img, object_masks[t])
            if c is not None:
                row["object_crop"] = image_metrics(*c, notes=notes)
        rows.append(row)
        if gt is not None:
            h_iou.append(_branch_iou(r, "human", gt.human_masks[t]))
            if scene.has_object and (gt.object_masks[t].any() or (r.branch_alpha["object"] > 0.5).any()):
                o_iou.append(_branch_iou(r, "object", gt.object_masks[t]))
        if rdir is not None:
            fid = scene.frame_ids[t]
            write_image(rdir / f"{fid}_composite.png", pred)
            write_image(rdir / f"{fid}_gt.png", img)
            write_image(rdir / f"{fid}_error.png", _error_map(pred, img))
            for b in model.available():
                rb = render_frame(model, scene, t, branches=(b,))
                write_image(rdir / f"{fid}_{b}.png", _numpy(rb.rgb))
    crops = {k: [row[k] for row in rows if row[k] is not None] for k in ("human_crop", "object_crop")}
    return [row["full"] for row in rows], crops["human_crop"], crops["object_crop"], h_iou, o_iou, rows


def _summarise_notes(notes: list[str]) -> list[str]:
    """Unique notes; per-crop size notes folded into one line each."""
    import re

    small = [n for n in notes if re.match(r"(lpips|ssim) is null: image \d+x\d+ is smaller", n)]
    out = sorted(set(n for n in notes if n not in small))
    metrics = ("lpips", "ssim")
    if any(n.startswith("lpips is null: ") and "smaller" not in n for n in out):
        # LPIPS is unavailable altogether: one line says why, not one per section and crop.
        out = [n for n in out if not re.match(r"[\w.]*lpips: not computable", n)]
        out.append("lpips is null in every section (the reason above)")
        metrics = ("ssim",)
    for metric in metrics:
        k = sum(1 for n in small if n.startswith(metric))
        if k:
            out.append(f"{metric} is null for {k} crop(s) smaller than its window (small objects); the crop means use the others")
    return out


def _novel_views(model, scene, notes: list[str], out: Path | None, show_progress: bool = True) -> dict | None:
    nv = scene.gt.novel
    if nv is None or len(nv.frames) == 0:
        notes.append("novel_view: the scene has no novel-view ground truth")
        return None
    rows, hcrop, h_iou, o_iou = [], [], [], []
    for i, t in track(enumerate(nv.frames), "eval: novel views", show_progress):
        r = render_frame(model, scene, int(t), viewmat=nv.cameras.world_to_camera[i], K=nv.cameras.K[i])
        pred = _numpy(r.rgb)
        img = nv.images[i].astype(np.float32) / 255.0
        rows.append(image_metrics(pred, img, notes=notes))
        # The rings see the person from all round, sides no training view may have seen:
        # the human's crop and silhouette there measure what the seed and anchoring leave.
        c = crop_to_mask(pred, img, nv.human_masks[i])
        if c is not None:
            hcrop.append(image_metrics(*c, notes=notes))
        if model.human is not None and nv.human_masks[i].any():
            h_iou.append(_branch_iou(r, "human", nv.human_masks[i]))
        if model.object is not None and nv.object_masks[i].any():
            o_iou.append(_branch_iou(r, "object", nv.object_masks[i]))
        if out is not None:
            write_image(out / "novel" / f"v{i:03d}_render.png", pred)
            write_image(out / "novel" / f"v{i:03d}_gt.png", img)
    res = _mean_metrics(rows, notes, "novel_view")
    res["human_crop"] = _mean_metrics(hcrop, notes, "novel_view.human_crop") if hcrop else None
    res["human_iou"] = float(np.mean(h_iou)) if h_iou else None
    res["object_iou"] = float(np.mean(o_iou)) if o_iou else None
    res["n_views"] = len(rows)
    for key in ("human_crop", "human_iou", "object_iou"):
        if res[key] is None:
            notes.append(f"novel_view.{key}: no novel view shows that branch (or the run has none)")
    return res


def _body_pose_error(human, scene, train: list[int], test: list[int]) -> dict:
    """How far the posed body's joints are from the truth: mean over joints and frames of
    the image distance (pixels, true cameras) and the 3D distance (mm).

    `input` poses the body as the scene's body.npz gives it; `fitted` as the trained run
    poses each frame (training frames: their fitted corrections; held-out frames: the
    interpolation of their fitted neighbours with a share of their own input's motion,
    `HumanBranch.held_out_pose`). The held-out human metrics can only be as good as these
    poses (benchmarks/human_pose_bound.py).
    """
    gt = scene.gt
    body = human.body
    dev = human.shape.device
    host = lambda a: torch.as_tensor(a, dtype=torch.float32, device=dev)  # noqa: E731
    w2c, K = host(gt.cameras.world_to_camera).cpu(), host(gt.cameras.K).cpu()

    def joints(pose, transl, shape):
        return body.bone_transforms(host(pose), host(transl), host(shape))[1].cpu()

    def pixels(J):
        return torch.stack([project_points(J[t], w2c[t], K[t])[0] for t in range(len(J))])

    with torch.no_grad():
        fitted = [human.frame_pose(t) for t in range(len(gt.body))]
        poses = {
            "input": joints(scene.body.pose, scene.body.transl, scene.body.shape),
            "fitted": joints(torch.cat([f[0] for f in fitted]), torch.cat([f[1] for f in fitted]), human.shape),
        }
        truth = joints(gt.body.pose, gt.body.transl, gt.body.shape)
    truth_px = pixels(truth)
    out: dict = {"joint_px": {}, "joint_mm": {}}
    for name, J in poses.items():
        px = (pixels(J) - truth_px).norm(dim=-1).mean(-1)
        mm = (J - truth).norm(dim=-1).mean(-1) * 1000.0
        for split, frames in (("train", train), ("test", test)):
            out["joint_px"][f"{name}_{split}"] = float(px[frames].mean())
            out["joint_mm"][f"{name}_{split}"] = float(mm[frames].mean())
    return out


def _object_pose_error(obj, gt_track, test: list[int], train: list[int]) -> dict:
    """Translation (m) and rotation (deg) error of the learned object poses vs ground truth.

    The object's canonical frame is only defined up to a constant rigid transform: the
    canonical Gaussians and the trajectory can trade one (a box modelled 3 degrees turned
    and a trajectory 3 degrees back render identically). So the learned canonical frame is
    first aligned to the ground truth's with the one rigid offset (R0, d0) that best maps
    the *training* frames' poses onto the truth (chordal mean of R_t^T R*_t; mean of
    R_t^T (t*_t - t_t)); the error is then measured on the held-out frames. The raw,
    unaligned errors are reported beside it.
    """
    assert len(gt_track) == obj.n_frames, "one ground-truth pose per frame"
    cpu = torch.device("cpu")
    with torch.no_grad():
        tr, q = obj.frame_poses()  # the poses rendered: held-out frames as `ObjectBranch.frame_pose` has them
    R = quat_to_rotmat(q).double().cpu()
    Rg = quat_to_rotmat(torch.as_tensor(gt_track.quats, device=cpu)).double()
    tg = torch.as_tensor(gt_track.translations, device=cpu).double()
    tr = tr.double().cpu()
    idx = torch.tensor(train, device=cpu)
    M = (R[idx].transpose(1, 2) @ Rg[idx]).sum(0)
    U, _, Vt = torch.linalg.svd(M)
    D = torch.diag(torch.tensor([1.0, 1.0, float(torch.sign(torch.det(U @ Vt)))], dtype=torch.float64, device=cpu))
    R0 = U @ D @ Vt
    d0 = (R[idx].transpose(1, 2) @ (tg[idx] - tr[idx])[..., None])[..., 0].mean(0)
    Ra, ta = R @ R0, tr + (R @ d0[:, None])[..., 0]

    def err(Rx, tx, frames):
        f = torch.tensor(frames, device=cpu)
        rot = torch.rad2deg(rotmat_geodesic_angle(Rx[f], Rg[f])).mean()
        return float((tx[f] - tg[f]).norm(dim=1).mean()), float(rot)

    t_al, r_al = err(Ra, ta, test)
    t_raw, r_raw = err(R, tr, test)
    return {"translation": t_al, "rotation_deg": r_al, "translation_unaligned": t_raw, "rotation_deg_unaligned": r_raw,
            "canonical_offset_deg": float(torch.rad2deg(rotmat_geodesic_angle(R0, torch.eye(3, dtype=torch.float64, device=cpu)))),
            "canonical_offset_m": float(d0.norm())}
