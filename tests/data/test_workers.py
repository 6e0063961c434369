"""Loader workers start from a fork server and ignore a SIGTERM sent to the whole job, yet never keep their process
from exiting."""

import contextlib
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from torch.utils.data import DataLoader, Dataset

from dapm_lightning.data.datamodules import UAPDDataModule
from dapm_lightning.data.workers import loader_workers

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


class ParentPid(Dataset):
    """Each item: the process id of the worker's parent (module level: a fork server's worker unpickles it)."""

    def __len__(self) -> int:
        return 2

    def __getitem__(self, index: int) -> int:
        return os.getppid()


class Pid(ParentPid):
    """Each item: the worker's own process id."""

    def __getitem__(self, index: int) -> int:
        return os.getpid()


def parents(loader: DataLoader) -> set[int]:
    return {int(pid) for batch in loader for pid in batch}


def test_workers_start_from_a_fork_server_not_from_this_process():
    """A worker forked from this process would inherit any lock its other threads hold (a start that hangs)."""
    assert parents(DataLoader(ParentPid(), **loader_workers(1, method="fork"))) == {os.getpid()}
    (server,) = parents(DataLoader(ParentPid(), **loader_workers(1)))
    assert server != os.getpid()
    assert parents(DataLoader(ParentPid(), **loader_workers(2))) == {server}  # one server for every loader


def test_the_fork_server_outlives_a_sigterm_to_the_whole_job():
    """A persistent worker follows its parent, the server: had the server died of a SIGTERM meant for the whole job,
    the worker would stop serving and the run fail on its next batch instead of stopping after its step."""
    loader = DataLoader(ParentPid(), persistent_workers=True, **loader_workers(1))
    (server,) = parents(loader)
    os.kill(server, signal.SIGTERM)
    time.sleep(0.5)
    os.kill(server, 0)  # still running (ProcessLookupError otherwise)
    assert parents(loader) == {server}


@pytest.mark.parametrize("method", ["forkserver", "fork"])
def test_workers_and_their_server_outlive_slurm_s_warning_signal(method):
    """SLURM's ``--signal=USR1@90`` (Lightning's auto-requeue) reaches every process of the step: meant for the
    training process. Before, it ended the fork server and the workers (the default action), and the run failed with
    ``EOFError``; a forked worker ran the training process's handler."""
    persistent = {"persistent_workers": True, **loader_workers(1, method=method)}
    workers, servers = DataLoader(Pid(), **persistent), DataLoader(ParentPid(), **persistent)
    (worker,), (parent,) = parents(workers), parents(servers)
    targets = {worker} if method == "fork" else {worker, parent}
    for number in (signal.SIGUSR1, signal.SIGUSR2):
        for pid in targets:
            os.kill(pid, number)
    time.sleep(0.5)
    for pid in targets:
        os.kill(pid, 0)  # still running (ProcessLookupError otherwise)
    assert parents(workers) == {worker} and parents(servers) == {parent}


def test_a_forked_worker_never_runs_the_training_process_s_warning_signal_handler(tmp_path, monkeypatch):
    """A forked worker inherits the training process's handlers (Lightning's auto-requeue on SIGUSR1: a save and
    ``scontrol requeue``) until its ``worker_init_fn``: a USR1 arriving before (here, as torch sets the worker's own
    handlers) ran it in the worker. Now the worker starts with the signal blocked, and ignores it from its start."""
    from torch.utils.data._utils import signal_handling

    def handler(signum, frame):
        (tmp_path / f"handled_in_{os.getpid()}").touch()

    set_handlers = signal_handling._set_worker_signal_handlers

    def warned_as_it_starts(*args):
        os.kill(os.getpid(), signal.SIGUSR1)
        time.sleep(0.1)
        set_handlers(*args)

    previous = signal.signal(signal.SIGUSR1, handler)
    try:
        monkeypatch.setattr(signal_handling, "_set_worker_signal_handlers", warned_as_it_starts)
        (worker,) = parents(DataLoader(Pid(), **loader_workers(1, method="fork")))
    finally:
        signal.signal(signal.SIGUSR1, previous)
    assert worker != os.getpid() and not list(tmp_path.iterdir())


