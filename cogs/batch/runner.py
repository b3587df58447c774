"""The entries on Ray: one chain of tasks per entry, a live table, the records.

Each step that is not done becomes one Ray task (`execute_step`), chained to the entry's
previous one by its ObjectRef, so Ray starts it when the previous step has finished and
a worker with the job's resources is free. A task runs the step's library call
(`cogs.batch.steps`) in a fresh worker process (`max_calls=1`): nothing — memory, global
generators, thread pools, a configured SMPL path — leaks from one entry into the next,
as with a subprocess per step, while errors and results come back as Python objects.
A task never raises for a failing step: it returns {"status": "failed", "error": ...}
and the entry's later tasks return "not run" at once; only a crashed worker (killed,
out of memory) surfaces as a Ray error, which the driver records the same way.

The driver is the only writer of OUT/NAME/batch.json and OUT/results.*; it rewrites them
after every step, so an interrupted batch leaves an accurate table. Tasks report what
they are doing to a small actor (`Board`), which the live table polls.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from cogs.batch.manifest import Entry
from cogs.batch.results import entry_row, write_results
from cogs.batch.steps import RECORD, STEP_FUNCTIONS, STEPS, read_record
from cogs.errors import UserError

log = logging.getLogger("cogs")


# -- inside the workers ----------------------------------------------------------------------


class Board:
    """A Ray actor: what each entry is doing now, as its tasks report it."""

    def __init__(self):
        self.rows: dict[str, tuple[str, str]] = {}

    def report(self, name: str, step: str, stage: str) -> None:
        self.rows[name] = (step, stage)

    def snapshot(self) -> dict[str, tuple[str, str]]:
        return dict(self.rows)


def execute_step(step: str, entry: Entry, edir: str, device: str, threads: int, board, upstream: dict | None = None
                 ) -> dict:
    """One step of one entry, in a Ray worker: the step's output goes to OUT/NAME, its log
    (and anything printed) to OUT/NAME/log.txt. `upstream` is the previous step's result."""
    if upstream is not None and upstream.get("status") != "done":
        return {"status": "not run"}
    edir = Path(edir)
    _limit_threads(threads)
    board.report.remote(entry.name, step, "")
    t0 = time.perf_counter()
    with _logging_to(edir / "log.txt"):
        log.info("== %s: %s (%s, %d thread(s))", entry.name, step, device, threads)
        try:
            result = STEP_FUNCTIONS[step](entry, edir, lambda stage: board.report.remote(entry.name, step, stage),
                                          device)
            out = {"status": "done", "result": result}
        except Exception as e:  # any failure is the entry's, never the batch's
            log.error("%s failed:\n%s", step, traceback.format_exc())
            out = {"status": "failed", "error": error_text(e)}
        out["seconds"] = time.perf_counter() - t0
        log.info("== %s: %s %s in %.1f s", entry.name, step, out["status"], out["seconds"])
    return out


def error_text(e: BaseException) -> str:
    """One line: a UserError's message as it is, anything else with its type."""
    cause = getattr(e, "cause", None) or e  # a RayTaskError carries the task's exception
    text = " ".join(str(cause).split()) or "(no message)"
    return text if isinstance(cause, UserError) else f"{type(cause).__name__}: {text}"


def _limit_threads(n: int) -> None:
    """The job's cores for torch and the renderer's pool (Ray sets OMP_NUM_THREADS alike)."""
    import numba
    import torch

    torch.set_num_threads(n)
    numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))


@contextlib.contextmanager
def _logging_to(path: Path):
    path.parent.mkdir(parents=True, exist_ok=True)
    root = logging.getLogger()
    with open(path, "a") as f, contextlib.redirect_stdout(f), contextlib.redirect_stderr(f):
        handler = logging.StreamHandler(f)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        level = root.level
        root.addHandler(handler)
        root.setLevel(logging.INFO)
        for noisy in ("matplotlib", "PIL", "numba", "warp"):
            logging.getLogger(noisy).setLevel(logging.WARNING)
        try:
            yield
        finally:
            root.removeHandler(handler)
            root.setLevel(level)


