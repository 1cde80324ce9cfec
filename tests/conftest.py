"""Shared test set-up: thread policy before torch loads, and the ../shared/data scenes."""

import os

import kc_splatfacto  # noqa: E402,F401  (sets OMP_WAIT_POLICY before torch loads)

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

PROJECT_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("KC_SHARED_DATA", PROJECT_ROOT.parent / "shared" / "data"))


def shared_scene(name: str) -> Path:
    """Path of a scene under ../shared/data, or skip the test with the reason (a user's clone has no ../shared)."""
    path = SHARED_DATA / name
    if not path.exists():
        pytest.skip(f"shared scene '{name}' not found at {path} (set KC_SHARED_DATA to the shared/data folder)")
    return path


@pytest.fixture
def castle_p30() -> Path:
    return shared_scene("castle-P30")


@pytest.fixture
def fountain_p11() -> Path:
    return shared_scene("fountain-P11")


@pytest.fixture
def garden_npz() -> Path:
    return shared_scene("gsplat-test-garden") / "test_garden.npz"
