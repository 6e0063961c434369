"""The quickstart's report: the model beside its baselines and beside itself given telemetry."""

from dapm_lightning.tools.quickstart import ROWS, baselines, report, with_telemetry


def test_report_has_a_telemetry_column_from_the_real_model(checkpoint, tiny_uapd):
    telemetry = with_telemetry(str(checkpoint), tiny_uapd)
    assert {"d1", "abs_rel", "rmse"} <= set(telemetry["depth"]) and "height_median" in telemetry["pose"]
    # the pose used is the noisy telemetry (sigma 3 m in height): far closer than an untrained network
    assert telemetry["pose"]["height_median"] < 6.0 and telemetry["pose"]["pitch_median"] < 3.0
    base = baselines(tiny_uapd)
    model = {"depth": dict(base["depth"]), "pose": dict(base["pose"])}
    table, failures = report(model, base, telemetry)
    header, *rows = table.splitlines()
    assert header.split()[-1] == "+telem." and len(rows) == len(ROWS) + 1
    depth_d1 = next(r for r in rows if r.startswith("depth d1"))
    assert depth_d1.split()[-1] == f"{telemetry['depth']['d1']:.3f}"
    assert "depth d1" in failures  # equal to the baseline is not beating it
