"""The three branches and the compositor (issue: branches)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from cogs.branches.build import BranchesConfig, build_human, build_object, build_scene
from cogs.branches.gaussians import GaussianSet
from cogs.branches.human import HumanBranch, HumanConfig, compute_visibility, sample_human_seed
from cogs.data.scene import load_scene
from cogs.geometry.camera import intrinsics_from_fov, look_at
from cogs.geometry.rotations import axis_angle_to_rotmat, quat_to_rotmat
from cogs.model import Model
from cogs.render import rasterize


# -- GaussianSet / PLY ---------------------------------------------------------------------


def _random_set(n=50, degree=1):
    g = torch.Generator().manual_seed(3)
    params = {
        "means": torch.randn(n, 3, generator=g),
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.randn(n, 3, generator=g) - 3,
        "opacities": torch.randn(n, generator=g),
        "sh0": torch.randn(n, 1, 3, generator=g),
    }
    if degree:
        params["shN"] = torch.randn(n, (degree + 1) ** 2 - 1, 3, generator=g)
    return GaussianSet(params, degree)


def test_ply_round_trip_is_exact(tmp_path):
    for degree in (0, 1, 3):
        g = _random_set(degree=degree)
        g.save_ply(tmp_path / f"g{degree}.ply")
        h = GaussianSet.load_ply(tmp_path / f"g{degree}.ply")
        assert h.sh_degree == degree
        for k in g.params:
            assert torch.equal(g.params[k].data, h.params[k].data), k


def test_ply_header_is_the_standard_3dgs_layout(tmp_path):
    g = _random_set(n=7, degree=3)
    g.save_ply(tmp_path / "g.ply")
    raw = (tmp_path / "g.ply").read_bytes()
    header = raw[: raw.index(b"end_header")].decode()
    props = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert props == expected
    assert "format binary_little_endian 1.0" in header
    assert "element vertex 7" in header
    assert all(line.split()[1] == "float" for line in header.splitlines() if line.startswith("property"))


def test_activations_and_concatenation():
    a, b = _random_set(5, 0), _random_set(7, 1)
    c = GaussianSet.cat([a, b])
    assert len(c) == 12 and c.sh_degree == 1
    torch.testing.assert_close(c.scales[:5], torch.exp(a.params["scales"]))
    torch.testing.assert_close(c.quats.norm(dim=1), torch.ones(12))
    assert torch.all((c.opacities > 0) & (c.opacities < 1))
    assert torch.equal(c.params["shN"][:5], torch.zeros(5, 3, 3))
    sel = c.select(torch.tensor([0, 11]))
    assert len(sel) == 2 and torch.equal(sel.means[1], b.means[6])


# -- human ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_human(body_model):
    cfg = HumanConfig(n_gaussians=3000, triplane_resolution=32, triplane_channels=8)
    seed = sample_human_seed(body_model, None, cfg, seed=0)
    T = 3
    return HumanBranch(body_model, body_model.default_shape, seed, torch.zeros(T, 104, 3), torch.zeros(T, 3), cfg)


def test_seed_lies_on_the_canonical_surface_with_tangent_discs(body_model, small_human):
    seed_means = small_human.seed_means
    can = body_model.canonical()
    d = torch.cdist(seed_means[:500], can.vertices).min(1).values
    assert d.max() < 0.03  # on the surface (within a triangle's size)
    R = quat_to_rotmat(small_human.seed_quats)
    s = small_human.seed_scales
    assert torch.all(s[:, 2] < s[:, 0])  # thin along the local z axis ...
    # ... which is the surface normal, so the disc is tangent to the surface.
    seed = sample_human_seed(body_model, None, small_human.cfg, seed=0)
    cos = (R[:, :, 2] * seed.normals).sum(-1).abs()
    assert cos.min() > 0.999


def test_seed_inset_moves_the_centres_inside_along_the_outward_normal(body_model):
    cfg = HumanConfig(n_gaussians=4000)
    on = sample_human_seed(body_model, None, dataclasses.replace(cfg, seed_inset_m=0.0), seed=0)
    inset = sample_human_seed(body_model, None, dataclasses.replace(cfg, seed_inset_m=0.01), seed=0)
    torch.testing.assert_close(inset.means, on.means - 0.01 * on.normals, rtol=0, atol=1e-6)
    # Outward normals: over a closed surface sampled by area, the mean of (x - c) . n is
    # 3 volume / area > 0 (divergence theorem), so -n points into the body.
    assert ((on.means - on.means.mean(0)) * on.normals).sum(-1).mean() > 0.01


def test_untrained_field_reproduces_the_seed(small_human):
    st = small_human.decode()
    torch.testing.assert_close(st.scales, small_human.seed_scales)
    torch.testing.assert_close(st.opacities, small_human.seed_opacities)
    torch.testing.assert_close(st.colors, small_human.seed_colors)
    torch.testing.assert_close(st.weights, small_human.seed_weights, atol=1e-5, rtol=0)
    cos = (st.quats * small_human.seed_quats).sum(-1).abs()
    assert cos.min() > 1 - 1e-6


def test_rest_pose_returns_the_canonical_gaussians(small_human):
    pose, transl = small_human.body.zero_pose()
    st = small_human.decode()
    posed = small_human.posed(pose, transl, st)
    torch.testing.assert_close(posed.means, st.means, atol=1e-5, rtol=0)
    assert (posed.quats * st.quats).sum(-1).abs().min() > 1 - 1e-5


def test_known_bone_rotation_moves_gaussians_and_orientations(small_human):
    h = small_human
    j = h.body.bone_index("lowerleg01.L")
    pose, transl = h.body.zero_pose()
    pose[0, j] = torch.tensor([0.7, 0.0, 0.0])
    st = h.decode()
    posed = h.posed(pose, transl, st)
    head = h.body.canonical().joints[j]
    subtree = [j]
    for b, parent in enumerate(h.body.bone_parents):
        if parent in subtree:
            subtree.append(b)
    rigid = torch.nonzero(st.weights[:, subtree].sum(1) > 0.999).flatten()
    assert len(rigid) > 5
    Rx = axis_angle_to_rotmat(torch.tensor([0.7, 0.0, 0.0]))
    torch.testing.assert_close(posed.means[rigid], (st.means[rigid] - head) @ Rx.T + head, atol=1e-4, rtol=0)
    torch.testing.assert_close(quat_to_rotmat(posed.quats[rigid]), Rx @ quat_to_rotmat(st.quats[rigid]), atol=2e-3, rtol=0)


def test_gradients_flow_to_canonical_parameters_field_and_pose_refinements(small_human):
    h = small_human
    h.zero_grad()
    posed = h.posed_frame(0)
    (posed.means.square().sum() + posed.colors.sum() + posed.scales.sum() + posed.opacities.sum()).backward()
    assert h.means.grad.abs().sum() > 0
    assert h.pose_delta.grad[0].abs().sum() > 0 and h.transl_delta.grad[0].abs().sum() > 0
    assert h.pose_delta.grad[1].abs().sum() == 0  # frame 0 is keyframe 0: the other key gets nothing
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in h.field.parameters())


def test_pose_corrections_interpolate_between_keyframes(small_human):
    h = small_human
    assert h.pose_key_times.tolist() == [0.0, 2.0]  # 3 frames, keys 4 frames apart at most
    with torch.no_grad():
        h.pose_delta[0] = 0.1
        h.pose_delta[1] = 0.3
    try:
        pose, _ = h.frame_pose(1)  # halfway between the keys
        major = [h.body.bone_index(b) for b in h.body.major_bones]
        others = [j for j in range(h.body.n_bones) if j not in major]
        torch.testing.assert_close(pose[0, major], torch.full((len(major), 3), 0.2))
        assert torch.all(pose[0, others] == 0)  # only the major bones are refined
    finally:
        with torch.no_grad():
            h.pose_delta.zero_()


def _back_of_torso(seed) -> torch.Tensor:
    """Seed indices on the torso's back (Anny faces -y), hidden from a camera in front."""
    m = seed.means
    torso = (m[:, 0].abs() < 0.12) & (m[:, 2] > -0.2) & (m[:, 2] < 0.3)
    return torch.nonzero(torso & (seed.normals[:, 1] > 0.9)).flatten()


