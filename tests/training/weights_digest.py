"""A callback for the DDP tests: each process writes the SHA-256 of its network's parameters as training starts."""

import hashlib
from pathlib import Path

import lightning as L


def parameters_digest(named_tensors) -> str:
    """SHA-256 over the float32 bytes of the given ``(name, tensor)`` pairs, in name order."""
    digest = hashlib.sha256()
    for name, tensor in sorted(named_tensors, key=lambda item: item[0]):
        digest.update(name.encode())
        digest.update(tensor.detach().float().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


class WeightsDigest(L.Callback):
    """Writes ``FOLDER/rank{global_rank}.txt``: the digest of ``pl_module.net``'s parameters at ``on_train_start``."""

    def __init__(self, folder: str) -> None:
        self.folder = Path(folder)

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        text = parameters_digest(pl_module.net.named_parameters())
        (self.folder / f"rank{trainer.global_rank}.txt").write_text(text)
