"""Shared fixtures: `--runslow` gates end-to-end tests; `shared_data` locates ../shared/data;
`--torch-threads N` runs the suite with N torch threads (CI runs it with 1 and with 2).

Property tests draw the same examples on every run (hypothesis `derandomize`), so CI results
are reproducible; `--hypothesis-profile=default` draws fresh ones, as a nightly job would, and
`--hypothesis-seed=N` with it replays such a run.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import settings

settings.register_profile("reproducible", derandomize=True)
settings.load_profile("reproducible")

# As in the CLI: idle OpenMP threads sleep rather than spin (set before torch is imported).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--runslow", action="store_true", help="also run tests marked slow")
    parser.addoption("--torch-threads", type=int, default=None, help="torch intra-op threads for the whole run")


def pytest_configure(config: pytest.Config) -> None:
    threads = config.getoption("--torch-threads")
    if threads:
        import torch

        torch.set_num_threads(threads)
        os.environ["OMP_NUM_THREADS"] = str(threads)  # for child processes


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--runslow"):
        return
    skip = pytest.mark.skip(reason="slow end-to-end test: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def shared_data() -> Path:
    """The team's real data folder; tests using it skip cleanly when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is not available")
    return SHARED_DATA


@pytest.fixture(scope="module")
def single_thread():
    """Modules of tiny tensor problems run torch single-threaded (on a busy 2-core machine
    intra-op threads only add synchronisation: 3-15x slower, measured) and restore it after."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