# -- the driver ------------------------------------------------------------------------------


@dataclass
class _Live:
    """The driver's view of one entry."""

    entry: Entry
    edir: Path
    todo: list[str]
    status: str = "queued"
    step: str = ""
    stage: str = ""
    started: float | None = None
    seconds: float = 0.0
    ran: list[str] = field(default_factory=list)


def run_batch(entries: list[Entry], out: Path, plans: dict[str, list[str]], *, address: str | None = None,
              cpus: int | None = None, cpus_per_job: int = 1, gpus_per_job: float = 0.0, title: str = "cogs batch"
              ) -> dict[str, dict]:
    """Run every entry's steps in `plans` (name -> steps to do) on Ray; write the records
    and the results table. Returns name -> {"status", "error", "ran": steps run now,
    "skipped": steps done earlier}. Ray starts only where there is work."""
    out = Path(out).resolve()  # the workers' folder, wherever their working directory is
    live = {e.name: _Live(e, out / e.name, list(plans[e.name])) for e in entries}
    for lv in live.values():
        if not lv.todo:
            lv.status = "done earlier"
    work = [lv for lv in live.values() if lv.todo]
    if work:
        _run_on_ray(work, live, out, address, cpus, cpus_per_job, gpus_per_job, title)
    else:
        _write_results(entries, out, title)
    summary = {}
    for name, lv in live.items():
        row = entry_row(lv.entry, lv.edir)
        summary[name] = {"status": row["status"], "error": row["error"], "ran": lv.ran,
                         "skipped": [s for s in STEPS if s not in lv.todo]}
    return summary


def _write_results(entries: list[Entry], out: Path, title: str) -> None:
    write_results([entry_row(e, out / e.name) for e in entries], out, title)


def _run_on_ray(work: list[_Live], live: dict[str, _Live], out: Path, address, cpus, cpus_per_job, gpus_per_job,
                title: str) -> None:
    try:
        import ray
    except ImportError:
        raise UserError("cogs batch runs on Ray, which is not installed: pip install -e '.[batch]' "
                        "(or pip install 'ray>=2.60')") from None
    from rich.live import Live

    from cogs.data.io import write_json
    from cogs.log import console

    started_ray = not ray.is_initialized()
    if started_ray:
        _init_ray(ray, address, cpus)
    try:
        _check_resources(ray, cpus_per_job, gpus_per_job)  # before anything is written
        device = "cuda" if gpus_per_job > 0 else "cpu"
        board = ray.remote(num_cpus=0)(Board).remote()
        task = ray.remote(max_calls=1, max_retries=0)(execute_step)
        refs: dict = {}  # ObjectRef -> (entry name, step)
        for lv in work:
            record = read_record(lv.edir) or {}
            steps = dict(record.get("steps") or {})
            for s in lv.todo:
                steps[s] = {"status": "queued", "spec": lv.entry.step_spec(s)}
            write_json(lv.edir / RECORD, {"spec": lv.entry.spec, "steps": steps})
            upstream = None
            for s in lv.todo:
                gpus = gpus_per_job if s != "prepare" else 0  # preparing runs on the host
                upstream = task.options(num_cpus=cpus_per_job, num_gpus=gpus, name=f"{lv.entry.name}:{s}").remote(
                    s, lv.entry, str(lv.edir), device, cpus_per_job, board, upstream)
                refs[upstream] = (lv.entry.name, s)
        try:
            with Live(_table(live), console=console, refresh_per_second=2, transient=False) as display:
                while refs:
                    ready, _ = ray.wait(list(refs), num_returns=len(refs), timeout=1.0)
                    for ref in ready:
                        name, step = refs.pop(ref)
                        try:
                            res = ray.get(ref)
                        except Exception as e:  # a crashed worker, or a step after one
                            res = {"status": "failed", "error": error_text(e), "seconds": 0.0}
                        _record(live[name], step, res, out, title, live)
                    _poll(board, live, ray)
                    display.update(_table(live))
            if not console.is_terminal:
                console.line()  # the table's last line has no newline of its own there
        finally:
            _write_results([lv.entry for lv in live.values()], out, title)
    finally:
        if started_ray:
            ray.shutdown()