@pytest.mark.slow
def test_a_spawned_worker_outlives_slurm_s_warning_signal_while_it_starts():
    """A spawned worker starts Python and imports torch (seconds) before its ``worker_init_fn`` ignores SIGUSR1:
    a USR1 to the whole step then killed it ("DataLoader worker ... is killed by signal: User defined signal 1")."""
    iterator = iter(DataLoader(Pid(), persistent_workers=True, **loader_workers(1, method="spawn")))
    (worker,) = [process.pid for process in iterator._workers]
    os.kill(worker, signal.SIGUSR1)
    assert {int(pid) for batch in iterator for pid in batch} == {worker}


def test_the_fork_server_knows_a_loader_worker_by_its_start_function():
    """The server keeps SIGTERM and the warning signals ignored in loader workers only: it names their start
    function (``data.workers`` imports the server's module, not the other way round), so a rename must reach it."""
    from types import SimpleNamespace

    from dapm_lightning.data.worker_server import _is_loader_worker

    start = loader_workers(1, method="fork")["worker_init_fn"]
    assert _is_loader_worker(SimpleNamespace(_args=(None, start)))
    assert not _is_loader_worker(SimpleNamespace(_args=(None, print))) and not _is_loader_worker(object())


def test_a_worker_seeds_as_the_training_process_was_told_when_the_loader_was_made(monkeypatch):
    """``seed_everything(workers=True)`` sets ``PL_SEED_WORKERS`` in this process, after a fork server may have
    started with another environment: the loader takes it from here."""
    monkeypatch.setenv("PL_SEED_WORKERS", "1")
    assert loader_workers(1)["worker_init_fn"].keywords["seed_workers"] is True
    monkeypatch.setenv("PL_SEED_WORKERS", "0")
    assert loader_workers(1)["worker_init_fn"].keywords["seed_workers"] is False


def test_an_unknown_start_method_is_refused_when_the_data_module_is_made(tmp_path):
    with pytest.raises(ValueError, match="worker_start_method: 'thread'.*forkserver, fork, spawn"):
        UAPDDataModule(root=str(tmp_path), worker_start_method="thread")  # type: ignore[arg-type]


KILLED = """
import time
from multiprocessing import forkserver
from torch.utils.data import DataLoader
from dapm_lightning.data.workers import loader_workers
from tests.data.test_workers import Pid

if __name__ == "__main__":
    loader = DataLoader(Pid(), persistent_workers=True, **loader_workers(2))
    print(*sorted({int(pid) for batch in loader for pid in batch}), flush=True)
    print(forkserver._forkserver._forkserver_pid, forkserver._forkserver._forkserver_address, flush=True)
    time.sleep(120)
"""


@pytest.mark.slow  # a process of its own
def test_workers_end_with_a_training_process_killed_without_its_exit_handlers(tmp_path):
    """SIGKILL, the OOM killer or a crash: a fork server's worker is not the training process's child, and PyTorch's
    worker follows its parent only. Before, the workers (and the server, which waits for them) ran for ever, and
    then the server's socket and its folder (``/tmp/pymp-*``) stayed behind."""
    script = tmp_path / "killed.py"
    script.write_text(KILLED)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    training = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        workers = [int(pid) for pid in training.stdout.readline().split()]  # type: ignore[union-attr]
        server, address = training.stdout.readline().split()  # type: ignore[union-attr]
        assert len(workers) == 2 and Path(address).is_socket()
    finally:
        training.kill()
        training.wait()
    alive = {*workers, int(server)}
    for _ in range(100):
        alive = {pid for pid in alive if _running(pid)}
        if not alive:
            break
        time.sleep(0.1)
    for pid in alive:
        os.kill(pid, signal.SIGKILL)
    assert not alive, "loader workers or their server outlived the training process"
    assert not Path(address).exists() and not Path(address).parent.exists()


