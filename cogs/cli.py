"""The `cogs` command: one entry point, one sub-command per job.

    cogs demo         the main job: synthesize -> train (quick) -> eval -> report
    cogs synth        write the synthetic benchmark scene
    cogs check        validate a scene folder, listing every problem
    cogs train        six-stage training of the three branches (resumable)
    cogs eval         evaluation protocols -> metrics.json and renders
    cogs ablate       the paper's ablations, one table
    cogs render-init  the initialised branches beside the ground truth, one PNG
    cogs preprocess   raw video -> native scene
    cogs import       NeuMan / HumanNeRF / HOSNeRF layouts -> native scene
    cogs doctor       what this machine offers cogs (backends, body model, LPIPS weights)
    cogs batch        many sequences (a YAML manifest) through prepare -> train -> eval on Ray
    cogs render       a trained run from new cameras, with new body motions and object paths
    cogs export       a trained run as 3DGS PLYs, an animatable glTF (.glb) and arrays (.npz)
    cogs view         a trained run in the browser: a timeline, branch toggles, new motions (viser)

Each sub-command is a dataclass whose fields are its documented options (tyro turns them
into flags); `run()` does the work. Errors the user can cause are `UserError`s: printed
as one message, exit status 2, no traceback.
"""

from __future__ import annotations

import signal
import sys
from dataclasses import dataclass
from pathlib import Path

import tyro

from cogs.errors import UserError


@dataclass
class Check:
    """Validate a scene folder and report every problem at once."""

    scene: Path
    """Scene folder (the one holding scene.json)."""

    def run(self) -> int:
        from rich.markup import escape

        from cogs.data.validate import check_scene
        from cogs.log import console

        problems = check_scene(self.scene)
        if problems:
            console.print(f"[red]{escape(str(self.scene))}: {len(problems)} problem(s)[/red]", soft_wrap=True)
            for p in problems:
                console.print(f"  - {p}", markup=False, highlight=False, soft_wrap=True)
            return 1
        from cogs.data.scene import load_scene

        s = load_scene(self.scene, validate=False)
        console.print(
            f"[green]ok[/green] {escape(str(self.scene))}: {s.n_frames} frames {s.width}x{s.height}, "
            f"body model {s.body.model}, object {'yes' if s.has_object else 'no'}, "
            f"{len(s.points_xyz)} points, train/test {len(s.split['train'])}/{len(s.split['test'])}"
            + (", ground truth" if s.gt is not None else "")
        )
        return 0


@dataclass
class Doctor:
    """Report what this machine offers cogs; `--warm` also builds one-time caches."""

    warm: bool = False
    """Build the body model's asset cache and compile the CPU kernels now."""

    def run(self) -> int:
        from cogs.doctor import report

        return report(warm=self.warm)


def _commands() -> dict[str, type]:
    from cogs.batch.command import Batch
    from cogs.commands import Ablate, Demo, Eval, RenderInit, Train
    from cogs.data.synth.command import Synth
    from cogs.preprocess.command import Preprocess
    from cogs.preprocess.importers import Import
    from cogs.use.export import Export
    from cogs.use.render import Render
    from cogs.use.view import View

    return {
        "demo": Demo,
        "synth": Synth,
        "check": Check,
        "train": Train,
        "eval": Eval,
        "ablate": Ablate,
        "render-init": RenderInit,
        "preprocess": Preprocess,
        "import": Import,
        "doctor": Doctor,
        "batch": Batch,
        "render": Render,
        "export": Export,
        "view": View,
    }


class Terminated(KeyboardInterrupt):
    """SIGTERM (a `kill`, a batch scheduler cancelling): raised in the main thread like
    Ctrl-C's KeyboardInterrupt, so that the same cleanup runs (a preprocess keeps only its
    cache, an output folder's claim and temporary folder go, a viewer closes)."""


def _terminate(signum, frame) -> None:
    raise Terminated()


def main(argv: list[str] | None = None) -> int:
    from rich.markup import escape

    from cogs.log import console, setup_logging

    setup_logging()
    if argv is None:  # the command line, not a caller's process
        if hasattr(signal, "SIGPIPE"):
            signal.signal(signal.SIGPIPE, signal.SIG_DFL)  # `cogs ... --help | head` ends quietly, as Unix tools do
        signal.signal(signal.SIGTERM, _terminate)
    cmd = tyro.extras.subcommand_cli_from_dict(_commands(), args=argv, prog="cogs")
    try:
        code = cmd.run()
    except UserError as e:
        console.print(f"[red]error:[/red] {escape(str(e))}", highlight=False, soft_wrap=True)  # paths stay whole
        return 2
    except Terminated:
        console.print("[yellow]terminated[/yellow]")
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        console.print("[yellow]interrupted[/yellow]")
        return 130
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
