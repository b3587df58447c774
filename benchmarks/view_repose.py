"""`cogs view`: how long a timeline step takes to re-pose the human and the object and reach
the browser, on a trained run (the demo run: ~90k Gaussians, of which the scene's ~60k are
sent once).

Usage:  python benchmarks/view_repose.py --run demo_out [--scene SCENE] [--steps 40]
                                         [--motion run] [--object run]

It starts the viewer (`View.start`, a real viser server on a free local port) and connects
a websocket client speaking viser's protocol in place of the browser: it reads every frame
the server sends, decodes its message header, and counts bytes. It then moves the "Frame"
slider as the page does, `--steps` times over the timeline, and times each step from the
slider's change to the moment the client has received the frame carrying that step's status
line (which is queued after the splats, in the same atomic group):

    pose_ms    posing the human and the object (LBS, object pose, shading) and turning them
               into viser's arrays (covariances, colours), in the viewer's worker
    queue_ms   packing them into viser's buffers and queueing them
    step_ms    slider change -> the step's last byte received by the client (all of it)

Progress goes to stderr; the last stdout line is one JSON object (medians, 90th
percentiles, bytes per step and the scene's bytes, sent once at connection).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import sys
import threading
import time
from pathlib import Path

import cogs  # noqa: F401  (before torch: torch's OpenMP wait policy as the cogs command has it)
import torch


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Client:
    """A websocket client in the browser's place: receives and decodes viser's frames."""

    def __init__(self, port: int):
        import viser
        from websockets.sync.client import connect

        self.ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"],
                          max_size=None, compression=None)
        self.frames: list[tuple[float, int, bytes]] = []  # (arrival time, bytes, decoded msgpack header)
        self.cond = threading.Condition()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        import zstandard

        d = zstandard.ZstdDecompressor()
        try:
            for raw in self.ws:
                t = time.perf_counter()
                n_inner = int.from_bytes(raw[:8], "little")
                n_comp = int.from_bytes(raw[8:16], "little")
                inner = d.decompress(raw[16 : 16 + n_comp], max_output_size=n_inner)
                with self.cond:
                    self.frames.append((t, len(raw), inner))
                    self.cond.notify_all()
        except Exception:  # closed
            return

    def wait_for(self, needle: bytes, after: int, timeout: float = 60.0) -> tuple[float, int]:
        """(arrival time, bytes received from frame `after` on) once a frame holding `needle` came."""
        with self.cond:
            ok = self.cond.wait_for(lambda: any(needle in f[2] for f in self.frames[after:]), timeout)
            assert ok, f"no frame with {needle!r} within {timeout} s"
            i = next(i for i in range(after, len(self.frames)) if needle in self.frames[i][2])
            return self.frames[i][0], sum(f[1] for f in self.frames[after : i + 1])

    def close(self) -> None:
        self.ws.close()
        self.thread.join(timeout=5)


def pct(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(q * (len(xs) - 1))))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=Path, default=Path("demo_out"))
    ap.add_argument("--scene", type=Path, default=None)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--motion", default="run")
    ap.add_argument("--object", default="run")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()

    from cogs.use.view import View

    port = free_port()
    t0 = time.perf_counter()
    viewer = View(run_dir=args.run, scene=args.scene, port=port, motion=args.motion, object=args.object,
                  device=args.device).start()
    log(f"viewer up in {time.perf_counter() - t0:.1f} s: {viewer.model.counts()} Gaussians, {viewer.n} steps")
    client = Client(port)
    try:
        # The page's first load: everything, the scene included, once.
        _, backlog = client.wait_for(b"frame 0 /", 0)
        counts = viewer.model.counts()
        # viser's layout: 32 bytes a Gaussian (centre f32 x3, covariance f16 x6, RGBA u8).
        scene_bytes = 32 * counts["scene"]
        log(f"first load: {backlog / 1e6:.2f} MB (the scene's splats: {scene_bytes / 1e6:.2f} MB)")
        viewer.timings.clear()
        n = viewer.n
        steps = [1 + (i * 37) % (n - 1) for i in range(args.steps)]  # spread over the timeline, each a change
        prev = 0
        step_ms, step_bytes = [], []
        for k in steps:
            if k == prev:
                continue
            after = len(client.frames)
            t = time.perf_counter()
            viewer.slider.value = k  # as the page's slider does
            arrived, nbytes = client.wait_for(f"frame {k} /".encode(), after)
            step_ms.append(1000 * (arrived - t))
            step_bytes.append(nbytes)
            prev = k
        pose = [x["pose_ms"] for x in viewer.timings]
        queue = [x["queue_ms"] for x in viewer.timings]
        result = {
            "benchmark": "view_repose",
            "run": args.run.name,
            "device": str(viewer.model.device),
            "gaussians": counts,
            "moving_gaussians_per_step": viewer.timings[-1]["splats"],
            "steps_timed": len(step_ms),
            "pose_ms_median": round(statistics.median(pose), 1),
            "pose_ms_p90": round(pct(pose, 0.9), 1),
            "queue_ms_median": round(statistics.median(queue), 1),
            "queue_ms_p90": round(pct(queue, 0.9), 1),
            "step_ms_median": round(statistics.median(step_ms), 1),
            "step_ms_p90": round(pct(step_ms, 0.9), 1),
            "step_ms_max": round(max(step_ms), 1),
            "bytes_per_step_median": int(statistics.median(step_bytes)),
            "first_load_bytes": backlog,
            "scene_splat_bytes_sent_once": scene_bytes,
            "target_ms": 100,
            "met": statistics.median(step_ms) < 100,
            "torch_threads": torch.get_num_threads(),
            "load_average_1min": round(os.getloadavg()[0], 2),
            "cpu_count": os.cpu_count(),
        }
    finally:
        client.close()
        viewer.close()
    print(json.dumps(result))


if __name__ == "__main__":
    main()