def _poll(board, live: dict[str, _Live], ray) -> None:
    """What the running entries report (the table is a convenience: a slow answer is skipped)."""
    try:
        rows = ray.get(board.snapshot.remote(), timeout=10)
    except Exception:
        return
    now = time.monotonic()
    for name, (step, stage) in rows.items():
        lv = live[name]
        if lv.status in ("queued", "running"):
            lv.status, lv.step, lv.stage = "running", step, stage
            lv.started = lv.started or now


def _record(lv: _Live, step: str, res: dict, out: Path, title: str, live: dict) -> None:
    from cogs.data.io import write_json

    record = read_record(lv.edir) or {"spec": lv.entry.spec, "steps": {}}
    entry = {"status": res["status"], "spec": lv.entry.step_spec(step)}
    if res["status"] == "not run" or lv.status == "failed":
        entry["status"] = "not run"  # an earlier step failed
    else:
        lv.ran.append(step)
        entry["seconds"] = round(float(res.get("seconds", 0.0)), 3)
        lv.seconds += entry["seconds"]
        if res["status"] == "failed":
            entry["error"] = res["error"]
            lv.status, lv.step, lv.stage = "failed", step, res["error"]
            log.error("%s: %s failed: %s", lv.entry.name, step, res["error"])
        else:
            log.info("%s: %s done in %.0f s", lv.entry.name, step, entry["seconds"])
            if step == lv.todo[-1]:
                lv.status, lv.step, lv.stage = "done", step, ""
    record["steps"][step] = entry
    write_json(lv.edir / RECORD, record)
    _write_results([x.entry for x in live.values()], out, title)


def _table(live: dict[str, _Live]):
    from rich.table import Table

    t = Table(title="cogs batch", title_justify="left")
    for c in ("entry", "step", "stage", "elapsed", "status"):
        t.add_column(c, no_wrap=c != "stage")
    now = time.monotonic()
    for lv in live.values():
        if lv.status == "running" and lv.started is not None:
            elapsed = now - lv.started
        else:
            elapsed = lv.seconds
        colour = {"done": "green", "failed": "red", "running": "cyan"}.get(lv.status, "")
        stage = lv.stage if len(lv.stage) <= 80 else lv.stage[:77] + "..."
        t.add_row(lv.entry.name, lv.step or "—", stage or "—", _clock(elapsed) if elapsed else "—",
                  f"[{colour}]{lv.status}[/{colour}]" if colour else lv.status)
    return t


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


def _init_ray(ray, address: str | None, cpus: int | None) -> None:
    env = {"OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
    if address is None:
        # Workers import this very cogs (a checkout, an editable install, a venv's copy).
        import cogs

        here = str(Path(cogs.__file__).resolve().parent.parent)
        env["PYTHONPATH"] = os.pathsep.join([here, *[p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]])
        ray.init(num_cpus=cpus, include_dashboard=False, log_to_driver=False, runtime_env={"env_vars": env})
        return
    try:  # a cluster: cogs must be installed on its nodes, OUT and the sources on a shared filesystem
        ray.init(address=address, log_to_driver=False, runtime_env={"env_vars": env})
    except (ConnectionError, RuntimeError, ValueError) as e:
        raise UserError(f"--address {address}: cannot join the Ray cluster ({' '.join(str(e).split())})") from None


def _check_resources(ray, cpus_per_job: int, gpus_per_job: float) -> None:
    """A job that no node can hold would wait forever: refuse it before any work."""
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    cpu = max((n["Resources"].get("CPU", 0) for n in nodes), default=0)
    gpu = max((n["Resources"].get("GPU", 0) for n in nodes), default=0)
    if cpus_per_job > cpu:
        raise UserError(f"--cpus-per-job {cpus_per_job}: the largest Ray node has {cpu:g} CPU(s)")
    if gpus_per_job > gpu:
        raise UserError(f"--gpus-per-job {gpus_per_job:g}: " + (f"the largest Ray node has {gpu:g} GPU(s)" if gpu else
                        "Ray sees no GPU (without --address it counts this machine's; torch must see CUDA too)"))
