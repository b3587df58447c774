"""Build the three initialised branches from a native scene's inputs (no ground truth)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import torch

from cogs.body import load_body_model
from cogs.branches.gaussians import GaussianSet
from cogs.branches.human import HumanBranch, HumanConfig, HumanSeed, sample_human_seed
from cogs.branches.object import ObjectBranch, ObjectConfig, carve_visual_hull, fit_initial_trajectory
from cogs.branches.scene import SceneBranch, SceneConfig
from cogs.branches.splatback import splat_statistics
from cogs.data.scene import Scene
from cogs.geometry.rotations import quat_to_rotmat, rotmat_from_two_vectors, rotmat_to_quat
from cogs.geometry.splines import sample_trajectory

log = logging.getLogger(__name__)


@dataclass
class BranchesConfig:
    human: HumanConfig = field(default_factory=HumanConfig)
    object: ObjectConfig = field(default_factory=ObjectConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    color_init_frames: int = 24
    """Training frames used to colour new Gaussians by splatting the images back."""
    seed: int = 0


def _frames_for_color(train: list[int], n: int) -> list[int]:
    if len(train) <= n:
        return list(train)
    idx = np.linspace(0, len(train) - 1, n).round().astype(int)
    return [train[i] for i in idx]


def _accumulate_colors(n: int, per_frame) -> tuple[torch.Tensor, torch.Tensor]:
    num = torch.zeros(n, 3)
    den = torch.zeros(n)
    for vis, col in per_frame:
        num += col
        den += vis
    return num, den


def _resolve(num: torch.Tensor, den: torch.Tensor, fallback: torch.Tensor) -> torch.Tensor:
    ok = den > 1e-3
    out = fallback.expand(len(den), 3).clone()
    out[ok] = (num[ok] / den[ok, None]).clamp(0, 1)
    return out


def build_human(scene: Scene, cfg: BranchesConfig, backend: str = "auto", seed: HumanSeed | None = None) -> HumanBranch:
    body = load_body_model(scene.body.model)
    shape = torch.as_tensor(scene.body.shape, dtype=torch.float32)
    if seed is None:
        seed = sample_human_seed(body, shape, cfg.human, seed=cfg.seed)
    human = HumanBranch(
        body, shape, seed,
        torch.as_tensor(scene.body.pose), torch.as_tensor(scene.body.transl), cfg.human,
        train_frames=list(scene.split["train"]),
    )
    images = torch.as_tensor(scene.images).float() / 255.0
    frames = _frames_for_color(scene.split["train"], cfg.color_init_frames)
    w2c = torch.as_tensor(scene.cameras.world_to_camera, dtype=torch.float32)
    Ks = torch.as_tensor(scene.cameras.K, dtype=torch.float32)
    weight = torch.as_tensor(scene.human_masks & ~scene.object_masks).float()

    def stats():
        with torch.no_grad():
            state = human.decode()
        for t in frames:
            with torch.no_grad():
                p = human.posed_frame(t, state)
            vis, col, _ = splat_statistics(p.means, p.quats, p.scales, p.opacities, w2c[t], Ks[t],
                                           scene.width, scene.height, weight[t], images[t], backend)
            yield vis, col

    num, den = _accumulate_colors(len(human), stats())
    mean_col = (images[frames] * weight[frames, ..., None]).sum((0, 1, 2)) / weight[frames].sum().clamp_min(1)
    human.seed_colors.copy_(_resolve(num, den, mean_col))
    log.info("human: %d seed Gaussians, %.0f%% coloured from the frames", len(human), 100 * float((den > 1e-3).float().mean()))
    return human


def build_object(scene: Scene, cfg: BranchesConfig, backend: str = "auto") -> ObjectBranch | None:
    if not scene.has_object:
        return None
    ocfg = cfg.object
    prior_t = torch.as_tensor(scene.object.translations, dtype=torch.float64)
    prior_q = torch.as_tensor(scene.object.quats, dtype=torch.float64)
    key_times, p, v, q = fit_initial_trajectory(prior_t, prior_q, ocfg)
    tau = torch.arange(scene.n_frames, dtype=torch.float64)
    tr, qs = sample_trajectory(key_times, p, v, q, tau)
    R = quat_to_rotmat(qs).numpy()
    centre = np.asarray(scene.object.centre, dtype=np.float64)
    train = scene.split["train"]
    pts, normals, voxel = carve_visual_hull(
        scene.object_masks, scene.human_masks, scene.cameras.K, scene.cameras.world_to_camera,
        tr.numpy(), R, centre, train, ocfg,
    )
    rng = np.random.default_rng(cfg.seed)
    if len(pts) == 0:
        log.warning("object: the visual hull is empty (masks and initial poses disagree); starting from a small sphere")
        d = rng.normal(size=(2000, 3))
        normals = d / np.linalg.norm(d, axis=1, keepdims=True)
        pts = centre + 0.05 * normals
        voxel = 0.01
    if len(pts) > ocfg.max_gaussians:
        keep = rng.choice(len(pts), ocfg.max_gaussians, replace=False)
        pts, normals = pts[keep], normals[keep]
    pts = pts + rng.uniform(-0.25, 0.25, pts.shape) * voxel
    xyz = torch.as_tensor(pts, dtype=torch.float32)
    n = torch.as_tensor(normals, dtype=torch.float32)
    quats = rotmat_to_quat(rotmat_from_two_vectors(torch.tensor([0.0, 0.0, 1.0]).expand_as(n), n))
    scales = torch.tensor([0.7, 0.7, 0.25]) * voxel
    g = GaussianSet.from_points(xyz, torch.full_like(xyz, 0.5), scales.expand(len(xyz), 3).clone(),
                                opacity=ocfg.init_opacity, quats=quats, sh_degree=ocfg.sh_degree)
    obj = ObjectBranch(g, torch.as_tensor(centre), key_times, p, v, q, prior_t, prior_q, ocfg)

    images = torch.as_tensor(scene.images).float() / 255.0
    frames = _frames_for_color(train, cfg.color_init_frames)
    w2c = torch.as_tensor(scene.cameras.world_to_camera, dtype=torch.float32)
    Ks = torch.as_tensor(scene.cameras.K, dtype=torch.float32)
    weight = torch.as_tensor(scene.object_masks).float()

    def stats():
        for t in frames:
            with torch.no_grad():
                tt, qq = obj.frame_pose(t)
                means, quats = obj.posed(tt, qq)
            vis, col, _ = splat_statistics(means, quats, g.scales, g.opacities, w2c[t], Ks[t],
                                           scene.width, scene.height, weight[t], images[t], backend)
            yield vis, col

    num, den = _accumulate_colors(len(obj), stats())
    mean_col = (images[frames] * weight[frames, ..., None]).sum((0, 1, 2)) / weight[frames].sum().clamp_min(1)
    rgb = _resolve(num, den, mean_col)
    with torch.no_grad():
        g.params["sh0"].copy_(((rgb - 0.5) / 0.28209479177387814)[:, None, :])
    log.info("object: %d Gaussians on a visual hull (voxel %.1f cm), %d keyframes", len(obj), 100 * voxel, len(key_times))
    return obj


def build_scene(scene: Scene, cfg: BranchesConfig) -> SceneBranch:
    planes = None
    if scene.planes is not None:
        from cogs.geometry.planes import Plane

        planes = [Plane(np.asarray(p.normal, np.float64), float(p.offset), np.zeros(0, np.int64)) for p in scene.planes]
    sb = SceneBranch.from_points(scene.points_xyz, scene.points_rgb, cfg.scene, planes)
    log.info("scene: %d Gaussians from sparse points, %d planes", len(sb), len(sb.planes))
    return sb


def build_branches(scene: Scene, cfg: BranchesConfig | None = None, backend: str = "auto"):
    """(human, object or None, scene) initialised from the scene's inputs."""
    cfg = cfg or BranchesConfig()
    return build_human(scene, cfg, backend), build_object(scene, cfg, backend), build_scene(scene, cfg)
