"""`SCENE/preview.png`: a contact sheet with every estimate drawn over evenly spaced frames.

Per tile: the person mask (blue tint), MediaPipe's keypoints and skeleton (red/white), the
fitted body's projected outline and skeleton (yellow), the object mask (green tint) and
its fitted pose (magenta outline of the cuboid or ellipsoid proxy, red/green/blue axes), and the sparse scene
points that project into the frame (cyan). The caption names the frame, whether its
camera was registered by SfM or interpolated, and the object mask's confidence (orange and
"not trusted" under the object branch's ``min_confidence``: that frame does not supervise
the object).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

BLUE = (60, 110, 255)
GREEN = (40, 220, 80)
YELLOW = (255, 225, 0)
RED = (255, 40, 40)
WHITE = (255, 255, 255)
MAGENTA = (255, 0, 255)
CYAN = (0, 255, 255)
ORANGE = (255, 150, 40)


def caption(frame_id: str, camera: str, confidence: float | None, min_confidence: float) -> tuple[str, tuple[int, int, int]]:
    """A tile's caption and its colour: the frame, the camera's status (``camera``: "" or
    e.g. "  cam: colmap"), and the object mask's ``confidence`` when the scene has one."""
    text, colour = f"frame {frame_id}{camera}", WHITE
    if confidence is not None:
        text += f"  obj {confidence:.2f}"
        if confidence < min_confidence:
            text, colour = text + " not trusted", ORANGE
    return text, colour


def _tint(img: np.ndarray, mask: np.ndarray, colour, alpha: float) -> None:
    if mask.any():
        img[mask] = (img[mask] * (1 - alpha) + np.array(colour) * alpha).astype(np.uint8)


def _outline(img: np.ndarray, mask: np.ndarray, colour, thickness: int) -> None:
    import cv2

    cs, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(img, cs, -1, colour, thickness, lineType=cv2.LINE_AA)


