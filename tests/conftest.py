"""Shared test guards."""
from pathlib import Path

import pytest

RECORDS = Path(__file__).resolve().parents[1] / "records"


def _tree(folder: Path) -> list:
    return sorted((str(p.relative_to(folder)), p.stat().st_mtime_ns) for p in folder.rglob("*")) if folder.exists() else []


@pytest.fixture(scope="session", autouse=True)
def repository_records_untouched():
    """Tests keep their run records in tmp folders: a test that wrote the repository's records/
    (the sweep command's default) would hand cached runs to every test after it."""
    before = _tree(RECORDS)
    yield
    after = _tree(RECORDS)
    assert after == before, f"a test changed {RECORDS}: {sorted(set(after) ^ set(before))[:5]}"
