"""A catalogue of broken inputs: every mistake ends in a clear message and nothing is lost.

Each case takes a copy of one small workspace (a valid scene with ground truth, an SMPL
scene, a run's config.yaml, a few frames and a short video, all written by cogs' own
code), breaks one thing in it, runs the real CLI in a subprocess and checks that

* the exit status is the documented one (1: `cogs check` found problems; 2: a user error),
* no traceback is printed,
* the message names the culprit (file, frame, option or setting),
* nothing in the workspace changed (a hash of every name, mode and byte, taken after
  breaking it and after the command).

Adding a case is one line in CASES: a name, how to break the workspace, the command (with
{ws} for the workspace), the texts the output must hold, and the exit status.
"""

from __future__ import annotations

import json
import os
import pickle
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from PIL import Image

from cogs.data.io import write_image, write_mask
from tests.fixtures import make_tiny_scene, tree_hash

REPO = Path(__file__).resolve().parents[1]
ROOT = os.geteuid() == 0 if hasattr(os, "geteuid") else False


# -- the workspace ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    from cogs.config import quick_config, save_config
    from cogs.preprocess.frames import write_video

    ws = tmp_path_factory.mktemp("catalogue") / "ws"
    make_tiny_scene(ws / "scene", ground_truth=True)
    smpl = make_tiny_scene(ws / "smpl_scene")
    T = 6
    np.savez(smpl / "body.npz", model=np.array("smpl"), shape=np.zeros(10, np.float32),
             pose=np.zeros((T, 24, 3), np.float32), transl=np.zeros((T, 3), np.float32))
    _edit_json(smpl / "scene.json", lambda m: m.update(body_model="smpl"))
    (ws / "run").mkdir()
    save_config(quick_config(), ws / "run" / "config.yaml")
    _train_tiny_run(ws)
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (6, 48, 64, 3), dtype=np.uint8)
    for i in range(3):
        write_image(ws / "frames" / f"{i:03d}.png", frames[i])
    write_video(ws / "clip.mp4", frames)
    return ws


def _train_tiny_run(ws: Path) -> None:
    """ws/trained: a finished run of every stage on ws/scene, trained by the real CLI (seconds)."""
    from cogs.cli import main
    from tests.fixtures import TINY

    assert main(["train", "--scene", str(ws / "scene"), "--out", str(ws / "trained"), "--set", *TINY]) == 0
    # The run folder is moved with the workspace: name the scene relative to where the CLI runs.
    _edit_json(ws / "trained" / "run.json", lambda m: m.update(scene="scene"))


def _edit_json(path: Path, change: Callable[[dict], None]) -> None:
    obj = json.loads(path.read_text())
    change(obj)
    path.write_text(json.dumps(obj))


def confidence(values: dict) -> Callable[[Path], None]:
    """Give object.json a per-frame `confidence` of 1, except `values` (frame index ->
    value; None leaves that frame without one)."""
    def change(o: dict) -> None:
        for i, f in enumerate(o["frames"]):
            v = values.get(i, 1.0)
            if v is not None:
                f["confidence"] = v
    return lambda ws: _edit_json(ws / "scene" / "object.json", change)


def _edit_npz(path: Path, **arrays) -> None:
    data = dict(np.load(path))
    data.update(arrays)
    np.savez(path, **data)


def _replace(path: Path, make: Callable[[Path], None]) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    else:
        path.unlink()
    make(path)


