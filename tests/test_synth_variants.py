"""Choreography variants of the synthetic benchmark (`SynthConfig.variant`): another video of
the same story, so that a default can be checked on a scene it was not chosen on.

Variant 0 must stay the reference script (every number of the project was measured on
it); the others must be physically the same story: the box rests on the table, the right
hand reaches and carries it without entering it, and the camera sees both throughout.
"""

from __future__ import annotations

import numpy as np
import pytest

from cogs.data.synth.motion import BOX_REST_XY, BOX_REST_YAW_DEG, CAMERA_KEYS, ROOT_KEYS, Choreography, _box_signed_distance, script
from cogs.data.synth.room import ROOM_HI, ROOM_LO, TABLE_XY_HI, TABLE_XY_LO

VARIANTS = (1, 2, 3, 4)
FRAMES = 40


def test_variant_0_is_the_reference_script_and_others_differ_from_it_and_each_other():
    ref = script(0)
    assert np.array_equal(ref.root_keys, ROOT_KEYS) and np.array_equal(ref.camera_keys, CAMERA_KEYS)
    assert np.array_equal(ref.box_rest_xy, BOX_REST_XY) and ref.box_rest_yaw_deg == BOX_REST_YAW_DEG
    seen = [ref]
    for v in VARIANTS:
        s = script(v)
        again = script(v)
        assert np.array_equal(s.root_keys, again.root_keys) and np.array_equal(s.camera_keys, again.camera_keys)
        for other in seen:
            assert np.abs(s.root_keys[:, 1:3] - other.root_keys[:, 1:3]).max() > 0.02
            assert np.abs(s.camera_keys[:, 1:] - other.camera_keys[:, 1:]).max() > 0.02
            assert np.abs(s.box_rest_xy - other.box_rest_xy).max() > 1e-3 or abs(s.box_rest_yaw_deg - other.box_rest_yaw_deg) > 0.5
        assert (s.root_keys[:, 0] == ROOT_KEYS[:, 0]).all()  # the same story: the same beats
        seen.append(s)


@pytest.fixture(scope="module")
def motions():
    from cogs.body import load_body_model
    from cogs.data.synth.config import SynthConfig

    model, shape = load_body_model("anny"), np.asarray(SynthConfig().shape, dtype=np.float64)
    out = {}
    for v in (0, *VARIANTS):
        c = Choreography(model, shape, v)
        out[v] = (c, c.evaluate(FRAMES))
    return out


@pytest.mark.parametrize("variant", VARIANTS)
def test_a_variant_tells_the_same_story_physically(motions, variant):
    c, mo = motions[variant]
    rig = c.rig
    V = rig.vertices_posed(rig.transforms(mo.pose, mo.transl))
    g = mo.grasp_frame
    assert 0 < g < FRAMES - 10
    # The box rests on the table until the grasp, then moves.
    rest = mo.box_t[0, :2]
    assert (rest > TABLE_XY_LO + 0.05).all() and (rest < TABLE_XY_HI - 0.05).all()
    assert np.allclose(mo.box_t[:g], mo.box_t[0]) and np.linalg.norm(mo.box_t[-1] - mo.box_t[0]) > 0.3
    c0, mo0 = motions[0]
    V0 = c0.rig.vertices_posed(c0.rig.transforms(mo0.pose, mo0.transl))
    for t in range(FRAMES):
        sd = _box_signed_distance(V[t], mo.box_R[t], mo.box_t[t], c.box_half)
        assert sd[~c.hand_r_vertices].min() > 0.0, f"frame {t}: the body inside the box"
        if mo.times[t] >= 3.0:  # the reach (from 3 s), the grasp and the carry are the reference's, relative to the box
            sd0 = _box_signed_distance(V0[t], mo0.box_R[t], mo0.box_t[t], c0.box_half)
            assert abs(sd[c.hand_r_vertices].min() - sd0[c0.hand_r_vertices].min()) < 1e-3, f"frame {t}"
        if t >= g:
            assert sd[c.hand_r_vertices].min() < 0.005, f"frame {t}: the box left the hand"
    assert (V[..., 2].min(axis=1) > -1e-6).all() and (np.abs(V[..., 2].min(axis=1)) < 1e-3).all()  # feet on the floor
    assert (V[..., :2] > ROOM_LO[:2] + 0.3).all() and (V[..., :2] < ROOM_HI[:2] - 0.3).all()
    # Box and body in front of every camera and inside its 55-degree view.
    for name, P in (("box", mo.box_t), ("body", mo.transl + np.array([0.0, 0.0, 0.9]))):
        cam = np.einsum("tij,tj->ti", mo.camera_w2c[:, :3, :3], P) + mo.camera_w2c[:, :3, 3]
        assert (cam[:, 2] > 1.0).all(), f"the {name} behind or too near the camera"
        half = np.tan(np.radians(55.0 / 2))
        assert (np.abs(cam[:, 1] / cam[:, 2]) < half).all() and (np.abs(cam[:, 0] / cam[:, 2]) < half * 4 / 3).all(), name
    # The person turns (three quarters of a turn or so) between the pickup and the walk out.
    assert 200 < c.script.root_keys[3, 3] - c.script.root_keys[2, 3] < 300


def test_a_variant_renders_another_video_of_a_valid_scene(tmp_path):
    from cogs.data.scene import load_scene, save_scene
    from cogs.data.synth import SynthConfig, generate_scene
    from cogs.data.validate import check_scene

    small = dict(frames=12, width=64, height=48, supersample=1, novel_rings=1, novel_per_ring=2, points=500)
    ref = generate_scene(SynthConfig(**small), show_progress=False)
    other = generate_scene(SynthConfig(**small, variant=3), show_progress=False)
    save_scene(other, tmp_path / "v3")
    assert check_scene(tmp_path / "v3") == []
    s = load_scene(tmp_path / "v3")
    assert s.source["config"]["variant"] == 3
    assert np.abs(s.images.astype(np.float32) - ref.images.astype(np.float32)).mean() > 5.0
    assert s.object_masks.reshape(12, -1).any(1).mean() >= 0.8
