"""SIGTERM under DDP: every process stops after the same training step, with no collective in a signal handler.

Lightning's (2.6) SIGTERM handler broadcasts a tensor from inside the handler. The handler runs wherever the main
thread happens to be, also between the collectives of a metric sync or a checkpoint save, so under DDP the
processes then wait in different collectives for ever: a SIGTERM at a random moment hung two runs in three
here. And each process stops at its own next check, so one may save while another validates.

:class:`SigtermAgreement` replaces that handler under DDP (once Lightning has installed it) with one that only
notes the signal and passes it on to the processes Lightning started (as Lightning does). After every training
batch the processes agree with one ``all_reduce``: when any of them got SIGTERM, those log it as Lightning does,
and all raise Lightning's ``SIGTERMException`` there; ``CheckpointOnSigterm`` then saves ``last.ckpt`` from that
same state on each. A validation in progress runs to its end first (its processes may hold different numbers of
batches), then one more training step. With one process Lightning's handler stays: it stops at the end of the
current batch, validation batches included.
"""

from __future__ import annotations

import logging
import signal
from types import FrameType

import lightning as L
import torch
import torch.distributed as dist
from lightning.pytorch.utilities.exceptions import SIGTERMException
from lightning_utilities.core.rank_zero import rank_prefixed_message

log = logging.getLogger("lightning.pytorch.trainer.connectors.signal_connector")


class SigtermAgreement:
    """Under DDP, a SIGTERM noted without collectives and acted on by all processes after the same training batch."""

    def __init__(self) -> None:
        self.received = False
        """Whether this process got SIGTERM (under DDP; with one process Lightning's ``trainer.received_sigterm``)."""
        self._trainer: L.Trainer | None = None

    def install(self, trainer: L.Trainer) -> None:
        """Replace Lightning's SIGTERM handler under DDP (call after Lightning installed it: sanity check, train start).

        Lightning puts the original handler back when the run ends.

        Args:
            trainer: the running trainer; nothing changes with one process.
        """
        if trainer.world_size <= 1 or self._trainer is trainer:
            return
        self._trainer, self.received = trainer, False
        signal.signal(signal.SIGTERM, self._on_sigterm)

    def _on_sigterm(self, signum: int, frame: FrameType | None) -> None:
        trainer = self._trainer  # no logging here: a write to a stream the interrupted code was writing fails
        launcher = trainer.strategy.launcher if trainer is not None else None
        if not self.received and launcher is not None and hasattr(launcher, "kill"):
            launcher.kill(signum)  # the processes Lightning started (plain signals, as Lightning does)
        self.received = True

    def agree(self, trainer: L.Trainer) -> None:
        """After a training batch, on every process: raise ``SIGTERMException`` on all if any got SIGTERM.

        Args:
            trainer: the running trainer (the one :meth:`install` was called with; else nothing happens).

        Raises:
            SIGTERMException: when any process got SIGTERM.
        """
        if self._trainer is not trainer or not (dist.is_available() and dist.is_initialized()):
            return
        received = self.received
        flag = torch.tensor([int(received)], device=trainer.strategy.root_device)
        dist.all_reduce(flag, op=dist.ReduceOp.MAX)
        if int(flag.item()):
            if received:
                log.info(rank_prefixed_message(f"Received SIGTERM: {int(signal.SIGTERM)}", trainer.local_rank))
            raise SIGTERMException


def stop_started_processes(trainer: L.Trainer | None) -> list[int]:
    """Kill the DDP processes this one started (Lightning's subprocess launcher) that still run; their ids.

    For a run that failed in this process (rank 0 of a job Lightning launched on one machine): the others would
    wait for it in their next collective until the process group's timeout (30 minutes), or for ever while
    connecting to it. Lightning kills them on Ctrl-C, and kills this process when one of them fails, but not
    the others when this one fails. Processes started by a cluster (SLURM, torchrun) are left to it.

    Args:
        trainer: the trainer of the failed run (None: nothing to do).

    Returns:
        The process ids killed (SIGKILL, as Lightning kills them: one hanging in a collective ignores SIGTERM).
    """
    launcher = getattr(getattr(trainer, "strategy", None), "launcher", None)
    killed = []
    for process in list(getattr(launcher, "procs", None) or []):
        if process.poll() is None:
            process.kill()
            process.wait()
            killed.append(process.pid)
    return killed


def sigterm_received(trainer: L.Trainer, agreement: SigtermAgreement | None) -> bool:
    """Whether this process got SIGTERM, whichever handler noted it (Lightning's or ``agreement``'s).

    Args:
        trainer: the running trainer (Lightning's flag; also set by ``CheckpointOnSigterm`` for SIGINT).
        agreement: the module's :class:`SigtermAgreement`, if any.

    Returns:
        True once this process has been told to stop.
    """
    return bool(trainer.received_sigterm or (agreement is not None and agreement.received))


__all__ = ["SigtermAgreement", "sigterm_received", "stop_started_processes"]
