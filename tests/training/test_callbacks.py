import math
import re
import warnings
from types import SimpleNamespace

import pytest
import torch

from dapm_lightning.models import DAPMConfig
from dapm_lightning.training.callbacks import DepthPanelLogger, IGDTeacherForcing
from dapm_lightning.training.module import DAPMModule, OptimizerConfig, PriorTraining, warmup_cosine


def test_teacher_forcing_schedule_start_middle_end():
    cb = IGDTeacherForcing()
    assert cb.share(0, 100) == 0.0
    assert cb.share(50, 100) == pytest.approx(0.5)
    assert cb.share(100, 100) == 1.0
    late = IGDTeacherForcing(start_share=0.2, end_share=1.0, start_fraction=0.5, end_fraction=0.75)
    assert late.share(10, 100) == pytest.approx(0.2)
    assert late.share(625, 1000) == pytest.approx(0.6)
    assert late.share(900, 1000) == 1.0
    with pytest.raises(ValueError):
        IGDTeacherForcing(start_fraction=0.8, end_fraction=0.2)


@pytest.mark.parametrize("shares", [(-0.5, 1.0), (0.0, 10.0)])
def test_teacher_forcing_shares_outside_0_1_are_refused(shares):
    """Before: accepted; start_share -0.5 fed the IGD 1.5 x the true pose - 0.5 x the prediction (a pose beyond the true
    one), end_share 10 (meant as 10 %?) handed the IGD over to the prediction by a tenth of training."""
    with pytest.raises(ValueError, match=r"start_share and end_share are shares of the predicted pose, in \[0, 1\]"):
        IGDTeacherForcing(start_share=shares[0], end_share=shares[1])


def test_priors_under_a_teacher_forcing_that_keeps_the_true_pose_are_flagged():
    with_priors = DAPMModule(DAPMConfig(backbone="resnet18"), prior_training=PriorTraining(enabled=True))
    with pytest.warns(UserWarning, match="prior_training changes nothing"):
        IGDTeacherForcing(start_share=0.0, end_share=0.0).on_fit_start(SimpleNamespace(), with_priors)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        IGDTeacherForcing().on_fit_start(SimpleNamespace(), with_priors)  # the share rises: the priors act
        IGDTeacherForcing(end_share=0.0).on_fit_start(SimpleNamespace(), DAPMModule(DAPMConfig(backbone="resnet18")))
        told = DAPMModule(DAPMConfig(backbone="resnet18", pose_prior_input=True),
                          prior_training=PriorTraining(enabled=True))
        IGDTeacherForcing(start_share=0.0, end_share=0.0).on_fit_start(SimpleNamespace(), told)  # the pose reads them


def test_callback_sets_share_and_eval_ignores_it(monkeypatch):
    module = DAPMModule(DAPMConfig(backbone="resnet18"), optimizer=OptimizerConfig(schedule_steps=120))
    module.log = lambda *a, **k: None
    trainer = SimpleNamespace(global_step=30, estimated_stepping_batches=120)
    IGDTeacherForcing().on_train_batch_start(trainer, module, None, 0)
    assert module.igd_predicted_share == pytest.approx(0.25)
    seen = []
    real_forward = module.net.forward
    monkeypatch.setattr(module.net, "forward", lambda image, forcing=None, prior=None: seen.append(forcing)
                        or real_forward(image, forcing, prior))
    module.log_dict = lambda *a, **k: None
    batch = dict(image=torch.rand(2, 3, 32, 32), depth=torch.full((2, 1, 32, 32), 50.0),
                 sky=torch.zeros(2, 1, 32, 32, dtype=torch.bool), valid=torch.ones(2, 1, 32, 32, dtype=torch.bool),
                 pose=torch.tensor([[50.0, -40, 0, 60]] * 2), has_pose=torch.ones(2, dtype=torch.bool))
    module._shared_step(batch, "train")
    module.eval()
    module._shared_step(batch, "val")
    assert seen[0].predicted_share == pytest.approx(0.25)
    torch.testing.assert_close(seen[0].pose_norm_true, module.net_config.igd.normalize(batch["pose"]))
    assert seen[1] is None  # validation: predictions only


def test_after_training_the_igd_sees_predictions_only():
    """The share the module is left with: a later fit without the callback must not keep feeding true poses."""
    module = DAPMModule(DAPMConfig(backbone="resnet18"), optimizer=OptimizerConfig(schedule_steps=120))
    module.log = lambda *a, **k: None
    callback = IGDTeacherForcing()
    callback.on_train_batch_start(SimpleNamespace(global_step=0), module, None, 0)
    assert module.igd_predicted_share == 0.0
    callback.on_train_end(SimpleNamespace(), module)
    assert module.igd_predicted_share == 1.0


