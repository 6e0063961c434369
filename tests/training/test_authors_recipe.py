"""configs/paper/uapd_dapm.yaml through the real CLI: the authors' recipe reaches the model and the data."""

from dapm_lightning.data.transforms import AUTHORS_AUGMENTATION
from dapm_lightning.models.config import AUTHORS_TRAINING
from tests.training.test_cli import PAPER, fast_fit


def test_paper_config_trains_with_the_authors_recipe_and_logs_their_pose_protocol(tiny_uapd, tmp_path, monkeypatch):
    cli = fast_fit(["--config", str(PAPER)], tiny_uapd, tmp_path, monkeypatch)
    assert cli.trainer.global_step == 1
    net = cli.model.net_config
    assert {k: getattr(net, k) for k in AUTHORS_TRAINING} == dict(AUTHORS_TRAINING)
    assert net.igd.model == "paper" and cli.model.criterion.igd.model == "paper"  # the feature and L_pd alike
    assert cli.model.net.pixel_mean.abs().sum() == 0 and (cli.model.net.pixel_std == 1).all()
    assert cli.datamodule.augmentation == AUTHORS_AUGMENTATION
    metrics = cli.trainer.callback_metrics
    for key in ("height", "pitch", "roll", "fov"):
        assert 0.0 <= float(metrics[f"val_poseauthors_{key}_auc5"]) <= 1.0
        assert float(metrics[f"val_poseauthors_{key}_mae"]) >= 0.0
    assert "val_pose_roll_auc5" in metrics  # GeoCalib's, beside it
