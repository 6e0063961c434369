"""SIGTERM and Ctrl-C in training: every process stops after the same optimizer step, no collective in a handler.

Lightning's (2.6) SIGTERM handler broadcasts a tensor from inside the handler. The handler runs wherever the main
thread happens to be, also between the collectives of a metric sync or a checkpoint save, so under DDP the
processes then wait in different collectives for ever: a SIGTERM at a random moment hung two runs in three
here. And each process stops at its own next check, so one may save while another validates. Lightning also stops
after the current batch even in the middle of gradient accumulation (``accumulate_grad_batches`` > 1): the
gradients of the window's first micro-batches are not saved, but the data position counts them as trained, so the
resumed run stepped with the window's remaining micro-batches only.

:class:`SigtermAgreement` replaces that handler (once Lightning has installed it) with one that only notes the
signal and passes it on to the processes Lightning started (as Lightning does); ``CheckpointOnSigterm`` notes
Ctrl-C there too (:func:`request_stop`). The signal is acted on after a training batch that ends an accumulation
window (the optimizer steps after it; every batch without accumulation, and the epoch's last batch). Under DDP the
processes then agree with one ``all_reduce``: when any of them got a signal, all raise Lightning's
``SIGTERMException`` there, and ``CheckpointOnSigterm`` saves ``last.ckpt`` from that same state on each. A
validation in progress runs to its end first (its processes may hold different numbers of batches), then training
runs to the end of the next accumulation window. With one process the signal is handed to Lightning at such a
point, and Lightning stops as it always does: after that batch, or after the current batch of a validation that
runs between two optimizer steps.
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


def between_optimizer_steps(trainer: L.Trainer) -> bool:
    """Whether no gradients are being accumulated: the last training batch ended an accumulation window, or none ran.

    Args:
        trainer: a fitting trainer, after a training batch or during a validation between two.

    Returns:
        False after a micro-batch the optimizer did not step after (``accumulate_grad_batches`` > 1).
    """
    return not trainer.fit_loop.epoch_loop._should_accumulate()


class SigtermAgreement:
    """SIGTERM (and Ctrl-C) noted without collectives, acted on by all processes after the same optimizer step."""

    def __init__(self) -> None:
        self.received = False
        """Whether this process was told to stop (SIGTERM, or Ctrl-C through :func:`request_stop`)."""
        self._signum: int | None = None
        self._trainer: L.Trainer | None = None

    def install(self, trainer: L.Trainer) -> None:
        """Replace Lightning's SIGTERM handler (call after Lightning installed it: sanity check, train start).

        A SIGTERM Lightning's handler noted before is taken over. Lightning puts the original handler back when the
        run ends.

        Args:
            trainer: the running trainer.
        """
        if self._trainer is trainer:
            return
        self._trainer, self.received, self._signum = trainer, False, None
        if trainer.received_sigterm:  # Lightning's handler logged it
            trainer._signal_connector.received_sigterm, self.received = False, True
        signal.signal(signal.SIGTERM, self._on_sigterm)

    def acts_for(self, trainer: L.Trainer) -> bool:
        """Whether this agreement handles ``trainer``'s stops (installed on it)."""
        return self._trainer is trainer

    def note(self, signum: int) -> None:
        """Stop at the next agreed point (see the module's docstring); safe inside a signal handler."""
        if not self.received:
            self.received, self._signum = True, signum

    def _on_sigterm(self, signum: int, frame: FrameType | None) -> None:
        trainer = self._trainer  # no logging here: a write to a stream the interrupted code was writing fails
        launcher = trainer.strategy.launcher if trainer is not None else None
        if not self.received and launcher is not None and hasattr(launcher, "kill"):
            launcher.kill(signum)  # the processes Lightning started (plain signals, as Lightning does)
        self.note(signum)

    def agree(self, trainer: L.Trainer) -> None:
        """After a training batch, on every process: stop all if any was told to, when the batch ended a window.

        Under DDP raises ``SIGTERMException`` on all processes; with one process sets Lightning's flag, which stops
        after this batch (or in the validation that follows it).

        Args:
            trainer: the running trainer (the one :meth:`install` was called with; else nothing happens).

        Raises:
            SIGTERMException: under DDP, when any process was told to stop.
        """
        if self._trainer is not trainer or not between_optimizer_steps(trainer):
            return
        distributed = trainer.world_size > 1 and dist.is_available() and dist.is_initialized()
        stop = self.received
        if distributed:
            flag = torch.tensor([int(stop)], device=trainer.strategy.root_device)
            dist.all_reduce(flag, op=dist.ReduceOp.MAX)
            stop = bool(flag.item())
        if not stop:
            return
        if self._signum == signal.SIGTERM:
            log.info(rank_prefixed_message(f"Received SIGTERM: {int(signal.SIGTERM)}", trainer.local_rank))
        if distributed:
            raise SIGTERMException
        trainer._signal_connector.received_sigterm = True

    def during_validation(self, trainer: L.Trainer) -> None:
        """With one process, after a validation batch: hand a noted stop to Lightning, unless it would cut a window.

        Lightning then stops after this batch, as it does without the agreement. Under DDP the stop waits for the
        next training batch (the processes may hold different numbers of validation batches).

        Args:
            trainer: the running trainer (the one :meth:`install` was called with; else nothing happens).
        """
        if self._trainer is trainer and trainer.world_size == 1 and self.received and between_optimizer_steps(trainer):
            trainer._signal_connector.received_sigterm = True


def request_stop(trainer: L.Trainer, signum: int) -> None:
    """Stop a fit as SIGTERM does, for another signal (Ctrl-C); safe inside a signal handler.

    Through the module's :class:`SigtermAgreement` when it handles the run (after the next optimizer step, on every
    process); else Lightning's own stop, at the end of the current batch.

    Args:
        trainer: the running trainer.
        signum: the signal received.
    """
    agreement = getattr(trainer.lightning_module, "sigterm", None)
    if isinstance(agreement, SigtermAgreement) and agreement.acts_for(trainer):
        agreement.note(signum)
    else:
        trainer._signal_connector.received_sigterm = True


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
    """Whether this process was told to stop (SIGTERM, Ctrl-C), whichever noted it (Lightning or ``agreement``).

    Args:
        trainer: the running trainer (Lightning's flag: without an agreement, and before it is installed).
        agreement: the module's :class:`SigtermAgreement`, if any.

    Returns:
        True once this process has been told to stop.
    """
    return bool(trainer.received_sigterm or (agreement is not None and agreement.received))


__all__ = ["SigtermAgreement", "between_optimizer_steps", "request_stop", "sigterm_received", "stop_started_processes"]
