"""SIGTERM and Ctrl-C in training: every process stops after the same optimizer step, no collective in a handler.

Lightning's (2.6) SIGTERM handler broadcasts a tensor from inside the handler. The handler runs wherever the main
thread happens to be, also between the collectives of a metric sync or a checkpoint save, so under DDP the
processes then wait in different collectives for ever: a SIGTERM at a random moment hung two runs in three
here. And each process stops at its own next check, so one may save while another validates. Lightning also stops
after the current batch even in the middle of gradient accumulation (``accumulate_grad_batches`` > 1): the
gradients of the window's first micro-batches are not saved, but the data position counts them as trained, so the
resumed run stepped with the window's remaining micro-batches only. And a stop before a validation that was due
(under DDP) or inside one (one process) lost that validation: the resumed run skips it, so its metrics and its
best-model checkpoint never existed.

:class:`SigtermAgreement` replaces that handler (once Lightning has installed it) with one that only notes the
signal and passes it on to the processes Lightning started (as Lightning does); ``CheckpointOnSigterm`` notes
Ctrl-C there too (:func:`request_stop`). The signal is acted on after a training batch that ends an accumulation
window (the optimizer steps after it; every batch without accumulation, and the epoch's last batch), or, when a
validation follows that batch or is running, at the end of that validation. Under DDP the processes agree there
with one ``all_reduce``: when any of them got a signal, all stop at that point. After a training batch, DDP
processes raise Lightning's ``SIGTERMException``, and one process sets Lightning's flag (Lightning stops after the
batch). After a validation every process sets the flag, and Lightning stops right after it (at an epoch's end,
after the epoch's end hooks and the checkpoints they save). ``CheckpointOnSigterm`` saves ``last.ckpt`` from that
same state on each process; a run resumed from it neither repeats nor skips the validation.

Lightning's SLURM auto-requeue (``SIGUSR1``, ``#SBATCH --signal=USR1@90``) has the same flaw: its handler saves
``hpc_ckpt_N.ckpt`` from inside the handler, and under DDP that save's collectives (the module's gather of every
process's RNG states, Lightning's barrier) met another process's collective of the step or of a metric sync: gloo
aborted both processes ("collective mismatch"), and the job failed with status 1, not requeued. The agreement notes
that signal too and runs Lightning's requeue handler (the save, then ``scontrol requeue`` on the first process) on
every process after the same optimizer step, agreed in the same ``all_reduce``; training then goes on, as Lightning's
does.
"""

from __future__ import annotations

import logging
import signal
from collections.abc import Callable
from types import FrameType
from typing import Any

import lightning as L
import torch
import torch.distributed as dist
from lightning.fabric.plugins.environments.slurm import SLURMEnvironment
from lightning.pytorch.trainer.states import TrainerFn
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


def is_distributed(trainer: L.Trainer) -> bool:
    """Whether ``trainer`` runs several processes with a process group up (collectives are due on every one)."""
    return trainer.world_size > 1 and dist.is_available() and dist.is_initialized()


def _cluster_environment(trainer: L.Trainer) -> Any:
    """The trainer's cluster environment, where Lightning's signal connector reads it (None if it cannot)."""
    return getattr(getattr(trainer, "_accelerator_connector", None), "cluster_environment", None)


def validation_follows(trainer: L.Trainer) -> bool:
    """Whether Lightning validates right after the current training batch (asked in ``on_train_batch_end``)."""
    loop = trainer.fit_loop.epoch_loop
    try:
        return bool(loop._should_check_val_fx(trainer.fit_loop._data_fetcher))  # type: ignore[arg-type]
    except (AttributeError, TypeError):  # another Lightning version: as if none followed
        return False


