"""The training's last step, the body-pose refit: exact on its cropped render, it recovers a
displaced pose, it changes only the training frames' poses, and a run trained before it
existed gets just this step on resume."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import pytest
import torch
import yaml

from cogs.cli import main
from cogs.config import PoseRefit
from cogs.train import checkpoint as ckpt
from cogs.train import losses as L
from cogs.train.posefit import fit_frame_pose, posed
from cogs.data.scene import load_scene
from cogs.eval.evaluate import load_run
from cogs.train.trainer import run_is_finished
from tests.fixtures import TINY


@pytest.fixture(scope="module")
def unrefitted(small_synthetic, tmp_path_factory) -> Path:
    """A tiny run trained through stage VI with the refit switched off."""
    run = tmp_path_factory.mktemp("refit") / "run"
    assert main(["train", "--scene", str(small_synthetic), "--out", str(run), "--set", *TINY, "refit.steps=0"]) == 0
    return run


def _frame(scene, t):
    vm = torch.as_tensor(scene.cameras.world_to_camera[t], dtype=torch.float32)
    K = torch.as_tensor(scene.cameras.K[t], dtype=torch.float32)
    return vm, K, torch.as_tensor(scene.images[t]).float() / 255.0


def _whole_frame_fit(model, img, vm, K, t, opts):
    """The reference: the same fit, rendering the whole frame with every Gaussian."""
    h = model.human
    with torch.no_grad():
        state = h.decode()
        bp, bt = h.frame_pose(t)
        others = model.splats(t, vm, tuple(b for b in model.available() if b != "human"))
    dp = torch.zeros(1, len(h.refined_bones), 3, requires_grad=True)
    dt = torch.zeros(1, 3, requires_grad=True)
    opt = torch.optim.Adam([{"params": [dp], "lr": opts.lr}, {"params": [dt], "lr": opts.lr * 0.5}])
    for _ in range(opts.steps):
        opt.zero_grad()
        pose = (bp.index_add(1, h.refined_bones, dp), bt + dt)
        splats = {**model.splats(t, vm, ("human",), poses={"human": pose}, prepared={"human": state}), **others}
        r = model.render(vm, K, img.shape[1], img.shape[0], t, background=torch.zeros(3), splats=splats)
        (L.l1(r.rgb, img) + opts.reg * (dp.square().sum() + dt.square().sum())).backward()
        opt.step()
    return dp.detach(), dt.detach()


def test_cropped_fit_is_the_whole_frame_fit(unrefitted):
    model, _, scene = load_run(unrefitted)
    t = int(scene.split["train"][3])
    vm, K, img = _frame(scene, t)
    # Three Adam steps: equal up to float summation order (the crop sums fewer pixels).
    # Over more steps Adam's normalised updates amplify those last-digit differences where a
    # gradient is near zero (after ten steps some corrections differ by a fifth of a step,
    # while after three they agree to 1e-7), which says nothing about the crop.
    opts = PoseRefit(steps=3)
    fit = fit_frame_pose(model, img, vm, K, t, opts)
    dp, dt = _whole_frame_fit(model, img, vm, K, t, opts)
    assert fit.dpose.abs().max() > 1e-3  # it did move
    torch.testing.assert_close(fit.dpose, dp, rtol=0, atol=1e-3 * float(dp.abs().max()))
    torch.testing.assert_close(fit.dtransl, dt, rtol=0, atol=1e-3 * float(dt.abs().max()))
    assert fit.loss_last < fit.loss_first


def test_fit_recovers_a_displaced_pose(unrefitted):
    """Target = the model's own render at frame t; start from that pose with the arms and
    the body moved: the fit brings the joints most of the way back."""
    model, _, scene = load_run(unrefitted)
    h = model.human
    t = int(scene.split["train"][5])
    vm, K, _ = _frame(scene, t)
    with torch.no_grad():
        true_pose, true_transl = h.frame_pose(t)
        target = model.render(vm, K, scene.width, scene.height, t, background=torch.zeros(3)).rgb
    g = torch.Generator().manual_seed(0)
    start = (true_pose.index_add(1, h.refined_bones, 0.08 * torch.randn(1, len(h.refined_bones), 3, generator=g)),
             true_transl + torch.tensor([[0.02, -0.01, 0.0]]))

    def joints_px(pose):
        J = h.body.bone_transforms(pose[0], pose[1], h.shape)[1][0]
        from cogs.geometry.camera import project_points

        return project_points(J, vm, K)[0]

    truth = joints_px((true_pose, true_transl))
    before = (joints_px(start) - truth).norm(dim=-1).mean()
    fit = fit_frame_pose(model, target, vm, K, t, replace(PoseRefit(), steps=80), pose=start)
    with torch.no_grad():
        after = (joints_px(posed(h, t, fit, start)) - truth).norm(dim=-1).mean()
    assert before > 0.5  # pixels: the displacement is visible
    assert after < 0.5 * before
    assert fit.loss_last < 0.5 * fit.loss_first


def test_refit_moves_only_the_training_frames_poses(unrefitted, small_synthetic, tmp_path):
    """A run trained before the refit existed (config without it, summary without stages)
    is unfinished under today's config; `--resume` runs just the refit: the training
    frames' per-frame pose corrections change, nothing else does."""
    run = tmp_path / "old"
    shutil.copytree(unrefitted, run)
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    del cfg["refit"]  # as written before the refit existed; its default (on) applies
    (run / "config.yaml").write_text(yaml.safe_dump(cfg))
    summary = json.loads((run / "train_summary.json").read_text())
    del summary["stages"]
    (run / "train_summary.json").write_text(json.dumps(summary))
    assert run_is_finished(unrefitted) and not run_is_finished(run)

    assert main(["eval", "--run", str(run), "--no-renders", "--pose-fit-steps", "0"]) == 0
    notes = json.loads((run / "eval" / "metrics.json").read_text())["notes"]
    assert any("unfinished" in n and "refit" in n for n in notes)

    before = ckpt.load(run / "checkpoints" / "last.pt")
    assert main(["train", "--scene", str(small_synthetic), "--out", str(run), "--resume"]) == 0
    after = ckpt.load(run / "checkpoints" / "last.pt")
    assert run_is_finished(run)
    summary = json.loads((run / "train_summary.json").read_text())
    assert summary["stages"][-2:] == ["VI", "refit"] and summary["stage_seconds"]["refit"] > 0
    log = json.loads((run / "train_log.json").read_text())["history"]
    refits = [e for e in log if e["stage"] == "refit"]
    scene = load_scene(json.loads((run / "run.json").read_text())["scene"])
    train = [int(t) for t in scene.split["train"]]
    assert [e["frame"] for e in refits] == train

    hb, ha = before["branches"]["human"], after["branches"]["human"]
    moved = (ha["frame_pose_delta"] - hb["frame_pose_delta"]).abs().amax(dim=(1, 2))
    held_out = [t for t in range(len(moved)) if t not in train]
    assert (moved[train] > 0).all() and (moved[held_out] == 0).all()
    for k in hb:
        if k not in ("frame_pose_delta", "frame_transl_delta"):
            torch.testing.assert_close(ha[k], hb[k], rtol=0, atol=0, msg=k)
    for b in ("object", "scene"):
        for k, v in before["branches"][b].items():
            torch.testing.assert_close(after["branches"][b][k], v, rtol=0, atol=0, msg=f"{b}.{k}")


def test_fit_of_a_person_out_of_view_changes_nothing(unrefitted):
    """A camera turned away from the person: no pixel depends on the pose, so the fit
    returns a zero correction and a finite, unchanged image loss."""
    model, _, scene = load_run(unrefitted)
    t = int(scene.split["train"][0])
    vm, K, img = _frame(scene, t)
    away = vm.clone()
    away[:3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0])) @ vm[:3]  # half a turn about the camera's y axis
    fit = fit_frame_pose(model, img, away, K, t, PoseRefit(steps=5))
    assert torch.count_nonzero(fit.dpose) == 0 and torch.count_nonzero(fit.dtransl) == 0
    assert fit.loss_first == fit.loss_last and 0 < fit.loss_first < 1
