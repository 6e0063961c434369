"""Lightning's loop counters in a checkpoint, made to resume where the training stopped.

Lightning (2.6) counts an epoch as done as soon as its epoch loop stops, also when ``max_steps``, a
``should_stop`` or a SIGTERM stopped it after a few of its batches. A checkpoint written from then on (the
``last.ckpt`` of ``on_train_end``, an ``on_train_epoch_end`` save, the SIGTERM save at the end of an
epoch) makes a resumed run start the *next* epoch, skipping the rest of the stopped one; and after a whole
epoch it makes the resumed run skip the next epoch entirely (its batch counters still say "all batches
run"). :func:`resume_after_last_batch` rewrites such counters to those of a checkpoint taken right after
the last training batch, which Lightning resumes exactly: the same epoch, the next batch (or the next
epoch from its first batch when the last batch ended it), without repeating the validation that ran there.
:func:`start_next_epoch_as_any_other` mends how Lightning then starts that next epoch, and
:func:`count_batches_as_resumed` how it counts an epoch resumed on another number of processes.
"""

from __future__ import annotations

from collections.abc import MutableMapping
from typing import Any

from dapm_lightning.training.checkpoint_files import is_remote, local_path


def epoch_closed(epoch_progress: MutableMapping[str, Any]) -> bool:
    """Whether the fit loop has closed its current epoch: started, and counted processed.

    Args:
        epoch_progress: the fit loop's ``epoch_progress`` state (``{"total": ..., "current": ...}``).

    Returns:
        True from the end of the epoch loop (``on_train_epoch_end``, ``on_train_end``) until the next epoch starts.
    """
    current = epoch_progress["current"]
    return bool(current["started"] > 0 and current["ready"] == current["started"] == current["processed"])


def resume_after_last_batch(fit_loop: MutableMapping[str, Any]) -> bool:
    """Rewrite a fit loop's saved state to that of a save right after its last training batch, if it was closed.

    Args:
        fit_loop: ``checkpoint["loops"]["fit_loop"]``, changed in place.

    Returns:
        Whether the state was rewritten (False: the epoch was still open, the state resumes as it is).
    """
    epochs = fit_loop.get("epoch_progress")
    batches = fit_loop.get("epoch_loop.batch_progress")
    if epochs is None or batches is None or not epoch_closed(epochs):
        return False
    if batches["current"]["processed"] == 0 or batches["current"]["completed"] != batches["current"]["processed"]:
        return False  # no batch in this epoch, or not after a whole batch: nothing Lightning would resume wrongly
    for progress in (epochs["current"], epochs["total"]):  # the epoch is open again: started, not processed
        progress["processed"] -= 1
        progress["completed"] = min(progress["completed"], progress["processed"])
    for progress in (batches["current"], batches["total"]):  # the last batch processed, its end hooks not counted
        progress["completed"] = progress["processed"] - 1
    state = fit_loop.get("epoch_loop.state_dict")
    if isinstance(state, MutableMapping) and state.get("_batches_that_stepped", 0) > 0:
        state["_batches_that_stepped"] -= 1  # counted once more when Lightning resumes after a training batch
    return True


def start_next_epoch_as_any_other(fit_loop: Any) -> bool:
    """After a resume from a save right after an epoch's last batch, let the next epoch start as every epoch does.

    Lightning (2.6) closes the restored epoch in ``FitLoop.reset`` but keeps the loop's restart stage "restarted
    mid-epoch" until the next epoch ends, so that epoch is not counted ready and started and its
    ``on_train_epoch_start`` hooks do not run. Its counters then end as (ready n, started n, processed n + 1),
    which no later save reads right: the resume after the next save skipped a whole epoch and said it had
    finished. Call it between the loop's reset and its first epoch (``on_train_start``).

    Args:
        fit_loop: the trainer's ``fit_loop``.

    Returns:
        Whether the restart stage was cleared (False: not such a resume, nothing changed).
    """
    progress = fit_loop.epoch_progress.total
    if fit_loop.restarted_mid_epoch and progress.processed == progress.started:  # reset closed the restored epoch
        fit_loop.reset_restart_stage()
        return True
    return False


def count_batches_as_resumed(fit_loop: Any, epoch: int, batches: int) -> bool:
    """Make the restored batch counters count the batches the training loader resumes after, in this run's batches.

    Lightning restores the number of batches the saved run had trained in its epoch. On another number of
    processes (or another batch size) those batches held another number of samples: Lightning then ends the
    resumed epoch when the restored count plus the batches of this run reach ``num_training_batches`` (too early,
    dropping samples, or too late, when the loader ends first), and the data module's next saved position (batches
    x batch size x processes) is wrong. With the counters set to the batches the loader skipped, the epoch ends
    with its last sample and each position saved is right. Nothing changes on the same number of processes.
    Call it between the loop's reset and its first epoch (``on_train_start``).

    Args:
        fit_loop: the trainer's ``fit_loop``.
        epoch, batches: the epoch the training loader resumes and the batches of it it skips (the data module's
            ``resumed_at``).

    Returns:
        Whether the counters changed.
    """
    progress = fit_loop.epoch_loop.batch_progress
    if fit_loop.epoch_progress.current.processed == epoch and not progress.is_last_batch:
        done = batches  # the loop holds the resumed epoch, open
    else:  # the loop holds the epoch before, over: all of its batches, so that Lightning starts the next afresh
        done = fit_loop.trainer.num_training_batches
    shift = done - progress.current.processed
    if shift == 0:
        return False
    for counts in (progress.current, progress.total):
        counts.ready += shift
        counts.started += shift
        counts.processed += shift
        counts.completed += shift
    return True


def keep_checkpoint_rankings(checkpoint: MutableMapping[str, Any], callbacks: Any, roots: Any = ()) -> list[str]:
    """Let each ``ModelCheckpoint`` resume its ranking of the saved models when the resumed run writes elsewhere.

    A resumed run logs into a new version folder, so its ``ModelCheckpoint`` folders differ from the saved ones,
    and Lightning then restores only ``best_model_path``: without the best score, the first validation after the
    resume saved its model as the best, however much worse. A saved state is given the callback's folder, so that
    Lightning restores the scores (the files ranked stay where they are), when it is this run's: its folder is a
    local one under one of ``roots`` (the run's folders) and its best model is still there. Another run's
    checkpoint (fine-tuning from it) starts a ranking of its own, as before.

    Args:
        checkpoint: the loaded checkpoint (``on_load_checkpoint``), changed in place; the file is not.
        callbacks: the trainer's checkpoint callbacks (``trainer.checkpoint_callbacks``).
        roots: the run's folders (``trainer.default_root_dir``, the loggers' ``save_dir``).

    Returns:
        The ``state_key`` of each callback whose state was given its folder.
    """
    states = checkpoint.get("callbacks") or {}
    local_roots = [local_path(root).resolve() for root in roots if root and not is_remote(root)]
    kept = []
    for callback in callbacks:
        state = states.get(getattr(callback, "state_key", None))
        folder = getattr(callback, "dirpath", None)
        if not isinstance(state, MutableMapping) or folder is None or state.get("dirpath") in (None, folder):
            continue
        saved, best = state["dirpath"], state.get("best_model_path")
        if is_remote(saved) or is_remote(folder) or not best or not local_path(best).is_file():
            continue
        if not any(local_path(saved).resolve().is_relative_to(root) for root in local_roots):
            continue
        state["dirpath"] = folder
        kept.append(callback.state_key)
    return kept


__all__ = ["count_batches_as_resumed", "epoch_closed", "keep_checkpoint_rankings", "resume_after_last_batch",
           "start_next_epoch_as_any_other"]
