"""The synthetic benchmark scene at its defaults (100 frames, 256x192): what every quality
number of the project relies on.

The default scene is generated once per test session and shared between xdist workers
through a locked folder (generation takes ~30 s on 2 cores); the checks then read it back
through `load_scene`, so they test the files a trainer gets.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.ndimage import binary_dilation, distance_transform_edt

from cogs.data.scene import load_scene, save_scene
from cogs.data.synth import NoiseConfig, SynthConfig, generate_scene
from cogs.data.synth.generate import build_assets
from cogs.data.synth.mesh import HUMAN, OBJECT, STATIC, point_triangle_distance
from cogs.data.synth.motion import _box_signed_distance
from cogs.data.synth.render import render_view
from cogs.data.synth.textures import BOX_SIZE
from cogs.data.validate import check_scene
from cogs.geometry.camera import camera_center
from cogs.geometry.rotations import axis_angle_to_rotmat, quat_geodesic_angle, rotmat_geodesic_angle


@pytest.fixture(scope="session")
def scene(default_scene_dir):
    return load_scene(default_scene_dir)  # validates


@pytest.fixture(scope="session")
def assets():
    return build_assets(SynthConfig())


def _gt_meshes(assets, scene, t, **which):
    gt = scene.gt
    rig = assets.choreo.rig
    A = rig.transforms(gt.body.pose[t:t + 1].astype(np.float64), gt.body.transl[t:t + 1].astype(np.float64))
    V = rig.vertices_posed(A)[0]
    R = gt.object.rotation_matrices()[t]
    return assets.scene_mesh(V, R, gt.object.translations[t], **which), A[0]


def test_default_scene_has_no_problems(default_scene_dir, scene):
    assert check_scene(default_scene_dir) == []
    assert (scene.n_frames, scene.width, scene.height, scene.fps) == (100, 256, 192, 10.0)
    assert scene.gt is not None and scene.gt.novel is not None and len(scene.gt.novel.frames) == 32


def test_split_is_hosnerf16(scene):
    assert scene.split["test"] == list(range(0, 96, 6))
    assert sorted(scene.split["train"] + scene.split["test"]) == list(range(100))


def test_object_is_visible_in_at_least_80_percent_of_frames(scene):
    visible = scene.gt.object_masks.reshape(scene.n_frames, -1).any(1)
    assert visible.mean() >= 0.8


def test_object_and_human_masks_touch_in_some_frames(scene):
    touching = [t for t in range(scene.n_frames)
                if (binary_dilation(scene.gt.object_masks[t]) & scene.gt.human_masks[t]).any()]
    assert len(touching) >= 20


def test_object_occludes_the_human_in_some_frames_and_is_occluded_in_others(scene, assets):
    obj_in_front, body_in_front = 0, 0
    for t in range(40, 100, 3):
        K, w2c = scene.gt.cameras.K[t], scene.gt.cameras.world_to_camera[t]
        body_only, _ = _gt_meshes(assets, scene, t, with_object=False, with_room=False)
        box_only, _ = _gt_meshes(assets, scene, t, with_body=False, with_room=False)
        vb = render_view(body_only, K, w2c, scene.width, scene.height, ss=1)
        vo = render_view(box_only, K, w2c, scene.width, scene.height, ss=1)
        both = (vb.depth > 0) & (vo.depth > 0)
        obj_in_front += int((both & (vo.depth < vb.depth) & (scene.gt.depth[t] > 0)).sum() > 20)
        body_in_front += int((both & (vb.depth < vo.depth)).sum() > 20)
    assert obj_in_front >= 3 and body_in_front >= 3


def test_box_rests_until_grasp_then_moves_rigidly_with_the_right_wrist(scene, assets):
    gt = scene.gt
    g = scene.source["object"]["grasp_frame"]
    assert 0 < g < scene.n_frames - 10
    assert np.allclose(gt.object.translations[:g], gt.object.translations[0], atol=1e-9)
    rig = assets.choreo.rig
    A = rig.transforms(gt.body.pose.astype(np.float64), gt.body.transl.astype(np.float64))[:, rig.i("wrist.R")]
    X = np.tile(np.eye(4), (scene.n_frames, 1, 1))
    X[:, :3, :3] = gt.object.rotation_matrices()
    X[:, :3, 3] = gt.object.translations
    rel = np.linalg.inv(A[g:]) @ X[g:]
    # float32 poses on disk: a tenth of a millimetre.
    assert np.abs(rel - rel[0]).max() < 2e-4
    # The box turns in the world while carried.
    angles = quat_geodesic_angle(torch.from_numpy(gt.object.quats[g:]), torch.from_numpy(gt.object.quats[g:g + 1]))
    assert np.rad2deg(angles.max().item()) > 90


def test_box_touches_the_hand_without_entering_the_body(scene, assets):
    rig = assets.choreo.rig
    gt = scene.gt
    hand = assets.choreo.hand_r_vertices
    R = gt.object.rotation_matrices()
    g = scene.source["object"]["grasp_frame"]
    for t in range(0, scene.n_frames, 3):
        A = rig.transforms(gt.body.pose[t:t + 1].astype(np.float64), gt.body.transl[t:t + 1].astype(np.float64))
        V = rig.vertices_posed(A)[0]
        sd = _box_signed_distance(V, R[t], gt.object.translations[t], BOX_SIZE / 2)
        assert sd[~hand].min() > 0.0, f"frame {t}: body inside the box"
        assert sd[hand].min() > -0.01, f"frame {t}: hand deep inside the box"
        if t >= g:
            assert sd[hand].min() < 0.005, f"frame {t}: box not touching the hand"


def test_camera_has_a_real_baseline_and_turns(scene):
    w2c = scene.gt.cameras.world_to_camera
    C = camera_center(w2c)
    assert np.linalg.norm(C[-1] - C[0]) >= 1.0
    assert np.linalg.norm(np.diff(C, axis=0), axis=1).sum() >= 1.0
    z = w2c[:, 2, :3]  # viewing directions in world
    assert np.rad2deg(np.arccos(np.clip(z[0] @ z[-1], -1, 1))) > 20


def test_sparse_points_lie_on_static_surfaces_within_the_noise(scene, assets):
    sigma = SynthConfig().noise.points_m
    pts = scene.points_xyz.astype(np.float64)
    assert 2000 <= len(pts) <= SynthConfig().points
    room = assets.room.mesh
    d = point_triangle_distance(pts, room.vertices[room.faces])
    assert d.max() <= 3 * sigma + 1e-4
    assert np.median(d) < 1.5 * sigma


def test_gt_masks_equal_the_rendered_label_buffer(scene, assets):
    for t in (0, 43, 64, 99):
        sm, _ = _gt_meshes(assets, scene, t)
        v = render_view(sm, scene.gt.cameras.K[t], scene.gt.cameras.world_to_camera[t], scene.width, scene.height)
        assert np.array_equal(v.label == HUMAN, scene.gt.human_masks[t])
        assert np.array_equal(v.label == OBJECT, scene.gt.object_masks[t])
        assert np.array_equal(v.rgb, scene.images[t])


def test_gt_depth_lies_on_the_room_surfaces(scene, assets):
    t = 10
    K, w2c = scene.gt.cameras.K[t], scene.gt.cameras.world_to_camera[t]
    sm, _ = _gt_meshes(assets, scene, t)
    v = render_view(sm, K, w2c, scene.width, scene.height)
    static = (v.centre_label == STATIC) & (scene.gt.depth[t] > 0)
    ii, jj = np.nonzero(static)
    sel = np.random.default_rng(0).choice(len(ii), 400, replace=False)
    z = scene.gt.depth[t][ii[sel], jj[sel]].astype(np.float64)
    xc = np.stack([(jj[sel] + 0.5 - K[0, 2]) / K[0, 0] * z, (ii[sel] + 0.5 - K[1, 2]) / K[1, 1] * z, z], 1)
    xw = (xc - w2c[:3, 3]) @ w2c[:3, :3]
    room = assets.room.mesh
    d = point_triangle_distance(xw, room.vertices[room.faces])
    assert (d <= 1e-3 * z + 1e-4).all()  # depth is stored as float16


def test_noisy_masks_differ_from_gt_only_near_boundaries(scene):
    changed_frames = 0
    for t in range(0, scene.n_frames, 4):
        for noisy, gt in ((scene.human_masks[t], scene.gt.human_masks[t]), (scene.object_masks[t], scene.gt.object_masks[t])):
            diff = noisy != gt
            if not gt.any():
                assert not noisy.any()
                continue
            changed_frames += int(diff.any())
            # Distance of each pixel centre to the true boundary (half a pixel past the
            # nearest pixel centre of the other class).
            dist = np.where(gt, distance_transform_edt(gt), distance_transform_edt(~gt)) - 0.5
            assert dist[diff].max(initial=0) <= 3.0
    assert changed_frames > 10


def test_noisy_inputs_are_off_by_the_configured_amounts(scene):
    cfg = NoiseConfig()
    gt = scene.gt
    dt = np.linalg.norm(scene.body.transl - gt.body.transl, axis=1)
    assert 0.005 < dt.mean() < 4 * cfg.transl_m * np.sqrt(3)
    dang = quat_geodesic_angle(torch.from_numpy(scene.object.quats), torch.from_numpy(gt.object.quats))
    assert 1.0 < np.rad2deg(dang.mean().item()) < 4 * cfg.object_deg * np.sqrt(3)
    dobj = np.linalg.norm(scene.object.translations - gt.object.translations, axis=1)
    assert 0.005 < dobj.mean() < 4 * cfg.object_m * np.sqrt(3)
    dcam = np.linalg.norm(camera_center(scene.cameras.world_to_camera) - camera_center(gt.cameras.world_to_camera), axis=1)
    assert 0.001 < dcam.mean() < 4 * cfg.camera_m * np.sqrt(3)
    Rn = axis_angle_to_rotmat(torch.from_numpy(scene.body.pose).double())
    Rg = axis_angle_to_rotmat(torch.from_numpy(gt.body.pose).double())
    dpose = np.rad2deg(rotmat_geodesic_angle(Rn, Rg).numpy())  # [T, J]
    moved = dpose.max(axis=0) > 1e-3
    assert 15 <= moved.sum() <= 20  # the major joints and the root moved, the fingers did not
    assert 1.0 < dpose[:, moved].mean() < 4 * cfg.body_deg * np.sqrt(3)
    assert dpose.max() < 30


def test_novel_views_are_off_the_training_path_and_see_the_person(scene):
    nv = scene.gt.novel
    train_c = camera_center(scene.gt.cameras.world_to_camera)
    for w2c in nv.cameras.world_to_camera:
        assert np.linalg.norm(train_c - camera_center(w2c), axis=1).min() >= 0.3
    assert nv.human_masks.reshape(len(nv.frames), -1).sum(1).min() > 300
    assert (nv.depth > 0).all()


def test_same_seed_writes_the_same_files_and_the_cli_previews(tmp_path):
    from cogs.data.synth.command import Synth

    small = dict(frames=6, width=64, height=48)
    a, b = tmp_path / "a", tmp_path / "b"
    assert Synth(out=a, seed=3, preview=True, **small).run() == 0
    assert Synth(out=b, seed=3, **small).run() == 0
    assert (a / "preview.png").exists()
    load_scene(a)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file() and p.name != "preview.png")
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for rel in files:
        if rel.name == "scene.json":
            ja, jb = json.loads((a / rel).read_text()), json.loads((b / rel).read_text())
            for j in (ja, jb):
                j["source"].pop("timings")
                j["source"].pop("body_model_build_seconds")
            assert ja == jb
        else:
            assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    c = generate_scene(SynthConfig(seed=4, **small), show_progress=False)
    sa = load_scene(a)
    assert not np.array_equal(c.body.pose, sa.body.pose)  # another seed, other noise
    assert np.array_equal(c.images, sa.images)  # ... but the same true renders


def test_a_scene_too_large_for_the_memory_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    from cogs.cli import main
    from cogs.data.synth.generate import peak_bytes
    from cogs.memory import GiB

    monkeypatch.setenv("COGS_MEMORY_GB", "4")
    out = tmp_path / "big"
    assert main(["synth", "--out", str(out), "--frames", "600", "--width", "1024", "--height", "1024"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "--frames 600 at 1024x1024 needs about" in err and "4.0 GiB available" in err and "Traceback" not in err
    assert not out.exists()
    # the frame count it names is the largest that fits, and the size it names fits too
    n = int(err.split("Make it fit with --frames ")[1].split()[0])
    assert peak_bytes(SynthConfig(frames=n, width=1024, height=1024)) <= 4 * GiB
    assert peak_bytes(SynthConfig(frames=n + 1, width=1024, height=1024)) > 4 * GiB
    w, h = (int(v) for v in err.split("--width ")[1].rstrip(".").split(" --height "))
    assert w == h < 1024 and peak_bytes(SynthConfig(frames=600, width=w, height=h)) <= 4 * GiB


def test_the_memory_estimate_is_above_what_generating_a_scene_takes(tmp_path):
    """The generator's peak, measured on a real run in a fresh process (ru_maxrss of the
    child), is below the estimate the refusal uses, and not far below it (a fresh clone's first
    run, compiling numba's kernels, measured 1,345,268 kB against 1,094,184 kB warm)."""
    import subprocess
    import sys

    from cogs.data.synth.generate import peak_bytes

    probe = ("import resource, subprocess, sys; "
             "subprocess.run([sys.executable, '-m', 'cogs.cli', 'synth', '--out', sys.argv[1], '--frames', '3', "
             "'--width', '512', '--height', '384'], check=True, capture_output=True); "
             "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    res = subprocess.run([sys.executable, "-c", probe, str(tmp_path / "s")], capture_output=True, text=True, check=True)
    measured = int(res.stdout.split()[-1]) * 1024  # kB on Linux
    estimate = peak_bytes(SynthConfig(frames=3, width=512, height=384))
    assert measured <= estimate <= 1.75 * measured, (measured, estimate)