class _TouchesMarker:
    """Unpickling this would create `marker` (it names os.system)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


# -- the breakages ----------------------------------------------------------------------------


def scene_json(change):
    return lambda ws: _edit_json(ws / "scene" / "scene.json", change)


def cams(change):
    return lambda ws: _edit_json(ws / "scene" / "cameras.json", change)


def body(**arrays):
    return lambda ws: _edit_npz(ws / "scene" / "body.npz", **arrays)


def write(rel: str, data: bytes | str):
    def go(ws):
        p = ws / rel
        if p.is_dir():
            shutil.rmtree(p)
        (p.write_bytes if isinstance(data, bytes) else p.write_text)(data)
    return go


def truncate(rel: str, keep: int):
    return lambda ws: (ws / rel).write_bytes((ws / rel).read_bytes()[:keep])


def folder_in_place_of(rel: str):
    return lambda ws: _replace(ws / rel, lambda p: p.mkdir())


def link_loop(rel: str):
    return lambda ws: _replace(ws / rel, lambda p: p.symlink_to(p))


def pipe_in_place_of(rel: str):
    return lambda ws: _replace(ws / rel, lambda p: os.mkfifo(p))


def unreadable(rel: str):
    return lambda ws: (ws / rel).chmod(0)


def delete(rel: str):
    return lambda ws: (shutil.rmtree if (ws / rel).is_dir() else Path.unlink)(ws / rel)


def all_human_masks_empty(ws):
    for p in (ws / "scene" / "masks" / "human").iterdir():
        write_mask(p, np.zeros((30, 40), bool))


def grey_mask(ws):
    Image.fromarray((np.arange(1200).reshape(30, 40) % 200).astype(np.uint8)).save(ws / "scene" / "masks" / "human" / "000002.png")


def colour_mask(ws):
    write_image(ws / "scene" / "masks" / "object" / "000003.png", np.full((30, 40, 3), (255, 0, 0), np.uint8))


def image_16bit(ws):
    Image.fromarray(np.zeros((30, 40), np.uint16)).save(ws / "scene" / "images" / "000005.png")


def image_wrong_size(ws):
    write_image(ws / "scene" / "images" / "000000.png", np.zeros((30, 41, 3), np.uint8))


def planes(rel: str, change):
    return lambda ws: _edit_json(ws / rel, change)


def evil_smpl_model(ws):
    (ws / "evil.pkl").write_bytes(pickle.dumps({"v_template": np.zeros((4, 3)), "f": _TouchesMarker(ws / "PWNED")}, protocol=2))


def config_yaml(text: str):
    return lambda ws: (ws / "run" / "config.yaml").write_text(text)


def nothing(ws):
    pass


def other_split_scene(ws):
    """ws/other: the workspace's scene with one frame moved from training to test."""
    shutil.copytree(ws / "scene", ws / "other")
    _edit_json(ws / "other" / "scene.json", lambda m: m.update(split={"train": m["split"]["train"][1:],
                                                                      "test": m["split"]["test"] + m["split"]["train"][:1]}))


def both(*fns):
    def go(ws):
        for f in fns:
            f(ws)
    return go


# -- the catalogue ------------------------------------------------------------------------------


@dataclass
class Case:
    name: str
    breaks: Callable[[Path], None]
    command: str
    names: list[str]
    code: int = 1
    env: dict = field(default_factory=dict)
    needs_non_root: bool = False