class SigtermAgreement:
    """SIGTERM (and Ctrl-C) noted without collectives, acted on by all processes after the same optimizer step."""

    def __init__(self) -> None:
        self.received = False
        """Whether this process was told to stop (SIGTERM, or Ctrl-C through :func:`request_stop`)."""
        self._signum: int | None = None
        self._trainer: L.Trainer | None = None
        self._after_validation = False
        """A stop agreed after a training batch that a validation follows: taken when that validation ends."""
        self._requeue_handler: Callable[[int, FrameType | None], Any] | None = None
        """Lightning's SLURM auto-requeue handler, taken over by :meth:`install` (run by :meth:`agree` instead)."""
        self.requeue_signum: int | None = None
        """The requeue signal this process received and :meth:`agree` has not acted on yet, if any."""

    def install(self, trainer: L.Trainer) -> None:
        """Replace Lightning's SIGTERM handler (call after Lightning installed it: sanity check, train start).

        A SIGTERM Lightning's handler noted before is taken over. Lightning puts the original handler back when the
        run ends.

        Args:
            trainer: the running trainer.
        """
        if self._trainer is trainer:
            return
        self._trainer, self.received, self._signum, self._after_validation = trainer, False, None, False
        self._requeue_handler, self.requeue_signum = None, None
        if trainer.received_sigterm:  # Lightning's handler logged it
            trainer._signal_connector.received_sigterm, self.received = False, True
        signal.signal(signal.SIGTERM, self._on_sigterm)
        self._take_over_requeue(trainer)

    def _take_over_requeue(self, trainer: L.Trainer) -> None:
        """Note Lightning's SLURM requeue signal instead of handling it there (its handler runs in :meth:`agree`)."""
        environment = _cluster_environment(trainer)
        if not isinstance(environment, SLURMEnvironment) or environment.requeue_signal is None:
            return
        current = signal.getsignal(environment.requeue_signal)
        ours = trainer._signal_connector._slurm_sigusr_handler_fn
        if not callable(current) or not any(handler == ours for handler in getattr(current, "signal_handlers", ())):
            return  # not Lightning's auto-requeue (off, or a handler of the user's that Lightning left alone)
        self._requeue_handler = current
        signal.signal(environment.requeue_signal, self._on_requeue)

    def _on_requeue(self, signum: int, frame: FrameType | None) -> None:
        self.requeue_signum = signum  # no save and no collective here: the processes act together in agree()

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

    def _agreed(self, trainer: L.Trainer) -> bool:
        """Whether any process was told to stop (a stop already agreed counts, without a collective)."""
        return self._agreed_with_requeue(trainer)[0]

    def _agreed_with_requeue(self, trainer: L.Trainer) -> tuple[bool, bool]:
        """Whether any process was told to stop, and whether any received the requeue signal (one ``all_reduce``).

        A stop already agreed counts without a collective (and the requeue then waits for the next agreement).
        """
        if self._after_validation:
            return True, False
        requeue = self.requeue_signum is not None
        if not is_distributed(trainer):
            return self.received, requeue
        flags = torch.tensor([int(self.received), int(requeue)], device=trainer.strategy.root_device)
        dist.all_reduce(flags, op=dist.ReduceOp.MAX)
        return bool(flags[0].item()), bool(flags[1].item())

    def _requeue(self) -> None:
        """Lightning's auto-requeue, on every process at once: ``hpc_ckpt_N.ckpt`` saved, the job requeued."""
        handler, signum = self._requeue_handler, self.requeue_signum
        self.requeue_signum = None
        if handler is not None:
            handler(signum or signal.SIGUSR1, None)

    def _log(self, trainer: L.Trainer) -> None:
        if self._signum == signal.SIGTERM:
            log.info(rank_prefixed_message(f"Received SIGTERM: {int(signal.SIGTERM)}", trainer.local_rank))

    def agree(self, trainer: L.Trainer) -> None:
        """After a training batch, on every process: stop all if any was told to, when the batch ended a window.

        When any process received Lightning's SLURM requeue signal, first runs Lightning's requeue handler on every
        process (a checkpoint of this step, the job requeued); training goes on unless a stop is agreed too.

        When a validation follows the batch, the stop waits for its end (:meth:`after_validation`); if it did not
        run after all (Lightning skipped it), the stop is taken after the next window instead. Else under DDP
        raises ``SIGTERMException`` on all processes; with one process sets Lightning's flag, which stops after
        this batch.

        Args:
            trainer: the running trainer (the one :meth:`install` was called with; else nothing happens).

        Raises:
            SIGTERMException: under DDP, when any process was told to stop.
        """
        if self._trainer is not trainer or not between_optimizer_steps(trainer):
            return
        stop, requeue = self._agreed_with_requeue(trainer)
        if requeue:  # SLURM's warning signal reached some process: Lightning's requeue, here, on every process
            self._requeue()
        if not stop:
            return
        if validation_follows(trainer) and not self._after_validation:  # set still: the last one did not run
            self._after_validation = True
            return
        self._after_validation = False  # no validation follows, or the one expected did not run: stop here
        self._log(trainer)
        if is_distributed(trainer):
            raise SIGTERMException
        trainer._signal_connector.received_sigterm = True

    def after_validation(self, trainer: L.Trainer) -> None:
        """At the end of a validation inside a fit, on every process: stop all if any was told to.

        The stop agreed before the validation, or a signal received during it (when no accumulation window is
        open; else the stop waits for its end, :meth:`agree`). Sets Lightning's flag on every process: Lightning
        stops right after the validation, or at an epoch's end after the epoch's end hooks (the checkpoints saved
        there, ``ModelCheckpoint``'s with a validation at each epoch's end).

        Args:
            trainer: the running trainer (the one :meth:`install` was called with; else nothing happens).

        """
        if (self._trainer is not trainer or trainer.sanity_checking or trainer.state.fn != TrainerFn.FITTING
                or not between_optimizer_steps(trainer) or not self._agreed(trainer)):
            return
        self._after_validation = False
        self._log(trainer)
        trainer._signal_connector.received_sigterm = True  # on every process, past the validation's collectives


def request_stop(trainer: L.Trainer, signum: int) -> None:
    """Stop a fit as SIGTERM does, for another signal (Ctrl-C); safe inside a signal handler.

    Through the module's :class:`SigtermAgreement` when it handles the run (after the next optimizer step, or the
    validation that follows it, on every process); else Lightning's own stop, at the end of the current batch.

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


__all__ = ["SigtermAgreement", "between_optimizer_steps", "request_stop", "sigterm_received", "stop_started_processes",
           "validation_follows"]
