"""What a finished run leaves behind besides checkpoints: standard PLYs, the object
trajectory, refined body poses, the loss history and a summary."""

from __future__ import annotations

import numpy as np
import torch

from cogs.branches.gaussians import GaussianSet, inverse_sigmoid, rgb_to_sh0
from cogs.data.io import write_json


def human_canonical_set(human) -> GaussianSet:
    """The decoded canonical human as a plain GaussianSet (raw parameters)."""
    with torch.no_grad():
        st = human.decode()
        return GaussianSet({
            "means": st.means, "quats": st.quats, "scales": torch.log(st.scales),
            "opacities": inverse_sigmoid(st.opacities), "sh0": rgb_to_sh0(st.colors),
        }, 0)


def export_run(trainer) -> None:
    out = trainer.out / "final"
    out.mkdir(parents=True, exist_ok=True)
    if trainer.human is not None:
        human_canonical_set(trainer.human).save_ply(out / "human_canonical.ply")
        with torch.no_grad():
            poses = [trainer.human.frame_pose(t) for t in range(trainer.scene.n_frames)]
        np.savez_compressed(out / "body_refined.npz",
                            pose=torch.cat([p for p, _ in poses]).numpy(), transl=torch.cat([t for _, t in poses]).numpy())
    if trainer.object is not None:
        trainer.object.gaussians.save_ply(out / "object_canonical.ply")
        with torch.no_grad():
            tr, q = trainer.object.pose(torch.arange(trainer.scene.n_frames, dtype=torch.float32))
        write_json(out / "object_trajectory.json", {
            "centre": trainer.object.centre.tolist(),
            "convention": "x_world = R(quat_wxyz) (x_canonical - centre) + translation",
            "keyframe_times": trainer.object.key_times.tolist(),
            "frames": [{"quat_wxyz": q[i].tolist(), "translation": tr[i].tolist()} for i in range(len(tr))],
        })
    if trainer.scene_branch is not None:
        trainer.scene_branch.gaussians.save_ply(out / "scene.ply")
    write_json(trainer.out / "train_log.json", {"history": trainer.state.history, "density": trainer.state.density_events})
    write_json(trainer.out / "train_summary.json", trainer.summary())
