"""Build the initialised branches from a native scene's inputs (no ground truth).

Initialisation runs on the host (the same seeds and colours whatever device trains);
`Model.to(device)` moves the result. The ablation variants of the seeds (CoGS Table:
"no human prior seed", "no object seed") are initialisations too and live here.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import torch

from cogs.body import load_body_model
from cogs.branches.gaussians import GaussianSet, rgb_to_sh0
from cogs.branches.human import HumanBranch, HumanConfig, HumanSeed, sample_human_seed
from cogs.branches.object import ObjectBranch, ObjectConfig, carve_visual_hull, fit_initial_trajectory
from cogs.branches.scene import SceneBranch, SceneConfig
from cogs.branches.splatback import splat_statistics
from cogs.data.scene import Scene
from cogs.errors import UserError
from cogs.geometry.rotations import quat_to_rotmat, rotmat_from_two_vectors, rotmat_to_quat
from cogs.geometry.splines import sample_trajectory

log = logging.getLogger(__name__)

CPU = torch.device("cpu")


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


def _host(a: np.ndarray, dtype=torch.float32) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a), dtype=dtype, device=CPU)


def _frame_tensors(scene: Scene, frames: list[int], person: bool):
    """Images [F, H, W, 3] in [0, 1], mask weights [F, H, W] (the person where the object
    does not hide it, or the object), cameras of `frames` (only these frames converted)."""
    images = torch.from_numpy(np.ascontiguousarray(scene.images[frames])).float() / 255.0
    om = scene.object_masks[frames]
    masks = scene.human_masks[frames] & ~om if person else om
    weight = torch.from_numpy(np.ascontiguousarray(masks)).float()
    w2c = _host(scene.cameras.world_to_camera[frames])
    Ks = _host(scene.cameras.K[frames])
    return images, weight, w2c, Ks


def _colors_from_frames(n: int, per_frame, images: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """[n, 3] weight-averaged colours from the splat-back statistics of each frame; the
    masks' mean colour where a Gaussian was never seen."""
    num = torch.zeros(n, 3, device=CPU)
    den = torch.zeros(n, device=CPU)
    for vis, col in per_frame:
        num += col
        den += vis
    mean_col = (images * weight[..., None]).sum((0, 1, 2)) / weight.sum().clamp_min(1)
    ok = den > 1e-3
    out = mean_col.expand(len(den), 3).clone()
    out[ok] = (num[ok] / den[ok, None]).clamp(0, 1)
    return out, float((den > 1e-3).float().mean())


def build_human(scene: Scene, cfg: BranchesConfig, backend: str = "auto", random_seed: bool = False) -> HumanBranch:
    """The human seed on the canonical body surface (or, `random_seed`, the ablation's
    cloud in the body's box), coloured from the frames by splatting back."""
    body = load_body_model(scene.body.model)
    shape = _host(scene.body.shape)
    seed = random_human_seed(body, shape, cfg) if random_seed else sample_human_seed(body, shape, cfg.human, seed=cfg.seed)
    human = HumanBranch(body, shape, seed, _host(scene.body.pose), _host(scene.body.transl), cfg.human,
                        train_frames=list(scene.split["train"]))
    frames = _frames_for_color(scene.split["train"], cfg.color_init_frames)
    images, weight, w2c, Ks = _frame_tensors(scene, frames, person=True)

    def stats():
        with torch.no_grad():
            state = human.decode()
        for i, t in enumerate(frames):
            with torch.no_grad():
                p = human.posed_frame(t, state)
            vis, col, _ = splat_statistics(p.means, p.quats, p.scales, p.opacities, w2c[i], Ks[i],
                                           scene.width, scene.height, weight[i], images[i], backend)
            yield vis, col

    colors, seen = _colors_from_frames(len(human), stats(), images, weight)
    human.seed_colors.copy_(colors)
    log.info("human: %d seed Gaussians, %.0f%% coloured from the frames", len(human), 100 * seen)
    return human


def random_human_seed(body, shape: torch.Tensor, cfg: BranchesConfig) -> HumanSeed:
    """Ablation "no human prior seed": the same number of Gaussians spread uniformly in the
    canonical body's bounding box, isotropic, with nearest-vertex skinning weights."""
    can = body.canonical(shape)
    n = cfg.human.n_gaussians
    lo, hi = can.vertices.min(0).values, can.vertices.max(0).values
    g = torch.Generator(device=CPU).manual_seed(cfg.seed)
    means = lo + (hi - lo) * torch.rand(n, 3, generator=g, device=CPU)
    nearest = torch.cdist(means, can.vertices).argmin(1)
    spacing = float(((hi - lo).prod() / n) ** (1 / 3))
    quats = torch.zeros(n, 4, device=CPU)
    quats[:, 0] = 1
    return HumanSeed(means=means, quats=quats, scales=torch.full((n, 3), 0.5 * spacing, device=CPU),
                     opacities=torch.full((n,), 0.1, device=CPU), colors=torch.full((n, 3), 0.5, device=CPU),
                     weights=can.weights[nearest].clone(), normals=torch.zeros(n, 3, device=CPU))


