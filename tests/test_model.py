"""The trained model apart from the trainer: it loads from a run folder without the scene's
images, renders any frame, and no tensor of the method is made on an implicit device."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from cogs.cli import main
from cogs.config import apply_overrides, quick_config
from cogs.data.scene import load_scene
from cogs.model import Model
from tests.fixtures import TINY


@pytest.fixture(scope="module")
def tiny_run(small_synthetic, tmp_path_factory) -> Path:
    """A tiny run trained on a copy of the small synthetic scene (so the test may delete its images)."""
    base = tmp_path_factory.mktemp("model")
    scene = base / "scene"
    shutil.copytree(small_synthetic, scene)
    run = base / "run"
    assert main(["train", "--scene", str(scene), "--out", str(run), "--set", *TINY]) == 0
    return run


def _camera(scene, t):
    return (torch.as_tensor(scene.cameras.world_to_camera[t], dtype=torch.float32),
            torch.as_tensor(scene.cameras.K[t], dtype=torch.float32))


def test_model_loads_and_renders_without_the_scene_images(tiny_run):
    scene_dir = Path(json.loads((tiny_run / "run.json").read_text())["scene"])
    scene = load_scene(scene_dir)
    t = int(scene.split["test"][0])
    vm, K = _camera(scene, t)
    with torch.no_grad():
        before = Model.load(tiny_run).render(vm, K, scene.width, scene.height, t)
    shutil.rmtree(scene_dir / "images")
    shutil.rmtree(scene_dir / "masks")
    model = Model.load(tiny_run, device="cpu")
    assert model.available() == ("human", "object", "scene")
    with torch.no_grad():
        after = model.render(vm, K, scene.width, scene.height, t)
        alone = model.render(vm, K, scene.width, scene.height, t, branches=("human",))
    torch.testing.assert_close(after.rgb, before.rgb, rtol=0, atol=0)
    assert float(after.alpha.mean()) > 0.1 and torch.isfinite(after.rgb).all()
    assert float(alone.branch_alpha["human"].sum()) > 0 and float(alone.branch_alpha["scene"].sum()) == 0
    # A new body pose renders another picture: the model poses, not replays.
    pose, transl = model.human.frame_pose(t)
    with torch.no_grad():
        moved = model.render(vm, K, scene.width, scene.height, t, poses={"human": (pose, transl + 0.1)})
    assert not torch.equal(moved.rgb, after.rgb)


def test_a_model_with_the_runs_tensors_renders_what_the_trainer_left(tiny_run, small_synthetic):
    """The loaded branches hold every tensor of the last checkpoint, bit for bit."""
    from cogs.train import checkpoint as ckpt

    saved = ckpt.load(tiny_run / "checkpoints" / "last.pt")["branches"]
    model = Model.load(tiny_run)
    for name, state in saved.items():
        mine = model.get(name).state_dict()
        assert mine.keys() == state.keys(), name
        for k, v in state.items():
            assert torch.equal(mine[k], v), f"{name}.{k}"


def _adam_keeps_its_step_on_the_host_under_a_default_device() -> bool:
    """torch 2.11's Adam (not 2.13's) creates a host parameter's step count on the default
    device, so under "meta" its first step fails inside torch, not in cogs (seen on the
    device machine, docs/experiments/2026-12-04-the-cuda-paths-after-a-week.md)."""
    p = torch.nn.Parameter(torch.zeros(1, device="cpu"))
    p.grad = torch.ones(1, device="cpu")
    torch.set_default_device("meta")
    try:
        torch.optim.Adam([p]).step()
        return True
    except RuntimeError:
        return False
    finally:
        torch.set_default_device(None)


@pytest.mark.skipif(not _adam_keeps_its_step_on_the_host_under_a_default_device(),
                    reason=f"torch {torch.__version__}'s Adam makes its step count on the default device (later torch: on the host)")
def test_every_stage_and_the_refit_make_no_tensor_on_an_implicit_device(small_synthetic, tmp_path, body_model):
    """With the default device set to "meta", any tensor the method creates without an
    explicit device lands on meta and fails when it meets the model's CPU tensors: a few
    steps of every stage, density control and the refit run clean."""
    from cogs.train.trainer import Trainer

    cfg = apply_overrides(quick_config(), [
        *TINY, "schedule.I=3", "schedule.II=3", "schedule.III=3", "schedule.IV=3", "schedule.V=3", "schedule.VI=4",
        "human_density.refine_every=1", "object_density.refine_every=1", "scene_density.refine_every=1",
        "weights.plane_warmup_fraction=0.25", "refit.steps=2", "visibility_every=2", "plane_assign_every=2",
    ])
    scene = load_scene(small_synthetic)
    body_model.canonical(torch.as_tensor(scene.body.shape, dtype=torch.float32))  # the third-party rig, built before
    torch.set_default_device("meta")
    try:
        assert torch.empty(1).device.type == "meta"
        trainer = Trainer(scene, cfg, tmp_path / "run", show_progress=False, device="cpu")
        summary = trainer.run()
    finally:
        torch.set_default_device(None)
    assert summary["stages"] == ["I", "II", "III", "IV", "V", "VI", "refit"]
    assert trainer.model.device.type == "cpu"
    events = {e["branch"] for e in trainer.state.density_events}
    assert events == {"human", "object", "scene"}
    assert all(p.device.type == "cpu" for p in trainer.model.parameters())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (runs where one is lent)")
def test_training_and_rendering_on_cuda(small_synthetic, tmp_path):
    """Every stage and the refit with the model on the GPU (gsplat), then the model loads
    on either device and renders the same picture within gsplat's tolerance."""
    run = tmp_path / "run"
    assert main(["train", "--scene", str(small_synthetic), "--out", str(run), "--device", "cuda", "--set", *TINY]) == 0
    summary = json.loads((run / "train_summary.json").read_text())
    assert summary["stages"][-1] == "refit"
    scene = load_scene(small_synthetic)
    vm, K = _camera(scene, 0)
    with torch.no_grad():
        on_gpu = Model.load(run, device="cuda").render(vm.cuda(), K.cuda(), scene.width, scene.height, 0)
        on_cpu = Model.load(run, device="cpu").render(vm, K, scene.width, scene.height, 0)
    assert on_gpu.rgb.device.type == "cuda"
    assert (on_gpu.rgb.cpu() - on_cpu.rgb).abs().mean() < 2e-3
    assert main(["eval", "--run", str(run), "--device", "cuda", "--no-renders", "--pose-fit-steps", "2"]) == 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (runs where one is lent)")
def test_on_cuda_adam_is_fused_and_a_host_checkpoint_resumes_fused():
    from cogs.train.trainer import adopt_fusion, make_adam

    cuda = torch.device("cuda")
    p = torch.nn.Parameter(torch.randn(6))
    host = make_adam([{"params": [p], "lr": 0.1}], torch.device("cpu"))
    p.grad = torch.ones(6)
    host.step()
    q = torch.nn.Parameter(p.detach().to(cuda))
    gpu = make_adam([{"params": [q], "lr": 0.1}], cuda)
    assert gpu.param_groups[0]["fused"]
    gpu.load_state_dict(host.state_dict())
    adopt_fusion(gpu, cuda)
    q.grad = torch.ones(6, device=cuda)
    gpu.step()
    assert gpu.param_groups[0]["fused"] and float(gpu.state[q]["step"]) == 2.0
    assert torch.allclose(gpu.state[q]["exp_avg"].cpu(), torch.full((6,), 0.19))
