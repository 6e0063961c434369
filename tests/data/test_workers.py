"""Loader workers ignore a SIGTERM sent to the whole job, yet never keep their process from exiting."""

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_a_process_whose_worker_failed_exits():
    """The pytest run of one test whose loader worker raised (the error kept, as pytest keeps it) exits: the
    worker's SIGTERM from multiprocessing's exit handler is heard. Before, the process joined it for ever."""
    test = ("tests/data/test_bad_files.py::"
            "test_without_skip_a_file_deleted_after_the_scan_stops_the_loader_as_missing_from_a_worker")
    result = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", test], cwd=REPO,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and "1 passed" in result.stdout, result.stdout[-2000:]
