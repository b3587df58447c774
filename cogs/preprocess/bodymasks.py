"""The fitted body as a second source of evidence for the masks (the `masks` step).

MediaPipe's person mask and the object tracker only see colour, motion and MediaPipe's
keypoints. After the body fit there is a posed mesh in every frame: its silhouette, drawn
by the triangle rasterizer of the synthetic scene's ground truth, says where the limbs
are. It is not precise (the fit's 2D joints are a few percent of the person's height off,
and the mesh is an unclothed body), so it only ever *proposes* pixels, and colour decides:

- **forearm**: pixels that the fitted lower arm or hand covers, that MediaPipe's mask
  missed and that look like the person (a colour model of this frame's person mask
  against the scene around it) join the person mask when they touch it (a forearm
  reaching down to a table is often absent from MediaPipe's mask);
- **fingers**: object pixels that the fitted hand covers (grown a little: the fingers'
  curl is unknown) and whose colour the person explains better than the rest of the
  object does leave the object mask (fingers around a held box); they go back to the
  person mask when MediaPipe's mask has them. At most a third of a frame's object mask
  is taken out this way;
- **bleed**: person pixels off the fitted body that the scene around the mask explains
  far better than the person's pixels on the body do leave the person mask (MediaPipe
  predicts its mask at low resolution, and it spreads over the background). At most a
  quarter of a frame's person mask is taken out this way.

Without the body's constraint the same colour test hurts (on the benchmark, human IoU
0.888 -> 0.881 and 0.880 -> 0.872): the shirt's stripes and the skin have scene colours.
"""

from __future__ import annotations

import cv2
import numpy as np

BINS = 16  # per channel, for the colour models
ARM_WORDS = ("lowerarm", "forearm", "elbow")
HAND_WORDS = ("wrist", "hand", "finger", "metacarpal", "thumb", "index", "middle", "ring", "pinky")
PERSON_P = 0.6  # colour posterior needed to add a forearm pixel / to call an object pixel a finger
MAX_REMOVED = 1.0 / 3.0
BLEED_P = 0.2  # colour posterior of the person below which a person pixel off the fitted body is scene
MAX_TRIMMED = 0.25  # of a frame's person mask, at most


def bone_parts(bone_names: list[str]) -> np.ndarray:
    """Per bone: 0 other, 1 forearm, 2 hand (by name, for any body model)."""
    out = np.zeros(len(bone_names), np.int64)
    for i, n in enumerate(bone_names):
        n = n.lower()
        if any(w in n for w in HAND_WORDS):
            out[i] = 2
        elif any(w in n for w in ARM_WORDS):
            out[i] = 1
    return out


def body_parts(model, shape, pose, transl, world_to_camera, K, width: int, height: int) -> np.ndarray:
    """[T, H, W] uint8 label of the fitted mesh in every frame: 0 none, 1 body, 2 forearm, 3 hand."""
    import torch

    from cogs.data.synth.raster import rasterize

    shape_t = torch.as_tensor(np.asarray(shape), dtype=torch.float32)
    with torch.no_grad():
        verts = model.posed_vertices(torch.as_tensor(np.asarray(pose), dtype=torch.float32),
                                     torch.as_tensor(np.asarray(transl), dtype=torch.float32), shape_t).double().numpy()
    can = model.canonical(shape_t)
    faces = can.faces.cpu().numpy()
    vertex_bone = can.weights.cpu().numpy().argmax(1)
    face_part = 1 + bone_parts(model.bone_names)[vertex_bone[faces[:, 0]]]
    lut = np.concatenate([[0], face_part]).astype(np.uint8)
    out = np.zeros((len(verts), height, width), np.uint8)
    for t in range(len(verts)):
        w2c = np.asarray(world_to_camera[t], np.float64)
        vc = verts[t] @ w2c[:3, :3].T + w2c[:3, 3]
        out[t] = lut[rasterize(vc, faces, np.asarray(K, np.float64), width, height).tri + 1]
    return out


def _hist(img: np.ndarray, m: np.ndarray) -> np.ndarray:
    q = img[m].astype(np.int64) // (256 // BINS)
    return np.bincount((q[:, 0] * BINS + q[:, 1]) * BINS + q[:, 2], minlength=BINS**3).astype(np.float64)


