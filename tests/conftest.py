"""Shared test set-up: thread policy before torch loads, and the ../shared/data scenes."""

import os
from pathlib import Path

import pytest

import kc_splatfacto  # noqa: F401  (sets OMP_WAIT_POLICY before torch loads: the first import of torch is through it)
from kc_splatfacto.data.base import READ_ONLY_DATA_ENV

PROJECT_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("KC_SHARED_DATA", PROJECT_ROOT.parent / "shared" / "data"))
# the shared scenes are read-only in intent, whatever their mode (a contributor's clone has them writable): derived
# images go to the cache, in this process and in every command the suite starts (ns-train, the GPU campaign's dry
# run), which inherit the environment; set at import, before test modules copy os.environ for their subprocesses
os.environ[READ_ONLY_DATA_ENV] = os.pathsep.join(
    filter(None, [os.environ.get(READ_ONLY_DATA_ENV, ""), str(SHARED_DATA.resolve())]))


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


def _shared_listing() -> dict[str, tuple[int, int]]:
    """Every path under ../shared/data with its size and mtime (empty when there is no shared folder)."""
    if not SHARED_DATA.is_dir():
        return {}
    return {str(p): (p.lstat().st_size, p.lstat().st_mtime_ns) for p in SHARED_DATA.rglob("*")}


@pytest.fixture(autouse=True, scope="session")
def shared_data_is_never_written():
    """Nothing in the suite may write into ../shared: the shared scenes are treated as read-only whatever their
    mount or mode bits say (``$KC_SPLATFACTO_READ_ONLY_DATA``, set above: derived images go to the user cache), and
    the folder is compared before and after."""
    before = _shared_listing()
    yield
    after = _shared_listing()
    changed = sorted(set(before.items()) ^ set(after.items()))
    assert not changed, f"the test suite wrote into {SHARED_DATA}: {changed[:10]}"


#: the files that take longest (minutes: each trains studies in subprocesses), started first so that under
#: pytest-xdist (`make test`, --dist loadfile) the other process works through the short files meanwhile instead of
#: waiting at the end for the last long one; pytest --durations in every CI log says which they are
HEAVIEST_FIRST = ("tests/test_gpu_campaign.py", "tests/cli/test_bench_ray.py", "tests/cli/test_bench_resume.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(HEAVIEST_FIRST)}
    root = Path(config.rootpath)

    def heaviness(item) -> int:
        try:
            name = Path(item.fspath).resolve().relative_to(root).as_posix()
        except ValueError:
            return len(rank)
        return rank.get(name, len(rank))

    items.sort(key=heaviness)  # stable: the rest keep their order
