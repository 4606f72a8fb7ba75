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


@pytest.fixture
def one_thread():
    """torch on one thread for the test (restored after): training results with one and two threads
    differ in the last bits, and the tests compare runs bit for bit. Use it with
    `pytestmark = pytest.mark.usefixtures("one_thread")` for a whole file."""
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
