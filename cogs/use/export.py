"""`cogs export`: a trained run as standard 3DGS PLYs, an animatable glTF and plain arrays.

OUT/ (layout and conventions: docs/export.md)

    human_canonical.ply, object_canonical.ply, scene.ply   canonical 3DGS PLYs, per branch
    body_refined.npz, object_trajectory.json               the run's refined poses (as final/)
    posed_frame_<T>.ply                                    the whole scene posed at frame T
    reconstruction.glb                                     KHR_gaussian_splatting primitives,
                                                           the human skinned, motion animated
    reconstruction.npz                                     the same as arrays
    export.json                                            what was written, and the skin's
                                                           four-weight approximation error
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
import tyro
from torch import Tensor

from cogs.errors import UserError

log = logging.getLogger("cogs")

MAX_INFLUENCES = 4
"""Joints per splat in the glTF skin (what engines support); the rest of each splat's
weight is dropped and the four renormalised."""


@dataclass
class Export:
    """Export a trained run: canonical and posed 3DGS PLYs, an animatable glTF binary
    (.glb) and plain arrays (.npz). Layout: docs/export.md."""

    run_dir: Annotated[Path, tyro.conf.arg(name="run")]
    """Run folder written by `cogs train`."""
    out: Path
    """Output folder (created; must not exist or be empty unless --overwrite)."""
    frame: int = 0
    """The frame the posed PLY shows, and the glTF's pose when its animation is not
    played (0 .. the clip's frames - 1)."""
    fps: float | None = None
    """Frame rate of the glTF animation (default: the scene's, from its scene.json; 10 if
    the scene cannot be found)."""
    checkpoint: str | None = None
    """Export this file of RUN/checkpoints (e.g. `stage_VI.pt`) instead of the newest."""
    overwrite: bool = False
    """Write into a non-empty --out, replacing the files of an earlier export."""

    def run(self) -> int:
        from cogs.data.outdir import claimed
        from cogs.model import Model

        if self.out.exists() and (not self.out.is_dir() or any(self.out.iterdir())) and not self.overwrite:
            raise UserError(f"--out {self.out} exists and is not empty; choose another folder or pass --overwrite")
        if self.fps is not None and not (np.isfinite(self.fps) and self.fps > 0):
            raise UserError(f"--fps {self.fps}: must be a positive number")
        ckpt = None
        if self.checkpoint is not None:
            ckpt = self.run_dir / "checkpoints" / self.checkpoint
            if not ckpt.is_file():
                raise UserError(f"--checkpoint {self.checkpoint}: no such file in {self.run_dir / 'checkpoints'}")
        model = Model.load(self.run_dir, device="cpu", checkpoint=ckpt)
        n = model.n_frames
        if not 0 <= self.frame < n:
            raise UserError(f"--frame {self.frame}: out of range, the run has frames 0..{n - 1}")
        fps = self.fps or run_fps(self.run_dir)
        with claimed(self.out):  # a second export into the same --out stops at once
            summary = export_bundle(model, self.out, self.frame, fps)
        log.info("exported %s: %s", self.out, ", ".join(summary["files"]))
        return 0


def run_fps(run: Path, default: float = 10.0) -> float:
    """The frame rate of the scene a run was trained on (its scene.json), or `default`."""
    from cogs.data.io import read_json

    info = run / "run.json"
    scene = read_json(info).get("scene") if info.is_file() else None
    meta = Path(scene) / "scene.json" if scene else None
    if meta is not None and meta.is_file():
        return float(read_json(meta).get("fps", default))
    log.warning("the run's scene.json was not found: assuming %.0f fps (set --fps)", default)
    return default


# -- the bundle -----------------------------------------------------------------------


def top_influences(weights: Tensor, k: int = MAX_INFLUENCES) -> tuple[Tensor, Tensor]:
    """The k largest skinning weights per row ([N, J] -> joints [N, k] int64, weights
    [N, k] summing to 1); joints of zero weight are set to 0."""
    w, j = weights.topk(min(k, weights.shape[1]), dim=1)
    w = w.clamp_min(0)
    w = w / w.sum(1, keepdim=True).clamp_min(1e-12)
    j = torch.where(w > 0, j, torch.zeros_like(j))
    return j, w


def human_joint_globals(human, frames: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(skinning transforms A [T, J, 4, 4] canonical -> world, joint globals G [T, J, 4, 4]
    = A @ translate(rest head), rest heads [J, 3]); float64, the run's refined poses."""
    body = human.body
    heads = body.canonical(human.shape).joints.detach().double().cpu().detach().cpu().numpy()
    A = []
    with torch.no_grad():
        for t in frames:
            pose, transl = human.frame_pose(t)
            a, _ = body.bone_transforms(pose.double(), transl.double(), human.shape)
            A.append(a[0].cpu().detach().cpu().numpy())
    A = np.stack(A)
    R = A[:, :, :3, :3]
    err = np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max()
    assert err < 1e-6, f"the body model's bone transforms are not rigid ({err:.1e}): no glTF joint can carry them"
    bind = np.tile(np.eye(4), (len(heads), 1, 1))
    bind[:, :3, 3] = heads
    return A, A @ bind, heads


def _raw(means, quats, scales, opacities, sh: Tensor) -> dict[str, Tensor]:
    """Activated attributes -> the raw PLY parameters (log scales, logit opacities)."""
    from cogs.branches.gaussians import inverse_sigmoid

    out = {"means": means, "quats": quats, "scales": torch.log(scales.clamp_min(1e-12)),
           "opacities": inverse_sigmoid(opacities), "sh0": sh[:, :1]}
    if sh.shape[1] > 1:
        out["shN"] = sh[:, 1:]
    return out


def _shaded_sh(sh: Tensor, irradiance: Tensor) -> Tensor:
    """SH [N, K, 3] of a colour c(d) = SH(d) + 0.5 -> those of E * c(d) for a per-splat
    irradiance E [N, 1] (the clamps aside)."""
    from cogs.render.sh import SH_C0

    E = irradiance[:, :, None]
    out = sh * E
    out[:, :1] = out[:, :1] + 0.5 * (E - 1.0) / SH_C0
    return out


@torch.no_grad()
def posed_branches(model, frame: int) -> dict[str, dict[str, Tensor]]:
    """Every branch at `frame` in world space, as activated attributes plus full SH
    [N, K, 3] with the moving branches' shading baked in: name -> dict(means, quats,
    scales, opacities, sh)."""
    from cogs.branches.gaussians import rgb_to_sh0
    from cogs.geometry.rotations import quat_to_rotmat
    from cogs.use.posing import posed_human_splats, rotate_sh

    out = {}
    h, o, s = model.human, model.object, model.scene
    if h is not None and len(h):
        p = posed_human_splats(h, *h.frame_pose(frame))
        out["human"] = {**{k: p[k] for k in ("means", "quats", "scales", "opacities")}, "sh": rgb_to_sh0(p["colors"])}
    if o is not None and len(o):
        tr, q = o.frame_pose(frame)
        means, quats = o.posed(tr, q)
        g = o.gaussians
        sh = rotate_sh(g.sh, quat_to_rotmat(q), g.sh_degree)
        if o.cfg.shading:
            sh = _shaded_sh(sh, o.shading(quat_to_rotmat(quats)[:, :, 2]))
        out["object"] = {"means": means, "quats": quats, "scales": g.scales, "opacities": g.opacities, "sh": sh}
    if s is not None and len(s):
        g = s.gaussians
        out["scene"] = {"means": g.means, "quats": g.quats, "scales": g.scales, "opacities": g.opacities, "sh": g.sh}
    return out


def _concat(parts: list[dict[str, Tensor]]) -> tuple[dict[str, Tensor], int]:
    K = max(p["sh"].shape[1] for p in parts)
    degree = int(round(K ** 0.5)) - 1
    sh = [torch.cat([p["sh"], p["sh"].new_zeros(len(p["sh"]), K - p["sh"].shape[1], 3)], 1) for p in parts]
    cat = {k: torch.cat([p[k] for p in parts]) for k in ("means", "quats", "scales", "opacities")}
    return _raw(cat["means"], cat["quats"], cat["scales"], cat["opacities"], torch.cat(sh)), degree


def export_bundle(model, out: Path, frame: int, fps: float) -> dict:
    """Write every export file of `model` into `out` (see the module docstring); returns
    the summary also written to export.json."""
    from cogs.branches.gaussians import write_ply
    from cogs.data.io import write_json

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = [p.name for p in model.export(out)]
    posed = posed_branches(model, frame)
    if posed:
        raw, degree = _concat(list(posed.values()))
        name = f"posed_frame_{frame:06d}.ply"
        write_ply(out / name, raw, degree)
        files.append(name)
    summary = write_gltf_and_arrays(model, out, frame, fps)
    files += ["reconstruction.glb", "reconstruction.npz", "export.json"]
    summary = {"frame": frame, "fps": fps, "files": files, "n_gaussians": model.counts(), **summary}
    write_json(out / "export.json", summary)
    return summary


@torch.no_grad()
def write_gltf_and_arrays(model, out: Path, frame: int, fps: float) -> dict:
    """reconstruction.glb and reconstruction.npz (docs/export.md); returns the world's up,
    the glTF rotation and the skin's approximation error."""
    from cogs.body import lbs_points
    from cogs.branches.gaussians import rgb_to_sh0
    from cogs.geometry.rotations import quat_multiply, quat_sign_continuous, quat_to_rotmat, rotmat_to_quat
    from cogs.use.gltf import UNSIGNED_BYTE, UNSIGNED_SHORT, GlbBuilder, trs
    from cogs.use.posing import gltf_from_world, posed_human_splats, world_up

    h, o, s = model.human, model.object, model.scene
    n_frames = model.n_frames
    frames = list(range(n_frames))
    times = np.arange(n_frames, dtype=np.float32) / np.float32(fps)
    up = world_up(h) if h is not None else np.array([0.0, 0.0, 1.0])
    Rup = gltf_from_world(up)
    Rup4 = np.eye(4)
    Rup4[:3, :3] = Rup
    q_up = rotmat_to_quat(torch.from_numpy(Rup)).float()  # wxyz
    glb = GlbBuilder()
    doc = glb.doc
    doc["extensionsUsed"] = ["KHR_gaussian_splatting"]
    doc["skins"], doc["animations"] = [], []
    world = glb.add_node({"name": "cogs_world", **trs(Rup4), "children": []})
    scene_nodes = [world]
    arrays: dict[str, np.ndarray] = {"world_up": up, "gltf_from_world": Rup, "fps": np.float64(fps),
                                     "export_frame": np.int64(frame), "times": times}
    channels, samplers = [], []
    t_acc = glb.add_accessor(times, minmax=True) if n_frames else None
    summary: dict = {"world_up": up.tolist(), "gltf_from_world": Rup.tolist()}

    def splat_primitive(means, quats_wxyz, scales, opacities, sh: np.ndarray, extra: dict | None = None) -> dict:
        attrs = {
            "POSITION": glb.add_accessor(means, vertex=True, minmax=True),
            "KHR_gaussian_splatting:ROTATION": glb.add_accessor(quats_wxyz[:, [1, 2, 3, 0]], vertex=True),
            "KHR_gaussian_splatting:SCALE": glb.add_accessor(scales, vertex=True),
            "KHR_gaussian_splatting:OPACITY": glb.add_accessor(opacities, vertex=True),
        }
        degree = int(round(sh.shape[1] ** 0.5)) - 1
        for l in range(degree + 1):
            for n in range(2 * l + 1):
                attrs[f"KHR_gaussian_splatting:SH_DEGREE_{l}_COEF_{n}"] = glb.add_accessor(sh[:, l * l + n], vertex=True)
        attrs.update(extra or {})
        return {"attributes": attrs, "mode": 0,
                "extensions": {"KHR_gaussian_splatting": {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"}}}

    def anim(node: int, translations: np.ndarray, rotations_wxyz: np.ndarray) -> None:
        q = quat_sign_continuous(torch.from_numpy(rotations_wxyz)).numpy()
        for path, values in (("translation", translations), ("rotation", q[:, [1, 2, 3, 0]])):
            samplers.append({"input": t_acc, "output": glb.add_accessor(values.astype(np.float32)), "interpolation": "LINEAR"})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": node, "path": path}})

    # -- human: skinned to the body model's skeleton ------------------------------------
    if h is not None and len(h):
        st = h.decode()
        A, G, heads = human_joint_globals(h, frames)
        body = h.body
        J = body.n_bones
        parents = body.bone_parents
        local = np.empty_like(G)
        for j in range(J):
            local[:, j] = G[:, j] if parents[j] < 0 else np.linalg.inv(G[:, parents[j]]) @ G[:, j]
        joint_nodes = []
        for j in range(J):
            joint_nodes.append(glb.add_node({"name": body.bone_names[j], **trs(local[frame, j])}))
        for j in range(J):
            kids = [joint_nodes[c] for c in range(J) if parents[c] == j]
            if kids:
                doc["nodes"][joint_nodes[j]]["children"] = kids
        doc["nodes"][world]["children"] += [joint_nodes[j] for j in range(J) if parents[j] < 0]
        joints4, w4 = top_influences(st.weights)
        at_t = posed_human_splats(h, *h.frame_pose(frame), st)
        means_bind = st.means.double().detach().cpu().numpy() @ Rup.T
        quats_bind = quat_multiply(q_up.expand(len(h), 4), st.quats).detach().cpu().numpy()
        sh = rgb_to_sh0(at_t["colors"]).detach().cpu().numpy()
        jt = UNSIGNED_BYTE if J <= 256 else UNSIGNED_SHORT
        skin_attrs = {"JOINTS_0": glb.add_accessor(joints4.detach().cpu().numpy(), jt, vertex=True),
                      "WEIGHTS_0": glb.add_accessor(w4.detach().cpu().numpy(), vertex=True)}
        prim = splat_primitive(means_bind, quats_bind, st.scales.detach().cpu().numpy(), st.opacities.detach().cpu().numpy(), sh, skin_attrs)
        mesh = glb.add_mesh({"name": "human", "primitives": [prim]})
        ibm = np.linalg.inv(Rup4 @ _translate(heads))  # [J, 4, 4]
        doc["skins"].append({"name": "body", "joints": joint_nodes,
                             "inverseBindMatrices": glb.add_accessor(np.swapaxes(ibm, 1, 2).reshape(J, 16)),
                             "skeleton": joint_nodes[next(j for j in range(J) if parents[j] < 0)]})
        # The skinned mesh's own node transform is ignored by glTF skinning: it sits at the root.
        scene_nodes.append(glb.add_node({"name": "human", "mesh": mesh, "skin": 0}))
        for j in range(J):
            anim(joint_nodes[j], local[:, j, :3, 3], rotmat_to_quat(torch.from_numpy(local[:, j, :3, :3])).detach().cpu().numpy())
        # What four influences cost against the model's own skinning (every frame).
        full = st.weights.double()
        w4_dense = torch.zeros_like(full).scatter_(1, joints4, w4.double())
        dev = []
        for t in frames:
            At = torch.from_numpy(A[t])
            dev.append((lbs_points(st.means.double(), w4_dense, At) - lbs_points(st.means.double(), full, At)).norm(dim=1))
        dev = torch.stack(dev)
        summary["skin_four_influences_error_m"] = {"mean": float(dev.mean()), "p99": float(torch.quantile(dev.flatten()[::7], 0.99)),
                                                  "max": float(dev.max())}
        summary["human_weight_outside_four"] = {"mean": float(1 - full.topk(4, 1).values.sum(1).mean()),
                                                "max": float(1 - full.topk(4, 1).values.sum(1).min())}
        arrays.update({
            "human_means": st.means.detach().cpu().numpy(), "human_quats": st.quats.detach().cpu().numpy(), "human_scales": st.scales.detach().cpu().numpy(),
            "human_opacities": st.opacities.detach().cpu().numpy(), "human_colors": at_t["colors"].detach().cpu().numpy(),
            "human_weights": st.weights.detach().cpu().numpy(), "human_joints4": joints4.detach().cpu().numpy(), "human_weights4": w4.detach().cpu().numpy(),
            "bone_names": np.array(body.bone_names), "bone_parents": np.array(parents), "bone_heads": heads,
            "bone_transforms": A, "body_model": np.array(body.name),
            "body_pose": torch.cat([h.frame_pose(t)[0] for t in frames]).detach().cpu().numpy(),
            "body_transl": torch.cat([h.frame_pose(t)[1] for t in frames]).detach().cpu().numpy(),
            "body_shape": h.shape.detach().cpu().numpy(),
        })

    # -- object: a rigid node on its trajectory -------------------------------------------
    if o is not None and len(o):
        g = o.gaussians
        tau = torch.arange(n_frames, dtype=torch.float32, device=o.centre.device)
        tr, q = o.pose(tau)
        tr, q = tr.double().detach().cpu().numpy(), q.double().detach().cpu().numpy()
        E = o.shading(quat_to_rotmat(o.posed(*o.frame_pose(frame))[1])[:, :, 2]) if o.cfg.shading else None
        sh = g.sh if E is None else _shaded_sh(g.sh, E)
        X = np.eye(4)
        X[:3, :3] = quat_to_rotmat(torch.from_numpy(q[frame])).detach().cpu().numpy()
        X[:3, 3] = tr[frame]
        prim = splat_primitive((g.means - o.centre).double().detach().cpu().numpy(), g.quats.detach().cpu().numpy(), g.scales.detach().cpu().numpy(),
                               g.opacities.detach().cpu().numpy(), sh.detach().cpu().numpy())
        node = glb.add_node({"name": "object", "mesh": glb.add_mesh({"name": "object", "primitives": [prim]}), **trs(X)})
        doc["nodes"][world]["children"].append(node)
        anim(node, tr, q)
        arrays.update({"object_means": g.means.detach().cpu().numpy(), "object_quats": g.quats.detach().cpu().numpy(), "object_scales": g.scales.detach().cpu().numpy(),
                       "object_opacities": g.opacities.detach().cpu().numpy(), "object_sh": sh.detach().cpu().numpy(), "object_centre": o.centre.detach().cpu().numpy(),
                       "object_translation": tr, "object_quat_wxyz": q})

    # -- scene: static -------------------------------------------------------------------
    if s is not None and len(s):
        g = s.gaussians
        prim = splat_primitive(g.means.double().detach().cpu().numpy(), g.quats.detach().cpu().numpy(), g.scales.detach().cpu().numpy(), g.opacities.detach().cpu().numpy(), g.sh.detach().cpu().numpy())
        node = glb.add_node({"name": "scene", "mesh": glb.add_mesh({"name": "scene", "primitives": [prim]})})
        doc["nodes"][world]["children"].append(node)
        arrays.update({"scene_means": g.means.detach().cpu().numpy(), "scene_quats": g.quats.detach().cpu().numpy(), "scene_scales": g.scales.detach().cpu().numpy(),
                       "scene_opacities": g.opacities.detach().cpu().numpy(), "scene_sh": g.sh.detach().cpu().numpy()})

    if channels:
        doc["animations"].append({"name": "motion", "channels": channels, "samplers": samplers})
    doc["scenes"].append({"name": "reconstruction", "nodes": scene_nodes})
    glb.write(out / "reconstruction.glb")
    np.savez_compressed(out / "reconstruction.npz", **{k: np.asarray(v) for k, v in arrays.items()})
    return summary


def _translate(points: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(points), 1, 1))
    T[:, :3, 3] = points
    return T
