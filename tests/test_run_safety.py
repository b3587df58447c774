"""A run folder is never overwritten silently, a damaged checkpoint is named with the
newest good one beside it, and evaluation refuses a scene the run did not train on."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest

from cogs.cli import main
from tests.fixtures import TINY


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha1(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def finished(small_synthetic, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("safety") / "run"
    assert main(["train", "--scene", str(small_synthetic), "--out", str(run), "--set", *TINY]) == 0
    return run


@pytest.fixture
def run(finished, tmp_path) -> Path:
    copy = tmp_path / "run"
    shutil.copytree(finished, copy)
    return copy


def test_a_finished_run_is_not_trained_over_without_resume_or_overwrite(run, small_synthetic, capsys):
    before = _digest(run)
    assert main(["train", "--scene", str(small_synthetic), "--out", str(run), "--set", *TINY]) == 2
    err = capsys.readouterr().err
    assert "finished run" in err and "--resume" in err and "--overwrite" in err and "Traceback" not in err
    assert _digest(run) == before


def test_overwrite_replaces_the_earlier_run_and_says_what_it_removed(run, small_synthetic, capsys):
    old = (run / "checkpoints" / "last.pt").stat().st_mtime_ns
    (run / "final" / "stale.txt").write_text("left by the old run")
    assert main(["train", "--scene", str(small_synthetic), "--out", str(run), "--overwrite",
                 "--set", *TINY, "schedule.VI=2"]) == 0
    err = capsys.readouterr().err
    assert "removed the earlier run's" in err and "checkpoints" in err
    assert not (run / "final" / "stale.txt").exists()
    assert (run / "checkpoints" / "last.pt").stat().st_mtime_ns != old
    assert "VI: 2" in (run / "config.yaml").read_text()


def test_a_folder_with_other_files_is_refused_even_with_overwrite(small_synthetic, tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("the user's")
    assert main(["train", "--scene", str(small_synthetic), "--out", str(out), "--overwrite", "--set", *TINY]) == 2
    assert "not a cogs run (notes.txt)" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_overwrite_is_checked_before_anything_is_removed(run, capsys):
    """A bad scene or option stops --overwrite before it removes the earlier run."""
    before = _digest(run)
    assert main(["train", "--scene", str(run / "no_scene_here"), "--out", str(run), "--overwrite"]) == 2
    assert _digest(run) == before
    assert main(["train", "--scene", str(run), "--out", str(run), "--overwrite", "--device", "tpu"]) == 2
    assert "--device 'tpu'" in capsys.readouterr().err
    assert _digest(run) == before


def test_a_damaged_checkpoint_is_named_with_the_newest_good_one(run, small_synthetic, capsys):
    last = run / "checkpoints" / "last.pt"
    last.write_bytes(last.read_bytes()[: len(last.read_bytes()) // 3])  # truncated mid-write
    (run / "train_summary.json").unlink()  # as if it died before finishing
    assert main(["train", "--scene", str(small_synthetic), "--out", str(run), "--resume"]) == 2
    err = capsys.readouterr().err
    assert "checkpoints/last.pt: not a readable cogs checkpoint" in err and "Traceback" not in err
    assert "--checkpoint stage_" in err
    good = err.split("newest readable checkpoint beside it is ")[1].split(":")[0]
    assert main(["eval", "--run", str(run), "--no-renders", "--pose-fit-steps", "0"]) == 2
    assert "not a readable cogs checkpoint" in capsys.readouterr().err
    assert main(["eval", "--run", str(run), "--no-renders", "--pose-fit-steps", "0", "--checkpoint", good]) == 0
    assert main(["train", "--scene", str(small_synthetic), "--out", str(run), "--resume", "--checkpoint", good]) == 0
    assert json.loads((run / "train_summary.json").read_text())["stages"][-1] == "refit"


def test_eval_refuses_a_scene_the_run_did_not_train_on(run, tmp_path, capsys):
    from cogs.data.scene import load_scene, save_scene

    other = load_scene(json.loads((run / "run.json").read_text())["scene"])
    other.split = {"train": other.split["train"][:-1], "test": other.split["test"] + other.split["train"][-1:]}
    save_scene(other, tmp_path / "other")
    assert main(["eval", "--run", str(run), "--scene", str(tmp_path / "other"), "--no-renders",
                 "--pose-fit-steps", "0"]) == 2
    err = capsys.readouterr().err
    assert "trained on another scene" in err and "split_sha1" in err
    assert not (run / "eval").exists()


def test_eval_of_a_moved_scene_hints_at_scene_and_accepts_it(run, tmp_path, capsys):
    info = json.loads((run / "run.json").read_text())
    moved = tmp_path / "moved"
    shutil.copytree(info["scene"], moved)
    (run / "run.json").write_text(json.dumps({**info, "scene": str(tmp_path / "gone")}))
    assert main(["eval", "--run", str(run), "--no-renders", "--pose-fit-steps", "0"]) == 2
    assert "pass it with --scene" in capsys.readouterr().err
    assert main(["eval", "--run", str(run), "--scene", str(moved), "--no-renders", "--pose-fit-steps", "0"]) == 0
    (run / "run.json").unlink()
    assert main(["eval", "--run", str(run), "--no-renders", "--pose-fit-steps", "0"]) == 2
    assert "has no run.json" in capsys.readouterr().err
