"""DDP with 2 CPU processes (gloo): every config trains, and logged validation figures equal a single-process run."""

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from dapm_lightning.data.synthetic import generate_uapd

pytestmark = pytest.mark.slow  # multi-process runs: `make test-all`
HERE = Path(__file__).resolve().parent
QUICKSTART = HERE.parents[1] / "dapm_lightning" / "configs" / "quickstart.yaml"


def run(tmp_path, name, *args, timeout=300):
    """Rank 0's figures (what the processes printed: ``NAME.out``); a run still going after ``timeout`` s fails the
    test, every process it started killed (the others would wait in a collective for the process group's 30
    minutes)."""
    out = tmp_path / f"{name}.json"
    process = subprocess.Popen([sys.executable, str(HERE / "ddp_run.py"), str(out), *args], cwd=tmp_path, text=True,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    try:
        stdout, stderr = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        pytest.fail(f"{name}: still running after {timeout} s (processes waiting for each other):\n"
                    f"{process.communicate()[1][-3000:]}")
    (tmp_path / f"{name}.out").write_text(stdout)
    if process.returncode:
        raise subprocess.CalledProcessError(process.returncode, process.args, stdout, stderr)
    return json.loads(out.read_text())


def test_ddp_two_cpu_processes_match_single_process(tmp_path):
    # 5 validation images: 3 on rank 0, 2 on rank 1 (the losses' means weigh the processes by their images)
    root = generate_uapd(tmp_path / "data", train=8, val=5, size=(24, 40), seed=11, workers=1)
    common = ["--config", str(QUICKSTART), "--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule",
              "--data.init_args.root", str(root), "--data.init_args.batch_size", "2",
              "--data.init_args.num_workers", "0", "--trainer.accelerator", "cpu",
              "--data.init_args.eval_batch_size", "1",  # per-image losses: the same sums whatever the split
              "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint",
              "--trainer.callbacks.dirpath", str(tmp_path / "ckpt")]
    try:
        fit = run(tmp_path, "fit", "fit", *common, "--trainer.devices", "2", "--trainer.strategy", "ddp",
                  "--trainer.max_steps", "3", "--trainer.limit_val_batches", "0",
                  "--model.prior_training.enabled", "true",  # telemetry priors under DDP, told to both branches
                  "--model.net.pose_prior_input", "true", "--model.net.depth_prior_input", "true",
                  "--model.net.pose_pool_grid", "2")  # the pose branch's pooled cells: every weight used
    except subprocess.CalledProcessError as error:
        pytest.fail(f"DDP fit failed:\n{error.stderr[-3000:]}")
    assert fit["global_step"] == 3
    ckpt = sorted((tmp_path / "ckpt").glob("*.ckpt"))[-1]
    single = run(tmp_path, "one", "validate", *common, "--trainer.devices", "1", "--ckpt_path", str(ckpt))
    double = run(tmp_path, "two", "validate", *common, "--trainer.devices", "2", "--trainer.strategy", "ddp",
                 "--ckpt_path", str(ckpt))
    keys = [k for k in single["metrics"] if k.startswith("val_")]  # metrics and epoch-level losses alike
    assert {"val_pose_roll_median", "val_depth_abs_rel", "val_loss", "val_loss_pd"} <= set(keys)
    for key in keys:
        assert double["metrics"][key] == pytest.approx(single["metrics"][key], rel=1e-5, abs=1e-6), key
    # `test` with the quickstart's loggers, panels and viewpoint figure: their rank-0 writes once asked
    # trainer.log_dir (a broadcast) on rank 0 alone, and the two processes waited for each other forever
    tested = run(tmp_path, "test", "test", *common, "--trainer.devices", "2", "--trainer.strategy", "ddp",
                 "--trainer.default_root_dir", str(tmp_path / "test_run"), "--ckpt_path", str(ckpt))
    assert tested["metrics"]["test_depth_d1"] == pytest.approx(single["metrics"]["val_depth_d1"], rel=1e-5)
    assert list((tmp_path / "test_run").rglob("viewpoints.png")) and list((tmp_path / "test_run").rglob("panels/*.png"))


def test_ddp_evaluates_fewer_images_than_processes(tmp_path):
    """One validation image, two processes: rank 1 has no batch, yet fit (its sanity check and validation), validate
    and test (with the quickstart's loggers, panels and viewpoint figure) end with one process's figures. Rank 1 once
    stopped with Lightning's "`DataLoader` within local rank has zero length"; allowed, it skipped the evaluation
    loop, and rank 0 waited in the collectives of the metrics, the logged losses and DDP's buffer sync."""
    root = generate_uapd(tmp_path / "data", train=4, val=1, size=(24, 32), seed=15, workers=1)
    common = ["--config", str(QUICKSTART), "--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule",
              "--data.init_args.root", str(root), "--data.init_args.batch_size", "2",
              "--data.init_args.num_workers", "0", "--trainer.accelerator", "cpu"]
    ddp = ["--trainer.devices", "2", "--trainer.strategy", "ddp"]

    def launch(name, subcommand, *args):
        try:
            return run(tmp_path, name, subcommand, *common, *args, timeout=180)
        except subprocess.CalledProcessError as error:
            pytest.fail(f"{name} failed:\n{error.stderr[-3000:]}")

    fit = launch("fit", "fit", *ddp, "--trainer.max_steps", "1", "--trainer.logger", "false",
                 "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint",
                 "--trainer.callbacks.dirpath", str(tmp_path / "ckpt"))  # one step per epoch: validated after it
    ckpt = str(next((tmp_path / "ckpt").glob("*.ckpt")))
    single = launch("one", "validate", "--trainer.devices", "1", "--trainer.logger", "false", "--ckpt_path", ckpt)
    tested = launch("test", "test", *ddp, "--trainer.default_root_dir", str(tmp_path / "test_run"), "--ckpt_path", ckpt)
    keys = [k for k in single["metrics"] if k.startswith("val_")]
    assert {"val_pose_roll_median", "val_depth_abs_rel", "val_loss", "val_loss_pd"} <= set(keys)
    for key in keys:
        expected = pytest.approx(single["metrics"][key], rel=1e-5, abs=1e-6)
        assert fit["metrics"][key] == expected and tested["metrics"]["test" + key[3:]] == expected, key
    assert list((tmp_path / "test_run").rglob("viewpoints.png")) and list((tmp_path / "test_run").rglob("panels/*.png"))


ALL_CONFIGS = [f"{folder}/{p.name}" for folder in ("paper", "ablations", "variants")
               for p in sorted((HERE.parents[1] / "configs" / folder).glob("*.yaml"))]


def test_every_shipped_config_trains_under_two_process_ddp(tmp_path, tiny_potsdam):
    """Each paper config and each ablation and variant overlay, as the README stacks them, under DDP without
    find_unused_parameters: a parameter built but not used stops DDP at the second step."""
    tiny_uapd = generate_uapd(tmp_path / "data", train=12, val=2, size=(24, 40), seed=12, workers=1)
    results = {}
    # a few configs per launch: each DDP fit raises a process's peak memory by ~0.5 GB that later fits in the
    # same process do not reuse (not seen in one-process fits), so 21 in one launch need ~10 GB per rank
    for launch, start in enumerate(range(0, len(ALL_CONFIGS), 6)):
        out, logs = tmp_path / f"configs{launch}.json", tmp_path / f"rank_logs{launch}"  # one log file per rank
        try:
            subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2",
                            "--master_port", str(29731 + launch), "--log-dir", str(logs), "--redirects", "3",
                            str(HERE / "ddp_configs_run.py"), str(out), str(tiny_uapd), str(tiny_potsdam),
                            *ALL_CONFIGS[start:start + 6]],
                           check=True, cwd=tmp_path, capture_output=True, text=True, timeout=600)
        except (subprocess.CalledProcessError, subprocess.TimeoutExpired) as error:
            launcher = error.stderr if isinstance(error.stderr, str) else (error.stderr or b"").decode()
            pytest.fail(f"DDP run failed ({error}):\n" + "\n".join(
                f"== {path.relative_to(logs)}\n{path.read_text()[-3000:]}" for path in sorted(logs.rglob("stderr.log")))
                + f"\n== torchrun\n{launcher[-2000:]}")
        results.update(json.loads(out.read_text()))
    # the configs' logs and checkpoints follow --trainer.default_root_dir: nothing in the working folder's outputs/
    assert not (tmp_path / "outputs").exists(), "a config wrote outside the run's folder"
    assert sorted(results) == sorted(ALL_CONFIGS)
    for config, result in results.items():
        assert result["world_size"] == 2 and result["global_step"] == 2, config
        assert result["last_ckpt_step"] == 2, config  # last.ckpt holds the final step, between two periodic saves
        assert not result["find_unused"], config
        assert not result["unsynced"], (config, result["unsynced"])


