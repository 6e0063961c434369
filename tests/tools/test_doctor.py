import json
import shutil

import numpy as np
import pytest

from dapm_lightning.cli import main
from dapm_lightning.data import parse_uapd_filename
from dapm_lightning.data.synthetic import generate_uapd
from dapm_lightning.tools.doctor import doctor_main


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    return generate_uapd(tmp_path_factory.mktemp("doc") / "d", train=16, val=4, size=64, seed=21, workers=1)


def test_synthetic_data_is_in_full_agreement(synthetic, capsys, tmp_path):
    before = sorted(p.relative_to(synthetic) for p in synthetic.rglob("*"))
    assert doctor_main([str(synthetic)]) == 0
    assert sorted(p.relative_to(synthetic) for p in synthetic.rglob("*")) == before  # nothing written into the data
    assert doctor_main([str(synthetic), "--json", str(tmp_path / "reports" / "doctor.json")]) == 0
    report = json.loads((tmp_path / "reports" / "doctor.json").read_text())
    assert [r["split"] for r in report] == ["train", "val"]
    assert all(not r["flagged"] and not r["errors"] for r in report)
    assert report[0]["count"] == 16 and report[0]["pose"]["roll"]["outside_range"] == 0
    assert "no problems found" in capsys.readouterr().out


def test_negated_roll_names_are_flagged_exactly(synthetic, tmp_path):
    root = shutil.copytree(synthetic, tmp_path / "copy")
    negated = []
    for rgb in sorted((root / "train" / "rgb").iterdir()):
        p = parse_uapd_filename(rgb.name)
        if abs(p["roll"]) > 12 and -75 < p["pitch"] < -5:
            new = rgb.name.replace(f"_roll_{p['roll']:.2f}_", f"_roll_{-p['roll']:.2f}_")
            for sub in ("rgb", "depth"):
                (root / "train" / sub / rgb.name).rename(root / "train" / sub / new)
            negated.append(new)
    assert len(negated) >= 3
    (root / "val" / "depth" / sorted((root / "val" / "depth").iterdir())[0].name).unlink()
    assert doctor_main([str(root), "--json", str(tmp_path / "r.json")]) == 1
    report = {r["split"]: r for r in json.loads((tmp_path / "r.json").read_text())}
    assert sorted(f["name"] for f in report["train"]["flagged"]) == sorted(negated)
    assert all("roll negated" in f["reason"] for f in report["train"]["flagged"])
    assert len(report["val"]["errors"]) == 1 and "no depth twin" in report["val"]["errors"][0]


def test_cli_doctor_exit_status_and_settings_file(synthetic, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["doctor", str(tmp_path / "missing")])
    assert info.value.code == 1 and f"{tmp_path / 'missing'}: no such folder" in capsys.readouterr().err
    config = tmp_path / "doctor.yaml"
    config.write_text(f"depth_kind: planar\nsplits: [val]\njson: {tmp_path / 'planar.json'}\n")
    with pytest.raises(SystemExit) as info:
        main(["doctor", str(synthetic), "--config", str(config), "--print_config"])
    printed = capsys.readouterr().out
    assert info.value.code == 0 and "depth_kind: planar" in printed and "- val" in printed
    with pytest.raises(SystemExit) as info:
        main(["doctor", str(synthetic), "--config", str(config)])
    report = json.loads((tmp_path / "planar.json").read_text())
    assert [r["split"] for r in report] == ["val"] and report[0]["depth_kind"] == "planar"
    with pytest.raises(SystemExit) as info:
        main(["doctor", str(synthetic), "--json", str(tmp_path / "r.json")])
    assert info.value.code == 0
    assert np.isfinite(json.loads((tmp_path / "r.json").read_text())[0]["ground_agreement"]["median"])
