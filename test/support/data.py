"""../shared/data for the tests: real sequences and reference vectors that are not shipped.

The folder is ../shared/data next to the repository, or $EKF_VO_SHARED_DATA. Tests that need
one of its sequences skip, saying which, when it is absent (a user's fresh clone)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def shared_data(name: str) -> Path | None:
    """The folder `name` of the shared data, or None when it is absent."""
    root = Path(os.environ.get('EKF_VO_SHARED_DATA', REPO.parent / 'shared' / 'data'))
    return root / name if (root / name).is_dir() else None


def need_shared_data(name: str, what: str = 'test') -> Path:
    """The folder `name` of the shared data; skips the calling test when it is absent."""
    folder = shared_data(name)
    if folder is None:
        pytest.skip(f'../shared/data/{name} is absent (a fresh clone; set '
                    f'EKF_VO_SHARED_DATA to its folder): {what} skipped')
    return folder
