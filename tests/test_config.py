"""Training settings are checked before anything is written: `check_config`, `--set`
(`apply_overrides`) and a run's config.yaml (`load_config`) list every problem at once."""

from __future__ import annotations

import pytest
import yaml

from cogs.config import (
    apply_overrides,
    check_config,
    load_config,
    paper_config,
    quick_config,
    save_config,
    to_dict,
)
from cogs.errors import UserError


def _problems(overrides: list[str]) -> list[str]:
    with pytest.raises(UserError) as e:
        apply_overrides(quick_config(), overrides)
    return [line[4:] for line in str(e.value).splitlines()[1:]]


def test_the_presets_are_valid():
    assert check_config(quick_config()) == [] and check_config(paper_config()) == []


@pytest.mark.parametrize("setting", ["checkpoint_every", "visibility_every", "log_every", "plane_assign_every",
                                     "human_density.refine_every", "object_density.refine_every",
                                     "scene_density.refine_every"])
@pytest.mark.parametrize("value", [0, -3])
def test_cadences_must_be_at_least_one(setting, value):
    assert _problems([f"{setting}={value}"]) == [f"{setting}: must be at least 1 (a period in steps), got {value}"]


def test_every_problem_is_listed_in_one_message():
    problems = _problems(["schedule=5", "branches.human.n_gaussians=0", "backend=nonsense", "schedule.III=-10",
                          "schedul.I=3", "weights.l1=abc", "human_density.stop_fraction=1.5", "refit.lr=.nan"])
    assert problems == [
        "schedule=5: `schedule` is a section, not a value; set one of its fields (I, II, III, IV, V, VI, "
        "single_stage), e.g. --set schedule.I=...",
        "schedul.I=3: `schedul` is not a setting (no field 'schedul' in TrainConfig); did you mean `schedule`?",
        "weights.l1=abc: `weights.l1` must be a number, got 'abc'",
        "schedule.III: must not be negative, got -10",
        "branches.human.n_gaussians: must be positive, got 0",
        "human_density.stop_fraction: is a fraction, must be in [0, 1], got 1.5",
        "refit.lr: must be a finite number, got nan",
        "backend: unknown 'nonsense'; known: auto, torch, cpu, gsplat",
    ]


def test_a_stage_of_zero_iterations_stays_legal():
    cfg = apply_overrides(quick_config(), ["schedule.II=0", "schedule.IV=0", "refit.steps=0"])
    assert (cfg.schedule.II, cfg.schedule.IV, cfg.refit.steps) == (0, 0, 0)


def test_values_take_their_settings_type():
    cfg = apply_overrides(quick_config(), ["weights.l1=2e-3", "schedule.I=1e3", "lr.shading=1"])
    assert cfg.weights.l1 == 0.002 and cfg.schedule.I == 1000 and isinstance(cfg.schedule.I, int)
    assert isinstance(cfg.lr.shading, float)
    assert _problems(["schedule.I=2.5"]) == ["schedule.I=2.5: `schedule.I` must be an integer, got 2.5"]
    assert _problems(["use_planes=1"]) == ["use_planes=1: `use_planes` must be true or false, got 1"]


def test_check_config_catches_what_code_sets_directly():
    cfg = quick_config()
    cfg.schedule = 5
    cfg.log_every = "often"
    assert check_config(cfg) == ["schedule: is a section of settings, got 5", "log_every: must be an integer, got 'often'"]


def test_a_saved_config_loads_back_equal(tmp_path):
    cfg = apply_overrides(paper_config(), ["schedule.VI=7", "weights.anchor=0.25"])
    save_config(cfg, tmp_path / "config.yaml")
    assert load_config(tmp_path / "config.yaml") == cfg


@pytest.mark.parametrize("text,message", [
    ("hello", "holds 'hello', not a mapping of settings"),
    ("preset: quick", "missing settings: schedule, weights, branches, lr"),
    ("", "holds None, not a mapping of settings"),
    ("{{{", "not valid YAML"),
])
def test_a_damaged_config_yaml_is_an_error_naming_the_file_never_the_paper_defaults(tmp_path, text, message):
    path = tmp_path / "run" / "config.yaml"
    path.parent.mkdir()
    path.write_text(text)
    with pytest.raises(UserError) as e:
        load_config(path)
    assert str(e.value).startswith(str(path)) and message in str(e.value)


def test_config_yaml_with_an_unknown_key_a_wrong_type_or_a_section_set_to_a_value(tmp_path):
    data = to_dict(quick_config())
    data["schedule"]["VII"] = 10
    data["checkpoint_every"] = "often"
    data["weights"] = 1.0
    data["backend"] = "vulkan"
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(UserError) as e:
        load_config(tmp_path / "config.yaml")
    lines = str(e.value).splitlines()
    assert lines[0] == f"{tmp_path / 'config.yaml'}: 4 problem(s):"
    assert sorted(lines[1:]) == [
        "  - backend: unknown 'vulkan'; known: auto, torch, cpu, gsplat",
        "  - checkpoint_every: must be an integer, got 'often'",
        "  - schedule.VII: unknown setting; did you mean `VI`?",
        "  - weights: is a section, expected a mapping of its settings, got 1.0",
    ]


def test_config_yaml_that_is_a_folder_or_missing_is_named(tmp_path):
    (tmp_path / "config.yaml").mkdir()
    with pytest.raises(UserError, match="config.yaml: is a folder"):
        load_config(tmp_path / "config.yaml")
    with pytest.raises(UserError, match="nope.yaml: missing"):
        load_config(tmp_path / "nope.yaml")


def test_older_runs_settings_that_were_retired_are_ignored(tmp_path):
    data = to_dict(quick_config())
    data["human_density"]["reset_opacity_every"] = 0  # removed from Density; harmless while it still exists
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data))
    assert load_config(tmp_path / "config.yaml") == quick_config()


def test_a_config_yaml_written_by_an_earlier_cogs_still_loads():
    """`tests/data/config_written_before_2026-11-28.yaml` is a quick-preset run's config.yaml
    as cogs wrote it before `smooth_about_initial` and `fused_adam` existed. A setting added
    since must be in ADDED (taking the default that reproduces the old run), or every run
    trained before it stops loading for eval, render, export and view."""
    from pathlib import Path

    cfg = load_config(Path(__file__).parent / "data" / "config_written_before_2026-11-28.yaml")
    assert cfg.preset == "quick" and cfg.branches.object.smooth_about_initial and cfg.fused_adam
    assert cfg == quick_config()  # that run used the preset as it was, and nothing it had has changed since
