"""A contact sheet of a scene: does the ground truth line up, and what do the inputs look like?

One row per chosen frame, four panels per row:

1. the image;
2. ground-truth masks filled (human red, object blue) with the noisy input masks'
   outlines (human yellow, object cyan);
3. ground-truth depth, colour-mapped (turbo, near = blue) with its range;
4. the noisy inputs over the dimmed image, projected with the noisy cameras: body
   skeleton from the noisy body pose (left limbs green, right limbs orange, spine and
   head white), the object's box outline and axes from its noisy pose (x red, y green,
   z blue), and the sparse points that pass a depth test (magenta dots).

Works on any scene with ground truth (`cogs synth --preview` writes it for the synthetic
one).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont
from scipy.ndimage import binary_erosion

from cogs.data.scene import Scene
from cogs.data.io import write_image
from cogs.geometry.camera import project_points

SCALE = 2
HEADER = 30


def choose_frames(scene: Scene, n: int = 8) -> list[int]:
    """n frames spread over the clip, including the grasp frame when the scene records one."""
    T = scene.n_frames
    frames = list(np.unique(np.rint(np.linspace(0, T - 1, n)).astype(int)))
    g = scene.source.get("object", {}).get("grasp_frame") if isinstance(scene.source, dict) else None
    if g is not None and 0 <= g < T and g not in frames:
        k = int(np.argmin([abs(f - g) for f in frames]))
        frames[k] = int(g)
    return sorted(int(f) for f in frames)


def _up(img: np.ndarray) -> np.ndarray:
    return np.repeat(np.repeat(img, SCALE, axis=0), SCALE, axis=1)


def _outline(mask: np.ndarray) -> np.ndarray:
    return mask & ~binary_erosion(mask)


def _depth_rgb(depth: np.ndarray) -> tuple[np.ndarray, float, float]:
    import matplotlib

    valid = depth > 0
    if not valid.any():
        return np.zeros(depth.shape + (3,), np.uint8), 0.0, 0.0
    lo, hi = float(depth[valid].min()), float(np.percentile(depth[valid], 99))
    x = np.clip((depth - lo) / max(hi - lo, 1e-6), 0, 1)
    rgb = (matplotlib.colormaps["turbo"](x)[..., :3] * 255).astype(np.uint8)
    rgb[~valid] = 0
    return rgb, lo, hi


_BOX_EDGES = [(0, 1), (0, 2), (0, 4), (1, 3), (1, 5), (2, 3), (2, 6), (3, 7), (4, 5), (4, 6), (5, 7), (6, 7)]


def _skeleton(scene: Scene):
    """Noisy joints [T, J, 3] and (parent, child, colour) bone segments to draw."""
    import torch

    from cogs.body import load_body_model

    model = load_body_model(scene.body.model)
    with torch.no_grad():
        _, joints = model.bone_transforms(torch.from_numpy(scene.body.pose).float(),
                                          torch.from_numpy(scene.body.transl).float(),
                                          torch.from_numpy(scene.body.shape).float())
    segs = []
    for j, (name, p) in enumerate(zip(model.bone_names, model.bone_parents)):
        if p < 0 or name.startswith(("finger", "toe", "metacarpal", "eye", "pelvis")):
            continue
        colour = (90, 230, 90) if name.endswith(".L") else (255, 150, 40) if name.endswith(".R") else (255, 255, 255)
        segs.append((p, j, colour))
    return joints.numpy(), segs


def write_preview(scene: Scene, path: str | Path, frames: list[int] | None = None) -> Path:
    """Write the contact sheet PNG of `scene` (which needs ground truth) to `path`."""
    assert scene.gt is not None, "the preview compares inputs with ground truth"
    frames = frames or choose_frames(scene)
    W, H = scene.width * SCALE, scene.height * SCALE
    titles = ["image", "GT masks (fill) + noisy masks (outline)", "GT depth", "noisy inputs: body, object, points"]
    sheet = Image.new("RGB", (4 * W, HEADER + len(frames) * (H + HEADER)), (24, 24, 24))
    draw = ImageDraw.Draw(sheet)
    font = ImageFont.load_default(size=15)
    for c, title in enumerate(titles):
        draw.text((c * W + 6, 6), title, fill=(240, 240, 240), font=font)
    joints, segs = _skeleton(scene)
    box_corners = None
    if scene.object is not None:
        size = np.array(scene.source.get("object", {}).get("size_m", [0.30, 0.22, 0.18]))
        box_corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * size / 2 + scene.object.centre
    images = scene.images
    for r, t in enumerate(frames):
        y0 = HEADER + r * (H + HEADER) + HEADER
        img = images[t]
        gt_h, gt_o = scene.gt.human_masks[t], scene.gt.object_masks[t] if scene.gt.object_masks is not None else None
        # Panel 2: masks.
        ov = img.astype(np.float64)
        ov[gt_h] = 0.45 * ov[gt_h] + 0.55 * np.array([230, 40, 40])
        if gt_o is not None:
            ov[gt_o] = 0.45 * ov[gt_o] + 0.55 * np.array([40, 80, 240])
        ov = _up(ov.astype(np.uint8))
        ov[_outline(_up(scene.human_masks[t]))] = (255, 235, 0)
        if scene.has_object:
            ov[_outline(_up(scene.object_masks[t]))] = (0, 240, 255)
        drgb, lo, hi = _depth_rgb(scene.gt.depth[t])
        panels = [_up(img), ov, _up(drgb), _up((img * 0.55).astype(np.uint8))]
        for c, p in enumerate(panels):
            sheet.paste(Image.fromarray(p), (c * W, y0))
        label = f"frame {t} ({'test' if t in scene.split.get('test', []) else 'train'})"
        draw.text((6, y0 - HEADER + 7), label, fill=(240, 240, 240), font=font)
        draw.text((2 * W + 6, y0 - HEADER + 7), f"depth {lo:.2f} - {hi:.2f} m", fill=(200, 200, 200), font=font)
        # Panel 4: noisy inputs, projected with the noisy camera.
        K, w2c = scene.cameras.K[t], scene.cameras.world_to_camera[t]
        ox = 3 * W

        def proj(P):
            uv, z = project_points(np.asarray(P, dtype=np.float64), w2c, K)
            return uv * SCALE + np.array([ox, y0]), z

        uv, z = proj(scene.points_xyz)
        px = np.floor((uv - np.array([ox, y0])) / SCALE).astype(int)
        inside = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < scene.width) & (px[:, 1] >= 0) & (px[:, 1] < scene.height)
        idx = np.flatnonzero(inside)
        d = scene.gt.depth[t][px[idx, 1], px[idx, 0]]
        for k in idx[z[idx] < d + 0.08]:
            draw.rectangle([uv[k, 0] - 1, uv[k, 1] - 1, uv[k, 0] + 1, uv[k, 1] + 1], fill=(255, 60, 255))
        juv, jz = proj(joints[t])
        for p, j, colour in segs:
            if jz[p] > 0.05 and jz[j] > 0.05:
                draw.line([tuple(juv[p]), tuple(juv[j])], fill=colour, width=3)
        if box_corners is not None:
            cw = scene.object.transform(t, box_corners)
            cuv, cz = proj(cw)
            if (cz > 0.05).all():
                for a, b in _BOX_EDGES:
                    draw.line([tuple(cuv[a]), tuple(cuv[b])], fill=(255, 255, 255), width=2)
                centre = scene.object.translations[t]
                R = scene.object.rotation_matrices()[t]
                for axis, colour in zip(R.T, [(255, 50, 50), (50, 255, 50), (60, 120, 255)]):
                    auv, az = proj(np.stack([centre, centre + 0.15 * axis]))
                    if (az > 0.05).all():
                        draw.line([tuple(auv[0]), tuple(auv[1])], fill=colour, width=3)
    path = Path(path)
    write_image(path, np.asarray(sheet))
    return path
