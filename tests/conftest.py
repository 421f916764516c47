"""Shared fixtures. BLAS/OpenMP are pinned to one thread before numpy loads (as the engine
runs), so tests behave the same on a 2-core CI machine as here."""

from __future__ import annotations

from sfmloc.threads import pin_threads_env  # imports no numpy

pin_threads_env()

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
REDKITCHEN = SHARED_DATA / "redkitchen-seq01"


@pytest.fixture(scope="session")
def redkitchen() -> Path:
    """The real 7-Scenes redkitchen frames, read in place (never copied into the repo)."""
    if not (REDKITCHEN / "pgt_sfm_seq01.txt").is_file():
        pytest.skip(
            f"real data not present: {REDKITCHEN} (7-Scenes redkitchen seq-01 is read from "
            "../shared/data)"
        )
    return REDKITCHEN


# The synthetic world with exact ground truth (server_helpers.build_world: rendered once per
# test session, each xdist worker on its own copy) and its map, for the modules that test the
# engine on it.
@pytest.fixture(scope="module")
def world(tmp_path_factory):
    from server_helpers import build_world

    return build_world(tmp_path_factory.getbasetemp())


@pytest.fixture(scope="module")
def bundle(world):
    from sfmloc.map.bundle import MapBundle

    return MapBundle(world.maps_dir / "room")


@pytest.fixture(scope="module")
def cam(world):
    from sfmloc.cameras import Camera

    return Camera.parse(world.camera_spec)