def _posterior(img: np.ndarray, h_fg: np.ndarray, h_bg: np.ndarray) -> np.ndarray:
    """P(foreground | colour) per pixel, both models smoothed alike (0.5 where neither has data)."""
    pf = (h_fg + 0.5) / (h_fg.sum() + 0.5 * BINS**3)
    pb = (h_bg + 0.5) / (h_bg.sum() + 0.5 * BINS**3)
    q = img.astype(np.int64) // (256 // BINS)
    return (pf / (pf + pb))[(q[..., 0] * BINS + q[..., 1]) * BINS + q[..., 2]]


def _disk(r: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def refine_frame(image: np.ndarray, person: np.ndarray, obj: np.ndarray, parts: np.ndarray, *, fingers: bool = True,
                 person_edges: bool = True) -> tuple[np.ndarray, np.ndarray, dict]:
    """One frame: (person mask, object mask, counts) with the fitted body's evidence.

    `person` is MediaPipe's mask (it may overlap the object), `obj` the tracker's; the
    returned masks are disjoint (object pixels win). `fingers` / `person_edges` off leave
    the object mask / the person mask's outline (forearm and bleed) as they are."""
    H, W = person.shape
    side = max(H, W)
    body = parts > 0
    info = {"forearm_px": 0, "finger_px": 0, "bleed_px": 0}
    obj = obj.copy()
    # Fingers out of the object mask.
    hand = parts == 3
    if fingers and obj.any() and hand.any() and person.any():
        region = cv2.dilate(hand.astype(np.uint8), _disk(max(2, round(0.008 * side)))) > 0
        sample_obj, sample_person = obj & ~region, person & ~obj & ~region
        if sample_obj.sum() >= 50 and sample_person.sum() >= 50:
            p_obj = _posterior(image, _hist(image, sample_obj), _hist(image, sample_person))
            finger = obj & region & (p_obj < 1.0 - PERSON_P)
            if 0 < finger.sum() <= MAX_REMOVED * obj.sum():
                obj &= ~finger
                info["finger_px"] = int(finger.sum())
    # The forearm into the person mask.
    arm = (parts >= 2) & ~person & ~obj
    if person_edges and arm.any() and person.any():
        near = cv2.dilate((person | body).astype(np.uint8), _disk(max(3, round(0.025 * side)))) > 0
        p_person = _posterior(image, _hist(image, person & ~obj), _hist(image, ~near & ~obj))
        cand = arm & (p_person > PERSON_P)
        n, lab = cv2.connectedComponents(cand.astype(np.uint8))
        if n > 1:
            touching = cv2.dilate(person.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
            ids = np.unique(lab[touching & cand])
            add = np.isin(lab, ids[ids > 0])
            person = person | add
            info["forearm_px"] = int(add.sum())
    # MediaPipe's mask bleeding over the scene: off the fitted body and coloured like the
    # scene around the mask, not like the person inside the body.
    off = person & ~body & ~obj
    if person_edges and off.any() and (person & body).any():
        ring = (cv2.dilate(person.astype(np.uint8), _disk(max(3, round(0.03 * side)))) > 0) & ~person & ~obj
        if ring.sum() >= 50:
            p_person = _posterior(image, _hist(image, person & body & ~obj), _hist(image, ring))
            bleed = off & (p_person < BLEED_P)
            if bleed.sum() <= MAX_TRIMMED * person.sum():
                person = person & ~bleed
                info["bleed_px"] = int(bleed.sum())
    return person & ~obj, obj, info


def refine_masks(images: np.ndarray, person: np.ndarray, obj: np.ndarray | None, parts: np.ndarray,
                 detected: np.ndarray, on_frame=None, fingers: bool = True,
                 person_edges: bool = True) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """Every frame through `refine_frame` (frames without a person detection are left as they are)."""
    T = len(images)
    human = person.copy()
    obj_out = None if obj is None else obj.copy()
    forearm, finger, bleed = [], [], []
    for t in range(T):
        o = np.zeros_like(person[t]) if obj is None else obj[t]
        if detected[t]:
            h, o2, info = refine_frame(images[t], person[t], o, parts[t], fingers=fingers, person_edges=person_edges)
            human[t] = h
            if obj_out is not None:
                obj_out[t] = o2
            forearm.append(info["forearm_px"])
            finger.append(info["finger_px"])
            bleed.append(info["bleed_px"])
        else:
            human[t] = person[t] & ~o
        if on_frame:
            on_frame(t + 1)
    stats = {"forearm_px": int(np.sum(forearm)), "finger_px": int(np.sum(finger)), "bleed_px": int(np.sum(bleed)),
             "frames_with_forearm": int(np.count_nonzero(forearm)), "frames_with_fingers": int(np.count_nonzero(finger))}
    return human, obj_out, stats
