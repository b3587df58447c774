"""The batch's results table: OUT/results.csv and OUT/results.md.

One row per entry of the manifest — name, status, error, PSNR / SSIM / LPIPS on the full
frame, the human crop and the object crop (held-out frames), training seconds — and a
mean row over the finished entries, laid out like the CoGS / HOSNeRF papers' per-sequence
tables. LPIPS is null where its weights are unavailable (`cogs doctor`): empty in the CSV,
"—" in the Markdown. The CSV keeps full precision; the Markdown rounds as the papers do.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

from cogs.batch.manifest import Entry
from cogs.batch.steps import STEPS, read_record, run_dir

REGIONS = (("full", "full"), ("human", "human_crop"), ("object", "object_crop"))
MEASURES = (("psnr", "PSNR ↑", "{:.2f}"), ("ssim", "SSIM ↑", "{:.3f}"), ("lpips", "LPIPS ↓", "{:.3f}"))
METRIC_COLUMNS = [f"{r}_{m}" for r, _ in REGIONS for m, _, _ in MEASURES]
COLUMNS = ["name", "status", "error", *METRIC_COLUMNS, "train_seconds"]


def entry_row(entry: Entry, edir: Path) -> dict:
    """The entry's row from what its folder holds: status and error from batch.json,
    numbers from the run's metrics.json (or train_summary.json before evaluation)."""
    from cogs.data.io import read_json

    record = read_record(edir) or {}
    steps = record.get("steps") or {}
    row = {c: None for c in COLUMNS}
    row["name"] = entry.name
    failed = [s for s in STEPS if (steps.get(s) or {}).get("status") == "failed"]
    if failed:
        row["status"] = "failed"
        row["error"] = f"{failed[0]}: {steps[failed[0]].get('error')}"
    elif all((steps.get(s) or {}).get("status") == "done" for s in STEPS):
        row["status"] = "done"
    else:
        row["status"] = "unfinished"
    run = run_dir(edir)
    metrics, summary = run / "eval" / "metrics.json", run / "train_summary.json"
    m = read_json(metrics) if row["status"] == "done" and metrics.is_file() else {}
    for region, key in REGIONS:
        for measure, _, _ in MEASURES:
            row[f"{region}_{measure}"] = (m.get(key) or {}).get(measure)
    if m.get("train_seconds") is not None:
        row["train_seconds"] = m["train_seconds"]
    elif summary.is_file():
        row["train_seconds"] = read_json(summary).get("train_seconds")
    return row


def mean_row(rows: list[dict]) -> dict:
    """Each column's mean over the finished rows that have it (None where none has)."""
    done = [r for r in rows if r["status"] == "done"]
    out = {c: None for c in COLUMNS}
    out["name"] = "mean"
    out["status"] = f"{len(done)}/{len(rows)} done"
    for c in [*METRIC_COLUMNS, "train_seconds"]:
        vals = [r[c] for r in done if r[c] is not None]
        out[c] = sum(vals) / len(vals) if vals else None
        assert out[c] is None or math.isfinite(out[c]), (c, vals)
    return out


def write_results(rows: list[dict], out: Path, title: str) -> tuple[Path, Path]:
    """OUT/results.csv and OUT/results.md from the entries' rows (a mean row appended)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    mean = mean_row(rows)
    csv_path, md_path = out / "results.csv", out / "results.md"
    tmp = csv_path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for r in [*rows, mean]:
            w.writerow({c: "" if r[c] is None else r[c] for c in COLUMNS})
    tmp.replace(csv_path)
    md_path.write_text(markdown(rows, mean, title))
    return csv_path, md_path


def markdown(rows: list[dict], mean: dict, title: str) -> str:
    head = ["sequence", *[f"{r.capitalize()} {label}" for r, _ in REGIONS for _, label, _ in MEASURES],
            "train (s)", "status"]
    fmt = {f"{r}_{m}": f for r, _ in REGIONS for m, _, f in MEASURES}
    lines = [f"# {title}", "",
             "| " + " | ".join(head) + " |", "|" + "---|" + "---:|" * (len(head) - 2) + "---|"]
    errors = []
    for r in [*rows, mean]:
        cells = [f"**{r['name']}**" if r is mean else r["name"]]
        cells += ["—" if r[c] is None else fmt[c].format(r[c]) for c in METRIC_COLUMNS]
        cells.append("—" if r["train_seconds"] is None else f"{r['train_seconds']:.0f}")
        status = r["status"]
        if r.get("error"):
            errors.append(r)
            status += f" [{len(errors)}]"
        cells.append(status)
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Held-out frames of each sequence's protocol; the mean row averages the finished entries "
              "that have the number. LPIPS — where its weights are unavailable (`cogs doctor`); object — "
              "where the protocol has no object crop."]
    if errors:
        lines += ["", "Errors (each entry's log: NAME/log.txt beside this file):", ""]
        lines += [f"{i}. {r['name']}: {_md_escape(r['error'])}" for i, r in enumerate(errors, 1)]
    return "\n".join(lines) + "\n"


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")
