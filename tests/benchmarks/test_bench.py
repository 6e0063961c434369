"""The benchmark's measurements and tables (`make bench`), on tiny settings."""

import argparse
import math

import pytest
import torch

from benchmarks.bench import measure, print_table, print_train_compare, train_compare, worker_start


def test_print_table_aligns_columns(capsys):
    print_table([{"name": "a", "value": 1.5}, {"name": "longer", "value": 12.25}],
                [("name", "config", 8, ""), ("value", "x", 7, ".2f")])
    lines = capsys.readouterr().out.splitlines()
    assert lines == ["config        x", "-" * 15, "a          1.50", "longer    12.25"]


def test_measure_counts_the_paper_and_efficient_networks():
    paper, efficient = (measure(name, "resnet18", 64, 1, "cpu") for name in ("paper", "efficient"))
    assert paper["params_m"] > efficient["params_m"] > 0
    assert paper["gmac"] > efficient["gmac"] > paper["encoder_gmac"] == efficient["encoder_gmac"] > 0
    assert torch.is_grad_enabled()  # measured without switching autograd off for the caller


@pytest.mark.parametrize("method", ["fork", "forkserver"])
def test_worker_start_times_two_loaders_of_the_method(tiny_uapd, method):
    row = worker_start(method, str(tiny_uapd))
    assert row["method"] == method and row["first_s"] > 0 and row["next_s"] > 0


@pytest.mark.slow
def test_train_compare_trains_both_through_the_lightning_module(capsys, monkeypatch):
    from dapm_lightning.training.module import DAPMModule

    steps: list[str] = []
    real_step = DAPMModule.training_step

    def counted(self, batch, batch_idx):
        steps.append(self.net_config.head_stride)
        return real_step(self, batch, batch_idx)

    monkeypatch.setattr(DAPMModule, "training_step", counted)
    rows = train_compare(["efficient", "paper"], backbone="resnet18", size=32, steps=2, batch=2, train_images=4,
                         val_images=2)
    assert [r["config"] for r in rows] == ["efficient", "paper"]
    assert steps == [4, 4, 1, 1]  # the module's own step, 2 per network (efficient heads at 1/4, paper at 1/1)
    for row in rows:
        assert all(math.isfinite(v) for k, v in row.items() if k != "config"), row
    print_train_compare(rows, argparse.Namespace(backbone="resnet18", train_size=32, train_images=4, val_images=2,
                                                 train_steps=2, train_batch=2))
    table = capsys.readouterr().out
    assert "\nefficient " in table and "\npaper " in table