def test_warmup_then_cosine():
    assert warmup_cosine(0, 100, 0.3, 0.0) == pytest.approx(1 / 30)
    assert warmup_cosine(29, 100, 0.3, 0.0) == pytest.approx(1.0)
    assert warmup_cosine(65, 100, 0.3, 0.0) == pytest.approx(0.5, abs=0.03)
    assert warmup_cosine(100, 100, 0.3, 0.1) == pytest.approx(0.1)


def test_data_and_model_depth_kinds_must_agree():
    module = DAPMModule(DAPMConfig(backbone="resnet18"))  # IGD of range depth
    module._trainer = SimpleNamespace(datamodule=SimpleNamespace(depth_kind="planar"))
    with pytest.raises(ValueError, match=r"model.net.igd.depth_kind: planar"):
        module.setup("fit")
    module._trainer = SimpleNamespace(datamodule=SimpleNamespace(depth_kind="range"))
    module.setup("fit")


def test_training_priors_are_drawn_anew_each_epoch_and_only_for_the_chosen_images():
    pose = torch.tensor([[50.0, -60.0, 0.0, 80.0]] * 8)
    has_pose, names = torch.ones(8, dtype=torch.bool), [f"img{k}" for k in range(8)]
    priors = PriorTraining(enabled=True, image_fraction=0.5, component_probability=0.9)
    epochs = [priors.sample(pose, has_pose, names, epoch) for epoch in (0, 1)]
    assert not torch.equal(epochs[0].known, epochs[1].known)
    assert torch.equal(priors.sample(pose, has_pose, names, 1).known, epochs[1].known)  # the same draws again
    none = PriorTraining(enabled=True, image_fraction=0.0, component_probability=1.0)
    assert not none.sample(pose, has_pose, names, 0).known.any()


def test_panels_are_rendered_once_per_optimizer_step_under_gradient_accumulation(monkeypatch):
    """global_step stands still over an accumulation window: before, each of its micro-batches rendered (an eval
    forward and, under DDP, a broadcast each) and overwrote the same PNG."""
    logger = DepthPanelLogger(every_n_steps=2)
    rendered: list[int] = []
    trainer = SimpleNamespace(global_step=0, log_dir=None)
    monkeypatch.setattr(logger, "_render", lambda trainer, *args: rendered.append(trainer.global_step))
    for step in (0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3, 4, 4, 4):  # accumulate_grad_batches=3
        trainer.global_step = step
        logger.on_train_batch_end(trainer, None, None, {}, 0)
    assert rendered == [0, 2, 4]


@pytest.mark.parametrize(("setting", "value", "wanted"), [
    ("lr", -1.0, ">= 0"), ("lr", math.nan, ">= 0"), ("weight_decay", -0.1, ">= 0"),
    ("betas", (0.9, 1.0), "two numbers in [0, 1)"), ("warmup_fraction", 1.5, "in [0, 1]"),
    ("min_lr_ratio", -1.0, "in [0, 1]"), ("schedule_steps", 0, ">= 1"), ("schedule_seconds", -1.0, "> 0")])
def test_optimizer_settings_that_cannot_train_are_refused_naming_them(setting, value, wanted):
    """Before, a negative lr failed inside torch after the data was rendered and a log folder made, naming no
    setting, and min_lr_ratio -1 trained at a negative learning rate (gradient ascent) and exited 0."""
    with pytest.raises(ValueError, match=rf"model\.optimizer\.{setting} must be {re.escape(wanted)}"):
        OptimizerConfig(**{setting: value})
    OptimizerConfig(lr=0.0, weight_decay=0.0, betas=(0.0, 0.999), warmup_fraction=1.0, min_lr_ratio=1.0,
                    schedule_steps=1, schedule_seconds=1.0)  # the bounds themselves pass


def test_a_bad_optimizer_setting_stops_fit_before_anything_is_written(tmp_path, monkeypatch, capsys):
    from tests.conftest import QUICKSTART, run_main

    monkeypatch.chdir(tmp_path)
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--data.init_args.root", "data",  # were it not refused:
                          "--data.init_args.train_size", "2", "--data.init_args.val_size", "1",  # a short run
                          "--data.init_args.image_size", "16", "--data.init_args.render_workers", "1",
                          "--trainer.max_steps", "1", "--model.optimizer.min_lr_ratio", "-1"], capsys)
    assert code == 1 and "model.optimizer.min_lr_ratio must be in [0, 1], got -1.0" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no data rendered, no log folder
