"""The CoGS ablation table: one run per removed component, evaluated alike.

Each variant is a set of config overrides on the chosen preset (see
`cogs.commands.ABLATIONS`). Runs live in OUT/<variant>; an interrupted ablation resumes,
finished variants are reused. Writes OUT/ablation.json and OUT/ablation.md.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

from cogs.data.io import read_json, write_json

log = logging.getLogger(__name__)


def slug(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", name.lower()).strip("_")


def run_ablation(scene_dir: Path, out: Path, preset: str, variants: dict[str, list[str]]) -> dict:
    from cogs.commands import Train
    from cogs.eval.evaluate import evaluate

    out = Path(out)
    rows: dict[str, dict] = {}
    for i, (name, overrides) in enumerate(variants.items()):
        run = out / slug(name)
        log.info("ablation %d/%d: %s %s", i + 1, len(variants), name, overrides or "")
        if not (run / "train_summary.json").exists():
            resume = (run / "checkpoints" / "last.pt").exists()
            Train(Path(scene_dir), run, preset=preset, set=[] if resume else overrides, resume=resume).run()
        m = read_json(run / "eval" / "metrics.json") if (run / "eval" / "metrics.json").exists() else evaluate(run, save_renders=False)
        rows[name] = {"overrides": overrides, "metrics": m}
        write_json(out / "ablation.json", rows)
    write_table(rows, out / "ablation.md", preset)
    return rows


def _get(m: dict, *path):
    for p in path:
        if not isinstance(m, dict) or m.get(p) is None:
            return None
        m = m[p]
    return m


def table_rows(rows: dict[str, dict]) -> list[dict]:
    full_lpips = _get(rows.get("full", {}), "metrics", "full", "lpips")
    out = []
    for name, r in rows.items():
        m = r["metrics"]
        lp = _get(m, "full", "lpips")
        out.append({
            "variant": name,
            "psnr": _get(m, "full", "psnr"),
            "ssim": _get(m, "full", "ssim"),
            "lpips": lp,
            "delta_lpips": (lp - full_lpips) if lp is not None and full_lpips is not None else None,
            "human_crop_psnr": _get(m, "human_crop", "psnr"),
            "novel_view_psnr": _get(m, "novel_view", "psnr"),
            "novel_human_iou": _get(m, "novel_view", "human_iou"),
            "human_iou": _get(m, "decomposition", "human_iou"),
            "object_iou": _get(m, "decomposition", "object_iou"),
            "object_rot_deg": _get(m, "object_pose_error", "rotation_deg"),
            "object_trans_cm": (_get(m, "object_pose_error", "translation") or 0) * 100 if _get(m, "object_pose_error", "translation") is not None else None,
            "train_s": m.get("train_seconds"),
        })
    return out


def write_table(rows: dict[str, dict], path: Path, preset: str) -> None:
    cols = ["variant", "psnr", "ssim", "lpips", "delta_lpips", "human_crop_psnr", "novel_view_psnr",
            "novel_human_iou", "human_iou", "object_iou", "object_rot_deg", "object_trans_cm", "train_s"]
    fmt = lambda v: "—" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v))  # noqa: E731
    lines = [f"Ablations, preset `{preset}` (held-out frames; LPIPS — when its weights are unavailable)", "",
             "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in table_rows(rows):
        lines.append("| " + " | ".join(fmt(r[c]) for c in cols) + " |")
    Path(path).write_text("\n".join(lines) + "\n")
    log.info("wrote %s\n%s", path, "\n".join(lines))
    print(json.dumps(table_rows(rows)))
