"""Console output and progress bars (rich), shared by every long-running command."""

from __future__ import annotations

import logging
import time
from contextlib import contextmanager

from rich.console import Console
from rich.logging import RichHandler
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

console = Console(stderr=True)


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(message)s",
        handlers=[RichHandler(console=console, show_path=False, show_time=False)],
        force=True,
    )
    for noisy in ("matplotlib", "PIL", "numba", "warp"):
        logging.getLogger(noisy).setLevel(logging.WARNING)


def progress() -> Progress:
    """A progress display with stage, step/total, rate, elapsed and remaining time.

    Every task must be added with the fields `rate` (see `rate_text`) and `info` (e.g.
    the current loss), both shown beside the bar.
    """
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(bar_width=28),
        MofNCompleteColumn(),
        TextColumn("[cyan]{task.fields[rate]}"),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[info]}"),
        console=console,
        transient=False,
    )


def rate_text(done: int, started: float) -> str:
    elapsed = max(time.perf_counter() - started, 1e-9)
    r = done / elapsed
    return f"{r:6.2f} it/s" if r >= 1 else f"{1 / max(r, 1e-9):6.2f} s/it"


def track(items, label: str, enabled: bool = True):
    """Iterate `items` under a progress bar labelled `label` (rate, elapsed, time left)."""
    items = list(items)
    if not enabled or not items:
        yield from items
        return
    started = time.perf_counter()
    with progress() as p:
        task = p.add_task(label, total=len(items), rate="", info="")
        for i, x in enumerate(items):
            yield x
            p.update(task, advance=1, rate=rate_text(i + 1, started))


@contextmanager
def timed(label: str, into: dict | None = None):
    """Time a block; store seconds in `into[label]` when given."""
    t0 = time.perf_counter()
    yield
    dt = time.perf_counter() - t0
    if into is not None:
        into[label] = dt
    logging.getLogger("cogs").debug("%s: %.2f s", label, dt)
