"""The CoGS ablation table: one run per removed component and seed, evaluated alike.

Each variant is a set of config overrides on the chosen preset (see
`cogs.commands.ABLATIONS`). A variant's run with seed 0 (the config's default, no
override) lives in OUT/<variant>, with any other seed k in OUT/<variant>.seed<k>, so a
one-seed ablation keeps the old layout and adding a seed reuses the runs already there.
An interrupted ablation resumes; finished runs are reused, and a run trained before a
stage was added gets just that stage.

With several seeds each row holds the mean over them, and ablation.md writes every value
as mean ± half the range over seeds. A value is starred where the variant's range over
seeds and the full model's do not overlap: the change is larger than what the seed alone
moves. Writes OUT/ablation.json (per row: overrides, mean metrics, per-seed metrics) and
OUT/ablation.md.
"""

from __future__ import annotations

import json
import logging
import math
import re
from pathlib import Path

from cogs.data.io import read_json, write_json

log = logging.getLogger(__name__)

COLUMNS = ["psnr", "ssim", "lpips", "delta_lpips", "human_crop_psnr", "novel_view_psnr",
           "novel_human_iou", "human_iou", "object_iou", "object_rot_deg", "object_trans_cm", "train_s"]


def slug(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", name.lower()).strip("_")


def run_dir(out: Path, name: str, seed: int) -> Path:
    """Where a variant's run with `seed` lives."""
    return Path(out) / (slug(name) if seed == 0 else f"{slug(name)}.seed{seed}")


def seed_overrides(overrides: list[str], seed: int) -> list[str]:
    return list(overrides) if seed == 0 else [*overrides, f"seed={seed}"]


def run_ablation(scene_dir: Path, out: Path, preset: str, variants: dict[str, list[str]],
                 seeds: tuple[int, ...] = (0,), device: str = "cpu") -> dict:
    from cogs.config import apply_overrides, load_config
    from cogs.config import preset as get_preset
    from cogs.data.scene import load_scene
    from cogs.eval.evaluate import evaluate
    from cogs.train.run_folder import prepare_new_run
    from cogs.train.trainer import Trainer, run_is_finished

    assert seeds and len(set(seeds)) == len(seeds), seeds
    out = Path(out)
    rows: dict[str, dict] = {}
    jobs = [(name, ov, s) for name, ov in variants.items() for s in seeds]
    for i, (name, overrides, seed) in enumerate(jobs):
        run = run_dir(out, name, seed)
        sets = seed_overrides(overrides, seed)
        log.info("ablation %d/%d: %s, seed %d %s", i + 1, len(jobs), name, seed, overrides or "")
        trained = not run_is_finished(run)
        if trained:
            resume = (run / "checkpoints" / "last.pt").exists()
            cfg = load_config(run / "config.yaml") if resume else apply_overrides(get_preset(preset), sets)
            if not resume:  # the ablation's own folder: a start that never reached a checkpoint is redone
                prepare_new_run(run, overwrite=True)
            Trainer(load_scene(scene_dir, ground_truth=False), cfg, run, resume=resume, device=device).run()
        saved = run / "eval" / "metrics.json"
        m = read_json(saved) if saved.exists() and not trained else evaluate(run, save_renders=False, device=device)
        row = rows.setdefault(name, {"overrides": overrides, "seeds": {}})
        row["seeds"][str(seed)] = m
        row["metrics"] = mean_metrics(list(row["seeds"].values()))
        write_json(out / "ablation.json", rows)
    write_table(rows, out / "ablation.md", preset)
    return rows


def mean_metrics(runs: list[dict]):
    """The mean over runs of every number in a metrics tree; None where any run has none,
    other leaves (strings, lists) from the first run."""
    first = runs[0]
    if isinstance(first, dict):
        return {k: mean_metrics([r.get(k) if isinstance(r, dict) else None for r in runs]) for k in first}
    if isinstance(first, bool) or not isinstance(first, (int, float)):
        return first
    if any(not isinstance(r, (int, float)) for r in runs):
        return None
    return sum(runs) / len(runs)


def _get(m: dict, *path):
    for p in path:
        if not isinstance(m, dict) or m.get(p) is None:
            return None
        m = m[p]
    return m


def _values(m: dict) -> dict:
    trans = _get(m, "object_pose_error", "translation")
    return {
        "psnr": _get(m, "full", "psnr"),
        "ssim": _get(m, "full", "ssim"),
        "lpips": _get(m, "full", "lpips"),
        "human_crop_psnr": _get(m, "human_crop", "psnr"),
        "novel_view_psnr": _get(m, "novel_view", "psnr"),
        "novel_human_iou": _get(m, "novel_view", "human_iou"),
        "human_iou": _get(m, "decomposition", "human_iou"),
        "object_iou": _get(m, "decomposition", "object_iou"),
        "object_rot_deg": _get(m, "object_pose_error", "rotation_deg"),
        "object_trans_cm": trans * 100 if trans is not None else None,
        "train_s": m.get("train_seconds"),
    }


def _seed_values(row: dict) -> list[dict]:
    """Each seed's column values (a row without per-seed metrics: its one run)."""
    runs = list(row["seeds"].values()) if row.get("seeds") else [row["metrics"]]
    return [_values(m) for m in runs]


def table_rows(rows: dict[str, dict]) -> list[dict]:
    """One dict per variant: the columns' means over seeds, `spread` (half the range over
    seeds, per column), `beyond_spread` (measures whose range over seeds misses the full
    model's; training time is not one) and `n_seeds`."""
    full = _seed_values(rows["full"]) if "full" in rows else None
    full_lpips = _mean([v["lpips"] for v in full]) if full else None
    out = []
    for name, r in rows.items():
        per = _seed_values(r)
        row = {"variant": name, "n_seeds": len(per), "spread": {}, "beyond_spread": []}
        for c in per[0]:
            vals = [v[c] for v in per]
            row[c] = _mean(vals)
            row["spread"][c] = None if row[c] is None else (max(vals) - min(vals)) / 2
            if full and name != "full" and c != "train_s" and _apart(vals, [v[c] for v in full]):
                row["beyond_spread"].append(c)
        row["delta_lpips"] = row["lpips"] - full_lpips if row["lpips"] is not None and full_lpips is not None else None
        out.append(row)
    return out


def _apart(vals: list, ref: list) -> bool:
    """Whether two ranges over seeds (two runs or more each, all measured) do not overlap."""
    if len(vals) < 2 or len(ref) < 2 or None in vals or None in ref:
        return False
    return min(vals) > max(ref) or max(vals) < min(ref)


def _mean(vals: list) -> float | None:
    if not vals or any(v is None for v in vals):
        return None
    m = sum(vals) / len(vals)
    assert math.isfinite(m), vals
    return m


def _cell(r: dict, c: str) -> str:
    v = r[c]
    if v is None:
        return "—"
    if c == "train_s":
        s = f"{v:.0f}"
    else:
        s = f"{v:.3f}"
        if r["n_seeds"] > 1 and r["spread"].get(c) is not None:
            s += f" ± {r['spread'][c]:.3f}"
    return s + ("*" if c in r["beyond_spread"] else "")


def write_table(rows: dict[str, dict], path: Path, preset: str) -> None:
    cols = ["variant", *COLUMNS]
    trs = table_rows(rows)
    n = max(r["n_seeds"] for r in trs)
    head = f"Ablations, preset `{preset}` (held-out frames; LPIPS — when its weights are unavailable)"
    if n > 1:
        head += (f"; mean ± half the range over {n} seeds, * where the variant's range over seeds"
                 " misses the full model's")
    lines = [head, "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in trs:
        lines.append("| " + " | ".join([r["variant"]] + [_cell(r, c) for c in COLUMNS]) + " |")
    Path(path).write_text("\n".join(lines) + "\n")
    log.info("wrote %s\n%s", path, "\n".join(lines))
    print(json.dumps(trs))