def _project(points: np.ndarray, w2c: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    uv = pc[:, :2] / np.where(z[:, None] > 1e-6, z[:, None], np.nan) * [K[0, 0], K[1, 1]] + K[:2, 2]
    return uv, z


def _mesh_mask(verts_uv: np.ndarray, faces: np.ndarray, shape) -> np.ndarray:
    import cv2

    H, W = shape
    tri = verts_uv[faces]  # [F, 3, 2]
    ok = np.isfinite(tri).all(axis=(1, 2))
    m = np.zeros((H, W), np.uint8)
    cv2.fillPoly(m, list((tri[ok] * 4).astype(np.int32)), 1, lineType=cv2.LINE_8, shift=2)
    return m.astype(bool)


def draw_frame(
    scene,
    t: int,
    kp2d: np.ndarray | None,
    body_verts: np.ndarray | None,
    faces: np.ndarray | None,
    body_joints: np.ndarray | None,
    bone_parents: list[int] | None,
    radii: np.ndarray | None,
    points_sel: np.ndarray | None,
    skeleton: list[tuple[int, int]] | None = None,
    proxy: str | None = None,
) -> np.ndarray:
    """One annotated frame [H, W, 3] uint8 at the scene's resolution."""
    import cv2

    from cogs.preprocess.persons import EDGES

    img = scene.images[t].copy()
    H, W = img.shape[:2]
    cam = scene.camera(t)
    K, w2c = cam.K, cam.world_to_camera
    lw = max(1, round(min(H, W) / 300))
    _tint(img, scene.human_masks[t], BLUE, 0.35)
    if scene.has_object:
        om = scene.object_masks[t]
        _tint(img, om, GREEN, 0.45)
        _outline(img, om, GREEN, lw)
    if points_sel is not None and len(points_sel):
        uv, z = _project(points_sel, w2c, K)
        ok = (z > 0) & np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        for x, y in uv[ok].astype(int):
            cv2.circle(img, (int(x), int(y)), max(1, lw - 1), CYAN, -1)
    if body_verts is not None:
        uv, z = _project(body_verts, w2c, K)
        if (z > 0).all():
            _outline(img, _mesh_mask(uv, faces, (H, W)), YELLOW, lw + 1)
    if body_joints is not None and skeleton:
        uv, z = _project(body_joints, w2c, K)
        for j, p in skeleton:
            if z[j] > 0 and z[p] > 0 and np.isfinite(uv[[j, p]]).all():
                cv2.line(img, tuple(uv[j].astype(int)), tuple(uv[p].astype(int)), YELLOW, lw, cv2.LINE_AA)
    if kp2d is not None and np.isfinite(kp2d[t]).all():
        k = kp2d[t]
        for a, b in EDGES:
            if min(k[a, 2], k[b, 2]) > 0.3:
                cv2.line(img, tuple(k[a, :2].astype(int)), tuple(k[b, :2].astype(int)), WHITE, lw, cv2.LINE_AA)
        for x, y, v in k:
            if v > 0.3:
                cv2.circle(img, (int(x), int(y)), lw + 1, RED, -1)
    if scene.has_object and radii is not None:
        from cogs.preprocess.objectfit import proxy_points

        R = scene.object.rotation_matrices()[t]
        c = scene.object.translations[t]
        pts = proxy_points(proxy or "ellipsoid", np.asarray(radii), 400) @ R.T + c
        uv, z = _project(pts, w2c, K)
        if (z > 0).all():
            hull = cv2.convexHull(uv.astype(np.float32)).astype(np.int32)
            cv2.polylines(img, [hull], True, MAGENTA, lw, cv2.LINE_AA)
            axes = c + np.eye(3) @ R.T * (1.3 * float(np.max(radii)))
            cuv, _ = _project(np.vstack([c, axes]), w2c, K)
            for k, col in enumerate((RED, GREEN, BLUE)):
                cv2.line(img, tuple(cuv[0].astype(int)), tuple(cuv[k + 1].astype(int)), col, lw, cv2.LINE_AA)
    return img


def _main_skeleton(model) -> list[tuple[int, int]]:
    """(bone, parent) pairs of the limbs, spine and head (no fingers, toes or eyes)."""
    skip = ("finger", "toe", "metacarpal", "eye")
    out = []
    for j, p in enumerate(model.bone_parents):
        if p >= 0 and not model.bone_names[j].startswith(skip) and not model.bone_names[p].startswith(skip):
            out.append((j, p))
    return out


def contact_sheet(
    scene_root: str | Path,
    out_path: str | Path,
    kp2d: np.ndarray | None = None,
    registered: np.ndarray | None = None,
    camera_method: str = "",
    radii: np.ndarray | None = None,
    proxy: str | None = None,
    n_frames: int = 12,
    tile_width: int | None = None,
    body_model: str | None = None,
) -> Path:
    """Write the contact sheet of the scene at ``scene_root`` to ``out_path``."""
    import cv2
    import torch

    from cogs.data.io import write_image
    from cogs.data.scene import load_scene

    scene = load_scene(scene_root, validate=False)
    T = scene.n_frames
    frames = sorted(set(np.linspace(0, T - 1, min(n_frames, T)).round().astype(int).tolist()))
    model = None
    try:
        from cogs.body import load_body_model

        model = load_body_model(body_model or scene.body.model)
    except Exception:  # the preview still shows everything else
        model = None
    verts = joints = faces = skeleton = None
    if model is not None:
        pose = torch.tensor(scene.body.pose[frames], dtype=torch.float32)
        transl = torch.tensor(scene.body.transl[frames], dtype=torch.float32)
        shape = torch.tensor(scene.body.shape, dtype=torch.float32)
        with torch.no_grad():
            verts = model.posed_vertices(pose, transl, shape).numpy()
            _, joints = model.bone_transforms(pose, transl, shape)
            joints = joints.numpy()
        faces = model.canonical(shape).faces.numpy()
        skeleton = _main_skeleton(model)
    from cogs.branches.object import ObjectConfig

    confidence = scene.object.confidence if scene.has_object else None
    min_confidence = ObjectConfig().min_confidence
    pts = scene.points_xyz
    if len(pts) > 1500:
        pts = pts[np.random.default_rng(0).choice(len(pts), 1500, replace=False)]
    H, W = scene.height, scene.width
    cols = 4 if H >= W else 3
    tw = tile_width or (300 if H >= W else 420)
    th = int(round(H * tw / W))
    cap = 22
    rows = (len(frames) + cols - 1) // cols
    sheet = np.full((rows * (th + cap) + 30, cols * tw, 3), 24, np.uint8)
    for i, t in enumerate(frames):
        img = draw_frame(
            scene, t, kp2d,
            None if verts is None else verts[i], faces,
            None if joints is None else joints[i], None, radii, pts, skeleton, proxy,
        )
        tile = cv2.resize(img, (tw, th), interpolation=cv2.INTER_AREA)
        r, c = divmod(i, cols)
        y0, x0 = r * (th + cap), c * tw
        sheet[y0 + cap : y0 + cap + th, x0 : x0 + tw] = tile
        status = f"  cam: {camera_method}" if camera_method else ""
        if registered is not None and not registered[t]:
            status += " (interpolated)" if camera_method.startswith("colmap") else " (no match: held)"
        text, colour = caption(scene.frame_ids[t], status, None if confidence is None else float(confidence[t]), min_confidence)
        cv2.putText(sheet, text, (x0 + 4, y0 + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
    legend = [("person mask", BLUE), ("keypoints", RED), ("fitted body", YELLOW), ("object mask", GREEN), ("object pose", MAGENTA), ("points", CYAN)]
    x = 6
    y = sheet.shape[0] - 10
    for text, col in legend:
        cv2.rectangle(sheet, (x, y - 10), (x + 12, y + 2), col, -1)
        cv2.putText(sheet, text, (x + 16, y), cv2.FONT_HERSHEY_SIMPLEX, 0.42, WHITE, 1, cv2.LINE_AA)
        x += 22 + 8 * len(text)
    write_image(out_path, sheet)
    return Path(out_path)
