"""`bench_predict memory`: a video through the Lightning form of `dapm-lightning predict`, memory sampled."""

from benchmarks.bench_predict import main


def test_memory_predicts_a_video_with_every_output_written(tmp_path, capsys):
    out = tmp_path / "pred"
    main(["memory", "--frames", "12", "--every", "4", "--batch_size", "4", "--num_workers", "0", "--out", str(out)])
    printed = capsys.readouterr().out
    assert [line.split()[0] for line in printed.splitlines() if "frames: RSS" in line] == ["4", "8", "12"]
    # 7 per frame, poses.csv/.json, the contact sheet and the video's preview (long_depth.mp4)
    assert "12 frames in" in printed and "88 files written" in printed
    assert "RSS change from frame 8 to 12" in printed
    assert len(list(out.glob("*_depth.npy"))) == 12 and (out / "poses.csv").is_file()