CHECK = "check --scene {ws}/scene"
C = Case
CASES = [
    # scene.json
    C("scene.json missing", delete("scene/scene.json"), CHECK, ["scene.json: missing (every scene needs its metadata file)"]),
    C("scene.json is a folder", folder_in_place_of("scene/scene.json"), CHECK, ["scene.json: is a folder, expected a file"]),
    C("scene.json is a bare string", write("scene/scene.json", '"hello"'), CHECK, ["scene.json: must hold a JSON object"]),
    C("scene.json truncated", truncate("scene/scene.json", 40), CHECK, ["scene.json: not valid JSON"]),
    C("fps 0", scene_json(lambda m: m.update(fps=0)), CHECK, ["scene.json: `fps` must be a positive number (frames per second), got 0"]),
    C("fps -1", scene_json(lambda m: m.update(fps=-1)), CHECK, ["scene.json: `fps` must be a positive number", "got -1"]),
    C("fps fast", scene_json(lambda m: m.update(fps="fast")), CHECK, ["scene.json: `fps` must be a positive number", "got 'fast'"]),
    C("frame id is a path", scene_json(lambda m: m["frames"].__setitem__(2, "../../x")), CHECK, ["scene.json: `frames`: frame id '../../x' cannot be a file name"]),
    C("split index out of range", scene_json(lambda m: m["split"]["test"].append(17)), CHECK, ["scene.json: `split.test` has indices outside 0..5: [17]"]),
    # cameras.json
    C("cameras.json is a folder", folder_in_place_of("scene/cameras.json"), CHECK, ["cameras.json: is a folder, expected a file"]),
    C("cameras.json truncated", truncate("scene/cameras.json", 100), CHECK, ["cameras.json: not valid JSON"]),
    C("cameras K of text", cams(lambda c: c["frames"][2].update(K="wide")), CHECK, ["cameras.json (frame 000002): `K` must be a 3x3 matrix of numbers"]),
    C("camera not a rotation", cams(lambda c: c["frames"][3]["world_to_camera"][0].__setitem__(0, 3.0)), CHECK,
      ["cameras.json (frame 000003): `world_to_camera` rotation block is not a rotation"]),
    # images and masks
    C("image truncated", truncate("scene/images/000004.png", 120), CHECK, ["images/000004.png (frame 000004): corrupt or unreadable image"]),
    C("image missing", delete("scene/images/000001.png"), CHECK, ["images/000001.png (frame 000001): missing"]),
    C("image is a folder", folder_in_place_of("scene/images/000002.png"), CHECK, ["images/000002.png (frame 000002): is a folder, expected a file"]),
    C("image is a symlink loop", link_loop("scene/images/000003.png"), CHECK, ["images/000003.png (frame 000003): a symbolic link loop"]),
    C("image 16-bit", image_16bit, CHECK, ["images/000005.png (frame 000005): expected an 8-bit image, got PIL mode I;16"]),
    C("image wrong size", image_wrong_size, CHECK, ["images/000000.png (frame 000000): image is 41x30, expected 40x30"]),
    C("images is a file", lambda ws: _replace(ws / "scene" / "images", lambda p: p.write_text("x")), CHECK, ["images: not a folder"]),
    C("mask not binary", grey_mask, CHECK, ["masks/human/000002.png (frame 000002): mask is not binary"]),
    C("mask in colour", colour_mask, CHECK, ["masks/object/000003.png (frame 000003): mask has colour"]),
    C("all human masks empty", all_human_masks_empty, CHECK, ["masks/human: every human mask is empty: no person in any of the 6 frames"]),
    C("masks folder unreadable", unreadable("scene/masks/object"), CHECK, ["masks/object: folder cannot be read (Permission denied)"], needs_non_root=True),
    # body.npz
    C("body.npz garbage", write("scene/body.npz", b"PK\x03\x04garbage"), CHECK, ["body.npz: unreadable npz"]),
    C("body.npz unreadable", unreadable("scene/body.npz"), CHECK, ["body.npz: unreadable (Permission denied)"], needs_non_root=True),
    C("pose not numbers", body(pose=np.full((6, 104, 3), "a")), CHECK, ["body.npz: `pose` must hold numbers, got dtype <U1"]),
    C("pose wrong shape", body(pose=np.zeros((6, 24, 3))), CHECK, ["body.npz: `pose` must be [T, 104, 3] for anny, got [6, 24, 3]"]),
    C("transl NaN in a frame", body(transl=np.where(np.arange(6)[:, None] == 3, np.nan, 0.0) * np.ones((6, 3))), CHECK,
      ["body.npz (frame 000003): `transl` has non-finite numbers"]),
    C("body.npz is one array", lambda ws: np.save(ws / "scene" / "body.npy", np.zeros(3)) or (ws / "scene" / "body.npy").rename(ws / "scene" / "body.npz"),
      CHECK, ["body.npz: not an .npz archive"]),
    # object, points, planes
    C("object.json is a pipe", pipe_in_place_of("scene/object.json"), CHECK, ["object.json: not a regular file"]),
    C("object quaternion zero", lambda ws: _edit_json(ws / "scene" / "object.json", lambda o: o["frames"][1].update(quat_wxyz=[0, 0, 0, 0])),
      CHECK, ["object.json (frame 000001): `quat_wxyz` is zero"]),
    C("object confidence above 1", confidence({2: 1.5}), CHECK,
      ["object.json (frame 000002): `confidence` must be in [0, 1] (0 = object lost, 1 = mask trusted), got 1.5"]),
    C("object confidence not finite", confidence({4: float("nan")}), CHECK, ["object.json (frame 000004): `confidence` must be finite"]),
    C("object confidence a string", confidence({0: "high"}), CHECK, ["object.json (frame 000000): `confidence` must be a number in [0, 1], got 'high'"]),
    C("object confidence on some frames only", confidence({3: None}), CHECK,
      ["object.json (frame 000003): `confidence` is missing here but given on 5 of the 6 frames"]),
    C("points.ply garbage", write("scene/points.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 9\n"), CHECK, ["points.ply: unreadable PLY"]),
    C("planes.json without offset", planes("scene/planes.json", lambda o: o["planes"][0].pop("offset")), CHECK, ["planes.json: plane 0: `offset` is missing"]),
    # ground truth
    C("gt/planes.json without offset", planes("scene/gt/planes.json", lambda o: o["planes"][0].pop("offset")), CHECK, ["gt/planes.json: plane 0: `offset` is missing"]),
    C("gt/depth.npz wrong shape", lambda ws: np.savez(ws / "scene" / "gt" / "depth.npz", depth=np.zeros((6, 30, 30))), CHECK,
      ["gt/depth.npz: depth must be [6, 30, 40], got [6, 30, 30]"]),
    C("gt/novel/cameras.json missing", delete("scene/gt/novel/cameras.json"), CHECK, ["gt/novel/cameras.json: missing"]),
    C("gt/novel image missing", delete("scene/gt/novel/images/v001.png"), CHECK, ["gt/novel/images/v001.png (frame v001): missing"]),
    C("gt/novel view of a frame that is not there", planes("scene/gt/novel/cameras.json", lambda o: o["frames"][0].update(frame=6)), CHECK,
      ["gt/novel/cameras.json (frame v000): `frame` must be the index of the scene frame the view shows (0..5), got 6"]),
    C("scene folder missing", nothing, "check --scene {ws}/nowhere", ["nowhere: scene folder does not exist"]),
    C("scene folder named like rich markup", lambda ws: shutil.copytree(ws / "scene", ws / "s[red]") and (ws / "s[red]" / "points.ply").unlink(),
      "check --scene {ws}/s[red]", ["{ws}/s[red]: 1 problem(s)", "points.ply: missing"]),
    # training settings, before anything is written
    C("--set a section to a value", nothing, "train --scene {ws}/scene --out {ws}/new_run --set schedule=5", ["`schedule` is a section, not a value"], code=2),
    C("--set a cadence to 0", nothing, "train --scene {ws}/scene --out {ws}/new_run --set checkpoint_every=0 visibility_every=0",
      ["checkpoint_every: must be at least 1", "visibility_every: must be at least 1"], code=2),
    C("--set an unknown backend", nothing, "train --scene {ws}/scene --out {ws}/new_run --set backend=nonsense", ["backend: unknown 'nonsense'"], code=2),
    C("--set no Gaussians", nothing, "train --scene {ws}/scene --out {ws}/new_run --set branches.human.n_gaussians=0", ["branches.human.n_gaussians: must be positive, got 0"], code=2),
    C("--set a negative stage", nothing, "train --scene {ws}/scene --out {ws}/new_run --set schedule.III=-100", ["schedule.III: must not be negative, got -100"], code=2),
    C("--set a misspelt setting", nothing, "train --scene {ws}/scene --out {ws}/new_run --set schedul.I=5", ["`schedul` is not a setting (no field 'schedul' in TrainConfig); did you mean `schedule`?"], code=2),
    C("config.yaml a bare string", config_yaml("hello"), "train --scene {ws}/scene --out {ws}/run --resume", ["{ws}/run/config.yaml", "holds 'hello'"], code=2),
    C("config.yaml only a preset", config_yaml("preset: quick\n"), "train --scene {ws}/scene --out {ws}/run --resume", ["{ws}/run/config.yaml", "missing settings: schedule"], code=2),
    # SMPL model files
    C("SMPL model that would run code", evil_smpl_model, "render-init --scene {ws}/smpl_scene --out {ws}/init.png",
      ["{ws}/evil.pkl: refusing to load this pickle: it names the global `posix.system`"], code=2, env={"COGS_SMPL_MODEL": "{ws}/evil.pkl"}),
    C("SMPL model truncated", lambda ws: (ws / "bad.pkl").write_bytes(pickle.dumps({"f": np.zeros(30)})[:25]),
      "render-init --scene {ws}/smpl_scene --out {ws}/init.png", ["{ws}/bad.pkl: not a readable pickle"], code=2, env={"COGS_SMPL_MODEL": "{ws}/bad.pkl"}),
    # preprocess: options, output folder, video
    C("--max-side negative", nothing, "preprocess {ws}/frames --out {ws}/new --max-side -5", ["--max-side must be at least 1, got -5"], code=2),
    C("--max-side 0", nothing, "preprocess {ws}/frames --out {ws}/new --max-side 0", ["--max-side must be at least 1, got 0"], code=2),
    C("--stride 0", nothing, "preprocess {ws}/frames --out {ws}/new --stride 0", ["--stride must be at least 1, got 0"], code=2),
    C("--object-box on a frame past the clip", nothing, "preprocess {ws}/frames --out {ws}/new --object-box 7 5 5 20 20",
      ["--object-box 7 5 5 20 20: frame 7 is outside the 3 processed frames (0..2)"], code=2),
    C("--object-box-frame past the clip", nothing, "preprocess {ws}/frames --out {ws}/new --object-box 5 5 20 20 --object-box-frame 3",
      ["--object-box-frame 3 is outside the 3 processed frames (0..2)"], code=2),
    C("--object-box outside the frame", nothing, "preprocess {ws}/frames --out {ws}/new --object-box 1 100 5 120 20",
      ["--object-box 1 100 5 120 20 lies outside the 64x48 frame"], code=2),
    C("--object-box empty", nothing, "preprocess {ws}/frames --out {ws}/new --object-box 1 20 5 20 30",
      ["--object-box 1 20 5 20 30: the box must be X0 Y0 X1 Y1 with X1 > X0 and Y1 > Y0"], code=2),
    C("--object-box twice on one frame", nothing, "preprocess {ws}/frames --out {ws}/new --object-box 1 5 5 20 20 --object-box 1 6 6 30 30",
      ["--object-box 1 6 6 30 30: frame 1 already has the box 1 5 5 20 20"], code=2),
    C("--object-negative-box over the object box", nothing,
      "preprocess {ws}/frames --out {ws}/new --object-box 1 5 5 20 20 --object-negative-box 1 0 0 30 30",
      ["--object-negative-box 1 0 0 30 30 covers most of --object-box 1 5 5 20 20 on frame 1"], code=2),
    C("--object-negative-box past the clip", nothing,
      "preprocess {ws}/frames --out {ws}/new --object-box 0 5 5 20 20 --object-negative-box 4 30 5 50 20",
      ["--object-negative-box 4 30 5 50 20: frame 4 is outside the 3 processed frames (0..2)"], code=2),
    C("--object-box with --object-masks", nothing, "preprocess {ws}/frames --out {ws}/new --object-box 5 5 20 20 --object-masks {ws}/frames",
      ["give either --object-box or --object-masks, not both"], code=2),
    C("preprocess --out an existing file", nothing, "preprocess {ws}/frames --out {ws}/clip.mp4", ["--out {ws}/clip.mp4 is an existing file"], code=2),
    C("preprocess --out an existing scene", nothing, "preprocess {ws}/frames --out {ws}/scene",
      ["--out {ws}/scene already holds a cogs scene 'tiny' (6 frames)", "--overwrite"], code=2),
    C("video of zero bytes", write("clip.mp4", b""), "preprocess {ws}/clip.mp4 --out {ws}/new", ["clip.mp4"], code=2),
    C("preprocess a clip too large for the memory", nothing, "preprocess {ws}/clip.mp4 --out {ws}/new",
      ["{ws}/clip.mp4: preprocessing 6 frames of 64x48 needs about", "more than the 1.0 GiB available"], code=2,
      env={"COGS_MEMORY_GB": "1"}),
    C("synth a scene too large for the memory", nothing, "synth --out {ws}/new --frames 600 --width 1024 --height 1024",
      ["--frames 600 at 1024x1024 needs about", "more than the 2.0 GiB available", "Make it fit with --width"], code=2,
      env={"COGS_MEMORY_GB": "2"}),
    C("video that is text", write("clip.mp4", "not a video\n" * 50), "preprocess {ws}/clip.mp4 --out {ws}/new", ["clip.mp4"], code=2),
    C("video truncated", truncate("clip.mp4", 10000), "preprocess {ws}/clip.mp4 --out {ws}/new", ["clip.mp4"], code=2),
    # import, synth, demo, render-init
    C("import --out an existing file", nothing, "import humannerf {ws}/frames --out {ws}/clip.mp4", ["--out {ws}/clip.mp4 is an existing file"], code=2),
    C("import with a missing SMPL model", nothing, "import humannerf {ws}/frames --out {ws}/new --body-model smpl --smpl-model {ws}/nope.pkl",
      ["SMPL model file {ws}/nope.pkl does not exist"], code=2),
    C("synth fps 0", nothing, "synth --out {ws}/new --frames 2 --fps 0", ["--fps must be a positive number"], code=2),
    C("synth over a user's scene", nothing, "synth --out {ws}/scene --frames 2", ["--out {ws}/scene already holds a cogs scene 'tiny'", "--overwrite"], code=2),
    C("demo over a user's scene", lambda ws: shutil.copytree(ws / "scene", ws / "D" / "scene"), "demo --out {ws}/D",
      ["{ws}/D/scene holds a cogs scene 'tiny' (6 frames), which the demo did not write"], code=2),
    C("demo --out a file", nothing, "demo --out {ws}/clip.mp4", ["--out {ws}/clip.mp4 is an existing file"], code=2),
    C("demo with a bad --set", nothing, "demo --out {ws}/D --set log_every=-1", ["log_every: must be at least 1"], code=2),
    C("render-init --frames 0", nothing, "render-init --scene {ws}/scene --frames 0 --out {ws}/init.png", ["--frames must be at least 1, got 0"], code=2),
    C("render-init --out unknown extension", nothing, "render-init --scene {ws}/scene --out {ws}/init.gif", ["--out {ws}/init.gif: unknown extension '.gif'"], code=2),
    C("render-init --out a folder", nothing, "render-init --scene {ws}/scene --out {ws}/frames", ["--out {ws}/frames is an existing folder"], code=2),
    # trained runs: their folders, checkpoints and scenes
    C("train over a finished run", nothing, "train --scene {ws}/scene --out {ws}/trained",
      ["--out {ws}/trained: holds a finished run", "--resume", "--overwrite"], code=2),
    C("train --out a file", nothing, "train --scene {ws}/scene --out {ws}/clip.mp4", ["--out {ws}/clip.mp4: is a file"], code=2),
    C("train into a folder of the user's", nothing, "train --scene {ws}/scene --out {ws}/frames --overwrite",
      ["--out {ws}/frames: the folder holds files that are not a cogs run"], code=2),
    C("train --resume and --overwrite", nothing, "train --scene {ws}/scene --out {ws}/trained --resume --overwrite",
      ["--resume continues the run in --out and --overwrite replaces it"], code=2),
    C("train --checkpoint without --resume", nothing, "train --scene {ws}/scene --out {ws}/new --checkpoint stage_I.pt",
      ["--checkpoint names the checkpoint --resume continues from"], code=2),
    C("train --device unknown", nothing, "train --scene {ws}/scene --out {ws}/new --device tpu", ["--device 'tpu'"], code=2),
    C("train --resume, last checkpoint truncated", truncate("trained/checkpoints/last.pt", 5000),
      "train --scene {ws}/scene --out {ws}/trained --resume",
      ["{ws}/trained/checkpoints/last.pt: not a readable cogs checkpoint", "--checkpoint stage_"], code=2),
    C("train --resume, last checkpoint garbage", write("trained/checkpoints/last.pt", "not a checkpoint\n"),
      "train --scene {ws}/scene --out {ws}/trained --resume", ["{ws}/trained/checkpoints/last.pt: not a readable cogs checkpoint"], code=2),
    C("train --resume from a checkpoint that is not there", nothing,
      "train --scene {ws}/scene --out {ws}/trained --resume --checkpoint stage_IX.pt", ["--checkpoint stage_IX.pt: no such file"], code=2),
    C("eval, last checkpoint truncated", truncate("trained/checkpoints/last.pt", 5000), "eval --run {ws}/trained",
      ["{ws}/trained/checkpoints/last.pt: not a readable cogs checkpoint", "cogs eval --checkpoint stage_"], code=2),
    C("eval of a folder that is not a run", nothing, "eval --run {ws}/frames", ["{ws}/frames is not a training run"], code=2),
    C("eval without run.json", lambda ws: (ws / "trained" / "run.json").unlink(), "eval --run {ws}/trained",
      ["{ws}/trained has no run.json", "--scene"], code=2),
    C("eval of a moved scene", lambda ws: _edit_json(ws / "trained" / "run.json", lambda m: m.update(scene="gone")),
      "eval --run {ws}/trained", ["names scene 'gone', which does not exist", "--scene"], code=2),
    C("eval against another scene", other_split_scene, "eval --run {ws}/trained --scene {ws}/other",
      ["{ws}/trained was trained on another scene", "split_sha1"], code=2),
    C("eval --checkpoint that is not there", nothing, "eval --run {ws}/trained --checkpoint nope.pt",
      ["--checkpoint nope.pt: no such file"], code=2),
    C("eval --pose-fit-steps negative", nothing, "eval --run {ws}/trained --pose-fit-steps -1",
      ["--pose-fit-steps must be 0 or more, got -1"], code=2),
    C("eval --out a file", nothing, "eval --run {ws}/trained --out {ws}/clip.mp4", ["--out {ws}/clip.mp4"], code=2),
]


