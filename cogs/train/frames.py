"""The scene's training inputs, held compactly and converted one frame per step.

Images stay uint8 and masks bool on the host, as the scene holds them; `frame(t)` turns
one frame into float tensors on the training device, with its masks' boundary bands
computed then. A step's memory is one frame's, whatever the clip's length.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from cogs.data.scene import Scene
from cogs.train import losses as L


@dataclass
class Frame:
    """One training frame on the device (H x W)."""

    t: int
    image: Tensor  # [H, W, 3] float in [0, 1]
    human: Tensor  # [H, W, 1] float 0/1
    object: Tensor  # [H, W, 1] float 0/1
    human_band: Tensor  # [H, W, 1] float 0/1: +-2 px round the human mask's outline
    object_band: Tensor  # [H, W, 1]
    viewmat: Tensor  # [4, 4] world -> camera
    K: Tensor  # [3, 3]
    object_px: int  # pixels of the object mask
    object_trusted: bool = True  # the object mask may supervise the object (its confidence >= the threshold)


class TrainFrames:
    """The scene's frames for training. `min_confidence`: frames whose object confidence
    (object.json) is below it do not supervise the object (`Frame.object_trusted`) and
    are not drawn by stages that only supervise the object (`pool`)."""

    def __init__(self, scene: Scene, device: torch.device | str = "cpu", min_confidence: float = 0.0):
        self.device = torch.device(device)
        self._images = scene.images  # [T, H, W, 3] uint8
        self._human = scene.human_masks  # [T, H, W] bool
        self._object = scene.object_masks
        self.viewmats = torch.as_tensor(scene.cameras.world_to_camera, dtype=torch.float32, device=self.device)
        self.Ks = torch.as_tensor(scene.cameras.K, dtype=torch.float32, device=self.device)
        self.width, self.height = scene.width, scene.height
        self.train = [int(t) for t in scene.split["train"]]
        self.train_tensor = torch.tensor(self.train, dtype=torch.long, device=self.device)
        self.object_trusted = scene.object_trusted(min_confidence)  # [T] bool
        self.object_train = [t for t in self.train if self.object_trusted[t]]

    def pool(self, objectives) -> list[int]:
        """The frames a stage running `objectives` draws from: the trusted ones when the
        object objective is all it runs (a lost frame would give it nothing to learn),
        every training frame otherwise. Same length and order as `train` when every frame
        is trusted, so such a scene draws exactly the frames it drew before confidences."""
        return self.object_train if tuple(objectives) == ("object",) else self.train

    def _mask(self, m: np.ndarray) -> Tensor:
        return torch.from_numpy(np.ascontiguousarray(m)).to(self.device).float()[..., None]

    def image(self, t: int) -> Tensor:
        return torch.from_numpy(np.ascontiguousarray(self._images[t])).to(self.device).float() / 255.0

    def person_mask(self, t: int) -> Tensor:
        """[H, W] bool: the human mask outside the object's (where the person is seen)."""
        return torch.from_numpy(self._human[t] & ~self._object[t]).to(self.device)

    def frame(self, t: int) -> Frame:
        hm, om = self._human[t], self._object[t]
        return Frame(
            t=t, image=self.image(t), human=self._mask(hm), object=self._mask(om),
            human_band=self._mask(L.boundary_band(hm)), object_band=self._mask(L.boundary_band(om)),
            viewmat=self.viewmats[t], K=self.Ks[t], object_px=int(om.sum()),
            object_trusted=bool(self.object_trusted[t]),
        )

    def object_share(self) -> float:
        """Mean fraction of the frame the object's padded crop box covers (trusted training frames)."""
        fr = []
        for t in self.object_train:
            m = torch.from_numpy(self._object[t])
            if bool(m.any()):
                y0, y1, x0, x1 = L.crop_box(m, m)
                fr.append((y1 - y0) * (x1 - x0) / (self.width * self.height))
        return float(np.mean(fr)) if fr else 1.0

    def extent(self) -> float:
        """3DGS's camera extent: 1.1 x the largest camera distance from their centroid (>= 1 m)."""
        v = self.viewmats.cpu()
        centres = -(v[:, :3, :3].transpose(1, 2) @ v[:, :3, 3:])[..., 0]
        return max(1.1 * float((centres - centres.mean(0)).norm(dim=1).max()), 1.0)
