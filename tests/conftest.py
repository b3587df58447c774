"""Shared fixtures. The body model is built once per test session (and its asset cache
once per machine, by `cogs doctor --warm` before the suite)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.fixtures import make_tiny_scene


@pytest.fixture(scope="session")
def body_model():
    from cogs.body import load_body_model

    return load_body_model("anny")


@pytest.fixture
def tiny_scene(tmp_path):
    """A small, valid scene folder written through the format's own writer."""
    return make_tiny_scene(tmp_path / "scene")


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    np.random.seed(0)
