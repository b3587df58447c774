"""`cogs batch`: its options and entry point."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from cogs.errors import UserError


@dataclass
class Batch:
    """Run many sequences, listed in a YAML manifest, through prepare -> train -> eval on Ray.

    Each entry writes OUT/NAME/ (scene/, run/, log.txt, batch.json); OUT/results.csv and
    OUT/results.md hold one row per entry and their mean. Ray starts locally, sized to
    this machine, unless --address joins a cluster. A failing entry is recorded and the
    others go on. Re-running the same command skips finished steps and resumes killed
    training from its last checkpoint. Manifest format: docs/batch.md.
    """

    manifest: tyro.conf.Positional[Annotated[Path, tyro.conf.arg(metavar="MANIFEST")]]
    """The manifest (YAML): `sequences:` (each one source: synth, video, scene, neuman or
    humannerf; optional train: and eval:) and an optional `defaults:` block."""
    out: Path
    """Output folder: one subfolder per entry, results.csv, results.md."""
    address: str | None = None
    """Join this Ray cluster (`auto` on a node of a running cluster, or HOST:PORT) instead
    of starting Ray locally. Every node needs cogs installed and OUT and the sources on a
    shared filesystem (docs/batch.md, Slurm included)."""
    cpus_per_job: int = 1
    """CPU cores each step gets (and its torch and renderer threads). Training on a CPU is
    mostly serial, so one core per job runs as many entries at once as there are cores."""
    gpus_per_job: float = 0.0
    """GPUs each training and evaluation step gets; above 0 they run on CUDA (fractions
    share a GPU, e.g. 0.5). Preparing a scene uses none."""
    cpus: int | None = None
    """Local Ray only: how many of this machine's cores the batch may use (None: all)."""

    def run(self) -> int:
        from cogs.batch.manifest import read_manifest
        from cogs.batch.runner import run_batch
        from cogs.batch.steps import STEPS, conflict, done_steps, read_record
        from cogs.log import console

        if self.cpus_per_job < 1:
            raise UserError(f"--cpus-per-job must be at least 1, got {self.cpus_per_job}")
        if self.gpus_per_job < 0:
            raise UserError(f"--gpus-per-job must be >= 0, got {self.gpus_per_job:g}")
        if self.cpus is not None and (self.address is not None or self.cpus < 1):
            raise UserError("--cpus sizes a local Ray instance (>= 1 core); with --address the cluster decides"
                            if self.address is not None else f"--cpus must be at least 1, got {self.cpus}")
        if self.out.exists() and not self.out.is_dir():
            raise UserError(f"--out {self.out}: is a file, not a folder")
        entries = read_manifest(self.manifest)
        plans, problems = {}, []
        for e in entries:
            edir = self.out / e.name
            record = read_record(edir) if (edir / "batch.json").is_file() else None
            why = conflict(e, edir, record)
            if why:
                problems.append(why)
                continue
            done = done_steps(e, edir, record)
            plans[e.name] = list(STEPS[len(done):])
        if problems:
            raise UserError(f"--out {self.out}: {'; '.join(problems)}. Choose another --out, or remove those "
                            "folders to redo their entries")
        n_todo = sum(bool(p) for p in plans.values())
        console.print(f"{len(entries)} entries, {len(entries) - n_todo} finished earlier; {n_todo} to run", highlight=False)
        summary = run_batch(entries, self.out, plans, address=self.address, cpus=self.cpus,
                            cpus_per_job=self.cpus_per_job, gpus_per_job=self.gpus_per_job,
                            title=f"cogs batch: {self.manifest.name}")
        done = sum(s["status"] == "done" for s in summary.values())
        colour = "green" if done == len(summary) else "yellow"
        console.print(f"[{colour}]{done}/{len(summary)} entries done[/{colour}]: {self.out / 'results.md'}, "
                      f"{self.out / 'results.csv'}", highlight=False)
        return 0 if done == len(summary) else 1
