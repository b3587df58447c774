"""`cogs preprocess` on the real development clips: a preview strip per clip and its numbers.

    python benchmarks/dev_clips.py --clips DIR --work DIR [--only NAME ...] [--max-side 384]

The clips are the ones named in the shared data's README (fetched by the user from their
public repositories; they are never part of this project): DIR holds ``juggle.mp4``,
``backpack.mp4``, ``bottle.webm``, ``guitar.webm``, ``loading/`` (the top-left 640x360
quadrant of SLAHMR's composite ``loading.mp4``, one PNG per frame; it keeps the
composite's "Input View" label, which a crop below it would take with the loader's head) and
``basketball_dribble.mp4``; and one clip the README does not list, ``tennis/`` (the same
crop of ``media/davis/tennis.mp4`` on the same repository's gh-pages branch, 139 frames: a
player swings a white racket in front of his white shirt, the case issue 27 was filed on).
A missing clip is skipped and reported as such.

Each clip is preprocessed (``cogs preprocess``, in a subprocess, so a failure is the
command's own message) with the prompts a user would draw: a box on the object on one
frame, and for the clip with two people a box on the person to follow. With
``--second-prompt``, the clips whose strip shows the track leaving the object get the
second box a user would then draw (``SECOND_PROMPTS``; tracking restarts from it). The
boxes are in pixels of the input video and were drawn by looking at the clips' frames;
nothing else is set per clip.

Writes ``WORK/<clip>/strip.png``: ten frames spread over the clip (two rows of five), the person's mask in
cyan and the object's in magenta, each frame labelled with its object confidence
(object.json). Prints one line per clip, then one JSON object on the last line: per clip
the frames, the fraction of frames with a person, with an object mask, and with object
confidence >= 0.2 (what the object branch is supervised on), the mean confidence, and the
seconds the preprocessing took.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

# name: (file, options). Boxes: X0 Y0 X1 Y1 in pixels of the input video.
CLIPS = {
    "basketball": ("basketball_dribble.mp4", ["--object-box", "5", "500", "1260", "660", "1430"]),
    "juggle": ("juggle.mp4", ["--stride", "2", "--limit", "100", "--object-box", "0", "605", "275", "700", "370"]),
    "backpack": ("backpack.mp4", ["--object-box", "0", "210", "125", "280", "275"]),
    "bottle": ("bottle.webm", ["--stride", "2", "--object-box", "0", "370", "925", "410", "1020"]),
    "guitar": ("guitar.webm", ["--stride", "2", "--object-box", "0", "270", "330", "810", "590"]),
    "loading": ("loading", ["--object-box", "12", "280", "145", "415", "240", "--person-box", "0", "330", "90", "530", "360"]),
    "tennis": ("tennis", ["--object-box", "0", "258", "160", "322", "188"]),
}
# The box a user adds (`--second-prompt`) where the first prompt's track leaves the
# object in the strip: the TV box's front face once it is tilted towards the camera (the
# first prompt is its top face), the bottle in the hands (the first is on the floor), the
# racket in front of the shorts on frame 70 (the frame the lost-stretch warning names).
SECOND_PROMPTS = {
    "loading": ["--object-box", "55", "325", "91", "528", "145"],
    "bottle": ["--object-box", "44", "310", "400", "356", "506"],
    "tennis": ["--object-box", "70", "150", "222", "212", "255"],
}


def strip(scene: Path, out: Path, n: int = 10) -> dict:
    """The strip of ``scene`` written to ``out``; returns the clip's statistics."""
    from PIL import Image, ImageDraw

    meta = json.loads((scene / "scene.json").read_text())
    frames = meta["frames"]
    obj = json.loads((scene / "object.json").read_text()) if (scene / "object.json").exists() else {"frames": []}
    conf = {f["id"]: f.get("confidence", 1.0) for f in obj["frames"]}
    stats = {"frames": len(frames), "person": 0, "object": 0, "trusted": 0}
    tiles = []
    pick = set(np.linspace(0, len(frames) - 1, n).astype(int).tolist())
    for i, fid in enumerate(frames):
        human = np.asarray(Image.open(scene / "masks" / "human" / f"{fid}.png")) > 127
        ob_path = scene / "masks" / "object" / f"{fid}.png"
        ob = np.asarray(Image.open(ob_path)) > 127 if ob_path.exists() else np.zeros_like(human)
        c = float(conf.get(fid, 0.0))
        stats["person"] += bool(human.any())
        stats["object"] += bool(ob.any())
        stats["trusted"] += c >= 0.2
        if i in pick:
            rgb = np.asarray(Image.open(scene / "images" / f"{fid}.png").convert("RGB")).astype(np.float32)
            rgb[human] = 0.55 * rgb[human] + 0.45 * np.array([0, 255, 255])
            rgb[ob] = 0.45 * rgb[ob] + 0.55 * np.array([255, 0, 255])
            tile = Image.fromarray(rgb.astype(np.uint8))
            scale = 300 / max(tile.size)
            tile = tile.resize((round(tile.width * scale), round(tile.height * scale)))
            ImageDraw.Draw(tile).text((4, 4), f"{fid} c={c:.2f}", fill=(255, 255, 0))
            tiles.append(tile)
    per_row = 5
    w, h = max(t.width for t in tiles), max(t.height for t in tiles)
    sheet = Image.new("RGB", (per_row * w, -(-len(tiles) // per_row) * h))
    for k, t in enumerate(tiles):
        sheet.paste(t, ((k % per_row) * w, (k // per_row) * h))
    sheet.save(out)
    T = len(frames)
    confs = [float(conf.get(f, 0.0)) for f in frames]
    return {"frames": T, "person": round(stats["person"] / T, 3), "object": round(stats["object"] / T, 3),
            "trusted": round(stats["trusted"] / T, 3), "mean_confidence": round(float(np.mean(confs)), 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clips", type=Path, required=True, help="folder holding the development clips")
    ap.add_argument("--work", type=Path, required=True, help="folder for the scenes and strips")
    ap.add_argument("--only", nargs="*", default=None, help="clip names to run (default: all)")
    ap.add_argument("--max-side", type=int, default=384, help="longer side of the processed frames")
    ap.add_argument("--strips-only", action="store_true", help="redraw the strips of scenes already in WORK")
    ap.add_argument("--cached", action="store_true",
                    help="reuse each scene's cached steps (default: recompute all): a change to a later step is then measured alone")
    ap.add_argument("--second-prompt", action="store_true",
                    help="add the second --object-box of SECOND_PROMPTS on the clips that have one (the others run as without)")
    args = ap.parse_args()
    results = {}
    for name, (file, options) in CLIPS.items():
        if args.only and name not in args.only:
            continue
        src = args.clips / file
        if not src.exists():
            print(f"{name}: {src} not found, skipped")
            results[name] = {"skipped": f"{file} not found"}
            continue
        work = args.work / name
        work.mkdir(parents=True, exist_ok=True)
        if args.strips_only:
            results[name] = strip(work / "scene", work / "strip.png")
            print(f"{name}: {results[name]}")
            continue
        cmd = [sys.executable, "-m", "cogs.cli", "preprocess", str(src), "--out", str(work / "scene"), "--overwrite",
               "--max-side", str(args.max_side), "--no-progress", *([] if args.cached else ["--force"]), *options]
        if args.second_prompt:
            cmd += SECOND_PROMPTS.get(name, [])
        t0 = time.perf_counter()
        done = subprocess.run(cmd, capture_output=True, text=True)
        seconds = round(time.perf_counter() - t0, 1)
        (work / "preprocess.log").write_text(done.stdout + done.stderr)
        if done.returncode != 0:
            lines = (done.stdout + done.stderr).strip().splitlines()
            last = next((ln for ln in lines if ln.startswith("error")), lines[-1] if lines else "?")
            print(f"{name}: preprocess failed ({last})")
            results[name] = {"failed": last, "seconds": seconds}
            continue
        row = strip(work / "scene", work / "strip.png") | {"seconds": seconds, "prompts": 1 + (args.second_prompt and name in SECOND_PROMPTS)}
        results[name] = row
        print(f"{name}: {row}")
    print(json.dumps(results))


if __name__ == "__main__":
    main()