def test_a_run_that_fails_on_rank_0_leaves_no_process_behind(tmp_path):
    """Rank 0 cannot open its rendezvous port (MASTER_PORT held by another program): the run ends with the error
    and kills the process it started, which would otherwise wait to connect for 30 minutes."""
    import os
    import signal
    import socket
    import time

    root = generate_uapd(tmp_path / "data", train=4, val=2, size=(24, 32), seed=3, workers=1)
    held = socket.socket()
    held.bind(("", 0))
    held.listen()
    env = dict(os.environ, MASTER_PORT=str(held.getsockname()[1]), MASTER_ADDR="127.0.0.1")
    process = subprocess.Popen(
        [sys.executable, "-m", "dapm_lightning", "fit", "--config", str(QUICKSTART), "--data.class_path",
         "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(root),
         "--data.init_args.num_workers", "0", "--trainer.accelerator", "cpu", "--trainer.devices", "2",
         "--trainer.strategy", "ddp", "--trainer.max_steps", "2", "--trainer.logger", "false"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        out, _ = process.communicate(timeout=120)  # the output closes when every process holding it has ended
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        pytest.fail(f"the run or a process it started was still running after 120 s:\n{process.communicate()[0]}")
    finally:
        held.close()
    assert process.returncode == 1 and "address already in use" in out.lower(), out[-3000:]
    assert "stopped the 1 other training process(es) of this run" in out, out[-3000:]
    assert f"Fix: MASTER_PORT={env['MASTER_PORT']} is taken" in out and "Traceback" not in out, out[-3000:]
    time.sleep(1)
    with pytest.raises(ProcessLookupError):
        os.killpg(process.pid, 0)


def test_fine_tuning_under_two_process_ddp_starts_from_the_weights_and_resumes_without_them(tmp_path):
    """``model.init_weights`` under DDP: each process starts from the file's weights (their digests as training
    starts), and the run resumes from its own checkpoint once the file is gone."""
    import shutil

    from dapm_lightning.training.checkpoint_files import read_checkpoint
    from dapm_lightning.training.checkpointing import load_dapm_module
    from tests.training.weights_digest import parameters_digest

    root = generate_uapd(tmp_path / "data", train=8, val=2, size=(24, 40), seed=13, workers=1)
    common = ["--config", str(QUICKSTART), "--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule",
              "--data.init_args.root", str(root), "--data.init_args.batch_size", "2",
              "--data.init_args.num_workers", "0", "--trainer.accelerator", "cpu", "--trainer.limit_val_batches", "0",
              "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint"]

    def fit(name, *args):
        try:
            return run(tmp_path, name, "fit", *common, "--trainer.callbacks.dirpath", str(tmp_path / name),
                       "--trainer.callbacks+=weights_digest.WeightsDigest",
                       "--trainer.callbacks.folder", str(tmp_path / f"{name}_digests"), *args)
        except subprocess.CalledProcessError as error:
            pytest.fail(f"{name} failed:\n{error.stderr[-3000:]}")

    fit("base", "--trainer.devices", "1", "--trainer.max_steps", "2")
    init = tmp_path / "init.ckpt"
    shutil.copy(sorted((tmp_path / "base").glob("*.ckpt"))[-1], init)
    names = [f"net.{name}" for name, _ in load_dapm_module(init).net.named_parameters()]
    start = read_checkpoint(init)["state_dict"]
    expected = parameters_digest((name.removeprefix("net."), start[name]) for name in names)
    ddp = ["--trainer.devices", "2", "--trainer.strategy", "ddp", "--model.init_weights", str(init)]
    tuned = fit("tuned", *ddp, "--trainer.max_steps", "2")
    assert tuned["global_step"] == 2
    # fit's closing lines, from the first process alone, name files that are there (the run's config as saved)
    said = (tmp_path / "tuned.out").read_text().splitlines()
    assert said.count("fit finished at step 2.") == 1, said
    evaluate = next(line for line in said if line.startswith("evaluate it: dapm-lightning test --config "))
    config, checkpoint = evaluate.split("--config ", 1)[1].split(" --ckpt_path ")
    assert (tmp_path / config).is_file() and (tmp_path / config).name == "config.yaml"
    assert (tmp_path / checkpoint).is_file() and checkpoint in {line.split(": ", 1)[1] for line in said if ": " in line}
    digests = [(tmp_path / "tuned_digests" / f"rank{rank}.txt").read_text() for rank in (0, 1)]
    assert digests == [expected, expected]
    saved = sorted((tmp_path / "tuned").glob("*.ckpt"))[-1]
    init.unlink()
    resumed = fit("resumed", *ddp, "--trainer.max_steps", "4", "--ckpt_path", str(saved))
    assert resumed["global_step"] == 4
    after = read_checkpoint(saved)["state_dict"]
    resumed_digest = parameters_digest((name.removeprefix("net."), after[name]) for name in names)
    assert [(tmp_path / "resumed_digests" / f"rank{rank}.txt").read_text() for rank in (0, 1)] == [resumed_digest] * 2


def test_two_process_ddp_steps_by_one_clock_and_resumes_it(tmp_path):
    """``model.optimizer.schedule_seconds`` under DDP: rank 1's clock starts 0.5 s after rank 0's (a sleep in its
    first step), yet both processes step with the same learning rates and IGD shares (the time of the latest process)
    and end with the same weights, also after a resume, which goes on from the time saved."""
    root = generate_uapd(tmp_path / "data", train=8, val=2, size=(24, 40), seed=14, workers=1)
    callbacks = tmp_path / "callbacks.yaml"
    callbacks.write_text(yaml.safe_dump({"trainer": {"logger": False, "callbacks": [
        {"class_path": "dapm_lightning.training.callbacks.IGDTeacherForcing", "init_args": {"end_share": 1.0}},
        {"class_path": "dapm_lightning.training.checkpointing.LastCheckpoint",
         "init_args": {"dirpath": str(tmp_path / "ckpt")}}]}}))
    common = ["--config", str(QUICKSTART), "--config", str(callbacks), "--data.class_path",
              "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(root),
              "--data.init_args.batch_size", "2", "--data.init_args.num_workers", "0", "--trainer.accelerator", "cpu",
              "--trainer.limit_val_batches", "0", "--trainer.devices", "2", "--trainer.strategy", "ddp",
              # a warm-up over 30 s: the learning rate changes with every thousandth of the 60 s
              "--model.optimizer.schedule_seconds", "60", "--model.optimizer.warmup_fraction", "0.5"]

    def fit(name, *args):
        try:
            run(tmp_path, name, "fit", *common, "--trainer.callbacks+=schedule_record.ScheduleRecord",
                "--trainer.callbacks.folder", str(tmp_path / name), "--trainer.callbacks.rank1_delay", "0.5", *args)
        except subprocess.CalledProcessError as error:
            pytest.fail(f"{name} failed:\n{error.stderr[-3000:]}")
        return [json.loads((tmp_path / name / f"rank{rank}.json").read_text()) for rank in (0, 1)]

    first = fit("first", "--trainer.max_steps", "3")
    assert len(first[0]["steps"]) == 3 and first[0] == first[1]
    assert first[0]["steps"][-1][1] >= 0.5  # the latest process's time: rank 0's, whose clock started first
    resumed = fit("resumed", "--trainer.max_steps", "6", "--ckpt_path", str(tmp_path / "ckpt" / "last.ckpt"))
    assert len(resumed[0]["steps"]) == 3 and resumed[0] == resumed[1]
    assert resumed[0]["steps"][0][1] == first[0]["steps"][-1][1]  # goes on from the time saved


def test_two_nodes_train_as_one_node_of_two_processes_and_resume(tmp_path, monkeypatch):
    """``num_nodes 2`` x ``devices 1``: two torchrun launchers on this machine (static rendezvous), sharing the data
    and run folders as a cluster's nodes share a file system. Each node renders the synthetic set into the same root
    at once (where a render cut short left images), trains one epoch, is resumed on two nodes for a second, and ends
    with the weights of one node of two processes trained without a stop. With ``prepare_data_per_node`` false the
    first node alone renders a new set, the other waiting for it."""
    import socket

    import torch

    from dapm_lightning.training.checkpoint_files import read_checkpoint

    root = tmp_path / "data"
    generate_uapd(root, train=3, val=1, size=(16, 16), seed=5, workers=1)
    (root / "synth.json").unlink()  # a render cut short: its images are replaced by each node's render
    common = ["--config", str(QUICKSTART), "--data.init_args.root", str(root), "--data.init_args.train_size", "8",
              "--data.init_args.val_size", "2", "--data.init_args.image_size", "32",
              "--data.init_args.batch_size", "2", "--data.init_args.num_workers", "1",
              "--data.init_args.persistent_workers", "true", "--data.init_args.render_workers", "1",
              "--trainer.accelerator", "cpu", "--trainer.strategy", "ddp",
              "--model.optimizer.schedule_steps", "4"]  # the learning rates of a 2-epoch run, before a resume too
    # one thread a process in both layouts (Lightning gives a node's processes the cores shared out, a node of one
    # process all of them; other thread counts sum the convolutions in another order: equal to rounding, not the bit)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")

    def two_nodes(name, *args):
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        out = tmp_path / f"{name}.json"
        launchers = [subprocess.Popen(
            [sys.executable, "-m", "torch.distributed.run", "--nnodes", "2", "--nproc_per_node", "1",
             "--node_rank", str(node), "--rdzv_backend", "static", "--master_addr", "127.0.0.1",
             "--master_port", str(port), str(HERE / "ddp_run.py"), str(out), "fit", *common,
             "--trainer.num_nodes", "2", "--trainer.devices", "1", *args],
            cwd=tmp_path, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            start_new_session=True) for node in (0, 1)]
        logs = []
        for launcher in launchers:
            try:
                logs.append(launcher.communicate(timeout=300)[0])
            except subprocess.TimeoutExpired:
                for each in launchers:
                    os.killpg(each.pid, signal.SIGKILL)
                pytest.fail(f"{name}: still running after 300 s:\n{launcher.communicate()[0][-3000:]}")
        if any(launcher.returncode for launcher in launchers):
            pytest.fail(f"{name} failed:\n"
                        + "\n".join(f"== node {node}\n{log[-3000:]}" for node, log in enumerate(logs)))
        return json.loads(out.read_text()), logs

    first, logs = two_nodes("first", "--trainer.max_epochs", "1", "--trainer.default_root_dir", str(tmp_path / "nodes"))
    assert all(f"{root}: rendering 8 + 2 synthetic images" in log for log in logs)  # one render per node
    assert first["global_step"] == 2  # 8 images, 2 processes, batches of 2
    resumed, _ = two_nodes("resumed", "--trainer.max_epochs", "2", "--ckpt_path", "last",
                           "--trainer.default_root_dir", str(tmp_path / "nodes"))
    assert resumed["global_step"] == 4
    try:
        one = run(tmp_path, "one_node", "fit", *common, "--trainer.devices", "2", "--trainer.max_epochs", "2",
                  "--trainer.default_root_dir", str(tmp_path / "one_node"))
    except subprocess.CalledProcessError as error:
        pytest.fail(f"one node failed:\n{error.stderr[-3000:]}")
    assert one["global_step"] == 4
    nodes, single = (read_checkpoint(max((tmp_path / folder).rglob("last.ckpt"), key=os.path.getmtime))["state_dict"]
                     for folder in ("nodes", "one_node"))
    assert sorted(nodes) == sorted(single)
    assert all(torch.equal(nodes[key], single[key]) for key in single)
    shared = tmp_path / "shared"  # data.init_args.prepare_data_per_node false: one render for the whole job
    once, logs = two_nodes("once", "--data.init_args.root", str(shared), "--data.init_args.prepare_data_per_node",
                           "false", "--trainer.max_steps", "1", "--trainer.default_root_dir", str(tmp_path / "once"))
    assert [f"{shared}: rendering 8 + 2 synthetic images" in log for log in logs] == [True, False]
    assert once["global_step"] == 1
