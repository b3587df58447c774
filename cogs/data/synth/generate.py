"""`generate_scene`: the synthetic benchmark scene, from script to a native `Scene`.

Stages (each timed into `scene.source["timings"]`):

1. body model + choreography (`motion.py`): true body pose, box trajectory, camera path;
2. room and baked textures (`room.py`, `textures.py`);
3. skinning of every frame;
4. rendering of every frame with the project's own rasterizer (`render.py`): RGB,
   labels -> human/object masks, depth;
5. novel views: rings of cameras around the person at a few frames;
6. inputs as a pipeline would produce them (`noise.py`, `points.py`): noisy body poses,
   object trajectory, cameras and masks; SfM-like sparse points of the static room.

The images are exact renders; everything else in the scene's main files is noisy, and the
exact values are in `scene.gt`. Same seed, same arrays (and files, except the timings).
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass

import numpy as np
import torch

from cogs.data.scene import BodyTrack, CameraTrack, GroundTruth, NovelViews, ObjectTrack, Scene, default_frame_ids
from cogs.data.synth import textures as tx
from cogs.data.synth.config import SynthConfig
from cogs.data.synth.mesh import HUMAN, OBJECT, Mesh, box, concat, vertex_normals
from cogs.data.synth.motion import SCRIPT_SECONDS, Choreography, Motion, novel_cameras
from cogs.data.synth.render import SceneMesh, View, render_view
from cogs.data.synth.room import Room, build_room, inside_free_space
from cogs.geometry.camera import camera_center, intrinsics_from_fov
from cogs.geometry.rotations import rotmat_to_quat

GENERATOR = "cogs.data.synth"
GENERATOR_VERSION = 1


def hosnerf_split(n: int) -> dict[str, list[int]]:
    """hosnerf-16: test = the first 16 of every (n // 16)-th frame, train = the rest.

    Clips of 16 frames or fewer hold out every other frame so training keeps frames.
    """
    if n <= 16:
        test = list(range(0, n, 2))
    else:
        test = list(range(0, n, n // 16))[:16]
    held = set(test)
    return {"train": [i for i in range(n) if i not in held], "test": test}


def continuous_quats(R: np.ndarray) -> np.ndarray:
    """[T, 3, 3] -> [T, 4] wxyz, signs chosen so consecutive quaternions have dot >= 0."""
    q = rotmat_to_quat(torch.from_numpy(np.ascontiguousarray(R))).numpy()
    for t in range(1, len(q)):
        if q[t] @ q[t - 1] < 0:
            q[t] = -q[t]
    return q


@dataclass
class Assets:
    """Everything that does not change from frame to frame."""

    model: object  # BodyModel
    choreo: Choreography
    shape: np.ndarray  # [6]
    faces: np.ndarray  # [F, 3] body triangles
    canonical: np.ndarray  # [V, 3] canonical body vertices (texture coordinates)
    parts: np.ndarray  # [V, P] body-part one-hots
    layout: tx.BodyLayout
    room: Room
    box: Mesh  # object in its local frame (centred)
    baked: tx.BakedTextures  # room textures + -1 for body and box faces

    def scene_mesh(self, body_vertices: np.ndarray, box_R: np.ndarray, box_t: np.ndarray,
                   with_body: bool = True, with_object: bool = True, with_room: bool = True) -> SceneMesh:
        """World-space mesh of one instant: room + posed body + posed box."""
        meshes, parts, face_tex = [], [], []
        if with_room:
            meshes.append(self.room.mesh)
            parts.append(np.zeros((len(self.room.mesh.vertices), self.parts.shape[1])))
            face_tex.append(self.baked.face_tex)
        if with_body:
            F = len(self.faces)
            meshes.append(Mesh(body_vertices, self.faces, vertex_normals(body_vertices, self.faces), self.canonical,
                               np.full(F, tx.BODY, np.int32), np.full(F, HUMAN, np.int8)))
            parts.append(self.parts)
            face_tex.append(np.full(F, -1, np.int32))
        if with_object:
            meshes.append(self.box.transformed(box_R, box_t))
            parts.append(np.zeros((len(self.box.vertices), self.parts.shape[1])))
            face_tex.append(np.full(self.box.n_faces, -1, np.int32))
        baked = tx.BakedTextures(np.concatenate(face_tex), self.baked.data, self.baked.meta)
        return SceneMesh(concat(meshes), np.concatenate(parts), self.layout, baked)


@functools.lru_cache(maxsize=1)
def _room_and_textures() -> tuple[Room, tx.BakedTextures]:
    room = build_room()
    return room, tx.bake(room.mesh.material, room.mesh.texcoords, room.mesh.faces)


@functools.lru_cache(maxsize=2)
def _choreography(shape: tuple[float, ...], variant: int = 0) -> Choreography:
    from cogs.body import load_body_model

    return Choreography(load_body_model("anny"), np.asarray(shape, dtype=np.float64), variant)


def build_assets(config: SynthConfig) -> Assets:
    """Frame-independent assets (the room, its baked textures and the choreography are
    pure functions of the configuration and cached per process)."""
    from cogs.body import load_body_model

    model = load_body_model("anny")
    shape = np.asarray(config.shape, dtype=np.float64)
    can = model.canonical(torch.tensor(shape, dtype=torch.float32))
    cv = can.vertices.double().numpy()
    room, baked = _room_and_textures()
    return Assets(
        model=model,
        choreo=_choreography(tuple(float(s) for s in config.shape), config.variant),
        shape=shape,
        faces=can.faces.numpy().astype(np.int64),
        canonical=cv,
        parts=tx.body_part_weights(model.bone_names, can.weights.numpy()),
        layout=tx.BodyLayout.from_joints(model.bone_names, can.joints.numpy(), cv),
        room=room,
        box=box(-tx.BOX_SIZE / 2, tx.BOX_SIZE / 2, tx.OBJECT_BOX, OBJECT),
        baked=baked,
    )


def novel_frames(n: int, rings: int) -> np.ndarray:
    """Frames of the novel-view rings: spread over the clip (20% .. 92%)."""
    return np.unique(np.clip(np.rint(np.linspace(0.2, 0.92, rings) * (n - 1)).astype(np.int64), 0, n - 1))


SYNTH_BASE_BYTES = int(1.1 * 1024**3)
"""The generator before any frame: Python, torch, numba's kernels, Anny and the baked room."""
HELD_BYTES_PER_PIXEL = 13
"""What the generator holds per pixel of every frame until the scene is written: RGB, two
label buffers, float32 depth, and the true and noisy human and object masks."""
NOVEL_BYTES_PER_PIXEL = 10
"""Per pixel of every novel view: RGB, label, float32 depth, two masks."""
RENDER_BYTES_PER_SAMPLE = 180
"""One view's rasterization and shading buffers per sample (``supersample``^2 per pixel)."""


def peak_bytes(cfg: SynthConfig) -> int:
    """The generator's peak memory for ``cfg``: it holds every frame until the scene is
    written. Measured with /usr/bin/time -v on the 2-core machines (20 frames of 256x192:
    858,232 kB; 3 of 512x384: 1,094,184 kB with numba's cache warm, 1,162,300 kB cold, and
    1,345,268 kB in a fresh clone's first run; 2 of 1024x1024 with 16 novel views:
    2,672,388 kB; 300 of 960x540: 3,162,488 kB; 600 of 1024x1024: 9.5 GiB) and rounded up:
    the estimate is above each of them."""
    px = cfg.width * cfg.height
    views = len(novel_frames(cfg.frames, cfg.novel_rings)) * cfg.novel_per_ring
    return (SYNTH_BASE_BYTES + cfg.frames * px * HELD_BYTES_PER_PIXEL + views * px * NOVEL_BYTES_PER_PIXEL
            + px * cfg.supersample**2 * RENDER_BYTES_PER_SAMPLE)


def generate_scene(config: SynthConfig | None = None, show_progress: bool = True) -> Scene:
    """Generate the synthetic scene in memory (pixels set; `save_scene` writes it)."""
    from cogs.data.synth import noise as nz
    from cogs.data.synth import points as pts

    cfg = config or SynthConfig()
    if cfg.frames < 2:
        raise ValueError("the synthetic clip needs at least 2 frames")
    if cfg.supersample < 1 or cfg.supersample % 2 == 0:
        raise ValueError("supersample must be a positive odd number")
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    T, W, H, ss = cfg.frames, cfg.width, cfg.height, cfg.supersample

    t0 = time.perf_counter()
    assets = build_assets(cfg)
    timings["assets"] = time.perf_counter() - t0
    body_build = float(getattr(assets.model, "build_seconds", float("nan")))

    t0 = time.perf_counter()
    mo: Motion = assets.choreo.evaluate(T)
    timings["motion"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    A = assets.choreo.rig.transforms(mo.pose, mo.transl)
    V = assets.choreo.rig.vertices_posed(A)
    timings["skinning"] = time.perf_counter() - t0

    K = intrinsics_from_fov(W, H, cfg.fov_deg)
    split = hosnerf_split(T)

    # -- training frames ---------------------------------------------------------------------
    t0 = time.perf_counter()
    images = np.empty((T, H, W, 3), np.uint8)
    labels = np.empty((T, H, W), np.int8)
    centre_labels = np.empty((T, H, W), np.int8)
    depth = np.empty((T, H, W), np.float32)
    body_face0 = assets.room.mesh.n_faces
    seen = np.zeros(len(assets.faces), np.int64)
    train_set = set(split["train"])
    with _Progress(show_progress, "render frames", T) as bar:
        for t in range(T):
            sm = assets.scene_mesh(V[t], mo.box_R[t], mo.box_t[t])
            v: View = render_view(sm, K, mo.camera_w2c[t], W, H, ss)
            images[t], labels[t], centre_labels[t], depth[t] = v.rgb, v.label, v.centre_label, v.depth
            if t in train_set:
                f = v.centre_tri[(v.centre_tri >= body_face0) & (v.centre_tri < body_face0 + len(assets.faces))]
                seen[np.unique(f - body_face0)] += 1
            bar.advance(f"frame {t}")
    timings["render_frames"] = time.perf_counter() - t0

    # -- novel views -------------------------------------------------------------------------
    t0 = time.perf_counter()
    nf = novel_frames(T, cfg.novel_rings)
    train_c = camera_center(mo.camera_w2c)
    n_w2c = novel_cameras(mo.transl[nf], cfg.novel_per_ring, lambda p: inside_free_space(p, assets.room, 0.3), train_c)
    n_frames = np.repeat(nf, cfg.novel_per_ring)
    NV = len(n_frames)
    n_img = np.empty((NV, H, W, 3), np.uint8)
    n_lab = np.empty((NV, H, W), np.int8)
    n_depth = np.empty((NV, H, W), np.float32)
    with _Progress(show_progress, "novel views", NV) as bar:
        for k in range(NV):
            t = n_frames[k]
            v = render_view(assets.scene_mesh(V[t], mo.box_R[t], mo.box_t[t]), K, n_w2c[k], W, H, ss)
            n_img[k], n_lab[k], n_depth[k] = v.rgb, v.label, v.depth
            bar.advance(f"view {k}")
    timings["render_novel"] = time.perf_counter() - t0

    # -- pipeline-like inputs ----------------------------------------------------------------
    t0 = time.perf_counter()
    rng = np.random.default_rng(cfg.seed)
    ncfg = cfg.noise
    sigma_frames = ncfg.smooth_s * T / SCRIPT_SECONDS
    gt_h, gt_o = labels == HUMAN, labels == OBJECT
    gt_quats = continuous_quats(mo.box_R)
    if ncfg.enabled:
        pose_n, transl_n, shape_n = nz.noisy_body(mo.pose, mo.transl, assets.shape, assets.model.bone_names,
                                                  ncfg, rng, sigma_frames)
        R_n, t_n = nz.noisy_rigid(mo.box_R, mo.box_t, ncfg.object_m, ncfg.object_jitter_m, ncfg.object_deg,
                                  ncfg.object_jitter_deg, rng, sigma_frames)
        cams_n = nz.noisy_cameras(mo.camera_w2c, ncfg, rng)
        h_n = np.stack([nz.noisy_mask(m, ncfg, rng) for m in gt_h])
        o_n = np.stack([nz.noisy_mask(m, ncfg, rng) for m in gt_o])
    else:
        pose_n, transl_n, shape_n = mo.pose.copy(), mo.transl.copy(), assets.shape.copy()
        R_n, t_n, cams_n, h_n, o_n = mo.box_R, mo.box_t, mo.camera_w2c.copy(), gt_h.copy(), gt_o.copy()
    timings["noise"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    xs, cs = [], []
    for t in split["train"]:
        x, c = pts.frame_points(images[t], centre_labels[t], labels[t], depth[t], K, mo.camera_w2c[t])
        xs.append(x)
        cs.append(c)
    xyz, rgb = pts.voxel_dedup(np.concatenate(xs), np.concatenate(cs), voxel=0.02)
    if len(xyz) > cfg.points:
        keep = np.sort(rng.choice(len(xyz), cfg.points, replace=False))
        xyz, rgb = xyz[keep], rgb[keep]
    points_true = xyz.copy()
    if ncfg.enabled:
        xyz = pts.perturb(xyz, ncfg.points_m, rng)
    timings["points"] = time.perf_counter() - t0

    # -- assemble ------------------------------------------------------------------------------
    Ks = np.repeat(K[None], T, axis=0)
    gt = GroundTruth(
        cameras=CameraTrack(K=Ks.copy(), world_to_camera=mo.camera_w2c),
        body=BodyTrack("anny", assets.shape.astype(np.float32), mo.pose.astype(np.float32), mo.transl.astype(np.float32)),
        object=ObjectTrack(centre=np.zeros(3), quats=gt_quats, translations=mo.box_t.copy()),
        human_masks=gt_h,
        object_masks=gt_o,
        depth=depth,
        planes=list(assets.room.planes),
        novel=NovelViews(
            frames=n_frames,
            cameras=CameraTrack(K=np.repeat(K[None], NV, axis=0), world_to_camera=n_w2c),
            images=n_img,
            human_masks=n_lab == HUMAN,
            object_masks=n_lab == OBJECT,
            depth=n_depth,
        ),
    )
    timings["total"] = time.perf_counter() - t_all
    body_area = _face_areas(assets.canonical, assets.faces)
    n_train = max(len(split["train"]), 1)
    source = {
        "generator": GENERATOR,
        "generator_version": GENERATOR_VERSION,
        "seed": cfg.seed,
        "config": cfg.to_dict(),
        "noise": dict(cfg.to_dict()["noise"]),
        "object": {
            "shape": "box",
            "size_m": tx.BOX_SIZE.tolist(),
            "canonical_frame": "box centre at the origin, edges along x (0.30 m), y (0.22 m), z (0.18 m)",
            "grasp_frame": int(mo.grasp_frame),
            "faces": {"+x": "red, white band", "-x": "teal, yellow disc", "+y": "yellow, blue diagonal",
                      "-y": "blue, white checks", "+z": "green, white cross", "-z": "cardboard, dark square"},
        },
        "body_visibility": {
            "area_fraction_never_seen_in_train": float(body_area[seen == 0].sum() / body_area.sum()),
            "area_fraction_seen_in_under_10pct_of_train": float(body_area[seen < 0.1 * n_train].sum() / body_area.sum()),
        },
        "counts": {"frames": T, "train": len(split["train"]), "test": len(split["test"]), "novel_views": NV,
                   "points": int(len(xyz)),
                   "frames_with_object_visible": int(gt_o.reshape(T, -1).any(1).sum())},
        "points_max_error_m": float(np.linalg.norm(xyz - points_true, axis=1).max()) if len(xyz) else 0.0,
        "body_model_build_seconds": body_build,
        "timings": {k: round(v, 3) for k, v in timings.items()},
    }
    scene = Scene(
        root=None,
        name="synth",
        width=W,
        height=H,
        fps=float(cfg.fps),
        frame_ids=default_frame_ids(T),
        split=split,
        cameras=CameraTrack(K=Ks, world_to_camera=cams_n),
        body=BodyTrack("anny", shape_n.astype(np.float32), pose_n.astype(np.float32), transl_n.astype(np.float32)),
        object=ObjectTrack(centre=np.zeros(3), quats=continuous_quats(R_n), translations=t_n),
        points_xyz=xyz.astype(np.float32),
        points_rgb=rgb.astype(np.uint8),
        planes=None,  # inputs carry none: the scene branch fits them to the noisy points (exact ones in gt/)
        gt=gt,
        source=source,
    )
    scene.set_pixels(images, h_n, o_n)
    return scene


def _face_areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)


class _Progress:
    """A rich progress bar (cogs.log) over one loop, or nothing when disabled."""

    def __init__(self, enabled: bool, label: str, total: int):
        self.enabled, self.label, self.total = enabled, label, total

    def __enter__(self):
        if self.enabled:
            from cogs.log import progress

            self.started = time.perf_counter()
            self.done = 0
            self.p = progress()
            self.p.__enter__()
            self.task = self.p.add_task(self.label, total=self.total, rate="", info="")
        return self

    def advance(self, info: str = "") -> None:
        if self.enabled:
            from cogs.log import rate_text

            self.done += 1
            self.p.update(self.task, advance=1, rate=rate_text(self.done, self.started), info=info)

    def __exit__(self, *exc):
        if self.enabled:
            self.p.__exit__(*exc)
        return False