STOPPED = """
import os, socket, time
from multiprocessing import forkserver
from torch.utils.data import DataLoader
from dapm_lightning.data.workers import loader_workers
from tests.data.test_workers import Pid

def batches():
    return sorted(int(pid) for batch in DataLoader(Pid(), **loader_workers(1)) for pid in batch)

def ended(pid):
    with open(f"/proc/{pid}/stat") as stat:
        return stat.read().rsplit(")", 1)[1].split()[0] == "Z"

if __name__ == "__main__":
    batches()
    folder = os.path.dirname(forkserver._forkserver._forkserver_address)
    forkserver._forkserver._stop()  # multiprocessing's own: it removes the socket
    assert os.path.isdir(folder)
    batches()  # a new server, its socket in the same folder
    server = forkserver._forkserver._forkserver_pid
    with socket.socket(socket.AF_UNIX) as client:  # a client that leaves before its request: the server fails
        client.connect(forkserver._forkserver._forkserver_address)
    for _ in range(600):
        if ended(server):
            break
        time.sleep(0.1)
    assert ended(server) and os.path.isdir(folder)
    batches()  # multiprocessing starts another
    print("ok", flush=True)
"""


@pytest.mark.slow  # a process of its own
def test_a_fork_server_ended_while_its_training_process_runs_leaves_its_folder(tmp_path):
    """A server ends before its training process (``multiprocessing``'s ``_stop()``, a request it failed on): the
    folder stays, for the next server's socket. Before, the server removed it, ``_stop()`` then failed on the socket
    and the next server could not start (FileNotFoundError), and the process's exit reported the folder missing."""
    script = tmp_path / "stopped.py"
    script.write_text(STOPPED)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, cwd=REPO,
                          timeout=300)
    assert done.returncode == 0 and done.stdout == "ok\n", done.stderr
    assert "FileNotFoundError" not in done.stderr, done.stderr


SHARED = """
import multiprocessing, os, time
from multiprocessing.connection import Listener

def train(server):
    from multiprocessing import forkserver
    from torch.utils.data import DataLoader
    from dapm_lightning.data.workers import loader_workers
    from tests.data.test_workers import Pid
    print(*{int(pid) for batch in DataLoader(Pid(), **loader_workers(1)) for pid in batch}, flush=True)
    server.send(forkserver._forkserver._forkserver_pid)

def running(pid):
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False

if __name__ == "__main__":
    with Listener() as listener:  # this process's folder, empty again once the listener has closed
        folder = os.path.dirname(listener.address)
    server, sent = multiprocessing.Pipe(duplex=False)
    training = multiprocessing.get_context("spawn").Process(target=train, args=(sent,))  # shares the folder
    training.start()
    server = server.recv()
    training.join()
    assert training.exitcode == 0
    for _ in range(300):  # the training process's server ends after it
        if not running(server):
            break
        time.sleep(0.1)
    with Listener() as listener:
        assert os.path.dirname(listener.address) == folder
    print("ok", flush=True)
"""


@pytest.mark.slow  # a process of its own
def test_a_fork_server_leaves_the_folder_of_the_process_that_started_its_training_process(tmp_path):
    """A training process started by another (``spawn``) shares that one's folder: its server, ending with it,
    leaves the folder to its owner. Before, it removed it (when empty), and the owner then failed on it."""
    script = tmp_path / "shared.py"
    script.write_text(SHARED)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, cwd=REPO,
                          timeout=300)
    assert done.returncode == 0 and done.stdout.endswith("ok\n"), done.stderr
    assert "FileNotFoundError" not in done.stderr, done.stderr


