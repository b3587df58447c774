"""Six-stage training, density control, checkpoints and resume, evaluation, the demo."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from cogs.cli import main
from cogs.config import apply_overrides, quick_config
from cogs.train import checkpoint as ckpt
from tests.fixtures import TINY


def _train(scene_dir: Path, out: Path, extra: list[str] = ()) -> None:
    assert main(["train", "--scene", str(scene_dir), "--out", str(out), "--set", *TINY, *extra]) == 0


def test_six_stages_train_evaluate_and_export(small_synthetic, tmp_path):
    run = tmp_path / "run"
    _train(small_synthetic, run)
    names = sorted(p.name for p in (run / "checkpoints").iterdir())
    for s in ("I", "II", "III", "IV", "V", "VI"):
        assert f"stage_{s}.pt" in names
    log = json.loads((run / "train_log.json").read_text())
    assert {h["stage"] for h in log["history"]} == {"I", "II", "III", "IV", "V", "VI", "refit"}
    assert all(np.isfinite(h["loss"]) for h in log["history"])
    assert (run / "final" / "human_canonical.ply").exists() and (run / "final" / "scene.ply").exists()
    assert main(["eval", "--run", str(run)]) == 0
    m = json.loads((run / "eval" / "metrics.json").read_text())
    assert m["protocol"] == "hosnerf-16" and m["n_test_frames"] == 8
    for key in ("full", "human_crop", "object_crop", "novel_view", "decomposition", "object_pose_error",
                "train_seconds", "stage_seconds", "n_gaussians", "notes"):
        assert key in m, key
    assert 5 < m["full"]["psnr"] < 60 and 0 < m["full"]["ssim"] <= 1
    # One row per held-out frame, and the top-level numbers are their means.
    rows = m["per_frame"]
    assert len(rows) == 8 and len({r["frame"] for r in rows}) == 8
    for group in ("full", "human_crop", "object_crop"):
        vals = [r[group]["psnr"] for r in rows if r[group] is not None]
        assert vals and abs(np.mean(vals) - m[group]["psnr"]) < 1e-9, group
    assert 0 <= m["decomposition"]["human_iou"] <= 1
    nv = m["novel_view"]  # the rings round the person: silhouettes and the human's crop
    assert nv["n_views"] > 0 and 0 < nv["human_iou"] <= 1 and 0 <= nv["object_iou"] <= 1
    assert 5 < nv["human_crop"]["psnr"] < 60
    assert m["object_pose_error"]["rotation_deg"] >= 0
    bpe = m["body_pose_error"]["joint_px"]
    assert set(bpe) == {"input_train", "input_test", "fitted_train", "fitted_test"}
    assert bpe["input_train"] > 0.2  # the scene's input poses carry the synthetic noise
    assert all(np.isfinite(v) and v >= 0 for v in bpe.values()) and bpe["fitted_train"] != bpe["input_train"]
    assert set(m["stage_seconds"]) == {"I", "II", "III", "IV", "V", "VI", "refit"}
    assert m["stages"] == ["I", "II", "III", "IV", "V", "VI", "refit"]
    if m["full"]["lpips"] is None:
        assert any("lpips" in n for n in m["notes"])  # a null always says why
    assert (run / "eval" / "renders").is_dir()


def test_single_stage_ablation_trains_all_branches_jointly(small_synthetic, tmp_path):
    run = tmp_path / "joint"
    _train(small_synthetic, run, ["schedule.single_stage=true"])
    log = json.loads((run / "train_log.json").read_text())
    assert {h["stage"] for h in log["history"]} == {"joint", "refit"}
    assert all(h["human"] > 0 and h["object"] > 0 and h["scene"] > 0 for h in log["history"])


def _state(run: Path) -> dict:
    return ckpt.load(run / "checkpoints" / "last.pt")["branches"]


def test_compositional_stages_can_hold_the_fitted_body_poses(small_synthetic, tmp_path):
    """compose_pose_lr_scale=0: V and VI leave the pose corrections where stage II put them
    while the rest of the human keeps training."""
    run = tmp_path / "held"
    _train(small_synthetic, run, ["compose_pose_lr_scale=0.0"])
    after_ii = ckpt.load(run / "checkpoints" / "stage_II.pt")["branches"]["human"]
    after_vi = ckpt.load(run / "checkpoints" / "stage_VI.pt")["branches"]["human"]
    for k in ("pose_delta", "frame_pose_delta", "transl_delta", "frame_transl_delta"):
        assert after_ii[k].abs().max() > 0, k  # the human stages did fit them
        torch.testing.assert_close(after_vi[k], after_ii[k], rtol=0, atol=0, msg=k)
    assert not torch.equal(after_vi["color_residual"], after_ii["color_residual"])


def test_human_stages_can_hold_the_canonical_positions(small_synthetic, tmp_path):
    """human_stage_means_lr_scale=0: stages I-II move the poses but not the canonical
    positions (they stay the seed's); V-VI train them."""
    run = tmp_path / "means_held"
    _train(small_synthetic, run, ["human_stage_means_lr_scale=0.0"])
    after_ii = ckpt.load(run / "checkpoints" / "stage_II.pt")["branches"]["human"]
    after_vi = ckpt.load(run / "checkpoints" / "stage_VI.pt")["branches"]["human"]
    torch.testing.assert_close(after_ii["means"], after_ii["seed_means"], rtol=0, atol=0)
    assert after_ii["pose_delta"].abs().max() > 0
    n = len(after_ii["means"])  # V-VI clone human Gaussians after the seed's rows
    assert not torch.equal(after_vi["means"][:n], after_ii["means"])


def test_killed_run_resumes_to_the_same_parameters(small_synthetic, tmp_path):
    """SIGKILL a training process in the middle of stage III; `cogs train --resume` ends
    with exactly the parameters of an uninterrupted run."""
    ref = tmp_path / "ref"
    _train(small_synthetic, ref)
    run = tmp_path / "killed"
    cmd = [sys.executable, "-m", "cogs.cli", "train", "--scene", str(small_synthetic), "--out", str(run), "--set", *TINY]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    info = run / "checkpoints" / "last.json"
    deadline = time.time() + 600
    try:
        while time.time() < deadline:
            if info.exists():
                try:
                    where = json.loads(info.read_text())
                except json.JSONDecodeError:
                    where = {}
                if where.get("stage") == 2 and where.get("step", 0) > 0:  # mid stage III
                    break
            if proc.poll() is not None:
                pytest.fail("training finished before it could be killed mid-stage")
            time.sleep(0.05)
        else:
            pytest.fail("no mid-stage-III checkpoint within the deadline")
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not (run / "train_summary.json").exists()
    assert main(["train", "--scene", str(small_synthetic), "--out", str(run), "--resume"]) == 0
    a, b = _state(ref), _state(run)
    for branch in ("human", "object", "scene"):
        assert a[branch].keys() == b[branch].keys()
        for k in a[branch]:
            assert a[branch][k].shape == b[branch][k].shape, (branch, k)
            torch.testing.assert_close(a[branch][k], b[branch][k], rtol=1e-6, atol=1e-6, msg=f"{branch}.{k}")


def test_resume_without_a_checkpoint_is_a_clear_error(small_synthetic, tmp_path, capsys):
    assert main(["train", "--scene", str(small_synthetic), "--out", str(tmp_path / "none"), "--resume"]) == 2
    err = capsys.readouterr().err
    assert "no config.yaml" in err and "Traceback" not in err


def test_bad_override_is_a_clear_error(small_synthetic, tmp_path, capsys):
    assert main(["train", "--scene", str(small_synthetic), "--out", str(tmp_path / "r"), "--set", "schedule.VII=3"]) == 2
    assert "no field 'VII'" in capsys.readouterr().err


def test_print_config_shows_the_resolved_preset(capsys, tmp_path):
    assert main(["train", "--scene", str(tmp_path), "--out", str(tmp_path / "r"), "--print-config",
                 "--set", "schedule.I=7"]) == 0
    out = capsys.readouterr().out
    assert "preset: quick" in out and "I: 7" in out


def test_checkpoints_load_without_unpickling_code(small_synthetic, tmp_path):
    run = tmp_path / "run"
    _train(small_synthetic, run, ["schedule.III=0", "schedule.IV=0", "schedule.V=2", "schedule.VI=2"])
    raw = torch.load(run / "checkpoints" / "last.pt", weights_only=True)  # raises on arbitrary objects
    assert "branches" in raw
    cfg = apply_overrides(quick_config(), TINY)
    assert cfg.schedule.I == 6


def test_unknown_ablation_is_refused_before_any_work(tmp_path, capsys):
    out = tmp_path / "abl"
    assert main(["ablate", "--out", str(out), "--only", "no such component"]) == 2
    assert "unknown ablation(s) ['no such component']" in capsys.readouterr().err
    assert not out.exists()  # no scene synthesized, no run started
    assert main(["ablate", "--out", str(out), "--seeds", "0", "0"]) == 2
    assert "--seeds must be distinct" in capsys.readouterr().err
    assert not out.exists()


def test_ablation_over_two_seeds_keeps_each_run_and_averages_them(small_synthetic, tmp_path):
    """`--seeds 0 1`: seed 0's run keeps the one-seed layout, seed 1's lands beside it
    with seed=1 in its config; the row is the mean of the two evaluations."""
    from cogs.eval.ablation import run_ablation

    out = tmp_path / "abl"
    rows = run_ablation(small_synthetic, out, "quick", {"full": TINY}, seeds=(0, 1))
    for seed, run in ((0, out / "full"), (1, out / "full.seed1")):
        assert (run / "eval" / "metrics.json").exists()
        assert f"\nseed: {seed}\n" in (run / "config.yaml").read_text()
    per = rows["full"]["seeds"]
    assert set(per) == {"0", "1"}
    p0, p1 = per["0"]["full"]["psnr"], per["1"]["full"]["psnr"]
    assert p0 != p1  # the seed reached the training
    assert rows["full"]["metrics"]["full"]["psnr"] == pytest.approx((p0 + p1) / 2)
    assert json.loads((out / "ablation.json").read_text())["full"]["seeds"].keys() == {"0", "1"}
    assert f"{(p0 + p1) / 2:.3f} ± {abs(p0 - p1) / 2:.3f}" in (out / "ablation.md").read_text()
    # A second call reuses both finished runs: nothing is trained again.
    stamp = (out / "full.seed1" / "train_summary.json").stat().st_mtime_ns
    run_ablation(small_synthetic, out, "quick", {"full": TINY}, seeds=(0, 1))
    assert (out / "full.seed1" / "train_summary.json").stat().st_mtime_ns == stamp


def test_ablation_table_stars_only_what_lies_beyond_the_seed_spread():
    from cogs.eval.ablation import table_rows

    def m(psnr, iou, secs):
        return {"full": {"psnr": psnr, "ssim": 0.9, "lpips": None}, "decomposition": {"human_iou": iou},
                "train_seconds": secs}

    rows = {
        "full": {"overrides": [], "seeds": {"0": m(31.0, 0.90, 600), "1": m(30.0, 0.89, 610)}},
        "worse": {"overrides": ["x"], "seeds": {"0": m(29.5, 0.895, 300), "1": m(29.0, 0.88, 310)}},
    }
    full, worse = table_rows(rows)
    assert full["psnr"] == pytest.approx(30.5) and full["spread"]["psnr"] == pytest.approx(0.5)
    assert worse["psnr"] == pytest.approx(29.25) and worse["n_seeds"] == 2
    # [29, 29.5] misses [30, 31]; [0.88, 0.895] meets [0.89, 0.9]; a training time is no measure
    assert worse["beyond_spread"] == ["psnr"] and worse["train_s"] == pytest.approx(305)
    assert full["beyond_spread"] == [] and worse["lpips"] is None and worse["delta_lpips"] is None
    # A row written before seeds were counted (metrics only) is one seed: nothing starred.
    old = table_rows({"full": {"metrics": m(31.0, 0.9, 600)}, "worse": {"metrics": m(20.0, 0.5, 300)}})
    assert [r["n_seeds"] for r in old] == [1, 1] and old[1]["beyond_spread"] == []


def test_an_optimizer_resumed_on_the_host_drops_the_gpus_fused_update():
    """A checkpoint written on CUDA carries Adam's `fused` flag; the host resumes it with
    its own (unfused) update, and keeps stepping from the saved moments."""
    from cogs.train.trainer import adopt_fusion, make_adam

    p = torch.nn.Parameter(torch.randn(6, generator=torch.Generator().manual_seed(0)))
    writer = torch.optim.Adam([{"params": [p], "lr": 0.1}], eps=1e-15, fused=True)  # as a GPU run saves it
    p.grad = torch.ones(6)
    writer.step()
    q = torch.nn.Parameter(p.detach().clone())
    reader = make_adam([{"params": [q], "lr": 0.1}], torch.device("cpu"))
    assert not reader.param_groups[0]["fused"]
    reader.load_state_dict(writer.state_dict())
    adopt_fusion(reader, torch.device("cpu"))
    assert not reader.param_groups[0]["fused"]
    q.grad = torch.ones(6)
    reader.step()
    assert float(reader.state[q]["step"]) == 2.0
    assert torch.allclose(reader.state[q]["exp_avg"], torch.full((6,), 0.19))  # 0.9 * 0.1 + 0.1
