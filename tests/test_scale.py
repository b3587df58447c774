"""Sequences at real size: training at a reduced resolution, and a run too large for the
memory refused before it starts."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cogs.cli import main
from cogs.data.scene import load_scene
from cogs.geometry.camera import project_points
from tests.fixtures import TINY


def test_a_scene_loaded_at_a_reduced_size_keeps_its_geometry(small_synthetic):
    full = load_scene(small_synthetic)
    half = load_scene(small_synthetic, max_side=48)
    assert (half.width, half.height) == (48, 36) and half.full_size == (96, 72)
    assert half.images.shape == (16, 36, 48, 3) and half.human_masks.shape == (16, 36, 48)
    assert half.gt.human_masks.shape == (16, 36, 48) and half.gt.novel.images.shape[1:3] == (36, 48)
    X = full.points_xyz[:20].astype(np.float64)
    for t in (0, 9):
        a, _ = project_points(X, full.cameras.world_to_camera[t], full.cameras.K[t])
        b, _ = project_points(X, half.cameras.world_to_camera[t], half.cameras.K[t])
        assert np.allclose(b, a * 0.5, atol=1e-9)
    # pixels: the mean colour of each 2x2 block
    block = full.images[3].reshape(36, 2, 48, 2, 3).mean((1, 3))
    assert np.abs(half.images[3].astype(float) - block).max() <= 1.0
    nofit = load_scene(small_synthetic, max_side=200)
    assert (nofit.width, nofit.height) == (96, 72) and nofit.full_size is None


def test_training_at_a_reduced_resolution_evaluates_there_unless_asked(small_synthetic, tmp_path):
    run = tmp_path / "run"
    assert main(["train", "--scene", str(small_synthetic), "--out", str(run), "--max-side", "48", "--set", *TINY]) == 0
    info = json.loads((run / "run.json").read_text())
    assert info["max_side"] == 48 and info["size"] == [48, 36] and info["fingerprint"]["width"] == 96
    assert main(["eval", "--run", str(run), "--no-renders", "--pose-fit-steps", "0"]) == 0
    m = json.loads((run / "eval" / "metrics.json").read_text())
    assert m["resolution"] == [48, 36] and 5 < m["full"]["psnr"] < 60
    assert main(["eval", "--run", str(run), "--no-renders", "--pose-fit-steps", "0", "--full-resolution",
                 "--out", str(tmp_path / "full")]) == 0
    f = json.loads((tmp_path / "full" / "metrics.json").read_text())
    assert f["resolution"] == [96, 72] and 5 < f["full"]["psnr"] < 60
    # --resume keeps the run's resolution; asking another is an error
    assert main(["train", "--scene", str(small_synthetic), "--out", str(run), "--resume", "--max-side", "64"]) == 2


def test_a_run_too_large_for_the_memory_is_refused_before_it_starts(small_synthetic, tmp_path, monkeypatch, capsys):
    from cogs.train.memory import estimate
    from cogs.config import quick_config

    need = estimate(16, 96, 72, quick_config()).total
    monkeypatch.setenv("COGS_MEMORY_GB", f"{0.95 * need / 1024**3:.4f}")
    out = tmp_path / "run"
    assert main(["train", "--scene", str(small_synthetic), "--out", str(out)]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "training 16 frames of 96x72 needs about" in err and "GiB available" in err and "fewer frames" in err
    assert not out.exists()
    monkeypatch.setenv("COGS_MEMORY_GB", f"{1.05 * need / 1024**3:.4f}")  # just enough: it trains
    assert main(["train", "--scene", str(small_synthetic), "--out", str(out), "--set", *TINY]) == 0


def test_the_estimate_grows_with_the_pixels_held_and_rendered():
    from cogs.config import quick_config
    from cogs.train.memory import estimate

    cfg = quick_config()
    a, b, c = estimate(100, 256, 192, cfg), estimate(600, 256, 192, cfg), estimate(100, 1024, 768, cfg)
    assert b.frame_bytes == 6 * a.frame_bytes and b.step_bytes == a.step_bytes
    assert c.step_bytes == 16 * a.step_bytes and c.frame_bytes == 16 * a.frame_bytes
    assert a.gaussian_bytes == b.gaussian_bytes == c.gaussian_bytes > 0


@pytest.mark.parametrize("value", ["8", "-5"])
def test_max_side_too_small_is_refused(small_synthetic, tmp_path, value, capsys):
    assert main(["train", "--scene", str(small_synthetic), "--out", str(tmp_path / "r"), "--max-side", value]) == 2
    assert "--max-side must be at least 32" in capsys.readouterr().err and not (tmp_path / "r").exists()


def test_the_refusal_names_the_resolution_that_fits(monkeypatch):
    from cogs.config import quick_config
    from cogs.errors import UserError
    from cogs.train.memory import GiB, check_fits, estimate

    cfg = quick_config()
    big = estimate(600, 1024, 1024, cfg)
    monkeypatch.setenv("COGS_MEMORY_GB", str(0.6 * big.total / GiB))
    with pytest.raises(UserError) as e:
        check_fits(600, 1024, 1024, cfg, "scene")
    side = int(str(e.value).split("--max-side ")[1].split()[0])
    assert 32 <= side < 1024 and estimate(600, side, side, cfg).total <= 0.6 * big.total