def _running(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, ended but not yet reaped, has ended)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def _ignores_sigterm(pid: int) -> bool:
    """Whether process ``pid`` ignores SIGTERM (``SigIgn`` in ``/proc/PID/status``, a mask of bit N-1 for signal N)."""
    try:
        with open(f"/proc/{pid}/status") as status:
            mask = next(line.split()[1] for line in status if line.startswith("SigIgn:"))
    except (FileNotFoundError, StopIteration):
        return False
    return bool(int(mask, 16) >> (signal.SIGTERM - 1) & 1)


def test_other_processes_of_the_fork_server_still_end_on_terminate():
    """The server is multiprocessing's, shared with this process's other ``forkserver`` processes (a ``Pool``, Python
    3.14's default): only loader workers keep its ignored SIGTERM. Before, ``terminate()`` left them running."""
    list(DataLoader(ParentPid(), **loader_workers(1)))  # the server started with this project's preload
    process = multiprocessing.get_context("forkserver").Process(target=time.sleep, args=(60,))
    process.start()
    deadline = time.monotonic() + 30  # until it has set its own SIGTERM (a sleep of 1 s raced a loaded machine)
    while _ignores_sigterm(process.pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    process.terminate()
    process.join(10)
    if process.is_alive():
        process.kill()
        process.join()
    assert process.exitcode == -signal.SIGTERM


FOREIGN_SERVER = """
import multiprocessing, time, warnings
from torch.utils.data import DataLoader
from dapm_lightning.data.workers import loader_workers
from tests.data.test_workers import ParentPid

if __name__ == "__main__":
    process = multiprocessing.get_context("forkserver").Process(target=time.sleep, args=(0,))
    process.start()  # the user's code starts multiprocessing's fork server first, without this project's preload
    process.join()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loader = DataLoader(ParentPid(), **loader_workers(1))
    print(list(loader), [str(warning.message).split(":")[0] for warning in caught])
"""


@pytest.mark.slow  # a process of its own
def test_a_fork_server_started_by_other_code_is_reported(tmp_path):
    """multiprocessing has one fork server a process: started by other code, it lacks the preload that makes it
    ignore a SIGTERM to the whole job, and it dies of one with the loader's workers (the loader fails)."""
    script = tmp_path / "foreign.py"
    script.write_text(FOREIGN_SERVER)
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120,
                            env={**os.environ, "PYTHONPATH": str(REPO)})
    assert result.returncode == 0, result.stderr[-2000:]
    assert "['Loader workers']" in result.stdout, result.stdout


SYS_PATH = """
import sys
sys.path.insert(0, {repo!r})  # a notebook's way to use a checkout
import os
from torch.utils.data import DataLoader, Dataset
from dapm_lightning.data.workers import loader_workers

class Preloaded(Dataset):
    def __len__(self):
        return 1

    def __getitem__(self, index):
        import dapm_lightning
        return dapm_lightning.__file__, "dapm_lightning.data.worker_server" in sys.modules

if __name__ == "__main__":
    print(repr(next(iter(DataLoader(Preloaded(), batch_size=None, **loader_workers(1))))))
"""


@pytest.mark.slow  # a process of its own
def test_the_fork_server_preloads_this_process_s_copy_of_the_package(tmp_path):
    """The server imports :data:`SERVER_PRELOAD` with this process's ``sys.path``, not the one it starts with: a path
    added in the process (a notebook's) had it import an installed copy instead, or nothing (no SIGTERM ignored)."""
    script = tmp_path / "sys_path.py"
    script.write_text(SYS_PATH.format(repo=str(REPO)))
    env = {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                            env=env)
    assert result.returncode == 0, result.stderr[-2000:]
    path, preloaded = eval(result.stdout.strip().splitlines()[-1])
    assert Path(path).resolve().is_relative_to(REPO) and preloaded, result.stdout


