"""The batch manifest: a YAML list of sequences, read and checked whole before any work.

    defaults:                      # optional: merged into every entry (see `merge`)
      train: {preset: quick, set: ["schedule.VI=2000"]}
      eval: {pose_fit_steps: 0}
    sequences:
      - synth: {seed: 0, frames: 100}          # name defaults to synth_seed0 (synth_seed0_variantN with a variant)
      - name: kitchen
        video: clips/kitchen.mp4
        preprocess: {object_box: [410, 300, 520, 420], stride: 2}
      - scene: scenes/lab                      # a native scene folder
        train: {preset: paper}
      - neuman: data/neuman/bike               # also humannerf: DIR
        import: {smpl_source: optimized}

Every problem found (unknown keys, wrong types, sources that do not exist, duplicate
names, overrides the config rejects) is collected and raised as one `UserError` naming
the manifest and each entry, so a long batch never dies on a typo in its last entry.
Relative paths are relative to the manifest's folder. The full format: docs/batch.md.
"""

from __future__ import annotations

import dataclasses
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from cogs.errors import UserError

SOURCES = ("synth", "video", "scene", "neuman", "humannerf")
"""An entry's source: exactly one of these keys."""

OPTION_BLOCKS = {"preprocess": ("video",), "import": ("neuman", "humannerf")}
"""Source-specific option blocks and the sources they belong to."""

BLOCKS = ("synth", *OPTION_BLOCKS, "train", "eval")
"""The mappings an entry (besides `synth:`, its source) and `defaults:` may hold."""

EVAL_TYPES = {"pose_fit_steps": int, "renders": bool}
EVAL_DEFAULTS = {"pose_fit_steps": 40, "renders": True}
"""`eval:` options: those of `cogs eval`, with its defaults."""

NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")
RESERVED = ("results.csv", "results.md")
"""Names the batch's own files take in OUT."""


@dataclass(frozen=True)
class Entry:
    """One sequence of the batch, defaults merged, paths resolved.

    `spec` is the entry as the manifest states it (defaults merged, paths as written): it
    is recorded in OUT/NAME/batch.json and compared on a re-run, so finished work is never
    silently reused for a changed entry."""

    name: str
    kind: str
    """One of SOURCES."""
    source: Path | None
    """The source path (absolute); None for synth."""
    options: dict
    """synth: SynthConfig fields (noise as a dict); video: `cogs preprocess` options;
    neuman / humannerf: importer options; scene: empty."""
    preset: str
    overrides: tuple[str, ...]
    eval: dict
    spec: dict = field(compare=False)

    def step_spec(self, step: str) -> dict:
        """What a step's result depends on: prepare the source, train also the training
        options, eval also the evaluation options."""
        keys = {"prepare": ("source", "options"), "train": ("source", "options", "train"),
                "eval": ("source", "options", "train", "eval")}[step]
        return {k: self.spec[k] for k in keys}