def test_the_catalogue_is_large_and_its_names_are_unique():
    assert len(CASES) >= 40 and len({c.name for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_broken_input_gives_a_clear_message_and_changes_nothing(workspace, tmp_path, case):
    if case.needs_non_root and ROOT:
        pytest.skip("root reads files whatever their mode")
    ws = tmp_path / "ws"
    shutil.copytree(workspace, ws, symlinks=True)
    case.breaks(ws)
    before = tree_hash(ws)
    fill = lambda s: s.replace("{ws}", str(ws))  # noqa: E731
    env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "10000", "NO_COLOR": "1",
           **{k: fill(v) for k, v in case.env.items()}}
    try:
        r = subprocess.run([sys.executable, "-m", "cogs.cli", *fill(case.command).split()], cwd=ws, env=env,
                           capture_output=True, text=True, timeout=300)
        after = tree_hash(ws)
    finally:
        if case.needs_non_root:  # let pytest remove the copy
            for dirpath, dirnames, filenames in os.walk(ws):
                for name in dirnames + filenames:
                    os.chmod(Path(dirpath) / name, 0o755)
    output = " ".join((r.stdout + r.stderr).split())
    assert "Traceback" not in output, output
    assert r.returncode == case.code, f"exit {r.returncode}: {output}"
    for name in case.names:
        assert fill(name) in output, f"{fill(name)!r} not in: {output}"
    assert after == before, f"the workspace changed: {output}"
