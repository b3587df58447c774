"""`cogs batch`: the manifest is checked whole before any work; on real local Ray every
entry gets a row (a broken one with its error), and a re-run does only what is unfinished."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import pytest
import yaml

from cogs.batch.manifest import parse_manifest, read_manifest
from cogs.batch.results import COLUMNS, markdown, mean_row
from cogs.cli import main
from cogs.errors import UserError
from tests.fixtures import TINY
from tests.test_importers import motion, write_humannerf  # noqa: F401 (motion is a fixture)

SMALL = {"frames": 16, "width": 96, "height": 72, "points": 1500}


def _write(path: Path, doc: dict) -> Path:
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def test_a_manifest_is_checked_whole_before_any_work(tmp_path, capsys):
    (tmp_path / "scene_a").mkdir()
    manifest = _write(tmp_path / "m.yaml", {"sequences": [
        {"name": "a", "scene": "scene_a", "trian": {}},                       # a typo'd key
        {"name": "a", "scene": "scene_a"},                                    # a second `a`
        {"video": "missing.mp4", "preprocess": {"strid": 2}},                 # no file, unknown option
        {"synth": {"seed": "one"}, "train": {"set": ["no.such=1"]}},          # wrong type, bad override
        {"scene": "scene_a", "import": {"body_model": "anny"}},               # import: is not a scene's
        {"synth": {}, "neuman": "scene_a"},                                   # two sources
    ]})
    with pytest.raises(UserError) as e:
        read_manifest(manifest)
    msg = str(e.value)
    for expected in ["sequences[0] (a): unknown key 'trian'", "sequences[1] (a): name 'a' is also sequences[0]'s",
                     "missing.mp4 does not exist", "unknown option 'strid'", "synth.seed: 'one' is not an integer",
                     "`no` is not a setting", "`import:` options belong to neuman / humannerf",
                     "needs exactly one source"]:
        assert expected in msg, (expected, msg)
    out = tmp_path / "out"
    assert main(["batch", str(manifest), "--out", str(out)]) == 2
    assert "problem(s)" in capsys.readouterr().err
    assert not out.exists()


def test_defaults_apply_to_every_entry_and_the_entrys_own_options_win(tmp_path):
    doc = {"defaults": {"synth": {**SMALL, "seed": 3}, "train": {"preset": "quick", "set": ["schedule.I=5"]},
                        "eval": {"pose_fit_steps": 0}},
           "sequences": [{"synth": None},
                         {"synth": {"seed": 4}, "train": {"set": ["schedule.I=7"]}, "eval": {"renders": False}},
                         {"synth": {"variant": 2}}]}
    problems: list[str] = []
    a, b, c = parse_manifest(doc, tmp_path, problems)
    assert not problems
    assert (a.name, a.options["seed"], a.options["frames"]) == ("synth_seed3", 3, 16)
    assert (b.name, b.options["seed"]) == ("synth_seed4", 4)
    assert (c.name, c.options["seed"], c.options["variant"]) == ("synth_seed3_variant2", 3, 2)  # another video
    assert b.overrides == ("schedule.I=5", "schedule.I=7")  # the entry's override comes last and wins
    assert a.eval == {"pose_fit_steps": 0, "renders": True} and b.eval == {"pose_fit_steps": 0, "renders": False}


def test_a_video_entry_takes_one_object_box_or_one_per_frame_and_negative_boxes(tmp_path):
    from cogs.preprocess.command import Preprocess

    (tmp_path / "clip.mp4").write_bytes(b"not read here")
    doc = {"sequences": [
        {"name": "one", "video": "clip.mp4", "preprocess": {"object_box": [410, 300, 520, 420], "object_box_frame": 5}},
        {"name": "several", "video": "clip.mp4", "preprocess": {"object_box": [[0, 410, 300, 520, 420], [30, 400, 310, 500, 430]],
                                                                 "object_negative_box": [[12, 0, 0, 50, 50]]}},
        {"name": "bad", "video": "clip.mp4", "preprocess": {"object_box": "around the ball"}},
    ]}
    problems: list[str] = []
    one, several = parse_manifest(doc, tmp_path, problems)
    assert problems == ["sequences[2] (bad): preprocess.object_box: 'around the ball' is not a list of numbers or "
                        "a list of lists of numbers or null"]
    prompts = [Preprocess(input=e.source, out=tmp_path / e.name, **e.options).object_prompts() for e in (one, several)]
    assert [(p.frame, p.box) for p in prompts[0][0]] == [(5, (410.0, 300.0, 520.0, 420.0))]
    assert [p.frame for p in prompts[1][0]] == [0, 30] and [(n.frame, n.box) for n in prompts[1][1]] == [(12, (0.0, 0.0, 50.0, 50.0))]


def test_the_mean_row_averages_the_finished_entries_and_missing_numbers_show_as_dashes():
    def row(name, status, psnr, lpips=None, error=None):
        r = {c: None for c in COLUMNS}
        r.update(name=name, status=status, error=error, full_psnr=psnr, full_lpips=lpips, train_seconds=10.0)
        return r

    rows = [row("a", "done", 30.0), row("b", "done", 32.0, lpips=0.1), row("c", "failed", None, error="prepare: x|y")]
    mean = mean_row(rows)
    assert mean["full_psnr"] == 31.0 and mean["full_lpips"] == 0.1 and mean["status"] == "2/3 done"
    md = markdown(rows, mean, "t")
    assert "| a | 30.00 | — |" in md and "| **mean** | 31.00 |" in md
    assert "failed [1]" in md and "1. c: prepare: x\\|y" in md


def test_a_dataset_entry_is_imported_into_its_folder_whole(tmp_path, motion):
    """The prepare step of a `humannerf:` entry, without Ray: the importer writes beside the
    scene folder, which then appears complete, and the step checks it."""
    from cogs.batch.steps import prepare

    joints, w2c = motion
    write_humannerf(tmp_path / "subject", joints, w2c)
    doc = {"sequences": [{"humannerf": "subject", "import": {"body_model": "anny"}}]}
    [entry] = parse_manifest(doc, tmp_path, problems := [])
    assert not problems and entry.name == "subject"
    edir, stages = tmp_path / "out" / entry.name, []
    assert prepare(entry, edir, stages.append) == {"scene": str(edir / "scene")}
    assert stages == ["import humannerf", "check"]
    assert sorted(p.name for p in edir.iterdir()) == ["scene"]  # no partial folder left
    assert (edir / "scene" / "scene.json").is_file()


def _rows(out: Path) -> dict[str, dict]:
    with open(out / "results.csv") as f:
        return {r["name"]: r for r in csv.DictReader(f)}


def _mtimes(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_a_batch_records_every_entry_and_a_rerun_does_only_the_unfinished_work(tmp_path):
    """Two tiny synthetic entries and a broken one on real local Ray. Then: one entry's
    training is set back to its state after stage IV (as if killed there), and the same
    command again finishes only that (resuming at stage V), evaluates it again, leaves
    the other finished entry untouched and records the broken one's error again."""
    pytest.importorskip("ray", reason="ray is in the optional `batch` extra (make test installs it)")
    broken = tmp_path / "broken_scene"
    broken.mkdir()
    (broken / "scene.json").write_text("{}")
    doc = {"defaults": {"synth": SMALL, "train": {"set": TINY}, "eval": {"pose_fit_steps": 0, "renders": False}},
           "sequences": [{"synth": {"seed": 0}}, {"synth": {"seed": 1}}, {"name": "broken", "scene": "broken_scene"}]}
    manifest = _write(tmp_path / "m.yaml", doc)
    out = tmp_path / "out"
    cmd = ["batch", str(manifest), "--out", str(out), "--cpus", "2"]

    assert main(cmd) == 1  # not every entry finished
    rows = _rows(out)
    assert list(rows) == ["synth_seed0", "synth_seed1", "broken", "mean"]
    for name in ("synth_seed0", "synth_seed1"):
        assert rows[name]["status"] == "done" and not rows[name]["error"]
        assert float(rows[name]["full_psnr"]) > 5 and float(rows[name]["train_seconds"]) > 0
        assert rows[name]["full_lpips"] == ""  # null offline
        assert (out / name / "run" / "eval" / "metrics.json").is_file()
    assert rows["broken"]["status"] == "failed"
    assert rows["broken"]["error"].startswith("prepare: scene ") and "broken_scene" in rows["broken"]["error"]
    assert "Traceback" in (out / "broken" / "log.txt").read_text()
    assert rows["mean"]["status"] == "2/3 done"
    md = (out / "results.md").read_text()
    assert all(f"| {n} |" in md for n in ("synth_seed0", "synth_seed1", "broken")) and "| **mean** |" in md

    # synth_seed1 as if killed after stage IV: its last checkpoint is IV's, nothing later exists.
    ck = out / "synth_seed1" / "run" / "checkpoints"
    shutil.copyfile(ck / "stage_IV.pt", ck / "last.pt")
    for later in ("stage_V.pt", "stage_VI.pt", "stage_refit.pt"):
        (ck / later).unlink()
    (out / "synth_seed1" / "run" / "train_summary.json").unlink()
    untouched = _mtimes(out / "synth_seed0")
    seed1_before = _mtimes(out / "synth_seed1")

    assert main(cmd) == 1
    assert _mtimes(out / "synth_seed0") == untouched  # nothing of it ran: not even its log grew
    seed1 = _mtimes(out / "synth_seed1")
    for kept in ["scene/scene.json", *(f"run/checkpoints/stage_{s}.pt" for s in ("I", "II", "III", "IV"))]:
        assert seed1[kept] == seed1_before[kept], kept  # neither the scene nor stages I-IV were redone
    assert {"run/checkpoints/stage_VI.pt", "run/train_summary.json"} <= set(seed1)
    assert seed1["run/eval/metrics.json"] > seed1_before["run/eval/metrics.json"]  # evaluated again
    assert "resumed at stage V step 0" in (out / "synth_seed1" / "log.txt").read_text()
    rows = _rows(out)
    assert [rows[n]["status"] for n in ("synth_seed0", "synth_seed1", "broken")] == ["done", "done", "failed"]

    # Finished work is never silently reused for a changed entry.
    doc["sequences"][0]["train"] = {"set": ["schedule.VI=12"]}
    _write(manifest, doc)
    assert main(cmd) == 2
    assert _mtimes(out / "synth_seed0") == untouched