def test_visibility_scores_and_anchor_gradients(body_model):
    """A Gaussian seen in every frame gets v = 1 and no anchor pull; one always hidden
    (behind the body, or under the object mask) gets v = 0 and is pulled back to the seed."""
    cfg = HumanConfig(n_gaussians=4000, triplane_resolution=16, triplane_channels=4, seed_opacity=0.95,
                      visibility_full_frames=0)
    seed = sample_human_seed(body_model, None, cfg, seed=1)
    T, W, H = 3, 64, 96
    h = HumanBranch(body_model, body_model.default_shape, seed, torch.zeros(T, 104, 3), torch.zeros(T, 3), cfg)
    K = torch.tensor(intrinsics_from_fov(W, H, 60.0), dtype=torch.float32)
    # Anny faces -y: a camera on the -y side sees the front.
    w2c = torch.tensor(look_at([0.0, -3.0, 0.0], [0.0, 0.0, 0.0]), dtype=torch.float32).expand(T, 4, 4)
    human_masks = np.ones((T, H, W), bool)
    object_masks = np.zeros((T, H, W), bool)
    object_masks[:, : H // 3, :] = True  # the object hides the head region in every frame
    person = lambda t: torch.from_numpy(human_masks[t] & ~object_masks[t])  # noqa: E731
    v = compute_visibility(h, [0, 1, 2], w2c, K.expand(T, 3, 3), W, H, person, backend="cpu")
    h.visibility.copy_(v)
    means = h.seed_means
    cam_y = -3.0
    depth = means[:, 1] - cam_y
    uv_row = (K[1, 1] * (-means[:, 2]) / depth + K[1, 2])
    low = uv_row > H / 3 + 4  # well below the object mask
    front = torch.nonzero(low & (seed.normals[:, 1] < -0.9)).flatten()
    back = _back_of_torso(seed)
    head = torch.nonzero((uv_row < H / 3 - 4) & (seed.normals[:, 1] < -0.9)).flatten()
    assert len(front) and len(back) and len(head)
    assert (v[front] == 1).float().mean() > 0.9
    assert v[back].max() == 0
    assert v[head].max() == 0
    i_vis, i_hid = int(front[v[front] == 1][0]), int(back[0])
    with torch.no_grad():
        h.means[i_vis] += 0.05
        h.means[i_hid] += 0.05
    h.zero_grad()
    h.anchor_loss(h.decode()).backward()
    assert h.means.grad[i_vis].abs().sum() == 0
    g = h.means.grad[i_hid]
    assert torch.all(g > 0)  # descending the gradient moves it back towards the seed
    with torch.no_grad():
        h.means[i_vis] -= 0.05
        h.means[i_hid] -= 0.05


# -- compositor -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_branches(tmp_path_factory):
    from tests.fixtures import make_tiny_scene

    root = make_tiny_scene(tmp_path_factory.mktemp("s") / "scene", n_frames=6, width=64, height=48)
    scene = load_scene(root)
    cfg = BranchesConfig()
    cfg.human.n_gaussians = 2000
    cfg.human.triplane_resolution = 16
    built = [build_human(scene, cfg, "cpu"), build_object(scene, cfg, "cpu"), build_scene(scene, cfg)]
    return scene, Model({b.name: b for b in built}, backend="cpu")


def _cam(scene, t):
    return (torch.tensor(scene.cameras.world_to_camera[t], dtype=torch.float32),
            torch.tensor(scene.cameras.K[t], dtype=torch.float32))


def test_branch_alphas_sum_to_the_total_alpha(tiny_branches):
    scene, comp = tiny_branches
    w2c, K = _cam(scene, 1)
    with torch.no_grad():
        out = comp.render(w2c, K, scene.width, scene.height, 1)
    total = sum(out.branch_alpha.values())
    torch.testing.assert_close(total, out.alpha, atol=1e-5, rtol=0)
    assert all(float(a.sum()) > 0 for a in out.branch_alpha.values())


def test_branch_only_render_equals_rendering_that_branch_alone(tiny_branches):
    scene, comp = tiny_branches
    w2c, K = _cam(scene, 2)
    with torch.no_grad():
        for b in ("human", "object", "scene"):
            only = comp.render(w2c, K, scene.width, scene.height, 2, branches=(b,))
            s = comp.splats(2, w2c, (b,))[b]
            ref = rasterize(s.means, s.quats, s.scales, s.opacities, s.rgb, w2c, K, scene.width, scene.height,
                            near=comp.near, far=comp.far, backend="cpu")
            torch.testing.assert_close(only.rgb, ref.colors, atol=1e-6, rtol=0)
            torch.testing.assert_close(only.branch_alpha[b], ref.alpha, atol=1e-6, rtol=0)
            others = [a for k, a in only.branch_alpha.items() if k != b]
            assert all(float(a.abs().max()) == 0 for a in others)


def test_object_follows_its_trajectory(tiny_branches):
    scene, comp = tiny_branches
    o = comp.object
    tr, q = o.frame_pose(3)
    means, _ = o.posed(tr, q)
    c = o.centre
    # The canonical centre maps to the trajectory's translation.
    centroid_canon = o.gaussians.means.mean(0)
    R = quat_to_rotmat(q)
    torch.testing.assert_close(means.mean(0), (centroid_canon - c) @ R.T + tr, atol=1e-5, rtol=0)


def _still_then_moving(T: int = 60, still: int = 25, seed: int = 0) -> torch.Tensor:
    """Positions [T, 3]: at rest for `still` frames (5 mm per-frame jitter, a 1 cm slow
    drift, like an estimate's errors), then moving at 5 cm per frame with a 3-frame pause."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T, dtype=torch.float64)
    speed = torch.where(t < still, 0.0, 0.05)
    speed[40:43] = 0.0  # a pause too short to count as a rest
    x = torch.cumsum(speed, 0)
    pos = torch.stack([x, 0.5 * x, torch.zeros(T, dtype=torch.float64)], -1)
    drift = 0.01 * torch.sin(t / 15.0)[:, None] * torch.tensor([1.0, -1.0, 0.5], dtype=torch.float64)
    return pos + drift + 0.005 * torch.randn(T, 3, generator=g, dtype=torch.float64)


def test_rest_frames_find_a_still_object_under_estimation_noise():
    from cogs.branches.object import rest_frames

    rest = rest_frames(_still_then_moving(), size=0.4)
    assert bool(rest[:22].all()), rest[:25]
    assert not bool(rest[27:].any()), rest[25:]
    # A slow carry (1.2 cm per frame, the synthetic benchmark's last frames) is motion.
    slow = torch.arange(40, dtype=torch.float64)[:, None] * torch.tensor([0.012, 0.0, 0.0], dtype=torch.float64)
    assert not bool(rest_frames(slow, size=0.4).any())


def test_rest_losses_hold_a_resting_object_still_and_leave_the_motion():
    from cogs.branches.object import ObjectBranch, ObjectConfig, fit_initial_trajectory
    from cogs.geometry.rotations import axis_angle_to_quat, quat_geodesic_angle

    T = 60
    prior_t = _still_then_moving(T).float()
    g = torch.Generator().manual_seed(1)
    # the initial rotations wander by a few degrees at rest, then the object turns
    angle = torch.where(torch.arange(T) < 25, 0.0, 0.1 * (torch.arange(T) - 25.0))
    axis_angle = torch.stack([angle, 0.05 * torch.randn(T, generator=g), 0.05 * torch.randn(T, generator=g)], -1)
    prior_q = axis_angle_to_quat(axis_angle)
    cfg = ObjectConfig()
    key_times, p, v, q = fit_initial_trajectory(prior_t.double(), prior_q.double(), cfg)
    pts = 0.15 * torch.randn(200, 3, generator=g)
    gs = GaussianSet.from_points(pts, torch.full_like(pts, 0.5), torch.full((200, 3), 0.01))
    obj = ObjectBranch(gs, torch.zeros(3), key_times, p, v, q, prior_t, prior_q, cfg)
    assert bool(obj.rest[:20].all()) and not bool(obj.rest[30:].any())

    frames = torch.arange(T, dtype=torch.float32)
    with torch.no_grad():
        _, q_moving_before = obj.pose(frames[30:])
    dt0, dq0 = (x.item() for x in obj.rest_losses())
    assert float(dt0) > 1e-3 and float(dq0) > 1e-3
    opt = torch.optim.Adam([obj.key_p, obj.key_v, obj.key_q], lr=2e-3)
    for _ in range(300):
        opt.zero_grad()
        dt, dq = obj.rest_losses()
        (5.0 * dt + 0.5 * dq).backward()
        opt.step()
    dt1, dq1 = (x.item() for x in obj.rest_losses())
    assert float(dt1) < 0.1 * float(dt0) and float(dq1) < 0.1 * float(dq0)
    with torch.no_grad():
        _, q_moving = obj.pose(frames[30:])
    # frames well away from the rest keep their motion
    assert float(quat_geodesic_angle(q_moving, q_moving_before).max()) < 1e-3


def test_the_smoothness_keeps_a_bouncing_ball_bouncing_and_still_resists_new_wiggles():
    # A dribbled ball at 12 fps: down to the floor and back up to the hand every 6 frames.
    # The training's motion terms (pose prior + acceleration, the default weights) must not
    # flatten the bounces the initial trajectory shows (that left the basketball clip's
    # trained ball up to 65 px off its masks), yet still penalise wiggles the training adds.
    from types import SimpleNamespace

    from cogs.branches.object import ObjectBranch, ObjectConfig, fit_initial_trajectory
    from cogs.config import LossWeights

    T = 36
    tau = torch.arange(T, dtype=torch.float64)
    height = 0.9 * (1 - torch.abs(torch.sin(torch.pi * tau / 6.0)))  # 0.9 m at the hand, 0 at the floor
    prior_t = torch.stack([0.02 * tau, torch.full_like(tau, 3.0), height], -1).float()
    prior_q = torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(T, 1)
    floor = (tau % 6 == 3).nonzero().flatten()
    w = LossWeights()
    weights = {"pose_prior": w.pose_prior, "pose_prior_rotation": w.pose_prior_rotation, "acceleration": w.acceleration}
    g = torch.Generator().manual_seed(0)
    pts = 0.1 * torch.randn(100, 3, generator=g)

    def trained(about_initial: bool) -> tuple[ObjectBranch, float]:
        cfg = ObjectConfig(frames_per_keyframe=1.0, smooth_about_initial=about_initial)
        key_times, p, v, q = fit_initial_trajectory(prior_t.double(), prior_q.double(), cfg)
        gs = GaussianSet.from_points(pts, torch.full_like(pts, 0.5), torch.full((100, 3), 0.01))
        obj = ObjectBranch(gs, torch.zeros(3), key_times, p, v, q, prior_t, prior_q, cfg)
        opt = torch.optim.Adam([obj.key_p, obj.key_v], lr=5e-3)
        for _ in range(300):
            opt.zero_grad()
            sum(obj.regularisers(weights, tau.long()).values()).backward()
            opt.step()
        with torch.no_grad():
            tr, _ = obj.pose(tau.float())
        return obj, float((tr[floor, 2] - prior_t[floor, 2]).abs().max())

    kept, lift_kept = trained(True)
    flattened, lift_flat = trained(False)
    assert lift_kept < 0.02 and lift_flat > 0.2, (lift_kept, lift_flat)  # metres above the floor at the bounces
    # Wiggles the training would add on top of the bounces still cost.
    with torch.no_grad():
        acc0, _ = kept.smoothness_losses()
        kept.key_p[::2, 1] += 0.02
        acc1, _ = kept.smoothness_losses()
    assert float(acc1) > 100 * float(acc0) + 1e-6
    # A model saved before the reference existed loads smoothed towards straight lines, as trained.
    state = {k: v for k, v in flattened.state_dict().items() if k != "ref_t"}
    old = ObjectBranch.from_state(state, SimpleNamespace(object=ObjectConfig()))
    assert float(old.ref_t.abs().max()) == 0.0


def test_held_out_interpolation_weights_reproduce_cubic_motion():
    from cogs.branches.held_out import lagrange_neighbours

    trained = [t not in (0, 6, 12) for t in range(20)]
    frames, w = lagrange_neighbours(6, trained, per_side=2, max_gap=3)
    assert frames == [4, 5, 7, 8]
    x, w = torch.tensor(frames, dtype=torch.float64), torch.tensor(w, dtype=torch.float64)
    for f in (lambda s: 1.0 + 0 * s, lambda s: s, lambda s: s**3 - 2 * s**2):
        torch.testing.assert_close((w * f(x)).sum(), f(torch.tensor(6.0, dtype=torch.float64)))
    # one side only (the clip's first frame) or nothing within reach: no interpolation
    assert lagrange_neighbours(0, trained, 2, 3) is None
    far = [t in (2, 15) for t in range(20)]
    assert lagrange_neighbours(8, far, 2, 3) is None
    assert lagrange_neighbours(7, trained, 1, 3)[0] == [5, 8]  # nearest trained on each side


def _jittered_human(body_model, T: int = 40, jitter: float = 0.03, seed: int = 0, speed: float = 0.15,
                    input_weight: float = 0.0, adaptive: bool = False, every: int = 6):
    """A human branch whose input poses are a sinusoidal motion (`speed` radians of phase
    per frame) plus per-frame jitter on the refined bones; the training frames' per-frame
    residuals hold exactly minus that jitter (what an ideal fit finds). Every `every`-th
    frame is held out. Held-out frames keep the fixed share `input_weight` of their input's
    detail, or the clip-decided one with `adaptive`. Returns (branch, true pose, held-out
    frames)."""
    cfg = HumanConfig(n_gaussians=500, triplane_resolution=8, triplane_channels=4, per_frame_pose=True,
                      held_out_input_weight=input_weight, held_out_adaptive=adaptive)
    sd = sample_human_seed(body_model, None, cfg, seed=0)
    g = torch.Generator().manual_seed(seed)
    major = torch.tensor([body_model.bone_index(b) for b in body_model.major_bones])
    t = torch.arange(T, dtype=torch.float32)[:, None, None]
    phase = torch.rand(1, len(major), 3, generator=g) * 6.0
    true = torch.zeros(T, 104, 3)
    true[:, major] = 0.3 * torch.sin(speed * t + phase)
    noisy = true.clone()
    noisy[:, major] += jitter * torch.randn(T, len(major), 3, generator=g)
    test = list(range(0, T, every))
    train = [k for k in range(T) if k not in test]
    h = HumanBranch(body_model, body_model.default_shape, sd, noisy, torch.zeros(T, 3), cfg, train_frames=train)
    with torch.no_grad():
        h.frame_pose_delta[train] = (true - noisy)[train][:, major]
    return h, true, test


def _held_out_error(h, true, test, pose_of=None) -> float:
    """Mean geodesic error (radians) on the refined bones of the held-out frames' poses
    (`pose_of(t)` -> [J, 3]; default: the branch's own `frame_pose`)."""
    from cogs.geometry.rotations import axis_angle_to_quat, quat_geodesic_angle

    pose_of = pose_of or (lambda t: h.frame_pose(t)[0][0])
    major = h.refined_bones
    errs = [quat_geodesic_angle(axis_angle_to_quat(pose_of(t)[major]), axis_angle_to_quat(true[t, major])).mean()
            for t in test[1:]]  # frame 0 has no neighbour before it
    return float(torch.stack(errs).mean())


def test_held_out_pose_leans_on_fitted_neighbours_when_the_input_jitters(body_model):
    h, true, test = _jittered_human(body_model)
    err_in = _held_out_error(h, true, test, pose_of=lambda t: h.base_pose[t])
    assert _held_out_error(h, true, test) < 0.3 * err_in
    # the first frame (neighbours on one side only) keeps its input
    pose0, _ = h.frame_pose(0)
    torch.testing.assert_close(pose0, h.base_pose[:1])


def test_held_out_pose_keeps_a_share_of_its_own_inputs_motion(body_model):
    """Motion too fast for the neighbours' interpolation: a share of the frame's own input
    detail recovers part of what the interpolation misses, at the cost of a share of its
    jitter; with a jitter-free input, all of it gives the frame's own input exactly."""
    err = {w: _held_out_error(*_jittered_human(body_model, jitter=0.01, speed=0.9, input_weight=w)) for w in (0.0, 0.3)}
    assert err[0.3] < 0.85 * err[0.0]
    h, true, test = _jittered_human(body_model, jitter=0.0, speed=0.9, input_weight=1.0)
    for t in test[1:]:
        torch.testing.assert_close(h.frame_pose(t)[0], h.base_pose[t : t + 1], atol=1e-5, rtol=0)
    # and where the input only jitters, the neighbours alone are the better guess
    slow = {w: _held_out_error(*_jittered_human(body_model, input_weight=w)) for w in (0.0, 0.3)}
    assert slow[0.0] < slow[0.3]


def test_adaptive_held_out_share_follows_the_clips_own_noise(body_model):
    """The clip decides the share: where the input only jitters (slow motion), it keeps
    little of it, well below the fixed share's error; where the motion is too fast for the
    interpolation and the jitter small, it keeps far more of the frame's own input; without
    jitter it is the frame's own input exactly."""
    slow = {k: _held_out_error(*_jittered_human(body_model, **kw))
            for k, kw in {"adaptive": {"adaptive": True}, "fixed": {"input_weight": 0.3}}.items()}
    assert slow["adaptive"] < 0.25 * slow["fixed"]
    fast = {k: _held_out_error(*_jittered_human(body_model, jitter=0.003, speed=0.9, **kw))
            for k, kw in {"adaptive": {"adaptive": True}, "fixed": {"input_weight": 0.3}}.items()}
    assert fast["adaptive"] < 0.7 * fast["fixed"]
    h, true, test = _jittered_human(body_model, jitter=0.0, speed=0.9, adaptive=True)
    for t in test[1:]:
        torch.testing.assert_close(h.frame_pose(t)[0], h.base_pose[t : t + 1], atol=1e-5, rtol=0)


def test_adaptive_held_out_share_never_falls_below_the_fixed_one(body_model):
    """`held_out_input_weight` is the adaptive share's floor: a jittering slow input keeps
    exactly it; a fast, clean one keeps more on some bone."""
    from cogs.branches.held_out import detail, lagrange_neighbours
    from cogs.geometry.rotations import axis_angle_to_quat, quat_sign_continuous

    for speed, jitter in ((0.15, 0.03), (0.9, 0.003)):
        h, _, test = _jittered_human(body_model, jitter=jitter, speed=speed, input_weight=0.3, adaptive=True)
        shares = []
        for t in test[1:]:
            nb = lagrange_neighbours(t, h._trained, h.cfg.held_out_neighbours, h.cfg.held_out_max_gap)
            d, d_t = detail(quat_sign_continuous(axis_angle_to_quat(h.base_pose)), h.base_transl, t, nb)
            w, w_t = h._input_shares(d, d_t)
            shares.append(w[h.refined_bones])
            assert float(w.min()) >= 0.3 - 1e-6 and float(w_t) >= 0.3 - 1e-6
        assert (float(torch.stack(shares).max()) > 0.5) == (speed > 0.5)


def test_adaptive_held_out_noise_is_recomputed_when_the_fit_changes(body_model):
    """The noise estimate is cached, but a change of the per-frame fit (a training step)
    is seen: undoing the ideal fit makes the fitted poses agree with the noisy input, the
    noise estimate falls to zero and the held-out frame keeps all of its input."""
    h, _, test = _jittered_human(body_model, adaptive=True)
    before = h._input_noise()[0].clone()
    assert float(before.min()) > 0
    with torch.no_grad():
        h.frame_pose_delta.zero_()
    after = h._input_noise()[0]
    assert float(after.max()) < 1e-6 * float(before.min())
    t = test[2]
    torch.testing.assert_close(h.frame_pose(t)[0][0, h.refined_bones], h.base_pose[t, h.refined_bones],
                               atol=1e-5, rtol=0)


def test_adaptive_held_out_share_falls_back_to_the_fixed_one_on_few_frames(body_model):
    """Too few training frames with neighbours on both sides to estimate the noise: the
    fixed `held_out_input_weight` applies, as with `held_out_adaptive` off."""
    kw = {"T": 7, "every": 3, "jitter": 0.03, "input_weight": 0.3}
    h_adaptive, _, test = _jittered_human(body_model, adaptive=True, **kw)
    h_fixed, _, _ = _jittered_human(body_model, **kw)
    assert h_adaptive._input_noise() is None
    torch.testing.assert_close(h_adaptive.frame_pose(3)[0], h_fixed.frame_pose(3)[0])


def test_without_per_frame_pose_held_out_frames_keep_their_corrected_input(body_model):
    h, _, test = _jittered_human(body_model)
    h.cfg = dataclasses.replace(h.cfg, per_frame_pose=False)
    for t in test:
        torch.testing.assert_close(h.frame_pose(t)[0], h.base_pose[t : t + 1])


def test_visibility_saturates_at_the_full_frame_count(body_model):
    """`visibility_full_frames` = N: a Gaussian seen in N frames counts as observed (v = 1)
    however many frames miss it; one never seen stays at v = 0. With 0 it is the fraction."""
    T, W, H = 3, 64, 96
    K = torch.tensor(intrinsics_from_fov(W, H, 60.0), dtype=torch.float32).expand(T, 3, 3)
    w2c = torch.tensor(look_at([0.0, -3.0, 0.0], [0.0, 0.0, 0.0]), dtype=torch.float32).expand(T, 4, 4)
    human_masks = np.zeros((T, H, W), bool)
    human_masks[0] = True  # only the first frame shows the person
    object_masks = np.zeros((T, H, W), bool)
    cfg = HumanConfig(n_gaussians=4000, triplane_resolution=16, triplane_channels=4, seed_opacity=0.95)
    seed = sample_human_seed(body_model, None, cfg, seed=1)
    h = HumanBranch(body_model, body_model.default_shape, seed, torch.zeros(T, 104, 3), torch.zeros(T, 3), cfg)
    scores = {}
    for n_full in (0, 1):
        h.cfg = dataclasses.replace(cfg, visibility_full_frames=n_full)
        person = lambda t: torch.from_numpy(human_masks[t] & ~object_masks[t])  # noqa: E731
        scores[n_full] = compute_visibility(h, [0, 1, 2], w2c, K, W, H, person, backend="cpu")
    front = torch.nonzero(seed.normals[:, 1] < -0.9).flatten()
    back = _back_of_torso(seed)
    seen = front[scores[0][front] > 0]
    assert len(seen) > 0.8 * len(front) and len(back)
    torch.testing.assert_close(scores[0][seen], torch.full((len(seen),), 1 / 3))
    assert torch.all(scores[1][seen] == 1)
    assert scores[0][back].max() == 0 and scores[1][back].max() == 0


def test_moving_the_human_branch_alone_moves_its_body_model(body_model):
    """The body model is kept out of the module tree (shared, not checkpointed); the trainer
    moves each branch it builds on its own, so `branch.to(device)` must move the body too
    (on CUDA it did not, and the first visibility pass failed). The meta device stands in
    for a GPU here; the CUDA test in test_model.py trains there."""
    cfg = HumanConfig(n_gaussians=500, triplane_resolution=8, triplane_channels=4)
    seed = sample_human_seed(body_model, None, cfg, seed=0)
    human = HumanBranch(body_model, body_model.default_shape, seed, torch.zeros(2, 104, 3), torch.zeros(2, 3), cfg)
    assert human.body.device.type == "cpu"
    human.to("meta")
    assert human.means.device.type == "meta" and human.body.device.type == "meta"
    assert body_model.device.type == "cpu"  # the shared host model itself stays where it was


def _bounced_object(weight: float, confidence: float, held: int = 10, T: int = 21):
    """An object moving along a straight line whose initial pose at frame `held` (outside
    the training split) is 0.2 m above the line and turned 30 degrees: a bounce between
    training frames that the keyframed trajectory, fitted to the line, does not show."""
    from cogs.branches.object import ObjectBranch, ObjectConfig, fit_initial_trajectory
    from cogs.geometry.rotations import axis_angle_to_quat, quat_multiply

    line_t = torch.arange(T, dtype=torch.float32)[:, None] * torch.tensor([0.05, 0.0, 0.0]) + torch.tensor([0.0, 0.0, 2.0])
    line_q = axis_angle_to_quat(torch.arange(T, dtype=torch.float32)[:, None] * torch.tensor([0.0, 0.02, 0.0]))
    cfg = ObjectConfig(held_out_input_weight=weight)
    key_times, p, v, q = fit_initial_trajectory(line_t.double(), line_q.double(), cfg)
    prior_t, prior_q = line_t.clone(), line_q.clone()
    prior_t[held] += torch.tensor([0.0, 0.2, 0.0])
    bump = axis_angle_to_quat(torch.tensor([0.0, 0.0, math.radians(30.0)]))
    prior_q[held] = quat_multiply(bump, prior_q[held])
    trained = torch.ones(T, dtype=torch.bool)
    trained[held] = False
    conf = torch.ones(T)
    conf[held] = confidence
    pts = 0.1 * torch.randn(50, 3, generator=torch.Generator().manual_seed(0))
    gs = GaussianSet.from_points(pts, torch.full_like(pts, 0.5), torch.full((50, 3), 0.01))
    obj = ObjectBranch(gs, torch.zeros(3), key_times, p, v, q, prior_t, prior_q, cfg, trained=trained, confidence=conf)
    return obj, prior_t, prior_q, line_t, line_q


def test_a_held_out_object_pose_follows_its_own_initial_pose_by_weight_and_confidence():
    """A held-out frame moves from the trajectory to its own initial pose by the weight
    times its confidence; a lost frame (confidence below `min_confidence`) and every
    training frame stay on the trajectory."""
    from cogs.geometry.rotations import quat_geodesic_angle

    held = 10
    with torch.no_grad():
        for weight, conf, share in ((1.0, 1.0, 1.0), (1.0, 0.5, 0.5), (0.5, 1.0, 0.5), (0.0, 1.0, 0.0), (1.0, 0.1, 0.0)):
            obj, prior_t, prior_q, line_t, line_q = _bounced_object(weight, conf, held)
            on_line_t, on_line_q = obj.pose(torch.tensor([float(held)]))
            assert float((on_line_t[0] - line_t[held]).norm()) < 1e-3  # the trajectory misses the bounce
            tr, q = obj.frame_pose(held)
            assert torch.allclose(tr, line_t[held] + share * torch.tensor([0.0, 0.2, 0.0]), atol=2e-3), (weight, conf, tr)
            turned = math.degrees(float(quat_geodesic_angle(q[None], on_line_q)))
            assert abs(turned - 30.0 * share) < 0.5, (weight, conf, turned)
            for t in (held - 1, held + 1, 0):
                a, b = obj.frame_pose(t), obj.pose(torch.tensor([float(t)]))
                assert torch.equal(a[0], b[0][0]) and torch.equal(a[1], b[1][0])
            all_t, all_q = obj.frame_poses()
            assert torch.allclose(all_t[held], tr) and torch.allclose(all_q[held], q)


def test_object_held_out_frames_survive_a_save_and_an_older_state_keeps_the_trajectory():
    """The training split and confidences are saved with the branch; a state written
    before they existed loads with every frame trained (posed on the trajectory, as then)."""
    from cogs.branches.object import ObjectBranch
    from cogs.config import TrainConfig

    obj, *_ = _bounced_object(1.0, 1.0)
    state = {k: v.clone() for k, v in obj.state_dict().items()}
    branches = TrainConfig().branches
    branches.object.held_out_input_weight = 1.0
    again = ObjectBranch.from_state(state, branches)
    assert torch.equal(again.trained, obj.trained) and torch.equal(again.input_confidence, obj.input_confidence)
    with torch.no_grad():
        assert torch.allclose(again.frame_pose(10)[0], obj.frame_pose(10)[0])
        older = {k: v for k, v in state.items() if k not in ("trained", "input_confidence")}
        old = ObjectBranch.from_state(older, branches)
        assert bool(old.trained.all())
        assert torch.equal(old.frame_pose(10)[0], old.pose(torch.tensor([10.0]))[0][0])