def read_manifest(path: Path) -> list[Entry]:
    """Parse and check the manifest at `path`; raises one UserError listing every problem."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise UserError(f"manifest {path}: {'not a file' if path.exists() else 'does not exist'}")
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise UserError(f"manifest {path}: not valid YAML ({' '.join(str(e).split())})") from None
    problems: list[str] = []
    entries = parse_manifest(doc, path.parent.resolve(), problems)
    if problems:
        shown = "; ".join(problems[:12]) + (f"; and {len(problems) - 12} more" if len(problems) > 12 else "")
        raise UserError(f"manifest {path}: {len(problems)} problem(s): {shown}")
    return entries


def parse_manifest(doc: Any, base: Path, problems: list[str]) -> list[Entry]:
    """The entries of a parsed manifest `doc`; problems are appended to `problems`."""
    if not isinstance(doc, dict):
        problems.append("expected a mapping with `sequences:` (and optionally `defaults:`)")
        return []
    _unknown(doc, ("defaults", "sequences"), "the top level", problems)
    defaults = doc.get("defaults") or {}
    if not isinstance(defaults, dict):
        problems.append("defaults: expected a mapping")
        defaults = {}
    _unknown(defaults, BLOCKS, "defaults", problems)
    for block in BLOCKS:
        if defaults.get(block) is not None and not isinstance(defaults[block], dict):
            problems.append(f"defaults: `{block}:` expected a mapping")
            defaults = {**defaults, block: None}
    seqs = doc.get("sequences")
    if not isinstance(seqs, list) or not seqs:
        problems.append("sequences: expected a non-empty list of entries")
        return []
    entries, names = [], {}
    for i, raw in enumerate(seqs):
        where = f"sequences[{i}]"
        if isinstance(raw, dict) and isinstance(raw.get("name"), str):
            where += f" ({raw['name']})"
        n_before = len(problems)
        entry = _entry(raw, defaults, base, where, problems)
        if entry is None:
            continue
        if entry.name in names:
            problems.append(f"{where}: name {entry.name!r} is also sequences[{names[entry.name]}]'s; "
                            "give each entry its own `name:`")
            continue
        names[entry.name] = i
        if len(problems) == n_before:
            entries.append(entry)
    return entries


def merge(defaults: dict, raw: dict, block: str) -> dict:
    """An entry's `block` over the defaults' one, key by key; `train.set` lists concatenate
    (the defaults' first, so the entry's own overrides win)."""
    base, own = defaults.get(block) or {}, raw.get(block) or {}
    out = {**base, **own}
    if block == "train" and ("set" in base or "set" in own):
        a, b = base.get("set") or [], own.get("set") or []
        out["set"] = [*a, *b] if isinstance(a, list) and isinstance(b, list) else own.get("set", base.get("set"))
    return out


def _entry(raw: Any, defaults: dict, base: Path, where: str, problems: list[str]) -> Entry | None:
    if not isinstance(raw, dict):
        problems.append(f"{where}: expected a mapping with one source ({', '.join(SOURCES)})")
        return None
    _unknown(raw, ("name", *SOURCES, *BLOCKS[1:]), where, problems)
    kinds = [k for k in SOURCES if k in raw]
    if len(kinds) != 1:
        problems.append(f"{where}: needs exactly one source of {', '.join(SOURCES)}"
                        + (f", has {', '.join(kinds)}" if kinds else ""))
        return None
    kind = kinds[0]
    for block, owners in OPTION_BLOCKS.items():
        if block in raw and kind not in owners:
            problems.append(f"{where}: `{block}:` options belong to {' / '.join(owners)} entries, not {kind}")
    bad = [b for b in BLOCKS if raw.get(b) is not None and not isinstance(raw[b], dict)]
    if bad:
        problems.extend(f"{where}: `{b}:` expected a mapping" for b in bad)
        return None

    source, options, written = None, {}, {}
    if kind == "synth":
        written = merge(defaults, raw, "synth")  # `synth:` alone (null) takes every default
        options = _check_options(written, _synth_config(), f"{where}: synth", base, problems)
        small = [k for k, least in (("frames", 2), ("width", 16), ("height", 16)) if options.get(k, least) < least]
        if small:
            problems.append(f"{where}: synth needs at least 2 frames of 16x16 pixels ({', '.join(small)})")
    else:
        value = raw[kind]
        if not isinstance(value, str) or not value:
            problems.append(f"{where}: `{kind}:` expected a path")
            return None
        written = value
        source = (base / value).resolve()
        if not source.exists():
            problems.append(f"{where}: {kind} {source} does not exist")
        elif kind != "video" and not source.is_dir():
            problems.append(f"{where}: {kind} {source} is not a folder")
        for block, owners in OPTION_BLOCKS.items():
            if kind in owners:
                types_ = _preprocess_options() if block == "preprocess" else _import_options(kind)
                options = _check_options(merge(defaults, raw, block), types_, f"{where}: {block}", base, problems)

    train = merge(defaults, raw, "train")
    _unknown(train, ("preset", "set"), f"{where}: train", problems)
    preset = train.get("preset", "quick")
    overrides = train.get("set") or []
    if not isinstance(overrides, list) or not all(isinstance(s, str) for s in overrides):
        problems.append(f"{where}: train.set: expected a list of `path.to.field=value` strings")
        overrides = []
    else:
        from cogs.config import apply_overrides, preset as get_preset

        try:
            apply_overrides(get_preset(str(preset)), overrides)
        except UserError as e:
            problems.append(f"{where}: train: {str(e).replace('--set ', 'set ')}")
    evals = {**EVAL_DEFAULTS, **_check_options(merge(defaults, raw, "eval"), EVAL_TYPES, f"{where}: eval", base,
                                                problems)}
    if evals["pose_fit_steps"] < 0:
        problems.append(f"{where}: eval.pose_fit_steps must be >= 0")

    name = raw.get("name")
    if name is None:
        name = (f"synth_seed{options.get('seed', 0)}" + (f"_variant{options['variant']}" if options.get("variant") else "")
                if kind == "synth" else source.stem)
    if not isinstance(name, str) or not NAME_RE.fullmatch(name) or name in RESERVED:
        problems.append(f"{where}: name {name!r} must be a folder name of letters, digits, '.', '_' or '-' "
                        "(set `name:`)")
        return None
    written_options = {}
    for block, owners in OPTION_BLOCKS.items():
        if kind in owners:
            written_options = merge(defaults, raw, block)
    spec = {"source": {kind: written}, "options": written_options,
            "train": {"preset": preset, "set": list(overrides)}, "eval": evals}
    return Entry(name=name, kind=kind, source=source, options=options, preset=str(preset), overrides=tuple(overrides),
                 eval=evals, spec=spec)


def _unknown(d: dict, known: tuple[str, ...], where: str, problems: list[str]) -> None:
    if not isinstance(d, dict):
        return
    for k in d:
        if k not in known:
            problems.append(f"{where}: unknown key {k!r} (known: {', '.join(known)})")


# -- typed option blocks ----------------------------------------------------------------------


def _synth_config() -> dict:
    from cogs.data.synth.config import SynthConfig

    return _field_types(SynthConfig)


def _preprocess_options() -> dict:
    from cogs.preprocess.command import Preprocess

    return {k: v for k, v in _field_types(Preprocess).items() if k not in ("input", "out", "progress")}


def _import_options(kind: str) -> dict:
    from cogs.preprocess.importers import Import

    t = {k: v for k, v in _field_types(Import).items() if k not in ("kind", "dir", "out")}
    if kind != "neuman":
        t.pop("smpl_source")
    return t


def _field_types(cls) -> dict:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _check_options(values: dict, types_: dict, where: str, base: Path, problems: list[str]) -> dict:
    """`values` checked against `types_` (field name -> type hint): unknown keys, wrong
    types and paths that do not exist are reported; paths are resolved against `base`,
    lists become tuples, a nested dataclass's mapping is checked field by field."""
    out = {}
    for k, v in values.items():
        if k not in types_:
            problems.append(f"{where}: unknown option {k!r} (known: {', '.join(types_)})")
            continue
        hint = types_[k]
        ok, value = _coerce(v, hint, base)
        if not ok:
            problems.append(f"{where}.{k}: {v!r} is not {_type_text(hint)}")
            continue
        if dataclasses.is_dataclass(hint):
            value = _check_options(v, _field_types(hint), f"{where}.{k}", base, problems)
        elif isinstance(value, Path) and not value.exists():
            problems.append(f"{where}.{k}: {value} does not exist")
        out[k] = value
    return out


