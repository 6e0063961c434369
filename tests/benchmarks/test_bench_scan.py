"""The start-up scan benchmark (`python -m benchmarks.bench_scan`) on tiny settings; its figures are not asserted."""

from benchmarks.bench_scan import main
from dapm_lightning.data.pngcheck import SCAN_THREADS


def test_the_scan_benchmark_runs_and_reports_files_per_second(capsys):
    report = main(["--pairs", "6", "--size", "32", "--rendered", "2", "--rounds", "1"])
    assert report["files"] == 12
    assert list(report["files_per_s"]) == [f"scan ({SCAN_THREADS} threads)", "scan, 1 thread", "header only (before)",
                                           "decode (cv2.imread)"]
    assert all(rate > 0 for rate in report["files_per_s"].values())
    assert "files/s" in capsys.readouterr().out
