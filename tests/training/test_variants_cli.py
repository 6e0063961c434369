"""The efficient variant overlay stacked on a paper config, through the real CLI."""

from tests.conftest import CONFIGS
from tests.training.test_cli import PAPER, fast_fit


def test_efficient_variant_overlay_trains_a_step(tiny_uapd, tmp_path, monkeypatch):
    cli = fast_fit(["--config", str(PAPER), "--config", str(CONFIGS / "variants" / "efficient.yaml")], tiny_uapd,
                   tmp_path, monkeypatch)
    assert cli.trainer.global_step == 1
    net = cli.model.hparams["net"]
    assert net["head_stride"] == 4 and not net["depth_residual_priors"] and not net["decoder_squeeze_excite"]
    assert net["pose_bins_source"] == "encoder" and net["pose_residual_init"]  # the paper's pose branch
    assert cli.model.hparams["loss"]["depth_space"] == "log_norm"  # the overlay changes the network only
    assert "val_depthauthors_rmse_unit" in cli.trainer.callback_metrics
