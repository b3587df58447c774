"""Test-time body-pose fitting: the evaluation protocol of Anim-NeRF / InstantAvatar.

Held-out frames carry the input (estimated) body pose plus the training's interpolated
correction. Per-frame pose-estimation error that no temporal model can predict (jitter)
then misaligns limbs by a pixel or two and dominates the human metrics. Many human-avatar
papers therefore fit the body pose of each test frame to that frame before measuring,
with everything else frozen. `cogs eval` reports both: the strict numbers (no test image
used) and, in `test_time_pose_fit`, the numbers after this fit. Only the pose of the
major bones and the body translation move; appearance, geometry, the object and the scene
stay exactly as trained.
"""

from __future__ import annotations

import torch

from cogs.train import losses as L


def fit_pose(comp, scene, t: int, steps: int = 40, lr: float = 3e-3, reg: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """(pose [1, J, 3], transl [1, 3]) of frame t fitted to its image and input masks."""
    human = comp.human
    vm = torch.as_tensor(scene.cameras.world_to_camera[t], dtype=torch.float32)
    K = torch.as_tensor(scene.cameras.K[t], dtype=torch.float32)
    img = torch.as_tensor(scene.images[t]).float() / 255.0
    hm = torch.as_tensor(scene.human_masks[t]).float()[..., None]
    om = torch.as_tensor(scene.object_masks[t]).float()[..., None]
    with torch.no_grad():
        state = human.decode()
        base_pose, base_transl = human.frame_pose(t)
        others = comp.splats(t, vm, tuple(b for b in comp.available() if b != "human"))
    dp = torch.zeros(1, len(human.refined_bones), 3, requires_grad=True)
    dt = torch.zeros(1, 3, requires_grad=True)
    opt = torch.optim.Adam([{"params": [dp], "lr": lr}, {"params": [dt], "lr": lr * 0.5}])
    for _ in range(steps):
        opt.zero_grad()
        pose = base_pose.index_add(1, human.refined_bones, dp)
        splats = {"human": comp.human_splats(t, (pose, base_transl + dt), state), **others}
        r = comp.render(vm, K, scene.width, scene.height, t, background=torch.zeros(3), splats=splats)
        a = r.branch_alpha["human"]
        loss = L.l1(r.rgb, img) + 0.5 * L.bce(a, hm, 1.0 - om) + 0.5 * L.dice(a * (1 - om), hm * (1 - om))
        loss = loss + reg * (dp.square().sum() + dt.square().sum())
        loss.backward()
        opt.step()
    with torch.no_grad():
        return base_pose.index_add(1, human.refined_bones, dp), base_transl + dt