def object_train_frames(scene: Scene, min_confidence: float) -> list[int]:
    """The training frames whose object mask may supervise the object (its confidence at
    least `min_confidence`); a `UserError` naming the scene when there is none."""
    trusted = scene.object_trusted(min_confidence)
    frames = [int(t) for t in scene.split["train"] if trusted[t]]
    if not frames:
        raise UserError(f"scene {scene.root}: no training frame has an object confidence of at least "
                        f"{min_confidence:g} (object.json): the object cannot be supervised; check the object "
                        "masks, or lower branches.object.min_confidence")
    return frames


def build_object(scene: Scene, cfg: BranchesConfig, backend: str = "auto",
                 randomise: torch.Generator | None = None) -> ObjectBranch | None:
    """Keyframes fitted to the initial poses and Gaussians on the voted visual hull,
    coloured from the frames; with `randomise` (a generator), the ablation's random cloud
    round the centre instead of the hull. None when the scene has no object."""
    if not scene.has_object:
        return None
    ocfg = cfg.object
    prior_t = _host(scene.object.translations, torch.float64)
    prior_q = _host(scene.object.quats, torch.float64)
    key_times, p, v, q = fit_initial_trajectory(prior_t, prior_q, ocfg)
    tau = torch.arange(scene.n_frames, dtype=torch.float64, device=CPU)
    tr, qs = sample_trajectory(key_times, p, v, q, tau)
    R = quat_to_rotmat(qs).numpy()
    centre = np.asarray(scene.object.centre, dtype=np.float64)
    train = object_train_frames(scene, ocfg.min_confidence)
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
    xyz = _host(pts)
    n = _host(normals)
    quats = rotmat_to_quat(rotmat_from_two_vectors(torch.tensor([0.0, 0.0, 1.0], device=CPU).expand_as(n), n))
    scales = torch.tensor([0.7, 0.7, 0.25], device=CPU) * voxel
    g = GaussianSet.from_points(xyz, torch.full_like(xyz, 0.5), scales.expand(len(xyz), 3).clone(),
                                opacity=ocfg.init_opacity, quats=quats, sh_degree=ocfg.sh_degree)
    in_split = torch.zeros(scene.n_frames, dtype=torch.bool, device=CPU)
    in_split[list(scene.split["train"])] = True
    obj = ObjectBranch(g, _host(centre, torch.float64), key_times, p, v, q, prior_t, prior_q, ocfg,
                       trained=in_split, confidence=_host(scene.object_confidence))

    frames = _frames_for_color(train, cfg.color_init_frames)
    images, weight, w2c, Ks = _frame_tensors(scene, frames, person=False)

    def stats():
        for i, t in enumerate(frames):
            with torch.no_grad():
                tt, qq = obj.frame_pose(t)
                means, quats = obj.posed(tt, qq)
            vis, col, _ = splat_statistics(means, quats, g.scales, g.opacities, w2c[i], Ks[i],
                                           scene.width, scene.height, weight[i], images[i], backend)
            yield vis, col

    rgb, _ = _colors_from_frames(len(obj), stats(), images, weight)
    with torch.no_grad():
        g.params["sh0"].copy_(rgb_to_sh0(rgb))
    log.info("object: %d Gaussians on a visual hull (voxel %.1f cm), %d keyframes", len(obj), 100 * voxel, len(key_times))
    if randomise is not None:
        _randomise_object(obj, randomise)
    return obj


def _randomise_object(obj: ObjectBranch, gen: torch.Generator) -> None:
    """Ablation "no object seed": a random cloud of the same size around the centre."""
    with torch.no_grad():
        m = obj.gaussians.params["means"]
        r = float((m - obj.centre).norm(dim=1).max())
        d = torch.randn(m.shape, generator=gen, device=gen.device).to(m.device)
        u = torch.rand(len(m), 1, generator=gen, device=gen.device).to(m.device)
        m.copy_(obj.centre + r * d / d.norm(dim=1, keepdim=True) * u ** (1 / 3))
        obj.gaussians.params["sh0"].zero_()


def build_scene(scene: Scene, cfg: BranchesConfig) -> SceneBranch:
    planes = None
    if scene.planes is not None:
        from cogs.geometry.planes import Plane

        planes = [Plane(np.asarray(p.normal, np.float64), float(p.offset), np.zeros(0, np.int64)) for p in scene.planes]
    sb = SceneBranch.from_points(scene.points_xyz, scene.points_rgb, cfg.scene, planes, device=CPU)
    log.info("scene: %d Gaussians from sparse points, %d planes", len(sb), len(sb.planes))
    return sb


def build_branch(name: str, scene: Scene, cfg: BranchesConfig, backend: str = "auto", seeded: bool = True,
                 generator: torch.Generator | None = None):
    """The named branch initialised from `scene` (None where the scene has nothing for it).
    `seeded` False gives the ablation's unseeded start (human: a cloud in the body's box;
    object: a random cloud round its centre, drawn from `generator`)."""
    if name == "human":
        return build_human(scene, cfg, backend, random_seed=not seeded)
    if name == "object":
        return build_object(scene, cfg, backend, randomise=None if seeded else generator)
    if name == "scene":
        return build_scene(scene, cfg)
    raise KeyError(f"no initialisation for a branch named {name!r}")
