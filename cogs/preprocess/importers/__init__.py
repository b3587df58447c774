"""Importers: public benchmarks' layouts -> the native scene format.

    cogs import neuman DIR --out SCENE       NeuMan sequence (COLMAP + SMPL fits)
    cogs import humannerf DIR --out SCENE    HumanNeRF / HOSNeRF subject

Each importer reads only what its layout documents (see docs/datasets.md), loads pickles
through the restricted unpickler (`cogs.data.safe_pickle`), and writes a scene that
passes `cogs check`. Bodies are retargeted onto the free Anny model from the SMPL joints by
default; `--body-model smpl` keeps SMPL parameters (needs the licensed model file).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from cogs.preprocess.importers.humannerf import import_humannerf
from cogs.preprocess.importers.neuman import import_neuman

IMPORTERS = {"neuman": import_neuman, "humannerf": import_humannerf}


@dataclass
class Import:
    """Import a public benchmark sequence (NeuMan, HumanNeRF/HOSNeRF) as a native scene."""

    kind: tyro.conf.Positional[Literal["neuman", "humannerf"]]
    """Layout of DIR: neuman, or humannerf (also HOSNeRF)."""
    dir: tyro.conf.Positional[Annotated[Path, tyro.conf.arg(metavar="DIR")]]
    """The dataset's sequence folder."""
    out: Path
    """Scene folder to write."""
    body_model: Literal["anny", "smpl"] = "anny"
    """anny: retarget the SMPL joints onto the free Anny model (no licence needed);
    smpl: keep the SMPL parameters (needs the licensed SMPL model file)."""
    smpl_model: Path | None = None
    """Licensed SMPL model file (SMPL_NEUTRAL.pkl/.npz) or its folder; default: $COGS_SMPL_MODEL."""
    smpl_source: Literal["auto", "optimized", "4d_humans"] = "auto"
    """NeuMan only: smpl_output_optimized.pkl + alignments.npy (optimized), HUGS'
    4d_humans/smpl_optimized_aligned_scale.npz (4d_humans), or auto."""
    overwrite: bool = False
    """Replace what OUT already holds, once the new scene is complete (without it an
    existing OUT is refused)."""
    start: int = 0
    """Keep frames from this index of the sequence (video order)."""
    stride: int = 1
    """Keep every this-many-th frame (2 halves a 570-frame sequence)."""
    limit: int | None = None
    """Keep at most this many frames."""
    max_side: int | None = None
    """Resize frames and masks so the longer side is at most this many pixels (intrinsics
    scaled). The dataset's split rule is applied to the frames kept."""

    def run(self) -> int:
        from cogs.data.outdir import check_out_folder
        from cogs.errors import UserError
        from cogs.log import console

        # Before any work: the options, the output folder and the SMPL model file.
        from cogs.preprocess.importers.common import FrameSelection

        select = FrameSelection(self.start, self.stride, self.limit, self.max_side).check()
        if not Path(self.dir).is_dir():
            raise UserError(f"{self.dir}: not a folder (expected a {self.kind} dataset folder)")
        out, src = Path(self.out).resolve(), Path(self.dir).resolve()
        if out == src or out.is_relative_to(src) or src.is_relative_to(out):
            raise UserError(f"--out {self.out} and the dataset folder {self.dir} overlap; write the scene somewhere else")
        check_out_folder(Path(self.out), overwrite=self.overwrite)
        if self.smpl_model is not None or self.body_model == "smpl":
            from cogs.body.smpl_body import resolve_smpl_model_file, set_smpl_model_path

            resolve_smpl_model_file(self.smpl_model)  # says what to set when there is none
            if self.smpl_model is not None:
                set_smpl_model_path(self.smpl_model)
        if self.kind == "neuman":
            out = import_neuman(self.dir, self.out, self.body_model, self.smpl_model, self.smpl_source,
                                overwrite=self.overwrite, select=select)
        else:
            out = import_humannerf(self.dir, self.out, self.body_model, self.smpl_model, overwrite=self.overwrite,
                                   select=select)
        console.print(f"[green]imported[/green] {self.dir} -> {out}  (check it with: cogs check {out})")
        return 0


__all__ = ["IMPORTERS", "Import", "import_humannerf", "import_neuman"]