NOTEBOOK = """
import warnings
import torch
from torch.utils.data import Dataset
from dapm_lightning.data.datamodules import DAPMDataModule

class Mine(Dataset):  # a notebook's cell: a class of __main__, which has no file
    def __len__(self):
        return 2

    def __getitem__(self, index):
        return {"image": torch.zeros(3, 4, 4, dtype=torch.uint8), "name": str(index)}

class MyData(DAPMDataModule):
    def make_dataset(self, split, train):
        return Mine()

module = MyData(batch_size=1, num_workers=1)
module.setup("fit")
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    batch = next(iter(module.train_dataloader()))
print(tuple(batch["image"].shape), [str(warning.message).split(":")[0] for warning in caught])
"""


@pytest.mark.slow  # a process of its own
def test_a_data_set_defined_in_a_notebook_is_loaded_by_forked_workers():
    """A fork server's worker cannot import a ``__main__`` without a file (a notebook, ``python -``): its data set
    could not be unpickled and the worker died ('DataLoader worker exited unexpectedly')."""
    result = subprocess.run([sys.executable, "-"], input=NOTEBOOK, capture_output=True, text=True, timeout=120,
                            cwd=REPO)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "(1, 3, 4, 4) ['Loader workers']" in result.stdout, result.stdout


FORKED = """
import faulthandler
import os
import sys
from torch.utils.data import DataLoader
from dapm_lightning.data.workers import loader_workers
from tests.data.test_workers import ParentPid

if __name__ == "__main__":
    first = list(DataLoader(ParentPid(), **loader_workers(1)))  # this process's fork server started
    child = os.fork()  # as Lightning's ddp_fork / ddp_notebook start their processes
    if child == 0:
        try:
            faulthandler.dump_traceback_later(100, exit=True)  # a hang shows where it waits (the test, 150 s)
            print("child", int(next(iter(DataLoader(ParentPid(), **loader_workers(1))))), flush=True)
        finally:
            os._exit(0)
    faulthandler.dump_traceback_later(130, exit=True)  # armed after the fork: its thread is not forked
    os.waitpid(child, 0)
    print("parent", int(first[0]), flush=True)
"""


def run_whole_session(command: list[str], folder: Path, timeout_s: float,
                      env: dict[str, str]) -> subprocess.CompletedProcess:
    """Run ``command`` in a session of its own, its output in files: a hang fails with what it printed, and the
    processes of the session still running (a grandchild holding a pipe would keep ``subprocess.run`` waiting)."""
    out, err = folder / "stdout.txt", folder / "stderr.txt"
    with out.open("w") as stdout, err.open("w") as stderr:
        process = subprocess.Popen(command, stdout=stdout, stderr=stderr, env=env, start_new_session=True)
        try:
            process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            left = subprocess.run(["ps", "-o", "pid,ppid,stat,wchan:20,args", "-s", str(process.pid)],
                                  capture_output=True, text=True).stdout
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
            pytest.fail(f"still running after {timeout_s} s; its processes:\n{left}\nstdout:\n"
                        f"{out.read_text()[-2000:]}\nstderr:\n{err.read_text()[-6000:]}")
    with contextlib.suppress(ProcessLookupError):  # what the session left running (none is expected)
        os.killpg(process.pid, signal.SIGKILL)
    return subprocess.CompletedProcess(command, process.returncode, out.read_text(), err.read_text())


@pytest.mark.slow  # a process of its own
def test_a_process_forked_after_a_loader_starts_its_own_fork_server(tmp_path):
    """multiprocessing asks its fork server's status with ``waitpid``, which a forked process cannot do for its
    parent's server: its first loader died with ``ChildProcessError: [Errno 10] No child processes``."""
    script = tmp_path / "forked.py"
    script.write_text(FORKED)
    result = run_whole_session([sys.executable, str(script)], tmp_path, 150, {**os.environ, "PYTHONPATH": str(REPO)})
    assert result.returncode == 0, result.stderr[-3000:]
    servers = dict(line.split() for line in result.stdout.splitlines() if line.startswith(("child", "parent")))
    assert set(servers) == {"child", "parent"} and servers["child"] != servers["parent"], result.stdout + result.stderr
