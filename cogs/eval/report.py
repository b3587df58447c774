"""The human-readable report of a run: metrics table, loss curves, image strips, videos.

Reads what training and evaluation wrote (train_log.json, eval/metrics.json,
eval/renders, eval/novel) and renders the two videos itself. Writes report.html and
report.md side by side, with every image next to them.
"""

from __future__ import annotations

import html
import logging
import math
from pathlib import Path

import numpy as np
import torch

from cogs.data.io import read_image, read_json, write_image
from cogs.geometry.camera import look_at

log = logging.getLogger(__name__)


# -- videos --------------------------------------------------------------------------------


def write_video(path: Path, frames: list[np.ndarray], fps: float = 10.0) -> None:
    """H.264 mp4 (yuv420p, even dimensions) from [H, W, 3] float/uint8 frames."""
    import av

    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = frames[0].shape[:2]
    H, W = h + h % 2, w + w % 2
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=int(round(fps)))
        stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
        stream.options = {"crf": "20"}
        for f in frames:
            f = np.asarray(f)
            if f.dtype != np.uint8:
                f = (np.clip(f, 0, 1) * 255 + 0.5).astype(np.uint8)
            f = np.pad(f, ((0, H - h), (0, W - w), (0, 0)), mode="edge")
            for packet in stream.encode(av.VideoFrame.from_ndarray(f, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def orbit_cameras(centre: np.ndarray, radius: float, height: float, n: int, up=(0.0, 0.0, 1.0)) -> list[np.ndarray]:
    """n world_to_camera matrices on a horizontal circle around `centre`, looking at it."""
    out = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = centre + np.array([radius * math.cos(a), radius * math.sin(a), height])
        out.append(look_at(eye, centre, up))
    return out


def render_videos(model, scene, out: Path, orbit_frames: int = 72) -> dict[str, str]:
    """Composite renders along the training camera path and along a new orbit."""
    from cogs.eval.evaluate import _numpy, render_frame

    path_frames = [_numpy(render_frame(model, scene, t).rgb) for t in range(scene.n_frames)]
    gt_frames = [scene.images[t] / 255.0 for t in range(scene.n_frames)]
    side = [np.concatenate([g, p], axis=1) for g, p in zip(gt_frames, path_frames)]
    write_video(out / "video_camera_path.mp4", side, fps=scene.fps)
    # Orbit around the person, the sequence playing while the camera circles.
    h = model.human
    with torch.no_grad():
        joints = [h.body.bone_transforms(*h.frame_pose(t), h.shape)[1][0].mean(0).cpu().numpy() for t in range(scene.n_frames)]
    centre = np.mean(joints, axis=0)
    cams = scene.cameras.world_to_camera
    eyes = -np.einsum("tji,tj->ti", cams[:, :3, :3], cams[:, :3, 3])
    radius = float(np.median(np.linalg.norm((eyes - centre)[:, :2], axis=1)))
    height = float(np.median(eyes[:, 2] - centre[2]))
    orbit = orbit_cameras(centre, radius, height, orbit_frames)
    frames = []
    for i, vm in enumerate(orbit):
        t = int(round(i / max(orbit_frames - 1, 1) * (scene.n_frames - 1)))
        frames.append(_numpy(render_frame(model, scene, t, viewmat=vm, K=scene.cameras.K[0]).rgb))
    write_video(out / "video_orbit.mp4", frames, fps=scene.fps)
    return {"camera_path": "video_camera_path.mp4", "orbit": "video_orbit.mp4"}


# -- figures ---------------------------------------------------------------------------------


def plot_losses(train_log: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hist = train_log.get("history", [])
    stages = list(dict.fromkeys(h["stage"] for h in hist))
    fig, axes = plt.subplots(1, max(len(stages), 1), figsize=(3.2 * max(len(stages), 1), 2.8), squeeze=False)
    for ax, st in zip(axes[0], stages):
        rows = [h for h in hist if h["stage"] == st]
        steps = [h["step"] for h in rows]
        keys = [k for k in rows[0] if k not in ("stage", "step", "frame", "human", "object", "scene", "total")]
        for k in keys:
            vals = [h.get(k) for h in rows]
            if all(v is not None and v > 0 for v in vals):
                ax.plot(steps, vals, label=k, lw=1.2 if k == "loss" else 0.8)
        ax.set_yscale("log")
        ax.set_title(f"stage {st}", fontsize=9)
        ax.set_xlabel("training frame (in order)" if st == "refit" else "step", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6, loc="upper right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _label(img: np.ndarray, text: str) -> np.ndarray:
    from PIL import Image, ImageDraw

    im = Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8) if img.dtype != np.uint8 else img)
    d = ImageDraw.Draw(im)
    d.rectangle([0, 0, 7 * len(text) + 6, 13], fill=(0, 0, 0))
    d.text((3, 1), text, fill=(255, 255, 255))
    return np.asarray(im)


def strip(rows: list[list[tuple[str, Path]]], path: Path) -> bool:
    """A grid image: each row a list of (label, png path); missing files become grey."""
    if not rows:
        return False
    grid = []
    shape = None
    for row in rows:
        cells = []
        for label, p in row:
            if p.exists():
                im = read_image(p)
                shape = im.shape
            else:
                im = None
            cells.append((label, im))
        grid.append(cells)
    if shape is None:
        return False
    out_rows = []
    for cells in grid:
        ims = [_label(im if im is not None else np.full(shape, 128, np.uint8), label) for label, im in cells]
        sep = np.full((shape[0], 2, 3), 255, np.uint8)
        out_rows.append(np.concatenate(sum([[im, sep] for im in ims], [])[:-1], axis=1))
    sep = np.full((2, out_rows[0].shape[1], 3), 255, np.uint8)
    write_image(path, np.concatenate(sum([[r, sep] for r in out_rows], [])[:-1], axis=0))
    return True


def _fmt(v) -> str:
    if v is None:
        return "—"
    if isinstance(v, float):
        return f"{v:.4f}" if abs(v) < 10 else f"{v:.2f}"
    return str(v)


def _flat(d: dict, prefix: str = "") -> dict:
    """{"a": 1, "b": {"c": 2}} -> {"a": 1, "b.c": 2}."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def metrics_table(m: dict) -> list[tuple[str, str]]:
    rows = []
    for group in ("full", "human_crop", "object_crop", "novel_view"):
        g = m.get(group)
        if isinstance(g, dict):
            rows.append((group, ", ".join(f"{k} {_fmt(v)}" for k, v in _flat(g).items())))
    for group in ("decomposition", "object_pose_error"):
        g = m.get(group)
        if isinstance(g, dict):
            rows.append((group, ", ".join(f"{k} {_fmt(v)}" for k, v in g.items())))
    fit = m.get("test_time_pose_fit")
    if isinstance(fit, dict):  # a separate protocol: it looks at the test images
        for group in ("full", "human_crop", "object_crop", "decomposition"):
            g = fit.get(group)
            if isinstance(g, dict):
                rows.append((f"with test-time pose fit ({fit.get('steps')} steps): {group}",
                             ", ".join(f"{k} {_fmt(v)}" for k, v in g.items())))
    rows.append(("train seconds", _fmt(m.get("train_seconds"))))
    if m.get("stage_seconds"):
        rows.append(("stage seconds", ", ".join(f"{k} {v:.0f}" for k, v in m["stage_seconds"].items())))
    if m.get("n_gaussians"):
        rows.append(("Gaussians", ", ".join(f"{k} {v}" for k, v in m["n_gaussians"].items())))
    return rows


def write_report(run: Path, title: str = "cogs run", extra: dict | None = None, videos: bool = True,
                 device: str = "cpu") -> Path:
    """Build report.html / report.md in RUN from the run's outputs; returns the HTML path."""
    from cogs.eval.evaluate import load_run

    run = Path(run)
    m = read_json(run / "eval" / "metrics.json")
    figs = run / "report_files"
    plot_losses(read_json(run / "train_log.json"), figs / "losses.png")
    model, _, scene = load_run(run, device)
    test = scene.split["test"]
    pick = [test[i] for i in np.linspace(0, len(test) - 1, min(4, len(test))).round().astype(int)] if test else []
    rd = run / "eval" / "renders"
    held = [[("GT", rd / f"{scene.frame_ids[t]}_gt.png"), ("render", rd / f"{scene.frame_ids[t]}_composite.png"),
             ("human", rd / f"{scene.frame_ids[t]}_human.png"), ("object", rd / f"{scene.frame_ids[t]}_object.png"),
             ("scene", rd / f"{scene.frame_ids[t]}_scene.png"), ("|error|", rd / f"{scene.frame_ids[t]}_error.png")] for t in pick]
    has_held = strip(held, figs / "heldout.png")
    nd = run / "eval" / "novel"
    n_novel = len(list(nd.glob("*_render.png"))) if nd.exists() else 0
    nv_rows = []
    idx = list(range(n_novel))[:: max(1, n_novel // 6)][:6]
    for a, b in zip(idx[0::2], idx[1::2]):
        nv_rows.append([(f"GT v{a}", nd / f"v{a:03d}_gt.png"), ("render", nd / f"v{a:03d}_render.png"),
                        (f"GT v{b}", nd / f"v{b:03d}_gt.png"), ("render", nd / f"v{b:03d}_render.png")])
    has_novel = strip(nv_rows, figs / "novel.png")
    vids = render_videos(model, scene, figs) if videos else {}

    table = metrics_table(m)
    notes = m.get("notes", [])
    md = [f"# {title}", "", f"Scene: `{scene.root}` ({scene.n_frames} frames, {scene.width}x{scene.height}); "
          f"protocol {m['protocol']}, {m['n_test_frames']} held-out frames.", ""]
    if extra:
        md += [f"- {k}: {v}" for k, v in extra.items()] + [""]
    md += ["| metric | value |", "|---|---|"] + [f"| {k} | {v} |" for k, v in table] + [""]
    md += ["## Loss curves", "", "![losses](report_files/losses.png)", ""]
    if has_held:
        md += ["## Held-out frames (GT | render | human | object | scene | error)", "", "![held-out](report_files/heldout.png)", ""]
    if has_novel:
        md += ["## Novel views", "", "![novel](report_files/novel.png)", ""]
    for k, v in vids.items():
        md += [f"- video ({k.replace('_', ' ')}): [report_files/{v}](report_files/{v})"]
    if notes:
        md += ["", "## Notes", ""] + [f"- {n}" for n in notes]
    (run / "report.md").write_text("\n".join(md) + "\n")

    esc = html.escape
    rows = "".join(f"<tr><td>{esc(k)}</td><td>{esc(v)}</td></tr>" for k, v in table)
    parts = [f"<!doctype html><meta charset='utf-8'><title>{esc(title)}</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto}td{padding:2px 10px;border-bottom:1px solid #ddd}img,video{max-width:100%}</style>",
             f"<h1>{esc(title)}</h1><p>Scene <code>{esc(str(scene.root))}</code>: {scene.n_frames} frames, {scene.width}x{scene.height}; "
             f"protocol {esc(m['protocol'])}, {m['n_test_frames']} held-out frames.</p>"]
    if extra:
        parts.append("<ul>" + "".join(f"<li>{esc(str(k))}: {esc(str(v))}</li>" for k, v in extra.items()) + "</ul>")
    parts.append(f"<table>{rows}</table><h2>Loss curves</h2><img src='report_files/losses.png'>")
    if has_held:
        parts.append("<h2>Held-out frames</h2><p>GT | render | human | object | scene | error</p><img src='report_files/heldout.png'>")
    if has_novel:
        parts.append("<h2>Novel views</h2><img src='report_files/novel.png'>")
    for k, v in vids.items():
        parts.append(f"<h2>Video: {esc(k.replace('_', ' '))}</h2><video controls loop src='report_files/{v}'></video>")
    if notes:
        parts.append("<h2>Notes</h2><ul>" + "".join(f"<li>{esc(n)}</li>" for n in notes) + "</ul>")
    (run / "report.html").write_text("\n".join(parts))
    return run / "report.html"