def _coerce(v: Any, hint: Any, base: Path) -> tuple[bool, Any]:
    """(whether `v` fits `hint`, the value converted: paths resolved, lists to tuples)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if v is None and type(None) in args:
            return True, None
        for a in args:
            if a is not type(None):
                ok, out = _coerce(v, a, base)
                if ok:
                    return True, out
        return False, v
    if origin is Literal:
        return v in args, v
    if origin is tuple:
        if not isinstance(v, (list, tuple)):
            return False, v
        items = args[:1] * len(v) if len(args) == 2 and args[1] is Ellipsis else args
        if len(items) != len(v):
            return False, v
        conv = [_coerce(x, a, base) for x, a in zip(v, items)]
        return all(ok for ok, _ in conv), tuple(x for _, x in conv)
    if dataclasses.is_dataclass(hint):
        return isinstance(v, dict), v
    if hint is bool:
        return isinstance(v, bool), v
    if hint is int:
        return isinstance(v, int) and not isinstance(v, bool), v
    if hint is float:
        return isinstance(v, (int, float)) and not isinstance(v, bool), float(v) if isinstance(v, (int, float)) else v
    if hint is str:
        return isinstance(v, str), v
    if hint is Path:
        return (True, (base / v).resolve()) if isinstance(v, str) and v else (False, v)
    return False, v


def _type_text(hint: Any) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_text(a) for a in args)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin is tuple:
        if Ellipsis in args and typing.get_origin(args[0]) is tuple:
            return "a list of lists of numbers"
        return f"a list of {len(args)} numbers" if Ellipsis not in args else "a list of numbers"
    if hint is type(None):
        return "null"
    if hint is Path:
        return "a path"
    if dataclasses.is_dataclass(hint):
        return "a mapping"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(hint, str(hint))
