"""What the held-out human metrics of the synthetic benchmark allow at best.

Usage:  python benchmarks/human_pose_bound.py [--frames N]

A held-out frame is rendered with its *input* body pose (an estimate: a smooth drift plus a
per-frame jitter, `cogs.data.synth.config.NoiseConfig`), corrected at most by what the
training frames teach. This script renders the synthetic scene's own meshes and textures,
a perfect model of the person's shape and appearance, posed four ways on the hosnerf-16
held-out frames, and scores each like `cogs eval` scores a trained run (human IoU against
the ground-truth mask, PSNR of the human's tight box and of the full frame; PSNR averages
the frames that differ from the truth at all, `frames_rendered_exactly` counts the rest):

* ``input``: the noisy input pose as it is;
* ``drift_only``: the input without its per-frame jitter;
* ``jitter_only``: the input without its smooth drift: the best any correction that is
  smooth in time (such as the trainer's keyframed one) can give, since the jitter of a
  held-out frame is independent of every other frame;
* ``true_neighbours``: the true poses of the frame's training neighbours, interpolated to
  it the way `HumanBranch.held_out_pose` interpolates fitted ones (cubic, two per side,
  without the share of the frame's own input, `held_out_input_weight=0`; the clip's first
  frame, which has none before it, as in ``jitter_only``): what that rule reaches once the
  training frames' poses are recovered exactly;
* ``truth``: the true pose (a check: IoU 1, PSNR infinite).

The noise is drawn with the scene's own seed and generator, so these are the poses the
demo's scene carries. Progress goes to stderr; the last stdout line is one JSON object.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time

import numpy as np


def interpolated_truth(motion, test: list[int], n_frames: int, fallback):
    """(pose [T, J, 3], transl [T, 3]): each held-out frame posed by the interpolation of
    its training neighbours' true poses (held_out_pose's rule); a frame without neighbours
    on both sides keeps `fallback` (its input without the drift, as the rule keeps the
    corrected input there)."""
    import torch

    from cogs.branches.human import _blend, _lagrange_neighbours
    from cogs.geometry.rotations import axis_angle_to_quat, quat_sign_continuous, quat_to_axis_angle

    trained = torch.ones(n_frames, dtype=torch.bool)
    trained[test] = False
    q = quat_sign_continuous(axis_angle_to_quat(torch.as_tensor(motion.pose)))  # as the branch keeps them
    tr = torch.as_tensor(motion.transl)
    pose, transl = fallback[0].copy(), fallback[1].copy()
    for t in test:
        nb = _lagrange_neighbours(t, trained, 2, 3)
        if nb is not None:
            qt, tt = _blend(q, tr, nb[0], nb[1].double())
            pose[t], transl[t] = quat_to_axis_angle(qt).numpy(), tt.numpy()
    return pose, transl


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100, help="clip length (the demo's default: 100)")
    args = ap.parse_args()

    from cogs.data.synth import generate as gen
    from cogs.data.synth import noise as nz
    from cogs.data.synth.config import SynthConfig
    from cogs.data.synth.mesh import HUMAN
    from cogs.data.synth.motion import SCRIPT_SECONDS
    from cogs.data.synth.render import render_view
    from cogs.eval.metrics import crop_to_mask, image_metrics, iou
    from cogs.geometry.camera import intrinsics_from_fov

    started = time.perf_counter()
    cfg = SynthConfig(frames=args.frames)
    assets = gen.build_assets(cfg)
    motion = assets.choreo.evaluate(cfg.frames)
    K = intrinsics_from_fov(cfg.width, cfg.height, cfg.fov_deg)
    test = gen.hosnerf_split(cfg.frames)["test"]
    sigma_frames = cfg.noise.smooth_s * cfg.frames / SCRIPT_SECONDS
    rig = assets.choreo.rig

    def noisy(**zeroed) -> tuple[np.ndarray, np.ndarray]:
        # the scene's generator draws the body noise first, from a fresh default_rng(seed);
        # zeroing a term scales its draws by 0 and keeps the stream aligned
        rng = np.random.default_rng(cfg.seed)
        ncfg = dataclasses.replace(cfg.noise, **zeroed)
        pose, transl, _ = nz.noisy_body(motion.pose, motion.transl, assets.shape,
                                        assets.model.bone_names, ncfg, rng, sigma_frames)
        return pose, transl

    variants = {
        "input": noisy(),
        "drift_only": noisy(body_jitter_deg=0.0, transl_jitter_m=0.0),
        "jitter_only": noisy(body_deg=0.0, root_deg=0.0, transl_m=0.0),
        "true_neighbours": interpolated_truth(motion, test, cfg.frames, noisy(body_deg=0.0, root_deg=0.0, transl_m=0.0)),
        "truth": (motion.pose, motion.transl),
    }

    def view(pose, transl, t):
        V = rig.vertices_posed(rig.transforms(pose[t:t + 1], transl[t:t + 1]))[0]
        mesh = assets.scene_mesh(V, motion.box_R[t], motion.box_t[t])
        return render_view(mesh, K, motion.camera_w2c[t], cfg.width, cfg.height, cfg.supersample)

    truth = {t: view(*variants["truth"], t) for t in test}
    result: dict = {"benchmark": "human_pose_bound", "frames": cfg.frames, "test_frames": test,
                    "noise": {k: getattr(cfg.noise, k) for k in ("body_deg", "body_jitter_deg", "root_deg",
                                                                 "transl_m", "transl_jitter_m")}}
    for name, (pose, transl) in variants.items():
        ious, crop, full = [], [], []
        for t in test:
            gt, v = truth[t], view(pose, transl, t)
            mask = gt.label == HUMAN
            ious.append(iou(v.label == HUMAN, mask))
            pred, img = v.rgb.astype(np.float32) / 255.0, gt.rgb.astype(np.float32) / 255.0
            crop.append(image_metrics(*crop_to_mask(pred, img, mask), with_lpips=False)["psnr"])
            full.append(image_metrics(pred, img, with_lpips=False)["psnr"])
        # a frame rendered exactly like the truth has infinite PSNR: counted, not averaged
        finite = lambda xs: float(np.mean([x for x in xs if math.isfinite(x)])) if any(math.isfinite(x) for x in xs) else None  # noqa: E731
        result[name] = {"human_iou": float(np.mean(ious)), "human_iou_min": float(np.min(ious)),
                        "human_crop_psnr": finite(crop), "full_psnr": finite(full),
                        "frames_rendered_exactly": int(sum(not math.isfinite(x) for x in full)),
                        "per_frame_human_iou": [round(x, 4) for x in ious]}
        print(f"{name}: human IoU {np.mean(ious):.3f}, crop PSNR {result[name]['human_crop_psnr']} dB", file=sys.stderr)
    result["seconds"] = round(time.perf_counter() - started, 1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
