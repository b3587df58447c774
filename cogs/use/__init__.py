"""Using a trained reconstruction: render it anew (`cogs render`), export it (`cogs export`),
look at it in the browser (`cogs view`).

* `render.py` — the `render` command: new cameras (`cameras.py`), body motions
  (`motion.py`, the Anny walk cycle in `walk.py`), object trajectories (`objects.py`), any
  subset of branches.
* `export.py` — the `export` command: standard 3DGS PLYs, an animatable glTF binary
  (`gltf.py`) and the same as plain arrays; the layout is `docs/export.md`.
* `view.py` — the `view` command: the run in a browser (viser) on a timeline, branch
  toggles, overlays, and cogs' own rasterizer on demand.
* `playback.py` — what render and view share: their options, the motion and object
  source resolved into one timeline, the poses at a step.
* `posing.py` — what render and export share: the world's up direction, a run's poses at
  any frame, skinning transforms projected onto rotations.

This package sits with `cogs.eval`: it imports the model, branches, body models, data and
geometry, and only the CLI imports it.
"""
