"""Folders a user has are never overwritten silently, and options are checked before any
work: `cogs preprocess`, `cogs synth`, the demo's scene and `cogs render-init`. One command
writes a folder at a time, and a command stopped by Ctrl-C or SIGTERM cleans up."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from cogs.cli import main
from cogs.data.validate import check_scene
from cogs.errors import UserError
from tests.fixtures import make_tiny_scene, tree_hash


def entries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


# -- preprocess -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    """Six frames of a person (the synthetic scene's images, 128x96): preprocess runs on them
    in seconds with the rotation-only cameras and a short body fit."""
    from cogs.data.scene import save_scene
    from cogs.data.synth import SynthConfig, generate_scene

    root = tmp_path_factory.mktemp("clip") / "synth"
    save_scene(generate_scene(SynthConfig(frames=6, width=128, height=96, points=300), show_progress=False), root)
    return root / "images"


@pytest.fixture
def no_person(tmp_path) -> Path:
    from cogs.data.io import write_image

    rng = np.random.default_rng(0)
    for i in range(3):
        write_image(tmp_path / "noise" / f"{i}.png", rng.integers(0, 255, (96, 128, 3), dtype=np.uint8))
    return tmp_path / "noise"


def preprocess(input: Path, out: Path, **kw):
    pytest.importorskip("mediapipe", reason="mediapipe is in the optional `preprocess` extra")
    from cogs.preprocess.command import Preprocess
    from cogs.preprocess.pipeline import run_preprocess

    opts = dict(sfm="rotation", body_iterations=10, max_side=128, progress=False)
    opts.update(kw)
    return run_preprocess(Preprocess(input=input, out=out, **opts))


def test_preprocess_puts_the_scene_in_place_only_once_it_is_complete(clip, tmp_path):
    report = preprocess(clip, tmp_path / "scene")
    assert entries(tmp_path) == ["scene"]  # no work folder left beside it
    assert check_scene(tmp_path / "scene") == []
    assert (tmp_path / "scene" / ".cache" / "frames.json").exists() and report.preview.exists()


def test_an_existing_out_is_refused_without_overwrite_and_left_as_it_was(clip, tmp_path):
    scene = make_tiny_scene(tmp_path / "scene")
    before = tree_hash(tmp_path)
    with pytest.raises(UserError) as e:
        preprocess(clip, scene)
    assert str(e.value).startswith(f"--out {scene} already holds a cogs scene 'tiny' (6 frames)")
    assert "--overwrite" in str(e.value)
    assert tree_hash(tmp_path) == before


def test_overwrite_replaces_the_scene_after_the_new_one_is_complete_reusing_its_cache(clip, tmp_path):
    preprocess(clip, tmp_path / "scene")
    report = preprocess(clip, tmp_path / "scene", body_iterations=12, overwrite=True)
    assert {"frames", "persons", "cameras"} <= set(report.cached) and "body" not in report.cached
    assert entries(tmp_path) == ["scene"] and check_scene(tmp_path / "scene") == []


def test_a_failed_run_leaves_only_its_cache_says_where_and_resumes_from_it(no_person, tmp_path):
    out = tmp_path / "scene"
    with pytest.raises(UserError) as e:
        preprocess(no_person, out)
    partial = tmp_path / "scene.partial"
    assert str(e.value) == (f"no person detected in any of the 3 frames of {no_person}: MediaPipe's detector (it finds a "
                            "person by the face) and its landmark model around the whole first frame found none. Where a "
                            "body is in view, give --person-box FRAME X0 Y0 X1 Y1 around it, or a larger --max-side (now 128)"
                            f"\nnothing was written to {out}; "
                            f"the 2 step(s) finished so far are cached in {partial / '.cache'}: run the same command "
                            f"again to resume from them (or delete {partial})")
    assert not out.exists()
    assert entries(partial) == [".cache", ".cogs-staging"]
    assert entries(partial / ".cache") == ["frames.json", "frames.npz", "persons.json", "persons.npz"]
    with pytest.raises(UserError, match="no person detected"):
        preprocess(no_person, out)  # resumed: both steps come from the cache
    assert entries(partial / ".cache") == ["frames.json", "frames.npz", "persons.json", "persons.npz"]


def test_a_failed_overwrite_leaves_the_old_scene_untouched(no_person, tmp_path):
    scene = make_tiny_scene(tmp_path / "scene")
    before = tree_hash(scene)
    with pytest.raises(UserError, match="nothing was written to"):
        preprocess(no_person, scene, overwrite=True)
    assert tree_hash(scene) == before


def test_a_users_folder_where_the_work_folder_goes_is_refused_and_kept(clip, tmp_path):
    (tmp_path / "scene.partial").mkdir()
    (tmp_path / "scene.partial" / "notes.txt").write_text("mine")
    with pytest.raises(UserError, match=r"scene\.partial is in the way"):
        preprocess(clip, tmp_path / "scene")
    assert entries(tmp_path) == ["scene.partial"] and entries(tmp_path / "scene.partial") == ["notes.txt"]


@pytest.mark.parametrize("option,kw", [
    ("--max-side", dict(max_side=-5)),
    ("--max-side", dict(max_side=0)),
    ("--stride", dict(stride=0)),
    ("--limit", dict(limit=0)),
    ("--start", dict(start=-1)),
    ("--focal-factor", dict(focal_factor=-1.2)),
    ("--focal-px", dict(focal_px=0.0)),
    ("--person-threshold", dict(person_threshold=1.5)),
    ("--track-side", dict(track_side=32)),
    ("--object-box", dict(object_box=(50.0, 50.0, 10.0, 10.0))),
    ("--object-box-frame", dict(object_box=(0.0, 0.0, 10.0, 10.0), object_box_frame=-1)),
    ("--object-box", dict(object_box=((1.0, 5.0, 5.0, 20.0, 20.0), (1.0, 6.0, 6.0, 30.0, 30.0)))),
    ("--object-negative-box", dict(object_box=((1.0, 5.0, 5.0, 20.0, 20.0),), object_negative_box=((1.0, 0.0, 0.0, 30.0, 30.0),))),
    ("--object-masks", dict(object_masks=Path("/nonexistent/masks"))),
    ("--body-model", dict(body_model="mystery")),
    ("--body-iterations", dict(body_iterations=0)),
    ("--out", dict(out="FILE")),
])
def test_preprocess_options_are_checked_before_anything_is_written(tmp_path, option, kw):
    from cogs.preprocess.command import Preprocess

    src = tmp_path / "frames"
    src.mkdir()
    (tmp_path / "FILE").write_text("a file of the user's")
    kw = dict(kw)
    out = tmp_path / kw.pop("out", "scene")
    before = tree_hash(tmp_path)
    with pytest.raises(UserError) as e:
        Preprocess(input=src, out=out, progress=False, **kw).run()
    assert str(e.value).startswith(option + " ")
    assert tree_hash(tmp_path) == before


def test_the_cli_exits_2_on_an_out_that_is_a_file(tmp_path, capsys):
    (tmp_path / "in").mkdir()
    (tmp_path / "taken").write_text("x")
    assert main(["preprocess", str(tmp_path / "in"), "--out", str(tmp_path / "taken")]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "is an existing file" in err and "Traceback" not in err


# -- one writer per folder ---------------------------------------------------------------------


def hold(out: Path):
    """Another process holding `out` the way a running cogs command does, until its stdin closes."""
    import subprocess
    import sys

    code = ("import sys; from pathlib import Path; from cogs.data.outdir import claimed\n"
            "with claimed(Path(sys.argv[1])):\n    print('held', flush=True); sys.stdin.read()")
    proc = subprocess.Popen([sys.executable, "-c", code, str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_preprocess_on_a_folder_being_written_stops_and_leaves_the_first_ones_work(clip, tmp_path):
    from cogs.data.outdir import MARKER, claimed, lock_file

    out = tmp_path / "scene"
    work = tmp_path / "scene.partial"  # what the first run has made so far
    (work / ".cache").mkdir(parents=True)
    (work / MARKER).touch()
    (work / ".cache" / "frames.json").write_text("{}")
    other = hold(out)
    before = tree_hash(tmp_path)
    with pytest.raises(UserError) as e:
        preprocess(clip, out)
    assert str(e.value) == (f"--out {out} is being written by another cogs command (process {other.pid}); "
                            "wait for it to finish or choose another --out")
    assert tree_hash(tmp_path) == before
    other.communicate("")  # the first run ends: its claim goes with it
    assert not lock_file(out).exists()
    with claimed(out):
        with claimed(out):  # one process claims a folder once, however deep
            assert lock_file(out).read_text() == str(os.getpid())
    assert not lock_file(out).exists()


@pytest.mark.parametrize("command", ["synth", "train"])
def test_the_cli_stops_on_a_folder_another_command_writes_and_takes_it_once_that_one_is_killed(tmp_path, capsys, command):
    import signal

    scene = make_tiny_scene(tmp_path / "tiny")
    out = tmp_path / "out"
    args = {"synth": ["synth", "--out", str(out), "--frames", "2", "--width", "32", "--height", "24"],
            "train": ["train", "--scene", str(scene), "--out", str(out), "--set", "schedule.I=1", "schedule.II=0", "schedule.III=0",
                      "schedule.IV=0", "schedule.V=0", "schedule.VI=0"]}[command]
    other = hold(out)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"is being written by another cogs command (process {other.pid})" in err and "Traceback" not in err
    assert not out.exists()
    other.send_signal(signal.SIGKILL)  # killed mid-write: the kernel releases the claim, the file stays
    other.wait()
    other.stdin.close()
    other.stdout.close()
    assert main(args) == 0
    assert (out / ("scene.json" if command == "synth" else "train_summary.json")).exists()


def test_export_and_render_stop_on_a_folder_another_command_writes(tmp_path, capsys):
    scene = make_tiny_scene(tmp_path / "tiny")
    run = tmp_path / "run"
    assert main(["train", "--scene", str(scene), "--out", str(run), "--set", "schedule.I=1", "schedule.II=0",
                 "schedule.III=0", "schedule.IV=0", "schedule.V=0", "schedule.VI=0"]) == 0
    capsys.readouterr()
    for args, out in ((["export", "--run", str(run)], tmp_path / "exp"), (["render", "--run", str(run)], tmp_path / "frames")):
        other = hold(out)
        try:
            assert main([*args, "--out", str(out)]) == 2
            err = capsys.readouterr().err
            assert f"is being written by another cogs command (process {other.pid})" in err and "Traceback" not in err
            assert not out.exists()
        finally:
            other.communicate("")


def test_a_folder_on_a_file_system_without_locks_is_written_unclaimed_with_a_warning(tmp_path, monkeypatch, caplog):
    import errno
    import fcntl
    import logging

    from cogs.data.outdir import claimed, lock_file

    def no_locks(fd, op):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    with caplog.at_level(logging.WARNING, logger="cogs"):
        with claimed(tmp_path / "out"):
            (tmp_path / "out").mkdir()
    assert (tmp_path / "out").is_dir() and not lock_file(tmp_path / "out").exists()
    assert any("cannot lock" in r.getMessage() and "No locks available" in r.getMessage() for r in caplog.records)


def test_a_command_killed_with_sigterm_cleans_up_like_ctrl_c(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    from cogs.data.outdir import lock_file

    scene = make_tiny_scene(tmp_path / "tiny")
    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "cogs.cli", "train", "--scene", str(scene), "--out", str(run), "--set",
                             "schedule.I=1000000"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 300
    while not (lock_file(run).exists() and (run / "config.yaml").exists()) and proc.poll() is None:
        assert time.monotonic() < deadline, "training never started"
        time.sleep(0.2)
    assert proc.poll() is None, proc.communicate()[0]
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGTERM, out
    assert "terminated" in out and "Traceback" not in out
    assert not lock_file(run).exists()  # the claim went with the cleanup, not only with the process


# -- synth and the demo's scene ------------------------------------------------------------------


def test_synth_replaces_its_own_scene_but_not_a_users_folder(tmp_path):
    from cogs.data.synth.command import Synth

    Synth(out=tmp_path / "s", frames=2, width=32, height=24).run()
    Synth(out=tmp_path / "s", frames=3, width=32, height=24).run()  # an earlier synthetic scene: replaced
    assert check_scene(tmp_path / "s") == [] and entries(tmp_path) == ["s"]
    user = make_tiny_scene(tmp_path / "mine")
    before = tree_hash(user)
    with pytest.raises(UserError, match="--overwrite"):
        Synth(out=user, frames=2, width=32, height=24).run()
    assert tree_hash(user) == before


@pytest.mark.parametrize("option,kw", [("--fps", dict(fps=0.0)), ("--fps", dict(fps=-1.0)), ("--seed", dict(seed=-1))])
def test_synth_options_are_checked_first(tmp_path, option, kw):
    from cogs.data.synth.command import Synth

    with pytest.raises(UserError, match=f"^{option}"):
        Synth(out=tmp_path / "s", frames=2, width=32, height=24, **kw).run()
    assert entries(tmp_path) == []


def test_the_demo_refuses_a_scene_it_did_not_write(tmp_path, capsys):
    make_tiny_scene(tmp_path / "D" / "scene")
    before = tree_hash(tmp_path)
    assert main(["demo", "--out", str(tmp_path / "D")]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert f"{tmp_path / 'D' / 'scene'} holds a cogs scene 'tiny' (6 frames), which the demo did not write" in err
    assert "Choose another --out, or delete" in err
    assert tree_hash(tmp_path) == before


def test_the_demo_refuses_its_own_scene_once_it_fails_cogs_check_and_reuses_a_valid_one(tmp_path, capsys):
    from cogs.data.synth.command import Synth, reusable_synthetic_scene

    scene = tmp_path / "D" / "scene"
    Synth(out=scene, frames=2, width=32, height=24).run()
    assert reusable_synthetic_scene(scene) is True  # the demo goes on to train on it
    (scene / "images" / "000001.png").unlink()
    before = tree_hash(tmp_path)
    assert main(["demo", "--out", str(tmp_path / "D"), "--frames", "2"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "holds a synthetic scene that fails cogs check (1 problem(s); the first: images/000001.png (frame 000001): missing)" in err
    assert tree_hash(tmp_path) == before


# -- render-init -------------------------------------------------------------------------------


@pytest.mark.parametrize("args,message", [
    (["--frames", "0"], "--frames must be at least 1, got 0"),
    (["--out", "{tmp}/init.gif"], "unknown extension '.gif'"),
    (["--out", "{tmp}"], "is an existing folder"),
    (["--out", "{scene}/scene.json/x.png"], "scene.json is a file, not a folder"),
])
def test_render_init_options_are_checked_before_rendering(tiny_scene, tmp_path, capsys, args, message):
    args = [a.format(tmp=tmp_path, scene=tiny_scene) for a in args]
    before = tree_hash(tmp_path)
    assert main(["render-init", "--scene", str(tiny_scene), *args]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert message in err and "Traceback" not in err
    assert tree_hash(tmp_path) == before
