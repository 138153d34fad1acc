"""Shared fixtures."""

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture
def shared_data():
    """``../shared/data`` beside the checkout, or skip the test saying it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"optional real data set not present at {SHARED_DATA}")
    return SHARED_DATA

