"""Shared fixtures. The body model is built once per test session (and its asset cache
once per machine, by `cogs doctor --warm` before the suite)."""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

import numpy as np
import pytest

import cogs  # noqa: F401  (before torch: sets torch's OpenMP wait policy, see cogs/__init__.py)
import torch

from tests.fixtures import make_tiny_scene


@pytest.fixture(scope="module")
def small_synthetic(tmp_path_factory) -> Path:
    """A 16-frame synthetic scene at 96x72 (ground truth included), written by cogs synth."""
    from cogs.data.scene import save_scene
    from cogs.data.synth import SynthConfig, generate_scene

    root = tmp_path_factory.mktemp("small") / "scene"
    save_scene(generate_scene(SynthConfig(frames=16, width=96, height=72, points=1500), show_progress=False), root)
    return root


@pytest.fixture(scope="session")
def body_model():
    from cogs.body import load_body_model

    return load_body_model("anny")


@pytest.fixture(scope="session")
def default_scene_dir(tmp_path_factory) -> Path:
    """The default synthetic benchmark scene (100 frames, 256x192), generated once per
    test run and shared between xdist workers through a locked folder (~30 s)."""
    from cogs.data.scene import save_scene
    from cogs.data.synth import SynthConfig, generate_scene

    # Under xdist each worker's basetemp sits in one folder per run: share that; a plain
    # run uses its own basetemp (never a folder an older run could have left behind).
    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    root = shared / "synth_default"
    with open(shared / "synth_default.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / "scene.json").exists():
            save_scene(generate_scene(SynthConfig(), show_progress=False), root)
    return root


@pytest.fixture
def tiny_scene(tmp_path):
    """A small, valid scene folder written through the format's own writer."""
    return make_tiny_scene(tmp_path / "scene")


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    np.random.seed(0)
